"""Boundary snap (`processing.boundaries`) on hand-built images whose right outline is known by construction:
flat colours at zero disparity (every channel aligned, so a pixel's colour is the colour of its side), and
the appearance transform in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.processing.boundaries import BoundaryParams, _appearance, _dilate, snap_boundaries

APERTURE = load_profile("paper-70d").aperture
RED = (0.6, 0.2, 0.1)
BLUE = (0.1, 0.25, 0.7)
INNER = np.s_[10:50]  # rows more than half a window from the image's top and bottom


def two_colours(shape=(60, 80), edge_x=40):
    planes = np.empty(shape + (3,), np.float32)
    planes[:, :edge_x] = RED
    planes[:, edge_x:] = BLUE
    truth = np.where(np.arange(shape[1])[None, :] < edge_x, 1, 2).repeat(shape[0], axis=0).astype(np.int32)
    models = {1: np.zeros(shape, np.float32), 2: np.zeros(shape, np.float32)}
    return planes, truth, models


def test_appearance_is_chromaticity_and_log_luminance():
    rng = np.random.default_rng(1)
    linear = rng.uniform(0.0, 2.0, (4, 5, 3)).astype(np.float32)
    linear[0, 0] = (0.0, 0.0, 0.0)
    white = 2.0
    got = _appearance(linear, white)
    rgb = np.maximum(linear / white, 1e-3)
    total = rgb.sum(axis=2)
    assert np.allclose(got[..., 0], rgb[..., 0] / total, atol=1e-6)
    assert np.allclose(got[..., 1], rgb[..., 2] / total, atol=1e-6)
    assert np.allclose(got[..., 2], 0.1 * np.log(total), atol=1e-6)
    assert np.allclose(got[0, 0], (1 / 3, 1 / 3, 0.1 * np.log(3e-3)), atol=1e-6)
    # shading (a scale of all three channels) moves the last component only
    shaded = _appearance(linear * np.float32(0.5), white)
    assert np.allclose(shaded[1:, :, :2], got[1:, :, :2], atol=1e-5)


def test_dilate_reaches_the_radius_along_the_axes_but_not_the_corners():
    mask = np.zeros((21, 21), bool)
    mask[10, 10] = True
    for radius in (1, 3, 5):
        grown = _dilate(mask, radius)
        ys, xs = np.nonzero(grown)
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):  # symmetric: the radius in all four directions
            assert grown[10 + dy * radius, 10 + dx * radius]
            assert not grown[10 + dy * (radius + 1), 10 + dx * (radius + 1)]
        assert not grown[10 + radius, 10 + radius]  # an ellipse, not a square
        assert np.all(np.hypot(ys - 10, xs - 10) <= radius + 0.5)


@pytest.mark.parametrize("drawn_x", [37, 43])
def test_a_boundary_three_pixels_off_moves_exactly_onto_the_colour_edge(drawn_x):
    planes, truth, models = two_colours()
    drawn = np.where(np.arange(80)[None, :] < drawn_x, 1, 2).repeat(60, axis=0).astype(np.int32)
    snapped = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams())
    # away from the image's top and bottom (where a region's window holds fewer pixels) the outline is exact
    assert np.array_equal(snapped[INNER], truth[INNER])
    assert snapped.dtype == np.int32
    assert not np.array_equal(drawn, truth)  # the input is left as it was


def test_a_boundary_beyond_the_band_cannot_reach_the_edge():
    """The drawn boundary 6 px off (region 1 reaches into the blue up to x = 45) with a band of 2 px: one pass
    gives the blue pixels within the band (x = 44, 45) to region 2 and cannot touch those beyond it (x = 40..43);
    more passes walk the boundary onto the edge."""
    planes, truth, models = two_colours()
    drawn = np.where(np.arange(80)[None, :] < 46, 1, 2).repeat(60, axis=0).astype(np.int32)
    snapped = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams(band_px=2, passes=1))
    assert np.all(snapped[:, :40] == 1) and np.all(snapped[:, 46:] == 2)
    assert np.all(snapped[INNER, 44:46] == 2)
    assert np.all(snapped[:, 40:44] == 1)  # beyond the band: untouched
    more = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams(band_px=2, passes=4))
    assert np.array_equal(more[INNER], truth[INNER])


def test_no_passes_or_no_boundary_leave_the_labels_as_they_are():
    planes, _truth, models = two_colours()
    drawn = np.where(np.arange(80)[None, :] < 43, 1, 2).repeat(60, axis=0).astype(np.int32)
    assert np.array_equal(snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams(passes=0)), drawn)
    one = np.ones((60, 80), np.int32)
    assert np.array_equal(snap_boundaries(planes, APERTURE, one, {1: models[1]}, BoundaryParams()), one)


def test_a_region_without_a_model_takes_no_pixels():
    """Only regions with a model compete: with region 2's model missing, region 1 never loses a pixel to 2 (and,
    alone in the competition, takes the band's pixels of region 2, but never all of them)."""
    planes, _truth, models = two_colours()
    drawn = np.where(np.arange(80)[None, :] < 37, 1, 2).repeat(60, axis=0).astype(np.int32)
    snapped = snap_boundaries(planes, APERTURE, drawn, {1: models[1]}, BoundaryParams())
    assert np.all(snapped[drawn == 1] == 1)
    assert np.all(snapped[INNER, 37:40] == 1)
    assert np.all(snapped[:, 45:] == 2)


def test_a_textured_region_accepts_its_spread_of_colours():
    """Region 1 is a texture (random grey levels between 0.2 and 0.8, shading only), region 2 flat blue. Pixels
    of the texture drawn into region 2 go back to region 1: their shading is within region 1's spread, far
    outside the flat region's. (The score is blurred over 3 x 3: the first blue column may go either way.)"""
    shape = (60, 80)
    rng = np.random.default_rng(5)
    planes, _truth, models = two_colours(shape)
    shade = rng.uniform(0.3, 1.0, (shape[0], 40)).astype(np.float32)
    planes[:, :40] = np.float32(0.5) * shade[..., None]
    drawn = np.where(np.arange(80)[None, :] < 37, 1, 2).repeat(60, axis=0).astype(np.int32)
    snapped = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams())
    assert np.all(snapped[INNER, :40] == 1) and np.all(snapped[:, 41:] == 2)


def test_boundary_params_are_frozen():
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        BoundaryParams().band_px = 1  # type: ignore[misc]


def test_a_region_whose_model_is_out_of_reach_is_passed_over_and_the_others_still_compete():
    """Region 1's model warps by far more than the image (1e4 px): it is not scored, and takes no pixels; region 2,
    after it in order, still is: the blue pixels drawn into region 1 go back to region 2."""
    planes, _truth, models = two_colours()
    drawn = np.where(np.arange(80)[None, :] < 43, 1, 2).repeat(60, axis=0).astype(np.int32)
    models[1] = np.full(drawn.shape, 1e4, np.float32)
    snapped = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams())
    assert np.all(snapped[drawn == 2] == 2)
    assert np.all(snapped[INNER, 40:43] == 2)


@pytest.mark.parametrize("drawn_y", [27, 33])
def test_a_horizontal_boundary_three_pixels_off_moves_onto_the_edge_out_to_both_sides(drawn_y):
    """Red above blue, the edge at y = 30, the drawn boundary 3 px off: the outline is exact away from the image's
    sides, and moves toward the edge in the first and last columns too (a region's window there holds fewer of its
    interior pixels, still enough to score)."""
    planes, _truth, models = two_colours((60, 80), 80)
    planes[30:] = BLUE
    truth = np.where(np.arange(60)[:, None] < 30, 1, 2).repeat(80, axis=1).astype(np.int32)
    drawn = np.where(np.arange(60)[:, None] < drawn_y, 1, 2).repeat(80, axis=1).astype(np.int32)
    snapped = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams())
    assert np.array_equal(snapped[:, 5:75], truth[:, 5:75])
    for x in (0, 79):
        assert np.sum(snapped[:, x] != truth[:, x]) < np.sum(drawn[:, x] != truth[:, x]), x


def test_a_regions_model_beyond_its_reach_does_not_matter():
    """A region's model is read over its reach only: band + half a window + 1 px (4 + 10 + 1 = 15 px) around it.
    Region 2 (x >= 43, drawn 3 px short of the blue) has a wild model value (1e4 px) 16 px from it: it still
    competes and takes back its blue pixels, as with no wild value at all. (One pass: the reach is measured around
    the region as it stands at the start of a pass.)"""
    planes, _truth, models = two_colours()
    drawn = np.where(np.arange(80)[None, :] < 43, 1, 2).repeat(60, axis=0).astype(np.int32)
    calm = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams(passes=1))
    assert np.all(calm[INNER, 41:43] == 2)
    models[2][:, 43 - 16] = 1e4
    snapped = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams(passes=1))
    assert np.array_equal(snapped, calm)
    models[2][:, 43 - 15] = 1e4  # within its reach: the region is passed over (its warp would leave the image)
    passed_over = snap_boundaries(planes, APERTURE, drawn, models, BoundaryParams(passes=1))
    assert np.all(passed_over[:, 40:43] == 1)
