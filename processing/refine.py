"""Sub-pixel refinement of the regions' disparity on the colour-alignment cost itself, with each region's support.

The surfaces carry the dense (semi-global) disparity, whose per-pixel precision is a fraction of a pixel. A
region (an object of the 2.1D sketch) has thousands of pixels; measured on the raw colour-line cost
(`processing.cost`) with all of them, its disparity is known to a few hundredths of a pixel. The model is
shifted by a set of offsets; for every cell (a square of `cell_px`) of every region the cost, weighted by
texture (times how much of it is signal rather than sensor noise, `features.signal_weight`: a window of noise
alone has texture too, and no say), is summed at each offset and the parabola through the lowest sum gives that
cell's own minimum. The
region's correction is then a robust fit to its cells' minima: one level for a fronto-parallel or curved
region, a plane for a slanted planar one. Cells, not pixels, vote: a few cells with bad data (a reflection, a
disocclusion) cannot move the region. A cell's vote is its texture times the curvature of its cost at the
minimum, so a cell on a strong edge can hold much of a region's weight: on paper-f four cells along one box's
edge held 57 % of it, their minima 0.3-0.6 px apart, and tilted the box 0.002 px per px. No cell votes with more
than `vote_cap` times the region's median cell vote, and the plane's outliers are judged by the weighted median
of the residuals, not their weighted spread, which a heavy outlier inflates (`_robust_plane`).

Occluding contours: the windows around an occluder's edge see the occluder's edge, at the occluder's
disparity. Every pixel within half a window of a nearer region is therefore warped with that nearer region's
model and does not count for its own region (it counts for the occluder only if it is the occluder's).
Whatever the order, a pixel within half a window of its region's boundary has a window that mixes the region
with its neighbour, and its cost minimum lies between their disparities: such pixels weigh a twentieth
(`surfaces.interior_weights`). On paper-e the green tomato's rim, whose windows saw the wall 11 px behind it,
had tilted and pulled its plane 0.15 px far (its depth 4 mm, 11 %); with its interior voting it is 0.01 px off.

Two passes: offsets `coarse_step_px` apart over +-`search_px`, then `fine_step_px` apart around each region's
first-pass correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.cost import CostInput, cost_at
from mca.processing.features import FeatureNoise
from mca.processing.labels import label_boxes
from mca.processing.surfaces import fit_planes, interior_weights


@dataclass(frozen=True)
class RefineParams:
    """Parameters of the region refinement (pixels of the grid refined on)."""

    search_px: float = 1.5  # first pass: offsets over +- this
    coarse_step_px: float = 0.5
    fine_step_px: float = 0.15  # second pass: 5 offsets this far apart around each region's first-pass result
    cell_px: int = 32  # side of the cells whose minima vote
    planar_tolerance_px: float = 0.25  # 90th percentile of |surfaces - region plane| of a planar region
    min_cells_for_slope: int = 6  # a curved region's correction gets a slope only with this many voting cells
    window_px: int = 9
    noise_floor: float = 2e-3
    # the cost's sampler (`processing.cost`): "phase", the band-limited one, keeps the noise's variance at every
    # offset, where bilinear sampling averages it down between pixels and a weakly textured region is pulled
    # towards the offsets where every channel falls between pixels (the noise model takes out only part of that).
    # Since the twenty-second stop (docs/evaluation.md); "bilinear" until then
    sampling: str = "phase"
    noise_model: bool = True  # the pipeline measures the noise for the cost (`refine_regions(noise=...)`)
    # a pixel's vote weighs its texture times s / (s + this), s its window's signal-to-noise ratio
    # (`features.signal_weight`; with the noise); 0: texture alone
    half_weight_snr: float = 0.1
    signal_channels: str = "second"  # whose signal-to-noise ratio (`DenseParams.signal_channels`)
    # no cell votes with more than this many times its region's median cell vote (0: no cap); see the module
    # docstring. 4 and 10 tried on the tuning renders (tenth stop): 4 a little better, both fix paper-c and -f
    vote_cap: float = 4.0


@dataclass
class Refinement:
    """The refined model and, per region, its plane when planar."""

    disparity_px: np.ndarray  # (H, W) float32
    planes: dict[int, tuple[float, float, float] | None]  # region id -> plane (a, b, c) if planar, else None
    corrections: dict[int, tuple[float, float, float]]  # region id -> plane added to its surfaces (curved regions)
    offsets_px: dict[int, float]  # region id -> correction at its centroid


def _median_by_label(labels: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """Median of `values` per label (flat arrays); inf for empty labels."""
    return _quantile_by_label(labels, values, count, 0.5)


@nb.njit(cache=True)
def _quantile_kernel(labels: np.ndarray, values: np.ndarray, q: float, out: np.ndarray) -> None:
    count = out.shape[0]
    starts = np.zeros(count + 1, np.int64)
    for i in range(labels.shape[0]):
        starts[labels[i] + 1] += 1
    for k in range(count):
        starts[k + 1] += starts[k]
    grouped = np.empty(values.shape[0], values.dtype)  # a counting sort by label
    filled = starts[:-1].copy()
    for i in range(labels.shape[0]):
        grouped[filled[labels[i]]] = values[i]
        filled[labels[i]] += 1
    for k in range(count):
        n = starts[k + 1] - starts[k]
        if n == 0:
            out[k] = np.inf
        else:
            rank = int(np.floor(q * (n - 1)))  # a selection, not a sort: the same element, NaN last as a sort puts it
            out[k] = np.partition(grouped[starts[k] : starts[k + 1]], rank)[rank]


def _quantile_by_label(labels: np.ndarray, values: np.ndarray, count: int, q: float) -> np.ndarray:
    """The q-quantile (lower) of `values` per label (flat arrays, labels 0..count - 1); inf for empty labels."""
    out = np.empty(count)
    _quantile_kernel(np.ascontiguousarray(labels, np.int64), np.ascontiguousarray(values), float(q), out)
    return out


def _owners(labels: np.ndarray, levels: np.ndarray, reach_px: int) -> np.ndarray:
    """For every pixel the region whose model warps it: the nearest region (smallest level) within `reach_px`."""
    count = levels.shape[0]
    rank_of = np.empty(count, np.int64)
    by_rank = np.argsort(levels, kind="stable")
    rank_of[by_rank] = np.arange(count)
    kernel = np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8)
    nearest_rank = cv2.erode(rank_of[labels].astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    return by_rank[nearest_rank.astype(np.int64)]


def _parabola_minima(curves: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of `curves` (n, K): the minimum of the parabola through the lowest sample and its neighbours
    (offset units) and its curvature (0 where the minimum is at an end)."""
    k = curves.shape[1]
    best = np.argmin(curves, axis=1)
    inner = np.clip(best, 1, k - 2)
    rows = np.arange(curves.shape[0])
    before, at, after = curves[rows, inner - 1], curves[rows, inner], curves[rows, inner + 1]
    curvature = before - 2.0 * at + after
    step = offsets[1] - offsets[0]
    shift = np.where(curvature > 1e-12, 0.5 * (before - after) / np.maximum(curvature, 1e-12), 0.0)
    minima = offsets[inner] + np.clip(shift, -1.0, 1.0) * step
    interior = (best > 0) & (best < k - 1)
    return minima, np.where(interior, curvature, 0.0)


def _robust_level(values: np.ndarray, weights: np.ndarray) -> float:
    """Weighted median of cell minima."""
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def _robust_plane(
    xs: np.ndarray, ys: np.ndarray, values: np.ndarray, weights: np.ndarray, iterations: int = 5
) -> np.ndarray:
    """(a, b, c): the plane a x + b y + c through the cells' minima, robust to cells whose weight is large.

    Cells vote by texture and by their cost's curvature, so a few cells can hold much of a region's weight; one of
    them at an occluding edge or on a reflection is a heavy outlier, and a weighted standard deviation grows
    with it and no longer drops it (paper-c's farthest box: one cell of 7 % of the weight 0.7 px off tilted the
    box 0.0028 px per px). Here the fit starts from the weighted median level, flat, and the spread is the
    weighted median absolute residual (times 1.4826, a standard deviation for Gaussian residuals), which such
    cells do not move: residuals beyond 1.5 of it are down-weighted (Huber), beyond 2 of it + 0.05 px dropped."""
    # plain numpy sums, no BLAS products: a threaded BLAS may split a product by its thread count, which a batch
    # worker has fewer of than a lone process, and the answer must not depend on it (tests/test_batch.py)
    total = float(np.sum(weights))
    cx = float(np.sum(weights * xs)) / total
    cy = float(np.sum(weights * ys)) / total
    x = xs - cx  # about the centroid: a well-conditioned system
    y = ys - cy
    a, b, c = 0.0, 0.0, _robust_level(values, weights)
    for _ in range(iterations):
        residual = np.abs(values - (a * x + b * y + c))
        sigma = max(1.4826 * _robust_level(residual, weights), 0.02)
        robust = np.where(residual <= 1.5 * sigma, 1.0, 1.5 * sigma / np.maximum(residual, 1e-12))
        robust[residual > 2.0 * sigma + 0.05] = 0.0
        w = weights * robust
        sw = float(np.sum(w))
        if sw <= 0:
            break
        wx, wy = w * x, w * y
        sx, sy, sxy = float(np.sum(wx)), float(np.sum(wy)), float(np.sum(wx * y))
        ridge = 1e-6 * sw  # a negligible ridge on the slopes, as before
        normal = np.array(
            [
                [float(np.sum(wx * x)) + ridge, sxy, sx],
                [sxy, float(np.sum(wy * y)) + ridge, sy],
                [sx, sy, sw],
            ]
        )
        rhs = np.array([float(np.sum(wx * values)), float(np.sum(wy * values)), float(np.sum(w * values))])
        try:
            a, b, c = (float(v) for v in np.linalg.solve(normal, rhs))
        except np.linalg.LinAlgError:
            break
    return np.array([a, b, c - a * cx - b * cy])


def refine_regions(
    bands: np.ndarray,
    aperture: FilterAperture,
    labels: np.ndarray,
    model: np.ndarray,
    params: RefineParams = RefineParams(),
    fronto_parallel: set[int] | frozenset[int] = frozenset(),
    noise: FeatureNoise | None = None,
    inputs: CostInput | None = None,
) -> Refinement:
    """Refine the disparity `model` (H, W) region by region (`labels` 1..L) on the feature planes `bands`
    ((B, 3, H, W), `processing.cost.stack_bands`); see the module docstring. Regions in `fronto_parallel` are
    held to one level; `noise` (`features.feature_noise` of the bands' planes) goes to the cost. `inputs`: the
    `cost.CostInput` whose stack `bands` is, when the caller has it: the texture and signal weights it has
    made already (the dense search's) are taken from it, not made again."""
    h, w = labels.shape
    count = int(labels.max()) + 1
    lab = labels.ravel()
    xs = np.arange(w, dtype=np.float32)[None, :]
    ys = np.arange(h, dtype=np.float32)[:, None]

    # region models: planar regions take their robust plane (one level if fronto-parallel), others the surfaces
    planes = fit_planes(labels, count, model, interior_weights(labels, 2), 1e-3)
    flat = np.zeros(count, bool)
    flat[[i for i in fronto_parallel if 0 < i < count]] = True
    levels = _median_by_label(lab, model.ravel(), count)
    planes[flat] = np.stack([np.zeros(flat.sum()), np.zeros(flat.sum()), levels[flat]], axis=1)
    plane_model = planes[labels, 0] * xs + planes[labels, 1] * ys + planes[labels, 2]
    deviation = _quantile_by_label(lab, np.abs(model - plane_model).ravel(), count, 0.9)
    planar = deviation <= params.planar_tolerance_px
    planar[0] = False
    current = np.where(planar[labels], plane_model, model).astype(np.float32)

    # who warps each pixel; which pixels vote for their own region, and with what weight
    reach = params.window_px // 2 + 1
    owner = _owners(labels, np.where(np.isfinite(levels), levels, np.inf), reach)
    clear = owner == labels
    if inputs is None:
        feature_planes = [np.moveaxis(bands[b], 0, -1) for b in range(bands.shape[0])]
        inputs = CostInput(feature_planes, bands, noise)
    elif inputs.stacked is not bands or (noise is not None and noise is not inputs.noise):
        raise ValueError("refine_regions: `inputs` must be the CostInput whose stack `bands` and noise these are")
    texture = inputs.texture_energy(params.window_px) * interior_weights(labels, reach)
    if noise is not None and params.half_weight_snr > 0:  # windows of noise alone do not vote
        texture *= inputs.signal_weight(params.window_px, params.half_weight_snr, params.signal_channels)
    weights = np.where(clear, texture, 0.0).astype(np.float32)
    cells_x = (w + params.cell_px - 1) // params.cell_px
    cell = (np.arange(h)[:, None] // params.cell_px) * cells_x + np.arange(w)[None, :] // params.cell_px
    n_cells = int(cell.max()) + 1
    bins = (lab * n_cells + cell.ravel()).astype(np.int64)
    n_bins = count * n_cells
    wflat = weights.ravel().astype(np.float64)
    wsum = np.bincount(bins, wflat, n_bins)
    used = np.nonzero(wsum > 0)[0]
    bin_region = used // n_cells
    bin_x = np.bincount(bins, wflat * np.tile(np.arange(w, dtype=np.float64), h), n_bins)[used] / wsum[used]
    bin_y = np.bincount(bins, wflat * np.repeat(np.arange(h, dtype=np.float64), w), n_bins)[used] / wsum[used]
    areas = np.maximum(np.bincount(lab, minlength=count), 1)
    cx_region = np.bincount(lab, np.tile(np.arange(w, dtype=np.float64), h), count) / areas
    cy_region = np.bincount(lab, np.repeat(np.arange(h, dtype=np.float64), w), count) / areas

    near_occluder = owner != labels

    def curves(base: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Per used (region, cell) bin and offset: the weighted cost sum of the model shifted by the offset."""
        maps = np.stack([base + np.float32(o) for o in offsets]).astype(np.float32)
        maps = _occluders_own_contours(maps, near_occluder, reach)
        costs = cost_at(
            bands,
            aperture,
            maps,
            params.window_px,
            params.noise_floor,
            sampling=params.sampling,
            noise=noise,
        )
        return np.stack([np.bincount(bins, (c.ravel() * wflat), n_bins)[used] for c in costs], axis=1)

    tilt = planar & ~flat  # slanted planar regions: the plane itself is refined
    free = ~planar  # curved regions: a planar correction of their surfaces

    corners = _bounding_corners(labels, count)

    def solve(minima: np.ndarray, strength: np.ndarray, searched_px: float) -> np.ndarray:
        """Per region: the correction (a, b, c) to add to the model, fitted to its cells' minima. A sloped
        correction that goes beyond twice the range searched (+-`searched_px`) at a corner of the region's
        bounding box is extrapolation from cells close together, not data: the region takes a level instead."""
        correction = np.zeros((count, 3))
        for rid in range(1, count):
            sel = (bin_region == rid) & (strength > 0)
            if not sel.any():
                continue
            vote = strength[sel] * wsum[used][sel]
            if params.vote_cap > 0:  # no cell weighs more than this many typical cells of its region
                vote = np.minimum(vote, params.vote_cap * np.median(vote))
            if (tilt[rid] and sel.sum() >= 4) or (free[rid] and sel.sum() >= params.min_cells_for_slope):
                # cell minima are precise to a few hundredths of a pixel, a few of them bad: a negligible
                # ridge, and cells beyond 2 robust sigmas + 0.05 px of the plane dropped
                plane = _robust_plane(bin_x[sel], bin_y[sel], minima[sel], vote)
                reach = np.abs(corners[rid] @ plane[:2] + plane[2]).max()
                if reach <= 2.0 * searched_px:
                    correction[rid] = plane
                    continue
            correction[rid, 2] = _robust_level(minima[sel], vote)
        return correction

    coarse = np.arange(-params.search_px, params.search_px + 1e-9, params.coarse_step_px)
    minima, strength = _parabola_minima(curves(current, coarse), coarse)
    first = solve(minima, strength, params.search_px)
    after_first = _apply(current, labels, first, xs, ys)
    fine = np.arange(-2, 3) * params.fine_step_px
    minima, strength = _parabola_minima(curves(after_first, fine), fine)
    second = solve(minima, strength, 2 * params.fine_step_px)
    final = _apply(after_first, labels, second, xs, ys)
    total = first + second

    result_planes: dict[int, tuple[float, float, float] | None] = {}
    offsets: dict[int, float] = {}
    for rid in range(1, count):
        if planar[rid]:
            plane = planes[rid] + total[rid]
            result_planes[rid] = (float(plane[0]), float(plane[1]), float(plane[2]))
        else:
            result_planes[rid] = None
        offsets[rid] = float(total[rid, 0] * cx_region[rid] + total[rid, 1] * cy_region[rid] + total[rid, 2])
    corrections = {rid: (float(total[rid, 0]), float(total[rid, 1]), float(total[rid, 2])) for rid in range(1, count)}
    return Refinement(final, result_planes, corrections, offsets)


def _bounding_corners(labels: np.ndarray, count: int) -> np.ndarray:
    """(count, 4, 2) float64: the (x, y) corners of each label 0..count-1's bounding box (zeros for an absent
    label), from `labels.label_boxes`."""
    corners = np.zeros((count, 4, 2))
    for k, box in enumerate(label_boxes(labels, first_label=0)[:count]):
        if box is not None:
            rows, cols = box
            left, right, top, bottom = cols.start, cols.stop - 1, rows.start, rows.stop - 1
            corners[k] = [(left, top), (right, top), (left, bottom), (right, bottom)]
    return corners


def _apply(
    current: np.ndarray, labels: np.ndarray, correction: np.ndarray, xs: np.ndarray, ys: np.ndarray
) -> np.ndarray:
    """The model plus each region's correction plane."""
    c = correction.astype(np.float32)
    return (current + c[labels, 0] * xs + c[labels, 1] * ys + c[labels, 2]).astype(np.float32)


def _occluders_own_contours(maps: np.ndarray, near_occluder: np.ndarray, reach_px: int) -> np.ndarray:
    """Each map with the pixels within `reach_px` of a nearer region warped at the smallest disparity within
    that reach, i.e. the occluder's: its edge is sampled where it is, not where this region's model would put it."""
    if not near_occluder.any():
        return maps
    kernel = np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8)
    out = maps.copy()
    for k in range(maps.shape[0]):
        nearest = cv2.erode(maps[k], kernel, borderType=cv2.BORDER_REPLICATE)
        out[k][near_occluder] = nearest[near_occluder]
    return out
