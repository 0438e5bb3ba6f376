"""Semi-global aggregation of a cost volume (Hirschmueller 2008) along eight paths, edge-adaptive penalties.

Along each path r the aggregated cost is
    L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d +- 1) + P1, min_k L_r(p-r, k) + P2(p)) - min_k L_r(p-r, k),
and the paths are summed. P1 charges a one-step change of disparity (slanted and curved surfaces), P2 any
larger jump; P2 shrinks where the guide image changes (an object boundary), P2(p) = max(1.5 P1,
P2 / (1 + alpha max(max_c |I_c(p) - I_c(p-r)| - floor, 0))) over the guide's channels, floor the steps noise
makes. On unevenly spaced candidates a change between neighbours more than one step apart is a jump (`gaps`).

Compiled with numba: the volume is (H, W, D) with D contiguous, each path is a sweep over columns (horizontal
paths, parallel over rows) or over rows: the three downward paths (vertical and diagonal) in one sweep and the
three upward ones in another, each row of a sweep shared out among the threads by columns. Every path adds into
one output volume: no second volume of the cost's size is made (at 20 MP one is a quarter of a gigabyte, whose
first touch costs more than the sweep's waits).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from mca.processing.jit import FASTMATH


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _smallest(a: np.ndarray) -> float:
    """The smallest value of `a`, in eight independent chains of comparisons: one chain waits on each comparison
    before the next (the compiler may not split a floating-point minimum itself), eight keep the core busy."""
    n = a.shape[0]
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = a[0]
    i = 0
    while i + 8 <= n:
        m0, m1, m2, m3 = min(m0, a[i]), min(m1, a[i + 1]), min(m2, a[i + 2]), min(m3, a[i + 3])
        m4, m5, m6, m7 = min(m4, a[i + 4]), min(m5, a[i + 5]), min(m6, a[i + 6]), min(m7, a[i + 7])
        i += 8
    while i < n:
        m0 = min(m0, a[i])
        i += 1
    return min(min(min(m0, m1), min(m2, m3)), min(min(m4, m5), min(m6, m7)))


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _step(c: np.ndarray, prev: np.ndarray, prev_min: float, gaps: np.ndarray, p2: float, out: np.ndarray) -> float:
    """One step of a path: `out` = L_r(p, .) from the costs `c` at p and `prev` = L_r(p - r, .) (float32
    throughout: a uint16 cost is read as float32, which holds it exactly); returns min_d out. `gaps[d]` is the
    penalty of a change between candidates d and d + 1 (P1, or more where they lie more than a step apart).

    The candidates inside the range run over slices indexed from 0, so that the compiler sees no negative index
    and vectorises the loop (it did not over prev[d - 1])."""
    count = c.shape[0]
    base = prev_min + p2
    if count == 1:
        out[0] = np.float32(c[0]) + min(prev[0], base) - prev_min
        return out[0]
    out[0] = np.float32(c[0]) + min(min(prev[0], prev[1] + gaps[0]), base) - prev_min
    n = count - 2
    below, at, above = prev[0:n], prev[1 : n + 1], prev[2 : n + 2]
    up, down = gaps[0:n], gaps[1 : n + 1]
    costs, inner = c[1 : n + 1], out[1 : n + 1]
    for i in range(n):
        inner[i] = np.float32(costs[i]) + min(min(at[i], below[i] + up[i]), min(above[i] + down[i], base)) - prev_min
    last = count - 1
    out[last] = np.float32(c[last]) + min(min(prev[last], prev[last - 1] + gaps[last - 1]), base) - prev_min
    return _smallest(out)


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _penalty(p1: float, p2: float, alpha: float, floor: float, g0: np.ndarray, g1: np.ndarray) -> float:
    """P2 at a step from guide pixel g1 to g0 (each a vector of channels): the largest channel's step counts,
    less `floor` (the steps noise makes)."""
    step = 0.0
    for c in range(g0.shape[0]):
        step = max(step, abs(g0[c] - g1[c]))
    return max(p2 / (1.0 + alpha * max(step - floor, 0.0)), 1.5 * p1)


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _vertical_row(cost, guide, p1, gaps, p2, alpha, floor, out, y, yp, x0, x1, prev, prev_min, cur, cur_min):
    """Row y of the three paths with predecessors in row yp (path k: (yp, x - dx_k), dx = 0, +1, -1) for the
    columns x0..x1 - 1; their sum is added into `out`."""
    w, count = cost.shape[1], cost.shape[2]
    for k in range(3):
        dx = 0 if k == 0 else (1 if k == 1 else -1)
        for x in range(x0, x1):
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
                pen = _penalty(p1, p2, alpha, floor, guide[y, x], guide[yp, xp])
                cur_min[k, x] = _step(c, prev[k, xp], prev_min[k, xp], gaps, pen, row)
    for x in range(x0, x1):
        o = out[y, x]
        for d in range(count):
            o[d] += cur[0, x, d] + cur[1, x, d] + cur[2, x, d]


@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _vertical_sweep(cost, guide, p1, gaps, p2, alpha, floor, out, dy, chunks):
    """The three paths with a vertical component dy (+1: top to bottom) in one sweep over the rows, their sum
    added into `out`. Each row is shared out among the threads in `chunks` column blocks; a row starts when
    the one before it is done (its predecessors are there)."""
    h, w, count = cost.shape
    bufs = np.empty((2, 3, w, count), np.float32)
    mins = np.empty((2, 3, w), np.float32)
    y0 = 0 if dy > 0 else h - 1
    for j in nb.prange(chunks):
        for x in range(j * w // chunks, (j + 1) * w // chunks):
            m = np.float32(np.inf)
            for d in range(count):
                m = min(m, cost[y0, x, d])
                out[y0, x, d] += 3.0 * cost[y0, x, d]
            for k in range(3):
                for d in range(count):
                    bufs[0, k, x, d] = cost[y0, x, d]
                mins[0, k, x] = m
    for i in range(1, h):
        y = y0 + dy * i
        p, q = (i - 1) % 2, i % 2
        for j in nb.prange(chunks):
            _vertical_row(
                cost,
                guide,
                p1,
                gaps,
                p2,
                alpha,
                floor,
                out,
                y,
                y - dy,
                j * w // chunks,
                (j + 1) * w // chunks,
                bufs[p],
                mins[p],
                bufs[q],
                mins[q],
            )


@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _columns_pass(cost, guide, p1, gaps, p2, alpha, floor, out, dx, assign):
    """Horizontal paths: every row on its own, x in order (dx = +1: left to right); `assign`: the path's values
    replace those in `out`, else they are added."""
    h, w, count = cost.shape
    for y in nb.prange(h):
        prev = np.empty(count, np.float32)
        row = np.empty(count, np.float32)
        x0 = 0 if dx > 0 else w - 1
        m = np.float32(np.inf)
        for d in range(count):
            prev[d] = cost[y, x0, d]
            out[y, x0, d] = prev[d] + (0.0 if assign else out[y, x0, d])
            m = min(m, prev[d])
        for i in range(1, w):
            x = x0 + dx * i
            pen = _penalty(p1, p2, alpha, floor, guide[y, x], guide[y, x - dx])
            m = _step(cost[y, x], prev, m, gaps, pen, row)  # type: ignore[assignment,arg-type]  # numba unifies float32 and float
            o = out[y, x]
            for d in range(count):
                o[d] = row[d] + (0.0 if assign else o[d])
                prev[d] = row[d]


def aggregate(
    cost_hwd: np.ndarray,
    guide: np.ndarray,
    p1: float,
    p2: float,
    alpha: float = 0.0,
    step_floor: float = 0.0,
    gaps: np.ndarray | None = None,
) -> np.ndarray:
    """Sum over the eight paths of the semi-global aggregation of `cost_hwd` (H, W, D), float32 (H, W, D).

    `cost_hwd` float32, or uint16 (the dense search's costs times `dense.COST_LEVELS`, penalties scaled alike:
    read as it is, not converted; at 20 MP a float32 copy would be another quarter of a gigabyte).

    `guide` (H, W) or (H, W, C) float32 image whose steps lower P2 (object boundaries; of a colour guide, the
    largest channel's step: two colours of one brightness still meet at an edge); `alpha` scales that effect
    (0: constant P2); steps up to `step_floor` (what noise makes) do not count. `gaps` (D - 1,): the penalty of a
    change between candidates d and d + 1, P1 where not given (unevenly spaced candidates charge more where two
    lie farther apart than one step of the search: `dense.search_candidates`)."""
    dtype = np.uint16 if cost_hwd.dtype == np.uint16 else np.float32
    cost = np.ascontiguousarray(cost_hwd, dtype=dtype)
    guide = np.ascontiguousarray(guide, dtype=np.float32)
    if guide.ndim == 2:
        guide = guide[..., None]
    out = np.empty(cost.shape, np.float32)  # every value written by the first pass
    a, q1, q2, f = np.float32(alpha), np.float32(p1), np.float32(p2), np.float32(step_floor)
    count = cost.shape[2]
    if gaps is None:
        g = np.full(max(count - 1, 1), q1, np.float32)
    else:
        g = np.ascontiguousarray(gaps, np.float32)
        if g.shape != (max(count - 1, 0),):
            raise ValueError(f"gaps: {g.shape} penalties for {count} candidates; one per pair of neighbours")
        g = g if count > 1 else np.zeros(1, np.float32)
    _columns_pass(cost, guide, q1, g, q2, a, f, out, 1, True)
    _columns_pass(cost, guide, q1, g, q2, a, f, out, -1, False)
    chunks = max(1, nb.get_num_threads())
    _vertical_sweep(cost, guide, q1, g, q2, a, f, out, 1, chunks)
    _vertical_sweep(cost, guide, q1, g, q2, a, f, out, -1, chunks)
    return out
