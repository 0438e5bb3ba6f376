"""Camera profiles on disk: the built-in TOML files beside this module and user files, loaded and validated."""

from __future__ import annotations

import tomllib
from pathlib import Path

from mca.processing.camera import CameraProfile, ProfileError, profile_from_mapping

BUILTIN_DIR = Path(__file__).resolve().parent
DEFAULT_PROFILE = "paper-70d"


def builtin_names() -> list[str]:
    """Names of the profiles shipped with the appliance."""
    return sorted(p.stem for p in BUILTIN_DIR.glob("*.toml"))


def load_profile_file(path: str | Path) -> CameraProfile:
    """Read and validate a profile TOML file; a `ProfileError` names the file and the field."""
    path = Path(path)
    source = str(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ProfileError(
            "<file>", "no such file; give a built-in name (mca profile list) or a path", source
        ) from None
    except IsADirectoryError:
        raise ProfileError("<file>", "is a directory, not a profile TOML file", source) from None
    except UnicodeDecodeError as exc:
        raise ProfileError("<file>", f"is not UTF-8 text ({exc.reason} at byte {exc.start})", source) from None
    except OSError as exc:
        raise ProfileError("<file>", f"cannot be read: {exc.strerror}", source) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError("<file>", f"is not valid TOML: {exc}", source) from None
    return profile_from_mapping(data, source)


def load_profile(name_or_path: str | Path) -> CameraProfile:
    """A built-in profile by name, or a profile file by path."""
    text = str(name_or_path)
    if text in builtin_names():
        return load_profile_file(BUILTIN_DIR / f"{text}.toml")
    path = Path(text)
    if path.suffix.lower() != ".toml" and not path.exists():
        raise ProfileError(
            "<name>", f"'{text}' is neither a built-in profile ({', '.join(builtin_names())}) nor a TOML file", text
        )
    return load_profile_file(path)


__all__ = ["DEFAULT_PROFILE", "ProfileError", "builtin_names", "load_profile", "load_profile_file"]
