"""Lateral colour (lateral chromatic aberration), measured blind from one capture and taken out of its planes.

A lens's lateral colour draws the red and blue images slightly larger or smaller than the green one: a
channel's displacement against green grows linearly with the distance from the image centre. It is a
fraction of a pixel at the corners, which is the size of the precision the depth needs, and it reads as
disparity that grows across the frame. Photographs that were resampled after capture (rectified stereo
pairs, for one) can be magnified differently along x and y, so the model is, per channel c,

    displacement_c(p) = (kx_c (x - cx), ky_c (y - cy))     (p = (x, y), centre (cx, cy) the image centre)

with green the reference (k = 0); a lens alone gives kx = ky.

Depth cannot be told from lateral colour along the direction in which depth moves a channel against
green, (s_c - s_g) in `disparity.channel_shifts`. Across that direction depth moves nothing, so what is
found there is lateral colour alone. Measured over tiles spread over the frame, that perpendicular
component n_c . displacement_c(p) = n_x kx_c (x - cx) + n_y ky_c (y - cy) gives kx_c and ky_c apart
whenever n_c is oblique (both n_x and n_y non-zero, as for the paper's filter layout); where n_c lies
along an axis only the isotropic lens model (kx = ky) can be fitted, and is.

Each tile's displacement is read from the phase correlation of the two channels' edge strength (gradient
magnitude of the log planes: an edge is an edge in every channel, whatever its colours): whole pixels from
its peak, the fraction from the slope of the cross-spectrum's phase, each frequency weighed by the
correlation's strength there and the slope fitted again on what the last fit leaves. (A slope with every
frequency weighed alike is flattened by the frequencies that carry only noise: it read half to two thirds
of the true magnification under defocus blur and sensor noise, where this one stays within a few per cent.) A tile whose edges all
run one way tells nothing across the depth direction and is weighed accordingly. The fit over the tiles
is robust (iteratively reweighted least squares with a Huber weight). The magnifications are
dimensionless, so they hold at every resolution of the same frame; a reading that is no magnification
(kx and ky of opposite signs) is not used.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.disparity import channel_shifts

TILE_PX = 64  # side of a tile (half-overlapping); displacements up to a quarter of it are read reliably
MIN_EDGE = 0.02  # mean edge strength (log units per pixel) below which a tile is too flat to read
MIN_PEAK = 0.08  # phase-correlation peak below which a tile's reading is not used
MIN_TILES = 24  # fewer readable tiles than this: no estimate (the frame is too flat or too small)
HUBER_PX = 0.15  # residual beyond which a tile's weight falls off (a tile reads to about 0.1 px)
SPECTRAL_SIGMA_PX = 1.0  # the Gaussian the correlation peak is smoothed to
PHASE_ITERATIONS = 4  # fits of the phase slope per tile
MIN_DISPLACEMENT_PX = 0.05  # largest displacement in the frame measured below which none is reported (noise)
MAX_DEPTH_STEP_PX = 1.0  # a step of disparity this large between neighbours of the quick search: an edge
MAX_TILES = 600  # tiles read per channel at most, spread evenly over the readable ones (the fit has plenty)


@dataclass(frozen=True)
class LateralColour:
    """Per-channel magnification against green: `k[c] = (kx, ky)`, dimensionless (red, green, blue)."""

    k: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
    tiles: int  # tiles the fit used (per channel, the smaller count)

    def largest_displacement_px(self, shape: tuple[int, int]) -> float:
        """The largest displacement this model gives anywhere in a frame of `shape` (at its corners)."""
        half_h, half_w = (shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0
        return max(float(np.hypot(kx * half_w, ky * half_h)) for kx, ky in self.k)

    @classmethod
    def from_ppt(cls, red: tuple[float, float], blue: tuple[float, float]) -> LateralColour:
        """Calibrated magnifications (kx, ky) of red and blue in parts per thousand, as `describe` gives them
        and a profile's `aperture.lateral_colour` holds them."""
        return cls(((red[0] / 1e3, red[1] / 1e3), (0.0, 0.0), (blue[0] / 1e3, blue[1] / 1e3)), 0)

    def describe(self) -> dict[str, float]:
        """The magnifications, for the recording and the logs (parts per thousand)."""
        names = ("red", "green", "blue")
        return {f"{names[c]}_{axis}_ppt": 1e3 * self.k[c][a] for c in (0, 2) for a, axis in enumerate("xy")}


NO_LATERAL_COLOUR = LateralColour(((0.0, 0.0), (0.0, 0.0), (0.0, 0.0)), 0)


def _edge_strength(planes: np.ndarray) -> list[np.ndarray]:
    """Gradient magnitude of each channel's log plane (`features.log_compress`), smoothed by 1 px."""
    from mca.processing.features import log_compress  # here: it loads numba, which start-up need not

    log = log_compress(planes)
    out = []
    for c in range(3):
        smooth = cv2.GaussianBlur(np.ascontiguousarray(log[..., c]), (0, 0), 1.0)
        gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
        out.append(cv2.magnitude(gx, gy))
    return out


def _tiles(plane: np.ndarray, corners: np.ndarray, tile: int) -> np.ndarray:
    """(N, tile, tile) float32 crops of `plane` at the (y, x) `corners`."""
    rows = corners[:, 0, None, None] + np.arange(tile)[None, :, None]
    cols = corners[:, 1, None, None] + np.arange(tile)[None, None, :]
    return plane[rows, cols]


def _spectra(tiles: np.ndarray) -> np.ndarray:
    """Windowed, zero-mean half spectra of (N, tile, tile) crops (float32 transforms on every core)."""
    import scipy.fft  # here, not at import: `processing.result` imports this module on every start-up

    window = cv2.createHanningWindow(tiles.shape[1:][::-1], cv2.CV_32F)[None]
    centred = (tiles - tiles.mean(axis=(1, 2), keepdims=True, dtype=np.float32)) * window
    return scipy.fft.rfft2(centred.astype(np.float32, copy=False), workers=-1)


def _peak_offsets(reference: np.ndarray, moving: np.ndarray, tile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per tile, from the half spectra of two sets of crops: (dx, dy) such that `moving`(p + (dx, dy))
    matches `reference`(p); the height of the correlation peak (1 for a perfect match); and how well the
    tile's content pins a displacement down in each direction, (Ixx, Ixy, Iyy) (the weighted second moments
    of its frequencies: edges all one way pin down only the displacement across them)."""
    import scipy.fft

    cross = moving * np.conj(reference)
    magnitude = np.abs(cross)
    cross /= magnitude + np.float32(1e-12)
    fy = np.fft.fftfreq(tile)[:, None]
    fx = np.fft.rfftfreq(tile)[None, :]
    gaussian = np.exp(-2.0 * (np.pi * SPECTRAL_SIGMA_PX) ** 2 * (fx * fx + fy * fy))
    surface = scipy.fft.irfft2(cross * gaussian.astype(np.float32)[None], s=(tile, tile), workers=-1)
    perfect = float(np.fft.irfft2(gaussian.astype(np.complex128), s=(tile, tile))[0, 0])  # the peak of a perfect match
    count = surface.shape[0]
    flat = surface.reshape(count, -1).argmax(axis=1)
    iy, ix = np.divmod(flat, tile)
    shift_x = np.where(ix > tile // 2, ix - tile, ix).astype(np.float64)
    shift_y = np.where(iy > tile // 2, iy - tile, iy).astype(np.float64)
    # The fraction from the slope of the phase (a parabola through the peak is pulled away from whole pixels
    # by up to a fifth of the fraction), each frequency weighed by its share of the correlation (frequencies
    # that carry only noise flatten the slope), fitted again on what the last estimate leaves.
    lowest = 2.0 / tile  # below about two cycles per tile the window, not the content, sets the phase
    band = gaussian * (1.0 - np.exp(-(fx * fx + fy * fy) / (lowest * lowest)))
    weight = band[None] * magnitude * np.where(fx > 0, 2.0, 1.0)[None]
    weight /= weight.sum(axis=(1, 2), keepdims=True) + 1e-30
    fx_, fy_ = fx[None], fy[None]
    sxx = np.sum(weight * fx_ * fx_, axis=(1, 2))
    syy = np.sum(weight * fy_ * fy_, axis=(1, 2))
    sxy = np.sum(weight * fx_ * fy_, axis=(1, 2))
    det = sxx * syy - sxy * sxy
    for _ in range(PHASE_ITERATIONS):
        ramp = np.exp(2j * np.pi * (fx_ * shift_x[:, None, None] + fy_ * shift_y[:, None, None]))
        phase = np.angle(cross * ramp) / (-2.0 * np.pi)
        bx = np.sum(weight * fx_ * phase, axis=(1, 2))
        by = np.sum(weight * fy_ * phase, axis=(1, 2))
        with np.errstate(divide="ignore", invalid="ignore"):
            shift_x += np.clip(np.where(det > 0, (syy * bx - sxy * by) / det, 0.0), -1.0, 1.0)
            shift_y += np.clip(np.where(det > 0, (sxx * by - sxy * bx) / det, 0.0), -1.0, 1.0)
    information = np.stack([sxx, sxy, syy], axis=1)
    return np.stack([shift_x, shift_y], axis=1), surface[np.arange(count), iy, ix] / perfect, information


def _information_across(information: np.ndarray, along: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """How well each tile tells its displacement along `normal` when depth may move it by any amount
    `along`: the information on the normal less what it shares with the depth direction (the Schur
    complement of (Ixx, Ixy, Iyy)); zero for a tile whose edges all run one way, unless across them is
    the normal itself."""

    def quadratic(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return (
            information[:, 0] * u[0] * v[0]
            + information[:, 1] * (u[0] * v[1] + u[1] * v[0])
            + information[:, 2] * u[1] * v[1]
        )

    return quadratic(normal, normal) - quadratic(normal, along) ** 2 / np.maximum(quadratic(along, along), 1e-30)


def _robust_fit(design: np.ndarray, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    coef = np.zeros(design.shape[1])
    for _ in range(8):
        residual = np.abs(values - design @ coef)
        w = np.sqrt(weights * np.minimum(1.0, HUBER_PX / np.maximum(residual, 1e-9)))
        coef = np.linalg.lstsq(design * w[:, None], values * w, rcond=None)[0]
    return coef


def _one_depth(disparity_px: np.ndarray, shape: tuple[int, int], corners: np.ndarray, tile: int) -> np.ndarray:
    """Which tiles of a frame of `shape` hold one surface: no step between neighbouring pixels of their
    disparities (a map of any size, in px of the frame) reaches `MAX_DEPTH_STEP_PX` (a slanted surface
    passes, an occluding edge does not)."""
    scale = disparity_px.shape[1] / shape[1]
    side = max(int(round(tile * scale)), 2)
    limit = (np.array(disparity_px.shape) - side).clip(min=0)
    at = np.minimum((corners * scale).round().astype(int), limit)
    disparity = np.ascontiguousarray(disparity_px, dtype=np.float32)
    step = np.zeros_like(disparity)
    step[:, 1:] = np.abs(np.diff(disparity, axis=1))
    step[1:, :] = np.maximum(step[1:, :], np.abs(np.diff(disparity, axis=0)))
    return _tiles(step, at, side).reshape(len(at), -1).max(axis=1) < MAX_DEPTH_STEP_PX


def estimate_lateral_colour(
    planes: np.ndarray, aperture: FilterAperture, tile_px: int = TILE_PX, disparity_px: np.ndarray | None = None
) -> LateralColour:
    """Lateral colour of (H, W, 3) linear planes (see the module's docstring). `disparity_px`, a disparity
    map of the frame at any size (in px of these planes), limits the reading to tiles of one depth: where
    depth changes inside a tile, the channels see different parts of the scene near the edge and the
    reading across moves too. None (all zero) when fewer than `MIN_TILES` tiles are textured enough (and
    of one depth), or when what is found moves no pixel of these planes by `MIN_DISPLACEMENT_PX` or more."""
    h, w = planes.shape[:2]
    if min(h, w) < 2 * tile_px:
        return NO_LATERAL_COLOUR
    edges = _edge_strength(planes)
    ys = np.arange(0, h - tile_px + 1, tile_px // 2)
    xs = np.arange(0, w - tile_px + 1, tile_px // 2)
    corners = np.stack(np.meshgrid(ys, xs, indexing="ij"), axis=-1).reshape(-1, 2)
    green_tiles = _tiles(edges[1], corners, tile_px)
    textured = green_tiles.mean(axis=(1, 2)) > MIN_EDGE
    if disparity_px is not None:
        textured &= _one_depth(disparity_px, (h, w), corners, tile_px)
    corners, green_tiles = corners[textured], green_tiles[textured]
    if len(corners) < MIN_TILES:
        return NO_LATERAL_COLOUR
    if len(corners) > MAX_TILES:
        pick = np.linspace(0, len(corners) - 1, MAX_TILES).round().astype(int)
        corners, green_tiles = corners[pick], green_tiles[pick]
    green = _spectra(green_tiles)
    centres_x = corners[:, 1] + tile_px / 2.0 - w / 2.0
    centres_y = corners[:, 0] + tile_px / 2.0 - h / 2.0
    shifts = channel_shifts(aperture)
    k = [(0.0, 0.0), (0.0, 0.0), (0.0, 0.0)]
    used = []
    for c in (0, 2):
        moving = _tiles(edges[c], corners, tile_px)
        readable = moving.mean(axis=(1, 2)) > MIN_EDGE
        if readable.sum() < MIN_TILES:
            return NO_LATERAL_COLOUR
        offsets, peak, info = _peak_offsets(green[readable], _spectra(moving[readable]), tile_px)
        depth_direction = shifts[c] - shifts[1]
        if not np.any(depth_direction):
            return NO_LATERAL_COLOUR
        along = depth_direction / np.hypot(*depth_direction)
        normal = np.array([-along[1], along[0]])
        across = offsets @ normal  # what depth cannot produce
        told = _information_across(info, along, normal)
        peak = peak * np.clip(told / max(float(np.median(told)), 1e-30), 0.0, 4.0)
        keep = (peak > MIN_PEAK) & (np.abs(across) < tile_px / 8.0)
        if keep.sum() < MIN_TILES:
            return NO_LATERAL_COLOUR
        x, y = centres_x[readable][keep], centres_y[readable][keep]
        ones = np.ones_like(x)
        if min(abs(normal[0]), abs(normal[1])) > 0.2:  # oblique: kx and ky apart
            coef = _robust_fit(np.stack([normal[0] * x, normal[1] * y, ones], 1), across[keep], peak[keep])
            kx, ky = float(coef[0]), float(coef[1])
            # a magnification stretches (or shrinks) both axes: opposite signs are none (the tiles read
            # something else: depth structure, a demosaicing or compression pattern), so leave the channel
            if kx * ky > 0:
                k[c] = (kx, ky)
        else:  # along an axis: the lens's isotropic magnification
            coef = _robust_fit(np.stack([normal[0] * x + normal[1] * y, ones], 1), across[keep], peak[keep])
            k[c] = (float(coef[0]), float(coef[0]))
        used.append(int(keep.sum()))
    found = LateralColour((k[0], k[1], k[2]), min(used))
    return found if found.largest_displacement_px((h, w)) >= MIN_DISPLACEMENT_PX else NO_LATERAL_COLOUR


def remove_lateral_colour(planes: np.ndarray, colour: LateralColour) -> np.ndarray:
    """(H, W, 3) planes of any size with red and blue resampled onto green's geometry: channel c read at
    centre + (1 + k_c) (p - centre), per axis, with Lanczos interpolation (OpenCV's bicubic moves content by
    up to a fifth more or less than asked at sub-pixel shifts). The planes as they are when there is none."""
    h, w = planes.shape[:2]
    if not any(kx or ky for kx, ky in colour.k):
        return planes
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    out = np.array(planes, dtype=np.float32, copy=True)
    for c in (0, 2):
        kx, ky = colour.k[c]
        if kx == 0.0 and ky == 0.0:
            continue
        matrix = np.array([[1.0 + kx, 0.0, -kx * cx], [0.0, 1.0 + ky, -ky * cy]], dtype=np.float64)
        out[..., c] = cv2.warpAffine(
            np.ascontiguousarray(planes[..., c], dtype=np.float32),
            matrix,
            (w, h),
            flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return out
