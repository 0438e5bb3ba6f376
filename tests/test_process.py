"""`mca process` and `process_file`: CR2, TIFF and PNG to the full set of outputs, bad files, resume and --force."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from mca.capture import outputs
from mca.capture.batch import run_batch
from mca.capture.cli import app
from mca.capture.pipeline_app import RESULT_NAME, process_file
from mca.capture.simulated_shots import write_cr2
from mca.devices.profiles import load_profile
from mca.devices.sim.cr2 import Cr2Metadata
from mca.processing.optics import MCAOptics
from mca.processing.result import DepthResult, MultiPlaneImage, Region

FULL_SET = {
    "depth.tiff",
    "regions.png",
    "result.json",
    "all_in_focus.png",
    "layers/00.png",
    "layers/01.png",
    "scene.ply",
    "scene.glb",
}


def fake_pipeline(planes, aperture, optics, *, pixel_scale=1.0, recorder=None, **options) -> DepthResult:
    """A stand-in for processing.pipeline.run_pipeline: two regions, the left one (at 950 mm) in front of the right
    one (at 1100 mm); without optics -4 and +6 px."""
    if not np.isfinite(planes).all() or planes.max() <= 0:
        raise ValueError("nothing to see: the planes are black")
    height, width = planes.shape[:2]
    labels = np.ones((height, width), np.uint16)
    labels[:, width // 2 :] = 2
    near, far = (
        (-4.0, 6.0)
        if optics is None
        else (float(optics.disparity_px_at_distance(950.0)), float(optics.disparity_px_at_distance(1100.0)))
    )
    disparity = np.where(labels == 1, near, far).astype(np.float32)
    regions = []
    for rid, d, order, occludes in ((1, near, 0, [2]), (2, far, 1, [])):
        region = Region(
            id=rid,
            pixels=int((labels == rid).sum()),
            order=order,
            occludes=occludes,
            disparity_px=d,
            in_focus=False,
            confidence=0.9,
            slant=(0.001, 0.0, d) if rid == 2 else None,
        )
        if optics is not None:
            estimate = optics.from_disparity(d)
            region.inter_image_depth_mm = estimate.inter_image_depth_mm
            region.inter_object_depth_mm = estimate.inter_object_depth_mm
            region.distance_mm = estimate.distance_mm
        regions.append(region)
    depth = None if optics is None else optics.distance_mm(disparity).astype(np.float32)
    layers = []
    for region in reversed(regions):  # deliberately back to front: the application orders them
        rgba = np.dstack([planes, (labels == region.id).astype(np.float32)])
        layers.append(
            MultiPlaneImage(
                region.id,
                rgba.astype(np.float32),
                region.inter_image_depth_mm,
                region.inter_object_depth_mm,
                region.disparity_px,
            )
        )
    if recorder is not None:
        recorder.record("disparity", disparity_px=disparity)
        recorder.timing("disparity", 0.001)
    return DepthResult(
        labels=labels,
        disparity_px=disparity,
        raw_disparity_px=disparity,
        confidence=np.full((height, width), 0.9, np.float32),
        depth_mm=depth,
        all_in_focus=planes.astype(np.float32),
        regions=regions,
        focus_region=None,
        layers=layers,
        pixel_scale=pixel_scale,
        timings_s={"sketch": 0.002},
    )


def _pattern(height: int, width: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    return np.dstack([0.2 + 0.6 * (x / width), 0.3 + 0.4 * (y / height), 0.5 + 0.3 * ((x + y) % 7 == 0)])


def make_png(path: Path, height: int = 48, width: int = 64) -> Path:
    cv2.imwrite(str(path), (outputs.linear_to_srgb8(_pattern(height, width)))[..., ::-1].copy())
    return path


def make_tiff(path: Path, height: int = 40, width: int = 56) -> Path:
    tifffile.imwrite(path, np.round(_pattern(height, width) * 65535).astype(np.uint16), photometric="rgb")
    return path


def make_cr2(path: Path, height: int = 64, width: int = 96) -> Path:
    rgb = _pattern(height // 2, width // 2)
    mosaic = np.zeros((height, width), np.uint16)
    scale = lambda c: (2048 + c * (15000 - 2048)).astype(np.uint16)  # noqa: E731
    mosaic[0::2, 0::2] = scale(rgb[..., 0])
    mosaic[0::2, 1::2] = scale(rgb[..., 1])
    mosaic[1::2, 0::2] = scale(rgb[..., 1])
    mosaic[1::2, 1::2] = scale(rgb[..., 2])
    return write_cr2(path, mosaic, metadata=Cr2Metadata(), preview=False)


def files_under(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def profile():
    return load_profile("paper-70d")


# --- process_file with the stand-in pipeline -------------------------------------------------------------------------


@pytest.mark.parametrize("maker, size", [(make_png, (64, 48)), (make_tiff, (56, 40)), (make_cr2, (96, 64))])
def test_process_file_writes_the_full_set(tmp_path, profile, maker, size):
    source = maker(tmp_path / f"shot{ {make_png: '.png', make_tiff: '.tiff', make_cr2: '.CR2'}[maker] }")
    outcome = process_file(source, tmp_path / "out", profile, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    folder = tmp_path / "out" / "shot"
    assert outcome.output_dir == folder and outcome.regions == 2
    assert files_under(folder) == FULL_SET
    width, height = size
    depth = tifffile.imread(folder / "depth.tiff")
    assert depth.dtype == np.float32 and depth.shape == (height, width)
    labels = cv2.imread(str(folder / "regions.png"), cv2.IMREAD_UNCHANGED)
    assert labels.dtype == np.uint16 and labels.shape == (height, width)
    assert set(np.unique(labels)) == {1, 2}
    result = json.loads((folder / RESULT_NAME).read_text())
    assert result["input"] == str(source) and result["profile"] == "paper-70d"
    assert result["input_size_px"] == [width, height] and result["mode"] == "distance"
    by_id = {r["id"]: r for r in result["regions"]}
    assert set(by_id[1]) >= {
        "id",
        "pixels",
        "order",
        "occludes",
        "disparity_px",
        "inter_image_depth_mm",
        "inter_object_depth_mm",
        "distance_mm",
        "slant",
    }
    assert by_id[1]["pixels"] + by_id[2]["pixels"] == width * height
    assert [by_id[i]["pixels"] for i in (1, 2)] == [int(np.sum(labels == i)) for i in (1, 2)]  # as regions.png
    assert by_id[1]["order"] == 0 and by_id[1]["occludes"] == [2] and by_id[1]["slant"] is None
    assert by_id[2]["slant"] == {"plane": [0.001, 0.0, pytest.approx(by_id[2]["disparity_px"])]}
    assert by_id[1]["distance_mm"] == pytest.approx(950.0, abs=0.5)  # eqs. 2, 13/14 vs the exact thin lens
    assert by_id[2]["distance_mm"] == pytest.approx(1100.0, abs=2.0)
    # the depth map holds each region's distance at input resolution
    assert np.allclose(depth[labels == 1], by_id[1]["distance_mm"])
    assert np.allclose(depth[labels == 2], by_id[2]["distance_mm"])
    assert by_id[1]["distance_mm"] < result["optics"]["focus_distance_mm"] < by_id[2]["distance_mm"]
    assert {"read", "disparity", "sketch", "pipeline", "write"} <= set(result["timings_s"])
    assert result["layers_order"] == "front-to-back" and by_id[1]["layer"] == "layers/00.png"
    nearest = cv2.imread(str(folder / "layers" / "00.png"), cv2.IMREAD_UNCHANGED)
    assert nearest.shape[2] == 4 and nearest[0, 0, 3] == 255 and nearest[0, -1, 3] == 0
    # every point of the cloud lies at one of the two region distances, in front of the camera: the scene
    # frame is glTF's (metres, y up, the camera looking down -z)
    vertices, comments = outputs.read_ply(folder / "scene.ply")
    assert len(vertices) > 0 and any("y up" in c and "metres" in c for c in comments)
    assert np.allclose(
        np.sort(np.unique(np.round(-vertices["z"] * 1000, 2))),
        np.round([by_id[1]["distance_mm"], by_id[2]["distance_mm"]], 2),
        atol=0.01,
    )
    gltf, binary = outputs.read_glb(folder / "scene.glb")
    assert len(gltf["meshes"]) == 2
    corners = [outputs.glb_accessor(gltf, binary, m["primitives"][0]["attributes"]["POSITION"]) for m in gltf["meshes"]]
    assert -corners[0][:, 2] * 1000 == pytest.approx([by_id[1]["distance_mm"]] * 4, rel=1e-6)
    # region 2 is slanted (disparity 0.001 x + c): its quad's corners lie on that plane, not at one depth
    optics = MCAOptics.from_profile(profile, pixel_pitch_mm=result["pixel_pitch_mm"])
    u = np.array([width // 2, width, width, width // 2]) - 0.5  # the box's pixel edges
    expected = optics.distance_mm(0.001 * u + by_id[2]["disparity_px"])
    assert -corners[1][:, 2] * 1000 == pytest.approx(expected, rel=1e-5)
    assert corners[1][1, 2] < corners[1][0, 2]  # farther to the right


def test_process_file_disparity_only(tmp_path, profile):
    import dataclasses

    no_lens = dataclasses.replace(profile, lens=None, name="none")
    outcome = process_file(make_png(tmp_path / "a.png"), tmp_path / "out", no_lens, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    folder = tmp_path / "out" / "a"
    assert files_under(folder) == {
        "depth.tiff",
        "disparity.tiff",
        "regions.png",
        "result.json",
        "all_in_focus.png",
        "layers/00.png",
        "layers/01.png",
    }
    assert np.isnan(tifffile.imread(folder / "depth.tiff")).all()
    disparity = tifffile.imread(folder / "disparity.tiff")
    assert disparity.shape == (48, 64) and set(np.unique(disparity)) == {-4.0, 6.0}
    result = json.loads((folder / RESULT_NAME).read_text())
    assert result["mode"] == "disparity-only" and result["optics"] is None
    assert all(r["distance_mm"] is None for r in result["regions"])


def test_process_file_never_raises_for_a_bad_file(tmp_path, profile):
    (tmp_path / "empty.CR2").write_bytes(b"")
    (tmp_path / "text.png").write_text("not an image")
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((30, 30, 3), np.uint8))
    for path in (tmp_path / "empty.CR2", tmp_path / "text.png", tmp_path / "missing.tiff", black):
        outcome = process_file(path, tmp_path / "out", profile, pipeline=fake_pipeline)
        assert outcome.status == "failed"
        assert str(path) in outcome.reason
        assert not (tmp_path / "out" / path.stem / RESULT_NAME).exists()


def test_a_ctrl_c_just_after_the_staging_folder_is_made_leaves_nothing(tmp_path, profile, monkeypatch):
    """The interrupt lands as the staging folder's mkdir returns (CPython checks for signals after each call; the
    clean-clone CI's Ctrl-C test, on a loaded machine, found a staging folder left): it is still discarded."""
    from mca.capture import output_folders

    class InterruptedAfterMkdir(type(Path())):  # type: ignore[misc]
        def mkdir(self, *args, **kwargs):
            super().mkdir(*args, **kwargs)
            raise KeyboardInterrupt

    own = output_folders.FolderClaim.staging_path
    monkeypatch.setattr(output_folders.FolderClaim, "staging_path", lambda claim: InterruptedAfterMkdir(own(claim)))
    with pytest.raises(KeyboardInterrupt):
        process_file(make_png(tmp_path / "a.png"), tmp_path / "out", profile, pipeline=fake_pipeline)
    # the root's lock file stays (every run takes it); no staging folder, no claim on the name
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [output_folders.ROOT_LOCK_NAME]


def test_resume_and_force(tmp_path, profile):
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("a", "b", "c"):
        make_png(inputs / f"{name}.png")
    out = tmp_path / "out"
    first = run_batch([inputs], out, profile, pipeline=fake_pipeline)
    assert sorted(o.status for o in first.outcomes) == ["done"] * 3
    # a run killed half-way: b's folder has its outputs and a stray temporary file, but no result.json
    (out / "b" / RESULT_NAME).unlink()
    (out / "b" / ".depth.tiff.123.abcd.tmp").write_bytes(b"partial")
    stamps = {n: (out / n / RESULT_NAME).stat().st_mtime_ns for n in ("a", "c")}
    second = run_batch([inputs], out, profile, pipeline=fake_pipeline)
    assert {o.input_path.stem: o.status for o in second.outcomes} == {"a": "skipped", "b": "done", "c": "skipped"}
    assert {n: (out / n / RESULT_NAME).stat().st_mtime_ns for n in ("a", "c")} == stamps
    assert files_under(out / "b") == FULL_SET
    third = run_batch([inputs], out, profile, force=True, pipeline=fake_pipeline)
    assert sorted(o.status for o in third.outcomes) == ["done"] * 3
    assert all((out / n / RESULT_NAME).stat().st_mtime_ns > stamps[n] for n in ("a", "c"))


def test_same_stem_gets_separate_folders(tmp_path, profile):
    make_png(tmp_path / "x.png")
    make_tiff(tmp_path / "x.tiff")
    report = run_batch([tmp_path / "x.png", tmp_path / "x.tiff"], tmp_path / "out", profile, pipeline=fake_pipeline)
    assert {o.input_path.suffix: o.output_dir.name for o in report.outcomes} == {".png": "x", ".tiff": "x-2"}
    assert all(o.status == "done" for o in report.outcomes)


# --- the command line -----------------------------------------------------------------------------------------------


def test_cli_bad_files_do_not_stop_the_batch(tmp_path):
    inputs = tmp_path / "in"
    inputs.mkdir()
    (inputs / "truncated.CR2").write_bytes(b"II*\x00\x10\x00\x00\x00CR\x02\x00")
    (inputs / "empty.png").write_bytes(b"")
    (inputs / "notes.txt").write_text("ignored: not a photograph")
    result = CliRunner().invoke(app, ["process", str(inputs), "--out", str(tmp_path / "out")])
    assert result.exit_code == 1, result.output
    assert "2 failed" in result.output
    assert "truncated.CR2" in result.output and "empty.png" in result.output
    assert "notes.txt" not in result.output


def test_cli_usage_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["process", str(tmp_path), "--out", str(tmp_path / "o"), "--profile", "nope"])
    assert result.exit_code == 2 and "nope" in result.output
    result = runner.invoke(app, ["process", str(tmp_path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "no input files" in result.output


@pytest.mark.parametrize("maker, suffix", [(make_cr2, ".CR2"), (make_tiff, ".tiff"), (make_png, ".png")])
def test_cli_full_set_with_the_real_pipeline(tmp_path, maker, suffix):
    source = maker(tmp_path / f"shot{suffix}")
    result = CliRunner().invoke(app, ["process", str(source), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    folder = tmp_path / "out" / "shot"
    names = files_under(folder)
    assert {"depth.tiff", "regions.png", "result.json", "all_in_focus.png"} <= names
    document = json.loads((folder / RESULT_NAME).read_text())
    assert document["status"] == "done" and document["profile"] == "paper-70d"
    if document["regions"]:
        assert any(n.startswith("layers/") for n in names)
    assert {"scene.ply", "scene.glb"} <= names
    assert os.path.getsize(folder / "depth.tiff") > 0


def test_downscaled_raw_spans_the_whole_sensor(tmp_path, profile):
    # a 96x64 CR2 from an EOS 70D (22.5 mm wide sensor) is a downscaled raw: each pixel is 22.5/96 mm
    outcome = process_file(make_cr2(tmp_path / "small.CR2"), tmp_path / "out", profile, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    result = json.loads((tmp_path / "out" / "small" / RESULT_NAME).read_text())
    assert result["pixel_pitch_mm"] == pytest.approx(22.5 / 96)
    assert result["pixel_scale"] == 2.0 and result["processing_size_px"] == [48, 32]
    assert result["capture"]["model"] == "Canon EOS 70D" and result["capture"]["cfa_pattern"] == "RGGB"


def test_cli_profile_none_gives_disparities_only(tmp_path):
    source = make_png(tmp_path / "shot.png")
    result = CliRunner().invoke(app, ["process", str(source), "--out", str(tmp_path / "out"), "--profile", "none"])
    assert result.exit_code == 0, result.output
    folder = tmp_path / "out" / "shot"
    document = json.loads((folder / RESULT_NAME).read_text())
    assert document["profile"] == "none" and document["mode"] == "disparity-only"
    assert np.isnan(tifffile.imread(folder / "depth.tiff")).all()
    assert tifffile.imread(folder / "disparity.tiff").shape == (48, 64)
    assert not (folder / "scene.ply").exists() and not (folder / "scene.glb").exists()
    assert all(r["distance_mm"] is None for r in document["regions"])


def _pipeline_without_layers(planes, aperture, optics, **options) -> DepthResult:
    result = fake_pipeline(planes, aperture, optics, **options)
    result.layers = []
    return result


def test_scene_quads_fall_back_to_region_masks(tmp_path, profile):
    outcome = process_file(make_png(tmp_path / "a.png"), tmp_path / "out", profile, pipeline=_pipeline_without_layers)
    assert outcome.status == "done", outcome.reason
    gltf, binary = outputs.read_glb(tmp_path / "out" / "a" / "scene.glb")
    assert [n["extras"]["region_id"] for n in gltf["nodes"][1:] if "mesh" in n] == [1, 2]
    assert [n["name"] for n in gltf["nodes"] if "camera" in n] == ["camera"]
    texture = cv2.imdecode(np.frombuffer(outputs.glb_image(gltf, binary, 0), np.uint8), cv2.IMREAD_UNCHANGED)
    assert texture.shape == (48, 32, 4) and (texture[..., 3] == 255).all()
    corners = outputs.glb_accessor(gltf, binary, 0)
    # the left half of a 64 px wide image: from its left edge to the optical axis
    assert corners[0, 0] < 0 and corners[1, 0] == pytest.approx(0.0, abs=1e-3)


KILLED_BATCH = """
import sys, time
sys.path.insert(0, sys.argv[3])
from pathlib import Path
from mca.capture.batch import run_batch
from mca.devices.profiles import load_profile
from mca.processing.optics import MCAOptics
from test_process import fake_pipeline

def slow_pipeline(*args, **kwargs):
    time.sleep(0.4)
    return fake_pipeline(*args, **kwargs)

run_batch([Path(sys.argv[1])], Path(sys.argv[2]), load_profile("paper-70d"), pipeline=slow_pipeline)
"""


def test_a_batch_killed_half_way_resumes_without_redoing_finished_files(tmp_path):
    """SIGKILL a real batch process mid-way; the rerun redoes only what had not finished."""
    import signal
    import subprocess
    import sys
    import time

    inputs = tmp_path / "in"
    inputs.mkdir()
    names = [f"f{i}" for i in range(8)]
    for name in names:
        make_png(inputs / f"{name}.png")
    out = tmp_path / "out"
    script = tmp_path / "batch.py"
    script.write_text(KILLED_BATCH)
    proc = subprocess.Popen([sys.executable, str(script), str(inputs), str(out), str(Path(__file__).parent)])
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any((out / n / RESULT_NAME).exists() for n in names[:3]):
        time.sleep(0.02)
    time.sleep(0.5)  # let it get into the middle of another file
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    # finished: its folder in place, or its staging folder complete (killed between the last write and the
    # rename: the rerun swaps it in, as the killed run was about to; seen on a loaded machine)
    results = {n: [out / n / RESULT_NAME, *out.glob(f".{n}.mca-staging-*/{RESULT_NAME}")] for n in names}
    finished = {n for n, found in results.items() if any(p.exists() for p in found)}
    assert 0 < len(finished) < len(names), finished
    stamps = {n: next(p for p in results[n] if p.exists()).stat().st_mtime_ns for n in finished}
    report = run_batch([inputs], out, load_profile("paper-70d"), pipeline=fake_pipeline)
    statuses = {o.input_path.stem: o.status for o in report.outcomes}
    assert {n for n, s in statuses.items() if s == "skipped"} == finished
    assert {n for n, s in statuses.items() if s == "done"} == set(names) - finished
    assert {n: (out / n / RESULT_NAME).stat().st_mtime_ns for n in finished} == stamps
    for name in names:
        assert files_under(out / name) == FULL_SET  # no half-written or temporary files survive


# --- the pitch of an image that names no camera --------------------------------------------------------------------


def test_an_image_naming_no_camera_gets_a_note_on_its_assumed_pitch(tmp_path, profile):
    """A PNG names no camera: its pixel pitch is the profile's, which is right for a crop at full resolution and
    wrong by the scale for a downscaled frame. result.json says so, with the pitch the other reading would take;
    a raw that names its body, or an image at the sensor's own size, gets no note."""
    from dataclasses import replace

    from mca.capture.api import pitch_note, read_input

    png = make_png(tmp_path / "small.png")  # 64 x 48, the sensor 5472 x 3648
    note = pitch_note(profile, read_input(png))
    assert note is not None
    assert "64x48" in note and "5472x3648" in note and "0.004109 mm" in note
    assert f"{0.004109 * 5472 / 64:.6g} mm" in note  # the pitch of the whole frame scaled down to 64 px
    outcome = process_file(png, tmp_path / "out", profile, pipeline=fake_pipeline)
    assert outcome.status == "done" and outcome.notes == (note,)
    document = json.loads((tmp_path / "out" / "small" / RESULT_NAME).read_text())
    assert document["notes"] == [note] and document["pixel_pitch_source"] == "profile"

    assert pitch_note(replace(profile, width_px=64, height_px=48), read_input(png)) is None  # the sensor's size
    assert pitch_note(load_profile("bando2008"), read_input(png)) is None  # no lens: no distances to be off
    raw = make_cr2(tmp_path / "body.CR2")  # names the EOS 70D: the pitch comes from the body
    assert read_input(raw).pixel_pitch_mm is not None and pitch_note(profile, read_input(raw)) is None
    outcome = process_file(raw, tmp_path / "out", profile, pipeline=fake_pipeline)
    assert outcome.notes == ()
    document = json.loads((tmp_path / "out" / "body" / RESULT_NAME).read_text())
    assert document["notes"] == [] and document["pixel_pitch_source"] == "file"


def test_the_summary_prints_each_note_once_with_its_files(tmp_path, capsys):
    from mca.capture.batch import _print_notes
    from mca.capture.pipeline_app import FileOutcome

    outcomes = [
        FileOutcome(tmp_path / f"{name}.png", "done", tmp_path, notes=notes)
        for name, notes in (("a", ("size A",)), ("b", ("size A",)), ("c", ()), ("d", ("size B",)))
    ]
    _print_notes(outcomes)
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["note: a.png, b.png: size A", "note: d.png: size B"]
