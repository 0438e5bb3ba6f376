"""`mca capture --filename PATTERN`: local file names from gphoto2-style patterns, always safe names.

A pattern names the file in the output folder; its fields are those of gphoto2's `--filename`:

- `%n` the shot's number in the catalog (unique in the folder, counting from 1; `%4n` or `%04n` pad it with
  zeros to 4 digits), `%f` the camera's file name without its suffix, `%C` the camera's suffix (no dot);
- `%Y %y %m %d %H %M %S %j %a %b` the date and time the file is stored (this computer's local time, as
  `strftime` writes them); `%%` a percent sign.

The result is made safe like every name a camera sends (`tether.sanitize_filename`): no folders, no `..`,
no control characters. A pattern with a `/`, an unknown field or nothing that varies from shot to shot is
refused before anything is taken (`FilenamePatternError`).
"""

from __future__ import annotations

import datetime
import re
from dataclasses import dataclass

_FIELD = re.compile(r"%(0?\d{0,2})([A-Za-z%])")
_DATE_FIELDS = "YymdHMSjab"
_SHOT_FIELDS = "nf"  # fields that differ between shots (a pattern needs one of them)


class FilenamePatternError(ValueError):
    """A `--filename` pattern that cannot be used; says which part and what is allowed."""


@dataclass(frozen=True)
class FilenamePattern:
    """A checked `--filename` pattern; `name_for` fills it in for one file."""

    text: str

    @classmethod
    def parse(cls, text: str) -> FilenamePattern:
        if not text or not text.strip():
            raise FilenamePatternError("--filename: the pattern is empty; e.g. 'bench-%04n.%C'")
        if "/" in text or "\\" in text:
            raise FilenamePatternError(
                f"--filename {text!r}: a file name, not a path (the folder is --out); e.g. 'bench-%04n.%C'"
            )
        seen = set()
        for match in _FIELD.finditer(text):
            width, code = match.groups()
            if code not in _DATE_FIELDS + "nfC%":
                raise FilenamePatternError(
                    f"--filename {text!r}: unknown field %{code}; use %n %f %C, %Y %y %m %d %H %M %S %j %a %b or %%"
                )
            if width and code != "n":
                raise FilenamePatternError(f"--filename {text!r}: only %n takes a width (%04n), not %{width}{code}")
            seen.add(code)
        stray = _FIELD.sub("", text)
        if "%" in stray:
            raise FilenamePatternError(f"--filename {text!r}: a lone '%'; write %% for a percent sign")
        if not seen & set(_SHOT_FIELDS):
            raise FilenamePatternError(
                f"--filename {text!r}: every shot would get the same name; put %n (shot number) or %f "
                "(the camera's name) in it"
            )
        return cls(text)

    def name_for(self, shot_number: int, camera_filename: str, when: datetime.datetime | None = None) -> str:
        """The name (not yet made safe) for the file `camera_filename` of shot `shot_number`, stored at `when`."""
        moment = when or datetime.datetime.now()
        base = camera_filename.replace("\\", "/").split("/")[-1]
        stem, dot, suffix = base.rpartition(".")
        if not dot:
            stem, suffix = base, ""

        def fill(match: re.Match[str]) -> str:
            width, code = match.groups()
            if code == "n":
                return str(shot_number).zfill(int(width) if width else 0)
            if code == "f":
                return stem
            if code == "C":
                return suffix
            if code == "%":
                return "%"
            return moment.strftime(f"%{code}")

        return _FIELD.sub(fill, self.text)
