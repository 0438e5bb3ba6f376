"""`mca capture` and `mca camera` as bench users of gphoto2 expect them, against the simulated EOS 70D: --json,
the config file's camera, a line per shot with a download bar, --hook-script, --filename, --debug-logfile."""

from __future__ import annotations

import datetime
import json
import re
import sqlite3
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mca.capture.cli import app
from mca.capture.file_names import FilenamePattern, FilenamePatternError
from mca.devices.sim.eos70d.responder import default_frame_source


@pytest.fixture(autouse=True)
def fast_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulated body "photographs" small deterministic files here (the rendering is tested elsewhere)."""
    from mca.devices.sim import world

    monkeypatch.setattr(world, "scene_frame_source", lambda *a, **k: default_frame_source)


@pytest.fixture(autouse=True)
def no_user_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A config file of this test's own (empty: defaults), never the user's."""
    path = tmp_path / "config.toml"
    path.write_text("")
    monkeypatch.setenv("MCA_CONFIG", str(path))
    return path


def run(*args: str):
    return CliRunner().invoke(app, list(args))


def catalog_rows(folder: Path) -> list[tuple]:
    with sqlite3.connect(folder / "catalog.sqlite") as db:
        return db.execute("SELECT id, camera_filename, file_name, size_bytes, sha256, status FROM shots").fetchall()


def hook(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "hook.sh"
    path.write_text("#!/bin/sh\n" + body)
    path.chmod(0o755)
    return path


# --- --json and the config file on `mca camera` ---------------------------------------------------------------------


def test_camera_list_info_and_config_print_json() -> None:
    listed = run("camera", "list", "--sim", "--json")
    assert listed.exit_code == 0, listed.output
    sims = [c for c in json.loads(listed.stdout)["cameras"] if c["port"] == "sim"]
    assert sims == [
        {"port": "sim", "manufacturer": "Canon Inc.", "product": "Canon EOS 70D", "serial_number": "SIM70D0000001"}
    ]
    info = json.loads(run("camera", "info", "--camera", "sim", "--json").stdout)
    assert info["model"] == "Canon EOS 70D" and info["serial_number"] == "SIM70D0000001"
    assert info["storages"] and all(0 < s["free_bytes"] <= s["capacity_bytes"] for s in info["storages"])
    everything = json.loads(run("camera", "config", "--camera", "sim", "--json").stdout)
    assert {"iso", "shutterspeed", "aperture"} <= set(everything)
    assert "400" in everything["iso"]["allowed"]
    changed = json.loads(run("camera", "config", "set", "iso", "400", "--camera", "sim", "--json").stdout)
    assert changed["iso"]["value"] == "400"
    one = json.loads(run("camera", "config", "get", "shutterspeed", "--camera", "sim", "--json").stdout)
    assert list(one) == ["shutterspeed"] and one["shutterspeed"]["value"] == everything["shutterspeed"]["value"]


def test_camera_commands_take_the_camera_from_the_config(tmp_path: Path) -> None:
    assert run("config", "set", "camera=sim").exit_code == 0
    for args in (("camera", "info"), ("camera", "config", "get", "iso")):
        done = run(*args)
        assert done.exit_code == 0, (args, done.output)
    assert "Canon EOS 70D" in run("camera", "info").stdout
    doctor = run("camera", "doctor", "--report", str(tmp_path / "report.txt"))
    assert doctor.exit_code == 0 and "SIM70D0000001" in (tmp_path / "report.txt").read_text()
    assert run("config", "set", "camera=usb:250:99").exit_code == 0
    for args in (("camera", "info"), ("camera", "config"), ("capture", "--out", str(tmp_path / "o"))):
        refused = run(*args)
        assert refused.exit_code != 0 and "250" in refused.output, (args, refused.output)
    assert run("camera", "info", "--camera", "sim").exit_code == 0  # the flag still wins over the config


def test_help_of_camera_commands_says_usb_bus_addr_not_an_emoji() -> None:
    for args in (("camera", "config", "-h"), ("camera", "doctor", "-h"), ("capture", "-h")):
        text = run(*args).output
        assert "usb:BUS:ADDR" in text and "\U0001f68c" not in text, args


# --- `mca capture`: a line per shot, the download bar, --json -------------------------------------------------------


def test_capture_prints_each_shot_as_it_lands_with_a_download_bar(tmp_path: Path) -> None:
    result = run("capture", "--camera", "sim", "--count", "3", "--out", str(tmp_path / "out"))
    assert result.exit_code == 0, result.output
    rows = catalog_rows(tmp_path / "out")
    lines = [line for line in result.stdout.splitlines() if re.match(r"shot \d+: \S+\s+[\d.]+ MB", line)]
    assert len(lines) == 3
    for line, (shot_id, _camera_name, file_name, size_bytes, _sha, _status) in zip(lines, rows):
        number, name, megabytes, clock = re.match(
            r"shot (\d+): (\S+)\s+([\d.]+) MB\s+at (\d\d:\d\d:\d\d)", line
        ).groups()
        assert (int(number), name) == (shot_id, file_name)
        assert float(megabytes) == pytest.approx(size_bytes / 1e6, abs=0.006)
        assert (tmp_path / "out" / name).stat().st_size == size_bytes
        datetime.time.fromisoformat(clock)
    bars = [line for line in result.stderr.splitlines() if line.startswith("download")]
    assert len(bars) == 3 and all("━" in line for line in bars)  # one finished bar per file
    for bar, (*_, size_bytes, _sha, _status) in zip(bars, rows):
        assert f"{size_bytes / 1000:.1f}/{size_bytes / 1000:.1f} kB" in bar


def test_capture_json_lists_every_file_with_its_catalog_row(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = run("capture", "--camera", "sim", "--count", "2", "--out", str(out), "--json")
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)  # stdout holds the document alone; the lines went to stderr
    assert "shot 1:" in result.stderr
    assert document["on_disk"] == 2 and document["interrupted"] is False and document["releases"] == []
    assert Path(document["catalog"]) == (out / "catalog.sqlite").resolve()
    by_id = {row[0]: row for row in catalog_rows(out)}
    for shot in document["shots"]:
        _, camera_name, file_name, size_bytes, sha, status = by_id[shot["id"]]
        assert (shot["camera_filename"], shot["size_bytes"], shot["sha256"], shot["status"]) == (
            camera_name,
            size_bytes,
            sha,
            status,
        )
        assert Path(shot["file"]) == (out / file_name).resolve() and Path(shot["file"]).stat().st_size == size_bytes
        assert shot["captured_at"].endswith("+00:00") and shot["downloaded_at"] >= shot["captured_at"]


# --- --hook-script ----------------------------------------------------------------------------------------------------


def test_hook_script_is_run_as_gphoto2_runs_it(tmp_path: Path) -> None:
    log = tmp_path / "hook.log"
    script = hook(tmp_path, f'echo "$ACTION|$ARGUMENT|$MCA_SHOT_ID|$(test -s "$ARGUMENT" && echo present)" >> {log}\n')
    out = tmp_path / "out"
    result = run("capture", "--camera", "sim", "--count", "2", "--out", str(out), "--hook-script", str(script))
    assert result.exit_code == 0, result.output
    calls = [line.split("|") for line in log.read_text().splitlines()]
    rows = catalog_rows(out)
    assert calls == [
        ["init", "", "", ""],
        ["start", "", "", ""],
        *[
            ["download", str((out / file_name).resolve()), str(shot_id), "present"]
            for shot_id, _, file_name, *_ in rows
        ],
        ["stop", "", "", ""],
    ]


def test_a_failing_hook_is_reported_and_never_loses_the_file(tmp_path: Path) -> None:
    script = hook(tmp_path, '[ "$ACTION" = download ] && { echo "cannot reach the LIMS" >&2; exit 3; }\nexit 0\n')
    out = tmp_path / "out"
    result = run("capture", "--camera", "sim", "--count", "2", "--out", str(out), "--hook-script", str(script))
    assert result.exit_code == 1, result.output
    assert result.output.count("exited with status 3: cannot reach the LIMS") >= 2
    rows = catalog_rows(out)
    assert [r[5] for r in rows] == ["downloaded", "downloaded"]
    for _, _, file_name, size_bytes, *_ in rows:
        assert (out / file_name).stat().st_size == size_bytes


def test_a_hook_that_deletes_the_file_is_reported(tmp_path: Path) -> None:
    script = hook(tmp_path, '[ "$ACTION" = download ] && rm -f "$ARGUMENT"\nexit 0\n')
    result = run("capture", "--camera", "sim", "--out", str(tmp_path / "out"), "--hook-script", str(script), "--json")
    assert result.exit_code == 1
    failures = json.loads(result.stdout)["hook_failures"]
    assert len(failures) == 1 and "no longer there" in failures[0]


def test_a_failing_init_hook_stops_the_run_before_a_shot(tmp_path: Path) -> None:
    script = hook(tmp_path, '[ "$ACTION" = init ] && exit 1\nexit 0\n')
    out = tmp_path / "out"
    result = run("capture", "--camera", "sim", "--count", "2", "--out", str(out), "--hook-script", str(script))
    assert result.exit_code == 1 and "nothing was taken" in result.output
    assert catalog_rows(out) == []


def test_a_hook_that_is_not_executable_is_refused_before_anything(tmp_path: Path) -> None:
    script = tmp_path / "hook.sh"
    script.write_text("#!/bin/sh\n")
    result = run("capture", "--camera", "sim", "--out", str(tmp_path / "out"), "--hook-script", str(script))
    assert result.exit_code == 2 and "chmod +x" in result.output and not (tmp_path / "out").exists()


# --- --filename -------------------------------------------------------------------------------------------------------


def test_filename_pattern_fields() -> None:
    when = datetime.datetime(2024, 5, 1, 10, 15, 2)
    pattern = FilenamePattern.parse("%Y%m%d-%H%M%S-%04n-%f.%C")
    assert pattern.name_for(7, "IMG_0042.CR2", when) == "20240501-101502-0007-IMG_0042.CR2"
    assert FilenamePattern.parse("bench-%n%%.%C").name_for(12, "IMG_1.JPG", when) == "bench-12%.JPG"
    for bad, said in (
        ("shots/%n.%C", "not a path"),
        ("%Q-%n", "unknown field %Q"),
        ("fixed.CR2", "same name"),
        ("%n-50%", "lone '%'"),
        ("%4f", "only %n takes a width"),
    ):
        with pytest.raises(FilenamePatternError, match=re.escape(said)):
            FilenamePattern.parse(bad)


def test_capture_names_files_by_the_pattern_and_keeps_them_safe(tmp_path: Path) -> None:
    out = tmp_path / "out"
    today = datetime.date.today().strftime("%Y%m%d")
    result = run(
        "capture", "--camera", "sim", "--count", "2", "--out", str(out), "--filename", "knife 1:%Y%m%d_%03n.%C"
    )
    assert result.exit_code == 0, result.output
    rows = catalog_rows(out)
    assert [r[2] for r in rows] == [f"knife_1_{today}_{shot_id:03d}.CR2" for shot_id, *_ in rows]
    assert [r[1] for r in rows] == ["IMG_0001.CR2", "IMG_0002.CR2"]  # the camera's names stay in the catalog
    refused = run("capture", "--camera", "sim", "--out", str(out), "--filename", "../%n.%C")
    assert refused.exit_code == 2 and "not a path" in refused.output
    assert len(catalog_rows(out)) == 2


# --- --debug-logfile --------------------------------------------------------------------------------------------------


def test_debug_logfile_logs_every_transaction_and_the_bytes_of_each_download(tmp_path: Path) -> None:
    out, log = tmp_path / "out", tmp_path / "ptp.log"
    result = run("capture", "--camera", "sim", "--count", "2", "--out", str(out), "--debug-logfile", str(log))
    assert result.exit_code == 0, result.output
    lines = log.read_text().splitlines()
    commands = [line for line in lines if " -> " in line]
    answers = [line for line in lines if " <- " in line and "<- event" not in line]
    assert any("OpenSession" in line for line in commands) and any("CloseSession" in line for line in commands)
    assert len(commands) == len(answers)  # every command has its answer (or its error) logged
    tids = [re.search(r"tid=(\d+)", line).group(1) for line in commands]
    assert tids == [re.search(r"tid=(\d+)", line).group(1) for line in answers]
    # the data-in bytes of the object transfers add up to the files on disk
    transfer_tids = {re.search(r"tid=(\d+)", line).group(1) for line in commands if "GetPartialObject" in line}
    received = sum(
        int(re.search(r"data-in=(\d+) B", line).group(1))
        for line in answers
        if re.search(r"tid=(\d+)", line).group(1) in transfer_tids
    )
    assert received == sum(row[3] for row in catalog_rows(out))
    assert all(re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z ", line) for line in lines)
    camera_log = tmp_path / "camera.log"
    assert run("camera", "info", "--camera", "sim", "--debug-logfile", str(camera_log)).exit_code == 0
    assert "GetDeviceInfo" in camera_log.read_text()


# --- `mca evaluate --json` --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_evaluate_table_2_json(tmp_path: Path) -> None:
    figures = tmp_path / "table2.json"
    result = run(
        "evaluate", "--scene", "paper-a", "--scale", "0.08", "--no-peers", "--json", "--json-file", str(figures)
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document == json.loads(figures.read_text())
    assert document["methods"] == ["ours"] and [s["scene"] for s in document["scenes"]] == ["paper-a"]
    scene = document["scenes"][0]
    regions = int(re.search(r"paper-a: (\d+) regions", result.stderr).group(1))
    assert scene["region_count"] == regions
    assert scene["objects"]
    for row in scene["objects"]:
        assert row["abs_error_mm"]["ours"] == pytest.approx(abs(row["estimates_mm"]["ours"] - row["true_mm"]))
