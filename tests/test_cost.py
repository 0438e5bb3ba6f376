"""The compiled colour-line cost (`processing.cost`) against a plain numpy reference and closed-form geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.ndimage
from mca_scenes import render_layers, texture

from mca.devices.profiles import load_profile
from mca.processing.cost import channel_shifts, cost_at, cost_volume, stack_bands
from mca.processing.features import feature_bands

APERTURE = load_profile("paper-70d").aperture


def bspline(plane: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Cubic B-spline sampling of the pixel values themselves (scipy's spline without its prefilter), edge
    pixels repeated beyond the image."""
    return scipy.ndimage.map_coordinates(plane, [my, mx], order=3, prefilter=False, mode="nearest")


def bilinear(plane: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Exact bilinear sampling at positions clamped to the image (OpenCV's remap quantises to 1/32 px before 5.0)."""
    h, w = plane.shape
    mx, my = np.clip(mx, 0, w - 1), np.clip(my, 0, h - 1)
    x0 = np.clip(np.floor(mx).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(my).astype(int), 0, h - 2)
    fx, fy = mx - x0, my - y0
    top = plane[y0, x0] * (1 - fx) + plane[y0, x0 + 1] * fx
    bottom = plane[y0 + 1, x0] * (1 - fx) + plane[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def reference_cost(
    bands: list[np.ndarray], shifts: np.ndarray, d: float | np.ndarray, window: int, noise: float, sample=bspline
) -> np.ndarray:
    """Bando's colour-line measure written out: channels sampled at x + d s_c (`sample`; `d` one disparity or
    one per pixel), products
    pooled over the bands, window sums clamped at the borders, L = 1 - rg^2 - rb^2 - gb^2 + 2 rg rb gb."""
    h, w = bands[0].shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    sums = {k: np.zeros((h, w), np.float64) for k in ("rr", "gg", "bb", "rg", "rb", "gb")}
    for band in bands:
        ch = []
        for c in range(3):
            mx = xs + np.float32(d * shifts[c, 0])
            my = ys + np.float32(d * shifts[c, 1])
            ch.append(sample(band[..., c].astype(np.float64), mx.astype(np.float64), my.astype(np.float64)))
        r, g, b = ch
        for key, value in (("rr", r * r), ("gg", g * g), ("bb", b * b), ("rg", r * g), ("rb", r * b), ("gb", g * b)):
            sums[key] += value
    radius = window // 2
    ones = np.ones((h, w))
    box = {
        k: cv2.boxFilter(v, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)
        for k, v in sums.items()
    }
    count = cv2.boxFilter(ones, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT) * len(bands)
    eps = noise**2 * count
    irr, igg, ibb = (1 / np.sqrt(box[k] + eps) for k in ("rr", "gg", "bb"))
    rg, rb, gb = box["rg"] * irr * igg, box["rb"] * irr * ibb, box["gb"] * igg * ibb
    del radius
    return np.clip(1 - rg * rg - rb * rb - gb * gb + 2 * rg * rb * gb, 0, 1)


def test_kernel_matches_the_written_out_measure():
    image = texture((48, 64), 7, blur_px=1.2)
    bands = feature_bands(image)
    shifts = channel_shifts(APERTURE)
    candidates = np.array([-2.5, -0.75, 0.0, 1.3, 4.0])
    volume = cost_volume(stack_bands(bands), APERTURE, candidates, 7, 2e-3, sampling="bspline")
    for k, d in enumerate(candidates):
        expected = reference_cost(bands, shifts, float(d), 7, 2e-3)
        assert np.abs(volume[k] - expected).max() < 2e-4, d


def test_per_pixel_maps_equal_the_volume_at_constant_disparity():
    bands = stack_bands(feature_bands(texture((40, 50), 3)))
    volume = cost_volume(bands, APERTURE, np.array([-1.25, 0.5, 2.0]), 9, 2e-3)
    maps = np.stack([np.full((40, 50), d, np.float32) for d in (-1.25, 0.5, 2.0)])
    assert np.allclose(cost_at(bands, APERTURE, maps, 9, 2e-3), volume, atol=1e-5)
    spline = cost_volume(bands, APERTURE, np.array([-1.25, 0.5, 2.0]), 9, 2e-3, sampling="bspline")
    assert np.allclose(cost_at(bands, APERTURE, maps, 9, 2e-3, sampling="bspline"), spline, atol=1e-5)


@pytest.mark.parametrize("sampling", ["bspline", "bilinear"])
def test_per_pixel_maps_at_varying_disparity_match_the_written_out_measure(sampling):
    """The refinement's per-pixel costs where the disparity changes from pixel to pixel (a slanted plane with a
    step; taps past every border): each channel sampled at x + d(x) s_c, against scipy's spline or the exact
    bilinear sampler written out."""
    h, w = 36, 52
    bands = feature_bands(texture((h, w), 9, blur_px=1.2))
    shifts = channel_shifts(APERTURE)
    ys, xs = np.mgrid[0:h, 0:w]
    ramp = (-4.0 + 0.16 * xs + 0.05 * ys + np.where(xs > 30, 1.7, 0.0)).astype(np.float32)
    maps = np.stack([ramp, -ramp, ramp + np.float32(0.37)])
    got = cost_at(stack_bands(bands), APERTURE, maps, 7, 2e-3, sampling=sampling)
    sample = bspline if sampling == "bspline" else bilinear
    for k in range(len(maps)):
        expected = reference_cost(bands, shifts, maps[k].astype(np.float64), 7, 2e-3, sample=sample)
        assert np.abs(got[k] - expected).max() < 2e-4, k


def test_bilinear_volume_matches_the_written_out_measure():
    """The Bayer-input sampler (`sampling="bilinear"`) at uniform candidates, green's vertical shift included."""
    image = texture((48, 64), 7, blur_px=1.2)
    bands = feature_bands(image)
    shifts = channel_shifts(APERTURE)
    candidates = np.array([-2.5, -0.75, 1.3])
    volume = cost_volume(stack_bands(bands), APERTURE, candidates, 7, 2e-3, sampling="bilinear")
    for k, d in enumerate(candidates):
        expected = reference_cost(bands, shifts, float(d), 7, 2e-3, sample=bilinear)
        assert np.abs(volume[k] - expected).max() < 2e-4, d


def test_bilinear_per_pixel_maps_match_the_written_out_measure():
    """The refinement's sampler (`sampling="bilinear"`) at per-pixel disparities."""
    bands = feature_bands(texture((40, 56), 5, blur_px=1.2))
    shifts = channel_shifts(APERTURE)
    maps = np.stack([np.full((40, 56), d, np.float32) for d in (-1.3, 0.6, 2.75)])
    got = cost_at(stack_bands(bands), APERTURE, maps, 7, 2e-3, sampling="bilinear")
    for k, d in enumerate((-1.3, 0.6, 2.75)):
        expected = reference_cost(bands, shifts, float(np.float32(d)), 7, 2e-3, sample=bilinear)
        assert np.abs(got[k] - expected).max() < 2e-4, d


@pytest.mark.parametrize("truth", [-3.5, 0.0, 2.25])
def test_cost_is_lowest_at_the_true_shift_for_any_gain_and_sign(truth):
    sharp = texture((120, 160), 5, blur_px=1.5)
    image = render_layers([(sharp, np.ones((120, 160), np.float32), truth)], (120, 160), APERTURE)
    flipped = image * np.float32([1.0, 0.3, 2.0])  # other channel gains
    flipped[..., 1] = 1.2 - flipped[..., 1]  # and an inverted green: the colour line does not care
    candidates = np.arange(-6.0, 6.01, 0.25)
    for planes in (image, flipped):
        volume = cost_volume(stack_bands(feature_bands(np.clip(planes, 1e-3, None))), APERTURE, candidates, 9, 2e-3)
        curve = volume[:, 25:-25, 25:-25].mean(axis=(1, 2))
        assert abs(candidates[int(np.argmin(curve))] - truth) <= 0.25
        assert curve.min() < 0.5 * np.median(curve)


@pytest.mark.parametrize("truth", [0.25, -1.75])
def test_sensor_noise_does_not_pull_the_minimum_to_half_pixel_samples(truth):
    """Interpolating between pixels averages their noise away: bilinear sampling at a half-pixel offset halves
    the noise variance, so noisy channels correlate best (the cost is lowest) where every channel falls
    between pixels (odd red-blue disparities for the paper's aperture), away from the true shift. The cubic
    B-spline's noise gain hardly changes with the offset (0.46-0.5): the minimum stays on the truth."""
    rng = np.random.default_rng(4)
    sharp = texture((160, 200), 8, blur_px=1.5)
    image = render_layers([(sharp, np.ones((160, 200), np.float32), truth)], (160, 200), APERTURE)
    noisy = np.clip(image + rng.normal(0.0, 0.04, image.shape).astype(np.float32), 1e-3, None)
    candidates = np.arange(truth - 1.5, truth + 1.51, 0.05)
    volume = cost_volume(stack_bands(feature_bands(noisy)), APERTURE, candidates, 9, 2e-3, sampling="bspline")
    curve = volume[:, 20:-20, 20:-20].mean(axis=(1, 2))
    assert abs(candidates[int(np.argmin(curve))] - truth) <= 0.1


def test_the_cost_inputs_hold_one_copy_of_the_bands():
    """`cost_input`'s band list views its stack (at 20 MP a second copy was 47 MB held through the dense search's
    peak), and gives what the bands made on their own give."""
    from mca.processing.cost import cost_input
    from mca.processing.features import feature_noise, signal_weight

    planes = np.clip(texture((40, 56), 7, blur_px=1.0), 1e-3, None).astype(np.float32)
    inputs = cost_input(planes)
    assert all(np.shares_memory(band, inputs.stacked) for band in inputs.bands)
    bands = feature_bands(planes)
    assert all(np.array_equal(view, band) for view, band in zip(inputs.bands, bands, strict=True))
    noise = feature_noise(planes, bands)
    assert inputs.noise is not None
    assert np.array_equal(inputs.noise.variance, noise.variance)
    assert np.array_equal(inputs.signal_weight(9, 0.1), signal_weight(bands, noise, 9, 0.1))
