"""Dense per-pixel MCA disparity: a colour-alignment cost volume, semi-global aggregation, sub-pixel minimum.

1. Range: a quick search on a quarter-size image over the whole range the optics allow finds the
   disparities the scene occupies; the full search covers those plus a margin (fewer candidates, and no
   false matches far outside the scene). Where that range would take the volumes past their memory budget,
   the candidates stay `step_px` apart over the quick map's bulk and grow coarser out to the range's ends
   (`search_candidates`).
2. Cost: the colour-line cost (`processing.cost`) of the feature planes at every candidate, plus the same cost
   computed at half size and brought back up (weak, fine texture is backed by coarser structure: upscaled or
   noisy content has little signal at the finest scale). Each pixel's cost curve is scaled by how much of its
   window is signal rather than sensor noise (`features.signal_weight`, from the noise model): on a texture-less
   surface the curve is the noise's, as deep at a wrong disparity as at the right one, and summed along the
   aggregation's paths it outvoted the few textured pixels that know the surface's disparity.
3. Aggregation: eight-path semi-global aggregation (`processing.sgm`) spreads the evidence of textured
   pixels along the image; textureless ones take it from their neighbours.
4. Winner and sub-pixel: the lowest aggregated cost, refined by a parabola through it and its neighbours.
   Confidence: how far the winner stands below the best candidate more than two steps away, in units of the
   aggregated price of a jump.

All disparities are of the widest filter pair in pixels of the planes handed in, + = farther than focus.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numba as nb
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.cost import CostInput, cost_input, cost_volume
from mca.processing.features import display_gamma, percentile
from mca.processing.jit import FASTMATH
from mca.processing.sgm import aggregate

_PATHS = 8  # semi-global aggregation paths: an isolated jump costs about this many P2


@dataclass(frozen=True)
class DenseParams:
    """Parameters of the dense search, in pixels of the planes searched (the analysis grid)."""

    window_px: int = 9  # side of the cost window
    step_px: float = 0.5  # spacing of the candidate disparities
    noise_floor: float = 2e-3  # feature amplitude treated as flat
    coarse_weight: float = 1.0  # weight of the half-size cost beside the full-size one (0: none)
    # an option, off (0: the share above everywhere): the half-size cost's share falls by the full-size window's
    # `features.signal_weight` with half weight at this signal-to-noise ratio (needs the noise model). Its window
    # is twice as wide and, beside a thin object or an edge, sees the background too. At 1 it helps the real-content
    # renders (docs/evaluation.md, tenth stop) but splits dog.png's books and joins bonsai.png's crown to the
    # background, and makes the card of tests/test_sketch.py's slanted floor slanted
    coarse_half_snr: float = 0.0
    p1: float = 0.2  # SGM penalty of a one-step disparity change (cost units, for 0.5 px steps)
    p2: float = 3.0  # SGM penalty of a larger jump (for 0.5 px steps)
    alpha: float = 0.0  # how much image edges lower P2
    # the guide of the edge-adaptive P2 (`alpha`): steps of any colour channel (else of the mean brightness), less
    # `noise_steps` robust sigmas of its pixel-to-pixel steps. Options, off: with alpha 100 and 3 sigmas they
    # help weakly textured renders (docs/evaluation.md) but put two paper scenes' in-focus objects 2.2-2.5 mm off
    colour_guide: bool = False
    noise_steps: float = 0.0
    narrow_range: bool = True  # find the occupied range on a quarter-size image first
    range_margin_px: float = 2.0  # kept around the occupied range
    # the search's two volumes (the uint16 cost and the float32 aggregation, 6 bytes per pixel and candidate) stay
    # within this: issue 16's 3 GB peak less what the rest of a 20 MP run holds (under 1 GB). Past it the
    # candidates are `step_px` apart only over the quick map's `core_percentiles` (`search_candidates`)
    volume_budget_mb: float = 2048.0
    core_percentiles: tuple[float, float] = (2.0, 98.0)
    sampling: str = "bilinear"  # the cost's sampler: "bilinear", "phase" or "bspline" (`processing.cost`)
    noise_model: bool = True  # measure the sensor noise and take its sampling bias out of the cost (`processing.cost`)
    # a pixel's cost counts by its window's signal-to-noise ratio s as s / (s + this) (`features.signal_weight`;
    # needs the noise model): noise alone 0, this ratio one half; 0 = every pixel's cost counts fully. 0.1 of
    # 0.1-2 tried on the tuning renders: lower helps weakly textured content more; 0.5 splits dog.png's wall
    half_weight_snr: float = 0.1
    # whose signal-to-noise ratio that is (`features.signal_weight`): "second", the channel with the second most
    # signal (the cost needs two channels with structure to align; docs/evaluation.md, fourteenth stop), or
    # "total", all channels' together (until then). The half-size share (`coarse_half_snr`) always asks "total"
    signal_channels: str = "second"


@dataclass
class DenseDisparity:
    """Per-pixel disparity on the analysis grid."""

    disparity_px: np.ndarray  # (H, W) float32, sub-pixel
    confidence: np.ndarray  # (H, W) float32 in [0, 1]
    candidates_px: np.ndarray  # (D,) the candidates searched
    search_range_px: tuple[float, float]  # the range they cover


def candidate_disparities(range_px: tuple[float, float], step_px: float) -> np.ndarray:
    """Evenly spaced candidates covering `range_px`, containing 0 exactly."""
    low, high = range_px
    return (np.arange(np.floor(low / step_px), np.ceil(high / step_px) + 1) * step_px).astype(np.float64)


def _volume_dhw(
    planes: np.ndarray,
    aperture: FilterAperture,
    candidates: np.ndarray,
    params: DenseParams,
    given: CostInput | None = None,
    out: np.ndarray | None = None,
    shifted: dict | None = None,
) -> np.ndarray:
    """The (D, H, W) cost volume of `planes`; `given` is their `CostInput` when the caller has it already,
    `out` a buffer to fill."""
    inputs = given if given is not None else cost_input(planes, params.noise_model)
    if params.noise_model and inputs.noise is None:
        raise ValueError("DenseParams.noise_model is set but the CostInput handed in carries no noise model")
    noise = inputs.noise if params.noise_model else None
    return cost_volume(
        inputs.stacked, aperture, candidates, params.window_px, params.noise_floor, params.sampling, noise, out, shifted
    )


@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _blend_kernel(
    fine: np.ndarray,
    coarse: np.ndarray,
    share: float,
    shares: np.ndarray,
    weight: np.ndarray,
    out: np.ndarray,
    first: int,
    levels: float = 0.0,
) -> None:
    """out[y, x, first + d] = weight[y, x] ((1 - c) fine[d, y, x] + c (coarse[d] brought up bilinearly)[y, x]),
    c = shares[y, x] (`share` where `shares` is empty), weight 1 where `weight` is empty; with `levels` > 0
    that value (a cost, in [0, 1]) times `levels`, rounded (an integer `out`)."""
    d_count, h, w = fine.shape
    _, ch, cw = coarse.shape
    weighted = weight.shape[0] > 0
    per_pixel = shares.shape[0] > 0
    sy, sx = ch / h, cw / w
    for y in nb.prange(h):
        fy = max((y + 0.5) * sy - 0.5, 0.0)
        y0 = min(int(fy), ch - 1)
        y1 = min(y0 + 1, ch - 1)
        ty = fy - y0
        for x in range(w):
            fx = max((x + 0.5) * sx - 0.5, 0.0)
            x0 = min(int(fx), cw - 1)
            x1 = min(x0 + 1, cw - 1)
            tx = fx - x0
            a, b = (1.0 - ty) * (1.0 - tx), (1.0 - ty) * tx
            c, e = ty * (1.0 - tx), ty * tx
            o = out[y, x]
            k = weight[y, x] if weighted else 1.0
            w_coarse = k * (shares[y, x] if per_pixel else share)
            w_fine = k - w_coarse
            for d in range(d_count):
                up = a * coarse[d, y0, x0] + b * coarse[d, y0, x1] + c * coarse[d, y1, x0] + e * coarse[d, y1, x1]
                value = w_fine * fine[d, y, x] + w_coarse * up
                if levels > 0.0:
                    o[first + d] = min(max(value * levels + 0.5, 0.0), levels)
                else:
                    o[first + d] = value


# The volume the aggregation takes holds each cost (in [0, 1]) times COST_LEVELS, rounded, as uint16: half the
# memory of float32 (at 20 MP 120 MB less to allocate and touch, and half the bytes every path of the aggregation
# reads), for a rounding of at most 7.6e-6, 4e-5 of the smallest penalty. The aggregation's penalties and the
# winner's jump cost are scaled alike, so the winners are those of the costs themselves: on the tuning renders the
# dense map's bad-1 is the same to 0.01 points. (The final map's is not: the 2.1D sketch turns changes this
# small into regions joined or split; docs/evaluation.md, nineteenth stop.)
COST_LEVELS = 65535.0

_CHUNK = 16  # candidates computed at a time: a (16, H, W) buffer used again, written out 64 bytes per pixel


def _cost_hwd(
    planes: np.ndarray,
    aperture: FilterAperture,
    candidates: np.ndarray,
    params: DenseParams,
    inputs: CostInput | None = None,
) -> np.ndarray:
    """The (H, W, D) uint16 volume the aggregation takes (costs times `COST_LEVELS`): the cost of `planes` at
    `candidates`, averaged with the cost at half size brought up bilinearly (pixel centres aligned, as
    cv2.resize; weight `params.coarse_weight`), each pixel's curve scaled by its `features.signal_weight`
    (`params.half_weight_snr`; when `inputs` carry a noise model).

    The full-size cost is made `_CHUNK` candidates at a time into one buffer and blended into place: at 20 MP a
    whole (D, H, W) volume beside the (H, W, D) one would be another quarter of a gigabyte to allocate."""
    h, w = planes.shape[:2]
    count = len(candidates)
    if inputs is None:
        inputs = cost_input(planes, params.noise_model)  # once, for every chunk
    shares = np.zeros((0, 0), np.float32)
    if params.coarse_weight > 0 and min(h, w) >= 32:
        coarse = _volume_dhw(cv2.pyrDown(planes), aperture, candidates / 2.0, params)
        share = params.coarse_weight / (1.0 + params.coarse_weight)
        if params.coarse_half_snr > 0 and inputs.noise is not None:
            shares = np.float32(share) * (
                np.float32(1.0) - inputs.signal_weight(params.window_px, params.coarse_half_snr, "total")
            )
    else:
        coarse = np.zeros((count, 1, 1), np.float32)
        share = 0.0
    weight = np.zeros((0, 0), np.float32)
    if params.half_weight_snr > 0 and inputs.noise is not None:
        weight = inputs.signal_weight(params.window_px, params.half_weight_snr, params.signal_channels)
    out = np.empty((h, w, count), np.uint16)
    buffer = np.empty((min(_CHUNK, count), h, w), np.float32)
    shifted: dict | None = {} if params.sampling == "phase" else None  # the bands shifted once for every chunk
    for first in range(0, count, _CHUNK):
        last = min(first + _CHUNK, count)
        fine = _volume_dhw(planes, aperture, candidates[first:last], params, inputs, buffer[: last - first], shifted)
        _blend_kernel(fine, coarse[first:last], share, shares, weight, out, first, COST_LEVELS)
    return out


@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _winner_kernel(
    aggregated: np.ndarray, candidates: np.ndarray, scale: float, disparity: np.ndarray, confidence: np.ndarray
) -> None:
    h, w, count = aggregated.shape
    step = candidates[1] - candidates[0] if count > 1 else 1.0
    even = True
    for d in range(2, count):
        if abs(candidates[d] - candidates[d - 1] - step) > 1e-9 * step:
            even = False
    for y in nb.prange(h):
        for x in range(w):
            a = aggregated[y, x]
            best = 0
            for d in range(1, count):
                if a[d] < a[best]:
                    best = d
            at = a[best]
            offset = 0.0
            if 0 < best < count - 1:
                curvature = a[best - 1] - 2.0 * at + a[best + 1]
                if curvature > 1e-9:
                    offset = min(max(0.5 * (a[best - 1] - a[best + 1]) / curvature, -0.5), 0.5)
            if even:
                disparity[y, x] = candidates[best] + offset * step
            elif offset > 0.0:  # uneven candidates (`search_candidates`): the spacing on the offset's side
                disparity[y, x] = candidates[best] + offset * (candidates[best + 1] - candidates[best])
            else:
                disparity[y, x] = candidates[best] + offset * (candidates[best] - candidates[best - 1])
            # no infinity as "none yet": fastmath lets the compiler assume there is none (second == inf is false)
            far = False
            second = 0.0
            for d in range(count):
                if abs(d - best) > 2 and (not far or a[d] < second):
                    second = a[d]
                    far = True
            if far:
                confidence[y, x] = min(max((second - at) / scale, 0.0), 1.0)
            else:
                confidence[y, x] = 0.0


def _winner(aggregated: np.ndarray, candidates: np.ndarray, jump_cost: float) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel winner (parabola through the lowest aggregated cost and its neighbours) and confidence of an
    (H, W, D) volume: how far the best candidate more than two steps away lies above the winner, in units of
    `jump_cost` (the aggregated price of one jump on all paths), clipped to [0, 1]."""
    h, w, _ = aggregated.shape
    disparity = np.empty((h, w), np.float32)
    confidence = np.empty((h, w), np.float32)
    _winner_kernel(aggregated, np.asarray(candidates, np.float64), float(jump_cost), disparity, confidence)
    return disparity, confidence


def quick_disparity(
    planes: np.ndarray, aperture: FilterAperture, range_px: tuple[float, float], params: DenseParams
) -> np.ndarray | None:
    """A quick dense disparity of `planes` on a quarter-size image over all of `range_px`, in px of `planes`
    (at quarter size, (H/4, W/4)); None when the image or the range is too small for it."""
    small = cv2.pyrDown(cv2.pyrDown(planes))
    if min(small.shape[:2]) < 24:
        return None
    candidates = candidate_disparities((range_px[0] / 4.0, range_px[1] / 4.0), params.step_px)
    if len(candidates) < 4:
        return None
    volume = _cost_hwd(small, aperture, candidates, replace(params, coarse_weight=0.0))
    p1, p2 = params.p1 * COST_LEVELS, params.p2 * COST_LEVELS
    aggregated = aggregate(volume, display_gamma(small).mean(axis=2), p1, p2)
    disparity, _ = _winner(aggregated, candidates, _PATHS * p2)
    return disparity * np.float32(4.0)


def occupied_range(
    planes: np.ndarray,
    aperture: FilterAperture,
    range_px: tuple[float, float],
    params: DenseParams,
    quick: np.ndarray | None = None,
) -> tuple[float, float]:
    """The part of `range_px` the scene occupies, from `quick_disparity` (made here unless given) + margin."""
    disparity = quick if quick is not None else quick_disparity(planes, aperture, range_px, params)
    if disparity is None:
        return range_px
    return _around(disparity, (0.2, 99.8), range_px, params)


def _around(quick: np.ndarray, percentiles: tuple[float, float], range_px: tuple[float, float], params: DenseParams):
    """The span between two percentiles of the quick map, + margin, within `range_px`."""
    margin = params.range_margin_px + 4.0 * params.step_px
    low, high = percentile(quick, percentiles[0]) - margin, percentile(quick, percentiles[1]) + margin
    return (max(range_px[0], low), min(range_px[1], high))


_VOLUME_BYTES = 6  # per pixel and candidate: the uint16 cost and the float32 aggregation


def search_candidates(
    search_px: tuple[float, float], pixels: int, params: DenseParams, quick: np.ndarray | None = None
) -> np.ndarray:
    """The candidates of the dense search over `search_px` for an image of `pixels`: `candidate_disparities`
    while their volumes fit `params.volume_budget_mb`. Past it, and given the quick map, they are `step_px` apart
    over the quick map's bulk (between its `core_percentiles`, + margin, widened by what the budget has left)
    and 4, 8, 16 or 32 times farther apart out to the range's ends: the fewest times that fit.

    A quick map strays where it has no evidence: in Venus-s1's dark, textureless corner about 2 % of it fell
    anywhere from -170 to +159 px, where the scene spans -24..+28 px, and the even search took 660 candidates and
    5.5 GB. Its pixels in the coarse tails can still take a disparity there; a scene truly that wide is searched
    on a coarser step only where little of the quick map lies. A range too wide even for that is searched evenly,
    as many steps apart as fit."""
    step = params.step_px
    even = candidate_disparities(search_px, step)
    fit = max(int(params.volume_budget_mb * 2**20 / (_VOLUME_BYTES * max(pixels, 1))), 8)
    if len(even) <= fit:
        return even
    if quick is not None:
        low, high = search_px
        core_low, core_high = _around(quick, params.core_percentiles, search_px, params)
        for factor in (4, 8, 16, 32):
            tail = factor * step
            tails = math.ceil((core_low - low) / tail) + math.ceil((high - core_high) / tail)
            spare = fit - tails - ((core_high - core_low) / step + 2)
            if spare >= 0:
                widen = 0.5 * max(spare - 4, 0) / (1.0 / step - 1.0 / tail)  # 4: the tails' rounding, as they shrink
                core = candidate_disparities((max(low, core_low - widen), min(high, core_high + widen)), step)
                below = core[0] - tail * np.arange(math.ceil(max(core[0] - low, 0.0) / tail), 0, -1)
                above = core[-1] + tail * np.arange(1, math.ceil(max(high - core[-1], 0.0) / tail) + 1)
                return np.concatenate([below, core, above])
    wider = math.ceil(len(even) / fit)
    while len(candidate_disparities(search_px, step * wider)) > fit:
        wider += 1
    return candidate_disparities(search_px, step * wider)


def _step_sigma(guide: np.ndarray) -> float:
    """Robust sigma (1.4826 x median absolute value) of the guide's horizontal pixel-to-pixel steps, the largest
    over its channels: what noise and fine texture make, beside the steps of object edges."""
    steps = np.abs(np.diff(guide.reshape(guide.shape[0], guide.shape[1], -1), axis=1))
    return float(1.4826 * max(np.median(steps[..., c]) for c in range(steps.shape[2])))


def estimate_dense(
    planes: np.ndarray,
    aperture: FilterAperture,
    range_px: tuple[float, float],
    params: DenseParams = DenseParams(),
    inputs: CostInput | None = None,
    quick: np.ndarray | None = None,
) -> DenseDisparity:
    """Dense disparity of (H, W, 3) linear colour planes over `range_px` (px of these planes); `inputs` is the
    planes' `cost.cost_input` and `quick` their `quick_disparity` over `range_px` when the caller has made
    them already (they then are not made again)."""
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    search = range_px
    if params.narrow_range:
        if quick is None:
            quick = quick_disparity(planes, aperture, range_px, params)
        search = occupied_range(planes, aperture, range_px, params, quick)
    candidates = search_candidates(search, planes.shape[0] * planes.shape[1], params, quick)
    volume = _cost_hwd(planes, aperture, candidates, params, inputs)
    scale = COST_LEVELS * params.step_px / 0.5  # penalties are given in cost units for 0.5 px steps
    guide = display_gamma(planes)
    if not params.colour_guide:
        guide = guide.mean(axis=2)
    spacing = np.diff(candidates)
    gaps = None
    if spacing.size and np.ptp(spacing) > 1e-9 * params.step_px:  # uneven: a coarse tail's neighbours are a jump apart
        gaps = np.where(spacing > 1.5 * params.step_px, params.p2 * scale, params.p1 * scale)
    aggregated = aggregate(
        volume,
        guide,
        params.p1 * scale,
        params.p2 * scale,
        params.alpha,
        params.noise_steps * _step_sigma(guide) if params.noise_steps > 0 else 0.0,
        gaps,
    )
    del volume
    disparity, confidence = _winner(aggregated, candidates, _PATHS * params.p2 * scale)
    return DenseDisparity(disparity, confidence, candidates, (float(candidates[0]), float(candidates[-1])))
