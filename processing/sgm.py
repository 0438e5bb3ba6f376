"""Semi-global aggregation of a cost volume (Hirschmueller 2008) along eight paths, edge-adaptive penalties.

Along each path r the aggregated cost is
    L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d +- 1) + P1, min_k L_r(p-r, k) + P2(p)) - min_k L_r(p-r, k),
and the paths are summed. P1 charges a one-step change of disparity (slanted and curved surfaces), P2 any
larger jump; P2 shrinks where the guide image changes (an object boundary), P2(p) = max(1.5 P1,
P2 / (1 + alpha |I(p) - I(p-r)|)). Compiled with numba: the volume is (H, W, D) with D contiguous, each
path is a sweep over columns (horizontal paths, parallel over rows) or over rows: the three downward paths
(vertical and diagonal) in one sweep and the three upward ones in another, the two sweeps side by side on
two threads into two sums (a sweep parallel over the columns of a row would wait at a barrier every row).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, fastmath=True, inline="always")
def _step(c: np.ndarray, prev: np.ndarray, prev_min: float, p1: float, p2: float, out: np.ndarray) -> float:
    count = c.shape[0]
    base = prev_min + p2
    if count == 1:
        out[0] = c[0] + min(prev[0], base) - prev_min
        return out[0]
    out[0] = c[0] + min(min(prev[0], prev[1] + p1), base) - prev_min
    for d in range(1, count - 1):
        out[d] = c[d] + min(min(prev[d], prev[d - 1] + p1), min(prev[d + 1] + p1, base)) - prev_min
    out[count - 1] = c[count - 1] + min(min(prev[count - 1], prev[count - 2] + p1), base) - prev_min
    smallest = out[0]
    for d in range(1, count):
        smallest = min(smallest, out[d])
    return smallest


@nb.njit(cache=True, fastmath=True, inline="always")
def _penalty(p1: float, p2: float, alpha: float, g0: float, g1: float) -> float:
    return max(p2 / (1.0 + alpha * abs(g0 - g1)), 1.5 * p1)


@nb.njit(cache=True, fastmath=True)
def _vertical_sweep(cost, guide, p1, p2, alpha, out, dy, assign):
    """The three paths with a vertical component dy (+1: top to bottom) in one sweep over the rows: path k has
    the predecessor (y - dy, x - dx_k), dx = 0, +1, -1. Their sum goes into `out` (`assign`: replaces its
    values, else adds to them). Serial: the caller runs the two sweeps side by side."""
    h, w, count = cost.shape
    prev = np.empty((3, w, count), np.float32)
    cur = np.empty((3, w, count), np.float32)
    prev_min = np.empty((3, w), np.float32)
    cur_min = np.empty((3, w), np.float32)
    y0 = 0 if dy > 0 else h - 1
    for x in range(w):
        m = np.float32(np.inf)
        for d in range(count):
            m = min(m, cost[y0, x, d])
            out[y0, x, d] = 3.0 * cost[y0, x, d] + (0.0 if assign else out[y0, x, d])
        for k in range(3):
            for d in range(count):
                prev[k, x, d] = cost[y0, x, d]
            prev_min[k, x] = m
    for i in range(1, h):
        y = y0 + dy * i
        yp = y - dy
        for k in range(3):
            dx = 0 if k == 0 else (1 if k == 1 else -1)
            for x in range(w):
                xp = x - dx
                c = cost[y, x]
                row = cur[k, x]
                if xp < 0 or xp >= w:
                    m = np.float32(np.inf)
                    for d in range(count):
                        row[d] = c[d]
                        m = min(m, c[d])
                    cur_min[k, x] = m
                else:
                    pen = _penalty(p1, p2, alpha, guide[y, x], guide[yp, xp])
                    cur_min[k, x] = _step(c, prev[k, xp], prev_min[k, xp], p1, pen, row)
        for x in range(w):
            o = out[y, x]
            if assign:
                for d in range(count):
                    o[d] = cur[0, x, d] + cur[1, x, d] + cur[2, x, d]
            else:
                for d in range(count):
                    o[d] += cur[0, x, d] + cur[1, x, d] + cur[2, x, d]
        prev, cur = cur, prev
        prev_min, cur_min = cur_min, prev_min


@nb.njit(cache=True, parallel=True)
def _vertical_passes(cost, guide, p1, p2, alpha, down, up):
    """The six paths with a vertical component: the downward sweep added into `down` and the upward one
    written into `up`, side by side on two threads (one sweep each, no barrier per row)."""
    for k in nb.prange(2):
        if k == 0:
            _vertical_sweep(cost, guide, p1, p2, alpha, down, 1, False)
        else:
            _vertical_sweep(cost, guide, p1, p2, alpha, up, -1, True)


@nb.njit(cache=True, parallel=True, fastmath=True)
def _add_into(out, other):
    h = out.shape[0]
    for y in nb.prange(h):
        out[y] += other[y]


@nb.njit(cache=True, parallel=True, fastmath=True)
def _columns_pass(cost, guide, p1, p2, alpha, out, dx):
    """Horizontal paths: every row on its own, x in order (dx = +1: left to right)."""
    h, w, count = cost.shape
    for y in nb.prange(h):
        prev = np.empty(count, np.float32)
        row = np.empty(count, np.float32)
        x0 = 0 if dx > 0 else w - 1
        m = np.float32(np.inf)
        for d in range(count):
            prev[d] = cost[y, x0, d]
            out[y, x0, d] += prev[d]
            m = min(m, prev[d])
        for i in range(1, w):
            x = x0 + dx * i
            pen = _penalty(p1, p2, alpha, guide[y, x], guide[y, x - dx])
            m = _step(cost[y, x], prev, m, p1, pen, row)  # type: ignore[assignment,arg-type]  # numba unifies float32 and float
            o = out[y, x]
            for d in range(count):
                o[d] += row[d]
                prev[d] = row[d]


def aggregate(cost_hwd: np.ndarray, guide: np.ndarray, p1: float, p2: float, alpha: float = 0.0) -> np.ndarray:
    """Sum over the eight paths of the semi-global aggregation of `cost_hwd` (H, W, D) float32.

    `guide` (H, W) float32 image whose steps lower P2 (object boundaries); `alpha` scales that effect
    (0: constant P2)."""
    cost = np.ascontiguousarray(cost_hwd, dtype=np.float32)
    guide = np.ascontiguousarray(guide, dtype=np.float32)
    out = np.zeros_like(cost)
    a, q1, q2 = np.float32(alpha), np.float32(p1), np.float32(p2)
    _columns_pass(cost, guide, q1, q2, a, out, 1)
    _columns_pass(cost, guide, q1, q2, a, out, -1)
    up = np.empty_like(cost)  # every value written by the upward sweep
    _vertical_passes(cost, guide, q1, q2, a, out, up)
    _add_into(out, up)
    return out
