"""Camera profiles: built-ins load, and malformed files are refused with the file and the field named."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from mca.devices.profiles import builtin_names, load_profile, load_profile_file
from mca.processing.camera import ProfileError

PAPER = """
name = "test"
[camera]
model = "Canon EOS 70D"
pixel_pitch_mm = 0.004109
[lens]
focal_length_mm = 50.0
focus_distance_mm = 1000.0
f_number = 1.8
[aperture]
filter_diameter_mm = 3.0
red = [6.0, 0.0]
green = [0.0, 6.0]
blue = [-6.0, 0.0]
"""


def _write(tmp_path: Path, text: str, name: str = "p.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_builtin_paper_profile_matches_the_paper():
    p = load_profile("paper-70d")
    assert p.model == "Canon EOS 70D"
    assert (p.width_px, p.height_px) == (5472, 3648)
    assert p.pixel_pitch_mm == pytest.approx(0.004109)
    assert p.lens.focal_length_mm == 50.0
    assert p.lens.sensor_distance_mm == pytest.approx(52.63)
    assert p.lens.focus_distance_mm == pytest.approx(1000.57, abs=0.01)
    assert p.aperture.widest_pair == ("red", "blue")
    assert p.aperture.filter_centre_distance_mm("red", "blue") == pytest.approx(12.0)
    assert p.has_optics


def test_builtin_names_and_disparity_only_profile():
    assert {"paper-70d", "bando2008"} <= set(builtin_names())
    bando = load_profile("bando2008")
    assert bando.lens is None and not bando.has_optics


def test_profile_is_frozen():
    p = load_profile("paper-70d")
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.name = "other"  # type: ignore[misc]


def test_focus_distance_gives_sensor_distance(tmp_path):
    p = load_profile_file(_write(tmp_path, PAPER))
    assert p.lens.sensor_distance_mm == pytest.approx(50 * 1000 / 950)
    assert p.lens.focus_distance_mm == pytest.approx(1000.0)


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda t: t.replace("focal_length_mm = 50.0\n", ""), "lens.focal_length_mm"),
        (lambda t: t.replace("focal_length_mm = 50.0", "focal_length_mm = -50.0"), "lens.focal_length_mm"),
        (lambda t: t.replace("focus_distance_mm = 1000.0", "focus_distance_mm = 40.0"), "lens.focus_distance_mm"),
        (lambda t: t.replace("focus_distance_mm = 1000.0", "sensor_distance_mm = 45.0"), "lens.sensor_distance_mm"),
        (
            lambda t: t.replace("focus_distance_mm = 1000.0", "focus_distance_mm = 1000.0\nsensor_distance_mm = 52.0"),
            "lens.focus_distance_mm",
        ),
        (lambda t: t.replace("red = [6.0, 0.0]", "red = [20.0, 0.0]"), "aperture.red"),
        (lambda t: t.replace("blue = [-6.0, 0.0]", "blue = [5.0, 0.5]"), "aperture.blue"),
        (lambda t: t.replace("green = [0.0, 6.0]", 'green = "top"'), "aperture.green"),
        (lambda t: t.replace("filter_diameter_mm = 3.0", "filter_diameter_mm = 0"), "aperture.filter_diameter_mm"),
        (lambda t: t.replace('model = "Canon EOS 70D"\n', ""), "camera.model"),
        (lambda t: t.replace("pixel_pitch_mm = 0.004109", "pixel_pitch_mm = 4.109"), "camera.pixel_pitch_mm"),
        (lambda t: t.replace('name = "test"\n', ""), "name"),
        (lambda t: t.replace("[aperture]", "[aperture]\ncrosstalk = [[1,0,0],[1,0,0],[0,0,1]]"), "aperture.crosstalk"),
        (lambda t: t.replace("[aperture]", "[aperture]\ncrosstalk = [[1,0],[0,1]]"), "aperture.crosstalk"),
        (lambda t: t.split("[aperture]")[0], "aperture"),
    ],
)
def test_malformed_profiles_name_the_file_and_field(tmp_path, edit, field):
    path = _write(tmp_path, edit(PAPER))
    with pytest.raises(ProfileError) as info:
        load_profile_file(path)
    assert info.value.field == field
    assert str(path) in str(info.value) and field in str(info.value)


def test_not_toml_at_all(tmp_path):
    path = _write(tmp_path, "this is { not toml")
    with pytest.raises(ProfileError, match="not valid TOML") as info:
        load_profile_file(path)
    assert str(path) in str(info.value)


def test_binary_file_and_missing_file_and_directory(tmp_path):
    binary = tmp_path / "b.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ProfileError, match="UTF-8"):
        load_profile_file(binary)
    with pytest.raises(ProfileError, match="no such file"):
        load_profile(tmp_path / "absent.toml")
    with pytest.raises(ProfileError, match="directory"):
        load_profile_file(tmp_path)
    with pytest.raises(ProfileError, match="neither a built-in"):
        load_profile("no-such-profile")


def test_crosstalk_is_read(tmp_path):
    text = PAPER.replace("[aperture]", "[aperture]\ncrosstalk = [[0.9,0.1,0],[0.05,0.9,0.05],[0,0.1,0.9]]")
    p = load_profile_file(_write(tmp_path, text))
    assert p.aperture.crosstalk[1] == (0.05, 0.9, 0.05)


def test_lateral_colour_is_read_and_bad_values_are_refused(tmp_path):
    measure = PAPER.replace("[aperture]", '[aperture]\nlateral_colour = "measure"')
    assert load_profile_file(_write(tmp_path, measure)).aperture.lateral_colour == "measure"
    calibrated = PAPER.replace("[aperture]", "[aperture]\nlateral_colour = [[0.02, 0.03], [0.4, 0.45]]")
    assert load_profile_file(_write(tmp_path, calibrated)).aperture.lateral_colour == ((0.02, 0.03), (0.4, 0.45))
    assert load_profile("paper-70d").aperture.lateral_colour is None
    for bad, message in (
        ('"auto"', "measure"),
        ("[0.4, 0.45]", "measure"),
        ("[[0.1, 0.2], [0.3, true]]", "measure"),
        ("[[0.1, 0.2], [30.0, 0.3]]", "parts per thousand"),
    ):
        text = PAPER.replace("[aperture]", f"[aperture]\nlateral_colour = {bad}")
        with pytest.raises(ProfileError, match=message) as info:
            load_profile_file(_write(tmp_path, text))
        assert "aperture.lateral_colour" in str(info.value) and "p.toml" in str(info.value)


def _mca(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mca", *args], capture_output=True, text=True, timeout=120)


def test_cli_optics_json_for_the_issue_example():
    result = _mca("optics", "--profile", "paper-70d", "--disparity-px", "10", "--json")
    assert result.returncode == 0, result.stderr
    values = json.loads(result.stdout)
    assert set(values) == {"disparity_px", "inter_image_depth_mm", "inter_object_depth_mm", "distance_mm"}
    assert values["inter_image_depth_mm"] == pytest.approx(0.1796, abs=0.00005)
    assert values["inter_object_depth_mm"] == pytest.approx(69.7, abs=0.05)


def test_cli_optics_from_distance_and_from_inter_image_depth_agree():
    by_distance = json.loads(_mca("optics", "--distance-mm", "1090", "--json").stdout)
    by_depth = json.loads(
        _mca("optics", "--inter-image-depth-mm", str(by_distance["inter_image_depth_mm"]), "--json").stdout
    )
    assert by_distance["distance_mm"] == pytest.approx(1090.0, abs=1e-3)
    assert by_depth["distance_mm"] == pytest.approx(1090.0, abs=0.01)
    assert by_depth["disparity_px"] == pytest.approx(by_distance["disparity_px"], abs=1e-4)


def test_cli_optics_refuses_two_inputs_and_bad_profile(tmp_path):
    both = _mca("optics", "--disparity-px", "1", "--distance-mm", "900")
    assert both.returncode == 2 and "exactly one" in both.stderr
    bad = _write(tmp_path, PAPER.replace("focal_length_mm = 50.0", "focal_length_mm = -1"))
    refused = _mca("optics", "--profile", str(bad), "--disparity-px", "1")
    assert refused.returncode == 2 and "lens.focal_length_mm" in refused.stderr and str(bad) in refused.stderr


def test_cli_profile_list_and_show(tmp_path):
    listing = _mca("profile", "list")
    assert listing.returncode == 0 and "paper-70d" in listing.stdout and "bando2008" in listing.stdout
    shown = _mca("profile", "show", "paper-70d")
    assert shown.returncode == 0
    assert "52.6300 mm" in shown.stdout and "red and blue" in shown.stdout
    by_path = _mca("profile", "show", str(_write(tmp_path, PAPER)))
    assert by_path.returncode == 0 and "1000.00 mm" in by_path.stdout
    broken = _mca("profile", "show", str(_write(tmp_path, "name = 1", "broken.toml")))
    assert broken.returncode == 2 and "broken.toml" in broken.stderr
