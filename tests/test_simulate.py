"""The MCA simulator against the optics it claims to follow: channel displacements, occlusion, noise, truth, CR2."""

from __future__ import annotations

import json

import numpy as np
import pytest
from skimage.registration import phase_cross_correlation

from mca.devices.profiles import load_profile
from mca.devices.sim.render import Layer, Scene, SensorModel, SimulationOptics, Slant, render
from mca.devices.sim.scenes import rounded_rect, target_scene
from mca.devices.sim.textures import Texture
from mca.processing.optics import MCAOptics

PROFILE = load_profile("paper-70d")
SMALL = SimulationOptics.from_profile(PROFILE, 0.25)  # 1368 x 912 mosaic, pitch 4x the 70D's
NOISELESS = SensorModel(noise=False)


def _shift_px(reference: np.ndarray, moving: np.ndarray) -> tuple[float, float]:
    """(dx, dy) in plane pixels by which `moving` is displaced relative to `reference` (cross-correlation)."""
    crop = (slice(60, -60), slice(60, -60))
    shift, _, _ = phase_cross_correlation(reference[crop], moving[crop], upsample_factor=200, normalization=None)
    return -float(shift[1]), -float(shift[0])


@pytest.mark.parametrize("inter_object_depth_mm", [-150.0, -60.0, 30.0, 90.0, 300.0])
def test_channel_displacements_follow_the_thin_lens(inter_object_depth_mm: float) -> None:
    distance = SMALL.focus_distance_mm + inter_object_depth_mm
    rendering = render(target_scene(distance), SMALL, NOISELESS, cosited=True)
    red, green, blue = (rendering.planes_linear[..., i] for i in range(3))
    expected = float(MCAOptics.from_profile(PROFILE, SMALL.pixel_pitch_mm).disparity_px_at_distance(distance))
    # Red moves right and blue left for a farther plane: red - blue = disparity (mosaic px = 2 plane px).
    dx, dy = _shift_px(blue, red)
    assert 2 * dx == pytest.approx(expected, abs=0.05)
    assert 2 * dy == pytest.approx(0.0, abs=0.05)
    # Green (filter above the axis) moves up by half the disparity relative to the red/blue midpoint.
    gx, gy = _shift_px(blue, green)
    assert 2 * gx == pytest.approx(expected / 2, abs=0.05)
    assert 2 * gy == pytest.approx(-expected / 2, abs=0.05)


def test_bayer_sites_add_their_offsets() -> None:
    """Sampled at the RGGB sites (red one pixel left of and above blue), the red plane's content appears one
    pixel right of and below the blue plane's, on top of the disparity."""
    distance = SMALL.focus_distance_mm + 90.0
    rendering = render(target_scene(distance), SMALL, NOISELESS)
    dx, dy = _shift_px(rendering.planes_linear[..., 2], rendering.planes_linear[..., 0])
    assert 2 * dx == pytest.approx(SMALL.disparity_px(distance) + 1.0, abs=0.05)
    assert 2 * dy == pytest.approx(1.0, abs=0.05)


def test_disparity_scales_with_render_size() -> None:
    full = SimulationOptics.from_profile(PROFILE)
    assert (full.width_px, full.height_px) == (5472, 3648)
    assert full.pixel_pitch_mm == pytest.approx(0.004109)
    distance = full.focus_distance_mm + 60.0
    assert SMALL.disparity_px(distance) == pytest.approx(full.disparity_px(distance) / 4, rel=1e-9)
    # Blur disk = filter diameter / d_a x disparity (3 mm / 12 mm).
    assert full.blur_diameter_px(distance) == pytest.approx(0.25 * full.disparity_px(distance))


def test_perturbed_lens_moves_the_focus_plane() -> None:
    nominal_focus = SMALL.focus_distance_mm
    lens = SMALL.perturbed(focal_length_factor=1.01)
    assert lens.focus_distance_mm > nominal_focus + 100.0  # a longer focal length focuses farther
    rendering = render(target_scene(nominal_focus), lens, NOISELESS, cosited=True)
    dx, _ = _shift_px(rendering.planes_linear[..., 2], rendering.planes_linear[..., 0])
    assert 2 * dx == pytest.approx(lens.disparity_px(nominal_focus), abs=0.05)
    assert lens.disparity_px(nominal_focus) < -1.0


def _two_squares() -> Scene:
    focus = SMALL.focus_distance_mm
    flat = Texture("gravel", 0.2, 0.0)
    near = Layer(1, "red square", "red", (0.8, 0.1, 0.1), focus - 40.0, flat, rounded_rect(0.6, 0.5, 0.4, 0.4, 0.0))
    far = Layer(2, "blue square", "blue", (0.1, 0.1, 0.8), focus + 120.0, flat, rounded_rect(0.9, 0.5, 0.4, 0.4, 0.0))
    return Scene("two-squares", "a near red square over a far blue one", (near, far), None)


def test_occlusion_composites_the_nearer_layer_over_the_farther() -> None:
    rendering = render(_two_squares(), SMALL, NOISELESS, cosited=True)
    h = SMALL.height_px // 2
    planes = rendering.planes_linear
    overlap = planes[int(0.45 * h) : int(0.55 * h), int(0.72 * h) : int(0.78 * h)]  # both squares cover this
    only_far = planes[int(0.45 * h) : int(0.55 * h), int(0.92 * h) : int(1.0 * h)]
    exposure = NOISELESS.exposure
    assert np.allclose(overlap.mean(axis=(0, 1)), np.array([0.8, 0.1, 0.1]) * exposure, atol=0.01)
    assert np.allclose(only_far.mean(axis=(0, 1)), np.array([0.1, 0.1, 0.8]) * exposure, atol=0.01)
    labels = rendering.labels
    assert labels[int(0.5 * SMALL.height_px), int(0.75 * SMALL.height_px)] == 1
    assert labels[int(0.5 * SMALL.height_px), int(0.95 * SMALL.height_px)] == 2
    objects = {o["id"]: o for o in rendering.truth["objects"]}
    assert objects[1]["occludes"] == [2] and objects[2]["occludes"] == []
    assert objects[1]["order"] == 0 and objects[2]["order"] == 1


def test_photon_and_read_noise_statistics() -> None:
    sensor = SensorModel(iso=400, read_noise_e=8.0)
    scene = target_scene(SMALL.focus_distance_mm)
    flat = Scene(
        scene.name,
        "uniform grey",
        (
            Layer(
                1,
                "grey",
                "grey",
                (0.5, 0.5, 0.5),
                SMALL.focus_distance_mm,
                Texture("gravel", 0.2, 0.0),
                scene.objects[0].shape,
            ),
        ),
    )
    rendering = render(flat, SMALL, sensor, seed=3)
    red = rendering.mosaic[0::2, 0::2].astype(np.float64)
    electrons = 0.5 * sensor.exposure * sensor.saturation_e
    gain = sensor.electrons_per_dn
    assert red.mean() == pytest.approx(sensor.black_level + electrons / gain, abs=0.5)
    expected_var = (electrons + sensor.read_noise_e**2) / gain**2 + 1 / 12
    assert red.var() == pytest.approx(expected_var, rel=0.03)
    # Without noise the mosaic is the rounded expectation.
    clean = render(flat, SMALL, SensorModel(iso=400, noise=False))
    assert clean.mosaic[0::2, 0::2].std() < 1.0


def test_truth_is_consistent_with_the_optics() -> None:
    focus = SMALL.focus_distance_mm
    knife = Layer(
        1,
        "knife",
        "steel",
        (0.5, 0.5, 0.5),
        focus + 35.0,
        texture=Texture(),
        shape=rounded_rect(0.75, 0.5, 1.0, 0.1, 0.0),
        slant=Slant(focus - 30.0, focus + 100.0, "x"),
    )
    scene = Scene("slant", "a slanted bar", (knife,), None)
    rendering = render(scene, SMALL, NOISELESS)
    optics = MCAOptics.from_profile(PROFILE, SMALL.pixel_pitch_mm)
    (entry,) = rendering.truth["objects"]
    assert entry["disparity_px"] == pytest.approx(float(optics.disparity_px_at_distance(focus + 35.0)))
    assert entry["inter_object_depth_mm"] == pytest.approx(35.0)
    assert float(optics.distance_mm(entry["disparity_px"])) == pytest.approx(focus + 35.0, abs=1e-6)
    assert entry["slant"]["from_inter_object_depth_mm"] == pytest.approx(-30.0)
    # The bar is a true plane: 1/distance (hence the disparity) is affine along it, from one end to the other.
    row = rendering.depth_mm[SMALL.height_px // 2]
    inside = np.nonzero(rendering.labels[SMALL.height_px // 2] == 1)[0]
    assert row[inside[0]] == pytest.approx(focus - 30.0, abs=0.5)
    assert row[inside[-1]] == pytest.approx(focus + 100.0, abs=0.5)
    assert np.all(np.diff(row[inside]) > 0)
    inverse = 1.0 / row[inside].astype(np.float64)
    line = np.polyfit(inside, inverse, 1)
    assert np.abs(np.polyval(line, inside) - inverse).max() < 1e-3 * (inverse.max() - inverse.min())
    distance = np.polyfit(inside, row[inside].astype(np.float64), 1)  # a linear distance ramp is not a plane
    assert np.abs(np.polyval(distance, inside) - row[inside]).max() > 1.0
    low, high = entry["slant"]["extent_px"]
    assert abs(low - inside[0]) <= 1.0 and abs(high - inside[-1]) <= 1.0
    assert knife.distance_at_mm(0.75) == pytest.approx(1.0 / (0.5 / (focus - 30.0) + 0.5 / (focus + 100.0)))
    # The slanted bar's channels: measured disparity near each end follows the local (planar) distance.
    h = SMALL.height_px // 2
    planes = render(scene, SMALL, NOISELESS, cosited=True).planes_linear
    for end in (0.40, 1.10):
        x = int(end * h)
        window = (slice(int(0.47 * h), int(0.53 * h)), slice(x - 40, x + 40))
        shift, _, _ = phase_cross_correlation(
            planes[..., 0][window], planes[..., 2][window], upsample_factor=50, normalization=None
        )
        expected = float(optics.disparity_px_at_distance(knife.distance_at_mm((x + 0.5) / h)))
        assert 2 * float(shift[1]) == pytest.approx(expected, abs=0.3)  # red relative to blue


def test_cr2_round_trip_returns_the_planes(tmp_path) -> None:
    from mca.capture.raw import read_raw
    from mca.capture.simulated_shots import write_capture
    from mca.devices.sim.world import render_scene

    capture = render_scene("paper-f", PROFILE, size=0.125, seed=1)
    paths = write_capture(capture, PROFILE, tmp_path)
    frame = read_raw(paths["cr2"])
    sensor = capture.sensor
    span = sensor.white_level - sensor.black_level
    m = capture.mosaic.astype(np.float32)
    expected = np.dstack(
        [
            (m[0::2, 0::2] - sensor.black_level) / span,
            ((m[0::2, 1::2] + m[1::2, 0::2]) / 2 - sensor.black_level) / span,
            (m[1::2, 1::2] - sensor.black_level) / span,
        ]
    )
    assert frame.planes.shape == capture.planes_linear.shape
    np.testing.assert_allclose(frame.planes, np.clip(expected, 0, 1), atol=1e-6)
    # And the noise-free planes are what the noisy ones scatter around.
    assert abs(float((frame.planes - capture.planes_linear).mean())) < 1e-3
    assert {paths[k].parent for k in ("truth", "depth", "labels")} == {tmp_path / "truth"}  # beside, not among
    assert paths["cr2"].parent == tmp_path
    truth = json.loads(paths["truth"].read_text())
    assert truth["scene"] == "paper-f" and truth["profile"] == "paper-70d"
    import cv2
    import tifffile

    labels = cv2.imread(str(paths["labels"]), cv2.IMREAD_UNCHANGED)
    assert labels.dtype == np.uint16 and np.array_equal(labels, capture.labels)
    depth = tifffile.imread(paths["depth"])
    assert depth.dtype == np.float32 and np.array_equal(depth, capture.depth_mm)
