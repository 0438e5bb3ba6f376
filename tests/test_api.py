"""The Python API: `mca.depth_from_file` / `depth_from_frame` give what `mca process` writes, to the pixel."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from sim_capture import make_capture

import mca
from mca.capture.pipeline_app import upsample_nearest
from mca.capture.raw import RawFrame, read_raw

README = Path(__file__).resolve().parent.parent / "README.md"


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory):
    return make_capture(tmp_path_factory.mktemp("api"))


def test_api_and_mca_process_agree_to_the_pixel(capture) -> None:
    result = mca.depth_from_file(capture.cr2, "paper-70d")
    assert result.pixel_scale == 2.0 and result.depth_mm is not None
    depth_file = tifffile.imread(capture.out_dir / "depth.tiff")
    labels_file = cv2.imread(str(capture.out_dir / "regions.png"), cv2.IMREAD_UNCHANGED)
    size = (depth_file.shape[1], depth_file.shape[0])
    np.testing.assert_array_equal(upsample_nearest(result.depth_mm, result.pixel_scale, size), depth_file)
    np.testing.assert_array_equal(upsample_nearest(result.labels, result.pixel_scale, size), labels_file)
    # and the depths are right: the knife and the wall of Fig. 4 g are 970-1100 mm and 1500 mm away
    distances = sorted(r.distance_mm for r in result.regions)
    assert distances[-1] == pytest.approx(1500, rel=0.02) and 950 < distances[0] < 1100  # small frame: 1517 mm


def test_depth_from_arrays_is_the_same_as_from_the_file(capture) -> None:
    frame = read_raw(capture.cr2)
    from_arrays = RawFrame.from_planes(
        frame.planes,
        pixel_pitch_mm=frame.pixel_pitch_mm,
        half_resolution=True,
        cfa_pattern=frame.metadata.cfa_pattern,
        make=frame.metadata.make,
        model=frame.metadata.model,
    )
    a = mca.depth_from_frame(from_arrays, "paper-70d")
    b = mca.depth_from_file(capture.cr2, mca.load_profile("paper-70d"))
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)


def test_half_resolution_planes_without_their_pattern_are_refused(capture) -> None:
    frame = read_raw(capture.cr2)
    blind = RawFrame.from_planes(frame.planes, pixel_pitch_mm=frame.pixel_pitch_mm, half_resolution=True)
    with pytest.raises(ValueError, match="cfa_pattern"):
        mca.depth_from_frame(blind, "paper-70d")


def test_the_bare_pipeline_without_the_app_facts_is_wrong_and_the_api_is_not(capture) -> None:
    """What issue 15 found: read_raw -> profile optics -> run_pipeline misses pitch, scale and Bayer offsets."""
    from mca.processing.optics import MCAOptics
    from mca.processing.pipeline import run_pipeline

    frame = read_raw(capture.cr2)
    profile = mca.load_profile("paper-70d")
    naive = run_pipeline(frame.planes, profile.aperture, MCAOptics.from_profile(profile))
    api = mca.depth_from_file(capture.cr2, profile)
    wall_naive = max(r.distance_mm for r in naive.regions)
    wall_api = max(r.distance_mm for r in api.regions)
    assert wall_api == pytest.approx(1500, rel=0.01)
    assert abs(wall_naive - 1500) > 5 * abs(wall_api - 1500)


def _readme_python_blocks() -> list[str]:
    text = README.read_text(encoding="utf-8")
    section = text.split("## Use from Python", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_use_from_python_runs(capture, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    blocks = _readme_python_blocks()
    assert blocks, "README.md has no python block under 'Use from Python'"
    monkeypatch.chdir(capture.cr2.parent)
    namespace: dict[str, object] = {"__name__": "readme"}
    for block in blocks:
        exec(compile(block.replace("IMG_0001.CR2", capture.cr2.name), str(README), "exec"), namespace)
    printed = capsys.readouterr().out
    assert "mm" in printed
