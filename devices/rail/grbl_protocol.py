"""GRBL 1.1 serial protocol as pure functions: bytes in, messages out, commands out as bytes; no I/O.

The host driver (`devices.rail.grbl`) and the simulated controller
(`devices.sim.grbl`) share this codec from the two ends of the line.
Reference: GRBL 1.1 `doc/markdown/interface.md`, `doc/csv/error_codes_en_US.csv`
and `doc/csv/alarm_codes_en_US.csv` (gnea/grbl).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

BAUD_RATE = 115200
BANNER_PREFIX = "Grbl "
BANNER = "Grbl 1.1h ['$' for help]"

# Real-time commands: picked off the byte stream by the firmware, no newline needed.
STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
SOFT_RESET = b"\x18"
REALTIME_BYTES = frozenset(STATUS_QUERY + FEED_HOLD + CYCLE_START + SOFT_RESET)

LINE_BUFFER_BYTES = 80  # GRBL's LINE_BUFFER_SIZE: a longer line is answered with error:11
MAX_REPLY_LINE_BYTES = 256  # a reply line longer than this is not GRBL talking

ERROR_MESSAGES: dict[int, str] = {
    1: "G-code word without a letter",
    2: "missing or malformed numeric value",
    3: "'$' system command not recognised",
    4: "negative value where a positive one is expected",
    5: "homing is not enabled in the settings ($22)",
    6: "step pulse must be longer than 3 us",
    7: "EEPROM read failed, defaults restored",
    8: "'$' command only allowed while Idle",
    9: "G-code locked out during alarm or jog state",
    10: "soft limits need homing enabled",
    11: "line longer than the line buffer",
    12: "setting exceeds the maximum step rate",
    13: "safety door opened",
    14: "startup line too long for EEPROM",
    15: "jog target exceeds machine travel",
    16: "invalid jog command",
    17: "laser mode needs PWM output",
    20: "unsupported or invalid G-code command",
    21: "more than one command of one modal group",
    22: "feed rate not set",
    23: "command needs an integer value",
    24: "more than one command using axis words",
    25: "repeated G-code word",
    26: "no axis words for a command that needs them",
    27: "invalid line number",
    28: "command is missing a required value word",
    29: "G59.x work coordinate systems unsupported",
    30: "G53 only allowed with G0 and G1",
    31: "axis words found where no command uses them",
    32: "G2/G3 arc needs an in-plane axis word",
    33: "invalid motion target",
    34: "invalid arc radius",
    35: "G2/G3 arc needs an in-plane offset word",
    36: "unused value words in block",
    37: "G43.1 offset not on the tool length axis",
    38: "tool number above the maximum",
}

ALARM_MESSAGES: dict[int, str] = {
    1: "hard limit triggered; position likely lost, re-home",
    2: "soft limit: motion target exceeds machine travel; position retained",
    3: "reset while in motion; position likely lost, re-home",
    4: "probe fail: probe not in the expected initial state",
    5: "probe fail: probe did not contact within travel",
    6: "homing fail: homing cycle was reset",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: pull-off did not clear the limit switch",
    9: "homing fail: limit switch not found within the search distance",
}


class GrblProtocolError(ValueError):
    """The peer sent something GRBL 1.1 never sends (or a line that overflows the buffer)."""


@dataclass(frozen=True)
class Ok:
    """`ok`: the line was parsed and executed (or queued in the planner)."""


@dataclass(frozen=True)
class ErrorReply:
    """`error:N`: the line was rejected; nothing was executed."""

    code: int

    @property
    def message(self) -> str:
        return ERROR_MESSAGES.get(self.code, "unknown error code")


@dataclass(frozen=True)
class AlarmMessage:
    """`ALARM:N` push message: the controller is locked until `$H`, `$X` (and for 1 and 2 a reset)."""

    code: int

    @property
    def message(self) -> str:
        return ALARM_MESSAGES.get(self.code, "unknown alarm code")


@dataclass(frozen=True)
class Banner:
    """Startup line printed after power-up or soft reset, e.g. `Grbl 1.1h ['$' for help]`."""

    version: str


@dataclass(frozen=True)
class Feedback:
    """Bracketed push or help line, e.g. `[MSG:'$H'|'$X' to unlock]`."""

    text: str


@dataclass(frozen=True)
class SettingLine:
    """One line of a `$$` listing, e.g. `$130=300.000`."""

    number: int
    value: float


@dataclass(frozen=True)
class StartupEcho:
    """`>line:ok` echo of an executed startup block."""

    text: str


@dataclass(frozen=True)
class StatusReport:
    """`<State|MPos:x,y,z|FS:f,s|...>` real-time status report (GRBL 1.1 format)."""

    state: str  # Idle, Run, Hold, Jog, Alarm, Door, Check, Home, Sleep
    substate: int | None = None  # Hold:0 (stopping) / Hold:1 (stopped), Door:N
    mpos_mm: tuple[float, ...] | None = None
    wpos_mm: tuple[float, ...] | None = None
    wco_mm: tuple[float, ...] | None = None
    feed_mm_per_min: float | None = None
    fields: dict[str, str] = field(default_factory=dict, compare=False)


GrblMessage = Ok | ErrorReply | AlarmMessage | Banner | Feedback | SettingLine | StartupEcho | StatusReport

MACHINE_STATES = frozenset({"Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep"})
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_SETTING_RE = re.compile(rf"^\$(\d+)=({_NUMBER})$")
_CODE_RE = re.compile(r"^(error|ALARM):(\d+)$")


def _axes(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise GrblProtocolError(f"bad coordinates in status report: {text!r}") from None


def parse_status(line: str) -> StatusReport:
    """Parse a `<...>` status report line (without the line ending)."""
    if not (line.startswith("<") and line.endswith(">")):
        raise GrblProtocolError(f"status report not enclosed in <>: {line!r}")
    parts = line[1:-1].split("|")
    state, _, sub = parts[0].partition(":")
    if state not in MACHINE_STATES:
        raise GrblProtocolError(f"unknown machine state {state!r} in {line!r}")
    substate = int(sub) if sub.isdigit() else None
    fields: dict[str, str] = {}
    for part in parts[1:]:
        key, sep, value = part.partition(":")
        if not sep or not key:
            raise GrblProtocolError(f"bad field {part!r} in status report {line!r}")
        fields[key] = value
    feed = None
    if "FS" in fields:
        feed = _axes(fields["FS"])[0]
    elif "F" in fields:
        feed = _axes(fields["F"])[0]
    return StatusReport(
        state=state,
        substate=substate,
        mpos_mm=_axes(fields["MPos"]) if "MPos" in fields else None,
        wpos_mm=_axes(fields["WPos"]) if "WPos" in fields else None,
        wco_mm=_axes(fields["WCO"]) if "WCO" in fields else None,
        feed_mm_per_min=feed,
        fields=fields,
    )


def parse_line(line: str) -> GrblMessage:
    """Classify one line GRBL sent (line ending already stripped); raise GrblProtocolError on anything else."""
    if line == "ok":
        return Ok()
    match = _CODE_RE.match(line)
    if match:
        code = int(match.group(2))
        return ErrorReply(code) if match.group(1) == "error" else AlarmMessage(code)
    if line.startswith("<"):
        return parse_status(line)
    if line.startswith(BANNER_PREFIX) and "['$' for help]" in line:
        return Banner(version=line[len(BANNER_PREFIX) :].split(" ", 1)[0])
    if line.startswith("[") and line.endswith("]"):
        return Feedback(line[1:-1])
    match = _SETTING_RE.match(line)
    if match:
        return SettingLine(int(match.group(1)), float(match.group(2)))
    if line.startswith("$N") and "=" in line:
        return StartupEcho(line)
    if line.startswith(">") and line.endswith(":ok"):
        return StartupEcho(line[1:-3])
    raise GrblProtocolError(f"not a GRBL 1.1 message: {line[:60]!r}")


class LineSplitter:
    """Turns received bytes into complete text lines; bounded, ASCII only, CR/LF tolerant."""

    def __init__(self, max_line_bytes: int = MAX_REPLY_LINE_BYTES) -> None:
        self._buffer = bytearray()
        self._max = max_line_bytes

    def feed(self, data: bytes) -> list[str]:
        """Add received bytes; return the complete non-empty lines they finish."""
        self._buffer.extend(data)
        lines: list[str] = []
        while True:
            ends = [i for i in (self._buffer.find(b"\n"), self._buffer.find(b"\r")) if i >= 0]
            if not ends:
                break
            end = min(ends)
            raw = bytes(self._buffer[:end])
            del self._buffer[: end + 1]
            if raw:
                lines.append(self._decode(raw))
        if len(self._buffer) > self._max:
            junk = bytes(self._buffer[:32])
            self._buffer.clear()
            raise GrblProtocolError(f"no line ending within {self._max} bytes (starts {junk!r})")
        return lines

    @staticmethod
    def _decode(raw: bytes) -> str:
        if any(b > 0x7E or (b < 0x20 and b != 0x09) for b in raw):
            raise GrblProtocolError(f"non-ASCII bytes on the line: {raw[:32]!r}")
        return raw.decode("ascii").strip()

    def clear(self) -> None:
        self._buffer.clear()


def format_status(
    state: str,
    mpos_mm: tuple[float, float, float],
    feed_mm_per_min: float,
    substate: int | None = None,
    wco_mm: tuple[float, float, float] | None = None,
) -> str:
    """Build a GRBL 1.1 status report as sent with `$10=1`, e.g. `<Idle|MPos:10.000,0.000,0.000|FS:0,0>`."""
    name = state if substate is None else f"{state}:{substate}"
    text = f"<{name}|MPos:{','.join(f'{v:.3f}' for v in mpos_mm)}|FS:{feed_mm_per_min:.0f},0"
    if wco_mm is not None:
        text += f"|WCO:{','.join(f'{v:.3f}' for v in wco_mm)}"
    return text + ">"


def move_command(x_mm: float, feed_mm_per_min: float) -> bytes:
    """Absolute linear move of the X axis in machine coordinates (G53 so a work offset cannot shift it)."""
    if not feed_mm_per_min > 0:
        raise ValueError(f"feed must be positive, got {feed_mm_per_min} mm/min")
    return f"G90 G53 G1 X{x_mm:.3f} F{feed_mm_per_min:.0f}\n".encode("ascii")


@dataclass(frozen=True)
class GrblAxisSettings:
    """The `$$` settings that decide how the X axis maps onto the rail."""

    status_report_mask: int = 1  # $10; bit 0 set -> reports MPos
    soft_limits: bool = False  # $20
    homing_enabled: bool = False  # $22
    homing_dir_mask: int = 0  # $23; bit 0 set -> X homes toward negative
    homing_pulloff_mm: float = 1.0  # $27
    max_rate_mm_per_min: float = 500.0  # $110
    max_travel_mm: float = 200.0  # $130

    @classmethod
    def from_settings(cls, settings: dict[int, float]) -> GrblAxisSettings:
        default = cls()
        return cls(
            status_report_mask=int(settings.get(10, default.status_report_mask)),
            soft_limits=bool(int(settings.get(20, 0))),
            homing_enabled=bool(int(settings.get(22, 0))),
            homing_dir_mask=int(settings.get(23, 0)),
            homing_pulloff_mm=settings.get(27, default.homing_pulloff_mm),
            max_rate_mm_per_min=settings.get(110, default.max_rate_mm_per_min),
            max_travel_mm=settings.get(130, default.max_travel_mm),
        )

    @property
    def homes_toward_negative(self) -> bool:
        return bool(self.homing_dir_mask & 1)


# GRBL's machine space is [-$130, 0] (limits.c, system_check_travel_limits). The rail
# coordinate is the distance from the home switch, positive away from it: [0, $130].
def machine_x_mm(rail_mm: float, axis: GrblAxisSettings) -> float:
    """Machine X (MPos) for a rail position measured from the home switch."""
    return rail_mm - axis.max_travel_mm if axis.homes_toward_negative else -rail_mm


def rail_mm(machine_x: float, axis: GrblAxisSettings) -> float:
    """Rail position measured from the home switch for a machine X (MPos)."""
    return machine_x + axis.max_travel_mm if axis.homes_toward_negative else -machine_x
