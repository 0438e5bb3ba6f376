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

import os
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from mca.processing.camera import CHANNELS, FilterAperture
from mca.processing.features import percentile
from mca.processing.sampling import remap_cubic, remap_linear


def channel_shifts(aperture: FilterAperture) -> np.ndarray:
    """(3, 2) array: (dx, dy) image displacement of red, green, blue per pixel of widest-pair disparity."""
    return np.array([aperture.shift_per_disparity(c) for c in CHANNELS], dtype=np.float64)


def sample_shifted(plane: np.ndarray, dx: float, dy: float, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """`plane` sampled at (x + dx, y + dy) for every pixel (x, y); borders replicate."""
    matrix = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], dtype=np.float64)
    return cv2.warpAffine(
        plane,
        matrix,
        (plane.shape[1], plane.shape[0]),
        flags=interpolation | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def sample_shifted_rows(
    plane: np.ndarray, dx: float, dy: float, row0: int, row1: int, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """Rows row0..row1 of `sample_shifted(plane, dx, dy)` (borders replicate at the plane's own edges)."""
    matrix = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy + row0]], dtype=np.float64)
    return cv2.warpAffine(
        plane,
        matrix,
        (plane.shape[1], row1 - row0),
        flags=interpolation | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def shift_channels(
    planes: np.ndarray, aperture: FilterAperture, disparity_px: float, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """Channels re-aligned for one uniform disparity: channel c sampled at x + d * s_c (removes its fringes)."""
    shifts = channel_shifts(aperture)
    out = np.empty_like(planes, dtype=np.float32)
    for c in range(3):
        out[..., c] = sample_shifted(
            np.ascontiguousarray(planes[..., c], dtype=np.float32),
            disparity_px * shifts[c, 0],
            disparity_px * shifts[c, 1],
            interpolation,
        )
    return out


def warp_channels(
    planes: np.ndarray,
    aperture: FilterAperture,
    disparity_px: np.ndarray,
    interpolation: int = cv2.INTER_LINEAR,
    origin_xy: tuple[int, int] = (0, 0),
    channels: Sequence[np.ndarray] | None = None,
) -> np.ndarray:
    """Channels re-aligned for a per-pixel disparity map (same grid as `planes`, or a crop at `origin_xy`);
    `channels`: the planes' float32 channels as `cv2.split` gives them, for a caller warping many crops."""
    shifts = channel_shifts(aperture)
    height, width = disparity_px.shape
    xs = np.arange(width, dtype=np.float32)[None, :] + np.float32(origin_xy[0])
    ys = np.arange(height, dtype=np.float32)[:, None] + np.float32(origin_xy[1])
    d = disparity_px.astype(np.float32, copy=False)
    split = cv2.split(np.asarray(planes, dtype=np.float32)) if channels is None else channels
    out = np.empty((height, width, 3), dtype=np.float32)
    rows = 64

    def strip(y0: int) -> None:
        """Rows y0..y0+rows, the maps made per strip (they stay in the cache; remap is per pixel)."""
        y1 = min(height, y0 + rows)
        ds = d[y0:y1]
        moved = []
        for c in range(3):
            map_x = _shifted_map(xs, ds, shifts[c, 0], (y1 - y0, width))
            map_y = _shifted_map(ys[y0:y1], ds, shifts[c, 1], (y1 - y0, width))
            moved.append(_remap(split[c], map_x, map_y, interpolation))
        out[y0:y1] = cv2.merge(moved)

    parallel_map(strip, range(0, height, rows))
    return out


def _remap(src: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, interpolation: int) -> np.ndarray:
    """`cv2.remap` with replicated borders; bilinear and cubic sampling by our own exact kernels
    (`processing.sampling`: OpenCV rounds the coordinates, and its releases differently), any other by OpenCV."""
    if interpolation == cv2.INTER_LINEAR:
        return remap_linear(src, map_x, map_y)
    if interpolation == cv2.INTER_CUBIC:
        return remap_cubic(src, map_x, map_y)
    return cv2.remap(src, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)


def _shifted_map(base: np.ndarray, d: np.ndarray, shift: float, shape: tuple[int, int]) -> np.ndarray:
    """base + d * shift as a full (H, W) float32 map (no multiply where the channel does not move on this axis)."""
    if shift == 0.0:
        return np.ascontiguousarray(np.broadcast_to(base, shape))
    out = np.multiply(d, np.float32(shift), dtype=np.float32)
    out += base
    return out


def parallel_map(function, items) -> list:
    """`function` over `items` on the shared worker threads (OpenCV and numpy release the GIL in their loops)."""
    items = list(items)
    if len(items) <= 1 or _WORKERS <= 1 or threading.current_thread().name.startswith("mca-processing"):
        return [function(item) for item in items]  # (from a worker itself: serially, no deadlock)
    return list(_pool().map(function, items))


# helper threads; MCA_THREADS: a batch worker's share of the cores (capture/threads.py)
_WORKERS = int(os.environ.get("MCA_THREADS") or 0) or max(1, min(4, os.cpu_count() or 1))
_POOL: ThreadPoolExecutor | None = None


def set_worker_threads(count: int) -> None:
    """Use `count` helper threads from now on (a batch worker's share of the cores; see capture/threads.py)."""
    global _WORKERS, _POOL
    _WORKERS = max(1, int(count))
    if _POOL is not None:
        _POOL.shutdown(wait=False)
        _POOL = None


def helper_threads() -> int:
    """Threads this process computes on: the helper pool's size (a batch worker's share of the cores)."""
    return _WORKERS


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=_WORKERS, thread_name_prefix="mca-processing")
    return _POOL


def band_pass(planes: np.ndarray, sigma_fine_px: float = 0.8, sigma_coarse_px: float = 4.0) -> np.ndarray:
    """Difference of Gaussians per channel on log-compressed intensities: edges and texture, no shading.

    The fine blur band-limits the image so that the linear interpolation used by the matching is
    nearly exact (no pixel locking); log compression makes the measure independent of exposure.
    """
    scale = percentile(planes, 99.5) or 1.0
    compressed = np.log1p(np.clip(planes, 0.0, None) * np.float32(32.0 / scale)).astype(np.float32)
    out = np.empty_like(compressed)

    def one(c: int) -> None:
        plane = np.ascontiguousarray(compressed[..., c])
        fine = cv2.GaussianBlur(plane, (0, 0), sigma_fine_px, borderType=cv2.BORDER_REFLECT)
        coarse = cv2.GaussianBlur(plane, (0, 0), sigma_coarse_px, borderType=cv2.BORDER_REFLECT)
        np.subtract(fine, coarse, out=out[..., c])

    parallel_map(one, range(planes.shape[2]))
    return out


@dataclass(frozen=True)
class DisparityParams:
    """Parameters of the per-pixel search, in pixels of the planes searched."""

    window_px: int = 9  # side of the square matching window
    step_px: float = 0.5  # spacing of the candidate disparities
    noise_floor: float = 2e-3  # std of band-pass signal treated as flat (regularises the correlations)
    aggregation_px: int = 0  # extra box aggregation of the cost (0 = none)
    subpixel: bool = True  # parabola fit around the winner (False: integer winner-takes-all)


@dataclass
class DisparityMap:
    """Per-pixel disparity of the widest filter pair (px of the planes searched), + = farther."""

    disparity_px: np.ndarray  # (H, W) float32, sub-pixel
    confidence: np.ndarray  # (H, W) float32 in [0, 1]
    cost: np.ndarray  # (H, W) float32, colour-line measure at the minimum (0 = aligned)
    candidates_px: np.ndarray  # (D,) the disparities searched


def _box(image: np.ndarray, window: int) -> np.ndarray:
    return cv2.boxFilter(image, cv2.CV_32F, (window, window), normalize=True, borderType=cv2.BORDER_REFLECT)


class AlignmentCost:
    """The colour-line measure of one set of band-pass planes for any channel sampling (uniform or per-pixel)."""

    def __init__(
        self,
        band: np.ndarray,
        aperture: FilterAperture,
        window_px: int,
        noise_floor: float,
        interpolation: int = cv2.INTER_LINEAR,
    ) -> None:
        self.interpolation = interpolation
        self.band = [np.ascontiguousarray(band[..., c], dtype=np.float32) for c in range(3)]
        self.shifts = channel_shifts(aperture)
        self.window = int(window_px) | 1
        self.eps = np.float32(noise_floor**2)

    def _measure(self, channels: list[np.ndarray]) -> np.ndarray:
        return colour_line_cost(channels, self.window, self.eps)

    def uniform(self, disparity_px: float) -> np.ndarray:
        """Cost map for one disparity everywhere."""
        channels = [
            sample_shifted(
                self.band[c], disparity_px * self.shifts[c, 0], disparity_px * self.shifts[c, 1], self.interpolation
            )
            for c in range(3)
        ]
        return self._measure(channels)

    def per_pixel(self, disparity_px: np.ndarray, origin_xy: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Cost map for a disparity map on a crop of the planes starting at `origin_xy`."""
        height, width = disparity_px.shape
        xs = np.arange(width, dtype=np.float32)[None, :] + np.float32(origin_xy[0])
        ys = np.arange(height, dtype=np.float32)[:, None] + np.float32(origin_xy[1])
        channels = []
        for c in range(3):
            map_x = _shifted_map(xs, disparity_px, self.shifts[c, 0], (height, width))
            map_y = _shifted_map(ys, disparity_px, self.shifts[c, 1], (height, width))
            channels.append(_remap(self.band[c], map_x, map_y, self.interpolation))
        return self._measure(channels)

    def offsets(self, disparity_px: np.ndarray, deltas: np.ndarray, reduce=None) -> list:
        """`per_pixel(disparity_px + delta)` for each delta, the maps built once and the deltas evaluated in
        parallel threads; with `reduce`, `reduce(k, cost)` is called (in the worker) for the k-th delta instead
        and its results are returned."""
        height, width = disparity_px.shape
        xs = np.arange(width, dtype=np.float32)[None, :]
        ys = np.arange(height, dtype=np.float32)[:, None]
        base = [
            (
                _shifted_map(xs, disparity_px, self.shifts[c, 0], (height, width)),
                _shifted_map(ys, disparity_px, self.shifts[c, 1], (height, width)),
            )
            for c in range(3)
        ]

        def one(k: int) -> np.ndarray:
            delta = float(deltas[k])
            moves = [(np.float32(delta * self.shifts[c, 0]), np.float32(delta * self.shifts[c, 1])) for c in range(3)]

            def sampled(a0: int, a1: int) -> list[np.ndarray]:
                """Rows a0..a1 of the three channels sampled at the model + delta (remap is per pixel)."""
                channels = []
                for c in range(3):
                    map_x, map_y = base[c][0][a0:a1], base[c][1][a0:a1]
                    sx, sy = moves[c]
                    channels.append(
                        _remap(
                            self.band[c],
                            map_x + sx if sx != 0 else map_x,
                            map_y + sy if sy != 0 else map_y,
                            self.interpolation,
                        )
                    )
                return channels

            cost = colour_line_cost_rows(sampled, height, self.window, self.eps)
            return cost if reduce is None else reduce(k, cost)

        return parallel_map(one, range(len(deltas)))

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


def colour_line_energy(channel: np.ndarray, window: int, eps: np.float32) -> np.ndarray:
    """1 / sqrt(box(c^2) + eps): the normalisation of one channel in `colour_line_cost`."""
    e = _box(channel * channel, window)
    e += eps
    np.sqrt(e, out=e)
    return np.reciprocal(e, out=e)


_STRIP_ROWS = 96  # the cost is computed in strips of rows (plus the window's halo) that stay in the cache


def colour_line_cost(
    channels: list[np.ndarray], window: int, eps: np.float32, energy: list[np.ndarray | None] | None = None
) -> np.ndarray:
    """The colour-line measure of three (band-pass, zero-mean) channels over `window` x `window` windows
    (float32). `energy` may hold precomputed 1/sqrt(box(c^2) + eps) maps per channel.

    Computed in strips of rows with a halo of half a window, so that the dozen intermediate maps stay in the
    cache (the whole-frame version is bound by memory bandwidth); each strip's rows see the same windows."""
    height = channels[0].shape[0]
    halo = window // 2
    if height <= 2 * _STRIP_ROWS:
        return _colour_line_block(channels, window, eps, energy)
    out = np.empty(channels[0].shape, np.float32)
    for y0 in range(0, height, _STRIP_ROWS):
        y1 = min(height, y0 + _STRIP_ROWS)
        a0, a1 = max(0, y0 - halo), min(height, y1 + halo)
        part = _colour_line_block(
            [ch[a0:a1] for ch in channels],
            window,
            eps,
            None if energy is None else [None if e is None else e[a0:a1] for e in energy],
        )
        out[y0:y1] = part[y0 - a0 : y1 - a0]
    return out


def colour_line_cost_rows(
    sampled, height: int, window: int, eps: np.float32, energy: list[np.ndarray | None] | None = None
) -> np.ndarray:
    """`colour_line_cost` of channels produced strip by strip: `sampled(a0, a1)` gives rows a0..a1 of the three
    channels (a warp of those rows only), so that the warped strips are used while still in the cache."""
    halo = window // 2
    if height <= 2 * _STRIP_ROWS:
        return _colour_line_block(sampled(0, height), window, eps, energy)
    out = None
    for y0 in range(0, height, _STRIP_ROWS):
        y1 = min(height, y0 + _STRIP_ROWS)
        a0, a1 = max(0, y0 - halo), min(height, y1 + halo)
        part = _colour_line_block(
            sampled(a0, a1), window, eps, None if energy is None else [None if e is None else e[a0:a1] for e in energy]
        )
        if out is None:
            out = np.empty((height, part.shape[1]), np.float32)
        out[y0:y1] = part[y0 - a0 : y1 - a0]
    assert out is not None  # height > 2 * _STRIP_ROWS: the loop ran
    return out


def _colour_line_block(
    channels: list[np.ndarray], window: int, eps: np.float32, energy: list[np.ndarray | None] | None = None
) -> np.ndarray:
    inv = []
    for c in range(3):
        if energy is not None and energy[c] is not None:
            inv.append(energy[c])
            continue
        inv.append(colour_line_energy(channels[c], window, eps))
    rg = _box(channels[0] * channels[1], window)
    rg *= inv[0]
    rg *= inv[1]
    rb = _box(channels[0] * channels[2], window)
    rb *= inv[0]
    rb *= inv[2]
    gb = _box(channels[1] * channels[2], window)
    gb *= inv[1]
    gb *= inv[2]
    triple = rg * rb
    triple *= gb
    triple *= np.float32(2.0)
    np.square(rg, out=rg)
    np.square(rb, out=rb)
    np.square(gb, out=gb)
    rg += rb
    rg += gb
    triple -= rg
    triple += np.float32(1.0)
    return np.clip(triple, 0.0, 1.0, out=triple)


def estimate_disparity(
    planes: np.ndarray,
    aperture: FilterAperture,
    range_px: tuple[float, float],
    params: DisparityParams = DisparityParams(),
    band: np.ndarray | None = None,
) -> DisparityMap:
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
    eps = np.float32(params.noise_floor**2)
    shifts = channel_shifts(aperture)
    candidates = candidate_disparities(range_px, params.step_px)
    count = len(candidates)
    height, width = band.shape[:2]
    volume = np.empty((count, height, width), dtype=np.float32)
    # a channel that does not move (no shift) has the same energy for every candidate
    still = [None if np.any(shifts[c] != 0) else colour_line_energy(channels[c], window, eps) for c in range(3)]

    def candidate(i: int) -> None:
        d = candidates[i]

        def sampled(a0: int, a1: int) -> list[np.ndarray]:
            """Rows a0..a1 of the channels sampled at x + d s_c (a warp of those rows only)."""
            return [
                channels[c][a0:a1]
                if still[c] is not None
                else sample_shifted_rows(channels[c], d * shifts[c, 0], d * shifts[c, 1], a0, a1)
                for c in range(3)
            ]

        cost = colour_line_cost_rows(sampled, height, window, eps, still)
        if params.aggregation_px > 1:
            cost = _box(cost, params.aggregation_px)
        volume[i] = cost

    parallel_map(candidate, range(count))
    best = np.empty((height, width), np.int64)
    at = np.empty((height, width), np.float32)
    before = np.empty_like(at)
    after = np.empty_like(at)
    mean_cost = np.empty_like(at)
    second = np.empty_like(at)

    def reduce_rows(rows: slice) -> None:
        """Winner, its neighbours, the mean and the best candidate more than two steps away, for a band of rows."""
        vol = volume[:, rows]
        b = np.zeros(vol.shape[1:], np.int64)
        a = vol[0].copy()
        total = vol[0].astype(np.float32)
        for i in range(1, count):
            np.copyto(b, i, where=vol[i] < a)  # strict: the first minimum wins, as np.argmin
            np.minimum(a, vol[i], out=a)
            total += vol[i]
        best[rows], at[rows] = b, a
        before[rows] = np.take_along_axis(vol, np.maximum(b - 1, 0)[None], axis=0)[0]
        after[rows] = np.take_along_axis(vol, np.minimum(b + 1, count - 1)[None], axis=0)[0]
        mean_cost[rows] = total / np.float32(count)
        sec = np.full_like(a, np.inf)
        for i in range(count):
            np.minimum(sec, vol[i], out=sec, where=np.abs(b - i) > 2)
        second[rows] = np.where(np.isfinite(sec), sec, mean_cost[rows])

    bands = max(1, min(_WORKERS * 2, height // 32))
    edges = np.linspace(0, height, bands + 1).astype(int)
    parallel_map(reduce_rows, [slice(edges[k], edges[k + 1]) for k in range(bands)])
    interior = (best > 0) & (best < count - 1)
    offset = np.where(interior & params.subpixel, subpixel_minimum(before, at, after), 0.0)
    disparity = (candidates[best] + offset * params.step_px).astype(np.float32)
    dip = np.clip((mean_cost - at) / np.maximum(mean_cost, 1e-6), 0.0, 1.0)
    unique = np.clip((second - at) / np.maximum(mean_cost - at, 1e-6) * 2.0, 0.0, 1.0)
    texture = np.zeros_like(at)
    for c in range(3):
        channel = np.ascontiguousarray(band[..., c])
        m = _box(channel, window)
        texture += np.maximum(_box(channel * channel, window) - m * m, 0.0)
    texture /= 3.0
    contrast = texture / (texture + np.float32(4.0 * params.noise_floor**2))
    confidence = (dip * unique * contrast).astype(np.float32)
    confidence[~interior] *= 0.25
    return DisparityMap(disparity, confidence, at.astype(np.float32), candidates)
