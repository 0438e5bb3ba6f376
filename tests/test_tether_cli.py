"""`mca capture`, `mca camera` and `mca camera doctor` against the simulated camera: files, catalog rows, clear
errors instead of tracebacks, summaries that survive Ctrl-C, and the doctor's report."""

from __future__ import annotations

import errno
import sqlite3
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mca.capture.cli import app
from mca.devices.ptp.codec import Container
from mca.devices.ptp.codes import ContainerType, Op, Resp
from mca.devices.sim.eos70d.responder import Reply, SimEos70D, default_frame_source


@pytest.fixture(autouse=True)
def fast_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulated body "photographs" small deterministic files here (the rendering is tested elsewhere)."""
    from mca.devices.sim import world

    monkeypatch.setattr(world, "scene_frame_source", lambda *a, **k: default_frame_source)


def _hook(monkeypatch: pytest.MonkeyPatch, hook) -> None:
    """Route every command the simulated body receives through `hook(sim, command, data_out, handle)`."""
    original = SimEos70D.handle
    monkeypatch.setattr(SimEos70D, "handle", lambda self, cmd, data_out=None: hook(self, cmd, data_out, original))


def _fail(cmd, code: int) -> Reply:
    return Reply(Container(ContainerType.RESPONSE, code, cmd.transaction_id, ()))


def _no_traceback(result) -> None:
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output


def test_capture_three_shots_leaves_three_cr2_files_and_a_catalog(tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    files = sorted(p.name for p in out.glob("*.CR2"))
    assert files == ["IMG_0001.CR2", "IMG_0002.CR2", "IMG_0003.CR2"]
    rows = (
        sqlite3.connect(out / "catalog.sqlite")
        .execute("SELECT file_name, status, size_bytes, sha256 FROM shots ORDER BY id")
        .fetchall()
    )
    assert [(r[0], r[1]) for r in rows] == [(f, "downloaded") for f in files]
    assert all(r[2] == (out / r[0]).stat().st_size and len(r[3]) == 64 for r in rows)


def test_camera_config_get_and_set_on_the_simulated_body() -> None:
    runner = CliRunner()
    got = runner.invoke(app, ["camera", "config", "get", "iso", "--camera", "sim"])
    assert got.exit_code == 0 and "iso = 100" in got.output and "6400" in got.output
    bad = runner.invoke(app, ["camera", "config", "set", "iso", "123", "--camera", "sim"])
    assert bad.exit_code == 2
    info = runner.invoke(app, ["camera", "info", "--camera", "sim"])
    assert "Canon EOS 70D" in info.output and "SIM70D0000001" in info.output


def test_an_unknown_property_name_is_a_plain_error_not_a_quoted_key_error() -> None:
    result = CliRunner().invoke(app, ["camera", "config", "get", "whitebalanc", "--camera", "sim"])
    assert result.exit_code == 2 and "unknown property 'whitebalanc'" in result.output
    assert '"unknown property' not in result.output
    _no_traceback(result)


# 13.8: capture problems end with clear errors ---------------------------------------------------------------------


def test_a_camera_error_answer_during_download_is_reported_not_a_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def hook(sim, cmd, data_out, handle):
        if cmd.code == Op.GET_OBJECT_INFO:
            return _fail(cmd, Resp.GENERAL_ERROR)
        return handle(sim, cmd, data_out)

    _hook(monkeypatch, hook)
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "1", "--out", str(tmp_path / "o")])
    _no_traceback(result)
    assert result.exit_code == 1 and "GENERAL_ERROR" in result.output
    assert "captured (download pending)" in result.output  # the shot is on the card; the next run fetches it


def test_an_output_folder_that_is_a_file_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "taken"
    blocker.write_text("not a folder")
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--out", str(blocker / "sub")])
    _no_traceback(result)
    assert result.exit_code == 2 and "cannot use" in result.output and str(blocker) in result.output


def test_a_damaged_catalog_is_a_clear_error(tmp_path: Path) -> None:
    out = tmp_path / "o"
    out.mkdir()
    (out / "catalog.sqlite").write_bytes(b"this is not a database" * 100)
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--out", str(out)])
    _no_traceback(result)
    assert result.exit_code == 2 and "catalog" in result.output and "move the damaged file aside" in result.output


def test_a_full_disk_leaves_no_part_file_and_keeps_the_shot_pending(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mca.capture.tether as tether

    written = {"n": 0}
    real_write = tether._HashingWriter.write

    def full(self, piece):
        written["n"] += len(piece)
        if written["n"] > 100_000:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, piece)

    monkeypatch.setattr(tether._HashingWriter, "write", full)
    out = tmp_path / "o"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "1", "--out", str(out)])
    _no_traceback(result)
    assert result.exit_code == 1
    assert not list(out.glob(".*.part")) and not list(out.glob("*.CR2"))
    assert "full" in result.output and "captured (download pending)" in result.output
    row = sqlite3.connect(out / "catalog.sqlite").execute("SELECT status, camera_filename FROM shots").fetchone()
    assert row == ("captured", "IMG_0001.CR2")


def test_ctrl_c_in_tethered_mode_prints_the_summary_and_fails_when_a_download_failed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A shutter-button shot whose download fails, then Ctrl-C: the summary lists the shot and the exit code
    says not everything reached the disk (it used to print nothing and exit 0)."""
    state = {"pressed": False, "info_seen": False, "interrupted": False}

    def hook(sim, cmd, data_out, handle):
        if cmd.code == Op.GET_OBJECT_INFO:
            state["info_seen"] = True
        if cmd.code == Op.EOS_GET_EVENT and state["info_seen"] and not state["interrupted"]:
            state["interrupted"] = True
            raise KeyboardInterrupt  # the photographer presses Ctrl-C once
        reply = handle(sim, cmd, data_out)
        if cmd.code == Op.EOS_SET_EVENT_MODE and cmd.params[:1] == (1,) and not state["pressed"]:
            state["pressed"] = True
            sim.frame_source = lambda i: ("IMG_0001.CR2", b"")  # an empty file: the host refuses it
            sim.press_shutter_button()
            sim.wait_idle()
        return reply

    _hook(monkeypatch, hook)
    out = tmp_path / "o"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--tethered", "--out", str(out)])
    _no_traceback(result)
    assert "IMG_0001.CR2" in result.output and "interrupted" in result.output
    assert result.exit_code == 1


def test_ctrl_c_during_a_batch_lists_the_shot_in_flight(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen_handles: list[int] = []
    interrupted: list[bool] = []

    def hook(sim, cmd, data_out, handle):
        if cmd.code == Op.EOS_GET_PARTIAL_OBJECT:
            if cmd.params[0] not in seen_handles:
                seen_handles.append(cmd.params[0])
            if len(seen_handles) == 2 and not interrupted:
                interrupted.append(True)
                raise KeyboardInterrupt  # Ctrl-C during the second shot's download
        return handle(sim, cmd, data_out)

    _hook(monkeypatch, hook)
    out = tmp_path / "o"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "3", "--out", str(out)])
    _no_traceback(result)
    assert result.exit_code != 0
    assert "IMG_0001.CR2" in result.output and "IMG_0002.CR2" in result.output
    assert "captured (download pending)" in result.output and "(interrupted)" in result.output
    assert not list(out.glob(".*.part"))


# the doctor ---------------------------------------------------------------------------------------------------------


def test_doctor_reports_the_wire_the_choices_and_writes_a_file(tmp_path: Path) -> None:
    report = tmp_path / "doctor.txt"
    result = CliRunner().invoke(app, ["camera", "doctor", "--camera", "sim", "--report", str(report), "--live-view"])
    assert result.exit_code == 0, result.output
    text = report.read_text()
    assert text == result.stdout
    assert "vendor extension id:      0x00000006 (6)" in text and "vendor extension version: 100" in text
    assert "model:                    'Canon EOS 70D'" in text and "firmware:                 '3-1.1.1'" in text
    assert "operations (169):" in text and "0x9128 EOS RemoteReleaseOn" in text
    assert (
        "0xD11C CaptureDestination" in text
        and "BatteryLevel: type 0x0002, ro, 75, allowed [100, 75, 50, 25, 0]" in text
    )
    assert "vendor extension id: 0xB (the body sends 6" in text
    assert (
        "shutter release:     RemoteReleaseOn/Off" in text
        and "download:            EOS GetPartialObject 0x9107" in text
    )
    assert "capture target card: value 2" in text and "live-view probe:     one JPEG" in text
    assert "transaction_timeout_s = 20.0" in text
    assert "== Findings ==" in text


def test_doctor_names_what_is_unexpected(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import struct

    def hook(sim, cmd, data_out, handle):
        if cmd.code == Op.EOS_SET_EVENT_MODE and cmd.params[:1] == (1,):
            sim.values[0xD120] = struct.pack("<5I", 1, 0x10, 1, 0, 3)  # the owner set Large Fine JPEG
        return handle(sim, cmd, data_out)

    _hook(monkeypatch, hook)
    result = CliRunner().invoke(
        app, ["camera", "doctor", "--camera", "sim:unknown-records", "--report", str(tmp_path / "r.txt")]
    )
    assert result.exit_code == 0, result.output
    assert "0xC1F6" in result.output and "no decoder" in result.output
    assert "image format is Large Fine JPEG: the depth pipeline wants RAW" in result.output
