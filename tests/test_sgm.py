"""Semi-global aggregation (`processing.sgm`) against the recurrence written out path by path in plain Python."""

from __future__ import annotations

import numpy as np
import pytest

from mca.processing.sgm import aggregate

DIRECTIONS = [(0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)]


def reference(
    cost: np.ndarray,
    guide: np.ndarray,
    p1: float,
    p2: float,
    alpha: float,
    floor: float = 0.0,
    gaps: np.ndarray | None = None,
) -> np.ndarray:
    """Hirschmueller's recurrence along each of the eight directions (dy, dx), summed; a colour guide's step is
    its largest channel's, less `floor`; `gaps[d]` the penalty between candidates d and d + 1 (else P1)."""
    h, w, count = cost.shape
    gaps = np.full(max(count - 1, 0), p1) if gaps is None else gaps
    guide = guide.reshape(h, w, -1)
    total = np.zeros_like(cost, dtype=np.float64)
    for dy, dx in DIRECTIONS:
        path = np.zeros_like(total)
        ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
        xs = list(range(w)) if dx >= 0 else list(range(w - 1, -1, -1))
        for y in ys:
            for x in xs:
                py, px = y - dy, x - dx
                if not (0 <= py < h and 0 <= px < w):
                    path[y, x] = cost[y, x]
                    continue
                prev = path[py, px]
                best = prev.min()
                step = max(float(np.max(np.abs(guide[y, x] - guide[py, px]))) - floor, 0.0)
                pen2 = max(p2 / (1 + alpha * step), 1.5 * p1)
                for d in range(count):
                    options = [prev[d], best + pen2]
                    if d > 0:
                        options.append(prev[d - 1] + gaps[d - 1])
                    if d < count - 1:
                        options.append(prev[d + 1] + gaps[d])
                    path[y, x, d] = cost[y, x, d] + min(options) - best
        total += path
    return total


def test_eight_paths_equal_the_written_out_recurrence():
    rng = np.random.default_rng(0)
    cost = rng.random((7, 9, 5)).astype(np.float32)
    guide = rng.random((7, 9)).astype(np.float32)
    for p1, p2, alpha in ((0.1, 0.8, 0.0), (0.3, 2.0, 3.0)):
        got = aggregate(cost, guide, p1, p2, alpha)
        assert np.allclose(got, reference(cost, guide, p1, p2, alpha), atol=1e-4)


def test_every_candidate_count_equals_the_recurrence_and_integer_costs_come_out_exact():
    """The step runs its inner candidates over slices and takes its minimum in eight chains with a tail: counts
    of 1 to 19 cross every split. Integer costs and penalties (the dense search's uint16 volume) are exact in
    float32, so there the sums equal the float64 recurrence exactly."""
    rng = np.random.default_rng(11)
    guide = rng.random((4, 5)).astype(np.float32)
    for count in range(1, 20):
        cost = rng.random((4, 5, count)).astype(np.float32)
        got = aggregate(cost, guide, 0.1, 0.8)
        assert np.allclose(got, reference(cost, guide, 0.1, 0.8, 0.0), atol=1e-4), count
        levels = np.floor(rng.random((4, 5, count)) * 65535.0).astype(np.uint16)
        exact = aggregate(levels, guide, 13107.0, 196605.0)
        assert np.array_equal(exact, reference(levels.astype(np.float64), guide, 13107.0, 196605.0, 0.0)), count


def test_penalties_per_pair_of_neighbours_equal_the_recurrence_and_p1_everywhere_is_the_default():
    """Unevenly spaced candidates (`dense.search_candidates`) charge a change between neighbours more than a step
    apart as a jump: P2 there, P1 between the fine ones. Every count from 1 to 12, integer costs, exact."""
    rng = np.random.default_rng(17)
    guide = rng.random((5, 6, 3)).astype(np.float32)
    p1, p2 = 13107.0, 196605.0
    for count in range(1, 13):
        levels = np.floor(rng.random((5, 6, count)) * 65535.0).astype(np.uint16)
        gaps = np.where(rng.random(max(count - 1, 0)) < 0.4, p2, p1)
        got = aggregate(levels, guide, p1, p2, 2.0, 0.05, gaps)
        expected = reference(levels.astype(np.float64), guide, p1, p2, 2.0, 0.05, gaps)
        assert np.allclose(got, expected, rtol=1e-6), count
        even = aggregate(levels, guide, p1, p2, 2.0, 0.05, np.full(max(count - 1, 0), p1))
        np.testing.assert_array_equal(even, aggregate(levels, guide, p1, p2, 2.0, 0.05))


def test_gaps_of_the_wrong_length_are_refused():
    cost = np.zeros((3, 4, 5), np.float32)
    with pytest.raises(ValueError, match="gaps"):
        aggregate(cost, np.zeros((3, 4), np.float32), 0.1, 0.8, gaps=np.zeros(5))


def test_a_uint16_volume_is_read_as_it_is_with_the_penalties_scaled_alike():
    """The dense search hands the aggregation its costs times 65535 as uint16 (`dense.COST_LEVELS`), penalties
    scaled alike: the recurrence over the integer costs, in floating point (levels near 65535 plus a penalty
    would wrap in uint16 arithmetic)."""
    rng = np.random.default_rng(5)
    levels = 65535.0
    cost = np.floor(rng.random((7, 9, 5)) * levels + 0.5).astype(np.uint16)
    cost[0, :, 0] = 65535  # the top of the range, where uint16 arithmetic would wrap
    guide = rng.random((7, 9)).astype(np.float32)
    got = aggregate(cost, guide, 0.3 * levels, 2.0 * levels, 3.0)
    assert got.dtype == np.float32
    expected = reference(cost.astype(np.float64), guide, 0.3 * levels, 2.0 * levels, 3.0)
    assert np.allclose(got, expected, rtol=1e-6, atol=0.05)


def test_a_colour_guide_counts_its_largest_channel_step_less_the_noise_floor():
    rng = np.random.default_rng(3)
    cost = rng.random((7, 9, 5)).astype(np.float32)
    colour = rng.random((7, 9, 3)).astype(np.float32)
    for floor in (0.0, 0.3):
        got = aggregate(cost, colour, 0.3, 2.0, 5.0, floor)
        assert np.allclose(got, reference(cost, colour, 0.3, 2.0, 5.0, floor), atol=1e-4)
    # two colours of one brightness: the grey guide sees no edge, the colour guide does
    grey_of_colour = np.repeat(colour.mean(axis=2, keepdims=True), 3, axis=2)
    assert not np.allclose(aggregate(cost, colour, 0.3, 2.0, 5.0), aggregate(cost, grey_of_colour, 0.3, 2.0, 5.0))


def test_aggregation_recovers_two_surfaces_from_sparse_evidence():
    """Each pixel's true label is cheaper than the rest on only 30 % of the pixels: the winner of the raw cost
    is mostly wrong, the aggregated one is right almost everywhere."""
    rng = np.random.default_rng(1)
    h, w, count = 60, 80, 20
    truth = np.full((h, w), 5)
    truth[:, 40:] = 14
    cost = rng.random((h, w, count)).astype(np.float32)
    hit = rng.random((h, w)) < 0.3
    yy, xx = np.nonzero(hit)
    cost[yy, xx, truth[yy, xx]] -= 0.8
    raw = np.mean(cost.argmin(axis=2) == truth)
    aggregated = np.mean(aggregate(cost, np.zeros((h, w), np.float32), 2.0, 8.0).argmin(axis=2) == truth)
    assert raw < 0.4 and aggregated > 0.98
