"""The refinement's building blocks (`processing.refine`) against references written out here: per-label
quantiles with numpy, the nearest region within reach by a brute-force window scan, the weighted median by its
definition, the parabola vertex in closed form, and the occluder's contour warp pixel by pixel."""

from __future__ import annotations

import numpy as np
import pytest

from mca.processing.refine import (
    _apply,
    _median_by_label,
    _occluders_own_contours,
    _owners,
    _parabola_minima,
    _quantile_by_label,
    _robust_level,
    _robust_plane,
)


@pytest.mark.parametrize("q", [0.0, 0.5, 0.9, 1.0])
def test_quantile_by_label_is_numpy_lower_quantile(q):
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 5, 200)
    labels[labels == 3] = 4  # label 3 is empty
    values = rng.normal(0, 1, 200)
    got = _quantile_by_label(labels, values, 6, q)
    for s in range(6):
        v = values[labels == s]
        if v.size == 0:
            assert got[s] == np.inf
        else:
            assert got[s] == np.quantile(v, q, method="lower")
    assert np.array_equal(_median_by_label(labels, values, 6), _quantile_by_label(labels, values, 6, 0.5))


@pytest.mark.parametrize("q", [0.0, 0.5, 0.9, 1.0])
def test_quantile_by_label_counts_nan_as_the_largest_value(q):
    """A value that is NaN ranks last, as np.sort puts it: below the top rank the quantile is a number."""
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 3, 300)
    values = rng.normal(0, 1, 300)
    values[rng.choice(300, 20, replace=False)] = np.nan
    got = _quantile_by_label(labels, values, 3, q)
    for s in range(3):
        ranked = np.sort(values[labels == s])
        expected = ranked[int(np.floor(q * (ranked.size - 1)))]
        assert got[s] == expected or (np.isnan(got[s]) and np.isnan(expected))


def test_owners_are_the_nearest_region_within_reach():
    rng = np.random.default_rng(2)
    labels = np.repeat(np.repeat(rng.integers(0, 4, (6, 7)), 4, axis=0), 4, axis=1)
    levels = np.array([3.0, 1.0, 2.0, 0.5])  # region 3 is the nearest
    for reach in (1, 2):
        got = _owners(labels, levels, reach)
        h, w = labels.shape
        for y in range(h):
            for x in range(w):
                window = labels[max(0, y - reach) : y + reach + 1, max(0, x - reach) : x + reach + 1]
                assert got[y, x] == window.ravel()[np.argmin(levels[window.ravel()])], (reach, y, x)


def test_owners_break_level_ties_by_region_order():
    labels = np.array([[0, 0, 1, 1]] * 3)
    got = _owners(labels, np.array([1.0, 1.0]), 1)
    assert np.array_equal(got, np.array([[0, 0, 0, 1]] * 3))


def test_weighted_median_by_its_definition():
    rng = np.random.default_rng(3)
    for _ in range(20):
        values = rng.normal(0, 1, 9)
        weights = rng.uniform(0.1, 1.0, 9)
        order = np.argsort(values)
        cumulative = np.cumsum(weights[order])
        # the smallest value whose cumulative weight reaches half the total
        expected = values[order][np.argmax(cumulative >= 0.5 * cumulative[-1])]
        assert _robust_level(values, weights) == expected
    assert _robust_level(np.array([5.0, -1.0, 2.0]), np.array([0.1, 0.1, 10.0])) == 2.0


def test_parabola_minima_in_closed_form():
    offsets = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    vertex = np.array([-0.1, 0.3, 0.62])
    curves = 2.0 * (offsets[None, :] - vertex[:, None]) ** 2 + 1.0
    minima, curvature = _parabola_minima(curves, offsets)
    assert np.allclose(minima, vertex, atol=1e-12)
    assert np.allclose(curvature, 2.0 * 2.0 * 0.25)  # second difference of 2 t^2 with step 0.5
    # a minimum at an end: the vertex of the end triple, clipped to one step, and no curvature
    ramp = np.array([[0.0, 1.0, 3.0, 6.0, 10.0], [10.0, 6.0, 3.0, 1.0, 0.0]])
    minima, curvature = _parabola_minima(ramp, offsets)
    assert np.array_equal(curvature, np.zeros(2))
    assert minima[0] == pytest.approx(-0.5 + np.clip(0.5 * (0 - 3) / 1.0, -1, 1) * 0.5)
    assert minima[1] == pytest.approx(0.5 + np.clip(0.5 * (3 - 0) / 1.0, -1, 1) * 0.5)
    # flat: no curvature, the lowest sample itself
    flat_minima, flat_curvature = _parabola_minima(np.ones((1, 5)), offsets)
    assert flat_minima[0] == offsets[1] and flat_curvature[0] == 0.0


def test_apply_adds_each_regions_plane():
    labels = np.array([[0, 1, 1], [2, 2, 1]])
    current = np.arange(6, dtype=np.float32).reshape(2, 3)
    correction = np.array([[0.0, 0.0, 0.0], [0.5, -1.0, 2.0], [0.0, 0.25, -3.0]])
    xs = np.arange(3, dtype=np.float32)[None, :]
    ys = np.arange(2, dtype=np.float32)[:, None]
    got = _apply(current, labels, correction, xs, ys)
    for y in range(2):
        for x in range(3):
            a, b, c = correction[labels[y, x]]
            assert got[y, x] == pytest.approx(current[y, x] + a * x + b * y + c)


def test_pixels_near_an_occluder_are_warped_at_the_smallest_disparity_within_reach():
    rng = np.random.default_rng(4)
    maps = rng.uniform(-2, 2, (2, 12, 15)).astype(np.float32)
    near = np.zeros((12, 15), bool)
    near[3:7, 4:9] = True
    got = _occluders_own_contours(maps, near, 2)
    for k in range(2):
        for y in range(12):
            for x in range(15):
                if near[y, x]:
                    expected = maps[k, max(0, y - 2) : y + 3, max(0, x - 2) : x + 3].min()
                else:
                    expected = maps[k, y, x]
                assert got[k, y, x] == expected
    untouched = _occluders_own_contours(maps, np.zeros((12, 15), bool), 2)
    assert untouched is maps


@pytest.mark.parametrize("rows", [32, 64])
def test_a_curved_region_gets_a_slope_only_from_six_cells(rows):
    """A curved region model (not planar: a bowl 0.6 px deep) of the wrong slope over a slanted textured surface.
    One row of five 32 px cells: fewer than `min_cells_for_slope` (6) vote, the correction is one level (no
    slope). Two rows, ten cells: the correction has a slope, toward the truth's (0.01 - 0.004 = 0.006 px/px)."""
    from mca_scenes import render_layers, texture

    from mca.devices.profiles import load_profile
    from mca.processing.cost import stack_bands
    from mca.processing.features import feature_bands
    from mca.processing.refine import RefineParams, refine_regions

    aperture = load_profile("paper-70d").aperture
    shape = (rows, 160)
    _ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    truth = 0.01 * xs - 0.8
    image = render_layers([(texture(shape, 7, blur_px=2.5), np.ones(shape, np.float32), truth)], shape, aperture)
    labels = np.ones(shape, np.int32)
    model = (0.004 * xs - 0.5 + 0.6 * ((xs - 80) / 80) ** 2).astype(np.float32)
    result = refine_regions(stack_bands(feature_bands(image)), aperture, labels, model, RefineParams(cell_px=32))
    assert result.planes[1] is None  # curved: its surfaces get a correction
    slope = result.corrections[1][0]
    if rows == 32:
        assert result.corrections[1][:2] == (0.0, 0.0)
    else:
        assert 0.002 < slope < 0.01


@pytest.mark.parametrize("offset_px", [0.0, 37.5])
def test_the_correction_plane_ignores_a_heavy_outlier_cell(offset_px):
    """Cell minima on a known plane (0.001 x - 0.0005 y + 0.2) with 0.01 px noise, 80 cells of weights 0.1-1, and
    one cell at the region's edge 0.7 px off holding a third of the weight (an edge whose windows see two
    depths). The weighted least-squares plane tilts toward the outlier; the robust plane keeps the truth to
    a few ten-thousandths of a px per px, whatever the coordinates' origin."""
    rng = np.random.default_rng(3)
    xs = rng.uniform(0, 300, 80) + offset_px
    ys = rng.uniform(0, 260, 80) + offset_px
    truth = np.array([0.001, -0.0005, 0.2])
    minima = truth[0] * xs + truth[1] * ys + truth[2] + rng.normal(0, 0.01, 80)
    weights = rng.uniform(0.1, 1.0, 80)
    edge = int(np.argmax(xs))
    minima[edge] += 0.7
    weights[edge] = 0.5 * (weights.sum() - weights[edge])
    design = np.stack([xs, ys, np.ones_like(xs)], axis=1)
    sw = np.sqrt(weights)
    least_squares = np.linalg.lstsq(design * sw[:, None], minima * sw, rcond=None)[0]
    assert abs(least_squares[0] - truth[0]) > 1e-3  # the reference really is pulled off
    plane = _robust_plane(xs, ys, minima, weights)
    np.testing.assert_allclose(plane[:2], truth[:2], atol=3e-4)
    centre = (xs.mean(), ys.mean())
    level = plane[0] * centre[0] + plane[1] * centre[1] + plane[2]
    assert abs(level - (truth[0] * centre[0] + truth[1] * centre[1] + truth[2])) < 0.02
    # without outliers it is the weighted least-squares plane
    clean = truth[0] * xs + truth[1] * ys + truth[2] + rng.normal(0, 0.01, 80)
    reference = np.linalg.lstsq(design * sw[:, None], clean * sw, rcond=None)[0]
    np.testing.assert_allclose(_robust_plane(xs, ys, clean, weights), reference, atol=2e-6)
