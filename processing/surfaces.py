"""Surfaces: superpixels that follow the image's edges, each a slanted disparity plane chosen with its neighbours.

Where a surface has texture the dense disparity (`processing.dense`) is right; where it has none, or beside an
occluding edge (whose disparity the window-based cost spreads onto the farther side), it is not. Surfaces
carry the depth across: the image is cut into superpixels along its colour edges (SLIC on the fringe-free
image), each superpixel gets a robust plane fitted to the dense disparity, and then each superpixel chooses
one plane among its own and those of its neighbours within two rings, minimising

    E = sum_s sum_(x in s) e(x) min(|d(x) - P_s(x)|, tau_data)                               (data)
      + lam * sum_(s,t adjacent) len_st * exp(-|c_s - c_t|^2 / sigma^2) * min(tau, |P_s - P_t|_boundary)

(smoothness: neighbours of similar colour should continue each other's plane across their shared boundary);
e(x) in [0, 1] is the evidence of pixel x (its texture): where there is none, the neighbours decide.
The minimisation is iterated conditional modes over the superpixels (compiled with numba). A plane
(a, b, c) gives disparity a x + b y + c at pixel (x, y) of the analysis grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from mca.processing.jit import FASTMATH
from mca.processing.slic import slic_labels


@dataclass(frozen=True)
class SurfaceParams:
    """Parameters of the superpixel surfaces (pixels of the analysis grid)."""

    superpixel_px: int = 550  # mean superpixel area
    compactness: float = 10.0  # SLIC: colour versus position
    slic_iterations: int = 10  # SLIC: k-means iterations
    interior_px: int = 2  # pixels this close to a superpixel's edge weigh little in its plane fit
    slope_ridge: float = 1e-2  # ridge on the plane slopes (per pixel of support), towards fronto-parallel
    rings: int = 2  # candidate planes: the superpixel's own and its neighbours' within this many rings
    data_clip_px: float = 2.0  # tau_data
    smoothness: float = 3.0  # lam
    colour_sigma: float = 0.3  # sigma, on display-gamma colour in [0, 1]
    jump_clip_px: float = 2.0  # tau
    boundary_samples: int = 10  # points per shared boundary at which two planes are compared
    sweeps: int = 10
    weak_evidence: float = 0.1  # superpixels whose mean evidence is below this are decided after their neighbours


@dataclass
class Surfaces:
    """Superpixels and their planes on the analysis grid."""

    labels: np.ndarray  # (H, W) int32, 0..n-1
    planes: np.ndarray  # (n, 3) float64 chosen plane (a, b, c) of each superpixel
    fitted: np.ndarray  # (n, 3) float64 each superpixel's own fit to the dense disparity
    colours: np.ndarray  # (n, 3) float64 mean display colour
    areas: np.ndarray  # (n,) int64 pixels
    pairs: np.ndarray  # (m, 2) int64 adjacent superpixels (i < j)
    pair_lengths: np.ndarray  # (m,) int64 shared boundary length in pixel edges

    @property
    def count(self) -> int:
        return int(self.planes.shape[0])

    def disparity(self, planes: np.ndarray | None = None) -> np.ndarray:
        """(H, W) float32 disparity of the plane of each pixel's superpixel."""
        return plane_map(self.labels, self.planes if planes is None else planes)


@nb.njit(cache=True, parallel=True)
def _plane_map_kernel(labels, coef, out, where, masked):
    h, w = labels.shape
    for y in nb.prange(h):
        fy = np.float32(y)
        for x in range(w):
            if masked and not where[y, x]:
                continue
            i = labels[y, x]
            out[y, x] = coef[i, 0] * np.float32(x) + coef[i, 1] * fy + coef[i, 2]


def plane_map(
    labels: np.ndarray, planes: np.ndarray, out: np.ndarray | None = None, where: np.ndarray | None = None
) -> np.ndarray:
    """(H, W) float32: a x + b y + c with each pixel's plane (a, b, c) = planes[labels] (float32 arithmetic).

    With `out` (H, W) float32 the values are written into it, only where `where` (H, W) bool is set when
    given; without `out` a new map (`where` then must be None)."""
    h, w = labels.shape
    if out is None:
        if where is not None:
            raise ValueError("plane_map: `where` needs an `out` to keep the other pixels in")
        out = np.empty((h, w), np.float32)
    coef = np.ascontiguousarray(planes, np.float32)
    mask = np.ones((1, 1), bool) if where is None else np.asarray(where, bool)
    _plane_map_kernel(np.ascontiguousarray(labels), coef, out, mask, where is not None)
    return out


def superpixels(image: np.ndarray, params: SurfaceParams = SurfaceParams()) -> np.ndarray:
    """(H, W) int32 SLIC labels 0..n-1 of an (H, W, 3) float image in [0, 1], about `superpixel_px` pixels each
    (scikit-image's SLIC, computed on both cores by `processing.slic`)."""
    h, w = image.shape[:2]
    count = max(4, int(round(h * w / params.superpixel_px)))
    # the connectivity pass numbers the pieces it keeps 0, 1, ... in raster order: dense already
    return slic_labels(np.asarray(image, np.float32), count, params.compactness, params.slic_iterations).astype(
        np.int32
    )


def interior_weights(labels: np.ndarray, margin_px: int) -> np.ndarray:
    """1 where a pixel's (2 margin + 1)^2 neighbourhood lies in its own superpixel, 0.05 elsewhere."""
    if margin_px <= 0:
        return np.ones(labels.shape, np.float32)
    lab = labels.astype(np.float32)
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    inside = (cv2.erode(lab, kernel) == lab) & (cv2.dilate(lab, kernel) == lab)
    return np.where(inside, np.float32(1.0), np.float32(0.05))


def fit_planes(
    labels: np.ndarray, count: int, disparity: np.ndarray, weights: np.ndarray, slope_ridge: float, iterations: int = 4
) -> np.ndarray:
    """Robust weighted least-squares plane per label of an image: (count, 3) float64 (a, b, c); see
    `fit_planes_at`."""
    h, w = labels.shape
    xs = np.tile(np.arange(w, dtype=np.float64), h)
    ys = np.repeat(np.arange(h, dtype=np.float64), w)
    return fit_planes_at(labels.ravel(), xs, ys, disparity.ravel(), weights.ravel(), count, slope_ridge, iterations)


def fit_planes_at(
    lab: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    values: np.ndarray,
    weights: np.ndarray,
    count: int,
    slope_ridge: float,
    iterations: int = 4,
    min_sigma_px: float = 0.25,
    drop_sigmas: float = 4.0,
    drop_px: float = 1.0,
) -> np.ndarray:
    """Robust weighted least-squares plane a x + b y + c through the points (xs, ys, values) of each label
    0..count-1 (flat arrays): (count, 3) float64, zeros for a label without weight.

    Iteratively reweighted: residuals beyond 1.5 sigmas are down-weighted (Huber), beyond `drop_sigmas` sigmas +
    `drop_px` dropped, sigma the label's weighted residual spread but at least `min_sigma_px`; a ridge of
    `slope_ridge` per unit weight pulls the slopes towards 0 (small or degenerate supports)."""
    lab = np.ascontiguousarray(lab, np.int64)
    xs = np.ascontiguousarray(xs, np.float64)
    ys = np.ascontiguousarray(ys, np.float64)
    d = np.ascontiguousarray(values, np.float64)
    wt = np.ascontiguousarray(weights, np.float64)
    coef: np.ndarray = np.zeros((count, 3))
    sums = np.zeros((9, count))
    for iteration in range(iterations):
        _plane_sums(lab, xs, ys, d, wt, coef, iteration > 0, min_sigma_px, drop_sigmas, drop_px, sums)
        s1, sx, sy = sums[0], sums[1], sums[2]
        a = np.empty((count, 3, 3))
        a[:, 0, 0] = sums[3]
        a[:, 0, 1] = a[:, 1, 0] = sums[4]
        a[:, 1, 1] = sums[5]
        a[:, 0, 2] = a[:, 2, 0] = sx
        a[:, 1, 2] = a[:, 2, 1] = sy
        a[:, 2, 2] = s1
        rhs = np.stack([sums[6], sums[7], sums[8]], axis=1)
        # a ridge on the slopes (the offset is free, so it acts about the support's centroid)
        ridge = slope_ridge * np.maximum(s1, 1e-9)
        a[:, 0, 0] += ridge
        a[:, 1, 1] += ridge
        a[:, 2, 2] += 1e-9
        coef = np.linalg.solve(a, rhs[..., None])[..., 0]
        coef[s1 <= 1e-9] = 0.0
    return coef


@nb.njit(cache=True)
def _plane_sums(lab, xs, ys, d, wt, coef, reweight, min_sigma_px, drop_sigmas, drop_px, sums):
    """One pass of `fit_planes_at`'s weighted sums per label into `sums` (9, count): 1, x, y, xx, xy, yy, xd,
    yd, d, each weighted by the robust weight (Huber beyond 1.5 sigmas, dropped beyond drop_sigmas sigmas +
    drop_px; the plain weights when not `reweight`). Serial, in the order of the points: the same sums as
    numpy's bincount."""
    n = lab.shape[0]
    count = sums.shape[1]
    sums[:] = 0.0
    sigma = np.empty(count)
    if reweight:
        spread = np.zeros(count)
        total = np.zeros(count)
        for i in range(n):
            k = lab[i]
            r = d[i] - (coef[k, 0] * xs[i] + coef[k, 1] * ys[i] + coef[k, 2])
            spread[k] += wt[i] * r * r
            total[k] += wt[i]
        for k in range(count):
            sigma[k] = max(np.sqrt(spread[k] / max(total[k], 1e-12)), min_sigma_px)
    for i in range(n):
        k = lab[i]
        x, y, v = xs[i], ys[i], d[i]
        w = wt[i]
        if reweight:
            r = v - (coef[k, 0] * x + coef[k, 1] * y + coef[k, 2])
            ratio = abs(r) / (1.5 * sigma[k])
            w = w / max(1.0, ratio) * (1.0 if abs(r) < drop_sigmas * sigma[k] + drop_px else 0.0)
        sums[0, k] += w
        sums[1, k] += w * x
        sums[2, k] += w * y
        sums[3, k] += w * x * x
        sums[4, k] += w * x * y
        sums[5, k] += w * y * y
        sums[6, k] += w * x * v
        sums[7, k] += w * y * v
        sums[8, k] += w * v


@dataclass
class _Graph:
    pairs: np.ndarray  # (m, 2) i < j
    lengths: np.ndarray  # (m,)
    sample_ptr: np.ndarray  # (m + 1,)
    sample_xy: np.ndarray  # (k, 2) float64 boundary points of each pair
    nb_ptr: np.ndarray  # (n + 1,) directed neighbour lists
    nb_other: np.ndarray
    nb_pair: np.ndarray
    cand_ptr: np.ndarray  # (n + 1,) candidate planes of each superpixel
    cand_list: np.ndarray
    pix_ptr: np.ndarray  # (n + 1,) pixels of each superpixel, sorted
    pix_index: np.ndarray


def boundary_edges(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every boundary pixel edge (4-neighbours with different labels): the smaller and larger label (int64) and
    the edge's midpoint (x, y) (float64), horizontal neighbours first."""
    ya, xa = np.nonzero(labels[:, :-1] != labels[:, 1:])
    yb, xb = np.nonzero(labels[:-1] != labels[1:])
    first = np.concatenate([labels[ya, xa], labels[yb, xb]]).astype(np.int64)
    second = np.concatenate([labels[ya, xa + 1], labels[yb + 1, xb]]).astype(np.int64)
    px = np.concatenate([xa + 0.5, xb.astype(np.float64)])
    py = np.concatenate([ya.astype(np.float64), yb + 0.5])
    return np.minimum(first, second), np.maximum(first, second), px, py


def _graph(labels: np.ndarray, count: int, rings: int, samples: int) -> _Graph:
    lo, hi, px, py = boundary_edges(labels)
    key = lo * count + hi
    order = np.argsort(key, kind="stable")
    key, px, py = key[order], px[order], py[order]
    uniq, start, lengths = np.unique(key, return_index=True, return_counts=True)
    pairs = np.stack([uniq // count, uniq % count], axis=1)
    # up to `samples` evenly spaced points per pair
    rank = np.arange(key.size) - np.repeat(start, lengths)
    stride = np.maximum(1, lengths // samples)
    keep = (rank % np.repeat(stride, lengths) == 0) & (rank // np.repeat(stride, lengths) < samples)
    kept_pair = np.repeat(np.arange(uniq.size), lengths)[keep]
    sample_xy = np.stack([px[keep], py[keep]], axis=1)
    sample_ptr = np.concatenate([[0], np.cumsum(np.bincount(kept_pair, minlength=uniq.size))])
    # directed neighbour lists
    m = pairs.shape[0]
    src = np.concatenate([pairs[:, 0], pairs[:, 1]])
    dst = np.concatenate([pairs[:, 1], pairs[:, 0]])
    pid = np.concatenate([np.arange(m), np.arange(m)])
    order = np.argsort(src, kind="stable")
    src, dst, pid = src[order], dst[order], pid[order]
    nb_ptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=count))])
    # candidates: neighbours within `rings`
    neighbours = [dst[nb_ptr[s] : nb_ptr[s + 1]] for s in range(count)]
    cand: list[np.ndarray] = []
    for s in range(count):
        seen = {s}
        frontier = [s]
        for _ in range(rings):
            nxt = []
            for f in frontier:
                for t in neighbours[f]:
                    t = int(t)
                    if t not in seen:
                        seen.add(t)
                        nxt.append(t)
            frontier = nxt
        cand.append(np.array(sorted(seen), np.int64))
    cand_ptr = np.concatenate([[0], np.cumsum([c.size for c in cand])]).astype(np.int64)
    flat = labels.ravel()
    pix_index = np.argsort(flat, kind="stable").astype(np.int64)
    pix_ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=count))]).astype(np.int64)
    return _Graph(
        pairs.astype(np.int64),
        lengths.astype(np.int64),
        sample_ptr.astype(np.int64),
        sample_xy,
        nb_ptr.astype(np.int64),
        dst.astype(np.int64),
        pid.astype(np.int64),
        cand_ptr,
        np.concatenate(cand),
        pix_ptr,
        pix_index,
    )


@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _data_terms(disparity, evidence, width, planes, pix_ptr, pix_index, cand_ptr, cand_list, clip):
    n = pix_ptr.shape[0] - 1
    out = np.zeros(cand_list.shape[0], np.float64)
    flat = disparity.ravel()
    weight = evidence.ravel()
    for s in nb.prange(n):
        for k in range(cand_ptr[s], cand_ptr[s + 1]):
            p = cand_list[k]
            a, b, c = planes[p, 0], planes[p, 1], planes[p, 2]
            acc = 0.0
            for i in range(pix_ptr[s], pix_ptr[s + 1]):
                idx = pix_index[i]
                y = idx // width
                x = idx - y * width
                acc += weight[idx] * min(abs(flat[idx] - (a * x + b * y + c)), clip)
            out[k] = acc
    return out


@nb.njit(cache=True)
def _icm(
    planes,
    cand_ptr,
    cand_list,
    data,
    nb_ptr,
    nb_other,
    nb_pair,
    weight,
    sample_ptr,
    sample_xy,
    jump_clip,
    sweeps,
    order,
    known,
):
    n = cand_ptr.shape[0] - 1
    label = np.arange(n)
    for _ in range(sweeps):
        changed = 0
        for t in range(n):
            s = order[t]
            best = label[s]
            best_value = np.inf
            for k in range(cand_ptr[s], cand_ptr[s + 1]):
                p = cand_list[k]
                value = data[k]
                for j in range(nb_ptr[s], nb_ptr[s + 1]):
                    if not known[nb_other[j]]:
                        continue  # a weak neighbour not yet visited has no say
                    q = label[nb_other[j]]
                    if q == p:
                        continue
                    pair = nb_pair[j]
                    total = 0.0
                    samples = sample_ptr[pair + 1] - sample_ptr[pair]
                    for i in range(sample_ptr[pair], sample_ptr[pair + 1]):
                        x = sample_xy[i, 0]
                        y = sample_xy[i, 1]
                        total += abs(
                            (planes[p, 0] - planes[q, 0]) * x
                            + (planes[p, 1] - planes[q, 1]) * y
                            + planes[p, 2]
                            - planes[q, 2]
                        )
                    if samples > 0:
                        value += weight[j] * min(jump_clip, total / samples)
                if value < best_value:
                    best_value = value
                    best = p
            known[s] = True
            if best != label[s]:
                label[s] = best
                changed += 1
        if changed == 0:
            break
    return label


def build_surfaces(
    image: np.ndarray,
    disparity: np.ndarray,
    params: SurfaceParams = SurfaceParams(),
    labels: np.ndarray | None = None,
    evidence: np.ndarray | None = None,
) -> Surfaces:
    """Superpixels of `image` (H, W, 3 display colour in [0, 1], fringe-free) with a plane each, chosen to fit
    `disparity` (H, W) and to continue their neighbours' planes (see the module docstring). `evidence` (H, W)
    in [0, 1] weighs each pixel's disparity in the fits and the data term (None: all alike)."""
    if labels is None:
        labels = superpixels(image, params)
    count = int(labels.max()) + 1
    areas = np.bincount(labels.ravel(), minlength=count)
    colours = (
        np.stack(
            [np.bincount(labels.ravel(), image[..., c].ravel().astype(np.float64), count) for c in range(3)], axis=1
        )
        / np.maximum(areas, 1)[:, None]
    )
    evidence = np.ones(labels.shape, np.float32) if evidence is None else np.asarray(evidence, np.float32)
    fitted = fit_planes(
        labels,
        count,
        disparity,
        interior_weights(labels, params.interior_px) * np.maximum(evidence, 0.02),
        params.slope_ridge,
    )
    graph = _graph(labels, count, params.rings, params.boundary_samples)
    data = _data_terms(
        np.ascontiguousarray(disparity, np.float32),
        np.ascontiguousarray(evidence, np.float32),
        labels.shape[1],
        fitted,
        graph.pix_ptr,
        graph.pix_index,
        graph.cand_ptr,
        graph.cand_list,
        float(params.data_clip_px),
    )
    # visited strongest evidence first; a weak superpixel's own plane does not speak to its neighbours before it
    # has been visited once (a texture-less patch of several superpixels would otherwise hold its garbage planes)
    mean_evidence = np.bincount(labels.ravel(), evidence.ravel().astype(np.float64), count) / np.maximum(areas, 1)
    order = np.argsort(-mean_evidence, kind="stable")
    src = np.repeat(np.arange(count), np.diff(graph.nb_ptr))
    similarity = np.exp(-np.sum((colours[src] - colours[graph.nb_other]) ** 2, axis=1) / params.colour_sigma**2)
    weight = params.smoothness * graph.lengths[graph.nb_pair] * similarity
    chosen = _icm(
        fitted,
        graph.cand_ptr,
        graph.cand_list,
        data,
        graph.nb_ptr,
        graph.nb_other,
        graph.nb_pair,
        weight.astype(np.float64),
        graph.sample_ptr,
        graph.sample_xy,
        float(params.jump_clip_px),
        int(params.sweeps),
        order,
        mean_evidence >= params.weak_evidence,
    )
    return Surfaces(labels, fitted[chosen], fitted, colours, areas, graph.pairs, graph.lengths)
