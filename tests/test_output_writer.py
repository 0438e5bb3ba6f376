"""Outputs written while the pipeline computes (issue 16): the depth and region maps start from the pipeline's
"depth" stage, the files are the same bytes as when written at the end, and a failure leaves nothing half-made."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from test_process import fake_pipeline, make_png

from mca.capture.output_folders import STAGING_MARK
from mca.capture.pipeline_app import RESULT_NAME, process_file
from mca.devices.profiles import load_profile

WAIT_S = 30.0  # how long a pipeline waits for a file to appear (a loaded machine is slow; this is no timing test)


@pytest.fixture(scope="module")
def profile():
    return load_profile("paper-70d")


def _wait_for(path: Path) -> bool:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        if path.exists():
            return True
        time.sleep(0.01)
    return False


def _staging_dirs(out_root: Path) -> list[Path]:
    return [p for p in out_root.rglob("*") if p.is_dir() and STAGING_MARK in p.name]


def reporting_pipeline(seen: dict, out_root: Path):
    """The fake pipeline, handing its depth maps to the recorder as processing.pipeline does at its "depth"
    stage, then waiting (as the all-in-focus and layer stages take time) until depth.tiff has been written."""

    def run(planes, aperture, optics, *, recorder=None, **options):
        result = fake_pipeline(planes, aperture, optics, recorder=None, **options)
        items = {"labels": result.labels, "disparity_px": result.disparity_px, "regions": result.regions}
        if result.depth_mm is not None:
            items["depth_mm"] = result.depth_mm
        recorder.record("depth", **items)
        staged = [p / "depth.tiff" for p in _staging_dirs(out_root)]
        seen["depth.tiff before the pipeline returned"] = any(_wait_for(p) for p in staged[:1])
        return result

    return run


@pytest.mark.parametrize("profile_name", ["paper-70d", "none"])
def test_depth_maps_are_written_while_the_pipeline_runs_and_match_the_files_written_after(tmp_path, profile_name):
    from mca.capture.profile_app import resolve_profile

    chosen = resolve_profile(profile_name)
    source = make_png(tmp_path / "a.png")
    seen: dict = {}
    early = process_file(source, tmp_path / "early", chosen, pipeline=reporting_pipeline(seen, tmp_path / "early"))
    late = process_file(source, tmp_path / "late", chosen, pipeline=fake_pipeline)
    assert early.status == late.status == "done", (early.reason, late.reason)
    assert seen == {"depth.tiff before the pipeline returned": True}
    early_doc = json.loads((tmp_path / "early" / "a" / RESULT_NAME).read_text())
    late_doc = json.loads((tmp_path / "late" / "a" / RESULT_NAME).read_text())
    assert early_doc["outputs"] == late_doc["outputs"]
    for name in early_doc["outputs"]:
        if name != RESULT_NAME:
            early_bytes = (tmp_path / "early" / "a" / name).read_bytes()
            assert early_bytes == (tmp_path / "late" / "a" / name).read_bytes(), name
    assert {"write depth.tiff", "write regions.png", "write all_in_focus.png"} <= set(early_doc["timings_s"])
    if profile_name == "none":
        assert "disparity.tiff" in early_doc["outputs"] and "scene.glb" not in early_doc["outputs"]


def test_a_result_unlike_what_the_depth_stage_handed_over_is_written_as_returned(tmp_path, profile):
    """The early files are made again when the pipeline returns other maps than the ones it recorded."""

    def changing(planes, aperture, optics, *, recorder=None, **options):
        result = fake_pipeline(planes, aperture, optics, recorder=None, **options)
        wrong = np.full_like(result.labels, 1)
        recorder.record("depth", labels=wrong, disparity_px=result.disparity_px, depth_mm=result.depth_mm)
        return result  # its labels have regions 1 and 2

    source = make_png(tmp_path / "a.png")
    assert process_file(source, tmp_path / "out", profile, pipeline=changing).status == "done"
    assert process_file(source, tmp_path / "ref", profile, pipeline=fake_pipeline).status == "done"
    for name in ("regions.png", "depth.tiff"):
        assert (tmp_path / "out" / "a" / name).read_bytes() == (tmp_path / "ref" / "a" / name).read_bytes(), name


def test_a_pipeline_failing_after_its_depth_stage_leaves_the_previous_result(tmp_path, profile):
    source = make_png(tmp_path / "a.png")
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and "lock" not in p.name}

    def failing(planes, aperture, optics, *, recorder=None, **options):
        result = fake_pipeline(planes * 0.5, aperture, optics, recorder=None, **options)
        recorder.record("depth", labels=result.labels, disparity_px=result.disparity_px + 1.0, depth_mm=result.depth_mm)
        raise RuntimeError("the all-in-focus stage broke")

    outcome = process_file(source, out, profile, pipeline=failing, force=True)
    assert outcome.status == "failed" and "all-in-focus stage broke" in outcome.reason
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and "lock" not in p.name}
    assert after == before  # the early depth.tiff went into the discarded staging folder, not over the result
    assert _staging_dirs(out) == []
