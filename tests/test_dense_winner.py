"""The dense search's winner (processing/dense.py) on cost curves whose answer is known in closed form: a parabola
through the lowest cost and its two neighbours finds the vertex of a quadratic cost exactly, and the confidence is
(best cost more than two steps away - winner's cost) / jump cost, clipped to [0, 1]."""

from __future__ import annotations

import numpy as np
import pytest
from mca_scenes import render_layers, texture

from mca.devices.profiles import load_profile
from mca.processing.dense import _winner, candidate_disparities, estimate_dense


def _volume(curves: list[np.ndarray]) -> np.ndarray:
    return np.ascontiguousarray(np.array(curves, np.float32)[None, :, :])  # (1, W, D)


@pytest.mark.parametrize("truth_px", [0.3, -0.62, 0.0, 1.1, -1.1])  # -1.1: the winner is the second candidate
def test_the_vertex_of_a_quadratic_cost_is_found_between_candidates(truth_px: float) -> None:
    candidates = candidate_disparities((-1.5, 1.5), 0.5)  # -1.5, -1.0, ..., 1.5
    curve = (candidates - truth_px) ** 2
    disparity, confidence = _winner(_volume([curve]), candidates, 10.0)
    assert disparity[0, 0] == pytest.approx(truth_px, abs=1e-5)
    best = int(np.argmin(curve))
    far = [curve[d] for d in range(len(curve)) if abs(d - best) > 2]
    assert confidence[0, 0] == pytest.approx(min(max((min(far) - curve[best]) / 10.0, 0.0), 1.0), rel=1e-5)


def test_a_winner_at_the_end_of_the_range_and_a_flat_curve_take_the_candidate_itself() -> None:
    candidates = candidate_disparities((-1.0, 1.0), 0.25)
    rising = (candidates + 1.3) ** 2  # lowest at the first candidate: no neighbour on its left
    falling = (candidates - 1.4) ** 2  # lowest at the last candidate
    flat = np.full_like(candidates, 0.7)
    disparity, confidence = _winner(_volume([rising, falling, flat]), candidates, 1e6)
    np.testing.assert_allclose(disparity[0], [candidates[0], candidates[-1], candidates[0]], atol=1e-6)
    assert confidence[0, 2] == 0.0  # nothing stands out
    assert 0.0 < confidence[0, 0] < 1e-5  # far candidates cost more, relative to a huge jump cost


@pytest.mark.parametrize("vertex", [2.3, 3.6, 4.5])  # between the coarse tail's candidates, and on either side
def test_on_uneven_candidates_the_offset_is_taken_with_the_spacing_on_its_side(vertex: float) -> None:
    """`search_candidates` spaces the tails of a wide range coarser than its core: a cost quadratic in the
    candidate's index has its vertex `vertex` indices in, and the winner lies that far along the candidates,
    linearly between the two around it."""
    candidates = np.array([-6.0, -4.0, -2.0, -1.5, -1.0, -0.5, 0.0, 2.0, 4.0])
    index = np.arange(len(candidates), dtype=np.float64)
    disparity, _ = _winner(_volume([(index - vertex) ** 2]), candidates, 10.0)
    below = int(np.floor(vertex))
    expected = candidates[below] + (vertex - below) * (candidates[below + 1] - candidates[below])
    assert disparity[0, 0] == pytest.approx(expected, abs=1e-5)


def test_the_confidence_is_clipped_and_zero_without_a_far_candidate() -> None:
    candidates = candidate_disparities((-1.0, 1.0), 0.5)  # five candidates
    curve = (candidates - 0.0) ** 2  # best in the middle: no candidate more than two steps away
    _, confidence = _winner(_volume([curve]), candidates, 0.01)
    assert confidence[0, 0] == 0.0
    wide = candidate_disparities((-3.0, 3.0), 0.5)
    _, confidence = _winner(_volume([(wide - 0.1) ** 2]), wide, 0.01)  # far costs >> jump cost
    assert confidence[0, 0] == 1.0
    single = np.array([0.5])
    disparity, confidence = _winner(_volume([np.array([2.0])]), single, 1.0)
    assert (disparity[0, 0], confidence[0, 0]) == (0.5, 0.0)


def test_a_textured_surface_is_found_with_confidence_and_a_flat_image_has_none() -> None:
    aperture = load_profile("paper-70d").aperture
    shape = (96, 120)
    image = render_layers([(texture(shape, 1), np.ones(shape, np.float32), 1.7)], shape, aperture)
    result = estimate_dense(image, aperture, (-8.0, 8.0))
    core = (slice(20, -20), slice(20, -20))
    assert abs(float(np.median(result.disparity_px[core])) - 1.7) < 0.1
    assert float(np.mean(result.confidence[core] > 0.05)) > 0.9
    assert float(result.confidence.min()) >= 0.0 and float(result.confidence.max()) <= 1.0
    flat = estimate_dense(np.full((*shape, 3), 0.4, np.float32), aperture, (-8.0, 8.0))
    assert float(flat.confidence.max()) == 0.0
