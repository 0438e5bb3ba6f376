"""The RGB-D renderer against closed-form truth: thin-lens channel shifts, occlusion, continuity, noise, files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from image_shift import phase_shift_px

from mca.devices.profiles import load_profile
from mca.devices.sim.render import SensorModel
from mca.devices.sim.render_rgbd import (
    DepthRange,
    Realism,
    fill_from_farther_neighbour,
    render_filter_images,
    render_rgbd,
    rgbd_optics,
)

PROFILE = load_profile("paper-70d")
MIDDLEBURY = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "middlebury"
F_MM, FILTER_CENTRES_MM = 50.0, {"red": (6.0, 0.0), "green": (0.0, 6.0), "blue": (-6.0, 0.0)}


def _optics(width: int = 256, height: int = 192, focus_mm: float = 1000.0):
    # a sensor 22.5 mm wide imaged by `width` pixels
    return rgbd_optics(PROFILE, width, height, focus_mm, 22.5)


def _thin_lens_shift_px(channel: str, distance_mm: float, focus_mm: float, pitch_mm: float) -> tuple[float, float]:
    """From first principles: the lens focused at F puts the sensor at d_ls = f F / (F - f); a point at Z focuses at
    v = f Z / (Z - f); its ray through the filter centre p meets the sensor p (d_ls - v) / v from the chief ray,
    i.e. (+p_x, -p_y) (d_ls - v) / v / pitch pixels in the image (y down)."""
    d_ls = F_MM * focus_mm / (focus_mm - F_MM)
    v = F_MM * distance_mm / (distance_mm - F_MM)
    px, py = FILTER_CENTRES_MM[channel]
    scale = (d_ls - v) / v / pitch_mm
    return (px * scale, -py * scale)


def _texture(height: int, width: int, seed: int = 3, sigma: float = 2.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), sigma)
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    return (0.15 + 0.7 * noise).astype(np.float32)


def test_the_phase_correlation_measures_a_known_shift() -> None:
    from mca.devices.sim.render import shift_image

    grey = _texture(192, 256)
    for shift in ((0.74, 0.3), (-1.6, 2.2), (3.3, -0.45)):
        moved = shift_image(np.pad(grey, 30, mode="reflect"), shift)[30:-30, 30:-30]
        assert phase_shift_px(moved, grey) == pytest.approx(shift, abs=0.005)


@pytest.mark.parametrize("distance_mm", [1400.0, 820.0])  # behind and before the focus plane
def test_a_fronto_parallel_plane_is_shifted_by_the_thin_lens_amount_in_each_filter(distance_mm: float) -> None:
    optics = _optics()
    h, w = optics.height_px, optics.width_px
    grey = _texture(h, w)
    radiance = np.repeat(grey[..., None], 3, axis=2)
    images = render_filter_images(radiance, np.full((h, w), distance_mm), optics)
    pitch = 22.5 / w
    for index, channel in enumerate(("red", "green", "blue")):
        expected = _thin_lens_shift_px(channel, distance_mm, 1000.0, pitch)
        measured = phase_shift_px(images[..., index], grey)
        assert measured == pytest.approx(expected, abs=0.01), channel
    # red against blue: the same blur on both, the widest-pair disparity exactly
    red_blue = phase_shift_px(images[..., 0], images[..., 2])
    disparity = _thin_lens_shift_px("red", distance_mm, 1000.0, pitch)[0] * 2.0
    assert abs(disparity) > 1.5  # a sub-pixel part and more than a pixel: not a lucky integer
    assert red_blue == pytest.approx((disparity, 0.0), abs=0.01)


def test_the_nearer_surface_hides_the_farther_one_in_every_channel_and_uncovers_it_beside() -> None:
    optics = _optics(640, 320)
    h, w = optics.height_px, optics.width_px
    distance = np.full((h, w), 1500.0)  # background behind the focus plane
    distance[100:220, 200:440] = 800.0  # a rectangle before it
    radiance = np.full((h, w, 3), 0.8, np.float32)
    radiance[100:220, 200:440] = 0.1
    images = render_filter_images(radiance, distance, optics)
    pitch = 22.5 / w
    reach = max(
        math.hypot(*_thin_lens_shift_px(c, z, 1000.0, pitch)) for c in FILTER_CENTRES_MM for z in (800.0, 1500.0)
    )
    blur = 3.0 / 12.0 * 2.0 * reach  # filter diameter / d_a * disparity
    inset = int(math.ceil(reach + blur / 2 + 3))
    inner = images[100 + inset : 220 - inset, 200 + inset : 440 - inset]
    np.testing.assert_allclose(inner, 0.1, atol=0.01)  # no background light through the rectangle, any channel
    np.testing.assert_allclose(images[: 100 - inset], 0.8, atol=0.01)
    # no doubled light where the two overlap: every value lies between the two radiances
    assert images.min() > 0.1 - 0.01 and images.max() < 0.8 + 0.02
    # Disocclusion: the rectangle (before focus) moves red left, the background (behind) moves red right, so
    # red shows, right of the rectangle's red image, background that the chief-ray view hides behind the
    # rectangle: sensor x in (440 + s_front, 440 + s_back). It must be the background's light, not a hole.
    s_front = _thin_lens_shift_px("red", 800.0, 1000.0, pitch)[0]
    s_back = _thin_lens_shift_px("red", 1500.0, 1000.0, pitch)[0]
    assert s_back - s_front > 5.0  # a strip 5 px wide
    strip = images[130:190, int(math.ceil(440 + s_front + 1.5)) : int(math.floor(440 + s_back - 1.5)), 0]
    assert strip.size and np.abs(strip - 0.8).max() < 0.05
    # and blue the same on the left side
    b_front = _thin_lens_shift_px("blue", 800.0, 1000.0, pitch)[0]
    b_back = _thin_lens_shift_px("blue", 1500.0, 1000.0, pitch)[0]
    strip = images[130:190, int(math.ceil(200 + b_back + 1.5)) : int(math.floor(200 + b_front - 1.5)), 2]
    assert strip.size and np.abs(strip - 0.8).max() < 0.05
    # the rectangle's channels really moved: red's left edge left of blue's by the red-blue disparity
    row = images[160]
    red_left_edge = np.argmax(row[:, 0] < 0.45)
    blue_left_edge = np.argmax(row[:, 2] < 0.45)
    assert red_left_edge - blue_left_edge == pytest.approx(s_front - b_front, abs=1.0)


def test_a_slanted_uniform_surface_renders_without_seams() -> None:
    # one continuous surface whose disparity spans many slices: slices must add, never hide each other
    optics = _optics(200, 120)
    h, w = optics.height_px, optics.width_px
    ramp = np.linspace(1.0 / 800.0, 1.0 / 1500.0, w)[None, :] * np.ones((h, 1))
    radiance = np.full((h, w, 3), 0.5, np.float32)
    images = render_filter_images(radiance, 1.0 / ramp, optics)
    # A slanted surface seen through an off-axis filter is stretched or compressed: channel c lands at
    # x + s_c(x), so its irradiance is the radiance / (1 + ds_c/dx) (light conserved), red and blue opposite;
    # green moves along y only, a shear, and keeps 0.5. A seam between slices would break this by far more.
    pitch = 22.5 / w
    shift = np.array([_thin_lens_shift_px("red", 1.0 / v, 1000.0, pitch)[0] for v in ramp[0]])
    slope = np.gradient(shift)
    expected = {0: 0.5 / (1.0 + slope), 1: np.full(w, 0.5), 2: 0.5 / (1.0 - slope)}
    assert np.abs(slope).max() > 0.005  # the stretch is measurable
    for channel, profile in expected.items():
        # the irradiance at output x comes from the source at x - s(x): compare at the source positions
        positions = np.arange(w) + (shift if channel == 0 else -shift if channel == 2 else 0.0)
        along = np.interp(positions, np.arange(w), images[60, :, channel])
        np.testing.assert_allclose(along[15:-15], profile[15:-15], atol=0.0015)
        assert np.ptp(images[20:-20, 30:-30, channel], axis=0).max() < 0.004  # no seam along y either


def test_the_sensor_noise_has_the_variance_of_the_sensor_model() -> None:
    optics = _optics(240, 160)
    h, w = optics.height_px, optics.width_px
    level = 0.5  # sRGB value of the flat grey
    image = np.full((h, w, 3), level, np.float32)
    stereo = np.tile(np.linspace(10.0, 20.0, w, dtype=np.float32), (h, 1))
    sensor = SensorModel(iso=800.0, exposure=0.6)
    rendering = render_rgbd(
        image, stereo, np.ones((h, w), bool), optics, DepthRange(900.0, 1200.0), Realism(sensor=sensor), seed=5
    )
    linear = ((level + 0.055) / 1.055) ** 2.4  # sRGB decoding, IEC 61966-2-1
    electrons = linear * 0.6 * 26000.0 * 100.0 / 800.0  # exposure x full well at ISO 100 scaled to ISO 800
    gain = 26000.0 * 100.0 / 800.0 / (15000 - 2048)  # electrons per digital number
    variance = (electrons + 12.0**2) / gain**2 + 1.0 / 12.0  # photon + read noise, plus rounding
    dn = rendering.image_dn[20:-20, 20:-20].astype(np.float64)
    assert dn.mean(axis=(0, 1)) == pytest.approx([2048 + electrons / gain] * 3, rel=0.005)
    assert dn.var(axis=(0, 1)) == pytest.approx([variance] * 3, rel=0.05)


def test_truth_maps_the_stereo_disparity_affinely_onto_inverse_distance() -> None:
    optics = _optics(120, 90)
    h, w = optics.height_px, optics.width_px
    rng = np.random.default_rng(0)
    stereo = rng.uniform(30.0, 90.0, (h, w)).astype(np.float32)
    stereo = cv2.GaussianBlur(stereo, (0, 0), 3)
    valid = np.ones((h, w), bool)
    valid[10:20, 30:40] = False
    image = np.repeat(_texture(h, w)[..., None], 3, axis=2)
    rendering = render_rgbd(image, stereo, valid, optics, DepthRange(850.0, 1400.0), Realism(SensorModel(noise=False)))
    d_min, d_max = stereo[valid].min(), stereo[valid].max()
    inverse = 1 / 1400.0 + (stereo - d_min) / (d_max - d_min) * (1 / 850.0 - 1 / 1400.0)
    np.testing.assert_allclose(rendering.distance_mm[valid], (1.0 / inverse)[valid], rtol=1e-5)
    assert np.isnan(rendering.distance_mm[~valid]).all() and np.isnan(rendering.disparity_px[~valid]).all()
    pitch = 22.5 / w
    z = rendering.distance_mm[valid].astype(np.float64)
    red = np.array([_thin_lens_shift_px("red", v, 1000.0, pitch)[0] for v in z[:200]])
    np.testing.assert_allclose(rendering.disparity_px[valid][:200], 2.0 * red, rtol=1e-4, atol=1e-4)
    assert rendering.truth["near_mm"] == 850.0 and rendering.truth["far_mm"] == 1400.0
    low, high = rendering.truth["disparity_range_px"]
    assert low == pytest.approx(np.nanmin(rendering.disparity_px)) and high == pytest.approx(
        np.nanmax(rendering.disparity_px)
    )


def test_unknown_disparity_is_filled_from_the_farther_neighbour_on_its_row() -> None:
    d = np.array([[5, 0, 0, 9, 9], [0, 0, 7, 0, 3], [0, 0, 0, 0, 0]], np.float32)
    filled = fill_from_farther_neighbour(d, d > 0)
    np.testing.assert_array_equal(filled, [[5, 5, 5, 9, 9], [7, 7, 7, 3, 3], [3, 3, 3, 3, 3]])


def test_vignetting_and_crosstalk_follow_their_definitions() -> None:
    from mca.devices.sim.render_rgbd import POLY_K2_RANGE, POLY_K4_RANGE, POLY_K_TYPICAL, sensor_signal, vignetting_gain

    optics = _optics(100, 80)
    cos4 = vignetting_gain(Realism(vignetting="cos4"), optics)
    corner_mm = math.hypot(49.5, 39.5) * optics.pixel_pitch_mm
    assert cos4[0, 0] == pytest.approx(math.cos(math.atan(corner_mm / optics.sensor_distance_mm)) ** 4, rel=1e-5)
    assert cos4.max() == pytest.approx(1.0, abs=1e-4)  # the centre pixels, half a pixel off the axis
    poly = vignetting_gain(Realism(vignetting="poly"), optics)  # no coefficients given: the typical ones
    assert Realism().vignetting_k == POLY_K_TYPICAL
    assert pytest.approx((sum(POLY_K2_RANGE) / 2, sum(POLY_K4_RANGE) / 2)) == POLY_K_TYPICAL
    k2, k4 = POLY_K_TYPICAL
    rn2 = (math.hypot(49.5, 39.5) / math.hypot(50.0, 40.0)) ** 2  # the corner pixel's centre, over the half-diagonal
    assert poly[0, 0] == pytest.approx(1.0 + k2 * rn2 + k4 * rn2 * rn2, rel=1e-5) and poly[0, 0] < 0.75
    assert poly.max() == pytest.approx(1.0, abs=1e-4)
    mix = ((0.9, 0.07, 0.03), (0.05, 0.9, 0.05), (0.02, 0.08, 0.9))
    images = np.zeros((80, 100, 3), np.float32)
    images[..., 1] = 1.0  # light through the green filter only
    signal = sensor_signal(images, Realism(SensorModel(exposure=0.5), crosstalk=mix), optics)
    np.testing.assert_allclose(signal[5, 5], [0.5 * 0.07, 0.5 * 0.9, 0.5 * 0.08], rtol=1e-6)


@pytest.mark.parametrize("fmt", ["tiff", "cr2"])
def test_written_captures_are_read_with_the_rendered_pitch_and_orientation(tmp_path, fmt: str) -> None:
    from mca.capture.pipeline_app import read_input
    from mca.capture.simulated_shots import RgbdSource, render_rgbd_capture, write_rgbd_capture

    h, w = 96, 160
    image = np.dstack([_texture(h, w, 1), _texture(h, w, 2), _texture(h, w, 3)])
    image[:10, :20] = 1.0  # a white corner: top-left stays top-left
    stereo = np.tile(np.linspace(10.0, 20.0, w, dtype=np.float32), (h, 1))
    source = RgbdSource("flat", image, stereo, np.ones((h, w), bool), Path("im.png"), Path("disp.png"), 1.0)
    capture = render_rgbd_capture(source, PROFILE, fmt=fmt, realism=Realism(SensorModel(noise=False)), seed=0)
    paths = write_rgbd_capture(capture, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [paths["image"].name, "truth"]
    loaded = read_input(paths["image"])
    truth = json.loads(paths["truth"].read_text())
    assert loaded.input_size_px == (w, h)
    assert loaded.pixel_pitch_mm == pytest.approx(truth["optics"]["pixel_pitch_mm"], rel=1e-9)
    planes = loaded.planes
    assert planes[: 4 // int(loaded.pixel_scale), : 8 // int(loaded.pixel_scale)].mean() > 0.5  # the white corner
    assert planes[-10:, -10:].mean() < 0.5
    from mca.devices.profiles import load_profile_file

    focused = load_profile_file(paths["profile"])
    assert focused.lens.focus_distance_mm == pytest.approx(truth["focus_distance_mm"], rel=1e-9)
    assert (focused.aperture, focused.model) == (PROFILE.aperture, PROFILE.model)


def test_a_native_pitch_render_is_a_window_of_the_sensor_read_back_with_the_bodys_pitch(tmp_path) -> None:
    """--pitch native: each pixel is one photosite of the body. The written TIFF names no camera, so `mca process`
    takes the profile's pitch; the red-blue shift measured in the file is the thin lens's at that pitch (4.1 um),
    where the same scene on the whole sensor width ("frame") moves by the sensor's width over the image's less."""
    from mca.capture.api import optics_for, pitch_note, read_input
    from mca.capture.simulated_shots import RgbdSource, render_rgbd_capture, write_rgbd_capture
    from mca.devices.profiles import load_profile_file

    h, w = 160, 224
    grey = _texture(h, w, 5, sigma=1.5)
    image = np.repeat(grey[..., None], 3, axis=2)
    stereo = np.full((h, w), 14.0, np.float32)  # one plane at the depth range's far end
    stereo[:6, :6] = 15.0  # and a corner at its near end (the range needs two depths); not measured
    source = RgbdSource("plane", image, stereo, np.ones((h, w), bool), Path("im.png"), Path("disp.png"), 1.0)
    quiet = Realism(SensorModel(noise=False))
    shifts = {}
    for pitch in ("frame", "native"):
        capture = render_rgbd_capture(
            source,
            PROFILE,
            realism=quiet,
            depth_range=DepthRange(900.0, 1150.0),
            focus_distance_mm=1000.0,
            seed=0,
            name=f"plane-{pitch}",
            pitch=pitch,
        )
        paths = write_rgbd_capture(capture, tmp_path / pitch)
        truth = json.loads(paths["truth"].read_text())
        assert truth["pitch"] == pitch
        loaded = read_input(paths["image"])
        profile = load_profile_file(paths["profile"])
        optics = optics_for(profile, loaded)
        if pitch == "native":
            assert loaded.pixel_pitch_mm is None  # the file names no body
            assert optics.pixel_pitch_mm == PROFILE.pixel_pitch_mm == truth["optics"]["pixel_pitch_mm"]
            assert (profile.width_px, profile.height_px) == (w, h) and pitch_note(profile, loaded) is None
        else:
            assert loaded.pixel_pitch_mm == pytest.approx(22.5 / w, rel=1e-9)
        planes = loaded.planes
        measured = phase_shift_px(planes[24:-16, 24:-16, 0], planes[24:-16, 24:-16, 2])[0]
        expected = 2.0 * _thin_lens_shift_px("red", 1150.0, 1000.0, optics.pixel_pitch_mm)[0]
        assert measured == pytest.approx(expected, abs=0.03), pitch
        assert np.median(capture.disparity_px[6:, 6:]) == pytest.approx(expected, abs=1e-3)  # as the truth says
        shifts[pitch] = measured
    assert shifts["native"] / shifts["frame"] == pytest.approx(22.5 / (PROFILE.pixel_pitch_mm * w), rel=0.01)


def test_a_native_pitch_cr2_is_refused_with_what_to_do() -> None:
    from mca.capture.simulated_shots import RgbdSource, render_rgbd_capture

    source = RgbdSource(
        "plane",
        np.full((64, 96, 3), 0.5, np.float32),
        np.ones((64, 96), np.float32),
        np.ones((64, 96), bool),
        Path("im.png"),
        Path("disp.png"),
        1.0,
    )
    with pytest.raises(ValueError, match="use --format tiff"):
        render_rgbd_capture(source, PROFILE, fmt="cr2", pitch="native")
    with pytest.raises(ValueError, match="pitch must be one of frame, native"):
        render_rgbd_capture(source, PROFILE, pitch="sensor")


@pytest.mark.skipif(not MIDDLEBURY.is_dir(), reason=f"the Middlebury scenes are not at {MIDDLEBURY}")
def test_a_tree_at_native_pitch_keeps_each_seeds_draw_with_four_times_the_disparities(tmp_path) -> None:
    from mca.capture.simulated_shots import render_rgbd_tree

    frame = render_rgbd_tree(MIDDLEBURY, tmp_path, PROFILE, seeds=(1,), scenes=("Venus",), width_px=300)
    native = render_rgbd_tree(
        MIDDLEBURY, tmp_path, PROFILE, seeds=(1,), scenes=("Venus",), width_px=300, pitch="native"
    )
    assert [o.name for o in frame + native] == ["Venus-s1", "Venus-s1-native"]
    truths = [json.loads((tmp_path / "truth" / f"{n}.json").read_text()) for n in ("Venus-s1", "Venus-s1-native")]
    assert truths[0]["draw"] == truths[1]["draw"]  # the same scene, focus, depth range and sensor
    ratio = truths[0]["optics"]["pixel_pitch_mm"] / truths[1]["optics"]["pixel_pitch_mm"]
    assert ratio == pytest.approx(22.5 / (300 * PROFILE.pixel_pitch_mm), rel=1e-9)
    low_f, high_f = truths[0]["disparity_range_px"]
    low_n, high_n = truths[1]["disparity_range_px"]
    assert (low_n, high_n) == pytest.approx((low_f * ratio, high_f * ratio), rel=1e-3)


@pytest.mark.skipif(not MIDDLEBURY.is_dir(), reason=f"the Middlebury scenes are not at {MIDDLEBURY}")
def test_a_middlebury_tree_renders_with_randomised_realism(tmp_path) -> None:
    from mca.capture.simulated_shots import render_rgbd_tree

    outcomes = render_rgbd_tree(MIDDLEBURY, tmp_path, PROFILE, seeds=(1, 2), scenes=("Venus",), width_px=300)
    assert [o.status for o in outcomes] == ["rendered", "rendered"]
    truths = [json.loads((tmp_path / "truth" / f"Venus-s{s}.json").read_text()) for s in (1, 2)]
    assert truths[0]["draw"] != truths[1]["draw"]  # each seed its own realism
    for truth in truths:
        draw = truth["draw"]
        assert 800.0 <= draw["focus_distance_mm"] <= 1400.0
        assert truth["near_mm"] == draw["near_mm"] and truth["far_mm"] == draw["far_mm"]
        assert truth["source"]["disparity_scale"] == 8.0  # from Venus's SOURCE.txt
        assert truth["optics"]["width_px"] == 300
    again = render_rgbd_tree(MIDDLEBURY, tmp_path, PROFILE, seeds=(1,), scenes=("Venus",), width_px=300)
    assert [o.status for o in again] == ["cached"]


def test_the_mosaic_samples_each_colour_at_its_own_bayer_site() -> None:
    """Through the RGGB mosaic, a plane's red and blue half-resolution planes are apart by half the red-blue
    disparity plus the sites' own offset, which the application's Bayer offsets (what `mca process` removes)
    account for exactly."""
    from mca.capture.api import bayer_channel_offsets_px
    from mca.devices.sim.render_rgbd import expose_mosaic, sensor_signal
    from mca.processing.evaluate import bayer_planes

    optics = _optics(320, 256)
    h, w = optics.height_px, optics.width_px
    grey = _texture(h, w, sigma=3.0)
    images = render_filter_images(np.repeat(grey[..., None], 3, axis=2), np.full((h, w), 1400.0), optics)
    sensor = SensorModel(noise=False, exposure=0.6)
    mosaic = expose_mosaic(sensor_signal(images, Realism(sensor), optics), sensor, np.random.default_rng(0))
    planes = bayer_planes(mosaic, sensor.black_level, sensor.white_level)
    offsets = bayer_channel_offsets_px("RGGB")  # (dx, dy) of R, G, B samples in half-resolution px
    measured = phase_shift_px(planes[..., 0], planes[..., 2], border=20)
    disparity = optics.disparity_px(1400.0)
    # red content at full-res x + d/2 sampled on even sites, blue at x - d/2 on odd ones
    expected_x = disparity / 2.0 - (offsets[0][0] - offsets[2][0])
    expected_y = -(offsets[0][1] - offsets[2][1])
    assert measured == pytest.approx((expected_x, expected_y), abs=0.02)


@pytest.mark.skipif(not MIDDLEBURY.is_dir(), reason=f"the Middlebury scenes are not at {MIDDLEBURY}")
def test_the_dev_set_refuses_the_options_it_would_ignore_and_writes_nothing(tmp_path) -> None:
    from typer.testing import CliRunner

    from mca.capture.cli import app

    out = tmp_path / "dev"
    result = CliRunner().invoke(
        app,
        ["simulate", "--from-rgbd-tree", str(MIDDLEBURY), "--dev-set", "--pitch", "native", "--seeds", "3"]
        + ["--out", str(out)],
    )
    assert result.exit_code == 2, result.output
    assert "drop --seeds, --pitch" in result.output and "leave out --dev-set" in result.output
    assert not any(p.is_file() for p in out.rglob("*"))  # refused before the first render
