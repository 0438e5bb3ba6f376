"""Boundary snap (`processing.boundaries`): region outlines that are a few pixels off move onto the object edges,
using each region's colour seen at its own disparity. Images from the tests' renderer (`tests/mca_scenes.py`)."""

from __future__ import annotations

import numpy as np
from mca_scenes import render_layers, texture

from mca.devices.profiles import load_profile
from mca.processing.boundaries import BoundaryParams, snap_boundaries

APERTURE = load_profile("paper-70d").aperture


def card_scene(card_d: float, wall_d: float):
    shape = (160, 220)
    card = np.zeros(shape, np.float32)
    card[40:120, 60:160] = 1
    image = render_layers(
        [
            (texture(shape, 21, (0.35, 0.45, 0.55), blur_px=2.0, contrast=0.25), np.ones(shape, np.float32), wall_d),
            (texture(shape, 22, (0.7, 0.4, 0.2), blur_px=2.0, contrast=0.25), card, card_d),
        ],
        shape,
        APERTURE,
    )
    truth = np.where(card > 0.5, 2, 1).astype(np.int32)
    models = {1: np.full(shape, wall_d, np.float32), 2: np.full(shape, card_d, np.float32)}
    return image, truth, models


def test_an_outline_three_pixels_too_large_moves_onto_the_edge():
    image, truth, models = card_scene(-1.0, 1.0)
    grown = np.ones_like(truth)
    grown[37:123, 57:163] = 2  # the card's region 3 px too large all round
    snapped = snap_boundaries(image, APERTURE, grown, models, BoundaryParams())
    before = int((grown != truth).sum())
    after = int((snapped != truth).sum())
    assert after < 0.25 * before, (before, after)


def test_an_outline_three_pixels_too_small_moves_onto_the_edge():
    image, truth, models = card_scene(0.5, 3.0)
    shrunk = np.ones_like(truth)
    shrunk[43:117, 63:157] = 2
    snapped = snap_boundaries(image, APERTURE, shrunk, models, BoundaryParams())
    before = int((shrunk != truth).sum())
    after = int((snapped != truth).sum())
    assert after < 0.35 * before, (before, after)


def test_pixels_far_from_a_boundary_never_change():
    image, truth, models = card_scene(-1.0, 1.0)
    snapped = snap_boundaries(image, APERTURE, truth, models, BoundaryParams(band_px=3))
    interior = np.ones_like(truth, bool)
    interior[33:127, 53:167] = False
    interior[47:113, 67:153] = True
    assert np.array_equal(snapped[interior], truth[interior])


def test_a_region_is_never_snapped_away():
    image, truth, models = card_scene(-1.0, 1.0)
    labels = truth.copy()
    labels[78:82, 100:104] = 3  # a 4 x 4 region inside the card, all of it within the band
    models[3] = np.full(truth.shape, 5.0, np.float32)
    snapped = snap_boundaries(image, APERTURE, labels, models, BoundaryParams())
    assert set(np.unique(snapped)) == {1, 2, 3}
