"""The config loader: defaults, search order, MCA_CONFIG, validation errors naming file and key, `mca config show`."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from mca.capture.config import KEYS, Config, ConfigError, load_config, read_config_file, user_config_path

REPO = Path(__file__).resolve().parents[1]


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    return {
        "system": tmp_path / "etc" / "mca" / "config.toml",
        "user": tmp_path / "home" / ".config" / "mca" / "config.toml",
        "home": tmp_path / "home",
    }


def _load(files: dict[str, Path], **env: str) -> Config:
    return load_config(env={"HOME": str(files["home"]), **env}, system_path=files["system"], user_path=files["user"])


def test_defaults_when_no_file_exists(files: dict[str, Path]) -> None:
    config = _load(files)
    assert config == Config()
    assert (config.profile, config.camera, config.rail, config.workers) == ("paper-70d", "auto", "sim", 1)
    assert config.output_dir == Path("~/mca").expanduser()
    assert all(config.source_of(key) == "default" for key in KEYS)


def test_user_file_wins_over_system_file_key_by_key(files: dict[str, Path]) -> None:
    _write(files["system"], 'camera = "sim"\nworkers = 4\nrail = "/dev/mca-rail"\n')
    _write(files["user"], "workers = 2\n")
    config = _load(files)
    assert config.workers == 2 and config.source_of("workers") == str(files["user"])
    assert config.camera == "sim" and config.source_of("camera") == str(files["system"])
    assert config.rail == "/dev/mca-rail" and config.source_of("rail") == str(files["system"])
    assert config.source_of("profile") == "default"


def test_mca_config_replaces_both_searched_files(files: dict[str, Path], tmp_path: Path) -> None:
    _write(files["system"], 'camera = "sim"\n')
    _write(files["user"], "workers = 2\n")
    explicit = _write(tmp_path / "bench.toml", 'camera = "usb:3:17"\n')
    config = _load(files, MCA_CONFIG=str(explicit))
    assert config.camera == "usb:3:17" and config.source_of("camera") == str(explicit)
    assert config.workers == 1 and config.source_of("workers") == "default"


def test_missing_mca_config_file_is_an_error(files: dict[str, Path], tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError) as info:
        _load(files, MCA_CONFIG=str(missing))
    assert info.value.path == str(missing)
    assert "MCA_CONFIG" in str(info.value)


def test_user_path_follows_xdg_config_home(tmp_path: Path) -> None:
    assert (
        user_config_path({"XDG_CONFIG_HOME": str(tmp_path / "cfg"), "HOME": "/nowhere"})
        == tmp_path / "cfg" / "mca" / "config.toml"
    )
    assert user_config_path({"HOME": str(tmp_path)}) == tmp_path / ".config" / "mca" / "config.toml"
    # A relative XDG_CONFIG_HOME is invalid per the XDG spec and ignored.
    assert (
        user_config_path({"XDG_CONFIG_HOME": "rel", "HOME": str(tmp_path)})
        == tmp_path / ".config" / "mca" / "config.toml"
    )


def test_relative_paths_are_relative_to_the_file(files: dict[str, Path]) -> None:
    _write(files["system"], 'output_dir = "data"\nprofile = "profiles/mine.toml"\n')
    config = _load(files)
    folder = files["system"].parent
    assert config.output_dir == folder / "data"
    assert config.profile == str(folder / "profiles" / "mine.toml")


def test_builtin_profile_name_is_kept_as_a_name(files: dict[str, Path]) -> None:
    _write(files["user"], 'profile = "bando2008"\n')
    assert _load(files).profile == "bando2008"


def test_bad_toml_names_the_file(files: dict[str, Path]) -> None:
    _write(files["user"], "workers = \n")
    with pytest.raises(ConfigError) as info:
        _load(files)
    assert info.value.path == str(files["user"])
    assert str(files["user"]) in str(info.value) and "not valid TOML" in str(info.value)
    assert "line 1" in str(info.value)


def test_unknown_key_names_file_and_key_and_suggests(files: dict[str, Path]) -> None:
    _write(files["system"], "workres = 3\n")
    with pytest.raises(ConfigError) as info:
        _load(files)
    assert info.value.key == "workres" and info.value.path == str(files["system"])
    assert "did you mean 'workers'" in str(info.value)
    assert str(info.value).startswith(f"{files['system']}: key 'workres': ")


@pytest.mark.parametrize(
    "text, key, fragment",
    [
        ('workers = "two"', "workers", "whole number"),
        ("workers = 0", "workers", "between 1 and"),
        ("workers = true", "workers", "whole number"),
        ("workers = 2.5", "workers", "whole number"),
        ('camera = "usb:1"', "camera", "usb:BUS:ADDR"),
        ('camera = "usb:0:5"', "camera", "usb:BUS:ADDR"),
        ('camera = "usb:1:200"', "camera", "usb:BUS:ADDR"),
        ('camera = "canon"', "camera", "auto"),
        ('camera = "ptpip:host:99999"', "camera", "ptpip:HOST[:PORT]"),
        ('rail = "ttyUSB0"', "rail", "/dev/ttyUSB0"),
        ("rail = 3", "rail", "non-empty string"),
        ('profile = ""', "profile", "non-empty string"),
        ('output_dir = ["a"]', "output_dir", "non-empty string"),
        ("[camera]\nbus = 1", "camera", "non-empty string"),
    ],
)
def test_bad_values_name_file_and_key(files: dict[str, Path], text: str, key: str, fragment: str) -> None:
    _write(files["user"], text + "\n")
    with pytest.raises(ConfigError) as info:
        _load(files)
    assert info.value.key == key
    assert info.value.path == str(files["user"])
    assert fragment in str(info.value)


@pytest.mark.parametrize(
    "camera, normalised",
    [
        ("auto", "auto"),
        ("sim", "sim"),
        ("usb:001:005", "usb:1:5"),
        ("usb:255:127", "usb:255:127"),
        ("ptpip:127.0.0.1", "ptpip:127.0.0.1"),
        ("ptpip:eos70d.local:15740", "ptpip:eos70d.local:15740"),
    ],
)
def test_camera_forms(files: dict[str, Path], camera: str, normalised: str) -> None:
    _write(files["user"], f'camera = "{camera}"\n')
    assert _load(files).camera == normalised


@pytest.mark.parametrize("rail", ["sim", "/dev/ttyUSB0", "/dev/mca-rail", "loop://", "socket://localhost:2300"])
def test_rail_forms(files: dict[str, Path], rail: str) -> None:
    _write(files["user"], f'rail = "{rail}"\n')
    assert _load(files).rail == rail


def test_unreadable_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        read_config_file(tmp_path)
    assert info.value.path == str(tmp_path) and "directory" in str(info.value)
    bad = _write(tmp_path / "latin1.toml", "")
    bad.write_bytes(b'profile = "caf\xe9"\n')
    with pytest.raises(ConfigError, match="not UTF-8"):
        read_config_file(bad)


def test_example_config_loads_and_states_the_defaults(tmp_path: Path) -> None:
    example = REPO / "deploy" / "config.example.toml"
    data = tomllib.loads(example.read_text(encoding="utf-8"))
    assert set(data) == set(KEYS)
    config = load_config(env={"MCA_CONFIG": str(example)})
    defaults = Config()
    for key in KEYS:
        assert getattr(config, key) == getattr(defaults, key), key
        assert config.source_of(key) == str(example)


def test_mca_config_show_prints_values_and_sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from mca.capture.cli import app

    explicit = _write(tmp_path / "bench.toml", 'camera = "sim"\nworkers = 3\n')
    monkeypatch.setenv("MCA_CONFIG", str(explicit))
    result = CliRunner().invoke(app, ["config", "show"])
    assert result.exit_code == 0, result.output
    lines = {line.split("=")[0].strip(): line for line in result.output.splitlines()}
    assert lines["camera"].startswith('camera = "sim"') and lines["camera"].endswith(f"# {explicit}")
    assert lines["workers"].startswith("workers = 3") and lines["workers"].endswith(f"# {explicit}")
    assert lines["profile"].endswith("# default")
    # The printed text is itself a valid config file.
    assert tomllib.loads(result.output)["workers"] == 3

    result = CliRunner().invoke(app, ["config", "show", "--json"])
    assert result.exit_code == 0, result.output
    shown = json.loads(result.output)
    assert shown["values"]["camera"] == "sim" and shown["sources"]["camera"] == str(explicit)
    assert shown["sources"]["rail"] == "default"


def test_mca_config_show_reports_errors_with_exit_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from mca.capture.cli import app

    bad = _write(tmp_path / "bad.toml", 'workers = "many"\n')
    monkeypatch.setenv("MCA_CONFIG", str(bad))
    result = CliRunner().invoke(app, ["config", "show"])
    assert result.exit_code == 2
    assert f"{bad}: key 'workers'" in result.output


def test_process_and_capture_take_their_defaults_from_the_config_file(tmp_path, monkeypatch):
    """A flag left out falls back to the config file: here a broken profile named there is what gets refused."""
    from typer.testing import CliRunner

    from mca.capture.cli import app

    config = tmp_path / "config.toml"
    config.write_text('profile = "no-such-profile"\nworkers = 1\n')
    monkeypatch.setenv("MCA_CONFIG", str(config))
    runner = CliRunner()
    image = tmp_path / "in.png"
    image.write_bytes(b"")
    result = runner.invoke(app, ["process", str(image), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2 and "no-such-profile" in result.output
    # with the flag given, the config's profile is not consulted
    given = runner.invoke(app, ["process", str(image), "--out", str(tmp_path / "out"), "--profile", "paper-70d", "-q"])
    assert "no-such-profile" not in given.output
    config.write_text('camera = "usb:99:99"\n')
    captured = runner.invoke(app, ["capture", "--out", str(tmp_path / "shots")])
    assert captured.exit_code != 0 and "99" in captured.output
