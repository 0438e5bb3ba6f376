"""The command line as bench users expect it: --version, -h, completion, --json, config set, the config honoured."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

import mca
from mca.capture.cli import app


def run(*args: str, env: dict[str, str] | None = None):
    return CliRunner().invoke(app, list(args), env=env)


def test_version_and_short_help() -> None:
    assert run("--version").output == f"mca {mca.__version__}\n"
    assert run("-V").exit_code == 0
    for args in ((), ("process",), ("config", "set"), ("rail", "home"), ("camera", "list")):
        short, long = run(*args, "-h"), run(*args, "--help")
        assert short.exit_code == 0 and short.output == long.output and "Usage: mca" in short.output


def test_help_says_usb_bus_addr_not_an_emoji() -> None:
    for args in (("capture", "-h"), ("calibrate", "-h"), ("demo", "-h"), ("camera", "info", "-h")):
        text = run(*args).output
        assert "usb:BUS:ADDR" in text and "\U0001f68c" not in text, args  # rich's :bus: is a bus emoji


def test_shell_completion_completes_commands_and_subcommands() -> None:
    env = dict(os.environ, _MCA_COMPLETE="complete_bash", COMP_WORDS="mca config s", COMP_CWORD="2")
    command = Path(sys.executable).parent / "mca"  # the installed console script, as a shell calls it
    out = subprocess.run([str(command)], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["show", "set"]
    # the script a user installs, from the console script itself (in-process, typer's completion state is global)
    quiet = dict(os.environ, _TYPER_COMPLETE_TEST_DISABLE_SHELL_DETECTION="1")  # the shell is named, never guessed
    script = subprocess.run(
        [str(command), "--show-completion=bash"], env=quiet, capture_output=True, text=True, timeout=60
    )
    assert script.returncode == 0 and "_MCA_COMPLETE" in script.stdout, script.stderr


@pytest.fixture()
def config_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    path = tmp_path / "config.toml"
    monkeypatch.setenv("MCA_CONFIG", str(path))
    return path


def test_config_set_writes_several_keys_at_once_or_none(config_file: Path, tmp_path: Path) -> None:
    done = run("config", "set", "camera=sim", "rail=sim", "workers=3")
    assert done.exit_code == 0, done.output
    shown = json.loads(run("config", "show", "--json").output)
    assert shown["values"] | {"output_dir": None, "profile": None} == {
        "camera": "sim",
        "rail": "sim",
        "workers": 3,
        "output_dir": None,
        "profile": None,
    }
    assert shown["sources"]["camera"] == str(config_file)
    before = config_file.read_text()
    refused = run("config", "set", "camera=auto", "workers=0")  # the second is out of range: nothing written
    assert refused.exit_code == 2 and "workers" in refused.output and str(config_file) in refused.output
    assert config_file.read_text() == before
    assert run("config", "set", "colour=blue").exit_code == 2
    assert run("config", "set", f"output_dir={tmp_path / 'x'}").exit_code == 0
    assert json.loads(run("config", "show", "--json").output)["values"]["workers"] == 3


def test_rail_takes_the_rail_from_the_config(config_file: Path) -> None:
    assert run("config", "set", "rail=sim").exit_code == 0
    status = run("rail", "status")
    assert status.exit_code == 0, status.output
    assert "mm from the home switch" in status.output
    run("config", "set", "rail=/dev/mca-no-such-rail")
    assert "/dev/mca-no-such-rail" in run("rail", "status").output


def test_demo_and_calibrate_take_the_camera_from_the_config(config_file: Path, tmp_path: Path) -> None:
    assert run("config", "set", "camera=usb:250:99", "rail=sim").exit_code == 0
    demo = run("demo", "--out", str(tmp_path / "demo"), "--count", "1")
    assert demo.exit_code != 0 and "usb:250:99" in demo.output
    calibrate = run("calibrate", "--out", str(tmp_path / "cal.toml"), "--from", "0", "--to", "10", "--step", "10")
    assert calibrate.exit_code != 0 and "250" in calibrate.output


@pytest.mark.slow
def test_calibrate_json_with_camera_and_rail_from_the_config(config_file: Path, tmp_path: Path) -> None:
    assert run("config", "set", "camera=sim", "rail=sim", "profile=paper-70d").exit_code == 0
    out = tmp_path / "cal.toml"
    result = CliRunner().invoke(
        app,
        [
            "calibrate",
            "--from",
            "-100",
            "--to",
            "150",
            "--step",
            "50",
            "--out",
            str(out),
            "--sim-scale",
            "0.1",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["profile"] == str(out) and out.is_file() and document["positions"] == 6
    fitted = document["parameters"]["filter_centre_distance_mm"]
    assert fitted["fitted"] == pytest.approx(fitted["sim_truth"], rel=0.01)


def test_process_json(tmp_path: Path) -> None:
    from test_process import fake_pipeline, make_png

    source = make_png(tmp_path / "a.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    from unittest import mock

    with mock.patch("mca.processing.pipeline.run_pipeline", fake_pipeline):
        result = run("process", str(source), str(tmp_path / "bad.png"), "--out", str(tmp_path / "out"), "--json")
    assert result.exit_code == 1  # one file failed
    document = json.loads(result.stdout)
    assert document["totals"] == {"done": 1, "skipped": 0, "failed": 1}
    by_name = {Path(f["input"]).name: f for f in document["files"]}
    assert by_name["a.png"]["status"] == "done" and by_name["a.png"]["regions"] == 2
    assert Path(by_name["a.png"]["result"]).is_file()
    assert by_name["bad.png"]["status"] == "failed" and "bad.png" in by_name["bad.png"]["reason"]
