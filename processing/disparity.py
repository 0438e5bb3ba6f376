"""Per-pixel MCA disparity: align the three colour planes along the filter geometry, with sub-pixel precision and confidence.

Geometry (see `FilterAperture.shift_per_disparity`): for a candidate disparity d of the
widest filter pair, channel c is sampled at x + d * s_c, where s_c = (dx, dy) is the
channel's displacement per pixel of disparity. Positive d = farther than the focus plane.
All disparities in this module are in pixels of the planes handed in.

Alignment measure: the colour-line measure of Bando et al. 2008,
L = det(C) / (var_r var_g var_b) over a window (C the 3x3 colour covariance), written
through the three regularised pairwise correlations rho_ab as
L = 1 - rho_rg^2 - rho_rb^2 - rho_gb^2 + 2 rho_rg rho_rb rho_gb. It is invariant to the
gain, offset and sign of each channel, so objects of any colour align; L = 0 when the
window's colours lie on a line (channels aligned), L -> 1 for unrelated channels. The
planes are first turned into band-pass images (difference of Gaussians, zero local mean, so
the correlations need no mean subtraction), which keeps the measure on edges and texture and makes sub-pixel
interpolation of the cost nearly unbiased.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from processing.camera import CHANNELS, FilterAperture


def channel_shifts(aperture: FilterAperture) -> np.ndarray:
    """(3, 2) array: (dx, dy) image displacement of red, green, blue per pixel of widest-pair disparity."""
    return np.array([aperture.shift_per_disparity(c) for c in CHANNELS], dtype=np.float64)


def sample_shifted(plane: np.ndarray, dx: float, dy: float, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """`plane` sampled at (x + dx, y + dy) for every pixel (x, y); borders replicate."""
    matrix = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], dtype=np.float64)
    return cv2.warpAffine(plane, matrix, (plane.shape[1], plane.shape[0]),
                          flags=interpolation | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def shift_channels(planes: np.ndarray, aperture: FilterAperture, disparity_px: float,
                   interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Channels re-aligned for one uniform disparity: channel c sampled at x + d * s_c (removes its fringes)."""
    shifts = channel_shifts(aperture)
    out = np.empty_like(planes, dtype=np.float32)
    for c in range(3):
        out[..., c] = sample_shifted(np.ascontiguousarray(planes[..., c], dtype=np.float32),
                                     disparity_px * shifts[c, 0], disparity_px * shifts[c, 1], interpolation)
    return out


def warp_channels(planes: np.ndarray, aperture: FilterAperture, disparity_px: np.ndarray,
                  interpolation: int = cv2.INTER_LINEAR, origin_xy: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Channels re-aligned for a per-pixel disparity map (same grid as `planes`, or a crop at `origin_xy`)."""
    shifts = channel_shifts(aperture)
    height, width = disparity_px.shape
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    out = np.empty((height, width, 3), dtype=np.float32)
    d = disparity_px.astype(np.float32)
    for c in range(3):
        map_x = xs + origin_xy[0] + d * np.float32(shifts[c, 0])
        map_y = ys + origin_xy[1] + d * np.float32(shifts[c, 1])
        out[..., c] = cv2.remap(np.ascontiguousarray(planes[..., c], dtype=np.float32), map_x, map_y,
                                interpolation, borderMode=cv2.BORDER_REPLICATE)
    return out


def band_pass(planes: np.ndarray, sigma_fine_px: float = 0.8, sigma_coarse_px: float = 4.0) -> np.ndarray:
    """Difference of Gaussians per channel on log-compressed intensities: edges and texture, no shading.

    The fine blur band-limits the image so that the linear interpolation used by the matching is
    nearly exact (no pixel locking); log compression makes the measure independent of exposure.
    """
    scale = float(np.percentile(planes, 99.5)) or 1.0
    compressed = np.log1p(np.clip(planes, 0.0, None) * np.float32(32.0 / scale)).astype(np.float32)
    out = np.empty_like(compressed)
    for c in range(planes.shape[2]):
        plane = np.ascontiguousarray(compressed[..., c])
        fine = cv2.GaussianBlur(plane, (0, 0), sigma_fine_px, borderType=cv2.BORDER_REFLECT)
        coarse = cv2.GaussianBlur(plane, (0, 0), sigma_coarse_px, borderType=cv2.BORDER_REFLECT)
        out[..., c] = fine - coarse
    return out


@dataclass(frozen=True)
class DisparityParams:
    """Parameters of the per-pixel search, in pixels of the planes searched."""

    window_px: int = 9              # side of the square matching window
    step_px: float = 0.5            # spacing of the candidate disparities
    noise_floor: float = 2e-3       # std of band-pass signal treated as flat (regularises the correlations)
    aggregation_px: int = 0         # extra box aggregation of the cost (0 = none)
    subpixel: bool = True           # parabola fit around the winner (False: integer winner-takes-all)


@dataclass
class DisparityMap:
    """Per-pixel disparity of the widest filter pair (px of the planes searched), + = farther."""

    disparity_px: np.ndarray        # (H, W) float32, sub-pixel
    confidence: np.ndarray          # (H, W) float32 in [0, 1]
    cost: np.ndarray                # (H, W) float32, colour-line measure at the minimum (0 = aligned)
    candidates_px: np.ndarray       # (D,) the disparities searched


def _box(image: np.ndarray, window: int) -> np.ndarray:
    return cv2.boxFilter(image, cv2.CV_32F, (window, window), normalize=True, borderType=cv2.BORDER_REFLECT)


class AlignmentCost:
    """The colour-line measure of one set of band-pass planes for any channel sampling (uniform or per-pixel)."""

    def __init__(self, band: np.ndarray, aperture: FilterAperture, window_px: int, noise_floor: float,
                 interpolation: int = cv2.INTER_LINEAR) -> None:
        self.interpolation = interpolation
        self.band = [np.ascontiguousarray(band[..., c], dtype=np.float32) for c in range(3)]
        self.shifts = channel_shifts(aperture)
        self.window = int(window_px) | 1
        self.eps = np.float32(noise_floor ** 2)

    def _measure(self, channels: list[np.ndarray]) -> np.ndarray:
        w = self.window
        energy = [_box(ch * ch, w) + self.eps for ch in channels]
        rho = {}
        for a, b in ((0, 1), (0, 2), (1, 2)):
            rho[a, b] = _box(channels[a] * channels[b], w) / np.sqrt(energy[a] * energy[b])
        return _colour_line(rho[0, 1], rho[0, 2], rho[1, 2])

    def uniform(self, disparity_px: float) -> np.ndarray:
        """Cost map for one disparity everywhere."""
        channels = [sample_shifted(self.band[c], disparity_px * self.shifts[c, 0], disparity_px * self.shifts[c, 1],
                                   self.interpolation) for c in range(3)]
        return self._measure(channels)

    def per_pixel(self, disparity_px: np.ndarray, origin_xy: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Cost map for a disparity map on a crop of the planes starting at `origin_xy`."""
        height, width = disparity_px.shape
        xs = np.arange(width, dtype=np.float32)[None, :] + np.float32(origin_xy[0])
        ys = np.arange(height, dtype=np.float32)[:, None] + np.float32(origin_xy[1])
        channels = []
        for c in range(3):
            map_x = xs + disparity_px * np.float32(self.shifts[c, 0])
            map_y = ys + disparity_px * np.float32(self.shifts[c, 1])
            channels.append(cv2.remap(self.band[c], map_x, map_y, self.interpolation, borderMode=cv2.BORDER_REPLICATE))
        return self._measure(channels)

    def texture(self) -> np.ndarray:
        """Mean band-pass variance in the window: how much there is to align."""
        w = self.window
        total = np.zeros_like(self.band[0])
        for ch in self.band:
            m = _box(ch, w)
            total += _box(ch * ch, w) - m * m
        return np.maximum(total / 3.0, 0.0)


def candidate_disparities(range_px: tuple[float, float], step_px: float) -> np.ndarray:
    """Evenly spaced candidates covering `range_px` and containing 0 exactly."""
    low, high = range_px
    start = np.floor(low / step_px)
    stop = np.ceil(high / step_px)
    return (np.arange(start, stop + 1) * step_px).astype(np.float64)


def subpixel_minimum(before: np.ndarray, at: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Offset in steps (-0.5..0.5) of the minimum of the parabola through three equally spaced costs."""
    curvature = before - 2.0 * at + after
    offset = np.where(curvature > 1e-9, 0.5 * (before - after) / np.maximum(curvature, 1e-9), 0.0)
    return np.clip(offset, -0.5, 0.5)


def _colour_line(rg: np.ndarray, rb: np.ndarray, gb: np.ndarray) -> np.ndarray:
    """det(C)/(var_r var_g var_b) from the three pairwise correlations (Bando et al. 2008)."""
    cost = 1.0 - rg * rg - rb * rb - gb * gb + 2.0 * rg * rb * gb
    return np.clip(cost, 0.0, 1.0, out=cost)


def estimate_disparity(planes: np.ndarray, aperture: FilterAperture, range_px: tuple[float, float],
                       params: DisparityParams = DisparityParams(), band: np.ndarray | None = None) -> DisparityMap:
    """Winner-takes-all over a colour-line cost volume, parabola sub-pixel refinement and a confidence.

    For speed the correlations are uncentred (the band-pass planes have zero local mean): per
    candidate 3 warps and 6 box filters. Confidence combines how far the cost dips below
    its mean over all candidates, how unique the minimum is (second-best candidate more than
    two steps away) and the texture in the window; flat areas get ~0.
    """
    if band is None:
        band = band_pass(planes)
    window = int(params.window_px) | 1
    channels = [np.ascontiguousarray(band[..., c], dtype=np.float32) for c in range(3)]
    eps = np.float32(params.noise_floor ** 2)
    shifts = channel_shifts(aperture)
    candidates = candidate_disparities(range_px, params.step_px)
    count = len(candidates)
    height, width = band.shape[:2]
    volume = np.empty((count, height, width), dtype=np.float32)
    for i, d in enumerate(candidates):
        moved = [sample_shifted(channels[c], d * shifts[c, 0], d * shifts[c, 1]) for c in range(3)]
        energy = [_box(m * m, window) + eps for m in moved]
        rg = _box(moved[0] * moved[1], window) / np.sqrt(energy[0] * energy[1])
        rb = _box(moved[0] * moved[2], window) / np.sqrt(energy[0] * energy[2])
        gb = _box(moved[1] * moved[2], window) / np.sqrt(energy[1] * energy[2])
        cost = _colour_line(rg, rb, gb)
        if params.aggregation_px > 1:
            cost = _box(cost, params.aggregation_px)
        volume[i] = cost
    best = np.argmin(volume, axis=0)
    at = np.take_along_axis(volume, best[None], axis=0)[0]
    before = np.take_along_axis(volume, np.maximum(best - 1, 0)[None], axis=0)[0]
    after = np.take_along_axis(volume, np.minimum(best + 1, count - 1)[None], axis=0)[0]
    interior = (best > 0) & (best < count - 1)
    offset = np.where(interior & params.subpixel, subpixel_minimum(before, at, after), 0.0)
    disparity = (candidates[best] + offset * params.step_px).astype(np.float32)
    mean_cost = volume.mean(axis=0)
    second = np.full_like(at, np.inf)
    for i in range(count):
        far = np.abs(best - i) > 2
        np.minimum(second, np.where(far, volume[i], np.inf), out=second)
    second = np.where(np.isfinite(second), second, mean_cost)
    dip = np.clip((mean_cost - at) / np.maximum(mean_cost, 1e-6), 0.0, 1.0)
    unique = np.clip((second - at) / np.maximum(mean_cost - at, 1e-6) * 2.0, 0.0, 1.0)
    texture = np.zeros_like(at)
    for c in range(3):
        channel = np.ascontiguousarray(band[..., c])
        m = _box(channel, window)
        texture += np.maximum(_box(channel * channel, window) - m * m, 0.0)
    texture /= 3.0
    contrast = texture / (texture + np.float32(4.0 * params.noise_floor ** 2))
    confidence = (dip * unique * contrast).astype(np.float32)
    confidence[~interior] *= 0.25
    return DisparityMap(disparity, confidence, at.astype(np.float32), candidates)
