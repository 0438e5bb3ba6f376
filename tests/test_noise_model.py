"""The sensor-noise model of the feature planes (`processing.features.feature_noise`) and what the cost does with
it (`processing.cost`, `DenseParams(noise_model=True)`, `RefineParams(noise_model=True)`).

The references are measured in the tests: the noise actually added, and the variance and autocorrelation of the
feature planes of pure noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mca_scenes import render_layers, texture

from mca.devices.profiles import load_profile
from mca.processing.cost import cost_volume, stack_bands
from mca.processing.dense import DenseParams
from mca.processing.features import feature_bands, feature_noise, log_compress
from mca.processing.refine import RefineParams, refine_regions

APERTURE = load_profile("paper-70d").aperture


def smooth_scene(shape: tuple[int, int]) -> np.ndarray:
    """Two brightness halves (dark left, bright right) with gentle shading and no fine structure."""
    h, w = shape
    _ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    base = np.where(xs < w / 2, 0.08, 0.6).astype(np.float32)
    shading = 1.0 + 0.1 * np.sin(xs / 37.0)
    return np.stack([base * shading * k for k in (1.0, 0.8, 1.2)], axis=-1).astype(np.float32)


def test_the_measured_noise_is_the_noise_added_at_every_brightness():
    rng = np.random.default_rng(1)
    shape = (240, 320)
    clean = smooth_scene(shape)
    sigma = 0.01 * np.sqrt(clean / 0.6)  # photon-like: noisier where brighter, in linear units
    noisy = clean + rng.standard_normal(clean.shape).astype(np.float32) * sigma
    model = feature_noise(noisy)
    # the truth: the variance of the noise in the log planes, from the noise that was added
    difference = log_compress(noisy) - _log_with_white_of(clean, noisy)
    for c in range(3):
        for half in (slice(10, 150), slice(170, 310)):
            truth = float(np.mean(difference[20:-20, half, c] ** 2))
            measured = float(np.mean(model.variance[c][20:-20, half]))
            assert 0.8 < measured / truth < 1.25, (c, half, measured, truth)


def _log_with_white_of(clean: np.ndarray, noisy: np.ndarray) -> np.ndarray:
    """`log_compress` of `clean` with the white level `log_compress` found for `noisy`."""
    white = float(np.percentile(noisy, 99.5))
    return np.log1p(np.clip(clean, 0.0, None) * np.float32(32.0 / white))


def test_band_gains_and_correlations_are_those_of_filtered_white_noise():
    rng = np.random.default_rng(2)
    flat = np.full((300, 300, 3), 0.5, np.float32)
    noisy = flat + rng.normal(0.0, 0.02, flat.shape).astype(np.float32)
    model = feature_noise(noisy)
    bands = feature_bands(noisy)  # of a flat scene: noise only
    pixel_variance = float(np.mean(model.variance[0]))
    for b, band in enumerate(bands):
        x = band[20:-20, 20:-20, 0].astype(np.float64)
        variance = float(np.mean(x * x))
        assert variance == pytest.approx(pixel_variance * model.band_gain[b], rel=0.15)
        for lag in (1, 2):
            along_x = float(np.mean(x[:, lag:] * x[:, :-lag])) / variance
            along_y = float(np.mean(x[lag:] * x[:-lag])) / variance
            assert along_x == pytest.approx(model.band_rho[b, 0, lag - 1], abs=0.05)
            assert along_y == pytest.approx(model.band_rho[b, 1, lag - 1], abs=0.05)
        # nothing but noise: its signal correlations are left at the noise's (nothing to keep in step with)
        assert np.allclose(model.signal_rho[b, 0], model.band_rho[b])


def noisy_plane(truth_px: float, sd: float, seed: int) -> np.ndarray:
    shape = (160, 200)
    image = render_layers([(texture(shape, 8, blur_px=1.5), np.ones(shape, np.float32), truth_px)], shape, APERTURE)
    rng = np.random.default_rng(seed)
    return np.clip(image + rng.normal(0.0, sd, image.shape).astype(np.float32), 1e-3, None)


@pytest.mark.parametrize("truth", [0.25, 2.0])
def test_the_noise_model_takes_the_sampling_bias_out_of_the_bilinear_cost(truth):
    """White noise in every channel: bilinear sampling halfway between pixels averages it down, so the cost
    without the model is lowest toward odd red-blue disparities (every channel halfway); with it, the minimum of
    the summed cost is at the truth."""
    noisy = noisy_plane(truth, 0.05, 3)
    bands = feature_bands(noisy)
    candidates = np.arange(truth - 1.0, truth + 1.001, 0.05)
    minima = {}
    for label, noise in (("plain", None), ("model", feature_noise(noisy, bands))):
        volume = cost_volume(stack_bands(bands), APERTURE, candidates, 9, 2e-3, "bilinear", noise)
        curve = volume[:, 25:-25, 25:-25].reshape(len(candidates), -1).mean(axis=1)
        minima[label] = float(candidates[int(np.argmin(curve))])
    assert abs(minima["model"] - truth) <= 0.1
    assert abs(minima["plain"] - truth) > 0.15  # the bias the model exists for


def test_on_a_noise_free_scene_the_noise_model_moves_nothing():
    """Without noise the measured 'noise' is only the finest texture the patches could not avoid; the cost moves
    a little and its minima hardly."""
    clean = noisy_plane(0.75, 0.0, 0)
    bands = feature_bands(clean)
    candidates = np.arange(-0.25, 1.76, 0.05)
    plain = cost_volume(stack_bands(bands), APERTURE, candidates, 9, 2e-3)
    with_model = cost_volume(stack_bands(bands), APERTURE, candidates, 9, 2e-3, noise=feature_noise(clean, bands))
    assert float(np.median(np.abs(plain - with_model))) < 1e-3
    inner = (slice(None), slice(25, -25), slice(25, -25))
    winners = candidates[np.argmin(with_model[inner], axis=0)]
    assert float(np.mean(winners == candidates[np.argmin(plain[inner], axis=0)])) > 0.95  # measured 0.98
    assert abs(float(np.median(winners)) - 0.75) < 0.03


def test_a_noise_model_of_other_planes_is_refused():
    planes = noisy_plane(0.0, 0.02, 0)
    other = cv2.pyrDown(planes)
    with pytest.raises(ValueError, match="noise model"):
        cost_volume(stack_bands(feature_bands(planes)), APERTURE, np.array([0.0]), 9, 2e-3, noise=feature_noise(other))


def test_the_pipeline_with_the_noise_model_keeps_a_noisy_region_where_it_is():
    """Dense search and refinement with the noise model: a noisy region at +0.25 px is found there."""
    from mca.processing.pipeline import PipelineParams, run_pipeline

    noisy = noisy_plane(0.25, 0.06, 4)
    middle = (slice(20, -20), slice(20, -20))
    params = PipelineParams(dense=DenseParams(noise_model=True), refine=RefineParams(noise_model=True), boundaries=None)
    result = run_pipeline(noisy, APERTURE, None, disparity_range_px=(-4.0, 4.0), params=params)
    assert abs(float(np.median(result.disparity_px[middle])) - 0.25) < 0.08
    labels = np.ones(noisy.shape[:2], np.int32)
    model = np.zeros(noisy.shape[:2], np.float32)
    bands = feature_bands(noisy)
    refined = refine_regions(
        stack_bands(bands), APERTURE, labels, model, RefineParams(), {1}, noise=feature_noise(noisy, bands)
    )
    assert abs(float(np.median(refined.disparity_px)) - 0.25) < 0.06


def test_cost_inputs_make_each_weight_once_and_the_refinement_reads_the_same_weights():
    """The dense search and the refinement ask the capture's `CostInput` for the same signal weight: it is made
    once, equal to `features.signal_weight` of the bands, and the refinement given the inputs gives what it
    gives making its weights itself. Inputs of other bands are refused."""
    from mca.processing.cost import cost_input
    from mca.processing.features import signal_weight, texture_energy

    noisy = noisy_plane(0.25, 0.06, 4)
    inputs = cost_input(noisy, True)
    weight = inputs.signal_weight(9, 0.1)
    assert inputs.signal_weight(9, 0.1) is weight
    np.testing.assert_array_equal(weight, signal_weight(inputs.bands, inputs.noise, 9, 0.1))
    np.testing.assert_array_equal(inputs.texture_energy(9), texture_energy(inputs.bands, 9))
    assert not np.array_equal(inputs.signal_weight(9, 1.0), weight)
    labels = np.ones(noisy.shape[:2], np.int32)
    model = np.zeros(noisy.shape[:2], np.float32)
    alone = refine_regions(inputs.stacked, APERTURE, labels, model, RefineParams(), {1}, noise=inputs.noise)
    shared = refine_regions(
        inputs.stacked, APERTURE, labels, model, RefineParams(), {1}, noise=inputs.noise, inputs=inputs
    )
    np.testing.assert_array_equal(alone.disparity_px, shared.disparity_px)
    with pytest.raises(ValueError, match="CostInput"):
        refine_regions(inputs.stacked.copy(), APERTURE, labels, model, RefineParams(), {1}, inputs=inputs)
    with pytest.raises(ValueError, match="noise model"):
        cost_input(noisy, False).signal_weight(9, 0.1)


def test_the_measured_noise_follows_every_object_of_a_rendered_scene():
    """paper-e (a wall filling most of the frame, tomatoes, a carrot, a spatula) rendered twice with the same seed,
    with and without sensor noise: the noise is the difference. Each object's measured variance, channel by
    channel, is within 0.7-1.5 of it; reading the variance off brightness bins without the photon-and-read
    curve (the model before) was 18 times too high in the red tomatoes' red channel."""
    from mca.devices.sim.render import SensorModel, SimulationOptics, render
    from mca.devices.sim.scenes import paper_scene
    from mca.processing.evaluate import bayer_planes
    from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX, align_channel_samples

    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 0.5)
    planes = {}
    for noise in (True, False):
        sensor = SensorModel(noise=noise)
        rendering = render(paper_scene("paper-e", optics.focus_distance_mm), optics, sensor, seed=0)
        mosaic = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
        planes[noise] = align_channel_samples(mosaic, RGGB_HALF_RES_OFFSETS_PX)
    labels = rendering.labels[::2, ::2][: planes[True].shape[0], : planes[True].shape[1]]
    model = feature_noise(planes[True])
    difference = log_compress(planes[True]) - _log_with_white_of(planes[False], planes[True])
    inner = cv2.erode(np.ones(labels.shape, np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    for k in np.unique(labels):
        mask = (labels == k) & inner
        mask &= cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        for c in range(3):
            truth = float(np.var(difference[..., c][mask]))
            measured = float(np.median(model.variance[c][mask]))
            assert 0.7 < measured / truth < 1.5, (int(k), c, measured, truth)


@pytest.mark.parametrize("sigma", [0.005, 0.02])
def test_the_signal_weight_is_near_zero_on_noise_alone_and_near_one_on_texture(sigma):
    """`features.signal_weight` against what was rendered: a flat grey plane plus noise is noise alone (weight
    about 0), a textured one plus the same noise is signal (about 1), at either noise level; a texture with a
    tenth of the contrast lies between."""
    from mca.processing.features import signal_weight

    rng = np.random.default_rng(11)
    shape = (200, 240)
    weights = {}
    for name, clean in (
        ("flat", np.full(shape + (3,), 0.4, np.float32)),
        ("faint", texture(shape, 3, colour=(0.4, 0.4, 0.4), contrast=0.35 * sigma / 0.02 * 0.3)),
        ("textured", texture(shape, 3, colour=(0.4, 0.4, 0.4), contrast=0.35)),
    ):
        noisy = clean + rng.normal(0.0, sigma, clean.shape).astype(np.float32)
        bands = feature_bands(noisy)
        weights[name] = float(np.median(signal_weight(bands, feature_noise(noisy, bands), 9, 1.0)))
    assert weights["flat"] < 0.15, weights
    assert weights["textured"] > 0.95, weights
    assert weights["flat"] + 0.2 < weights["faint"] < weights["textured"] - 0.02, weights


def test_the_signal_weight_needs_two_channels_with_structure():
    """`signal_weight(channels="second")` (the default) reads the channel with the second most signal: texture in
    one channel alone (red over flat green and blue) is noise to the colour-alignment cost, weight about 0, while
    all channels' signal together ("total") calls it signal. Texture in two channels, or in all three, is signal
    either way; each channel's ratio is against its own noise, so a channel with more noise than the others counts
    at its own level. Unknown channel settings are refused with their name."""
    from mca.processing.features import signal_weight

    rng = np.random.default_rng(12)
    shape = (200, 240)
    grain = texture(shape, 5, colour=(0.4, 0.4, 0.4), contrast=0.35)[..., 0]
    weights = {}
    for name, textured in (("red", (0,)), ("red-green", (0, 1)), ("all", (0, 1, 2))):
        clean = np.full(shape + (3,), 0.4, np.float32)
        for c in textured:
            clean[..., c] = grain
        noisy = clean + rng.normal(0.0, 0.01, clean.shape).astype(np.float32)
        bands = feature_bands(noisy)
        noise = feature_noise(noisy, bands)
        weights[name] = {
            ch: float(np.median(signal_weight(bands, noise, 9, 1.0, channels=ch))) for ch in ("second", "total")
        }
    assert weights["red"]["second"] < 0.15 and weights["red"]["total"] > 0.9, weights
    assert weights["red-green"]["second"] > 0.9 and weights["all"]["second"] > 0.95, weights
    assert abs(weights["all"]["second"] - weights["all"]["total"]) < 0.02, weights
    with pytest.raises(ValueError, match="'brightest'"):
        signal_weight(bands, noise, 9, 1.0, channels="brightest")


def test_the_signal_evidence_is_the_signal_weight_and_without_a_noise_model_the_texture():
    """`PipelineParams.evidence = "signal"` weighs the surfaces' pixels by `features.signal_weight`; inputs
    without a noise model fall back to the texture evidence rather than failing."""
    from mca.processing.cost import cost_input
    from mca.processing.dense import DenseDisparity
    from mca.processing.features import signal_weight
    from mca.processing.pipeline import _evidence

    shape = (120, 160)
    noisy = texture(shape, 4) + np.random.default_rng(6).normal(0.0, 0.01, shape + (3,)).astype(np.float32)
    noisy[:, :60] = 0.4 + np.random.default_rng(7).normal(0.0, 0.01, (shape[0], 60, 3)).astype(np.float32)
    dense = DenseDisparity(np.zeros(shape, np.float32), np.ones(shape, np.float32), np.zeros(1), (0.0, 0.0))
    with_noise = cost_input(noisy, True)
    got = _evidence(with_noise, dense, "signal", 0.1)
    np.testing.assert_array_equal(got, signal_weight(with_noise.bands, with_noise.noise, 9, 0.1))
    assert float(np.median(got[:, 10:50])) < 0.3 < 0.9 < float(np.median(got[:, 80:150]))  # flat half: noise alone
    without = cost_input(noisy, False)
    np.testing.assert_array_equal(_evidence(without, dense, "signal", 0.1), _evidence(without, dense, "texture", 0.1))


# --- the photon-and-read-noise fit's non-negative least squares ----------------------------------------------------


def test_the_two_unknown_nnls_is_scipys():
    from scipy.optimize import nnls

    from mca.processing.features import nnls_2

    rng = np.random.default_rng(3)
    clamped = 0
    for trial in range(400):
        rows = int(rng.integers(2, 30))
        design = rng.normal(size=(rows, 2)) * rng.uniform(0.01, 100.0, size=2)
        if trial % 3 == 0:  # the noise curve's shape: positive, one column decaying
            levels = rng.uniform(0.0, 3.0, rows)
            design = np.stack([np.expm1(levels), np.ones(rows)], axis=1) * np.exp(-2.0 * levels)[:, None]
        target = design @ rng.normal(size=2) + rng.normal(scale=rng.uniform(0.0, 1.0), size=rows)
        ours = nnls_2(design, target)
        theirs = nnls(design, target)[0]
        clamped += int(np.any(theirs == 0.0))
        assert np.all(ours >= 0)
        residual_ours = np.linalg.norm(design @ ours - target)
        residual_theirs = np.linalg.norm(design @ theirs - target)
        assert residual_ours <= residual_theirs * (1 + 1e-9) + 1e-12, (trial, ours, theirs)
        np.testing.assert_allclose(ours, theirs, rtol=1e-7, atol=1e-9 * np.abs(theirs).max(initial=1.0))
    assert clamped > 50  # the boundary cases were exercised, not only interior optima
