"""`benchmarks/surface_floors.py`: the floors it prints are what they say (the truth picks among the candidates)."""

from __future__ import annotations

import numpy as np
import pytest
from tools import benchmark_module

from mca.processing.surfaces import Surfaces


def _three_strips() -> tuple[np.ndarray, np.ndarray]:
    """Superpixels 0 | 1 | 2 side by side (20 px wide each) and a truth of 2 px on 0 and 1, 8 px on 2."""
    labels = np.repeat(np.repeat(np.arange(3, dtype=np.int32), 20)[None, :], 12, axis=0)
    truth = np.where(labels < 2, 2.0, 8.0).astype(np.float32)
    return labels, truth


def test_the_best_candidate_is_the_neighbours_plane_where_the_own_fit_lies_between():
    """Superpixel 1's own fit says 5 px (between its neighbours, as beside an occluding edge); among its own plane
    and its neighbours' the truth's pick is superpixel 0's 2 px, which the chosen 5 px misses everywhere."""
    floors = benchmark_module("surface_floors")
    labels, truth = _three_strips()
    fitted = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 5.0], [0.0, 0.0, 8.0]])
    surfaces = Surfaces(
        labels, fitted.copy(), fitted, np.zeros((3, 3)), np.bincount(labels.ravel()), np.zeros((0, 2)), np.zeros(0)
    )
    best = floors.best_candidates(surfaces, truth, 1.0, rings=1, samples=10)
    assert np.allclose(best[:, 2], [2.0, 2.0, 8.0])
    chosen = fitted[labels][..., 2]
    assert floors.bad_1(chosen, truth) == pytest.approx(100.0 / 3)


def test_bad_1_counts_a_missing_estimate_as_bad_and_an_unknown_truth_not_at_all():
    floors = benchmark_module("surface_floors")
    truth = np.array([[1.0, 2.0, np.nan, 4.0]], np.float32)
    estimate = np.array([[1.5, np.nan, 0.0, 2.0]], np.float32)
    assert floors.bad_1(estimate, truth) == pytest.approx(100.0 * 2 / 3)
