"""The appliance's config file: find, read and validate `config.toml`, and remember where each value came from.

Search order, later wins key by key:

1. built-in defaults (`Config()`),
2. the system file `/etc/mca/config.toml` (what the services read),
3. the user file `$XDG_CONFIG_HOME/mca/config.toml` (`~/.config/mca/config.toml`).

If the environment sets `MCA_CONFIG`, that one file replaces both searched files
and must exist. Relative paths in a file (`output_dir`, a `profile` path) are
taken relative to the folder of the file that names them.

The loader is pure apart from reading the files: nothing here opens a camera or
a serial port, it only checks that the values have a usable shape. `set_config_values`
(`mca config set`) writes a file, atomically, after checking every value as the loader does.
"""

from __future__ import annotations

import difflib
import json
import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

SYSTEM_CONFIG = Path("/etc/mca/config.toml")
ENV_VAR = "MCA_CONFIG"
DEFAULT_SOURCE = "default"

_USB_ADDRESS = re.compile(r"^usb:(\d{1,3}):(\d{1,3})$")
_PTPIP_ADDRESS = re.compile(r"^ptpip:([A-Za-z0-9._-]+|\[[0-9A-Fa-f:]+\])(?::(\d{1,5}))?$")
MAX_WORKERS = 256


class ConfigError(ValueError):
    """A config file that cannot be used; names the file and, where there is one, the key."""

    def __init__(self, path: str | Path, reason: str, key: str | None = None) -> None:
        self.path = str(path)
        self.key = key
        self.reason = reason
        where = f"{self.path}: key '{key}': " if key else f"{self.path}: "
        super().__init__(where + reason)


@dataclass(frozen=True)
class Config:
    """The effective configuration; `sources` maps each key to the file it came from, or "default"."""

    profile: str = "paper-70d"  # built-in profile name or path to a profile TOML file
    output_dir: Path = field(default_factory=lambda: Path("~/mca").expanduser())
    camera: str = "auto"  # auto | sim | usb:BUS:ADDR | ptpip:HOST[:PORT]
    rail: str = "sim"  # sim | a serial device such as /dev/ttyUSB0 | a pyserial URL
    workers: int = 1  # processes the watcher runs in parallel
    sources: Mapping[str, str] = field(default_factory=dict, compare=False)

    def source_of(self, key: str) -> str:
        """Where `key` got its value: a file path, or "default"."""
        return self.sources.get(key, DEFAULT_SOURCE)


KEYS: tuple[str, ...] = tuple(f.name for f in fields(Config) if f.name != "sources")


def user_config_path(env: Mapping[str, str] | None = None) -> Path:
    """`$XDG_CONFIG_HOME/mca/config.toml`, falling back to `~/.config/mca/config.toml`."""
    env = os.environ if env is None else env
    base = env.get("XDG_CONFIG_HOME") or ""
    root = Path(base) if base and Path(base).is_absolute() else Path(env.get("HOME") or Path.home()) / ".config"
    return root / "mca" / "config.toml"


def config_paths(
    env: Mapping[str, str] | None = None, system_path: Path = SYSTEM_CONFIG, user_path: Path | None = None
) -> list[Path]:
    """The files `load_config` reads, lowest precedence first (`MCA_CONFIG` alone if it is set)."""
    env = os.environ if env is None else env
    explicit = env.get(ENV_VAR)
    if explicit:
        return [Path(explicit).expanduser()]
    return [Path(system_path), Path(user_path) if user_path is not None else user_config_path(env)]


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Parse one config file into a mapping; a `ConfigError` names the file when it cannot be read or parsed."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(path, "no such file") from None
    except IsADirectoryError:
        raise ConfigError(path, "is a directory, not a TOML file") from None
    except PermissionError:
        raise ConfigError(path, "permission denied: make it readable by this user (chmod 0644)") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(path, f"is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(path, f"cannot be read: {exc.strerror}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(path, f"is not valid TOML: {exc}") from None


def _relative_to(path_text: str, base: Path, source: Path | None = None, key: str | None = None) -> Path:
    if "\0" in path_text:
        raise ConfigError(source or base, "a path cannot hold a NUL character", key)
    try:
        path = Path(path_text).expanduser()
    except RuntimeError:  # "~name" of a user this machine does not know
        raise ConfigError(
            source or base, f"cannot expand {path_text.split('/')[0]!r}: no such user's home folder", key
        ) from None
    return path if path.is_absolute() else (base / path)


def _looks_like_path(text: str) -> bool:
    return "/" in text or text.lower().endswith(".toml")


def _check_str(path: Path, key: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(path, f"must be a non-empty string in quotes, got {value!r}", key)
    return value.strip()


def validate_value(path: Path, key: str, value: Any) -> Any:
    """Check and normalise one key's value as read from `path`; raise `ConfigError` naming file and key."""
    base = path.parent
    if key == "profile":
        text = _check_str(path, key, value)
        return str(_relative_to(text, base, path, key)) if _looks_like_path(text) else text
    if key == "output_dir":
        return _relative_to(_check_str(path, key, value), base, path, key)
    if key == "camera":
        text = _check_str(path, key, value)
        if text in ("auto", "sim"):
            return text
        match = _USB_ADDRESS.match(text)
        if match:
            bus, address = int(match.group(1)), int(match.group(2))
            if 1 <= bus <= 255 and 1 <= address <= 127:
                return f"usb:{bus}:{address}"
        match = _PTPIP_ADDRESS.match(text)
        if match and (match.group(2) is None or 1 <= int(match.group(2)) <= 65535):
            return text
        raise ConfigError(
            path,
            f'must be "auto", "sim", "usb:BUS:ADDR" (bus 1-255, address 1-127, '
            f'as lsusb shows them) or "ptpip:HOST[:PORT]", got {value!r}',
            key,
        )
    if key == "rail":
        text = _check_str(path, key, value)
        if text == "sim" or text.startswith("/") or "://" in text:
            return text
        raise ConfigError(
            path,
            f'must be "sim", a serial device path such as "/dev/mca-rail" or '
            f'"/dev/ttyUSB0", or a pyserial URL, got {value!r}',
            key,
        )
    if key == "workers":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, f"must be a whole number without quotes, got {value!r}", key)
        if not 1 <= value <= MAX_WORKERS:
            raise ConfigError(path, f"must be between 1 and {MAX_WORKERS}, got {value}", key)
        return value
    raise _unknown_key(path, key)


def _unknown_key(path: Path, key: str) -> ConfigError:
    close = difflib.get_close_matches(key, KEYS, n=1)
    hint = f"did you mean '{close[0]}'? " if close else ""
    return ConfigError(path, f"unknown key; {hint}known keys: {', '.join(KEYS)}", key)


def apply_file(config: Config, path: str | Path, data: Mapping[str, Any]) -> Config:
    """`config` with the keys of one parsed file laid over it, each recorded as coming from `path`."""
    path = Path(path)
    changes: dict[str, Any] = {}
    for key, value in data.items():
        changes[key] = validate_value(path, key, value)
    sources = dict(config.sources)
    sources.update({key: str(path) for key in changes})
    return replace(config, **changes, sources=sources)


def load_config(
    env: Mapping[str, str] | None = None, system_path: Path = SYSTEM_CONFIG, user_path: Path | None = None
) -> Config:
    """The effective configuration: defaults, then the system file, then the user file (or `MCA_CONFIG` alone).

    Missing searched files are skipped; a missing `MCA_CONFIG` file is an error,
    since somebody asked for it by name.
    """
    env = os.environ if env is None else env
    explicit = bool(env.get(ENV_VAR))
    config = Config()
    for path in config_paths(env, system_path, user_path):
        if not path.exists():
            if explicit:
                raise ConfigError(
                    path,
                    f"no such file (named by ${ENV_VAR}); create it from "
                    "deploy/config.example.toml or unset the variable",
                )
            continue
        data = read_config_file(path)
        config = apply_file(config, path, data)
    return config


__all__ = [
    "ENV_VAR",
    "KEYS",
    "SYSTEM_CONFIG",
    "Config",
    "ConfigError",
    "apply_file",
    "config_document",
    "config_lines",
    "config_paths",
    "load_config",
    "read_config_file",
    "set_config_values",
    "settable_config_path",
    "toml_value",
    "user_config_path",
    "validate_value",
]


def fill_from_config(**given: Any) -> dict[str, Any]:
    """The flags as given, with those left out (None) taken from the config (defaults, then files, read once)."""
    unknown = set(given) - set(KEYS)
    if unknown:
        raise KeyError(", ".join(sorted(unknown)))
    if all(value is not None for value in given.values()):
        return dict(given)
    config = load_config()
    return {key: getattr(config, key) if value is None else value for key, value in given.items()}


def toml_value(value: object) -> str:
    """`value` as TOML: an integer as it is, anything else as a basic string."""
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    return json.dumps(str(value))  # a JSON string is a valid TOML basic string


def config_document(config: Config) -> dict[str, dict[str, Any]]:
    """`mca config show --json`: every key's effective value and the file it came from (or "default")."""
    return {
        "values": {key: (getattr(config, key) if key == "workers" else str(getattr(config, key))) for key in KEYS},
        "sources": {key: config.source_of(key) for key in KEYS},
    }


def config_lines(config: Config) -> list[str]:
    """`mca config show`: the effective config as TOML lines, each commented with the file it came from."""
    rendered = [(f"{key} = {toml_value(getattr(config, key))}", config.source_of(key)) for key in KEYS]
    width = max(len(text) for text, _ in rendered)
    return [f"{text:<{width}}  # {source}" for text, source in rendered]


def settable_config_path(system: bool = False, env: Mapping[str, str] | None = None) -> Path:
    """The file `mca config set` writes: the system file if asked, else `$MCA_CONFIG`, else the user file."""
    env = os.environ if env is None else env
    if system:
        return SYSTEM_CONFIG
    if env.get(ENV_VAR):
        return Path(env[ENV_VAR]).expanduser()
    return user_config_path(env)


def set_config_values(path: Path, assignments: list[str]) -> dict[str, object]:
    """Validate every KEY=VALUE, then write them all into the TOML file at `path` (atomically); returns them.

    Values are checked as the loader checks them (a `ConfigError` naming the file and the key, and nothing
    written); a relative path (output_dir, a profile file) is made absolute from the current folder, since
    the loader would read it relative to the file's folder.
    """
    from mca.capture.outputs import write_bytes_atomic

    changes: dict[str, object] = {}
    for assignment in assignments:
        key, sep, text = assignment.partition("=")
        key, text = key.strip(), text.strip()
        if not sep or not key:
            raise ConfigError(path, f"'{assignment}' is not KEY=VALUE (e.g. camera=sim)")
        value: object = text
        if key == "workers":
            try:
                value = int(text)
            except ValueError:
                raise ConfigError(path, f"must be a whole number, got {text!r}", key) from None
        elif key == "output_dir" or (key == "profile" and ("/" in text or text.lower().endswith(".toml"))):
            value = str(Path(text).expanduser().resolve())
        validate_value(path, key, value)  # raises naming the file and the key
        changes[key] = value
    data = dict(read_config_file(path)) if path.exists() else {}
    data.update(changes)
    text = "# mca appliance configuration (mca config set; see deploy/config.example.toml)\n"
    text += "".join(f"{key} = {toml_value(value)}\n" for key, value in data.items())
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, text.encode("utf-8"))
    return changes
