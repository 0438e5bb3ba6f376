"""Colour: one sRGB curve, the camera's as-shot white balance and colour matrix for every displayed image."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import rawpy
from tools import require

from mca.capture import outputs, raw
from mca.capture.pipeline_app import process_file
from mca.capture.simulated_shots import write_cr2
from mca.devices.profiles import load_profile
from mca.devices.sim.cr2 import Cr2Metadata
from mca.processing import colour
from mca.processing.colour import CameraColour, camera_colour, camera_to_srgb_from_xyz

ROOT = Path(__file__).resolve().parent.parent


def _reference_encode(x: float) -> float:  # IEC 61966-2-1, written out independently
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def test_the_srgb_curve_has_one_home() -> None:
    values = np.linspace(0, 1, 101)
    assert colour.srgb_encode(values) == pytest.approx([_reference_encode(v) for v in values], abs=1e-6)
    assert colour.srgb_decode(colour.srgb_encode(values)) == pytest.approx(values, abs=1e-5)
    assert outputs.linear_to_srgb8 is colour.linear_to_srgb8 and raw.srgb_to_linear is colour.srgb_decode
    constants = re.compile(r"0\.0031308|0\.04045|1\.0? */ *2\.4")
    for folder in ("capture", "processing", "devices"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.name != "colour.py":
                assert not constants.search(path.read_text(encoding="utf-8")), f"a second sRGB curve in {path}"


def _mosaic(rgb: tuple[float, float, float], height: int = 64, width: int = 96, black: int = 2048) -> np.ndarray:
    span = 15000 - black
    mosaic = np.empty((height, width), np.uint16)
    r, g, b = (int(round(black + c * span)) for c in rgb)
    mosaic[0::2, 0::2], mosaic[0::2, 1::2], mosaic[1::2, 0::2], mosaic[1::2, 1::2] = r, g, g, b
    return mosaic


def test_camera_matrix_is_what_libraw_applies(tmp_path: Path) -> None:
    """Our camera-to-sRGB matrix is the one LibRaw's own sRGB output applies (the independent reference).

    Three flat patches are developed by LibRaw twice over: linear, no white balance, sRGB output. The
    3x3 map from the patches' raw values to LibRaw's sRGB values is LibRaw's rgb_cam (up to one scale).
    """
    span = 15000 - 2048  # white - black level of `_mosaic`
    patches = [(0.30, 0.30, 0.30), (0.36, 0.30, 0.27), (0.27, 0.30, 0.35)]
    raw_values, developed = [], []
    for index, rgb in enumerate(patches):
        path = write_cr2(tmp_path / f"p{index}.CR2", _mosaic(rgb), metadata=Cr2Metadata(), preview=False)
        with rawpy.imread(str(path)) as r:
            out = r.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                use_camera_wb=False,
                user_wb=[1, 1, 1, 1],
                output_color=rawpy.ColorSpace.sRGB,
                user_flip=0,
            )
            cam_xyz = np.asarray(r.rgb_xyz_matrix)[:3, :3]
        raw_values.append([round(c * span) for c in rgb])
        developed.append(out[16:48, 16:80].reshape(-1, 3).mean(axis=0))
    libraw = np.array(developed, float).T @ np.linalg.inv(np.array(raw_values, float).T)
    libraw /= libraw.sum(axis=1).mean()
    ours = camera_to_srgb_from_xyz(cam_xyz)
    np.testing.assert_allclose(ours, libraw, atol=5e-3)
    assert np.allclose(ours.sum(axis=1), 1.0)  # white stays white
    frame = raw.read_raw(tmp_path / "p0.CR2")
    np.testing.assert_allclose(frame.colour.camera_to_srgb, ours, atol=1e-9)
    assert "as-shot white balance" in frame.colour.source and "colour matrix" in frame.colour.source


def test_simulated_cr2_says_its_pixels_are_neutral(tmp_path: Path) -> None:
    """The simulator renders a white surface as R = G = B: its as-shot white balance must be 1, 1, 1."""
    path = write_cr2(tmp_path / "sim.CR2", _mosaic((0.4, 0.4, 0.4)), metadata=Cr2Metadata(), preview=False)
    with rawpy.imread(str(path)) as r:
        wb = np.asarray(r.camera_whitebalance, float)
    assert wb[:3] / wb[1] == pytest.approx([1.0, 1.0, 1.0])
    assert raw.read_raw(path).colour.wb_gains == (1.0, 1.0, 1.0)


def test_exiftool_reads_the_written_white_balance(tmp_path: Path) -> None:
    exiftool = require("exiftool", "apt-get install libimage-exiftool-perl")
    for levels in ((1024, 1024, 1024, 1024), (2048, 1024, 1024, 1536)):
        path = write_cr2(tmp_path / f"{levels[0]}.CR2", _mosaic((0.3, 0.3, 0.3)), metadata=Cr2Metadata(wb_rggb=levels))
        out = subprocess.run([exiftool, "-j", "-n", "-WB_RGGBLevelsAsShot", str(path)], capture_output=True, text=True)
        assert json.loads(out.stdout)[0]["WB_RGGBLevelsAsShot"] == " ".join(map(str, levels))


def test_displayed_images_get_the_as_shot_white_balance_and_matrix(tmp_path: Path) -> None:
    """A grey card shot under a light that the camera balanced with R x2, B x1.5: raw R = G/2, B = G/1.5.

    The planes the pipeline sees stay unbalanced; all_in_focus.png and the layers show the card grey.
    """
    grey = 0.36
    mosaic = _mosaic((grey / 2.0, grey, grey / 1.5))
    path = write_cr2(
        tmp_path / "card.CR2", mosaic, metadata=Cr2Metadata(wb_rggb=(2048, 1024, 1024, 1536)), preview=False
    )
    frame = raw.read_raw(path)
    assert frame.colour.wb_gains == pytest.approx((2.0, 1.0, 1.5))
    assert frame.planes[..., 0].mean() == pytest.approx(frame.planes[..., 1].mean() / 2, rel=1e-3)  # unbalanced
    seen = {}

    def flat(planes, aperture, optics, *, pixel_scale=1.0, recorder=None, **options):
        from mca.processing.result import DepthResult, MultiPlaneImage, Region

        seen["planes"] = planes
        h, w = planes.shape[:2]
        labels = np.ones((h, w), np.uint16)
        zero = np.zeros((h, w), np.float32)
        depth = np.full((h, w), 1000.0, np.float32)
        region = Region(1, h * w, 0, [], 0.0, 0.0, 0.0, 1000.0, None, True, 1.0)
        layer = MultiPlaneImage(1, None, 0.0, 0.0, 0.0, source=(planes, labels))
        return DepthResult(labels, zero, zero, zero + 1, depth, planes, [region], 1, [layer], pixel_scale)

    outcome = process_file(path, tmp_path / "out", load_profile("paper-70d"), pipeline=flat)
    assert outcome.status == "done", outcome.reason
    assert seen["planes"][..., 0].mean() == pytest.approx(seen["planes"][..., 1].mean() / 2, rel=1e-3)
    shown = cv2.imread(str(tmp_path / "out" / "card" / "all_in_focus.png"))[..., ::-1].reshape(-1, 3)
    r, g, b = shown.mean(axis=0)
    assert abs(r - g) <= 1.5 and abs(b - g) <= 1.5 and 100 < g < 200
    layer = cv2.imread(str(tmp_path / "out" / "card" / "layers" / "00.png"), cv2.IMREAD_UNCHANGED)
    assert np.abs(layer[..., 2].astype(int) - layer[..., 1]).max() <= 2  # BGRA: red vs green
    document = json.loads((tmp_path / "out" / "card" / "result.json").read_text())
    assert document["colour"]["white_balance_gains_rgb"] == pytest.approx([2.0, 1.0, 1.5])


def test_linear_tiff_and_srgb_images_say_what_is_assumed(tmp_path: Path) -> None:
    import tifffile

    tifffile.imwrite(tmp_path / "a.tiff", np.full((8, 8, 3), 30000, np.uint16), photometric="rgb")
    cv2.imwrite(str(tmp_path / "b.png"), np.full((8, 8, 3), 128, np.uint8))
    tiff, png = raw.read_raw(tmp_path / "a.tiff"), raw.read_raw(tmp_path / "b.png")
    assert tiff.colour.is_identity and "assumed" in tiff.colour.source
    assert png.colour.is_identity and "sRGB" in png.colour.source


def test_camera_colour_from_what_a_file_says() -> None:
    c = camera_colour((2.1, 1.05, 1.4, 1.05), None)
    assert c.wb_gains == pytest.approx((2.0, 1.0, 4 / 3)) and "no colour matrix" in c.source
    assert camera_colour(None, None).is_identity
    assert CameraColour().to_srgb8(np.array([[0.5, 0.5, 0.5]])).tolist() == [[188, 188, 188]]
