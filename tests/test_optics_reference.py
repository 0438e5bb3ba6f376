"""Depth optics against truth that does not pass through the code under test: ray geometry written here.

Every expected value below comes from the Gaussian lens equation 1/f = 1/u + 1/v and similar triangles,
computed in this file from the paper's setup (section VI-A: EF 50 mm, d_ls = 52.63 mm, filter centres
12 mm apart, 70D photosites 4.109 um), never from `mca.processing.optics`, `mca.processing.camera` or
the profile loader. So a wrong loader (d_ls 0.1 % too long moves the focus plane by 18.6 mm), a wrong
equation or a wrong sign fails here even if the simulator and the pipeline share the mistake.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mca.devices.profiles import load_profile, load_profile_file
from mca.processing import optics
from mca.processing.camera import ProfileError
from mca.processing.depth import depth_map_mm, region_depth
from mca.processing.optics import MCAOptics

# The paper's setup, section VI-A (numbers from the paper's text, not from the profile file)
F_MM = 50.0
D_LS_MM = 52.63
D_A_MM = 12.0
PITCH_MM = 0.004109
FOCUS_MM = 1.0 / (1.0 / F_MM - 1.0 / D_LS_MM)  # 1000.5703 mm: "focused at 100 cm"


def image_distance(u_mm: float, f_mm: float = F_MM) -> float:
    """v from 1/f = 1/u + 1/v."""
    return 1.0 / (1.0 / f_mm - 1.0 / u_mm)


def ray_disparity_mm(u_mm: float, d_ls: float = D_LS_MM, f_mm: float = F_MM, d_a: float = D_A_MM) -> float:
    """Where the chief rays through the two filter centres (+-d_a/2) cross the sensor, traced here.

    A ray from aperture height h toward the on-axis image point at v meets the sensor plane (d_ls behind
    the lens) at h (1 - d_ls / v). The two sub-images are then d_a |1 - d_ls/v| apart; positive (farther
    than focus) when the image forms in front of the sensor (v < d_ls).
    """
    v = image_distance(u_mm, f_mm)
    at_red = (d_a / 2) * (1 - d_ls / v)
    at_blue = (-d_a / 2) * (1 - d_ls / v)
    return at_blue - at_red  # = d_a (d_ls/v - 1): > 0 when v < d_ls


DISTANCES_MM = [450.0, 600.0, 800.0, 950.0, 1000.5703422053223, 1050.0, 1200.0, 1600.0, 2500.0, 6000.0]


def test_the_paper_profile_is_focused_at_100_cm_to_the_tenth_of_a_millimetre() -> None:
    profile = load_profile("paper-70d")
    assert profile.lens is not None
    assert profile.lens.sensor_distance_mm == pytest.approx(D_LS_MM, rel=1e-9)
    assert profile.lens.focal_length_mm == pytest.approx(F_MM, rel=1e-9)
    assert profile.aperture.baseline_mm == pytest.approx(D_A_MM, rel=1e-9)
    assert profile.pixel_pitch_mm == pytest.approx(PITCH_MM, rel=1e-9)
    bound = MCAOptics.from_profile(profile)
    # d_ls 0.1 % too long would put the focus plane at 981.9 mm
    assert bound.focus_distance_mm == pytest.approx(FOCUS_MM, abs=0.1)
    assert profile.lens.focus_distance_mm == pytest.approx(FOCUS_MM, abs=0.1)
    assert bound.magnification == pytest.approx((D_LS_MM - F_MM) / F_MM, rel=1e-12)


@pytest.mark.parametrize("distance_mm", DISTANCES_MM)
def test_a_point_at_a_known_distance_comes_back_from_its_traced_disparity(distance_mm: float) -> None:
    bound = MCAOptics.from_profile(load_profile("paper-70d"))
    disparity_px = ray_disparity_mm(distance_mm) / PITCH_MM
    assert float(bound.distance_mm(disparity_px)) == pytest.approx(distance_mm, rel=1e-9, abs=1e-6)
    estimate = bound.from_disparity(disparity_px)
    v = image_distance(distance_mm)
    assert estimate.disparity_px == pytest.approx(disparity_px)
    assert estimate.inter_image_depth_mm == pytest.approx(D_LS_MM - v, rel=1e-9, abs=1e-12)  # eq. 2
    assert estimate.inter_object_depth_mm == pytest.approx(distance_mm - FOCUS_MM, rel=1e-9, abs=1e-6)  # eqs. 13/14
    assert estimate.distance_mm == pytest.approx(distance_mm, rel=1e-9)
    # and the way back: the exact model's disparity for that distance is the traced one
    assert float(bound.disparity_px_at_distance(distance_mm)) == pytest.approx(disparity_px, rel=1e-9, abs=1e-9)
    back = bound.from_distance(distance_mm)
    assert back.distance_mm == pytest.approx(distance_mm, rel=1e-9)
    assert bound.from_inter_image_depth(D_LS_MM - v).distance_mm == pytest.approx(distance_mm, rel=1e-9)
    # region depth (processing/depth.py) gives the same chain
    region = region_depth(disparity_px, bound)
    assert region.inter_image_depth_mm == pytest.approx(D_LS_MM - v, rel=1e-9, abs=1e-12)
    assert region.inter_object_depth_mm == pytest.approx(distance_mm - FOCUS_MM, rel=1e-9, abs=1e-6)
    assert region.distance_mm == pytest.approx(distance_mm, rel=1e-9)
    assert region.disparity_px == disparity_px


def test_sign_convention_farther_is_positive() -> None:
    bound = MCAOptics.from_profile(load_profile("paper-70d"))
    far = bound.from_distance(1500.0)
    near = bound.from_distance(700.0)
    assert far.disparity_px > 0 and far.inter_image_depth_mm > 0 and far.inter_object_depth_mm > 0
    assert near.disparity_px < 0 and near.inter_image_depth_mm < 0 and near.inter_object_depth_mm < 0
    # 1 px of disparity at the focus plane: a few mm of depth (the paper's "millimetre-order" claim)
    one_px = bound.from_disparity(1.0)
    v_one_px = D_A_MM * D_LS_MM / (D_A_MM + PITCH_MM)  # sensor crossing d_a (d_ls/v - 1) = pitch
    u_one_px = 1.0 / (1.0 / F_MM - 1.0 / v_one_px)
    assert one_px.distance_mm == pytest.approx(u_one_px, rel=1e-9)
    assert 3.0 < one_px.inter_object_depth_mm < 10.0


def test_the_free_functions_against_the_traced_geometry() -> None:
    m = (D_LS_MM - F_MM) / F_MM
    for u in DISTANCES_MM:
        v = image_distance(u)
        delta = ray_disparity_mm(u)
        dd = D_LS_MM - v
        assert optics.magnification(D_LS_MM, F_MM) == pytest.approx(m)
        assert optics.image_distance_mm(u, F_MM) == pytest.approx(v, rel=1e-12)
        assert optics.thin_lens_disparity_mm(u, D_LS_MM, F_MM, D_A_MM) == pytest.approx(delta, rel=1e-9, abs=1e-12)
        assert optics.thin_lens_distance_mm(delta, D_LS_MM, F_MM, D_A_MM) == pytest.approx(u, rel=1e-9)
        assert optics.inter_image_depth_mm(delta, D_LS_MM, D_A_MM) == pytest.approx(dd, rel=1e-9, abs=1e-12)
        assert optics.disparity_mm_from_inter_image_depth(dd, D_LS_MM, D_A_MM) == pytest.approx(
            delta, rel=1e-9, abs=1e-12
        )
        assert optics.inter_object_depth_from_disparity_mm(delta, D_LS_MM, F_MM, D_A_MM) == pytest.approx(
            u - FOCUS_MM, rel=1e-9, abs=1e-6
        )
        signed = optics.inter_object_depth_mm(dd, D_LS_MM, F_MM)
        assert isinstance(signed, float)
        assert signed == pytest.approx(u - FOCUS_MM, rel=1e-9, abs=1e-6)
        if dd >= 0:
            assert optics.inter_object_depth_far_mm(dd, D_LS_MM, F_MM) == pytest.approx(
                u - FOCUS_MM, rel=1e-9, abs=1e-6
            )
        else:
            assert optics.inter_object_depth_near_mm(-dd, D_LS_MM, F_MM) == pytest.approx(
                FOCUS_MM - u, rel=1e-9, abs=1e-6
            )
        assert optics.inter_image_depth_from_inter_object_depth_mm(u - FOCUS_MM, D_LS_MM, F_MM) == pytest.approx(
            dd, rel=1e-9, abs=1e-12
        )


def test_arrays_go_through_elementwise_and_stay_arrays() -> None:
    bound = MCAOptics(F_MM, D_LS_MM, D_A_MM, PITCH_MM)
    u = np.array(DISTANCES_MM)
    disparity_px = np.array([ray_disparity_mm(x) for x in DISTANCES_MM]) / PITCH_MM
    got = bound.distance_mm(disparity_px)
    assert isinstance(got, np.ndarray)
    np.testing.assert_allclose(got, u, rtol=1e-9)
    image = bound.inter_image_depth_mm(disparity_px)
    np.testing.assert_allclose(bound.disparity_px(image), disparity_px, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(bound.inter_image_depth_from_inter_object_mm(u - FOCUS_MM), image, rtol=1e-9, atol=1e-12)
    # the dense map (processing/depth.py): float32, NaN where not valid
    grid = disparity_px.reshape(2, 5)
    valid = np.ones(grid.shape, bool)
    valid[1, 3] = False
    dense = depth_map_mm(grid, bound, valid)
    assert dense.dtype == np.float32
    assert np.isnan(dense[1, 3])
    ok = valid
    np.testing.assert_allclose(dense[ok], u.reshape(2, 5)[ok], rtol=1e-6)
    np.testing.assert_allclose(depth_map_mm(grid, bound), u.reshape(2, 5), rtol=1e-6)


@given(st.floats(min_value=300.0, max_value=20000.0))
def test_any_distance_round_trips_through_the_traced_disparity(distance_mm: float) -> None:
    bound = MCAOptics(F_MM, D_LS_MM, D_A_MM, PITCH_MM)
    disparity_px = ray_disparity_mm(distance_mm) / PITCH_MM
    assert float(bound.distance_mm(disparity_px)) == pytest.approx(distance_mm, rel=1e-8)


def test_a_profile_given_its_focus_distance_puts_the_sensor_where_the_lens_equation_says(tmp_path) -> None:
    text = (
        'name = "focus-given"\n[camera]\nmodel = "x"\npixel_pitch_mm = 0.004\n'
        "[lens]\nfocal_length_mm = 50.0\nfocus_distance_mm = 1500.0\n"
        "[aperture]\nfilter_diameter_mm = 3.0\nred = [6.0, 0.0]\ngreen = [0.0, 6.0]\nblue = [-6.0, 0.0]\n"
    )
    path = tmp_path / "focus.toml"
    path.write_text(text)
    profile = load_profile_file(path)
    assert profile.lens is not None
    assert profile.lens.sensor_distance_mm == pytest.approx(image_distance(1500.0), rel=1e-12)
    bound = MCAOptics.from_profile(profile)
    assert bound.focus_distance_mm == pytest.approx(1500.0, rel=1e-12)
    assert bound.pixel_pitch_mm == 0.004
    assert MCAOptics.from_profile(profile, pixel_pitch_mm=0.008).pixel_pitch_mm == 0.008


def test_a_profile_without_lens_or_pitch_says_what_is_missing() -> None:
    profile = load_profile("bando2008")
    with pytest.raises(ValueError, match=r"bando2008.*no \[lens\]"):
        MCAOptics.from_profile(profile)
    paper = load_profile("paper-70d")
    from dataclasses import replace

    no_pitch = replace(paper, pixel_pitch_mm=None)
    with pytest.raises(ValueError, match=r"paper-70d.*pixel_pitch_mm"):
        MCAOptics.from_profile(no_pitch)
    assert MCAOptics.from_profile(no_pitch, pixel_pitch_mm=0.005).pixel_pitch_mm == 0.005
    with pytest.raises(ProfileError):
        load_profile_file("/nonexistent/profile.toml")
    assert math.isfinite(MCAOptics.from_profile(paper).focus_distance_mm)


def test_bound_optics_cannot_be_changed_after_the_fact() -> None:
    from dataclasses import FrozenInstanceError

    bound = MCAOptics(F_MM, D_LS_MM, D_A_MM, PITCH_MM)
    with pytest.raises(FrozenInstanceError):
        bound.sensor_distance_mm = 60.0  # type: ignore[misc]
    region = region_depth(2.0, bound)
    with pytest.raises(FrozenInstanceError):
        region.distance_mm = 1.0  # type: ignore[misc]
