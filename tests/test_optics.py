"""The optics of accurate depth against the paper's Table 1 and against the Gaussian lens equation."""

from __future__ import annotations

import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.processing import optics
from mca.processing.optics import MCAOptics

# The paper's setup (section VI-A) as Table 1 was computed with it.
D_LS_MM = 52.63
F_MM = 50.0
D_A_MM = 12.0
PITCH_MM = 0.004109

ROWS = "abcdefg"
LABELS = "ABCDEF"
# Table 1, second block: estimated inter-image plane depths in mm.
INTER_IMAGE_MM = {
    "a": [0.1796, 0.1079, 0.0720, 0, -0.1084],
    "b": [0.1438, 0.1438, 0.2154, 0],
    "c": [-0.2172, -0.1084, 0, -0.0720, 0.2154, 0.2868],
    "d": [0.323, 0.2868, 0, -0.3630],
    "e": [-0.2172, -0.2172, 0, 0.1438, 0.2868],
    "f": [0.2868, 0.217, 0],
    "g": [-0.0722, 0.2868, 0],
}
# Table 1, third block: estimated inter-object depth in mm "using (13)".
INTER_OBJECT_MM = {
    "a": [69, 40, 26, 0, -37],
    "b": [55, 55, 84, 0],
    "c": [-71, -37, 0, 26, 84, 116],
    "d": [126, 116, 0, -67],
    "e": [-44, -44, 0, 54, 116],
    "f": [129, 84, 0],
    "g": [-25, 116, 0],
}
INTEGER_DISPARITIES_PX = [s * p for p in (4, 6, 8, 10, 12, 16, 18, 20) for s in (1, -1)] + [0]

# Entries where the paper contradicts its own equations, with the value the equation gives.
# Second block vs eq. 2 from the nearest integer disparity (tolerance 0.0005 mm):
EQ2_CONTRADICTIONS = {
    ("d", "A"): 0.3224,  # printed 0.323; +18 px gives 0.3224 (0.0006 off)
    ("f", "B"): 0.2154,  # printed 0.217; +12 px gives 0.2154, -12 px gives -0.2172
}
# Third block vs eq. 13 applied to the second block (tolerance 1.5 mm):
EQ13_CONTRADICTIONS = {
    ("c", "A"): -72.51,  # printed -71
    ("c", "D"): -25.33,  # printed +26 for -0.0720: sign lost (+0.0720 would give +26.76)
    ("d", "A"): 133.09,  # printed 126
    ("d", "D"): -115.29,  # printed -67
    ("e", "A"): -72.51,  # printed -44
    ("e", "B"): -72.51,  # printed -44
    ("f", "A"): 116.35,  # printed 129
}


def _entries(block: dict[str, list[float]]):
    for row in ROWS:
        for label, value in zip(LABELS, block[row]):
            yield row, label, value


def test_table1_second_block_from_integer_disparities_eq2():
    candidates = {px: optics.inter_image_depth_mm(px * PITCH_MM, D_LS_MM, D_A_MM) for px in INTEGER_DISPARITIES_PX}
    contradictions = {}
    for row, label, printed in _entries(INTER_IMAGE_MM):
        _px, computed = min(candidates.items(), key=lambda item: abs(item[1] - printed))
        if abs(computed - printed) > 0.0005:
            contradictions[(row, label)] = round(computed, 4)
    assert contradictions == EQ2_CONTRADICTIONS


def test_table1_examples_named_in_the_issue():
    assert optics.inter_image_depth_mm(10 * PITCH_MM, D_LS_MM, D_A_MM) == pytest.approx(0.1796, abs=0.0005)
    assert optics.inter_image_depth_mm(-12 * PITCH_MM, D_LS_MM, D_A_MM) == pytest.approx(-0.2172, abs=0.0005)


def test_table1_third_block_from_second_block_eq13():
    contradictions = {}
    for row, label, printed_image_mm in _entries(INTER_IMAGE_MM):
        computed = optics.inter_object_depth_mm(printed_image_mm, D_LS_MM, F_MM)
        printed = INTER_OBJECT_MM[row][LABELS.index(label)]
        if abs(computed - printed) > 1.5:
            contradictions[(row, label)] = round(computed, 2)
    assert contradictions == pytest.approx(EQ13_CONTRADICTIONS, abs=0.01)


def test_eq11_inverts_eq2():
    disparity_mm = np.linspace(-0.2, 0.2, 41)
    depth = optics.inter_image_depth_mm(disparity_mm, D_LS_MM, D_A_MM)
    back = optics.disparity_mm_from_inter_image_depth(depth, D_LS_MM, D_A_MM)
    np.testing.assert_allclose(back, disparity_mm, atol=1e-12)


def test_eq8_magnification():
    assert optics.magnification(D_LS_MM, F_MM) == pytest.approx(2.63 / 50)


def test_eq10_equals_eq2_then_eq13():
    disparity_mm = np.linspace(-0.15, 0.15, 31)
    direct = optics.inter_object_depth_from_disparity_mm(disparity_mm, D_LS_MM, F_MM, D_A_MM)
    chained = optics.inter_object_depth_mm(optics.inter_image_depth_mm(disparity_mm, D_LS_MM, D_A_MM), D_LS_MM, F_MM)
    np.testing.assert_allclose(direct, chained, rtol=1e-10, atol=1e-9)


def test_eq14_is_the_near_side_mirror_of_eq13():
    magnitude = np.linspace(0.0, 0.5, 11)
    near = optics.inter_object_depth_near_mm(magnitude, D_LS_MM, F_MM)
    signed = optics.inter_object_depth_mm(-magnitude, D_LS_MM, F_MM)
    np.testing.assert_allclose(signed, -near, atol=1e-12)
    # and the near side is compressed relative to the far side for the same |Δd|
    far = optics.inter_object_depth_far_mm(magnitude[1:], D_LS_MM, F_MM)
    assert np.all(near[1:] < far)


def test_eq13_against_the_exact_thin_lens_model_over_minus300_to_plus300mm():
    """How far eq. 13/14 are from the Gaussian lens equation solved directly: they agree to rounding.

    Eq. 13 simplifies algebraically to f²Δd / ((d_ls - f)(d_ls - f - Δd)), the difference of two
    object distances from 1/u + 1/v = 1/f, so over -300..+300 mm the discrepancy is numerical noise;
    the paper's 10-57 % errors come from its integer disparities, not from eq. 13.
    """
    focus_mm = F_MM * D_LS_MM / (D_LS_MM - F_MM)
    inter_object_true = np.linspace(-300.0, 300.0, 601)
    image_distance = optics.image_distance_mm(focus_mm + inter_object_true, F_MM)
    inter_image = D_LS_MM - image_distance
    via_eq13 = optics.inter_object_depth_mm(inter_image, D_LS_MM, F_MM)
    worst_mm = float(np.max(np.abs(via_eq13 - inter_object_true)))
    print(f"eq. 13/14 vs exact thin lens over -300..+300 mm: worst difference {worst_mm:.3e} mm")
    assert worst_mm < 1e-6
    # The image side is strongly compressed (about M² = 1/361): 600 mm of scene fit in 1.84 mm behind the lens,
    # and unequally: the near 300 mm take twice the image depth of the far 300 mm.
    assert inter_image.max() - inter_image.min() == pytest.approx(1.8437, abs=0.001)
    assert -inter_image.min() / inter_image.max() == pytest.approx(1.922, abs=0.01)


def test_exact_thin_lens_disparity_round_trip_and_sign_convention():
    distances = np.array([700.0, 900.0, 1000.57, 1100.0, 1300.0])
    disparity = optics.thin_lens_disparity_mm(distances, D_LS_MM, F_MM, D_A_MM)
    assert disparity[0] < 0 and disparity[1] < 0 and abs(disparity[2]) < 1e-5
    assert disparity[3] > 0 and disparity[4] > disparity[3]
    back = optics.thin_lens_distance_mm(disparity, D_LS_MM, F_MM, D_A_MM)
    np.testing.assert_allclose(back, distances, rtol=1e-12)


def test_mca_optics_from_the_paper_profile_chain():
    model = MCAOptics.from_profile(load_profile("paper-70d"))
    assert model.filter_centre_distance_mm == pytest.approx(12.0)
    estimate = model.from_disparity(10)
    assert estimate.inter_image_depth_mm == pytest.approx(0.1796, abs=0.00005)
    assert estimate.inter_object_depth_mm == pytest.approx(69.67, abs=0.01)
    assert estimate.distance_mm == pytest.approx(model.focus_distance_mm + 69.67, abs=0.01)
    # distance -> disparity (thin lens) -> distance (eqs. 2, 13/14) closes the loop
    for distance in (850.0, 970.0, 1090.0, 1300.0):
        assert model.from_distance(distance).distance_mm == pytest.approx(distance, abs=1e-6)
    # inter-object depth -> inter-image depth inverts eq. 13/14
    for depth in (-150.0, -30.0, 60.0, 300.0):
        image = model.inter_image_depth_from_inter_object_mm(depth)
        assert model.inter_object_depth_mm(image) == pytest.approx(depth, abs=1e-9)


def test_channel_shift_convention_far_object_moves_toward_its_filter():
    aperture = load_profile("paper-70d").aperture
    # red filter sits right (+x), green top (+y up = -y in the image), blue left
    assert aperture.shift_per_disparity("red") == pytest.approx((0.5, -0.0))
    assert aperture.shift_per_disparity("green") == pytest.approx((0.0, -0.5))
    assert aperture.shift_per_disparity("blue") == pytest.approx((-0.5, -0.0))
    red_x, _ = aperture.shift_per_disparity("red")
    blue_x, _ = aperture.shift_per_disparity("blue")
    # one pixel of disparity is one pixel between the red and blue images
    assert red_x - blue_x == pytest.approx(1.0)
