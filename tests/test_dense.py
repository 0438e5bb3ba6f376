"""Dense disparity (`processing.dense`): sub-pixel recovery of known shifts, the occupied range, confidence."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mca_scenes import render_layers, texture, two_boxes_scene

from mca.devices.profiles import load_profile
from mca.processing.dense import (
    DenseParams,
    candidate_disparities,
    estimate_dense,
    occupied_range,
    search_candidates,
)

APERTURE = load_profile("paper-70d").aperture


def test_candidates_cover_the_range_and_contain_zero():
    c = candidate_disparities((-3.2, 4.1), 0.5)
    assert c[0] <= -3.2 and c[-1] >= 4.1 and 0.0 in c
    assert np.allclose(np.diff(c), 0.5)


@pytest.mark.parametrize("truth", [-4.3, 0.0, 1.7, 6.25])
def test_uniform_disparity_is_recovered_to_a_fraction_of_a_pixel(truth):
    shape = (160, 200)
    image = render_layers([(texture(shape, 1), np.ones(shape, np.float32), truth)], shape, APERTURE)
    result = estimate_dense(image, APERTURE, (-12.0, 12.0))
    core = result.disparity_px[30:-30, 30:-30]
    assert abs(float(np.median(core)) - truth) < 0.1
    assert float(np.mean(np.abs(core - truth) < 0.3)) > 0.95
    low, high = result.search_range_px
    assert low <= truth <= high and high - low < 24.0  # narrowed around the scene


def test_occupied_range_contains_every_surface_and_little_else():
    image, _, truth = two_boxes_scene(APERTURE)
    low, high = occupied_range(image, APERTURE, (-30.0, 30.0), DenseParams())
    assert low <= min(truth.values()) and high >= max(truth.values())
    assert high - low < 25.0


def _budget_mb(pixels: int, candidates: int) -> float:
    """The volume budget that fits this many candidates on an image of `pixels` (6 bytes each)."""
    return candidates * pixels * 6 / 2**20


def test_the_candidates_are_even_within_the_volume_budget():
    pixels = 300 * 400
    even = candidate_disparities((-20.0, 30.0), 0.5)  # 101
    quick = np.zeros(1000, np.float32)
    params = DenseParams(volume_budget_mb=_budget_mb(pixels, len(even)))
    np.testing.assert_array_equal(search_candidates((-20.0, 30.0), pixels, params, quick), even)


def test_past_the_budget_the_candidates_are_fine_over_the_quick_maps_bulk_and_coarse_beyond():
    """A quick map whose bulk spans -10..+12 px, with 1 % strays from -150 to +140 px (a dark corner matching
    anywhere): the search covers all of the range within the budget, 0.5 px apart over the bulk."""
    rng = np.random.default_rng(3)
    bulk = rng.uniform(-10.0, 12.0, 9900)
    quick = np.concatenate([bulk, rng.uniform(-150.0, 140.0, 100)]).astype(np.float32)
    pixels = 1368 * 912
    params = DenseParams(volume_budget_mb=_budget_mb(pixels, 120))
    c = search_candidates((-152.0, 142.0), pixels, params, quick)
    assert len(c) <= 120 < len(candidate_disparities((-152.0, 142.0), 0.5))
    assert c[0] <= -152.0 and c[-1] >= 142.0 and np.all(np.diff(c) > 0)
    np.testing.assert_allclose(c / 0.5, np.round(c / 0.5))  # every candidate on the even search's grid
    fine = c[1:][np.diff(c) == 0.5]
    assert fine.min() <= -10.0 - 4.0 and fine.max() >= 12.0 + 4.0  # the bulk and its margin: 0.5 px apart
    assert np.diff(c).max() in (2.0, 4.0, 8.0, 16.0)  # the tails: 4, 8, 16 or 32 steps


def test_a_range_too_wide_for_any_tail_is_searched_evenly_on_a_wider_step():
    quick = np.linspace(-100.0, 100.0, 5000, dtype=np.float32)  # a bulk wider than the budget
    pixels = 1000 * 1000
    params = DenseParams(volume_budget_mb=_budget_mb(pixels, 150))
    c = search_candidates((-110.0, 110.0), pixels, params, quick)
    assert len(c) <= 150 and c[0] <= -110.0 and c[-1] >= 110.0
    assert np.allclose(np.diff(c), np.diff(c)[0]) and np.diff(c)[0] > 0.5


def test_a_small_object_in_a_coarse_tail_is_still_found():
    """A textured wall at 0 px and a patch at +8.2 px on 1.5 % of the image (under the bulk's 2 %), searched over -12..+12 px with a
    budget that leaves the candidates 0.5 px apart only around the wall: the patch comes out within a pixel,
    the wall as precise as on an even search."""
    shape = (320, 400)
    wall = (texture(shape, 1), np.ones(shape, np.float32), 0.0)
    patch = np.zeros(shape, np.float32)
    patch[140:180, 240:288] = 1.0
    image = render_layers([wall, (texture(shape, 2, (0.3, 0.5, 0.4)), patch, 8.2)], shape, APERTURE)
    even = len(candidate_disparities((-12.0, 12.0), 0.5))
    params = DenseParams(narrow_range=True, volume_budget_mb=_budget_mb(shape[0] * shape[1], even // 2))
    result = estimate_dense(image, APERTURE, (-12.0, 12.0), params)
    c = result.candidates_px
    assert len(c) <= even // 2 and np.diff(c).max() > 0.5  # uneven: coarse past the wall's bulk
    assert set(np.arange(-2.0, 2.5, 0.5)) <= set(c)  # fine around the wall
    assert abs(float(np.median(result.disparity_px[148:172, 248:280])) - 8.2) < 1.0
    assert abs(float(np.median(result.disparity_px[40:120, 40:200]))) < 0.1


def test_depth_steps_between_objects_are_kept():
    image, points, truth = two_boxes_scene(APERTURE)
    result = estimate_dense(image, APERTURE, (-10.0, 10.0))
    for name, (x, y) in points.items():
        patch = result.disparity_px[y - 5 : y + 6, x - 5 : x + 6]
        assert abs(float(np.median(patch)) - truth[name]) < 0.5, (
            name
        )  # one candidate step (0.5 px); the steps are 2 px and more
    assert result.confidence.shape == result.disparity_px.shape
    assert float(result.confidence.min()) >= 0.0 and float(result.confidence.max()) <= 1.0


def test_the_b_spline_sampler_removes_the_noise_bias_of_full_colour_input():
    """`DenseParams(sampling="bspline")` without the noise model: a textured plane at +0.25 px with white noise
    in every channel comes out there, not pulled toward +1 where every channel is sampled halfway between pixels
    (bilinear sampling without the noise model: +0.46; the default takes the bias out with the noise model,
    tests/test_noise_model.py)."""
    from mca.processing.pipeline import PipelineParams, run_pipeline

    rng = np.random.default_rng(4)
    shape = (160, 200)
    sharp = texture(shape, 8, blur_px=1.5)
    image = render_layers([(sharp, np.ones(shape, np.float32), 0.25)], shape, APERTURE)
    noisy = np.clip(image + rng.normal(0.0, 0.04, image.shape).astype(np.float32), 1e-3, None)
    middle = (slice(20, -20), slice(20, -20))
    medians = {}
    for sampling in ("bspline", "bilinear"):
        params = PipelineParams(dense=DenseParams(sampling=sampling, noise_model=False), refine=None, boundaries=None)
        result = run_pipeline(noisy, APERTURE, None, disparity_range_px=(-4.0, 4.0), params=params)
        medians[sampling] = float(np.median(result.raw_disparity_px[middle]))
    assert abs(medians["bspline"] - 0.25) < 0.15
    assert medians["bilinear"] - 0.25 > 0.15  # the bias this sampler exists for


@pytest.mark.parametrize("shape", [(40, 64), (37, 51)])
def test_the_coarse_cost_comes_back_up_as_opencv_resizes_it(shape):
    """The fused blend (fine volume averaged with the half-size one brought up, transposed to (H, W, D) in one
    pass, one chunk of candidates at a time, with one share of the half-size cost or a share per pixel, each
    pixel scaled by its weight when weights are given) against OpenCV's bilinear resize of each slice, on odd
    and even sizes."""
    from mca.processing.dense import _blend_kernel

    rng = np.random.default_rng(5)
    h, w = shape
    fine = rng.random((7, h, w), dtype=np.float32)
    coarse = rng.random((7, (h + 1) // 2, (w + 1) // 2), dtype=np.float32)
    up = np.stack([cv2.resize(s, (w, h), interpolation=cv2.INTER_LINEAR) for s in coarse])
    weight = rng.random((h, w), dtype=np.float32)
    shares = rng.random((h, w), dtype=np.float32) * 0.5
    none = np.zeros((0, 0), np.float32)
    for share_map, share in ((none, 0.5 / 1.5), (shares, shares[None])):
        expected = ((1.0 - share) * fine + share * up).transpose(1, 2, 0)
        for given, scale in ((none, 1.0), (weight, weight[..., None])):
            blended = np.full((h, w, 7), np.nan, np.float32)
            for first, last in ((0, 4), (4, 7)):
                _blend_kernel(fine[first:last], coarse[first:last], 0.5 / 1.5, share_map, given, blended, first)
            assert np.abs(blended - expected * scale).max() < 1e-5


def test_the_chunked_volume_is_the_whole_volume_blended():
    """`_cost_hwd` makes the full-size cost `_CHUNK` candidates at a time into one buffer: with more candidates
    than a chunk, it equals the cost volume made at once and blended with the half-size one, rounded to
    `COST_LEVELS` levels (uint16)."""
    from mca.processing.cost import cost_input, cost_volume
    from mca.processing.dense import _CHUNK, COST_LEVELS, _cost_hwd

    shape = (64, 80)
    planes = render_layers([(texture(shape, 2), np.ones(shape, np.float32), 1.5)], shape, APERTURE)
    params = DenseParams(coarse_weight=0.5, coarse_half_snr=0.0)
    candidates = np.arange(-(_CHUNK + 3), _CHUNK + 4) * 0.5
    assert len(candidates) > 2 * _CHUNK
    inputs = cost_input(planes)

    def volume(given, c: np.ndarray) -> np.ndarray:
        noise = given.noise if params.noise_model else None
        return cost_volume(given.stacked, APERTURE, c, params.window_px, params.noise_floor, params.sampling, noise)

    fine = volume(inputs, candidates)
    coarse = volume(cost_input(cv2.pyrDown(planes)), candidates / 2.0)
    up = np.stack([cv2.resize(s, (80, 64), interpolation=cv2.INTER_LINEAR) for s in coarse])
    expected = ((fine + 0.5 * up) / 1.5).transpose(1, 2, 0)
    got = _cost_hwd(planes, APERTURE, candidates, params, inputs)
    assert got.shape == (64, 80, len(candidates)) and got.flags.c_contiguous and got.dtype == np.uint16
    assert np.abs(got - expected * COST_LEVELS).max() <= 0.5 + 1e-5 * COST_LEVELS  # rounded; float32 sums
    alone = _cost_hwd(planes, APERTURE, candidates, DenseParams(coarse_weight=0.0), inputs)
    assert np.array_equal(alone, np.floor(fine.transpose(1, 2, 0).astype(np.float64) * COST_LEVELS + 0.5))


@pytest.mark.parametrize("seed", [1, 3])
def test_a_one_colour_wall_framed_by_texture_takes_the_frames_disparity_despite_the_noise(seed):
    """A plane at +3 px whose middle is one flat colour (a painted wall) and whose 16-px frame is textured, with
    strong sensor noise. The wall's cost curves are the noise's: unweighted, their chance minima, summed along
    the aggregation's paths, put 5 % or more of the wall elsewhere; weighted by their signal
    (`DenseParams.half_weight_snr`), the wall takes the frame's disparity."""
    shape = (220, 320)
    frame = texture(shape, 1, colour=(0.5, 0.4, 0.3), contrast=0.35)
    wall = np.zeros(shape + (3,), np.float32)
    wall[:] = (0.3, 0.45, 0.6)
    inside = np.zeros(shape, np.float32)
    inside[16:-16, 16:-16] = 1.0
    clean = render_layers([(frame, np.ones(shape, np.float32), 3.0), (wall, inside, 3.0)], shape, APERTURE)
    noisy = clean + np.random.default_rng(seed).normal(0.0, 0.02, clean.shape).astype(np.float32)
    wrong = {}
    for half in (0.0, DenseParams().half_weight_snr):
        result = estimate_dense(noisy, APERTURE, (-12.0, 12.0), DenseParams(half_weight_snr=half))
        wrong[half] = float(np.mean(np.abs(result.disparity_px[30:-30, 30:-30] - 3.0) > 1.0))
    assert wrong[0.0] > 0.05, wrong
    assert wrong[DenseParams().half_weight_snr] < 0.01, wrong


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_wall_textured_in_one_colour_alone_takes_the_frames_disparity(seed):
    """A plane at +3 px whose middle (a dark red sofa, a red wall) has texture in its red channel alone, green and
    blue flat, and whose 16-px frame is textured in every channel, with sensor noise. The colour-alignment cost
    needs two channels with structure: the middle's cost curves are the noise's. Weighted by the signal of all
    channels together (`signal_channels="total"`), the red texture counts them fully and 10-22 % of the middle
    goes wrong; weighted by the channel with the second most signal (the default), the middle takes the frame's
    disparity."""
    shape = (220, 320)
    frame = texture(shape, seed, colour=(0.5, 0.4, 0.3), contrast=0.35)
    wall = np.full(shape + (3,), 0.3, np.float32)
    wall[..., 0] = texture(shape, seed + 20, colour=(0.6, 0.3, 0.3), contrast=0.35)[..., 0]
    inside = np.zeros(shape, np.float32)
    inside[16:-16, 16:-16] = 1.0
    clean = render_layers([(frame, np.ones(shape, np.float32), 3.0), (wall, inside, 3.0)], shape, APERTURE)
    noisy = clean + np.random.default_rng(seed).normal(0.0, 0.01, clean.shape).astype(np.float32)
    wrong = {}
    for channels in ("total", "second"):
        result = estimate_dense(noisy, APERTURE, (-12.0, 12.0), DenseParams(signal_channels=channels))
        wrong[channels] = float(np.mean(np.abs(result.disparity_px[30:-30, 30:-30] - 3.0) > 1.0))
    assert DenseParams().signal_channels == "second"
    assert wrong["total"] > 0.05, wrong
    assert wrong["second"] < 0.01, wrong


@pytest.mark.parametrize("seed", [1, 2])
def test_a_thin_near_bar_keeps_its_disparity_where_its_own_windows_have_signal(seed):
    """An 8-px textured bar at -2 px before a textured wall at +4 px, with sensor noise. The half-size cost's
    window is twice as wide and sees the wall beside the bar: at a fixed share it takes 16-47 % of the bar's
    middle to the wall or between; with its share lowered where the full-size window has signal
    (`DenseParams.coarse_half_snr`), the bar keeps its disparity."""
    shape = (160, 240)
    wall = (texture(shape, seed, (0.45, 0.43, 0.40), blur_px=1.5, contrast=0.3), np.ones(shape, np.float32), 4.0)
    alpha = np.zeros(shape, np.float32)
    alpha[:, 100:108] = 1
    bar = (texture(shape, seed + 10, (0.7, 0.3, 0.2), blur_px=1.0, contrast=0.4), alpha, -2.0)
    image = render_layers([wall, bar], shape, APERTURE)
    rng = np.random.default_rng(seed)
    noisy = np.clip(image + rng.normal(0.0, 0.01, image.shape).astype(np.float32), 1e-3, None)
    found = {}
    for half_snr in (0.0, 1.0):
        disparity = estimate_dense(noisy, APERTURE, (-8.0, 8.0), DenseParams(coarse_half_snr=half_snr)).disparity_px
        found[half_snr] = float(np.mean(np.abs(disparity[20:-20, 101:107] + 2.0) < 0.5))
    assert found[1.0] >= 0.95, found
    assert found[0.0] <= 0.9, found  # the fixed share, which the test would not tell apart otherwise
