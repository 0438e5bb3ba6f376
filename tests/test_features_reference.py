"""processing/features.py against values worked out here from its definitions: log1p(32 v / white) with white the
99.5th percentile, the RMS feature amplitude of constant bands, the 1/2.2 display gamma, the derivative planes of
a ramp and the difference of Gaussians of a flat plane.
"""

from __future__ import annotations

import numpy as np
import pytest

from mca.processing.features import display_gamma, feature_bands, log_compress, texture_energy


def _planes() -> np.ndarray:
    return np.random.default_rng(5).uniform(0.0, 0.8, (40, 50, 3))


def test_log_compression_is_log1p_of_32_times_the_value_over_the_99_5th_percentile() -> None:
    planes = _planes()
    white = np.percentile(planes, 99.5)
    np.testing.assert_allclose(log_compress(planes), np.log1p(32.0 * planes / white), rtol=1e-5)
    np.testing.assert_array_equal(log_compress(np.zeros((4, 4, 3))), 0.0)  # black: white taken as 1, no NaN
    assert log_compress(-planes).max() == 0.0  # negative noise is clipped to black


def test_display_gamma_puts_white_at_the_99_5th_percentile() -> None:
    planes = _planes()
    white = np.percentile(planes, 99.5)
    expected = np.clip(planes / white, 0.0, 1.0) ** (1 / 2.2)
    got = display_gamma(planes)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    assert got.max() == pytest.approx(1.0) and (got[planes >= white] == pytest.approx(1.0))


@pytest.mark.parametrize("amplitude", [0.0, 0.3, 2.0])
def test_texture_energy_of_constant_bands_is_their_amplitude(amplitude: float) -> None:
    """RMS over the bands' channels: three bands of 3 channels all at a give sqrt(9 a^2 / 9) = a."""
    bands = [np.full((12, 16, 3), sign * amplitude, np.float32) for sign in (1.0, -1.0, 1.0)]
    np.testing.assert_allclose(texture_energy(bands, 5), amplitude, rtol=1e-6)
    one = texture_energy([np.full((12, 16, 3), amplitude, np.float32)], 3)  # one band: still its amplitude
    np.testing.assert_allclose(one, amplitude, rtol=1e-6)


def test_the_derivative_bands_of_a_log_ramp_are_its_slope_and_the_dog_of_a_flat_plane_is_zero() -> None:
    """Planes exp(s x) / 32 (white 1) have log1p(32 v) ~ s x + log(1 + e^{-s x}): away from x = 0 a ramp of slope s
    per pixel in x, none in y; a flat plane has no band-pass content."""
    slope = 0.05
    x = np.arange(80, dtype=np.float64)
    ramp = np.exp(slope * (x + 40))[None, :, None] * np.ones((30, 1, 3))
    ramp /= np.percentile(ramp, 99.5)
    log = np.log1p(32.0 * ramp)
    gx, gy, _dog = feature_bands(ramp)
    expected = np.gradient(log, axis=1)[8:-8, 8:-8]
    np.testing.assert_allclose(gx[8:-8, 8:-8], expected, atol=2e-3)
    np.testing.assert_allclose(gy[8:-8, 8:-8], 0.0, atol=1e-5)
    flat = feature_bands(np.full((24, 24, 3), 0.4))
    for band in flat:
        np.testing.assert_allclose(band, 0.0, atol=1e-6)


@pytest.mark.parametrize("size", [1, 2, 7, 1000, 4097])
def test_percentile_is_numpys_taken_in_float64_whatever_the_dtype(size: int) -> None:
    """`features.percentile` interpolates in float64 (numpy 2.0 and 2.4 round a float32 array's percentile
    differently): numpy's linear percentile of the same values as float64, to the bit."""
    from mca.processing.features import percentile

    values = np.random.default_rng(size).normal(0.3, 0.1, size).astype(np.float32)
    for q in (0.0, 0.2, 37.5, 50.0, 99.5, 99.8, 100.0):
        expected = float(np.percentile(values.astype(np.float64), q))
        assert percentile(values, q) == expected, q
        assert percentile(values.reshape(1, -1, 1), q) == expected  # any shape: all its values


@pytest.mark.parametrize("width", [31, 342, 684, 1368])
@pytest.mark.parametrize("sigma_px", [0.6, 1.5])
def test_the_padded_gaussian_blur_is_opencvs_reflected_blur(width: int, sigma_px: float) -> None:
    """`features.gaussian_blur` pads the right edge to a multiple of 32 px so that every release of OpenCV takes
    the same vector path there: the result is OpenCV's reflected blur of the plane, to float32 rounding."""
    import cv2

    from mca.processing.features import gaussian_blur

    plane = np.random.default_rng(width).uniform(0.0, 1.0, (23, width)).astype(np.float32)
    expected = cv2.GaussianBlur(plane, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    got = gaussian_blur(plane, sigma_px)
    assert got.shape == plane.shape and got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-6)
