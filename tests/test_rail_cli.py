"""`mca rail home|move|status` against `--rail sim` and a missing port."""

from __future__ import annotations

from typer.testing import CliRunner

from mca.capture.cli import app

runner = CliRunner()


def _text(result) -> str:
    return result.output + (getattr(result, "stderr", "") or "")


def test_status_of_a_fresh_sim_controller_shows_the_lock() -> None:
    result = runner.invoke(app, ["rail", "status", "--rail", "sim"])
    assert result.exit_code == 0, _text(result)
    assert "Alarm at 0.000 mm" in result.output and "travel 0 .. 300.000 mm" in result.output


def test_home_and_move() -> None:
    result = runner.invoke(app, ["rail", "home", "--rail", "sim"])
    assert result.exit_code == 0 and "Idle at 1.000 mm" in result.output
    result = runner.invoke(app, ["rail", "move", "50", "--rail", "sim", "--home", "--feed", "3000"])
    assert result.exit_code == 0, _text(result)
    assert "Idle at 50.000 mm" in result.output and "machine X -50.000" in result.output


def test_move_errors_tell_what_to_do() -> None:
    locked = runner.invoke(app, ["rail", "move", "50", "--rail", "sim"])
    assert locked.exit_code == 1 and "error:9" in _text(locked) and "mca rail home" in _text(locked)
    beyond = runner.invoke(app, ["rail", "move", "999", "--rail", "sim", "--home"])
    assert beyond.exit_code == 1 and "outside the travel" in _text(beyond)


def test_missing_port_names_it() -> None:
    result = runner.invoke(app, ["rail", "home", "--rail", "/dev/ttyUSB-missing"])
    assert result.exit_code == 1
    assert "/dev/ttyUSB-missing" in _text(result) and "cannot open" in _text(result)
