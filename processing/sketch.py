"""The 2.1D sketch (paper section IV-A, eq. 1): the image as L regions with their disparity and occlusion order.

Regions are built from the surfaces (`processing.surfaces`): neighbouring superpixels whose planes meet along
their shared boundary (within `continuity_px`) and whose colours are alike belong to one object (along the
boundary, an edge whose planes are more than `gap_clip_px` apart counts as that much: it is a discontinuity
whatever its size, and one stray plane cannot keep two parts of a surface apart); regions
smaller than `min_region_fraction` of the image join the neighbour they meet most continuously. A chain of
superpixels that lean across a depth step the dense disparity smoothed (two overlapping cards of one colour) can
join two objects with every link continuous; such a region's pixel levels fall into two groups with few between,
and it splits at that valley (`split_valley`: the histogram of its levels, smoothed at a quarter of
`continuity_px`, falls below that share of the lower of the peaks either side) when each side is one level
(the sketch's layers; a slanted floor with an object on it has a valley at the object's levels, but two slopes
either side of it). Parts of one surface that a nearer object cuts apart (a knife under a carrot) are not
neighbours; they join when their colours are close and one plane fits both (`occluded_join_px`). Each region
gets a robust plane fitted to the surface disparity (slanted objects keep their slant) and a representative
disparity at its centroid. Where two regions meet, the one with the smaller disparity along the boundary is
nearer and occludes the other (T-junctions and depth steps alike); the order is nearest first.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from mca.processing.surfaces import Surfaces, boundary_edges, fit_planes, interior_weights


@dataclass(frozen=True)
class SketchParams:
    """Parameters of the region decomposition (pixels of the analysis grid)."""

    continuity_px: float = 0.6  # neighbouring regions whose planes meet within this (mean over the boundary) join
    # a boundary edge's |plane gap| counts at most this much in that mean (0: no limit): twice `continuity_px`,
    # an edge this far apart is a discontinuity whatever its size. Unlimited, one superpixel whose plane strayed
    # (a weakly textured one: on dog.png's wall sheet 1.96 px along 32 of the 178 px it shares with the cloth)
    # outweighed the rest of the boundary (0.07-0.59 px), and the wall came out in two
    gap_clip_px: float = 1.2
    colour_distance: float = 0.35  # ... when their mean display colours are at most this far apart
    same_depth_px: float = 0.2  # then regions whose planes meet within this join whatever their colours (0: off)
    split_valley: float = 0.3  # a region whose pixel levels' valley is below this share of its peaks splits (0: off)
    split_fraction: float = 0.01  # ... into parts of at least this fraction of the image
    occluded_join_px: float = 0.15  # parts of one surface a nearer region cuts apart join (0: off) when one
    occluded_colour_distance: float = 0.1  # plane fits both within this RMS and their colours are this close
    min_region_fraction: float = 0.002  # smaller regions join a neighbour
    sliver_fraction: float = 0.01  # a region smaller than this ...
    sliver_width_px: float = 12.0  # ... and on average thinner (2 area / boundary) is a rim sliver
    occlusion_margin_px: float = 0.5  # a region occludes a neighbour this much farther along their boundary
    slant_px: float = 0.5  # a region whose plane varies more than this over its extent is slanted
    focus_tolerance_px: float = 0.5  # in-focus region: |disparity| at most this (input px: at least 1)


@dataclass
class SketchRegion:
    """One region of the sketch on the analysis grid."""

    id: int  # 1..L
    pixels: int
    plane: tuple[float, float, float]  # disparity a x + b y + c, analysis px
    slanted: bool
    centroid_xy: tuple[float, float]
    disparity_px: float  # plane at the centroid, analysis px
    confidence: float  # mean dense-disparity confidence over the region

    def disparity_at(self, x: float | np.ndarray, y: float | np.ndarray) -> float | np.ndarray:
        a, b, c = self.plane
        return a * x + b * y + c


@dataclass
class Sketch:
    """Regions 1..L on the analysis grid with their occlusion relations."""

    labels: np.ndarray  # (H, W) int32 region ids 1..L
    regions: list[SketchRegion]
    order: dict[int, int]  # id -> rank, 0 = nearest
    occludes: dict[int, list[int]]  # id -> ids it occludes
    superpixel_region: np.ndarray  # (n,) region id of each superpixel
    pair_gap_px: dict[tuple[int, int], float] = field(default_factory=dict)  # mean signed gap (j - i) per region pair

    def region(self, region_id: int) -> SketchRegion:
        for r in self.regions:
            if r.id == region_id:
                return r
        raise KeyError(region_id)


def _edge_gaps(planes: np.ndarray, lo: np.ndarray, hi: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """P_hi - P_lo at each boundary edge's midpoint (px, py), planes[k] = (a, b, c) of label k."""
    return (planes[hi, 0] - planes[lo, 0]) * px + (planes[hi, 1] - planes[lo, 1]) * py + planes[hi, 2] - planes[lo, 2]


def _occlusions(pair_gap: dict[tuple[int, int], float], ids: list[int], margin_px: float) -> dict[int, list[int]]:
    """id -> the ids it occludes: of each pair (i, j) with mean gap P_j - P_i, i occludes j beyond `margin_px`
    and j occludes i below -margin_px."""
    occludes: dict[int, list[int]] = {i: [] for i in ids}
    for (i, j), mean in pair_gap.items():
        if mean > margin_px:
            occludes[i].append(j)
        elif mean < -margin_px:
            occludes[j].append(i)
    return {k: sorted(v) for k, v in occludes.items()}


def _boundary_gaps(surfaces: Surfaces, clip_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Signed and absolute mean (P_j - P_i) of each adjacent superpixel pair (i, j) over their shared boundary;
    with `clip_px` > 0 each edge's |P_j - P_i| counts at most that much in the absolute mean."""
    planes = surfaces.planes
    lo, hi, px, py = boundary_edges(surfaces.labels)  # evaluated at the boundary edges' midpoints
    count = surfaces.count
    key = lo * count + hi
    pair_keys = surfaces.pairs[:, 0] * count + surfaces.pairs[:, 1]
    index = np.searchsorted(pair_keys, key)
    gap = _edge_gaps(planes, lo, hi, px, py)
    counts = np.maximum(np.bincount(index, minlength=pair_keys.size), 1)
    size = np.abs(gap) if clip_px <= 0 else np.minimum(np.abs(gap), clip_px)
    return np.bincount(index, gap, pair_keys.size) / counts, np.bincount(index, size, pair_keys.size) / counts


def _merge_continuous(surfaces: Surfaces, abs_gaps: np.ndarray, params: SketchParams) -> np.ndarray:
    """Region of each superpixel: adjacent regions merge, most continuous first, while the length-weighted mean
    |plane gap| over their whole shared boundary is within `continuity_px` and their mean colours are within
    `colour_distance`; then regions below the minimum size join the neighbour they meet most continuously.
    Aggregating over the whole boundary, one stray superpixel cannot chain two objects together."""
    count = surfaces.count
    area = surfaces.areas.astype(np.float64).copy()
    colour_sum = surfaces.colours * area[:, None]
    flat = surfaces.labels.ravel()
    disparity_sum = np.bincount(flat, surfaces.disparity().ravel().astype(np.float64), count)
    links: dict[int, dict[int, list[float]]] = {i: {} for i in range(count)}
    for (i, j), gap, length in zip(surfaces.pairs, abs_gaps, surfaces.pair_lengths, strict=True):
        i, j = int(i), int(j)
        entry = links[i].setdefault(j, [0.0, 0.0])
        entry[0] += gap * length
        entry[1] += length
        links[j][i] = entry
    sets = _UnionFind(count)

    def merge(a: int, b: int) -> int:
        """b into a (both roots); combines their boundaries with every neighbour."""
        sets.parent[b] = a
        area[a] += area[b]
        colour_sum[a] += colour_sum[b]
        disparity_sum[a] += disparity_sum[b]
        del links[a][b]
        for other, (gap_len, length) in links.pop(b).items():
            if other == a:
                continue
            del links[other][b]
            entry = links[a].setdefault(other, [0.0, 0.0])
            entry[0] += gap_len
            entry[1] += length
            links[other][a] = entry
        return a

    def continuity_pass(limit: float, colour_limit: float) -> None:
        heap = [(v[0] / max(v[1], 1e-9), i, j) for i in links for j, v in links[i].items() if i < j]
        heapq.heapify(heap)
        while heap:
            value, i, j = heapq.heappop(heap)
            if value > limit:
                break
            if sets.parent[i] != i or sets.parent[j] != j or j not in links[i]:
                continue
            current = links[i][j][0] / max(links[i][j][1], 1e-9)
            if abs(current - value) > 1e-12:
                heapq.heappush(heap, (current, i, j))
                continue
            colour = np.linalg.norm(colour_sum[i] / area[i] - colour_sum[j] / area[j])
            if colour > colour_limit:
                continue
            a = merge(min(i, j), max(i, j))
            for other, (gap_len, length) in links[a].items():
                heapq.heappush(heap, (gap_len / max(length, 1e-9), min(a, other), max(a, other)))

    continuity_pass(params.continuity_px, params.colour_distance)
    if params.same_depth_px > 0:
        continuity_pass(params.same_depth_px, np.inf)
    # small regions: into the most continuous neighbour, whatever its colour
    minimum = params.min_region_fraction * float(surfaces.labels.size)
    for _ in range(count):
        small = [r for r in links if area[r] < minimum and links[r]]
        if not small:
            break
        r = min(small, key=lambda k: area[k])
        other = min(links[r], key=lambda k: links[r][k][0] / max(links[r][k][1], 1e-9))
        merge(min(r, other), max(r, other))
    # rim slivers: a thin strip along an occluding edge is where the windows saw both sides (and the disoccluded
    # background); it joins the farthest neighbour that shares at least a quarter of its boundary
    sliver_area = params.sliver_fraction * float(surfaces.labels.size)
    for _ in range(count):
        slivers = [
            r
            for r in links
            if links[r]
            and area[r] < sliver_area
            and 2.0 * area[r] / max(sum(v[1] for v in links[r].values()), 1.0) < params.sliver_width_px
        ]
        if not slivers:
            break
        r = min(slivers, key=lambda k: area[k])
        perimeter = sum(v[1] for v in links[r].values())
        sharing = [k for k in links[r] if links[r][k][1] >= 0.25 * perimeter] or list(links[r])
        other = max(sharing, key=lambda k: disparity_sum[k] / area[k])
        merge(min(r, other), max(r, other))
    return np.array([sets.find(i) for i in range(count)])


def _level_valley(levels: np.ndarray, min_mass: float, smooth_px: float, bin_px: float = 0.05) -> tuple[float, float]:
    """The deepest valley of the distribution of `levels` (a histogram of `bin_px` bins smoothed by a Gaussian of
    `smooth_px`): (its height over the lower of the highest peaks on either side, its level), over the levels
    with at least `min_mass` values on each side; (inf, nan) when there is none. An evenly spread (slanted)
    surface, or a plateau beside a peak, has no valley (ratio 1) however wide its range."""
    low, high = float(levels.min()), float(levels.max())
    pad = int(np.ceil(3.0 * smooth_px / bin_px))
    bins = int(np.ceil((high - low) / bin_px)) + 1
    counts = np.bincount(np.minimum(((levels - low) / bin_px).astype(np.int64), bins - 1), minlength=bins)
    taps = np.exp(-0.5 * (np.arange(-pad, pad + 1) * bin_px / smooth_px) ** 2)
    smooth = np.convolve(np.pad(counts.astype(np.float64), pad), taps / taps.sum(), mode="valid")
    below = np.cumsum(counts)
    peak_before = np.maximum.accumulate(smooth)
    peak_after = np.maximum.accumulate(smooth[::-1])[::-1]
    ok = (below >= min_mass) & (below[-1] - below >= min_mass)
    ok[-1] = False
    if not ok.any():
        return np.inf, float("nan")
    ratio = np.where(ok, smooth / np.maximum(np.minimum(peak_before, peak_after), 1e-12), np.inf)
    i = int(np.argmin(ratio))
    return float(ratio[i]), low + (i + 1) * bin_px


def _split_at_valleys(surfaces: Surfaces, disparity: np.ndarray, root: np.ndarray, params: SketchParams) -> np.ndarray:
    """Regions whose pixels' levels fall into two groups with few between (two objects at different depths that
    a chain of superpixels leaning across the depth step joined) split at the valley, repeatedly: the
    superpixels whose mean level lies beyond it form a new region. Only when each group is one level (within
    half of `continuity_px`, RMS), the layers of the 2.1D sketch: a slanted floor with an object standing on it
    has fewer floor pixels at the object's levels (a valley), but its two sides are slopes, not levels, and it
    stays one region."""
    flat = surfaces.labels.ravel()
    values = disparity.ravel().astype(np.float64)
    level_px = 0.5 * params.continuity_px
    areas = surfaces.areas.astype(np.float64)
    levels = np.bincount(flat, values, surfaces.count) / np.maximum(areas, 1.0)
    min_mass = params.split_fraction * float(flat.size)
    root = root.copy()
    pixel_root = root[flat]
    queue = [int(r) for r in np.unique(root)]
    next_id = int(root.max()) + 1
    while queue:
        r = queue.pop()
        members = np.nonzero(root == r)[0]
        if areas[members].sum() < 2 * min_mass:
            continue
        inside = np.nonzero(pixel_root == r)[0]
        region_values = values[inside]
        ratio, t = _level_valley(region_values, min_mass, 0.25 * params.continuity_px)
        if ratio >= params.split_valley:
            continue
        part = levels[flat[inside]] > t  # the pixels of the superpixels beyond the valley
        if part.all() or not part.any():
            continue  # every superpixel's mean on one side: nothing to split off (and no spread of an empty part)
        if max(_level_spread_px(region_values[part]), _level_spread_px(region_values[~part])) <= level_px:
            root[members[levels[members] > t]] = next_id
            pixel_root[inside[part]] = next_id
            queue += [r, next_id]
            next_id += 1
    return root


def _plane_moments(labels: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """(count, 10) sums of 1, x, y, v, xx, xy, yy, xv, yv, vv over each label's pixels (labels 0..count-1)."""
    h, w = labels.shape
    flat = labels.ravel()
    xs = np.tile(np.arange(w, dtype=np.float64), h)
    ys = np.repeat(np.arange(h, dtype=np.float64), w)
    v = values.ravel().astype(np.float64)
    terms = (None, xs, ys, v, xs * xs, xs * ys, ys * ys, xs * v, ys * v, v * v)
    return np.stack([np.bincount(flat, t, count) for t in terms], axis=1)


def _plane_rms(m: np.ndarray) -> float:
    """Root-mean-square residual of the least-squares plane through the pixels whose moments `m` sums."""
    n = m[0]
    normal = np.array([[m[4], m[5], m[1]], [m[5], m[6], m[2]], [m[1], m[2], n]])
    rhs = np.array([m[7], m[8], m[3]])
    coef = np.linalg.lstsq(normal, rhs, rcond=None)[0]
    return float(np.sqrt(max(m[9] - coef @ rhs, 0.0) / n))


def _extra_plane_rms(a: np.ndarray, b: np.ndarray) -> float:
    """How much worse (RMS, px) one plane fits the pixels of two regions than each region's own plane does."""
    own = (a[0] * _plane_rms(a) ** 2 + b[0] * _plane_rms(b) ** 2) / (a[0] + b[0])
    return float(np.sqrt(max(_plane_rms(a + b) ** 2 - own, 0.0)))


def _region_pair_gaps(surfaces: Surfaces, gaps: np.ndarray, region_of: np.ndarray) -> dict[tuple[int, int], float]:
    """Mean signed plane gap P_j - P_i along the whole boundary of each pair of neighbouring regions (i < j),
    weighted by length, from the superpixel pairs' mean gaps `gaps`; `region_of` is each superpixel's region."""
    region_gap: dict[tuple[int, int], list[float]] = {}
    for (i, j), gap, length in zip(surfaces.pairs, gaps, surfaces.pair_lengths, strict=True):
        ri, rj = int(region_of[i]), int(region_of[j])
        if ri == rj:
            continue
        key = (min(ri, rj), max(ri, rj))
        signed = gap if ri < rj else -gap
        entry = region_gap.setdefault(key, [0.0, 0.0])
        entry[0] += signed * length
        entry[1] += length
    return {key: weighted / max(length, 1e-9) for key, (weighted, length) in region_gap.items()}


def _join_occluded_parts(
    surfaces: Surfaces, gaps: np.ndarray, disparity: np.ndarray, root: np.ndarray, params: SketchParams
) -> np.ndarray:
    """Regions that do not touch but share a neighbour that is not behind either of them (by more than
    `occlusion_margin_px`: an occluder, or an object that crosses their depth there) join when their colours are
    within `occluded_colour_distance` and one plane fits both within `occluded_join_px` (RMS, beyond what their
    own planes leave): the parts of one surface that a nearer object cuts apart (a knife under a carrot, the
    wall either side of a pole). Two alike objects in front of a wall stay apart: the wall is behind them.
    Closest fits first; a pair joins only if the plane still fits what each side has joined so far."""
    ids, region_of = np.unique(root, return_inverse=True)
    n = ids.size
    if n < 3:
        return root
    area = np.bincount(region_of, surfaces.areas.astype(np.float64), n)
    colour_sum = np.stack([np.bincount(region_of, surfaces.colours[:, k] * surfaces.areas, n) for k in range(3)], 1)
    colour = colour_sum / np.maximum(area, 1.0)[:, None]
    pair_gap = _region_pair_gaps(surfaces, gaps, region_of)
    in_front_of: dict[int, set[int]] = {}  # a region -> the neighbours it is not behind
    for (i, j), mean in pair_gap.items():  # mean P_j - P_i
        if mean > -params.occlusion_margin_px:
            in_front_of.setdefault(i, set()).add(j)
        if mean < params.occlusion_margin_px:
            in_front_of.setdefault(j, set()).add(i)
    candidates = set()
    for hidden in in_front_of.values():
        for a in hidden:
            for b in hidden:
                if a < b and (a, b) not in pair_gap:  # not neighbours themselves
                    candidates.add((a, b))
    alike = [(a, b) for a, b in candidates if np.linalg.norm(colour[a] - colour[b]) <= params.occluded_colour_distance]
    if not alike:
        return root
    # every other pixel along both axes: plenty for a fit's RMS, and a quarter of the sums
    moments = _plane_moments(region_of[surfaces.labels[::2, ::2]], disparity[::2, ::2], n)
    scored = [(_extra_plane_rms(moments[a], moments[b]), a, b) for a, b in alike]
    sets = _UnionFind(n)
    for extra, a, b in sorted(scored):
        if extra > params.occluded_join_px:
            break
        ra, rb = sets.find(a), sets.find(b)
        if ra != rb and _extra_plane_rms(moments[ra], moments[rb]) <= params.occluded_join_px:
            keep, gone = min(ra, rb), max(ra, rb)
            sets.parent[gone] = keep
            moments[keep] += moments[gone]
    joined = np.array([sets.find(k) for k in range(n)])
    return ids[joined][region_of]


def _level_spread_px(values: np.ndarray) -> float:
    """Root-mean-square distance of `values` from their median: how far a part is from being one level."""
    return float(np.sqrt(np.mean((values - np.median(values)) ** 2)))


def plane_occlusions(
    labels: np.ndarray, regions: list[SketchRegion], margin_px: float
) -> tuple[dict[int, list[int]], dict[tuple[int, int], float]]:
    """Who occludes whom, from the regions' own planes: along each shared boundary of `labels` (ids 1..L) the
    mean signed gap P_j - P_i of the pair (i < j), and i occludes j where it exceeds `margin_px` (j occludes i
    below -margin_px). The refined planes are precise to a few hundredths of a pixel where the superpixels
    along a boundary lean across it (`build_sketch` decides on those first)."""
    lo, hi, px, py = boundary_edges(labels)
    count = int(labels.max()) + 1
    planes = np.zeros((count, 3))
    for r in regions:
        planes[r.id] = r.plane
    keys, index = np.unique(lo * count + hi, return_inverse=True)
    mean = np.bincount(index, _edge_gaps(planes, lo, hi, px, py), keys.size) / np.bincount(index, minlength=keys.size)
    pair_gap = {(int(key // count), int(key % count)): float(value) for key, value in zip(keys, mean, strict=True)}
    return _occlusions(pair_gap, [r.id for r in regions], margin_px), pair_gap


class _UnionFind:
    def __init__(self, n: int) -> None:
        self.parent = np.arange(n)

    def find(self, i: int) -> int:
        parent = self.parent
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return int(root)


def build_sketch(
    surfaces: Surfaces, disparity: np.ndarray, confidence: np.ndarray, params: SketchParams = SketchParams()
) -> Sketch:
    """Regions, planes and occlusion order from the surfaces (see the module docstring).

    `disparity` (H, W) is the surface disparity on the analysis grid, `confidence` the dense confidence."""
    gaps, abs_gaps = _boundary_gaps(surfaces, params.gap_clip_px)
    root = _merge_continuous(surfaces, abs_gaps, params)
    if params.split_valley > 0:
        root = _split_at_valleys(surfaces, disparity, root, params)
    if params.occluded_join_px > 0:
        root = _join_occluded_parts(surfaces, gaps, disparity, root, params)
    roots, superpixel_region = np.unique(root, return_inverse=True)
    superpixel_region = (superpixel_region + 1).astype(np.int32)
    labels = superpixel_region[surfaces.labels]
    region_count = roots.size

    weights = interior_weights(labels, 2) * np.maximum(confidence, 0.05)
    planes = fit_planes(labels, region_count + 1, disparity, weights, 1e-3)
    h, w = labels.shape
    flat = labels.ravel()
    areas = np.bincount(flat, minlength=region_count + 1)
    xs = np.tile(np.arange(w, dtype=np.float64), h)
    ys = np.repeat(np.arange(h, dtype=np.float64), w)
    cx = np.bincount(flat, xs, region_count + 1) / np.maximum(areas, 1)
    cy = np.bincount(flat, ys, region_count + 1) / np.maximum(areas, 1)
    mean_conf = np.bincount(flat, confidence.ravel().astype(np.float64), region_count + 1) / np.maximum(areas, 1)
    x0 = np.full(region_count + 1, np.inf)
    x1 = np.full(region_count + 1, -np.inf)
    y0 = np.full(region_count + 1, np.inf)
    y1 = np.full(region_count + 1, -np.inf)
    np.minimum.at(x0, flat, xs)
    np.maximum.at(x1, flat, xs)
    np.minimum.at(y0, flat, ys)
    np.maximum.at(y1, flat, ys)
    regions = []
    for rid in range(1, region_count + 1):
        a, b, c = (float(v) for v in planes[rid])
        spread = abs(a) * (x1[rid] - x0[rid]) + abs(b) * (y1[rid] - y0[rid])
        slanted = bool(spread > params.slant_px)
        if not slanted:
            level = float(np.median(disparity[labels == rid]))
            a, b, c = 0.0, 0.0, level
        centre = (float(cx[rid]), float(cy[rid]))
        regions.append(
            SketchRegion(
                id=rid,
                pixels=int(areas[rid]),
                plane=(a, b, c),
                slanted=slanted,
                centroid_xy=centre,
                disparity_px=a * centre[0] + b * centre[1] + c,
                confidence=float(np.clip(mean_conf[rid], 0.0, 1.0)),
            )
        )
    # occlusion: along each region boundary the nearer side (smaller disparity) occludes the other
    pair_gap = _region_pair_gaps(surfaces, gaps, superpixel_region)
    occludes = _occlusions(pair_gap, [r.id for r in regions], params.occlusion_margin_px)
    ranked = sorted(regions, key=lambda r: r.disparity_px)
    order = {r.id: rank for rank, r in enumerate(ranked)}
    return Sketch(labels, regions, order, occludes, superpixel_region, pair_gap)
