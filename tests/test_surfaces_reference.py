"""Superpixel surfaces (`processing.surfaces`) against references written out here: brute-force loops over
small label maps, numpy's least squares, and plane choices whose answer is known by construction."""

from __future__ import annotations

import numpy as np
import pytest

from mca.processing.surfaces import (
    SurfaceParams,
    boundary_edges,
    build_surfaces,
    fit_planes,
    fit_planes_at,
    interior_weights,
    plane_map,
    superpixels,
)


def _random_labels(h: int, w: int, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, n, (h // 3 + 1, w // 3 + 1))
    labels = np.repeat(np.repeat(coarse, 3, axis=0), 3, axis=1)[:h, :w]
    return np.unique(labels, return_inverse=True)[1].reshape(h, w).astype(np.int32)


def _brute_edges(labels: np.ndarray) -> list[tuple[int, int, float, float]]:
    h, w = labels.shape
    out = []
    for y in range(h):
        for x in range(w):
            if x + 1 < w and labels[y, x] != labels[y, x + 1]:
                a, b = sorted((int(labels[y, x]), int(labels[y, x + 1])))
                out.append((a, b, x + 0.5, float(y)))
            if y + 1 < h and labels[y, x] != labels[y + 1, x]:
                a, b = sorted((int(labels[y, x]), int(labels[y + 1, x])))
                out.append((a, b, float(x), y + 0.5))
    return sorted(out)


def test_boundary_edges_match_a_pixel_by_pixel_walk():
    labels = _random_labels(17, 23, 6, seed=1)
    lo, hi, px, py = boundary_edges(labels)
    got = sorted(zip(lo.tolist(), hi.tolist(), px.tolist(), py.tolist(), strict=True))
    assert got == _brute_edges(labels)
    assert lo.dtype == np.int64 and np.all(lo < hi)


def test_pairs_and_boundary_lengths_match_a_count_of_edges():
    labels = _random_labels(30, 36, 7, seed=2)
    n = int(labels.max()) + 1
    image = np.zeros(labels.shape + (3,), np.float32)
    surfaces = build_surfaces(image, np.zeros(labels.shape, np.float32), labels=labels)
    counts: dict[tuple[int, int], int] = {}
    for a, b, _, _ in _brute_edges(labels):
        counts[(a, b)] = counts.get((a, b), 0) + 1
    got = {(int(i), int(j)): int(c) for (i, j), c in zip(surfaces.pairs, surfaces.pair_lengths, strict=True)}
    assert got == counts
    assert surfaces.count == n
    assert np.array_equal(surfaces.areas, np.bincount(labels.ravel(), minlength=n))


def test_mean_colours_are_the_mean_of_each_superpixel():
    labels = _random_labels(24, 30, 5, seed=3)
    rng = np.random.default_rng(4)
    image = rng.random(labels.shape + (3,)).astype(np.float32)
    surfaces = build_surfaces(image, np.zeros(labels.shape, np.float32), labels=labels)
    for s in range(surfaces.count):
        assert np.allclose(surfaces.colours[s], image[labels == s].mean(axis=0), atol=1e-6)


def test_interior_weights_match_a_neighbourhood_check():
    labels = _random_labels(20, 25, 5, seed=5)
    for margin in (1, 2):
        weights = interior_weights(labels, margin)
        h, w = labels.shape
        for y in range(h):
            for x in range(w):
                window = labels[max(0, y - margin) : y + margin + 1, max(0, x - margin) : x + margin + 1]
                expected = 1.0 if np.all(window == labels[y, x]) else 0.05
                assert weights[y, x] == pytest.approx(expected), (margin, y, x)
    assert np.array_equal(interior_weights(labels, 0), np.ones(labels.shape, np.float32))


def test_plane_map_is_a_x_plus_b_y_plus_c():
    labels = _random_labels(9, 13, 4, seed=6)
    planes = np.array([[0.1, -0.2, 3.0], [-0.05, 0.3, 1.0], [0.0, 0.0, -2.0], [0.25, 0.125, 0.5]])
    got = plane_map(labels, planes[: int(labels.max()) + 1])
    for y in range(labels.shape[0]):
        for x in range(labels.shape[1]):
            a, b, c = planes[labels[y, x]]
            assert got[y, x] == pytest.approx(a * x + b * y + c, abs=1e-5)


def test_plane_fit_without_outliers_is_weighted_least_squares():
    """With no outliers the robust fit is the plain weighted least-squares plane (numpy's lstsq on
    sqrt-weighted rows), for every label, at every iteration count; a label without weight gets zeros."""
    rng = np.random.default_rng(7)
    k = 300
    lab = rng.integers(0, 3, k)
    xs = rng.uniform(0, 50, k)
    ys = rng.uniform(0, 40, k)
    truth = np.array([[0.03, -0.02, 2.0], [-0.01, 0.05, -1.0], [0.0, 0.0, 0.0]])
    values = truth[lab, 0] * xs + truth[lab, 1] * ys + truth[lab, 2] + rng.normal(0, 0.05, k)
    weights = rng.uniform(0.2, 1.0, k)
    weights[lab == 2] = 0.0
    for iterations in (1, 4):
        coef = fit_planes_at(lab, xs, ys, values, weights, 3, 1e-9, iterations)
        for s in (0, 1):
            m = lab == s
            sw = np.sqrt(weights[m])
            design = np.stack([xs[m], ys[m], np.ones(m.sum())], axis=1) * sw[:, None]
            ref = np.linalg.lstsq(design, values[m] * sw, rcond=None)[0]
            if iterations == 1:
                assert np.allclose(coef[s], ref, atol=1e-6)
            else:  # reweighting only touches points beyond 1.5 sigma: close to the plain fit
                assert np.allclose(coef[s], ref, atol=(2e-3, 2e-3, 0.05))
        assert np.array_equal(coef[2], np.zeros(3))


def test_plane_fit_ridge_pulls_the_slopes_toward_zero_about_the_centroid():
    """The ridge adds slope_ridge * (weight sum) to the slope terms of the normal equations: the exact
    solution of those regularised equations, written out here."""
    rng = np.random.default_rng(8)
    k = 80
    xs = rng.uniform(0, 20, k)
    ys = rng.uniform(0, 20, k)
    values = 0.2 * xs - 0.1 * ys + 1.0
    lab = np.zeros(k, np.int64)
    wt = np.ones(k)
    ridge = 5.0
    coef = fit_planes_at(lab, xs, ys, values, wt, 1, ridge, iterations=1)[0]
    design = np.stack([xs, ys, np.ones(k)], axis=1)
    normal = design.T @ design + np.diag([ridge * k, ridge * k, 1e-9])
    ref = np.linalg.solve(normal, design.T @ values)
    assert np.allclose(coef, ref, atol=1e-8)
    assert abs(coef[0]) < 0.2 and abs(coef[1]) < 0.1  # pulled toward fronto-parallel


def test_plane_fit_drops_far_outliers_and_keeps_the_plane():
    """One point in forty off by 100 px: after reweighting they are dropped (beyond 4 sigma + 1 px) and the fit
    is the clean plane; a single-pass fit is not."""
    h, w = 30, 40
    ys, xs = np.mgrid[0:h, 0:w]
    disparity = (0.05 * xs + 0.02 * ys + 2.0).astype(np.float32)
    corrupted = disparity.copy()
    corrupted[::5, ::8] += 100.0
    labels = np.zeros((h, w), np.int32)
    robust = fit_planes(labels, 1, corrupted, np.ones((h, w), np.float32), 0.0)[0]
    assert np.allclose(robust, (0.05, 0.02, 2.0), atol=(1e-4, 1e-4, 1e-3))
    plain = fit_planes(labels, 1, corrupted, np.ones((h, w), np.float32), 0.0, iterations=1)[0]
    assert abs(plain[2] - 2.0) > 1.0


def test_superpixels_are_dense_labels_of_about_the_asked_size():
    image = np.dstack([np.linspace(0, 1, 80, dtype=np.float32)[None, :].repeat(60, axis=0)] * 3)
    labels = superpixels(image, SurfaceParams(superpixel_px=200))
    n = int(labels.max()) + 1
    assert labels.dtype == np.int32 and labels.shape == (60, 80)
    assert np.array_equal(np.unique(labels), np.arange(n))
    assert 60 * 80 / 200 * 0.5 <= n <= 60 * 80 / 200 * 1.5
    tiny = superpixels(image[:8, :8], SurfaceParams(superpixel_px=10_000))  # at least 4 are asked for: a 2 x 2 grid
    assert int(tiny.max()) + 1 == 4


def _strips(h: int, w: int, n: int) -> np.ndarray:
    return np.repeat(np.arange(n, dtype=np.int32), w // n)[None, :].repeat(h, axis=0)


def test_without_smoothness_every_superpixel_keeps_its_own_plane():
    h, w, n = 20, 60, 6
    labels = _strips(h, w, n)
    rng = np.random.default_rng(10)
    disparity = (labels + rng.normal(0, 0.01, labels.shape)).astype(np.float32)
    image = np.full((h, w, 3), 0.5, np.float32)
    surfaces = build_surfaces(image, disparity, SurfaceParams(smoothness=0.0, interior_px=0), labels=labels)
    assert np.array_equal(surfaces.planes, surfaces.fitted)
    assert np.allclose(surfaces.fitted[:, 2], np.arange(n), atol=0.02)


def test_a_textureless_strip_takes_a_plane_from_its_rings_only():
    """Strips 0..6 side by side, all the same colour, disparity 5 everywhere except in strip 3 (no texture: the
    dense disparity there reads 0). With one ring strip 3 chooses among its own plane and its two neighbours';
    the neighbours' plane (5) wins. Strip 0 is three rings away from strip 3: its candidates never include 3's."""
    h, w, n = 20, 70, 7
    labels = _strips(h, w, n)
    disparity = np.full((h, w), 5.0, np.float32)
    disparity[labels == 3] = 0.0
    evidence = np.ones((h, w), np.float32)
    evidence[labels == 3] = 0.02
    image = np.full((h, w, 3), 0.5, np.float32)
    for rings in (1, 2):
        surfaces = build_surfaces(
            image, disparity, SurfaceParams(rings=rings, interior_px=0), labels=labels, evidence=evidence
        )
        assert np.allclose(surfaces.fitted[3], (0, 0, 0), atol=1e-6)
        assert np.allclose(surfaces.planes[:, 2], 5.0, atol=1e-4)


def test_a_weak_superpixel_does_not_drag_its_strong_neighbours():
    """A strong strip beside a weak one with a wrong plane: the strong strip is visited first and the weak one
    has no say yet, so the strong strip keeps its plane even with a large smoothness; the weak one follows."""
    h, w = 20, 40
    labels = _strips(h, w, 2)
    disparity = np.where(labels == 0, 4.0, 0.0).astype(np.float32)
    evidence = np.where(labels == 0, 0.5, 0.05).astype(np.float32)
    image = np.full((h, w, 3), 0.5, np.float32)
    surfaces = build_surfaces(
        image, disparity, SurfaceParams(smoothness=50.0, interior_px=0), labels=labels, evidence=evidence
    )
    assert np.allclose(surfaces.planes[:, 2], 4.0, atol=1e-4)


def test_a_colour_edge_lets_a_depth_jump_stand():
    """Two strips at 2 and 6 px with full evidence. Same colour: a strong smoothness makes one take the other's
    plane. Very different colour (black against white, similarity exp(-3 / 0.09)): each keeps its own."""
    h, w = 20, 40
    labels = _strips(h, w, 2)
    disparity = np.where(labels == 0, 2.0, 6.0).astype(np.float32)
    params = SurfaceParams(smoothness=50.0, interior_px=0)
    grey = np.full((h, w, 3), 0.5, np.float32)
    same = build_surfaces(grey, disparity, params, labels=labels)
    assert same.planes[0, 2] == pytest.approx(same.planes[1, 2], abs=1e-6)
    contrast = np.where((labels == 0)[..., None], 0.0, 1.0).astype(np.float32) * np.ones(3, np.float32)
    apart = build_surfaces(contrast, disparity, params, labels=labels)
    assert np.allclose(apart.planes[:, 2], (2.0, 6.0), atol=1e-4)


def test_the_jump_penalty_is_clipped():
    """A weak strip (evidence 0.2) at 0 px beside a strong one at 10 px. The data cost of taking the neighbour's
    plane is evidence x area x min(10, clip); the smoothness cost of keeping its own is lam x length x
    min(jump_clip, 10). With jump_clip 2 and data_clip 20 keeping wins; with jump_clip 20 the neighbour's wins."""
    h, w = 10, 20
    labels = _strips(h, w, 2)
    disparity = np.where(labels == 0, 10.0, 0.0).astype(np.float32)
    evidence = np.where(labels == 0, 1.0, 0.2).astype(np.float32)
    image = np.full((h, w, 3), 0.5, np.float32)
    # strip 1: area 100, data cost of plane 10 = 0.2 * 100 * 10 = 200; smoothness = lam * 10 * min(jc, 10)
    kept = build_surfaces(
        image,
        disparity,
        SurfaceParams(smoothness=5.0, jump_clip_px=2.0, data_clip_px=20.0, interior_px=0),
        labels=labels,
        evidence=evidence,
    )  # keep: 5 * 10 * 2 = 100 < 200
    assert np.allclose(kept.planes[:, 2], (10.0, 0.0), atol=1e-4)
    moved = build_surfaces(
        image,
        disparity,
        SurfaceParams(smoothness=5.0, jump_clip_px=20.0, data_clip_px=20.0, interior_px=0),
        labels=labels,
        evidence=evidence,
    )  # keep: 5 * 10 * 10 = 500 > 200
    assert np.allclose(moved.planes[:, 2], (10.0, 10.0), atol=1e-4)
    clipped = build_surfaces(
        image,
        disparity,
        SurfaceParams(smoothness=5.0, jump_clip_px=20.0, data_clip_px=1.0, interior_px=0),
        labels=labels,
        evidence=evidence,
    )  # with data clipped at 1 px the strong strip's cost of plane 0 is 1 x 100 x 1 = 100 < 5 x 10 x 10 = 500:
    # the strong strip (visited first) gives way to its neighbour's plane, and both end at 0
    assert np.allclose(clipped.planes[:, 2], (0.0, 0.0), atol=1e-4)


def test_residuals_within_one_and_a_half_sigmas_keep_their_full_weight():
    """A plane plus a skewed error (0 on two pixels in three, +6 px on the third): the plain fit is off by +2 and
    its residuals (-2, +4) lie within 1.5 sigmas (sigma = the residual spread, 2.8 px), so the robust fit keeps
    every weight and is the plain least-squares fit (numpy's lstsq)."""
    h, w = 30, 30
    ys, xs = np.mgrid[0:h, 0:w]
    values = 0.03 * xs - 0.02 * ys + 1.0 + np.where((xs + ys) % 3 == 0, 6.0, 0.0)
    labels = np.zeros((h, w), np.int32)
    robust = fit_planes(labels, 1, values, np.ones((h, w)), 1e-9)[0]
    design = np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)], axis=1).astype(np.float64)
    plain = np.linalg.lstsq(design, values.ravel(), rcond=None)[0]
    assert plain[2] == pytest.approx(3.0, abs=0.1)
    assert np.allclose(robust, plain, atol=1e-6)


def test_a_surface_slanted_along_x_keeps_its_slope():
    """Two textured squares of one colour side by side: one slanted along x (1 .. 1.95 px), one flat at 1.5 px.
    Each keeps its own plane: the data term measures the slanted plane at each pixel's own column."""
    h, w = 20, 40
    labels = _strips(h, w, 2)
    xs = np.arange(w, dtype=np.float32)[None, :].repeat(h, axis=0)
    disparity = np.where(labels == 0, 0.05 * xs + 1.0, 1.5).astype(np.float32)
    image = np.full((h, w, 3), 0.5, np.float32)
    surfaces = build_surfaces(image, disparity, SurfaceParams(), labels=labels)
    assert np.allclose(surfaces.planes[0], (0.05, 0.0, 1.0), atol=(2e-4, 2e-4, 1e-3))  # the small slope ridge
    assert np.allclose(surfaces.planes[1], (0.0, 0.0, 1.5), atol=1e-4)


def test_the_jump_between_planes_is_measured_on_their_shared_boundary():
    """A weak square (evidence 0.12) above a strong one, planes P = 0.1 y (the weak one's own) and Q = 2.5 (the
    strong one's). On their boundary (y = 19.5) P - Q = -0.55 px: keeping P costs lam x 20 x 0.55 = 33, taking Q
    costs 0.12 x sum min(|0.1 y - 2.5|, 2) = 0.12 x 590 = 71; the weak square keeps its own plane. (Measured
    anywhere else, e.g. with y's sign flipped, the jump is clipped at 2 px: 120 > 71, and it would take Q.)"""
    h, w = 40, 20
    labels = (np.arange(h)[:, None] >= 20).astype(np.int32).repeat(w, axis=1)
    ys = np.arange(h, dtype=np.float32)[:, None].repeat(w, axis=1)
    disparity = np.where(labels == 0, 0.1 * ys, 2.5).astype(np.float32)
    evidence = np.where(labels == 0, 0.12, 1.0).astype(np.float32)
    image = np.full((h, w, 3), 0.5, np.float32)
    surfaces = build_surfaces(image, disparity, SurfaceParams(), labels=labels, evidence=evidence)
    assert np.allclose(surfaces.planes[0], (0.0, 0.1, 0.0), atol=(2e-4, 2e-4, 1e-3))  # the small slope ridge
    assert np.allclose(surfaces.planes[1], (0.0, 0.0, 2.5), atol=1e-4)


def test_the_default_jump_clip_is_two_pixels():
    """A weak strip (evidence 0.075) at 0 px beside a strong one at 10 px, data clipped at 20 px. Keeping its own
    plane costs lam x 10 x min(tau, 10) = 60 with the documented tau of 2 px; taking the neighbour's costs
    0.075 x 100 x 10 = 75: it keeps its own (with tau = 3 px, 90 > 75, it would not)."""
    h, w = 10, 20
    labels = _strips(h, w, 2)
    disparity = np.where(labels == 0, 10.0, 0.0).astype(np.float32)
    evidence = np.where(labels == 0, 1.0, 0.075).astype(np.float32)
    image = np.full((h, w, 3), 0.5, np.float32)
    surfaces = build_surfaces(image, disparity, SurfaceParams(data_clip_px=20.0), labels=labels, evidence=evidence)
    assert np.allclose(surfaces.planes[:, 2], (10.0, 0.0), atol=1e-4)
