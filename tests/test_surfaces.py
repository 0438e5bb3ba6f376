"""Superpixel surfaces (`processing.surfaces`): robust plane fits and planes carried across texture-less parts."""

from __future__ import annotations

import numpy as np

from mca.processing.surfaces import SurfaceParams, build_surfaces, fit_planes, interior_weights, plane_map


def test_robust_plane_fit_ignores_outliers():
    h, w = 60, 80
    ys, xs = np.mgrid[0:h, 0:w]
    disparity = (0.02 * xs - 0.01 * ys + 1.5).astype(np.float32)
    labels = np.zeros((h, w), np.int32)
    labels[:, 40:] = 1
    disparity[:, 40:] = 4.0
    corrupted = disparity.copy()
    rng = np.random.default_rng(0)
    bad = rng.random((h, w)) < 0.15
    corrupted[bad] += rng.uniform(-5, 5, bad.sum()).astype(np.float32)
    planes = fit_planes(labels, 2, corrupted, np.ones((h, w), np.float32), 1e-4)
    assert np.allclose(planes[0], (0.02, -0.01, 1.5), atol=(4e-3, 4e-3, 0.1))
    assert np.allclose(planes[1], (0.0, 0.0, 4.0), atol=(4e-3, 4e-3, 0.1))
    assert np.allclose(plane_map(labels, planes)[:, :40], disparity[:, :40], atol=0.15)


def test_interior_weights_are_low_at_superpixel_edges():
    labels = np.zeros((20, 20), np.int32)
    labels[:, 10:] = 1
    weights = interior_weights(labels, 2)
    assert weights[10, 9] < 0.1 and weights[10, 10] < 0.1 and weights[10, 3] == 1.0


def test_a_textureless_part_takes_the_plane_of_its_surface():
    """A grey card at 3 px on a dark wall at 8 px; the card's middle has no texture, so its dense disparity there
    is garbage (here: the wall's). Its superpixels share the card's colour: they take the card's plane."""
    h, w = 120, 160
    image = np.full((h, w, 3), 0.15, np.float32)
    image[30:90, 40:120] = 0.7
    disparity = np.full((h, w), 8.0, np.float32)
    disparity[30:90, 40:120] = 3.0
    disparity[45:75, 60:100] = 8.0  # the texture-less middle reads like the wall
    labels = np.zeros((h, w), np.int32)  # a grid of 20 x 20 superpixels, cut along the card
    labels[:] = (np.arange(h)[:, None] // 15) * 100 + (np.arange(w)[None, :] // 20)
    labels = np.unique(labels, return_inverse=True)[1].reshape(h, w).astype(np.int32)
    card = np.zeros((h, w), bool)
    card[30:90, 40:120] = True
    labels = np.where(card, labels + labels.max() + 1, labels)
    labels = np.unique(labels, return_inverse=True)[1].reshape(h, w).astype(np.int32)
    evidence = np.ones((h, w), np.float32)
    evidence[45:75, 60:100] = 0.02  # what the pipeline's texture evidence says there: nothing to see
    surfaces = build_surfaces(image, disparity, SurfaceParams(), labels=labels, evidence=evidence)
    result = surfaces.disparity()
    assert (
        float(np.median(result[45:75, 60:100])) == np.float32(3.0)
        or abs(float(np.median(result[45:75, 60:100])) - 3.0) < 0.2
    )
    assert abs(float(np.median(result[5:20, 5:30])) - 8.0) < 0.2


def test_surface_params_are_frozen():
    import dataclasses

    import pytest

    with pytest.raises(dataclasses.FrozenInstanceError):
        SurfaceParams().jump_clip_px = 1.0  # type: ignore[misc]


def test_a_surface_slanted_along_y_keeps_its_slope():
    """A textured floor whose disparity grows down the image (0.04 px per row) under a flat wall: every floor
    superpixel's chosen plane has the floor's slope along y and none along x."""
    h, w = 120, 160
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    rng = np.random.default_rng(3)
    image = np.clip(0.4 + 0.1 * rng.standard_normal((h, w, 3)), 0.05, 1.0).astype(np.float32)
    image[:40] = (0.2, 0.2, 0.6)
    disparity = np.where(ys < 40, 1.0, 2.0 + 0.04 * (ys - 40)).astype(np.float32)
    labels = ((ys // 20) * 8 + xs // 20).astype(np.int32)  # 20 x 20 superpixels, cut at the wall's edge
    surfaces = build_surfaces(image, disparity, SurfaceParams(), labels=labels)
    floor = np.unique(labels[50:, :])
    assert np.allclose(surfaces.planes[floor, 1], 0.04, atol=5e-3)
    assert np.allclose(surfaces.planes[floor, 0], 0.0, atol=5e-3)
    result = surfaces.disparity()
    assert float(np.max(np.abs(result[45:, :] - disparity[45:, :]))) < 0.15
