"""Lateral colour (`processing.chromatic`): a lens draws red and blue slightly magnified against green; the
pipeline measures that from the capture itself, across the directions in which depth moves the channels,
and takes it out before the search. Real image content (a Middlebury photograph's grey version, so that its
own camera's lateral colour is not in it) is magnified with a known k per channel and axis by OpenCV's
affine warp, and displaced along the filter geometry as depth would."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.processing.camera import FilterAperture
from mca.processing.chromatic import (
    MIN_DISPLACEMENT_PX,
    NO_LATERAL_COLOUR,
    LateralColour,
    estimate_lateral_colour,
    remove_lateral_colour,
)
from mca.processing.disparity import channel_shifts

PROFILE = load_profile("paper-70d")
MIDDLEBURY = Path(__file__).resolve().parents[2] / "shared" / "data" / "middlebury"
pytestmark = pytest.mark.skipif(not MIDDLEBURY.is_dir(), reason=f"the Middlebury scenes are not at {MIDDLEBURY}")


def grey_content(scene: str = "Art", width_px: int = 1000) -> np.ndarray:
    """A real photograph's luminance, linear, as three identical channels (no lateral colour of its own)."""
    image = cv2.imread(str(MIDDLEBURY / scene / "im.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
    h, w = image.shape
    image = cv2.resize(image, (width_px, int(round(h * width_px / w))), interpolation=cv2.INTER_AREA)
    linear = image**2.2
    return np.dstack([linear, linear, linear])


def magnified(planes: np.ndarray, colour: LateralColour) -> np.ndarray:
    """Each channel drawn magnified by (1 + kx, 1 + ky) about the frame's centre (what a lens does)."""
    h, w = planes.shape[:2]
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    out = planes.copy()
    for c, (kx, ky) in enumerate(colour.k):
        forward = np.array([[1.0 + kx, 0.0, -kx * cx], [0.0, 1.0 + ky, -ky * cy]])
        out[..., c] = cv2.warpAffine(
            planes[..., c], forward, (w, h), flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT
        )
    return out


def displaced(planes: np.ndarray, aperture: FilterAperture, disparity_px: np.ndarray) -> np.ndarray:
    """Each channel moved by the MCA's displacement for a per-column disparity (near left, far right)."""
    h, w = planes.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    shifts = channel_shifts(aperture)
    out = np.empty_like(planes)
    for c in range(3):
        out[..., c] = cv2.remap(
            planes[..., c],
            xs + disparity_px * np.float32(shifts[c, 0]),
            ys + disparity_px * np.float32(shifts[c, 1]),
            cv2.INTER_LANCZOS4,
            borderMode=cv2.BORDER_REFLECT,
        )
    return out


LENS = LateralColour(((0.45e-3, 0.25e-3), (0.0, 0.0), (-0.35e-3, -0.6e-3)), 0)


def test_a_known_magnification_is_found_whatever_the_depth() -> None:
    """Two depths (4 px of disparity apart) across the frame: depth moves the channels along the filter
    geometry only, so the magnifications still come out within 12 % (0.06 px at this frame's corners)."""
    content = grey_content()
    depth = np.where(np.arange(content.shape[1]) < content.shape[1] // 2, -2.0, 2.0).astype(np.float32)
    capture = displaced(magnified(content, LENS), PROFILE.aperture, np.broadcast_to(depth, content.shape[:2]))
    found = estimate_lateral_colour(capture, PROFILE.aperture)
    assert found.tiles >= 200
    for c in (0, 2):
        np.testing.assert_allclose(found.k[c], LENS.k[c], rtol=0.12, atol=0.03e-3)
    assert found.k[1] == (0.0, 0.0)
    # taken out, nothing measurable is left
    assert estimate_lateral_colour(remove_lateral_colour(capture, found), PROFILE.aperture) == NO_LATERAL_COLOUR


@pytest.mark.parametrize("scene", ["Dolls", "Laundry"])
def test_defocus_blur_and_sensor_noise_do_not_shrink_the_reading(scene: str) -> None:
    """Defocused (a 3-px disc) and noisy (1 % of full scale at mid-grey, shot noise): a phase slope with
    every frequency weighed alike read two thirds of the magnification here; weighed by the correlation's
    strength, it reads within 12 %."""
    content = magnified(grey_content(scene, 1000), LENS)
    disc = np.zeros((7, 7), np.float32)
    cv2.circle(disc, (3, 3), 3, 1.0, -1)
    blurred = cv2.filter2D(content, -1, disc / disc.sum())
    noise = np.random.default_rng(3).normal(0.0, 0.01, blurred.shape).astype(np.float32)
    capture = blurred + noise * np.sqrt(np.clip(blurred, 0.0, None) + 0.01)
    found = estimate_lateral_colour(capture, PROFILE.aperture)
    for c in (0, 2):
        np.testing.assert_allclose(found.k[c], LENS.k[c], rtol=0.12, atol=0.03e-3)


def test_no_lateral_colour_is_reported_where_there_is_none() -> None:
    """Identical channels displaced by depth alone, and a flat frame: none found, planes left as they are."""
    content = grey_content("Books", 800)
    ramp = np.linspace(-3.0, 5.0, content.shape[1], dtype=np.float32)
    capture = displaced(content, PROFILE.aperture, np.broadcast_to(ramp, content.shape[:2]))
    assert estimate_lateral_colour(capture, PROFILE.aperture) == NO_LATERAL_COLOUR
    assert remove_lateral_colour(capture, NO_LATERAL_COLOUR) is capture
    flat = np.full((400, 600, 3), 0.3, np.float32)
    assert estimate_lateral_colour(flat, PROFILE.aperture) == NO_LATERAL_COLOUR
    assert estimate_lateral_colour(flat[:100, :100], PROFILE.aperture) == NO_LATERAL_COLOUR  # smaller than 2 tiles


def test_a_filter_layout_along_the_axes_falls_back_to_the_lens_model() -> None:
    """Red and blue moved by depth along x only: across is y alone, so one magnification per channel (a
    lens's, equal along both axes) is all that can be told, and it is found."""
    aperture = FilterAperture(3.0, red_mm=(6.0, 0.0), green_mm=(0.0, 0.0), blue_mm=(-6.0, 0.0), diameter_mm=27.8)
    lens = LateralColour(((0.4e-3, 0.4e-3), (0.0, 0.0), (-0.5e-3, -0.5e-3)), 0)
    content = grey_content("Moebius", 900)
    found = estimate_lateral_colour(magnified(content, lens), aperture)
    for c in (0, 2):
        assert found.k[c][0] == found.k[c][1]
        np.testing.assert_allclose(found.k[c], lens.k[c], rtol=0.12)


def test_a_reading_no_magnification_makes_is_refused() -> None:
    """Red stretched along x and squeezed along y, blue stretched along x alone: neither is a lens's (or a
    resampling's) magnification, so neither channel is touched; the readings came from something else."""
    content = grey_content("Art", 900)
    odd = LateralColour(((0.5e-3, -0.5e-3), (0.0, 0.0), (0.8e-3, 0.0)), 0)
    assert estimate_lateral_colour(magnified(content, odd), PROFILE.aperture) == NO_LATERAL_COLOUR


def test_only_tiles_of_one_surface_are_read_when_depth_is_given() -> None:
    """A quarter-size disparity map (as the quick search gives) of a slanted plane with an occluding step in
    it: tiles on the slant are read, tiles across the step are not."""
    from mca.processing.chromatic import _one_depth

    h, w, tile = 512, 768, 64
    xs = np.arange(w // 4, dtype=np.float32)
    quarter = np.broadcast_to(0.01 * 4 * xs, (h // 4, w // 4)).copy()  # 0.01 px per px: 7.7 px across
    quarter[:, 100:] += 3.0  # a 3-px step at x = 400
    corners = np.stack(np.meshgrid(np.arange(0, h - tile + 1, 32), np.arange(0, w - tile + 1, 32), indexing="ij"), -1)
    corners = corners.reshape(-1, 2)
    one = _one_depth(quarter, (h, w), corners, tile)
    straddles = (corners[:, 1] < 400) & (corners[:, 1] + tile > 400)
    assert not one[straddles].any()
    assert one[~straddles].all()


def test_largest_displacement_is_at_the_corners() -> None:
    colour = LateralColour(((1e-3, 0.0), (0.0, 0.0), (0.0, -2e-3)), 10)
    assert colour.largest_displacement_px((101, 201)) == pytest.approx(0.1)
    assert colour.describe() == pytest.approx(
        {"red_x_ppt": 1.0, "red_y_ppt": 0.0, "blue_x_ppt": 0.0, "blue_y_ppt": -2.0}
    )
    assert MIN_DISPLACEMENT_PX <= 0.1


def test_the_pipeline_takes_a_lens_lateral_colour_out_before_the_search() -> None:
    """A real photograph rendered through the MCA optics 150-600 mm behind focus (`render_rgbd`), then drawn
    through a lens with lateral colour: left in, it reads as disparity growing across the frame; measured and
    taken out by the pipeline, the disparities come back to what the same render gives without it.

    The render alone reads about 0.15 parts per thousand (0.07 px at the sides) of its own: where depth
    changes within a tile, the tile's reading across the depth direction moves a little. What the lens adds
    is read to within 10 %."""
    from mca.capture.simulated_shots import read_rgbd_source, sensor_width_mm
    from mca.devices.sim.render import SensorModel
    from mca.devices.sim.render_rgbd import DepthRange, Realism, render_rgbd, rgbd_optics
    from mca.processing.pipeline import PipelineParams, run_pipeline

    source = read_rgbd_source(MIDDLEBURY / "Art" / "im.png", MIDDLEBURY / "Art" / "disp.png")
    h, w = source.valid.shape
    size = (900, int(round(h * 900 / w)))
    grey = cv2.cvtColor(cv2.resize(source.image_srgb, size, interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY)
    image = np.dstack([grey, grey, grey])
    disparity = cv2.resize(source.disparity, size, interpolation=cv2.INTER_NEAREST) * (900 / w)
    valid = cv2.resize(source.valid.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    optics = rgbd_optics(PROFILE, size[0], size[1], 1000.0, sensor_width_mm(PROFILE))
    sensor = SensorModel(noise=False)
    rendering = render_rgbd(image, disparity, valid, optics, DepthRange(1150.0, 1600.0), Realism(sensor), output="rgb")
    planes = (rendering.image_dn.astype(np.float32) - sensor.black_level) / (sensor.white_level - sensor.black_level)
    lens = LateralColour(((0.0, 0.0), (0.0, 0.0), (0.8e-3, 0.8e-3)), 0)  # 0.36 px at the sides
    measure = dataclasses.replace(PROFILE.aperture, lateral_colour="measure")  # as a profile asks for it
    without = run_pipeline(planes, measure, None)
    reference = without.raw_disparity_px
    with_lens = magnified(planes, lens)
    left_in = run_pipeline(with_lens, PROFILE.aperture, None).raw_disparity_px  # the default: none taken out
    result = run_pipeline(with_lens, measure, None)
    assert result.lateral_colour.tiles > 100
    added = np.subtract(result.lateral_colour.k, without.lateral_colour.k)
    np.testing.assert_allclose(added[2], lens.k[2], rtol=0.10)
    np.testing.assert_allclose(added[0], (0.0, 0.0), atol=0.02e-3)
    sides = np.zeros(valid.shape, bool)
    sides[:, : size[0] // 5] = sides[:, -size[0] // 5 :] = True
    inside = rendering.valid & sides
    error_in = np.median(np.abs(left_in - reference)[inside])
    error_out = np.median(np.abs(result.raw_disparity_px - reference)[inside])
    assert error_in > 0.12
    assert error_out < 0.25 * error_in
    # the same numbers given as a calibration (parts per thousand) take it out as well, with no measuring
    ppt = np.asarray(result.lateral_colour.k) * 1e3
    calibrated = dataclasses.replace(PROFILE.aperture, lateral_colour=((ppt[0, 0], ppt[0, 1]), (ppt[2, 0], ppt[2, 1])))
    given = run_pipeline(with_lens, calibrated, None, params=PipelineParams(lateral_colour=False))
    assert given.lateral_colour.tiles == 0
    np.testing.assert_allclose(given.lateral_colour.k, result.lateral_colour.k, rtol=1e-9)
    np.testing.assert_allclose(given.raw_disparity_px, result.raw_disparity_px, atol=1e-4)
