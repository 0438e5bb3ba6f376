"""The 2.1D sketch's rules one by one (`processing.sketch.build_sketch`), on surfaces built by hand.

Each test lays out superpixels on a small grid with chosen planes and colours, so the right regions, planes,
centroids and occlusions are known by construction; the adjacency (pairs and shared boundary lengths) is counted
here, pixel edge by pixel edge."""

from __future__ import annotations

import numpy as np
import pytest

from mca.processing.sketch import SketchParams, SketchRegion, _level_valley, build_sketch, plane_occlusions
from mca.processing.surfaces import Surfaces

GREY = (0.5, 0.5, 0.5)
RED = (0.9, 0.1, 0.1)


def surfaces_of(labels: np.ndarray, levels: dict[int, float], colours: dict[int, tuple[float, float, float]]):
    """Surfaces with fronto-parallel planes at `levels` and mean colours `colours` per superpixel label."""
    labels = labels.astype(np.int32)
    n = int(labels.max()) + 1
    planes = np.zeros((n, 3))
    for k, v in levels.items():
        planes[k, 2] = v
    edges: dict[tuple[int, int], int] = {}
    h, w = labels.shape
    for y in range(h):
        for x in range(w):
            for yy, xx in ((y, x + 1), (y + 1, x)):
                if yy < h and xx < w and labels[y, x] != labels[yy, xx]:
                    key = (min(labels[y, x], labels[yy, xx]), max(labels[y, x], labels[yy, xx]))
                    edges[key] = edges.get(key, 0) + 1
    keys = sorted(edges)
    return Surfaces(
        labels=labels,
        planes=planes,
        fitted=planes.copy(),
        colours=np.array([colours[k] for k in range(n)], np.float64),
        areas=np.bincount(labels.ravel(), minlength=n).astype(np.int64),
        pairs=np.array(keys, np.int64).reshape(-1, 2),
        pair_lengths=np.array([edges[k] for k in keys], np.int64),
    )


def sketch(surfaces: Surfaces, params: SketchParams = SketchParams(), confidence: float = 0.8):
    disparity = surfaces.disparity()
    return build_sketch(surfaces, disparity, np.full(disparity.shape, confidence, np.float32), params)


def halves(shape=(60, 80)) -> np.ndarray:
    labels = np.zeros(shape, np.int32)
    labels[:, shape[1] // 2 :] = 1
    return labels


@pytest.mark.parametrize(
    ("gap_px", "colour", "regions"),
    [
        (0.3, GREY, 1),  # continuous and alike: one object
        (0.9, GREY, 2),  # a step beyond continuity_px (0.6): two objects
        (0.3, RED, 2),  # continuous but another colour: two objects
    ],
)
def test_neighbours_join_when_continuous_and_alike(gap_px, colour, regions):
    s = sketch(surfaces_of(halves(), {0: 1.0, 1: 1.0 + gap_px}, {0: GREY, 1: colour}))
    assert len(s.regions) == regions


@pytest.mark.parametrize(
    ("gap_px", "same_depth_px", "regions"),
    [
        (0.15, 0.2, 1),  # unlike colours, planes within same_depth_px (the default, 0.2): one surface
        (0.3, 0.2, 2),  # 0.3 px apart: two, as unlike colours keep them
        (0.3, 0.5, 1),
        (0.15, 0.0, 2),  # the pass off
    ],
)
def test_the_same_depth_pass_joins_unlike_neighbours_whose_planes_meet(gap_px, same_depth_px, regions):
    surfaces = surfaces_of(halves(), {0: 1.0, 1: 1.0 + gap_px}, {0: GREY, 1: RED})
    assert len(sketch(surfaces, SketchParams(same_depth_px=same_depth_px)).regions) == regions
    if same_depth_px == SketchParams().same_depth_px:
        assert len(sketch(surfaces).regions) == regions


def test_one_stray_plane_along_a_boundary_does_not_keep_a_surface_apart():
    """A grey surface of three superpixels: 0 on the left, 1 and 2 on the right, all at 1 px, but 2's plane (rows
    36-59) is steep (0.3 px a row, as a weakly textured superpixel's fit can be) and misses 0 by 0.15-7 px along its
    24 px of their boundary while meeting 1. Every edge counts at most `gap_clip_px` (1.2 px): the mean over the
    boundary is 0.41-0.44 px, within `continuity_px`, and the surface is one region. Unclipped (0), that one
    superpixel's 3.6 px mean makes it 1.35-1.44 px, and the surface came out in two."""
    labels = halves()
    labels[36:, 40:] = 2
    surfaces = surfaces_of(labels, {0: 1.0, 1: 1.0, 2: 1.0}, {0: GREY, 1: GREY, 2: GREY})
    surfaces.planes[2] = surfaces.fitted[2] = (0.0, 0.3, 1.0 - 0.3 * 35.5)  # 1 px on its boundary with 1 (y = 35.5)
    assert len(sketch(surfaces).regions) == 1
    assert len(sketch(surfaces, SketchParams(gap_clip_px=0.0)).regions) == 2


def test_a_small_region_joins_the_neighbour_it_continues_whatever_its_colour():
    labels = np.zeros((60, 90), np.int32)
    labels[:, 45:] = 1
    labels[28:30, 43:47] = 2  # 8 px across the boundary (the minimum is 0.2 % of 5,400 = 10.8 px)
    levels = {0: 1.0, 1: 4.0, 2: 3.8}  # it continues 1 (0.2 px), not 0 (2.8 px)
    s = sketch(surfaces_of(labels, levels, {0: GREY, 1: GREY, 2: RED}))
    assert s.superpixel_region[2] == s.superpixel_region[1]
    assert s.superpixel_region[2] != s.superpixel_region[0]
    big = labels.copy()
    big[26:32, 41:49] = 2  # 48 px: not small, and too unlike either side to join them
    s = sketch(surfaces_of(big, levels, {0: GREY, 1: GREY, 2: RED}), SketchParams(sliver_fraction=0.0))
    assert len(s.regions) == 3


def test_a_thin_rim_sliver_joins_its_farthest_neighbour():
    # near object (0) left, far wall (1) right, a 3 px strip (2) between them at an in-between depth and another
    # colour: 180 px of 24,000 (under 1 %), 2 area / boundary = 2 x 180 / 120 = 3 px (under 12): a rim sliver
    labels = np.zeros((60, 400), np.int32)
    labels[:, 198:] = 1
    labels[:, 195:198] = 2
    levels = {0: 1.0, 1: 6.0, 2: 3.0}
    colours = {0: GREY, 1: (0.2, 0.2, 0.8), 2: RED}
    s = sketch(surfaces_of(labels, levels, colours))
    assert s.superpixel_region[2] == s.superpixel_region[1]  # the farther (larger disparity) side
    assert s.superpixel_region[0] != s.superpixel_region[1]
    # thinness is the test: a 3 px strip is not thinner than 2 px, and stays
    s = sketch(surfaces_of(labels, levels, colours), SketchParams(sliver_width_px=2.0))
    assert len(s.regions) == 3


def test_region_properties_are_those_of_its_pixels():
    labels = halves((40, 100))
    s = sketch(surfaces_of(labels, {0: -1.5, 1: 2.25}, {0: GREY, 1: RED}), confidence=0.6)
    assert len(s.regions) == 2
    by_level = sorted(s.regions, key=lambda r: r.disparity_px)
    near, far = by_level
    assert near.pixels == far.pixels == 2000
    assert near.centroid_xy == pytest.approx((24.5, 19.5))
    assert far.centroid_xy == pytest.approx((74.5, 19.5))
    assert near.disparity_px == pytest.approx(-1.5, abs=1e-4)
    assert far.disparity_px == pytest.approx(2.25, abs=1e-4)
    assert not near.slanted and not far.slanted
    assert near.confidence == pytest.approx(0.6, abs=1e-6)
    assert s.order[near.id] == 0 and s.order[far.id] == 1  # front to back
    # the nearer side of a boundary occludes the other, by more than the margin
    assert s.occludes[near.id] == [far.id] and s.occludes[far.id] == []
    assert np.all(s.labels[:, :50] == near.id) and np.all(s.labels[:, 50:] == far.id)


def test_neighbours_within_the_occlusion_margin_occlude_nothing():
    labels = halves((40, 100))
    s = sketch(surfaces_of(labels, {0: 1.0, 1: 1.4}, {0: GREY, 1: RED}))  # 0.4 px apart, margin 0.5
    assert len(s.regions) == 2
    assert all(not v for v in s.occludes.values())


def test_a_confidence_above_one_is_reported_as_one():
    labels = halves((40, 100))
    s = sketch(surfaces_of(labels, {0: 1.0, 1: 3.0}, {0: GREY, 1: RED}), confidence=1.7)
    assert all(r.confidence == 1.0 for r in s.regions)


def test_sketch_params_are_frozen():
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        SketchParams().continuity_px = 1.0  # type: ignore[misc]


def test_equal_depths_of_unlike_colours_are_one_surface_by_default():
    # the sketch's regions are surfaces apart in depth: two colours on one plane (a printed box) are one region
    assert len(sketch(surfaces_of(halves(), {0: 2.0, 1: 2.0}, {0: GREY, 1: RED})).regions) == 1


@pytest.mark.parametrize(("width_px", "sliver"), [(11, True), (12, False)])
def test_a_strip_is_a_sliver_only_when_thinner_than_the_width(width_px, sliver):
    # 20 rows x 1,300 columns: 1 % is 260 px, so strips of 11 and 12 columns (220, 240 px) are both small
    labels = np.zeros((20, 1300), np.int32)
    labels[:, 650 + width_px :] = 1
    labels[:, 650 : 650 + width_px] = 2
    s = sketch(surfaces_of(labels, {0: 1.0, 1: 6.0, 2: 3.0}, {0: GREY, 1: (0.2, 0.2, 0.8), 2: RED}))
    assert (s.superpixel_region[2] == s.superpixel_region[1]) == sliver
    assert len(s.regions) == (2 if sliver else 3)


def test_a_sliver_ignores_a_neighbour_it_barely_touches():
    # the strip's boundary: 60 edges with the near object, 50 with the wall, 10 with a far region below the wall
    # (under a quarter of it): it joins the wall, not the farthest neighbour
    labels = np.zeros((60, 400), np.int32)
    labels[:, 198:] = 1
    labels[50:, 198:] = 3
    labels[:, 195:198] = 2
    levels = {0: 1.0, 1: 6.0, 2: 3.0, 3: 9.0}
    colours = {0: GREY, 1: (0.2, 0.2, 0.8), 2: RED, 3: (0.1, 0.8, 0.1)}
    s = sketch(surfaces_of(labels, levels, colours))
    assert s.superpixel_region[2] == s.superpixel_region[1]
    assert s.superpixel_region[3] != s.superpixel_region[1]


@pytest.mark.parametrize(("a", "b"), [(0.03, 0.0), (0.0, 0.03)])
def test_a_slanted_region_keeps_its_plane_and_reports_it_at_its_centroid(a, b):
    labels = np.zeros((60, 90), np.int32)
    labels[:, 40:] = 1
    surfaces = surfaces_of(labels, {0: -2.0, 1: 0.0}, {0: GREY, 1: RED})
    surfaces.planes[1] = (a, b, 1.0)
    surfaces.fitted[1] = (a, b, 1.0)
    s = sketch(surfaces)
    slanted = [r for r in s.regions if r.slanted]
    assert len(slanted) == 1  # 0.03 px/px over 50 or 60 px: 1.5-1.8 px of spread (above 0.5)
    region = slanted[0]
    assert region.centroid_xy == pytest.approx((64.5, 29.5))
    assert region.plane == pytest.approx((a, b, 1.0), abs=2e-3)
    assert region.disparity_px == pytest.approx(a * 64.5 + b * 29.5 + 1.0, abs=0.02)
    assert float(region.disparity_at(40.0, 10.0)) == pytest.approx(a * 40.0 + b * 10.0 + 1.0, abs=0.02)


def _cards_joined_by_a_leaning_superpixel(card_px: int = 100, ramp_px: int = 10) -> Surfaces:
    """Two same-coloured cards of 10-px-wide superpixels at 2.0 and 3.0 px, and between them one superpixel whose
    plane leans from the one to the other (what the dense disparity's smoothing makes of a depth step): every
    superpixel boundary is continuous (0.05 px), so the merge alone makes one region of them."""
    labels = np.repeat(np.arange(2 * card_px + ramp_px)[None, :] // 10, 40, axis=0).astype(np.int32)
    ramp = card_px // 10
    levels = {k: 2.0 if k < ramp else 3.0 for k in range(int(labels.max()) + 1)}
    surfaces = surfaces_of(labels, levels, dict.fromkeys(levels, GREY))
    slope = 1.0 / ramp_px
    surfaces.planes[ramp] = (slope, 0.0, 2.0 - slope * card_px)
    surfaces.fitted[ramp] = surfaces.planes[ramp]
    return surfaces


def test_two_cards_bridged_by_a_leaning_superpixel_split_at_the_dip_of_their_levels():
    surfaces = _cards_joined_by_a_leaning_superpixel()
    assert len(sketch(surfaces, SketchParams(split_valley=0.0)).regions) == 1  # the merge alone chains them
    s = sketch(surfaces)
    assert len(s.regions) == 2
    levels = sorted(r.disparity_px for r in s.regions)
    assert levels == pytest.approx([2.0, 3.0], abs=0.06)
    regions = s.superpixel_region
    assert len(set(regions[:10])) == len(set(regions[11:])) == 1 and regions[0] != regions[11]  # card by card


def test_a_slanted_floor_of_many_superpixels_has_no_dip_and_stays_one_region():
    labels = np.repeat(np.arange(300)[None, :] // 10, 40, axis=0).astype(np.int32)
    surfaces = surfaces_of(labels, {}, dict.fromkeys(range(30), GREY))
    surfaces.planes[:] = (0.04, 0.0, 1.0)  # 12 px of disparity across the floor, one plane
    surfaces.fitted[:] = surfaces.planes
    s = sketch(surfaces, SketchParams(split_valley=0.9))
    assert len(s.regions) == 1 and s.regions[0].slanted


def test_level_valley_of_two_groups_with_few_between():
    rng = np.random.default_rng(0)
    levels = np.concatenate([rng.normal(2.0, 0.03, 4000), rng.uniform(2.0, 3.0, 400), rng.normal(3.0, 0.03, 4000)])
    ratio, at = _level_valley(levels, 1000.0, 0.15)
    assert ratio < 0.1 and 2.3 < at < 2.7
    # the ramp between them as heavy as either group: no valley worth the name
    levels = np.concatenate([rng.normal(2.0, 0.03, 4000), rng.uniform(2.0, 3.0, 12000), rng.normal(3.0, 0.03, 4000)])
    assert _level_valley(levels, 1000.0, 0.15)[0] > 0.3


@pytest.mark.parametrize(
    "levels",
    [
        np.linspace(0.0, 12.0, 20000),  # an evenly slanted surface
        np.concatenate([np.linspace(0.0, 3.0, 6000), np.full(20000, 3.0)]),  # a floor running into a wall
    ],
)
def test_level_valley_sees_none_in_a_slope_or_a_plateau_beside_a_peak(levels):
    assert _level_valley(levels, 1000.0, 0.15)[0] > 0.8


def test_level_valley_needs_the_minimum_mass_on_both_sides():
    levels = np.concatenate([np.full(500, 1.0), np.full(5000, 3.0)])
    assert _level_valley(levels, 1000.0, 0.15)[0] == np.inf
    assert _level_valley(levels, 100.0, 0.15)[0] < 0.01


def test_plane_occlusions_come_from_the_regions_own_planes():
    labels = np.ones((40, 90), np.int32)
    labels[:, 30:60] = 2
    labels[:, 60:] = 3
    regions = [
        SketchRegion(1, 1200, (0.0, 0.0, 2.0), False, (14.5, 19.5), 2.0, 0.8),
        SketchRegion(2, 1200, (0.0, 0.0, 3.0), False, (44.5, 19.5), 3.0, 0.8),  # 1 px behind region 1
        SketchRegion(3, 1200, (0.01, 0.0, 2.6), True, (74.5, 19.5), 3.345, 0.8),  # meets 2 at 3.195 px
    ]
    occludes, gaps = plane_occlusions(labels, regions, 0.5)
    assert occludes == {1: [2], 2: [], 3: []}  # 2 and 3 are 0.2 px apart along their boundary: neither
    assert gaps[(1, 2)] == pytest.approx(1.0) and gaps[(2, 3)] == pytest.approx(0.195, abs=1e-9)


def cut_in_two(
    part_planes: tuple[tuple[float, float, float], tuple[float, float, float]],
    part_colours: tuple[tuple[float, float, float], tuple[float, float, float]] = (GREY, GREY),
    strip_level: float = 0.5,
) -> Surfaces:
    """A surface cut in two by a vertical strip: superpixel 0 left (columns 0-129), 1 the strip (130-169, red, a
    level), 2 right (170-299); the parts' planes and colours as given."""
    labels = np.zeros((40, 300), np.int32)
    labels[:, 130:170] = 1
    labels[:, 170:] = 2
    surfaces = surfaces_of(labels, {0: 0.0, 1: strip_level, 2: 0.0}, {0: part_colours[0], 1: RED, 2: part_colours[1]})
    surfaces.planes[0], surfaces.planes[2] = part_planes
    surfaces.fitted[:] = surfaces.planes
    return surfaces


KNIFE = (0.01, 0.0, 2.0)  # 3.3-3.7 px where the strip (0.5 px) hides it: the strip is nearer


def test_the_parts_of_a_surface_a_nearer_region_cuts_apart_are_one_region():
    s = sketch(cut_in_two((KNIFE, KNIFE)))
    assert len(s.regions) == 2
    assert s.superpixel_region[0] == s.superpixel_region[2] != s.superpixel_region[1]
    knife = s.region(int(s.superpixel_region[0]))
    np.testing.assert_allclose(knife.plane, KNIFE, atol=1e-3)  # one plane through both parts
    assert s.order[knife.id] > s.order[int(s.superpixel_region[1])]  # behind the strip
    assert len(sketch(cut_in_two((KNIFE, KNIFE)), SketchParams(occluded_join_px=0.0)).regions) == 3  # off


@pytest.mark.parametrize(
    ("planes", "colours", "strip_level", "why"),
    [
        ((KNIFE, KNIFE), (GREY, (0.5, 0.5, 0.75)), 0.5, "colours 0.25 apart: two materials"),
        (((0.0, 0.0, 2.0), (0.0, 0.0, 3.0)), (GREY, GREY), 0.5, "two levels 1 px apart: one plane fits 0.22 px worse"),
        (((0.0, 0.0, 2.0), (0.0, 0.0, 2.0)), (GREY, GREY), 10.0, "the strip is behind: two objects in front of it"),
    ],
)
def test_parts_apart_stay_apart_unless_alike_on_one_plane_behind_an_occluder(planes, colours, strip_level, why):
    assert len(sketch(cut_in_two(planes, colours, strip_level)).regions) == 3, why
