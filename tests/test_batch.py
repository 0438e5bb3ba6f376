"""Local batches: a spawn-context process pool gives the same outputs as one worker; watch mode; recordings."""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from test_process import fake_pipeline, files_under, make_cr2, make_png, make_tiff
from typer.testing import CliRunner

from mca.capture.batch import LineProgress, discover_inputs, run_batch
from mca.capture.cli import app
from mca.capture.pipeline_app import RESULT_NAME
from mca.devices.profiles import load_profile


@pytest.fixture(scope="module")
def profile():
    return load_profile("paper-70d")


def comparable_result(folder: Path) -> dict:
    """result.json without what legitimately differs between runs (timings)."""
    document = json.loads((folder / RESULT_NAME).read_text())
    document.pop("timings_s")
    return document


def assert_same_outputs(first: Path, second: Path) -> None:
    """Two output roots hold the same folders, files, results (modulo timings) and arrays."""
    folders = sorted(p.name for p in first.iterdir() if p.is_dir())
    assert folders == sorted(p.name for p in second.iterdir() if p.is_dir())
    for name in folders:
        a, b = first / name, second / name
        assert files_under(a) == files_under(b), name
        assert comparable_result(a) == comparable_result(b), name
        for tiff in ("depth.tiff", "disparity.tiff"):
            if (a / tiff).exists():
                np.testing.assert_array_equal(tifffile.imread(a / tiff), tifffile.imread(b / tiff))
        for png in sorted(f for f in files_under(a) if f.endswith(".png")):
            np.testing.assert_array_equal(
                cv2.imread(str(a / png), cv2.IMREAD_UNCHANGED), cv2.imread(str(b / png), cv2.IMREAD_UNCHANGED)
            )
        for binary in ("scene.ply", "scene.glb"):
            if (a / binary).exists():
                assert (a / binary).read_bytes() == (b / binary).read_bytes(), f"{name}/{binary}"


@pytest.fixture(scope="module")
def small_inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("inputs")
    make_png(folder / "p1.png", 40, 56)
    make_tiff(folder / "t1.tiff", 36, 48)
    make_cr2(folder / "c1.CR2", 64, 80)
    return folder


def test_two_workers_equal_one(tmp_path, small_inputs, profile):
    one = run_batch([small_inputs], tmp_path / "one", profile, workers=1)
    two = run_batch([small_inputs], tmp_path / "two", profile, workers=2)
    assert sorted(o.status for o in one.outcomes) == ["done"] * 3, [o.reason for o in one.outcomes]
    assert sorted(o.status for o in two.outcomes) == ["done"] * 3, [o.reason for o in two.outcomes]
    assert_same_outputs(tmp_path / "one", tmp_path / "two")


def test_pool_keeps_going_past_bad_files(tmp_path, profile):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a", "b"):
        make_png(folder / f"{name}.png")
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 20)
    (folder / "broken.CR2").write_bytes(b"II*\0")
    lines: list[str] = []
    report = run_batch(
        [folder], tmp_path / "out", profile, workers=2, pipeline=fake_pipeline, progress=LineProgress(lines.append)
    )
    statuses = {o.input_path.name: o.status for o in report.outcomes}
    assert statuses == {"a.png": "done", "b.png": "done", "broken.png": "failed", "broken.CR2": "failed"}
    assert all("broken" in o.reason for o in report.failed)
    assert len(lines) == 4 and lines[-1].startswith("[4/4]")


def test_watch_processes_files_as_they_arrive(tmp_path, profile):
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    make_png(inbox / "first.png")
    holder: dict = {}

    def watch() -> None:
        # settle 2 s against a 0.6 s pause mid-copy: margin for a writer stalled on two busy cores
        holder["report"] = run_batch(
            [inbox],
            tmp_path / "out",
            profile,
            watch=True,
            watch_timeout_s=3.0,
            poll_interval_s=0.1,
            settle_s=2.0,
            pipeline=fake_pipeline,
        )

    thread = threading.Thread(target=watch)
    thread.start()
    try:
        deadline = time.monotonic() + 20
        while not (tmp_path / "out" / "first" / RESULT_NAME).exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (tmp_path / "out" / "first" / RESULT_NAME).exists()
        # a file copied in slowly: processed only once complete (its size stable)
        source = make_png(tmp_path / "second.png")
        data = source.read_bytes()
        with open(inbox / "second.png", "wb") as handle:
            handle.write(data[:40])
            handle.flush()
            time.sleep(0.6)
            handle.write(data[40:])
        shutil.copy(source, inbox / "third.png")
    finally:
        thread.join(timeout=60)
    assert not thread.is_alive()
    report = holder["report"]
    assert {o.input_path.name: o.status for o in report.outcomes} == {
        "first.png": "done",
        "second.png": "done",
        "third.png": "done",
    }


def test_discovery_skips_hidden_and_foreign_files(tmp_path):
    for name in ("b.png", "a.CR2", ".a.png.123.tmp", ".hidden.png", "notes.txt", "c.JPG"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "deep.png").write_bytes(b"x")
    assert [p.name for p in discover_inputs([tmp_path])] == ["a.CR2", "b.png", "c.JPG"]
    assert [p.name for p in discover_inputs([tmp_path / "notes.txt", tmp_path])] == [
        "notes.txt",
        "a.CR2",
        "b.png",
        "c.JPG",
    ]


def test_cli_workers_and_record(tmp_path):
    pytest.importorskip("rerun")
    from test_recording import read_columns

    folder = tmp_path / "in"
    folder.mkdir()
    make_png(folder / "a.png", 32, 40)
    make_png(folder / "b.png", 32, 40)
    merged = tmp_path / "all.rrd"
    result = CliRunner().invoke(
        app, ["process", str(folder), "--out", str(tmp_path / "out"), "--workers", "2", "--record", str(merged)]
    )
    assert result.exit_code == 0, result.output
    assert "2 done" in result.output
    assert merged.stat().st_size > 0
    # a rerun skips both and keeps their shots in the recording it writes again
    again = CliRunner().invoke(app, ["process", str(folder), "--out", str(tmp_path / "out"), "--record", str(merged)])
    assert again.exit_code == 0 and "2 skipped" in again.output
    assert sorted(set(read_columns(merged)["/shot/input"]["shot"])) == [0, 1]
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*.rrd")) == [Path("all.rrd")]


def test_record_stores_each_recording_once(tmp_path):
    """`--record` keeps one copy of every shot's recording (the merged file), not one per result folder as well,
    and the merged file still holds every entity of every shot, as recorded on its own."""
    pytest.importorskip("rerun")
    from test_recording import read_columns, rrd_verify

    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a", "b"):
        make_png(folder / f"{name}.png", 32, 40)
    alone: dict[str, Path] = {}
    for name in ("a", "b"):  # each photograph recorded on its own, elsewhere: the reference
        alone[name] = tmp_path / "alone" / f"{name}.rrd"
        done = CliRunner().invoke(
            app,
            [
                "process",
                str(folder / f"{name}.png"),
                "--out",
                str(tmp_path / f"alone-{name}"),
                "--record",
                str(alone[name]),
            ],
        )
        assert done.exit_code == 0, done.output
    out, merged = tmp_path / "out", tmp_path / "rec" / "all.rrd"
    result = CliRunner().invoke(
        app, ["process", str(folder), "--out", str(out), "--workers", "2", "--record", str(merged), "-q"]
    )
    assert result.exit_code == 0, result.output
    assert rrd_verify(merged).returncode == 0

    on_disk = sorted(out.rglob("*.rrd")) + sorted(merged.parent.rglob("*.rrd"))
    assert on_disk == [merged], on_disk  # no per-folder copies, no parts left behind
    assert not list(out.glob(".mca-recording-parts-*"))
    for name in ("a", "b"):
        assert "recording.rrd" not in json.loads((out / name / RESULT_NAME).read_text())["outputs"]
    single_bytes = sum(p.stat().st_size for p in alone.values())
    assert merged.stat().st_size < 1.25 * single_bytes, (merged.stat().st_size, single_bytes)

    columns = read_columns(merged)
    for shot, name in enumerate(("a", "b")):
        expected = {e for e, c in read_columns(alone[name]).items() if "shot" in c}
        present = {e for e, c in columns.items() if shot in c.get("shot", [])}
        assert expected and expected <= present, sorted(expected - present)


class StageLog:
    """A progress display that keeps every stage it hears."""

    wants_stages = True

    def __init__(self) -> None:
        self.stages: list[tuple[str, str]] = []

    def discovered(self, total: int) -> None: ...

    def started(self, task) -> None: ...

    def stage(self, task, stage: str) -> None:
        self.stages.append((task.input_path.name, stage))

    def finished(self, task, outcome) -> None: ...

    def close(self) -> None: ...


@pytest.mark.parametrize("workers", [1, 2])
def test_stage_progress_reaches_the_display(tmp_path, profile, workers):
    for name in ("a", "b"):
        make_png(tmp_path / f"{name}.png", 24, 32)
    log = StageLog()
    report = run_batch(
        [tmp_path / "a.png", tmp_path / "b.png"],
        tmp_path / "out",
        profile,
        workers=workers,
        pipeline=fake_pipeline,
        progress=log,
    )
    assert [o.status for o in report.outcomes] == ["done", "done"]
    for name in ("a.png", "b.png"):
        assert [s for n, s in log.stages if n == name] == ["read", "disparity", "write"]


def test_batch_recording_is_one_timeline_of_shots(tmp_path):
    """The merged --record file holds one recording whose `shot` timeline steps through the inputs."""
    pytest.importorskip("rerun")
    from test_recording import read_columns, rrd_verify

    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a", "b", "c"):
        make_png(folder / f"{name}.png", 32, 40)
    merged = tmp_path / "all.rrd"
    result = CliRunner().invoke(
        app, ["process", str(folder), "--out", str(tmp_path / "out"), "--workers", "2", "--record", str(merged), "-q"]
    )
    assert result.exit_code == 0, result.output
    assert rrd_verify(merged).returncode == 0
    shots = sorted(set(read_columns(merged)["/shot/input"]["shot"]))
    assert shots == [0, 1, 2]
