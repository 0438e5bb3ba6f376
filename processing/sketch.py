"""The 2.1D sketch (paper section IV-A, eq. 1): the image as L regions with their disparity and occlusion order.

Regions are built from the surfaces (`processing.surfaces`): neighbouring superpixels whose planes meet along
their shared boundary (within `continuity_px`) and whose colours are alike belong to one object; regions
smaller than `min_region_fraction` of the image join the neighbour they meet most continuously. A chain of
superpixels that lean across a depth step the dense disparity smoothed (two overlapping cards of one colour) can
join two objects with every link continuous; such a region's pixel levels fall into two groups with few between,
and it splits at that dip (`split_dip`: the levels within continuity_px / 2 of it hold less than that share of
either side's band of the same width; an evenly slanted surface has no dip however wide). Each region
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
    colour_distance: float = 0.35  # ... when their mean display colours are at most this far apart
    same_depth_px: float = 0.0  # then regions whose planes meet within this join whatever their colours (0: off)
    split_dip: float = 0.3  # a region whose pixel levels dip below this share of either side splits (0: off)
    split_fraction: float = 0.01  # ... into parts of at least this fraction of the image
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


def _boundary_gaps(surfaces: Surfaces) -> tuple[np.ndarray, np.ndarray]:
    """Signed and absolute mean (P_j - P_i) of each adjacent superpixel pair (i, j) over their shared boundary."""
    planes = surfaces.planes
    lo, hi, px, py = boundary_edges(surfaces.labels)  # evaluated at the boundary edges' midpoints
    count = surfaces.count
    key = lo * count + hi
    pair_keys = surfaces.pairs[:, 0] * count + surfaces.pairs[:, 1]
    index = np.searchsorted(pair_keys, key)
    gap = (planes[hi, 0] - planes[lo, 0]) * px + (planes[hi, 1] - planes[lo, 1]) * py + planes[hi, 2] - planes[lo, 2]
    counts = np.maximum(np.bincount(index, minlength=pair_keys.size), 1)
    return np.bincount(index, gap, pair_keys.size) / counts, np.bincount(index, np.abs(gap), pair_keys.size) / counts


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


def _level_dip(levels: np.ndarray, weights: np.ndarray, half_px: float, min_mass: float) -> tuple[float, float]:
    """The deepest dip of the weighted level distribution: (mass within `half_px` of t over the smaller mass
    in the `2 half_px` bands either side of that, t), over t every `half_px / 4` with at least `min_mass` on
    each side; (inf, nan) when there is none. Density-relative, so an evenly spread (slanted) surface has no
    dip however wide its range."""
    order = np.argsort(levels)
    sorted_levels = levels[order]
    cum = np.concatenate([[0.0], np.cumsum(weights[order])])

    def mass(low: float, high: float) -> float:
        return float(cum[np.searchsorted(sorted_levels, high)] - cum[np.searchsorted(sorted_levels, low)])

    best = (np.inf, float("nan"))
    for t in np.arange(sorted_levels[0], sorted_levels[-1], 0.25 * half_px):
        below = mass(-np.inf, t)
        if below < min_mass or cum[-1] - below < min_mass:
            continue
        side = min(mass(t - 3 * half_px, t - half_px), mass(t + half_px, t + 3 * half_px))
        if side > 0:
            ratio = mass(t - half_px, t + half_px) / side
            if ratio < best[0]:
                best = (ratio, float(t))
    return best


def _split_at_dips(surfaces: Surfaces, disparity: np.ndarray, root: np.ndarray, params: SketchParams) -> np.ndarray:
    """Regions whose pixels' levels fall into two groups with few between (two objects at different depths that
    a chain of superpixels leaning across the depth step joined) split at the dip, repeatedly: the superpixels
    whose mean level lies beyond it form a new region."""
    flat = surfaces.labels.ravel()
    values = disparity.ravel().astype(np.float64)
    areas = surfaces.areas.astype(np.float64)
    levels = np.bincount(flat, values, surfaces.count) / np.maximum(areas, 1.0)
    min_mass = params.split_fraction * float(flat.size)
    root = root.copy()
    queue = [int(r) for r in np.unique(root)]
    next_id = int(root.max()) + 1
    while queue:
        r = queue.pop()
        members = np.nonzero(root == r)[0]
        if areas[members].sum() < 2 * min_mass:
            continue
        inside = np.isin(flat, members)
        ratio, t = _level_dip(values[inside], np.ones(int(inside.sum())), 0.5 * params.continuity_px, min_mass)
        if ratio < params.split_dip:
            root[members[levels[members] > t]] = next_id
            queue += [r, next_id]
            next_id += 1
    return root


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
    gaps, abs_gaps = _boundary_gaps(surfaces)
    root = _merge_continuous(surfaces, abs_gaps, params)
    if params.split_dip > 0:
        root = _split_at_dips(surfaces, disparity, root, params)
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
    region_gap: dict[tuple[int, int], list[float]] = {}
    lengths = surfaces.pair_lengths
    for (i, j), gap, length in zip(surfaces.pairs, gaps, lengths, strict=True):
        ri, rj = int(superpixel_region[i]), int(superpixel_region[j])
        if ri == rj:
            continue
        key = (min(ri, rj), max(ri, rj))
        signed = gap if ri < rj else -gap
        entry = region_gap.setdefault(key, [0.0, 0.0])
        entry[0] += signed * length
        entry[1] += length
    occludes: dict[int, list[int]] = {r.id: [] for r in regions}
    pair_gap = {}
    for (ri, rj), (weighted, length) in region_gap.items():
        mean = weighted / max(length, 1e-9)
        pair_gap[(ri, rj)] = mean
        if mean > params.occlusion_margin_px:
            occludes[ri].append(rj)
        elif mean < -params.occlusion_margin_px:
            occludes[rj].append(ri)
    ranked = sorted(regions, key=lambda r: r.disparity_px)
    order = {r.id: rank for rank, r in enumerate(ranked)}
    return Sketch(labels, regions, order, {k: sorted(v) for k, v in occludes.items()}, superpixel_region, pair_gap)
