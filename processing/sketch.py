"""The 2.1D sketch (paper section IV-A, eq. 1): the image decomposed into L regions with disparities and occlusion order.

Steps, all on the analysis grid:
1. re-align the channels with the (smoothed) per-pixel disparity, so that colour fringes
   of out-of-focus objects vanish and every object shows its own colour;
2. oversegment into superpixels (SLIC) in a space of chromaticity, log luminance and
   disparity: texture modulates luminance, objects differ in chromaticity or depth;
3. merge adjacent superpixels greedily while both their colour and their disparity
   models agree (plane models, so a slanted object grows along its slope); same-colour
   objects at different depths stay apart, different-colour objects at one depth too;
4. absorb slivers (defocus rims, colour fringes) into their most similar neighbour;
5. per region a robust disparity model: constant or plane, chosen by model selection;
6. occlusion: for each pair of touching regions the one in front (smaller disparity at
   their shared boundary) occludes the other; boundary ownership (the raw disparity
   measured on the boundary follows the occluder's) is recorded as evidence. The order
   ranks regions by disparity, 0 = nearest.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import cv2
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.disparity import DisparityMap, parallel_map, warp_channels


@dataclass(frozen=True)
class SketchParams:
    """Parameters of the decomposition; lengths in analysis-grid pixels."""

    superpixel_px: int = 14  # typical superpixel side (on grids up to 0.3 MP; grows beyond)
    slic_compactness: float = 1.0
    disparity_weight: float = 0.6  # SLIC feature units per pixel of disparity
    chroma_threshold: float = 0.045  # chromaticity distance that separates two colours
    luminance_threshold: float = 1.5  # |log luminance| difference that separates two colours
    disparity_threshold_px: float = 0.7  # disparity step at a shared boundary that separates two objects
    min_region_fraction: float = 0.015  # smaller regions are absorbed by a neighbour
    sliver_thickness_px: float = 6.0  # thinner regions (2 area / perimeter) are rims, absorbed too ...
    sliver_max_fraction: float = 0.04  # ... up to this size
    join_disparity_px: float = 1.0  # pieces of one surface seen on both sides of an occluder: models
    # agreeing this well (each at the other's centroid) are joined
    slant_min_span_px: float = 1.2  # a plane is kept only if it spans at least this much disparity
    slant_min_gain: float = 0.5  # ... and explains this fraction of the constant model's residual
    focus_tolerance_px: float = 0.6  # |disparity| below which a region counts as in focus


@dataclass
class SketchRegion:
    """One region of the sketch on the analysis grid."""

    id: int
    pixels: int
    centroid_xy: tuple[float, float]
    plane: tuple[float, float, float]  # disparity = a x + b y + c (analysis px, analysis coordinates)
    slanted: bool
    confidence: float
    colour: tuple[float, float, float]  # mean linear RGB of the re-aligned image

    def disparity_at(self, x: float | np.ndarray, y: float | np.ndarray) -> float | np.ndarray:
        a, b, c = self.plane
        return a * x + b * y + c

    @property
    def disparity_px(self) -> float:
        return float(self.disparity_at(*self.centroid_xy))


@dataclass
class Sketch:
    """The 2.1D sketch: labels 1..L, regions, occlusion pairs and front-to-back order (0 = nearest)."""

    labels: np.ndarray  # (H, W) int32, 1..L
    regions: list[SketchRegion]
    occludes: dict[int, list[int]]  # id -> ids it occludes (touching and behind it)
    ownership: dict[tuple[int, int], float]  # (front, back) -> fraction of boundary evidence agreeing
    order: dict[int, int]  # id -> rank, 0 = nearest
    focus_region: int | None
    aligned: np.ndarray  # (H, W, 3) re-aligned planes the segmentation used
    superpixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int32))

    def region(self, region_id: int) -> SketchRegion:
        return next(r for r in self.regions if r.id == region_id)


# --- helpers ---------------------------------------------------------------------------------------------------


def smooth_disparity(disparity: DisparityMap, sigma_px: float) -> np.ndarray:
    """Confidence-weighted Gaussian smoothing (normalised convolution) of the per-pixel disparity."""
    weight = disparity.confidence.astype(np.float32) + 1e-4
    num = cv2.GaussianBlur(disparity.disparity_px * weight, (0, 0), sigma_px)
    den = cv2.GaussianBlur(weight, (0, 0), sigma_px)
    return (num / den).astype(np.float32)


def _colour_features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chromaticity (r, g) / (r + g + b) and log luminance of a linear RGB image."""
    total = image.sum(axis=2) + 1e-4
    chroma = image[..., :2] / total[..., None]
    log_lum = np.log(total / 3.0 + 1e-3)
    return chroma.astype(np.float32), log_lum.astype(np.float32)


def weighted_median_by_label(labels: np.ndarray, values: np.ndarray, weights: np.ndarray, count: int) -> np.ndarray:
    """Weighted median of `values` in each label 0..count-1 (NaN for empty labels)."""
    flat_l = labels.ravel()
    flat_v = values.ravel().astype(np.float64)
    flat_w = weights.ravel().astype(np.float64) + 1e-9
    if flat_v.size and np.isfinite(flat_v).all():
        # one sort of label * span + value (the label dominates): ties hold one value, so an unstable sort
        # gives the same medians as the lexsort, several times faster
        low = float(flat_v.min())
        span = float(flat_v.max()) - low + 1.0
        order = np.argsort(flat_l.astype(np.float64) * span + (flat_v - low))
    else:
        order = np.lexsort((flat_v, flat_l))
    sv, sw = flat_v[order], flat_w[order]
    cum = np.cumsum(sw)
    totals = np.bincount(flat_l, weights=flat_w, minlength=count)
    starts = np.concatenate([[0.0], np.cumsum(totals)[:-1]])
    index = np.searchsorted(cum, starts + 0.5 * totals)
    result = np.full(count, np.nan)
    present = np.bincount(flat_l, minlength=count) > 0
    result[present] = sv[np.minimum(index[present], len(sv) - 1)]
    return result


def adjacency(labels: np.ndarray) -> dict[tuple[int, int], int]:
    """Touching label pairs (a < b) with their boundary length in pixel edges (4-connectivity)."""
    pairs = []
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1, :], labels[1:, :])):
        diff = a != b
        lo = np.minimum(a[diff], b[diff]).astype(np.int64)
        hi = np.maximum(a[diff], b[diff]).astype(np.int64)
        pairs.append(lo * (int(labels.max()) + 1) + hi)
    keys, counts = np.unique(np.concatenate(pairs), return_counts=True)
    base = int(labels.max()) + 1
    return {(int(k // base), int(k % base)): int(c) for k, c in zip(keys, counts)}


def boundary_pixels(labels: np.ndarray, first: int, second: int, width_px: int = 1) -> np.ndarray:
    """Mask of pixels of either region within `width_px` of their shared boundary."""
    kernel = np.ones((2 * width_px + 1, 2 * width_px + 1), np.uint8)
    a = (labels == first).astype(np.uint8)
    b = (labels == second).astype(np.uint8)
    return ((cv2.dilate(a, kernel) & b) | (cv2.dilate(b, kernel) & a)).astype(bool)


class _Stats:
    """Mergeable sufficient statistics of a region (superpixel-level points for the disparity plane).

    Plain Python floats with the derived values (chromaticity, mean log luminance, ridge plane) computed
    once per node: the greedy merge evaluates the cost of every edge of a grown region again.
    """

    __slots__ = ("b", "cg", "count", "cr", "g", "log_lum", "mean_lum", "pixels", "plane_", "r", "sums")

    def __init__(
        self, pixels: float, rgb: tuple[float, float, float], log_lum: float, sums: tuple[float, ...], count: int
    ) -> None:
        self.pixels, self.log_lum, self.sums, self.count = pixels, log_lum, sums, count
        self.r, self.g, self.b = rgb
        total = self.r + self.g + self.b + 1e-9
        self.cr, self.cg = self.r / total, self.g / total
        self.mean_lum = log_lum / max(pixels, 1.0)
        self.plane_ = self.plane(40.0 / max(count, 1) ** 0.5)

    def merged(self, other: _Stats) -> _Stats:
        return _Stats(
            self.pixels + other.pixels,
            (self.r + other.r, self.g + other.g, self.b + other.b),
            self.log_lum + other.log_lum,
            tuple(u + v for u, v in zip(self.sums, other.sums)),
            self.count + other.count,
        )

    @property
    def sw(self) -> float:
        return self.sums[0]

    def plane(self, ridge_px: float) -> tuple[float, float, float]:
        """Weighted least squares plane, slopes shrunk toward 0 (ridge of a region of size `ridge_px`)."""
        sw, sx, sy, sd, sxx, syy, sxy, sxd, syd, _ = self.sums
        if sw <= 0:
            return (0.0, 0.0, 0.0)
        mx, my, md = sx / sw, sy / sw, sd / sw
        cxx = sxx / sw - mx * mx + ridge_px**2
        cyy = syy / sw - my * my + ridge_px**2
        cxy = sxy / sw - mx * my
        cxd = sxd / sw - mx * md
        cyd = syd / sw - my * md
        det = cxx * cyy - cxy * cxy
        if det <= 1e-12:
            return (0.0, 0.0, md)
        a = (cyy * cxd - cxy * cyd) / det
        b = (cxx * cyd - cxy * cxd) / det
        return (a, b, md - a * mx - b * my)


def _superpixel_stats(
    superpixels: np.ndarray,
    count: int,
    aligned: np.ndarray,
    log_lum: np.ndarray,
    disparity: np.ndarray,
    confidence: np.ndarray,
) -> list[_Stats]:
    flat = superpixels.ravel()
    pixels = np.bincount(flat, minlength=count).astype(np.float64)
    rgb = np.stack([np.bincount(flat, weights=aligned[..., c].ravel(), minlength=count) for c in range(3)], axis=1)
    lum = np.bincount(flat, weights=log_lum.ravel(), minlength=count)
    height, width = superpixels.shape
    safe = np.maximum(pixels, 1.0)
    xs = np.broadcast_to(np.arange(width, dtype=np.float64)[None, :], (height, width)).ravel()
    ys = np.broadcast_to(np.arange(height, dtype=np.float64)[:, None], (height, width)).ravel()
    cx = np.bincount(flat, weights=xs, minlength=count) / safe
    cy = np.bincount(flat, weights=ys, minlength=count) / safe
    step = 2 if superpixels.size > 300_000 else 1  # every 4th pixel is plenty for a median
    d = weighted_median_by_label(
        superpixels[::step, ::step], disparity[::step, ::step], confidence[::step, ::step], count
    )
    conf = np.bincount(flat, weights=confidence.ravel(), minlength=count)
    w = np.where(np.isfinite(d), conf, 0.0)
    d = np.where(np.isfinite(d), d, 0.0)
    sums = np.stack(
        [w, w * cx, w * cy, w * d, w * cx * cx, w * cy * cy, w * cx * cy, w * cx * d, w * cy * d, w * d * d], axis=1
    ).tolist()
    rgb_l, pixels_l, lum_l = rgb.tolist(), pixels.tolist(), lum.tolist()
    return [_Stats(pixels_l[i], tuple(rgb_l[i]), lum_l[i], tuple(sums[i]), 1) for i in range(count)]


# --- the sketch -------------------------------------------------------------------------------------------------


def build_sketch(
    planes: np.ndarray, aperture: FilterAperture, disparity: DisparityMap, params: SketchParams = SketchParams()
) -> Sketch:
    """Decompose the analysis-grid `planes` into the regions of a 2.1D sketch (see the module docstring)."""
    from skimage.segmentation import slic

    height, width = planes.shape[:2]
    smooth = smooth_disparity(disparity, 2.0)
    aligned = warp_channels(planes, aperture, smooth)
    chroma, log_lum = _colour_features(aligned)

    # 2. superpixels in (chromaticity, log luminance, disparity)
    lum_scale = 0.05
    features = np.dstack(
        [chroma / params.chroma_threshold, log_lum * (lum_scale / 0.05) * 0.5, smooth * params.disparity_weight]
    ).astype(np.float32)
    side = params.superpixel_px * max(1.0, (height * width / 300_000) ** 0.5)  # fewer, larger ones on big grids
    n_segments = max(16, int(height * width / side**2))
    # SLIC's own pre-smoothing (sigma 0.5, reflect) done by OpenCV: the same 5-tap kernel, several times faster
    features = cv2.GaussianBlur(features, (5, 5), 0.5, borderType=cv2.BORDER_REFLECT)
    superpixels = slic(
        features,
        n_segments=n_segments,
        compactness=params.slic_compactness,
        start_label=0,
        channel_axis=-1,
        enforce_connectivity=True,
        convert2lab=False,
        sigma=0,
        max_num_iter=6,
    )  # the merge that follows forgives a rougher start
    superpixels = superpixels.astype(np.int32)
    count = int(superpixels.max()) + 1

    stats = _superpixel_stats(superpixels, count, aligned, log_lum, disparity.disparity_px, disparity.confidence)
    edges = adjacency(superpixels)
    region_of = _merge(stats, edges, superpixels, params, height * width)
    labels = region_of[superpixels]
    labels = _relabel(labels)
    labels = _absorb_small(labels, aligned, disparity, params)
    regions = _fit_regions(labels, aligned, disparity, params)
    occludes, ownership = _occlusion(labels, regions, disparity)
    joined = _join_across_occluders(labels, regions, occludes, params)
    if joined is not None:
        labels = joined
        regions = _fit_regions(labels, aligned, disparity, params)
        occludes, ownership = _occlusion(labels, regions, disparity)
    ranked = sorted(regions, key=lambda r: r.disparity_px)
    order = {r.id: rank for rank, r in enumerate(ranked)}
    focus = min(regions, key=lambda r: abs(r.disparity_px)) if regions else None
    focus_id = focus.id if focus is not None and abs(focus.disparity_px) <= params.focus_tolerance_px else None
    return Sketch(labels, regions, occludes, ownership, order, focus_id, aligned, superpixels)


def _join_across_occluders(
    labels: np.ndarray, regions: list[SketchRegion], occludes: dict[int, list[int]], params: SketchParams
) -> np.ndarray | None:
    """One surface cut in two by an object in front of it (a spatula behind a carrot, a slanted knife behind a
    carrot) is one region of the 2.1D sketch: join regions that do not touch, are both occluded by the same
    region, have the same colour and whose disparity models agree. Returns new labels, or None if none joined."""
    by_id = {r.id: r for r in regions}
    touching = set(adjacency(labels))
    parent = {r.id: r.id for r in regions}

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    def chroma(r: SketchRegion) -> np.ndarray:
        rgb = np.asarray(r.colour, np.float64)
        return rgb[:2] / max(float(rgb.sum()), 1e-9)

    def lum(r: SketchRegion) -> float:
        return float(np.log(sum(r.colour) / 3.0 + 1e-3))

    joined = False
    for _front, backs in occludes.items():
        for i, a in enumerate(backs):
            for b in backs[i + 1 :]:
                if (min(a, b), max(a, b)) in touching or root(a) == root(b):
                    continue
                ra, rb = by_id[a], by_id[b]
                if (
                    np.linalg.norm(chroma(ra) - chroma(rb)) > params.chroma_threshold
                    or abs(lum(ra) - lum(rb)) > params.luminance_threshold
                ):
                    continue
                # one model explaining the other piece is enough (a slanted piece predicts a constant one)
                gap = min(
                    abs(ra.disparity_at(*rb.centroid_xy) - rb.disparity_px),
                    abs(rb.disparity_at(*ra.centroid_xy) - ra.disparity_px),
                )
                if gap < params.join_disparity_px:
                    parent[root(b)] = root(a)
                    joined = True
    if not joined:
        return None
    lookup = np.zeros(int(labels.max()) + 1, np.int32)
    roots = sorted({root(i) for i in parent})
    number = {r: k + 1 for k, r in enumerate(roots)}
    for i in parent:
        lookup[i] = number[root(i)]
    return lookup[labels]


def _merge_cost(a: _Stats, b: _Stats, boundary_xy: tuple[float, float], params: SketchParams) -> float:
    """Largest of the colour and disparity distances, each in units of its threshold (merge when < 1)."""
    chroma = ((a.cr - b.cr) ** 2 + (a.cg - b.cg) ** 2) ** 0.5 / params.chroma_threshold
    lum = abs(a.mean_lum - b.mean_lum) / params.luminance_threshold
    x, y = boundary_xy
    if a.sums[0] > 0 and b.sums[0] > 0:
        pa, pb = a.plane_, b.plane_
        da = pa[0] * x + pa[1] * y + pa[2]
        db = pb[0] * x + pb[1] * y + pb[2]
        disparity = abs(da - db) / params.disparity_threshold_px
    else:
        disparity = 0.0
    return max(chroma, lum, disparity)


def _merge(
    stats: list[_Stats],
    edges: dict[tuple[int, int], int],
    superpixels: np.ndarray,
    params: SketchParams,
    total_pixels: int,
) -> np.ndarray:
    """Greedy agglomeration of superpixels; returns the region index of each superpixel."""
    count = len(stats)
    _height, _width = superpixels.shape
    # boundary midpoints of superpixel pairs (sums of x, y and the number of pixel edges per pair)
    keys, mx, my = [], [], []
    for a_img, b_img, dx, dy in (
        (superpixels[:, :-1], superpixels[:, 1:], 0.5, 0.0),
        (superpixels[:-1, :], superpixels[1:, :], 0.0, 0.5),
    ):
        diff = a_img != b_img
        ys_, xs_ = np.nonzero(diff)
        lo = np.minimum(a_img[diff], b_img[diff]).astype(np.int64)
        hi = np.maximum(a_img[diff], b_img[diff]).astype(np.int64)
        keys.append(lo * count + hi)
        mx.append(xs_ + dx)
        my.append(ys_ + dy)
    uniq, inverse = np.unique(np.concatenate(keys), return_inverse=True)
    sx_all = np.bincount(inverse, weights=np.concatenate(mx))
    sy_all = np.bincount(inverse, weights=np.concatenate(my))
    n_all = np.bincount(inverse).astype(np.float64)
    pair_a, pair_b = (uniq // count).tolist(), (uniq % count).tolist()
    parent = list(range(count))
    alive = {i: stats[i] for i in range(count)}
    neighbours: dict[int, dict[int, list[float]]] = {i: {} for i in range(count)}
    for a, b, sx_, sy_, n_ in zip(pair_a, pair_b, sx_all.tolist(), sy_all.tolist(), n_all.tolist()):
        neighbours[a][b] = [sx_, sy_, n_]
        neighbours[b][a] = [sx_, sy_, n_]
    version = [0] * count
    heap: list[tuple[float, int, int, int, int]] = []
    # per-node values of `_merge_cost` as arrays, so that all edges of a node are priced at once
    feats = np.array(
        [(st.cr, st.cg, st.mean_lum) + tuple(st.plane_) + (1.0 if st.sums[0] > 0 else 0.0,) for st in stats], np.float64
    ).reshape(count, 7)

    def costs(a: int, others: np.ndarray, entries: np.ndarray) -> np.ndarray:
        """`_merge_cost` of node a against each of `others` (boundary sums `entries`), vectorised."""
        fa, fo = feats[a], feats[others]
        chroma = np.sqrt((fa[0] - fo[:, 0]) ** 2 + (fa[1] - fo[:, 1]) ** 2) / params.chroma_threshold
        lum = np.abs(fa[2] - fo[:, 2]) / params.luminance_threshold
        x, y = entries[:, 0] / entries[:, 2], entries[:, 1] / entries[:, 2]
        da = fa[3] * x + fa[4] * y + fa[5]
        db = fo[:, 3] * x + fo[:, 4] * y + fo[:, 5]
        disparity = np.where((fa[6] > 0) & (fo[:, 6] > 0), np.abs(da - db) / params.disparity_threshold_px, 0.0)
        return np.maximum(np.maximum(chroma, lum), disparity)

    def push_all(a: int, others: list[int]) -> None:
        if not others:
            return
        nb = neighbours[a]
        idx = np.array(others, np.int64)
        cost = costs(a, idx, np.array([nb[c] for c in others], np.float64))
        va = version[a]
        for k in np.flatnonzero(cost < 1.0).tolist():
            c = others[k]
            heapq.heappush(heap, (float(cost[k]), a, c, va, version[c]))

    if len(uniq):
        first = np.array(pair_a, np.int64)
        fa, fo = feats[first], feats[np.array(pair_b, np.int64)]
        chroma = np.sqrt((fa[:, 0] - fo[:, 0]) ** 2 + (fa[:, 1] - fo[:, 1]) ** 2) / params.chroma_threshold
        lum = np.abs(fa[:, 2] - fo[:, 2]) / params.luminance_threshold
        x, y = sx_all / n_all, sy_all / n_all
        da = fa[:, 3] * x + fa[:, 4] * y + fa[:, 5]
        db = fo[:, 3] * x + fo[:, 4] * y + fo[:, 5]
        disparity = np.where((fa[:, 6] > 0) & (fo[:, 6] > 0), np.abs(da - db) / params.disparity_threshold_px, 0.0)
        cost = np.maximum(np.maximum(chroma, lum), disparity)
        heap = [(float(cost[k]), pair_a[k], pair_b[k], 0, 0) for k in np.flatnonzero(cost < 1.0).tolist()]
        heapq.heapify(heap)
    while heap:
        cost, a, b, va, vb = heapq.heappop(heap)
        if a not in alive or b not in alive or version[a] != va or version[b] != vb:
            continue
        # merge b into a
        merged = alive[a].merged(alive[b])
        alive[a] = merged
        feats[a] = (
            (merged.cr, merged.cg, merged.mean_lum) + tuple(merged.plane_) + (1.0 if merged.sums[0] > 0 else 0.0,)
        )
        del alive[b]
        parent[b] = a
        for c, (sx_, sy_, n_) in neighbours.pop(b).items():
            neighbours[c].pop(b, None)
            if c == a:
                continue
            entry = neighbours[a].setdefault(c, [0.0, 0.0, 0.0])
            entry[0] += sx_
            entry[1] += sy_
            entry[2] += n_
            neighbours[c][a] = entry
        version[a] += 1
        push_all(a, list(neighbours[a]))
    region = np.empty(count, dtype=np.int32)
    for i in range(count):
        root = i
        while parent[root] != root:
            root = parent[root]
        region[i] = root
    return region


def _relabel(labels: np.ndarray) -> np.ndarray:
    """Consecutive ids 1..L, numbered in raster order of first appearance; each id one connected component."""
    from scipy import ndimage

    out = np.zeros(labels.shape, np.int32)
    next_id = 1
    low = int(labels.min())
    shifted = (labels - (low - 1)).astype(np.int32)  # 1.. for find_objects
    for index, box in enumerate(ndimage.find_objects(shifted)):
        if box is None:
            continue
        mask = shifted[box] == index + 1  # components inside the value's bounding box:
        n, components = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)  # same raster order
        region = out[box]
        region[mask] = components[mask] + (next_id - 1)
        next_id += n - 1
    return out


def _absorb_small(labels: np.ndarray, aligned: np.ndarray, disparity: DisparityMap, params: SketchParams) -> np.ndarray:
    """Merge small regions and thin rims (defocus rims, colour fringes at occlusion boundaries) into the
    touching region most alike in colour and disparity, smallest first."""
    total = labels.size
    count = int(labels.max()) + 1
    flat = labels.ravel()
    chroma, log_lum = _colour_features(aligned)
    sizes = np.bincount(flat, minlength=count).astype(np.float64)
    csum = np.stack([np.bincount(flat, weights=chroma[..., k].ravel(), minlength=count) for k in range(2)], axis=1)
    lsum = np.bincount(flat, weights=log_lum.ravel(), minlength=count)
    dmed = weighted_median_by_label(labels, disparity.disparity_px, disparity.confidence, count)
    edges = adjacency(labels)
    perimeter = np.zeros(count)
    neighbours: dict[int, dict[int, float]] = {i: {} for i in range(count)}
    for (a, b), length in edges.items():
        neighbours[a][b] = neighbours[b].get(a, 0) + length
        neighbours[b][a] = neighbours[a][b]
        perimeter[a] += length
        perimeter[b] += length
    border = np.zeros(count)
    for line in (labels[0], labels[-1], labels[:, 0], labels[:, -1]):
        border += np.bincount(line, minlength=count)
    perimeter += border
    parent = np.arange(count)

    def fragment(i: int) -> bool:
        """A piece of a neighbour: same disparity and nearly the same colour (mixed pixels at its rim)."""
        for j in neighbours[i]:
            if sizes[j] <= sizes[i] or not (np.isfinite(dmed[i]) and np.isfinite(dmed[j])):
                continue
            if (
                abs(dmed[i] - dmed[j]) < 0.5 * params.disparity_threshold_px
                and np.linalg.norm(csum[i] / sizes[i] - csum[j] / sizes[j]) < 2.0 * params.chroma_threshold
            ):
                return True
        return False

    def distinct(i: int) -> bool:
        """A piece of an object cut off by an occluder: clearly at another depth than everything it touches
        (it is joined with the rest of its object later, see `_join_across_occluders`)."""
        if not np.isfinite(dmed[i]) or sizes[i] < 0.4 * params.min_region_fraction * total:
            return False
        return all(
            np.isfinite(dmed[j]) and abs(dmed[i] - dmed[j]) > 2.0 * params.disparity_threshold_px for j in neighbours[i]
        )

    def is_small(i: int) -> bool:
        thickness = 2.0 * sizes[i] / max(perimeter[i], 1.0)
        if thickness >= 3.0 * params.sliver_thickness_px and distinct(i):
            return False
        return sizes[i] > 0 and (
            sizes[i] < params.min_region_fraction * total
            or (
                sizes[i] < params.sliver_max_fraction * total
                and (thickness < params.sliver_thickness_px or fragment(i))
            )
        )

    while True:
        small = [i for i in range(1, count) if parent[i] == i and is_small(i) and neighbours[i]]
        if not small:
            break
        i = min(small, key=lambda k: sizes[k])
        best, best_cost = None, np.inf
        for j, length in neighbours[i].items():
            ci, cj = csum[i] / sizes[i], csum[j] / sizes[j]
            dd = abs(dmed[i] - dmed[j]) if np.isfinite(dmed[i]) and np.isfinite(dmed[j]) else 0.0
            cost = (
                np.linalg.norm(ci - cj) / params.chroma_threshold
                + abs(lsum[i] / sizes[i] - lsum[j] / sizes[j]) / params.luminance_threshold
                + dd / params.disparity_threshold_px
                - 0.5 * np.log(length / max(perimeter[i], 1.0))
            )
            if cost < best_cost:
                best, best_cost = j, cost
        assert best is not None
        j = best
        parent[i] = j
        if np.isfinite(dmed[i]) and np.isfinite(dmed[j]):
            dmed[j] = (dmed[j] * sizes[j] + dmed[i] * sizes[i] * 0.0) / sizes[j]  # keep the larger one's value
        sizes[j] += sizes[i]
        csum[j] += csum[i]
        lsum[j] += lsum[i]
        shared = neighbours[i].get(j, 0.0)
        perimeter[j] += perimeter[i] - 2 * shared
        for k, length in neighbours.pop(i).items():
            neighbours[k].pop(i, None)
            if k == j:
                continue
            neighbours[j][k] = neighbours[j].get(k, 0.0) + length
            neighbours[k][j] = neighbours[j][k]
        sizes[i] = 0
    root = parent.copy()
    for i in range(count):
        r = i
        while parent[r] != r:
            r = parent[r]
        root[i] = r
    merged = root[labels]
    uniq = np.unique(merged)
    lookup = np.zeros(count, np.int32)
    lookup[uniq] = np.arange(1, len(uniq) + 1) if uniq[0] != 0 else np.arange(len(uniq))
    return lookup[merged]


def robust_plane(
    xs: np.ndarray, ys: np.ndarray, values: np.ndarray, weights: np.ndarray, iterations: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS (Tukey-like) fit of values = a x + b y + c; returns (a, b, c) and the final weights."""
    w = weights.astype(np.float64).copy()
    design = np.stack([xs, ys, np.ones_like(xs)], axis=1).astype(np.float64)
    coef = np.zeros(3)
    for _ in range(iterations):
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(design * sw[:, None], values * sw, rcond=None)
        residual = values - design @ coef
        scale = 1.4826 * np.median(np.abs(residual[w > 0])) + 1e-3 if np.any(w > 0) else 1.0
        w = weights * np.clip(1.0 - (residual / (4.0 * scale)) ** 2, 0.0, 1.0) ** 2
    return coef, w


def robust_constant(values: np.ndarray, weights: np.ndarray, iterations: int = 6) -> tuple[float, np.ndarray]:
    """IRLS location estimate with biweight weights; returns the value and the final weights."""
    w = weights.astype(np.float64).copy()
    value = float(np.average(values, weights=w + 1e-12))
    order = np.argsort(values)
    cum = np.cumsum(w[order])
    value = float(values[order][np.searchsorted(cum, cum[-1] / 2)]) if cum[-1] > 0 else value
    for _ in range(iterations):
        residual = values - value
        scale = 1.4826 * np.median(np.abs(residual[w > 0])) + 1e-3 if np.any(w > 0) else 1.0
        w = weights * np.clip(1.0 - (residual / (4.0 * scale)) ** 2, 0.0, 1.0) ** 2
        if w.sum() <= 0:
            break
        value = float(np.average(values, weights=w))
    return value, w


def interior_weights(labels: np.ndarray, confidence: np.ndarray, margin_px: int) -> np.ndarray:
    """Confidence with pixels closer than `margin_px` to a region boundary down-weighted (mixed windows)."""
    edges = np.zeros(labels.shape, np.uint8)
    edges[:, 1:] |= (labels[:, 1:] != labels[:, :-1]).astype(np.uint8)
    edges[1:, :] |= (labels[1:, :] != labels[:-1, :]).astype(np.uint8)
    distance = cv2.distanceTransform((1 - edges).astype(np.uint8), cv2.DIST_L2, 3)
    return confidence * np.clip(distance / max(margin_px, 1), 0.0, 1.0)


def _fit_regions(
    labels: np.ndarray, aligned: np.ndarray, disparity: DisparityMap, params: SketchParams, max_samples: int = 20_000
) -> list[SketchRegion]:
    """Per region: centroid and colour over all its pixels (bincount), the disparity model from at most
    `max_samples` of its pixels (an even subsample: the robust fits need no more)."""
    weights = interior_weights(labels, disparity.confidence, 5)
    height, width = labels.shape
    flat = labels.ravel()
    count = int(flat.max()) + 1
    sizes = np.bincount(flat, minlength=count)
    xs_all = np.broadcast_to(np.arange(width, dtype=np.float64)[None, :], (height, width)).ravel()
    ys_all = np.broadcast_to(np.arange(height, dtype=np.float64)[:, None], (height, width)).ravel()
    safe = np.maximum(sizes, 1)
    cxs = np.bincount(flat, weights=xs_all, minlength=count) / safe
    cys = np.bincount(flat, weights=ys_all, minlength=count) / safe
    colours = (
        np.stack([np.bincount(flat, weights=aligned[..., c].ravel(), minlength=count) for c in range(3)], axis=1)
        / safe[:, None]
    )
    d_all = disparity.disparity_px.ravel()
    w_all = weights.ravel()
    c_all = disparity.confidence.ravel()

    def fit(region_id: int) -> SketchRegion:
        n = int(sizes[region_id])
        members = np.flatnonzero(flat == region_id)  # raster order
        if n > max_samples:
            members = members[:: int(np.ceil(n / max_samples))]
        x, y = xs_all[members], ys_all[members]
        d = d_all[members].astype(np.float64)
        w = w_all[members].astype(np.float64)
        if w.sum() < 1e-6:
            w = c_all[members].astype(np.float64) + 1e-6
        cx, cy = float(cxs[region_id]), float(cys[region_id])
        plane, slanted, confidence = select_model(x - cx, y - cy, d, w, params)
        a, b, c = plane
        colour = tuple(float(v) for v in colours[region_id])
        return SketchRegion(region_id, n, (cx, cy), (a, b, c - a * cx - b * cy), slanted, confidence, colour)  # type: ignore[arg-type]

    # regions are independent: fitted on the worker threads (the sorts and solves release the GIL)
    return parallel_map(fit, [i for i in range(1, count) if sizes[i] > 0])


def select_model(
    x: np.ndarray, y: np.ndarray, d: np.ndarray, w: np.ndarray, params: SketchParams
) -> tuple[tuple[float, float, float], bool, float]:
    """Constant or plane disparity for one region (coordinates centred): keep the plane only if it spans
    a real disparity range over the region and removes most of the constant model's residual."""
    value, wc = robust_constant(d, w)
    coef, wp = robust_plane(x, y, d, w)
    resid_c = float(np.sum(wc * (d - value) ** 2) / max(wc.sum(), 1e-9))
    resid_p = float(np.sum(wp * (d - (coef[0] * x + coef[1] * y + coef[2])) ** 2) / max(wp.sum(), 1e-9))
    inliers = wp > 0.05 * (w.max() if w.size else 1.0)
    if inliers.sum() > 10:
        predicted = coef[0] * x[inliers] + coef[1] * y[inliers]
        span = float(np.percentile(predicted, 95) - np.percentile(predicted, 5))
    else:
        span = 0.0
    gain = 1.0 - resid_p / max(resid_c, 1e-12)
    confidence = float(np.clip(w.mean() * 4.0, 0.0, 1.0))
    if span >= params.slant_min_span_px and gain >= params.slant_min_gain:
        return (float(coef[0]), float(coef[1]), float(coef[2])), True, confidence
    return (0.0, 0.0, float(value)), False, confidence


def _occlusion(
    labels: np.ndarray, regions: list[SketchRegion], disparity: DisparityMap
) -> tuple[dict[int, list[int]], dict[tuple[int, int], float]]:
    """Touching pairs: the nearer region (smaller disparity at the shared boundary) occludes the other.

    Ownership evidence: on the boundary the measured disparity follows the occluding region, so
    the fraction of confident boundary pixels closer to the front region's model is recorded.
    """
    from scipy import ndimage

    by_id = {r.id: r for r in regions}
    occludes: dict[int, list[int]] = {r.id: [] for r in regions}
    ownership: dict[tuple[int, int], float] = {}
    boxes = ndimage.find_objects(labels)
    height, width = labels.shape
    for (a, b), _length in adjacency(labels).items():
        if a == 0 or b == 0 or a not in by_id or b not in by_id:
            continue
        # the boundary band lies inside the union of the two regions' bounding boxes (plus the band's width)
        ba, bb = boxes[a - 1], boxes[b - 1]
        y0 = max(0, min(ba[0].start, bb[0].start) - 3)
        y1 = min(height, max(ba[0].stop, bb[0].stop) + 3)
        x0 = max(0, min(ba[1].start, bb[1].start) - 3)
        x1 = min(width, max(ba[1].stop, bb[1].stop) + 3)
        band = boundary_pixels(labels[y0:y1, x0:x1], a, b, 2)
        ys, xs = np.nonzero(band)
        ys, xs = ys + y0, xs + x0
        da = by_id[a].disparity_at(xs, ys)
        db = by_id[b].disparity_at(xs, ys)
        front, back = (a, b) if float(np.mean(da - db)) < 0 else (b, a)
        measured = disparity.disparity_px[ys, xs]
        conf = disparity.confidence[ys, xs]
        d_front = by_id[front].disparity_at(xs, ys)
        d_back = by_id[back].disparity_at(xs, ys)
        agree = np.abs(measured - d_front) < np.abs(measured - d_back)
        ownership[(front, back)] = float(np.sum(conf * agree) / max(np.sum(conf), 1e-9))
        occludes[front].append(back)
    for key in occludes:
        occludes[key].sort()
    return occludes, ownership


# --- sub-pixel refinement of the region models at processing resolution ------------------------------------------


def rescale_plane(plane: tuple[float, float, float], factor: float) -> tuple[float, float, float]:
    """A disparity plane moved to a grid `factor` times finer: x_new = (x_old + 0.5) factor - 0.5, d scaled too."""
    a, b, c = plane
    return (a, b, factor * c + (a + b) * (0.5 - 0.5 * factor))


def occlusion_aware_weights(
    labels: np.ndarray, confidence: np.ndarray, occludes: dict[int, list[int]], margin_px: int
) -> np.ndarray:
    """Confidence, zeroed in each region within `margin_px` of a region that occludes it: there the
    windows mix the occluder's edge (at the occluder's disparity) and per-channel disocclusions."""
    weights = confidence.astype(np.float32).copy()
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    for front, backs in occludes.items():
        if not backs:
            continue
        grown = cv2.dilate((labels == front).astype(np.uint8), kernel).astype(bool)
        for back in backs:
            weights[grown & (labels == back)] = 0.0
    return weights


@dataclass(frozen=True)
class RefineParams:
    """Sub-pixel refinement of region models on the processing grid (or one Gaussian-pyramid level of it)."""

    window_px: int = 9
    noise_floor: float = 2e-3
    search_radius_px: float = 1.5  # +- around the sketch's estimate, processing px
    coarse_step_px: float = 0.5  # first pass: offsets this far apart (processing px) ...
    fine_step_px: float = 0.1  # ... second pass around each region's first-pass centre
    fine_count: int = 2  # second pass (pyramid level): offsets -fine_count..+fine_count ...
    level_fine_step_px: float = 0.2  # ... this far apart (processing px): 5 evaluations cover +-0.4 px
    max_pixels: int = 1_400_000  # the refinement runs on the first pyramid level at most this large
    band_sigma_px: tuple[float, float] = (2.0, 10.0)  # band-pass at the level: band-limits, so that the
    # linear interpolation does not pull toward whole pixels
    cell_px: int = 48  # side of the cells whose minima are fitted robustly (processing px)
    coarse_on_next_level: bool = False  # pass 1 on the next (4x smaller) pyramid level: ~2x faster refinement,
    # but it moved paper-e's spatula by 0.2 input px and lowered the dips;
    # off until `mca evaluate` shows no regression


def _parabola_min(xs: np.ndarray, ys: np.ndarray) -> float:
    from mca.processing.disparity import subpixel_minimum

    i = int(np.argmin(ys))
    if 0 < i < len(xs) - 1:
        step = xs[i + 1] - xs[i]
        return float(xs[i] + step * subpixel_minimum(np.array(ys[i - 1]), np.array(ys[i]), np.array(ys[i + 1])))
    return float(xs[i])


@dataclass
class RefineLevel:
    """The pyramid level the refinement runs on (0 = the processing grid itself) and its band-pass planes."""

    level: int
    band: np.ndarray | None  # (h, w, 3) float32 band-pass of the level; None for level 0
    coarse_band: np.ndarray | None = None  # band-pass of the next level (pass 1), when asked for


def prepare_refine_level(planes: np.ndarray, params: RefineParams = RefineParams()) -> RefineLevel:
    """The first Gaussian-pyramid level of at most `params.max_pixels` and its band-pass (no sketch needed)."""
    from mca.processing.disparity import band_pass

    level = 0
    while planes.shape[0] * planes.shape[1] / 4**level > params.max_pixels:
        level += 1
    if level == 0:
        return RefineLevel(0, None)
    reduced = planes
    for _ in range(level):
        reduced = cv2.pyrDown(reduced)  # anti-aliased: aliasing would not move with the disparity
    coarse = band_pass(cv2.pyrDown(reduced), *params.band_sigma_px) if params.coarse_on_next_level else None
    return RefineLevel(level, band_pass(reduced, *params.band_sigma_px), coarse)


class _LevelState:
    """One pyramid level's share of `refine_regions`: labels, weights, per-pixel model owner and the (region, cell)
    bins of the level, and the cost of model-map offsets reduced over those bins."""

    def __init__(
        self,
        band: np.ndarray,
        level: int,
        labels: np.ndarray,
        weights: np.ndarray,
        ids: list[int],
        planes_px: dict[int, tuple[float, float, float]],
        aperture: FilterAperture,
        params: RefineParams,
    ) -> None:
        from mca.processing.disparity import AlignmentCost

        height, width = band.shape[:2]
        factor = 2.0**level
        if level:
            llabels = cv2.resize(labels.astype(np.int32), (width, height), interpolation=cv2.INTER_NEAREST)
            lweights = cv2.resize(weights.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        else:
            llabels, lweights = labels.astype(np.int32), weights.astype(np.float32)
        count = len(ids)
        lut = np.full(max(int(llabels.max()), max(ids)) + 1, count, np.int64)
        lut[ids] = np.arange(count)
        index = lut[llabels]  # region index per pixel, `count` = not refined
        lplanes = np.array([rescale_plane(planes_px[i], 1.0 / factor) for i in ids] + [(0.0, 0.0, 0.0)])
        xs = np.arange(width, dtype=np.float32)[None, :]
        ys = np.arange(height, dtype=np.float32)[:, None]

        def model_map(coef: np.ndarray, where: np.ndarray | None = None) -> np.ndarray:
            c32 = coef.astype(np.float32)
            at = index if where is None else where
            return c32[at, 0] * xs + c32[at, 1] * ys + c32[at, 2]

        radius = params.search_radius_px / factor
        model = model_map(lplanes)
        # windows reaching past the image border see replicated pixels, not the scene: leave them out
        border = params.window_px // 2 + int(np.ceil(float(np.abs(model).max()) * 0.75 + radius)) + 1
        inside = np.zeros((height, width), bool)
        inside[border : -border or None, border : -border or None] = True
        sizes = np.bincount(index.ravel(), minlength=count + 1)[:count]
        inner = np.bincount(index[inside], minlength=count + 1)[:count]
        keep_all = inner < 0.1 * sizes  # tiny regions at the border keep their border pixels
        use = inside | keep_all[np.minimum(index, count - 1)] & (index < count)
        # Every pixel is warped with one region's model, so a window that straddles a boundary would mix two
        # models. An occluding contour moves with the occluder: each pixel takes the model of the nearest region
        # within half a window (a min filter over the regions' depth ranks), so the occluder's windows see its
        # model on both sides of its contour; a pixel counts for its own region only when it kept its own model.
        mean_model = np.bincount(index.ravel(), weights=model.ravel(), minlength=count + 1)[:count] / np.maximum(
            sizes, 1
        )
        rank_of = np.empty(count + 1, np.int64)
        rank_of[np.argsort(mean_model, kind="stable")] = np.arange(count)
        rank_of[count] = count
        by_rank = np.append(np.argsort(mean_model, kind="stable"), count)
        reach_px = params.window_px // 2 + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach_px + 1, 2 * reach_px + 1))
        owner = by_rank[cv2.erode(rank_of[index].astype(np.uint16), kernel, borderType=cv2.BORDER_REPLICATE)]
        clear = owner == index
        index_model = owner
        model = model_map(lplanes, index_model)
        w = np.where(use & clear & (index < count), lweights, 0.0).astype(np.float32)
        wsum_region = np.bincount(index.ravel(), weights=w.ravel(), minlength=count + 1)[:count]
        empty = wsum_region < 1e-6  # no confident pixel: every pixel counts
        if empty.any():
            fill = empty[np.minimum(index, count - 1)] & (index < count) & use
            w[fill] = 1.0
        cell = max(8, int(params.cell_px / factor))
        cells_x = (width + cell - 1) // cell
        cells_y = (height + cell - 1) // cell
        n_cells = cells_x * cells_y
        cell_id = (np.arange(height)[:, None] // cell) * cells_x + np.arange(width)[None, :] // cell
        bins = (np.where(w > 0, index, count) * n_cells + cell_id).ravel()
        n_bins = (count + 1) * n_cells
        wflat = w.ravel()
        wsum = np.bincount(bins, weights=wflat, minlength=n_bins).reshape(count + 1, n_cells)[:count]
        cxs = np.bincount(bins, weights=(w * xs).ravel(), minlength=n_bins).reshape(count + 1, n_cells)[:count]
        cys = np.bincount(bins, weights=(w * ys).ravel(), minlength=n_bins).reshape(count + 1, n_cells)[:count]
        cxs /= np.maximum(wsum, 1e-12)
        cys /= np.maximum(wsum, 1e-12)
        cost_model = AlignmentCost(band, aperture, params.window_px, params.noise_floor)

        self.count, self.factor, self.wsum, self.cxs, self.cys = count, factor, wsum, cxs, cys
        self.lplanes, self.index_model, self.model_map, self.model = lplanes, index_model, model_map, model
        self.w, self.bins, self.n_bins, self.n_cells, self.cost_model = w, bins, n_bins, n_cells, cost_model

    def curves(self, base: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """(count, n_cells, K) summed weighted cost at each offset added to the model map `base`."""
        count, n_cells, n_bins, bins, w = self.count, self.n_cells, self.n_bins, self.bins, self.w
        out = np.empty((count, n_cells, len(offsets)))

        def reduce(k: int, cost: np.ndarray) -> None:
            cost *= w
            out[:, :, k] = np.bincount(bins, weights=cost.ravel(), minlength=n_bins).reshape(count + 1, n_cells)[:count]

        self.cost_model.offsets(base, offsets, reduce)
        return out


def refine_regions(
    planes: np.ndarray,
    aperture: FilterAperture,
    labels: np.ndarray,
    weights: np.ndarray,
    planes_px: dict[int, tuple[float, float, float]],
    slanted: dict[int, bool],
    params: RefineParams = RefineParams(),
    prepared: RefineLevel | None = None,
) -> tuple[dict[int, tuple[float, float, float]], dict[int, float]]:
    """Refine every region's disparity model (processing px) at once by minimising the colour-line cost
    summed over its weighted pixels.

    All regions share one per-pixel model map, so each candidate offset costs one warp of the whole
    level (a Gaussian-pyramid level of at most `max_pixels`); the costs are reduced per (region, cell)
    with one bincount. Pass 1 samples offsets `coarse_step_px` apart over +-`search_radius_px`, pass 2
    `fine_step_px` apart around pass 1's model. Each cell gets a parabola minimum; a robust constant
    (or, for slanted regions, a robust plane) over the cells, weighted by curvature x weight, is the
    region's model: cells contaminated by another object (mislabelled pixels, occluder edges) are rejected.

    `prepared` (from `prepare_refine_level`, which needs no sketch and can run beside it) saves the
    pyramid level and its band-pass.

    Returns the refined planes and, per region, the depth of the cost dip (a confidence in [0, 1]).
    """
    from mca.processing.disparity import subpixel_minimum

    ids = sorted(planes_px)
    if not ids:
        return {}, {}
    if prepared is None:
        prepared = prepare_refine_level(planes, params)
    level = prepared.level
    if level == 0:
        # small grids: per-region crops are affordable and keep the most pixels of small objects
        return _refine_per_region(planes, aperture, labels, weights, planes_px, slanted, params)
    state = _LevelState(prepared.band, level, labels, weights, ids, planes_px, aperture, params)
    coarse_state = state
    if prepared.coarse_band is not None and min(prepared.coarse_band.shape[:2]) >= 4 * params.window_px:
        coarse_state = _LevelState(prepared.coarse_band, level + 1, labels, weights, ids, planes_px, aperture, params)
    count, factor, wsum, cxs, cys = state.count, state.factor, state.wsum, state.cxs, state.cys
    lplanes, index_model, model_map = state.lplanes, state.index_model, state.model_map

    def fit(coef: np.ndarray, offsets: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """New plane per region from the cells' parabola minima (relative to `coef`)."""
        k = len(offsets)
        best = np.argmin(cells, axis=2)
        ok = (best > 0) & (best < k - 1) & (wsum > 0)
        idx = np.clip(best, 1, k - 2)
        before = np.take_along_axis(cells, (idx - 1)[..., None], axis=2)[..., 0]
        at = np.take_along_axis(cells, idx[..., None], axis=2)[..., 0]
        after = np.take_along_axis(cells, (idx + 1)[..., None], axis=2)[..., 0]
        step = float(offsets[1] - offsets[0])
        minima = offsets[idx] + step * subpixel_minimum(before, at, after)
        curvature = np.maximum(before - 2 * at + after, 0.0) / np.maximum(wsum, 1e-9)
        cell_w = np.where(ok, np.sqrt(wsum) * np.sqrt(curvature), 0.0)
        new = coef.copy()
        for r, region_id in enumerate(ids):
            a, b, c = coef[r]
            cw = cell_w[r]
            used = cw > 0
            if not used.any():
                total = cells[r].sum(axis=0)
                new[r] = (a, b, c + _parabola_min(offsets, total))
            elif slanted.get(region_id, False) and np.count_nonzero(used) >= 4:
                mx = float(np.average(cxs[r][used], weights=cw[used]))
                my = float(np.average(cys[r][used], weights=cw[used]))
                fitted, _ = robust_plane(cxs[r][used] - mx, cys[r][used] - my, minima[r][used], cw[used])
                new[r] = (a + fitted[0], b + fitted[1], c + fitted[2] - fitted[0] * mx - fitted[1] * my)
            else:
                value, _ = robust_constant(minima[r][used], cw[used])
                new[r] = (a, b, c + value)
        return new

    # pass 1 (on the coarse state's level): robust centre per region, the weighted median of its cells' minima
    cs = coarse_state
    coarse_step = params.coarse_step_px / cs.factor
    radius = params.search_radius_px / cs.factor
    steps = int(np.ceil(radius / coarse_step - 1e-9)) if radius > 0 else 0
    coarse = np.arange(-steps, steps + 1) * coarse_step
    coarse_cells = cs.curves(cs.model, coarse)
    total = coarse_cells.sum(axis=1) / np.maximum(cs.wsum.sum(axis=1), 1e-9)[:, None]
    coef = lplanes[:count].copy()
    cell_best = coarse[np.argmin(coarse_cells, axis=2)] * (cs.factor / factor)  # in px of the fine level
    for r in range(count):
        used = cs.wsum[r] > 0.05 * max(float(cs.wsum[r].max()), 1e-12)
        if used.any():
            order = np.argsort(cell_best[r][used])
            cum = np.cumsum(cs.wsum[r][used][order])
            coef[r, 2] += float(cell_best[r][used][order][np.searchsorted(cum, cum[-1] / 2)])
    fine = np.arange(-params.fine_count, params.fine_count + 1) * (params.level_fine_step_px / factor)
    if params.fine_count > 0:
        coef = fit(coef, fine, state.curves(model_map(np.vstack([coef, [(0.0, 0.0, 0.0)]]), index_model), fine))
    results, dips = {}, {}
    for r, region_id in enumerate(ids):
        mean = float(total[r].mean())
        dips[region_id] = float(np.clip((mean - float(total[r].min())) / max(mean, 1e-6) * 3.0, 0.0, 1.0))
        results[region_id] = rescale_plane(tuple(float(v) for v in coef[r]), factor)
    return results, dips


def _refine_per_region(
    planes: np.ndarray,
    aperture: FilterAperture,
    labels: np.ndarray,
    weights: np.ndarray,
    planes_px: dict[int, tuple[float, float, float]],
    slanted: dict[int, bool],
    params: RefineParams = RefineParams(),
) -> tuple[dict[int, tuple[float, float, float]], dict[int, float]]:
    """`refine_regions` for grids that need no pyramid level (at most `max_pixels`): one crop per region with
    the region's own model extended over the crop (its occluding contours keep their windows whole)."""
    from mca.processing.disparity import AlignmentCost, band_pass

    pyramid = {0: (band_pass(planes, *params.band_sigma_px), labels, weights)}
    band = planes
    results: dict[int, tuple[float, float, float]] = {}
    dips: dict[int, float] = {}
    counts = np.bincount(labels.ravel(), minlength=int(labels.max()) + 1)
    for region_id, plane in planes_px.items():
        level = 0
        while counts[region_id] / 4**level > params.max_pixels:
            level += 1
        if level not in pyramid:
            f = 2**level
            size = (max(1, band.shape[1] // f), max(1, band.shape[0] // f))
            # Gaussian pyramid (anti-aliased): aliasing would not move with the disparity and pull it toward 0
            reduced = planes
            for _ in range(level):
                reduced = cv2.pyrDown(reduced)
            reduced = (
                cv2.resize(reduced, size, interpolation=cv2.INTER_LINEAR) if reduced.shape[1::-1] != size else reduced
            )
            pyramid[level] = (
                band_pass(reduced, *params.band_sigma_px),
                cv2.resize(labels.astype(np.int32), size, interpolation=cv2.INTER_NEAREST),
                cv2.resize(weights, size, interpolation=cv2.INTER_AREA),
            )
        lband, llabels, lweights = pyramid[level]
        factor = 2.0**level
        lplane = rescale_plane(plane, 1.0 / factor)
        mask = llabels == region_id
        ys, xs = np.nonzero(mask)
        if xs.size == 0:
            results[region_id], dips[region_id] = plane, 0.0
            continue
        d_range = np.array(
            [
                lplane[0] * x + lplane[1] * y + lplane[2]
                for x, y in ((xs.min(), ys.min()), (xs.max(), ys.max()), (xs.min(), ys.max()), (xs.max(), ys.min()))
            ]
        )
        radius = params.search_radius_px / factor
        reach = int(np.ceil(np.abs(d_range).max() * 0.75 + radius + params.window_px)) + 2
        x0, x1 = max(0, xs.min() - reach), min(lband.shape[1], xs.max() + reach + 1)
        y0, y1 = max(0, ys.min() - reach), min(lband.shape[0], ys.max() + reach + 1)
        crop = np.ascontiguousarray(lband[y0:y1, x0:x1])
        cost_model = AlignmentCost(crop, aperture, params.window_px, params.noise_floor)
        cy, cx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        model = (lplane[0] * cx + lplane[1] * cy + lplane[2]).astype(np.float32)
        cmask = mask[y0:y1, x0:x1]
        # windows reaching past the image border see replicated pixels, not the scene: leave them out
        border = params.window_px // 2 + int(np.ceil(np.abs(d_range).max() * 0.75 + radius)) + 1
        inside = np.zeros(lband.shape[:2], bool)
        inside[border : -border or None, border : -border or None] = True
        cmask_inner = cmask & inside[y0:y1, x0:x1]
        if cmask_inner.sum() >= 0.1 * cmask.sum():
            cmask = cmask_inner
        w = lweights[y0:y1, x0:x1] * cmask
        if w.sum() < 1e-6:
            w = cmask.astype(np.float32)
        # cells of a grid over the region: each gets its own sub-pixel minimum, then a robust fit over
        # the cells rejects those contaminated by another object (mislabelled pixels, occluder edges)
        cell = max(8, int(params.cell_px / factor))
        cell_ids = ((cy - y0) // cell).astype(np.int64) * ((x1 - x0) // cell + 1) + ((cx - x0) // cell).astype(np.int64)
        n_cells = int(cell_ids.max()) + 2
        bins = np.where(cmask, cell_ids, n_cells - 1)

        def curve(offsets: np.ndarray) -> np.ndarray:
            out = np.empty((n_cells, len(offsets)))
            for k, delta in enumerate(offsets):
                cost = cost_model.per_pixel(model + np.float32(delta))
                out[:, k] = np.bincount(bins.ravel(), weights=(cost * w).ravel(), minlength=n_cells)
            return out[:-1]

        wsum = np.bincount(bins.ravel(), weights=w.ravel(), minlength=n_cells)[:-1]
        coarse = np.arange(-radius, radius + 1e-9, params.coarse_step_px / factor) if radius > 0 else np.zeros(1)
        coarse_cells = curve(coarse)
        coarse_curve = coarse_cells.sum(axis=0) / max(wsum.sum(), 1e-9)
        # robust centre: weighted median of the cells' coarse minima
        cell_best = coarse[np.argmin(coarse_cells, axis=1)]
        used = wsum > 0.05 * wsum.max()
        order_ = np.argsort(cell_best[used])
        cum = np.cumsum(wsum[used][order_])
        centre = float(cell_best[used][order_][np.searchsorted(cum, cum[-1] / 2)]) if used.any() else 0.0
        fine_step = params.fine_step_px / factor
        fine = centre + np.arange(-6, 7) * fine_step
        fine_cells = curve(fine)
        total = fine_cells.sum(axis=0) / max(wsum.sum(), 1e-9)
        dips[region_id] = float(
            np.clip((coarse_curve.mean() - total.min()) / max(coarse_curve.mean(), 1e-6) * 3.0, 0.0, 1.0)
        )
        # per-cell minimum, weight = curvature x weight; minima at the end of the fine range are outliers
        best = np.argmin(fine_cells, axis=1)
        inner = (best > 0) & (best < len(fine) - 1) & (wsum > 0)
        idx = np.clip(best, 1, len(fine) - 2)
        rows = np.arange(len(best))
        before, at, after = fine_cells[rows, idx - 1], fine_cells[rows, idx], fine_cells[rows, idx + 1]
        from mca.processing.disparity import subpixel_minimum

        offsets = fine[idx] + fine_step * subpixel_minimum(before, at, after)
        curvature = np.maximum(before - 2 * at + after, 0.0) / np.maximum(wsum, 1e-9)
        cell_w = np.where(inner, np.sqrt(wsum) * np.sqrt(curvature), 0.0)
        cxs = np.bincount(bins.ravel(), weights=(cx * w).ravel(), minlength=n_cells)[:-1] / np.maximum(wsum, 1e-9)
        cys = np.bincount(bins.ravel(), weights=(cy * w).ravel(), minlength=n_cells)[:-1] / np.maximum(wsum, 1e-9)
        a, b = lplane[0], lplane[1]
        if np.count_nonzero(cell_w) == 0:
            new = (a, b, lplane[2] + _parabola_min(fine, total))
        elif slanted.get(region_id, False) and np.count_nonzero(cell_w) >= 4:
            mx, my = np.average(cxs, weights=cell_w + 1e-12), np.average(cys, weights=cell_w + 1e-12)
            coef, _ = robust_plane(cxs - mx, cys - my, offsets, cell_w)
            new = (a + coef[0], b + coef[1], lplane[2] + coef[2] - coef[0] * mx - coef[1] * my)
        else:
            value, _ = robust_constant(offsets, cell_w)
            new = (a, b, lplane[2] + value)
        results[region_id] = rescale_plane(new, factor)
    return results, dips


@dataclass(frozen=True)
class BoundaryParams:
    """Narrow-band reassignment of region labels (see `snap_boundaries`)."""

    band_px: int = 5  # half-width (analysis px) of the band reconsidered on the analysis grid:
    # the sketch's boundaries are off by up to about 4 analysis px
    model_window_px: int = 21  # side of the window (analysis px) of each region's local colour model
    interior_px: int = 2  # the model uses region pixels this far inside (analysis px)
    min_contrast: float = 1.0  # the two regions' local models must differ this much (feature units)
    chroma_scale: float = 0.045  # feature units: chromaticity / chroma_scale, log luminance * lum_weight
    lum_weight: float = 0.5


def _boundary_features(rgb: np.ndarray, params: BoundaryParams) -> np.ndarray:
    """(..., 3) float32: chromaticity (r, g) / chroma_scale and log luminance * lum_weight."""
    total = rgb.sum(axis=-1) + np.float32(1e-4)
    out = np.empty(rgb.shape[:-1] + (3,), np.float32)
    np.divide(rgb[..., 0], total * np.float32(params.chroma_scale), out=out[..., 0])
    np.divide(rgb[..., 1], total * np.float32(params.chroma_scale), out=out[..., 1])
    out[..., 2] = np.log(total / np.float32(3.0) + np.float32(1e-3)) * np.float32(params.lum_weight)
    return out


class _LocalColourModels:
    """Per region, the mean boundary features of its interior pixels in a window around each analysis pixel."""

    def __init__(self, labels_an: np.ndarray, aligned_an: np.ndarray, params: BoundaryParams) -> None:
        self.labels, self.params = labels_an, params
        self.features = _boundary_features(np.asarray(aligned_an, np.float32)[::2, ::2], params)  # every 2nd px
        self.kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * params.interior_px + 1,) * 2)
        self.maps: dict[int, tuple[int, int, np.ndarray]] = {}

    def _map(self, region_id: int) -> tuple[int, int, np.ndarray]:
        """(row0, col0, sums (h, w, 4): feature sums and pixel count) over the region's bounding box + window."""
        if region_id not in self.maps:
            mask = (self.labels == region_id).astype(np.uint8)
            inner = cv2.erode(mask, self.kernel, borderType=cv2.BORDER_REPLICATE)[::2, ::2]  # away from mixed px
            if not inner.any():
                inner = mask[::2, ::2]
            h, w = inner.shape
            half = self.params.model_window_px // 4  # the window on the grid of every 2nd pixel
            x, y, bw, bh = cv2.boundingRect(inner)
            if bw == 0:
                self.maps[region_id] = (0, 0, np.zeros((1, 1, 4), np.float32))
                return self.maps[region_id]
            r0, r1 = max(0, y - half), min(h, y + bh + half)
            c0, c1 = max(0, x - half), min(w, x + bw + half)
            m = inner[r0:r1, c0:c1].astype(np.float32)
            stack = np.empty((r1 - r0, c1 - c0, 4), np.float32)
            np.multiply(self.features[r0:r1, c0:c1], m[..., None], out=stack[..., :3])
            stack[..., 3] = m
            size = (2 * half + 1, 2 * half + 1)
            self.maps[region_id] = (
                r0,
                c0,
                cv2.boxFilter(stack, cv2.CV_32F, size, normalize=False, borderType=cv2.BORDER_CONSTANT),
            )
        return self.maps[region_id]

    def lookup(self, cand: np.ndarray, ya: np.ndarray, xa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Models (2, N, 3) of the candidate regions `cand` (2, N) at analysis pixels (ya, xa), and where defined."""
        models = np.zeros(cand.shape + (3,), np.float32)
        support = np.zeros(cand.shape, bool)
        order = np.argsort(cand, axis=None, kind="stable")
        flat = cand.ravel()[order]
        starts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]])
        ends = np.r_[starts[1:], flat.size]
        for start, end in zip(starts, ends):
            at = order[start:end]
            r0, c0, sums = self._map(int(flat[start]))
            yy, xx = ya[at % ya.size] // 2 - r0, xa[at % xa.size] // 2 - c0
            ok = (yy >= 0) & (yy < sums.shape[0]) & (xx >= 0) & (xx < sums.shape[1])
            got = np.zeros((at.size, 4), np.float32)
            got[ok] = sums[yy[ok], xx[ok]]
            has = got[:, 3] > 0.5
            models.reshape(-1, 3)[at[has]] = got[has, :3] / got[has, 3:4]
            support.reshape(-1)[at[has]] = True
        return models, support


def _reassign(
    planes: np.ndarray,
    aperture: FilterAperture,
    ys: np.ndarray,
    xs: np.ndarray,
    cand: np.ndarray,
    current: np.ndarray,
    coef: np.ndarray,
    models: np.ndarray,
    support: np.ndarray,
    params: BoundaryParams,
    smooth: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """For band pixels (ys, xs) of `planes` with candidate labels `cand` (2, N): (pixels to change, new labels).

    Each pixel's colour is sampled with each candidate's disparity model (`coef[id]` = (a, b, c) in px of
    `planes`: channel c at x + d s_c, so without colour fringes) and compared with the candidate's local model;
    the nearer wins, where the two models differ enough and the current label is one of the two."""
    from mca.processing.disparity import channel_shifts

    shifts = channel_shifts(aperture).astype(np.float32)
    fx, fy = xs.astype(np.float32), ys.astype(np.float32)
    n = ys.size
    height, width = planes.shape[:2]
    flat = planes.reshape(-1)
    dist = np.empty((2, n), np.float32)
    for s in range(2):
        k = cand[s]
        d = (coef[k, 0] * fx + coef[k, 1] * fy + coef[k, 2]).astype(np.float32)
        rgb = np.empty((n, 3), np.float32)
        for c in range(3):
            # bilinear sampling at (x + d s_cx, y + d s_cy), borders replicated: gathers from the interleaved planes
            sx = np.clip(fx + d * shifts[c, 0], 0, width - 1)
            sy = np.clip(fy + d * shifts[c, 1], 0, height - 1)
            x0 = np.minimum(sx.astype(np.int64), width - 2)
            y0 = np.minimum(sy.astype(np.int64), height - 2)
            wx, wy = sx - x0, sy - y0
            at = (y0 * width + x0) * 3 + c
            top = flat[at] * (1 - wx) + flat[at + 3] * wx
            at += 3 * width
            bottom = flat[at] * (1 - wx) + flat[at + 3] * wx
            rgb[:, c] = top * (1 - wy) + bottom * wy
        diff = _boundary_features(rgb, params) - models[s]
        dist[s] = np.einsum("ij,ij->i", diff, diff)
    score = dist[0] - dist[1]
    if smooth:
        # the decision box-smoothed over 3x3 px against noise, inside the band's bounding box
        y0, x0 = ys.min(), xs.min()
        grid = np.zeros((ys.max() + 1 - y0, xs.max() + 1 - x0), np.float32)
        grid[ys - y0, xs - x0] = score
        score = cv2.boxFilter(grid, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)[ys - y0, xs - x0]
    gap = models[0] - models[1]
    decide = (
        support[0]
        & support[1]
        & (np.einsum("ij,ij->i", gap, gap) >= params.min_contrast**2)
        & ((current == cand[0]) | (current == cand[1]))
    )
    new = np.where(score > 0, cand[1], cand[0])
    change = decide & (new != current)
    return change, new[change]


def snap_boundaries(
    planes: np.ndarray,
    aperture: FilterAperture,
    labels_full: np.ndarray,
    small: np.ndarray,
    labels_an: np.ndarray,
    aligned_an: np.ndarray,
    coef: np.ndarray,
    factor: int,
    params: BoundaryParams = BoundaryParams(),
) -> np.ndarray:
    """Region labels at processing resolution with boundaries that follow the image edges.

    `labels_full` is the analysis-grid `labels_an` (grid of `small`, `factor` times coarser than `planes`)
    upsampled by nearest neighbour: its boundaries are blocks of `factor` px and off by up to a few analysis px.
    Only pixels near a label change are reconsidered, each between the lowest and highest label of its
    neighbourhood: its colour, sampled with each candidate's disparity model (`coef[id]` = (a, b, c), processing
    px), is compared with each candidate's local colour model (mean features of the region's interior pixels in
    a window of `aligned_an`); the nearer wins; where the two models barely differ (one colour, two depths) the
    label is kept. Two passes: on the analysis grid within `band_px` (the decision box-smoothed over 3x3 px),
    then at processing resolution within one analysis px of the new boundaries (per pixel: smoothing measured no
    better there). Returns a new int32 label map (processing resolution)."""
    _h_an, _w_an = labels_an.shape
    height, width = labels_full.shape
    local = _LocalColourModels(labels_an, aligned_an, params)
    coef_an = coef.astype(np.float64).copy()  # the models on the analysis grid (rescale_plane inverse)
    coef_an[:, 2] = (coef[:, 2] + (coef[:, 0] + coef[:, 1]) * (0.5 * factor - 0.5)) / factor
    out = labels_full.astype(np.int32, copy=True)
    dy, dx = np.divmod(np.arange(factor * factor), factor)

    def blocks(ya: np.ndarray, xa: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The processing pixels of analysis pixels (ya, xa): rows, columns, and the index of their block."""
        ys = (ya[:, None] * factor + dy[None, :]).ravel()
        xs = (xa[:, None] * factor + dx[None, :]).ravel()
        owner = np.repeat(np.arange(ya.size), factor * factor)
        ok = (ys < height) & (xs < width)
        return ys[ok], xs[ok], owner[ok]

    def band(labels: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lab16 = labels.astype(np.uint16)
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 1, 2 * radius + 1))
        lo = cv2.erode(lab16, kernel, borderType=cv2.BORDER_REPLICATE)
        hi = cv2.dilate(lab16, kernel, borderType=cv2.BORDER_REPLICATE)
        ya, xa = np.nonzero(lo != hi)
        return ya, xa, np.stack([lo[ya, xa].astype(np.int32), hi[ya, xa].astype(np.int32)])

    # pass 1: the analysis grid, a band of `band_px`
    ya, xa, cand = band(labels_an, params.band_px)
    if ya.size == 0:
        return out
    models, support = local.lookup(cand, ya, xa)
    labels_new = labels_an.astype(np.int32, copy=True)
    change, new = _reassign(
        np.ascontiguousarray(small, dtype=np.float32),
        aperture,
        ya,
        xa,
        cand,
        labels_an[ya, xa],
        coef_an,
        models,
        support,
        params,
        True,
    )
    labels_new[ya[change], xa[change]] = new
    ys, xs, owner = blocks(ya[change], xa[change])
    out[ys, xs] = new[owner]
    # pass 2: processing resolution, within one analysis px of the new boundaries
    ya, xa, cand = band(labels_new, 1)
    if ya.size == 0:
        return out
    models, support = local.lookup(cand, ya, xa)
    ys, xs, owner = blocks(ya, xa)
    cand_full = cand[:, owner]
    change, new = _reassign(
        np.ascontiguousarray(planes, dtype=np.float32),
        aperture,
        ys,
        xs,
        cand_full,
        out[ys, xs],
        coef,
        models[:, owner],
        support[:, owner],
        params,
        False,
    )
    out[ys[change], xs[change]] = new
    return out
