"""The window-based winner-takes-all disparity (`processing.disparity`, the colour-line peer and the live preview's
building blocks) on synthetic shifted textures with known disparity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.processing.disparity import DisparityParams, channel_shifts, estimate_disparity, shift_channels

APERTURE = load_profile("paper-70d").aperture


def textured(shape: tuple[int, int], seed: int, colour=(0.6, 0.4, 0.3), blur_px: float = 1.5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), blur_px)
    noise /= noise.std()
    return (np.clip(1.0 + 0.35 * noise, 0.05, 3.0)[..., None] * np.asarray(colour, np.float32)).astype(np.float32)


def mca_image(sharp: np.ndarray, disparity_px: float) -> np.ndarray:
    """What the MCA camera records of a fronto-parallel plane: channel c displaced by d * s_c."""
    return shift_channels(sharp, APERTURE, -disparity_px, cv2.INTER_CUBIC)


def test_channel_shifts_follow_the_filter_geometry():
    shifts = channel_shifts(APERTURE)
    assert np.allclose(shifts[0], (0.5, 0.0)) and np.allclose(shifts[2], (-0.5, 0.0))
    assert np.allclose(shifts[1], (0.0, -0.5))  # green on top moves up (y down)
    assert np.isclose(np.linalg.norm(shifts[0] - shifts[2]), 1.0)  # disparity is the red-blue shift


@pytest.mark.parametrize("truth", [-3.3, 0.0, 1.25, 4.6])
def test_uniform_disparity_recovered_sub_pixel(truth):
    sharp = textured((160, 200), 1)
    result = estimate_disparity(mca_image(sharp, truth), APERTURE, (-8.0, 8.0))
    core = result.disparity_px[30:-30, 30:-30]
    assert abs(float(np.median(core)) - truth) < 0.15  # the coarse stage; regions are refined
    assert float(np.mean(np.abs(core - truth) < 0.25)) > 0.9
    assert result.confidence[30:-30, 30:-30].mean() > 0.05


def test_flat_areas_get_low_confidence():
    sharp = textured((120, 160), 2)
    sharp[:, :60] = (0.5, 0.4, 0.3)  # a flat band
    result = estimate_disparity(mca_image(sharp, 2.0), APERTURE, (-6.0, 6.0))
    assert result.confidence[20:-20, 5:40].mean() < 0.3 * result.confidence[20:-20, 100:-20].mean()


def test_integer_wta_has_no_sub_pixel():
    sharp = textured((120, 160), 3)
    result = estimate_disparity(
        mca_image(sharp, 1.3), APERTURE, (-4.0, 4.0), DisparityParams(step_px=1.0, subpixel=False)
    )
    assert set(np.unique(result.disparity_px)) <= set(np.arange(-5.0, 6.0))
