"""`benchmarks/halo_cost.py`: its occlusion count is the MCA's geometry, its halo the one it says it is."""

from __future__ import annotations

import numpy as np
from tools import benchmark_module

from mca.devices.profiles import load_profile
from mca.processing.cost import channel_shifts


def _square_scene() -> np.ndarray:
    """A near square (disparity -10 px) before a far wall (+10 px): a red-blue jump of 20 px at its sides."""
    truth = np.full((80, 120), 10.0, np.float32)
    truth[20:60, 30:70] = -10.0
    return truth


def test_a_channel_is_occluded_in_the_strip_half_the_jump_wide_beside_the_near_square():
    """Red moves +d/2 in x and blue -d/2: just right of the square the wall's blue sample (10 px to the left, at
    the wall's +10 px) falls where blue sees the square (its right edge moved 5 px left, to x = 64), for a strip
    half the jump (10 px) wide; red and green see the wall. Beyond the strip, and far from the square, none."""
    halo = benchmark_module("halo_cost")
    shifts = channel_shifts(load_profile("paper-70d").aperture)
    assert np.allclose(shifts, [[0.5, 0.0], [0.0, -0.5], [-0.5, 0.0]])
    truth = _square_scene()
    strip = np.zeros(truth.shape, bool)
    strip[30:50, 71:78] = True  # inside the 10 px strip right of the square (x 70..79), clear of its corners
    beyond = np.zeros(truth.shape, bool)
    beyond[30:50, 83:95] = True
    far = np.zeros(truth.shape, bool)
    far[65:75, 100:115] = True
    assert np.all(halo.occluded_channels(truth, shifts, strip) == 1)
    assert np.all(halo.occluded_channels(truth, shifts, beyond) == 0)
    assert np.all(halo.occluded_channels(truth, shifts, far) == 0)
    inside = np.zeros(truth.shape, bool)
    inside[35:45, 40:60] = True  # the square itself: nothing is nearer
    assert np.all(halo.occluded_channels(truth, shifts, inside) == 0)


def test_the_halo_is_the_far_side_read_near_and_only_beside_a_near_edge():
    halo = benchmark_module("halo_cost")
    truth = _square_scene()
    dense = truth.copy()
    dense[20:60, 70:80] = -9.0  # the square's disparity spread 10 px into the wall on its right
    dense[5:10, 100:110] = 0.0  # a miss far from any near edge (more than 25 px from the square)
    mask = halo.halo_mask(dense, truth)
    assert mask[20:60, 70:80].all()
    assert not mask[5:10, 100:110].any()
    assert mask.sum() == 40 * 10


def test_the_nearest_surface_wins_where_two_land_on_one_pixel():
    """Each pixel lands on the two pixels at and right of where its shift takes it (a 1-row image)."""
    halo = benchmark_module("halo_cost")
    disparity = np.array([[4.0, 0.0, 0.0, 0.0, 0.0, 0.0]], np.float32)
    shifts = np.array([[0.5, 0.0], [0.0, 0.0], [-0.5, 0.0]])
    red, green, blue = halo.visible_disparity(disparity, shifts)[:, 0]
    # red: pixel 0 (+4) lands on x = 2, 3, where pixels 1-3 (0) land too: the nearer 0 wins; nothing lands on x = 0
    assert np.isinf(red[0]) and red[1] == 0.0 and red[2] == 0.0 and red[3] == 0.0
    # green does not move: pixel 0 covers x = 0 alone and shares x = 1 with pixel 1
    assert green[0] == 4.0 and green[1] == 0.0
    # blue: pixel 0 lands at x = -2, outside the image
    assert np.isinf(blue[0]) and blue[1] == 0.0
