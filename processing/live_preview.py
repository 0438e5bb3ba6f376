"""A fast, coarse MCA disparity preview of one live-view frame, for framing and focusing with depth in view.

Pure: an 8-bit RGB frame and the profile's filter geometry in, a disparity map out.
The frame is downscaled to at most `max_width_px`, each channel band-passed
(difference of Gaussians), and for every candidate disparity d of the widest
filter pair each channel is sampled at x + d * s_c, with s_c its displacement
per pixel of disparity (`FilterAperture.shift_per_disparity`). The cost is the
colour-line measure of Bando et al. 2008 over a box window,
L = 1 - rho_rg^2 - rho_rb^2 - rho_gb^2 + 2 rho_rg rho_rb rho_gb (rho the local
correlations of the band-passed channels), low where the channels align.
The winner takes all, refined by a parabola through its neighbours; the
confidence is how much better the winner is than the mean cost.

Disparities are in pixels of the frame handed in (a live-view frame is a
fraction of the sensor's width; the caller scales them if it wants sensor pixels).
Positive = farther than the focus plane, as everywhere in mca.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mca.processing.camera import CHANNELS, FilterAperture


@dataclass(frozen=True)
class LivePreviewParams:
    """How coarse and how wide the preview search is."""

    max_width_px: int = 320  # the frame is downscaled to at most this width first
    max_disparity_px: float = 12.0  # search range +-, in pixels of the frame handed in
    candidates: int = 13  # disparities tried, evenly spaced over the range
    window_px: int = 9  # box window of the colour-line measure, at preview resolution
    sigma_fine_px: float = 0.7  # band-pass: difference of these Gaussians, at preview resolution
    sigma_coarse_px: float = 3.0
    eps: float = 1e-4  # regularises the correlations in flat areas (band-passed values are in [0, 1] units)


@dataclass
class LivePreview:
    """The preview of one frame; maps are at preview resolution (`scale` frame pixels per preview pixel)."""

    disparity_px: np.ndarray  # (h, w) float32, in pixels of the frame handed in
    confidence: np.ndarray  # (h, w) float32 in [0, 1]
    scale: float
    candidates_px: np.ndarray  # the disparities tried, in pixels of the frame handed in


def _band_pass(plane: np.ndarray, params: LivePreviewParams) -> np.ndarray:
    fine = cv2.GaussianBlur(plane, (0, 0), params.sigma_fine_px)
    coarse = cv2.GaussianBlur(plane, (0, 0), params.sigma_coarse_px)
    return fine - coarse


def _shifted(plane: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """`plane` sampled at (x + dx, y + dy); borders replicate."""
    m = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], dtype=np.float32)
    return cv2.warpAffine(
        plane,
        m,
        (plane.shape[1], plane.shape[0]),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def colour_line_cost(r: np.ndarray, g: np.ndarray, b: np.ndarray, window_px: int, eps: float) -> np.ndarray:
    """Bando et al.'s colour-line measure over a box window, from the pairwise correlations of zero-mean planes."""
    k = (window_px, window_px)

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, -1, k, normalize=True, borderType=cv2.BORDER_REFLECT)

    vr, vg, vb = box(r * r) + eps, box(g * g) + eps, box(b * b) + eps
    rg = box(r * g) / np.sqrt(vr * vg)
    rb = box(r * b) / np.sqrt(vr * vb)
    gb = box(g * b) / np.sqrt(vg * vb)
    return 1.0 - rg * rg - rb * rb - gb * gb + 2.0 * rg * rb * gb


def live_disparity(
    frame_rgb8: np.ndarray, aperture: FilterAperture, params: LivePreviewParams | None = None
) -> LivePreview:
    """The coarse disparity preview of one (H, W, 3) uint8 RGB frame."""
    params = params or LivePreviewParams()
    if frame_rgb8.ndim != 3 or frame_rgb8.shape[2] != 3:
        raise ValueError(f"a live-view frame must be (H, W, 3) RGB, got shape {frame_rgb8.shape}")
    height, width = frame_rgb8.shape[:2]
    if width < 16 or height < 16:
        raise ValueError(f"a live-view frame of {width}x{height} px is too small for a preview")
    scale = max(1.0, width / params.max_width_px)
    small_size = (max(16, round(width / scale)), max(16, round(height / scale)))
    small = cv2.resize(frame_rgb8, small_size, interpolation=cv2.INTER_AREA).astype(np.float32) * (1.0 / 255.0)
    planes = [_band_pass(np.ascontiguousarray(small[..., i]), params) for i in range(3)]
    shifts = [aperture.shift_per_disparity(c) for c in CHANNELS]
    candidates = np.linspace(-params.max_disparity_px, params.max_disparity_px, params.candidates)
    costs = np.empty((len(candidates), small_size[1], small_size[0]), np.float32)
    for i, d_frame in enumerate(candidates):
        d = d_frame / scale  # in preview pixels
        r, g, b = (_shifted(p, d * sx, d * sy) for p, (sx, sy) in zip(planes, shifts, strict=True))
        costs[i] = colour_line_cost(r, g, b, params.window_px, params.eps)
    best = np.argmin(costs, axis=0)
    rows, cols = np.indices(best.shape)
    at = costs[best, rows, cols]
    before = costs[np.maximum(best - 1, 0), rows, cols]
    after = costs[np.minimum(best + 1, len(candidates) - 1), rows, cols]
    curvature = before - 2.0 * at + after
    offset = np.where(curvature > 1e-6, 0.5 * (before - after) / np.maximum(curvature, 1e-6), 0.0)
    offset = np.where((best == 0) | (best == len(candidates) - 1), 0.0, np.clip(offset, -0.5, 0.5))
    step = candidates[1] - candidates[0] if len(candidates) > 1 else 0.0
    disparity = (candidates[best] + offset * step).astype(np.float32)
    mean_cost = costs.mean(axis=0)
    confidence = np.clip((mean_cost - at) / np.maximum(mean_cost, 1e-6), 0.0, 1.0).astype(np.float32)
    return LivePreview(disparity, confidence, scale, candidates.astype(np.float32))


def disparity_colours(preview: LivePreview, max_abs_px: float | None = None) -> np.ndarray:
    """(h, w, 3) uint8 RGB false colours: blue nearer, red farther than the focus plane, dark where unsure."""
    limit = max_abs_px or float(np.max(np.abs(preview.candidates_px))) or 1.0
    t = np.clip(0.5 + 0.5 * preview.disparity_px / limit, 0.0, 1.0)
    grey = (t * 255).astype(np.uint8)
    coloured = cv2.applyColorMap(grey, cv2.COLORMAP_JET)[..., ::-1]
    weight = (0.25 + 0.75 * preview.confidence)[..., None]
    return (coloured * weight).astype(np.uint8)
