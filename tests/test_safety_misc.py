"""Profiles refused at load, the rail's end of travel, camera property messages (issue 13, items 7 and 11).

Before the fix a profile with no baseline or with 1e300 mm was accepted and every photograph then
failed with ZeroDivisionError; a rail target of 300.0000001 mm was refused on a 300 mm rail; an
unknown camera property printed a quoted KeyError.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mca.capture.cli import app
from mca.devices.profiles import load_profile_file
from mca.devices.rail import GrblRail
from mca.devices.sim.grbl import SimGrbl, SimGrblPty
from mca.processing.camera import ProfileError

PROFILE = """
name = "hostile"
[camera]
model = "Canon EOS 70D"
pixel_pitch_mm = 0.004109
[lens]
focal_length_mm = {focal}
focus_distance_mm = {focus}
[aperture]
filter_diameter_mm = {filter_diameter}
red = [{red}, 0.0]
green = [0.0, {green}]
blue = [{blue}, 0.0]
"""
GOOD = {"focal": 50.0, "focus": 1000.0, "filter_diameter": 3.0, "red": 6.0, "green": 6.0, "blue": -6.0}


def _write(tmp_path: Path, **changes: object) -> Path:
    path = tmp_path / "p.toml"
    path.write_text(PROFILE.format(**{**GOOD, **changes}))
    return path


def test_the_good_profile_loads(tmp_path):
    assert load_profile_file(_write(tmp_path)).aperture.baseline_mm == pytest.approx(12.0)


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"red": 0.0, "green": 0.0, "blue": 0.0, "filter_diameter": 1e-12}, "aperture.red"),
        ({"red": 1e-9, "green": 0.0, "blue": 0.0, "filter_diameter": 1e-12}, "aperture.red"),
        ({"focal": 1e300}, "lens.focal_length_mm"),
        ({"focus": 1e300}, "lens.focus_distance_mm"),
        ({"filter_diameter": 1e300}, "aperture.filter_diameter_mm"),
        ({"red": 1e300}, "aperture.red"),
        ({"blue": -1e300}, "aperture.blue"),
    ],
    ids=["zero-baseline", "nano-baseline", "focal-1e300", "focus-1e300", "filter-1e300", "red-1e300", "blue-1e300"],
)
def test_implausible_profiles_are_refused_at_load_naming_the_field(tmp_path, changes, field):
    path = _write(tmp_path, **changes)
    with pytest.raises(ProfileError) as caught:
        load_profile_file(path)
    assert caught.value.field == field and str(path) in str(caught.value)


def test_process_refuses_such_a_profile_before_any_file(tmp_path):
    image = tmp_path / "a.png"
    image.write_bytes(b"")
    path = _write(tmp_path, red=0.0, green=0.0, blue=0.0, filter_diameter=1e-12)
    result = CliRunner().invoke(app, ["process", str(image), "--out", str(tmp_path / "out"), "--profile", str(path)])
    assert result.exit_code == 2 and "aperture.red" in result.output and "no baseline" in result.output


@pytest.fixture
def rail(tmp_path: Path) -> Iterator[GrblRail]:
    with (
        SimGrblPty(SimGrbl(speedup=2000.0), link_path=tmp_path / "ttyRAIL") as sim,
        GrblRail(sim.port, poll_interval_s=0.01, answer_timeout_s=1.0) as stage,
    ):
        yield stage


def test_a_target_a_hair_beyond_the_end_of_travel_is_the_end(rail: GrblRail) -> None:
    rail.home()
    assert rail.travel_mm == 300.0
    status = rail.move_to(300.0000001)
    assert status.position_mm == pytest.approx(300.0, abs=0.001)
    status = rail.move_to(-0.0000001)
    assert status.position_mm == pytest.approx(0.0, abs=0.001)
    from mca.devices.rail import RailCommandError

    with pytest.raises(RailCommandError, match="outside the travel"):
        rail.move_to(300.01)


def test_an_unknown_camera_property_is_named_without_a_quoted_key_error() -> None:
    result = CliRunner().invoke(app, ["camera", "config", "get", "nosuchthing", "--camera", "sim"])
    assert result.exit_code == 2
    assert "error: unknown property 'nosuchthing'" in result.output
    assert '"unknown property' not in result.output
