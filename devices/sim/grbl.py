"""A simulated GRBL 1.1h controller for one rail axis, and a runner serving it on a real pseudo-terminal.

`SimGrbl` is the firmware as a state machine (bytes in, bytes out, motion
driven by a clock) so tests can step it with a fake clock; `SimGrblPty` runs
it in a thread behind a pty, so pyserial opens a real tty exactly as it opens
`/dev/ttyUSB0`. Replies follow GRBL 1.1: `ok`, `error:N`, `ALARM:N`,
`<Idle|MPos:...|FS:...>`, the banner `Grbl 1.1h ['$' for help]`.
"""

from __future__ import annotations

import collections
import os
import re
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mca.devices.rail import grbl_protocol as gp

# A configured bench rail: homing on, soft limits on, 300 mm of travel.
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10,
    1: 25,
    2: 0,
    3: 0,
    4: 0,
    5: 0,
    6: 0,
    10: 1,
    11: 0.010,
    12: 0.002,
    13: 0,
    20: 1,
    21: 0,
    22: 1,
    23: 0,
    24: 25.0,
    25: 500.0,
    26: 250,
    27: 1.0,
    30: 1000,
    31: 0,
    32: 0,
    100: 80.0,
    101: 250.0,
    102: 250.0,
    110: 3000.0,
    111: 500.0,
    112: 500.0,
    120: 100.0,
    121: 10.0,
    122: 10.0,
    130: 300.0,
    131: 200.0,
    132: 200.0,
}
PLANNER_BLOCKS = 15  # GRBL 1.1 on an ATmega328p
_WORD_RE = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))?")


@dataclass
class _Segment:
    target_x_mm: float
    feed_mm_per_min: float
    jog: bool = False


class SimGrbl:
    """GRBL 1.1h firmware for the X axis: feed it received bytes, send back what it returns.

    Motion runs at the commanded feed (no acceleration) on `clock`, sped up by
    `speedup`. `carriage_from_switch_mm` is where the carriage physically stands
    at power-up; homing travels that far at the seek rate `$25`.
    """

    # the controller's state, set by _reset_state (power-up, soft reset)
    state: str
    _critical: bool
    _rx: bytearray
    _rx_overflow: bool
    _lines: collections.deque[bytes | None]
    _queue: collections.deque[_Segment]
    _moving_from: tuple[float, float] | None  # (start x, sim time) of the head segment
    _homing_done_at: float
    _waiting_sync: bool
    _absolute: bool
    _feed_mm_per_min: float | None
    _modal_motion: int
    _reports: int

    def __init__(
        self,
        settings: dict[int, float] | None = None,
        *,
        speedup: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        carriage_from_switch_mm: float = 50.0,
    ) -> None:
        if not speedup > 0:
            raise ValueError(f"speedup must be positive, got {speedup}")
        self.settings = dict(DEFAULT_SETTINGS if settings is None else settings)
        self.speedup = speedup
        self._clock = clock
        self._carriage_from_switch_mm = carriage_from_switch_mm
        self.machine_x_mm = 0.0
        self.power_up_count = 0
        self._reset_state()

    # -- public surface ---------------------------------------------------------------
    def power_up(self) -> bytes:
        """Cold start: the position counter is zero, and with homing on the controller is locked."""
        self.power_up_count += 1
        self.machine_x_mm = 0.0
        self._reset_state()
        self.state = "Alarm" if self.settings.get(22) else "Idle"
        return self._startup_text()

    def receive(self, data: bytes) -> bytes:
        """Process received bytes; real-time commands act at once, other bytes build lines."""
        out = bytearray(self.tick())
        for byte in data:
            if byte in gp.REALTIME_BYTES:
                out += self._realtime(bytes([byte]))
            elif byte in (0x0A, 0x0D):
                line, self._rx = bytes(self._rx), bytearray()
                if self._rx_overflow:
                    self._rx_overflow = False
                    self._lines.append(None)
                elif line.strip():
                    self._lines.append(line)
            else:
                if len(self._rx) >= gp.LINE_BUFFER_BYTES - 1:
                    self._rx_overflow = True
                else:
                    self._rx.append(byte)
        out += self.tick()
        return bytes(out)

    def tick(self) -> bytes:
        """Advance motion to now; finish homing or dwells; run lines that were waiting."""
        out = bytearray()
        now = self._sim_now()
        self._advance(now)
        if self.state == "Home" and now >= self._homing_done_at:
            self.machine_x_mm = self._home_machine_x()
            self.state = "Idle"
            out += b"ok\r\n"
        while self._lines and not self._busy(now):
            line = self._lines.popleft()
            out += self._execute(line)
            self._advance(self._sim_now())
        if self._waiting_sync and not self._queue and self.state not in ("Run", "Hold", "Jog"):
            self._waiting_sync = False
            out += b"ok\r\n"
        return bytes(out)

    def trigger_alarm(self, code: int) -> bytes:
        """A fault from outside the serial line, e.g. a hard limit switch (1): stops and locks."""
        self._advance(self._sim_now())
        self._queue.clear()
        self._moving_from = None
        self.state = "Alarm"
        self._critical = code in (1, 2)
        text = f"ALARM:{code}\r\n"
        if self._critical:
            text += "[MSG:Reset to continue]\r\n"
        return text.encode("ascii")

    @property
    def position_mm(self) -> float:
        """Machine X now (mm), as the next status report would give it."""
        self._advance(self._sim_now())
        return self.machine_x_mm

    # -- internals --------------------------------------------------------------------
    def _reset_state(self) -> None:
        self.state = "Idle"
        self._critical = False
        self._rx = bytearray()
        self._rx_overflow = False
        self._lines = collections.deque()
        self._queue = collections.deque()
        self._moving_from = None
        self._homing_done_at = 0.0
        self._waiting_sync = False
        self._absolute = True
        self._feed_mm_per_min: float | None = None
        self._modal_motion = 0
        self._reports = 0

    def _sim_now(self) -> float:
        return self._clock() * self.speedup

    def _startup_text(self) -> bytes:
        text = "\r\n" + gp.BANNER + "\r\n"
        if self.state == "Alarm":
            text += "[MSG:'$H'|'$X' to unlock]\r\n"
        return text.encode("ascii")

    def _busy(self, now: float) -> bool:
        return self._critical or self.state == "Home" or self._waiting_sync or len(self._queue) >= PLANNER_BLOCKS

    def _home_machine_x(self) -> float:
        pulloff = self.settings.get(27, 1.0)
        travel = self.settings.get(130, 200.0)
        # limits.c: machine space is all negative; the switch end is 0 or -max travel.
        return -travel + pulloff if int(self.settings.get(23, 0)) & 1 else -pulloff

    def _advance(self, now: float) -> None:
        """Move the carriage along the queued segments up to sim time `now`."""
        while self._queue and self.state in ("Run", "Jog"):
            segment = self._queue[0]
            if self._moving_from is None:
                self._moving_from = (self.machine_x_mm, now)
            start_x, start_t = self._moving_from
            rate = min(segment.feed_mm_per_min, self.settings.get(110, 500.0)) / 60.0
            distance = segment.target_x_mm - start_x
            duration = abs(distance) / rate
            if now - start_t >= duration:
                self.machine_x_mm = segment.target_x_mm
                self._queue.popleft()
                self._moving_from = (self.machine_x_mm, start_t + duration) if self._queue else None
                continue
            fraction = (now - start_t) / duration if duration > 0 else 1.0
            self.machine_x_mm = start_x + distance * fraction
            return
        if self.state in ("Run", "Jog") and not self._queue:
            self.state = "Idle"
            self._moving_from = None

    def _current_feed(self) -> float:
        if self.state in ("Run", "Jog") and self._queue:
            return min(self._queue[0].feed_mm_per_min, self.settings.get(110, 500.0))
        if self.state == "Home":
            return self.settings.get(25, 500.0)
        return 0.0

    def _status_line(self) -> bytes:
        self._advance(self._sim_now())
        x = self.machine_x_mm
        if self.state == "Home":
            remaining = max(0.0, self._homing_done_at - self._sim_now())
            x = self._home_machine_x() - remaining * self.settings.get(25, 500.0) / 60.0
        substate = 1 if self.state == "Hold" else None
        self._reports += 1
        wco = (0.0, 0.0, 0.0) if self._reports % 10 == 1 else None
        line = gp.format_status(self.state, (x, 0.0, 0.0), self._current_feed(), substate, wco)
        return (line + "\r\n").encode("ascii")

    def _realtime(self, byte: bytes) -> bytes:
        if byte == gp.STATUS_QUERY:
            return self._status_line()
        if byte == gp.FEED_HOLD:
            if self.state in ("Run", "Jog"):
                self._advance(self._sim_now())
                self._moving_from = None
                self.state = "Hold"
            return b""
        if byte == gp.CYCLE_START:
            if self.state == "Hold":
                self._moving_from = None
                self.state = "Run"
            return b""
        # ctrl-x: soft reset. Motion is killed; position kept unless it was moving.
        self._advance(self._sim_now())
        out = b""
        if self.state in ("Run", "Hold", "Jog"):
            out += b"ALARM:3\r\n"
            self.state = "Alarm"
        elif self.state == "Home":
            out += b"ALARM:6\r\n"
            self.state = "Alarm"
        prior = self.state
        self._reset_state()
        self.state = prior
        return out + self._startup_text()

    def _execute(self, line: bytes | None) -> bytes:
        if line is None:
            return self._error(11)
        text = re.sub(r"\([^)]*\)|;.*$", "", line.decode("ascii", "replace")).replace(" ", "").upper()
        if not text:
            return b"ok\r\n"
        if text.startswith("$"):
            return self._system_command(text)
        if self.state == "Alarm":
            return self._error(9)
        return self._gcode(text, jog=False)

    def _error(self, code: int) -> bytes:
        return f"error:{code}\r\n".encode("ascii")

    def _system_command(self, text: str) -> bytes:
        moving = self.state in ("Run", "Hold", "Jog", "Home")
        if text == "$":
            return b"[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\nok\r\n"
        if text == "$$":
            if moving:
                return self._error(8)
            body = "".join(f"${n}={self._format_setting(v)}\r\n" for n, v in sorted(self.settings.items()))
            return (body + "ok\r\n").encode("ascii")
        if text == "$I":
            return b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"
        if text == "$X":
            if moving:
                return self._error(8)
            if self.state == "Alarm":
                self.state = "Idle"
                return b"[MSG:Caution: Unlocked]\r\nok\r\n"
            return b"ok\r\n"
        if text == "$H":
            if not self.settings.get(22):
                return self._error(5)
            if moving:
                return self._error(8)
            distance = self._carriage_from_switch_mm + self.settings.get(27, 1.0)
            seek_s = distance / (self.settings.get(25, 500.0) / 60.0)
            locate_s = 2 * self.settings.get(27, 1.0) / (self.settings.get(24, 25.0) / 60.0)
            self._carriage_from_switch_mm = self.settings.get(27, 1.0)
            self._homing_done_at = self._sim_now() + seek_s + locate_s
            self.state = "Home"
            return b""  # `ok` once the cycle completes
        if text.startswith("$J="):
            if self.state in ("Alarm", "Run", "Hold", "Home"):
                return self._error(9 if self.state == "Alarm" else 8)
            return self._gcode(text[3:], jog=True)
        match = re.fullmatch(r"\$(\d+)=(.*)", text)
        if match:
            number, raw = int(match.group(1)), match.group(2)
            if moving:
                return self._error(8)
            if number not in self.settings:
                return self._error(3)
            try:
                value = float(raw)
            except ValueError:
                return self._error(2)
            if value < 0:
                return self._error(4)
            if number == 20 and value and not self.settings.get(22):
                return self._error(10)
            self.settings[number] = value
            return b"ok\r\n"
        return self._error(3)

    @staticmethod
    def _format_setting(value: float) -> str:
        return str(int(value)) if float(value).is_integer() and abs(value) < 1e6 else f"{value:.3f}"

    def _gcode(self, text: str, jog: bool) -> bytes:
        words: list[tuple[str, float]] = []
        position = 0
        for match in _WORD_RE.finditer(text):
            if match.start() != position:
                return self._error(1)
            if match.group(2) is None:
                return self._error(2)
            words.append((match.group(1), float(match.group(2))))
            position = match.end()
        if position != len(text):
            return self._error(1)
        absolute, motion, machine_coords, dwell = self._absolute, None, False, False
        x = feed = dwell_s = None
        seen: set[str] = set()
        for letter, value in words:
            if letter != "G" and letter in seen:
                return self._error(25)
            seen.add(letter)
            if letter == "G":
                if value in (90, 91):
                    absolute = value == 90
                elif value in (0, 1):
                    motion = int(value)
                elif value == 53:
                    machine_coords = True
                elif value == 4:
                    dwell = True
                elif value in (17, 21, 54, 94):
                    pass
                else:
                    return self._error(20)
            elif letter == "X":
                x = value
            elif letter in ("Y", "Z"):
                if value != 0:
                    return self._error(33)  # this rail has one axis
            elif letter == "F":
                if value <= 0:
                    return self._error(4)
                feed = value
            elif letter == "P":
                dwell_s = value
            elif letter == "N":
                pass
            else:
                return self._error(20)
        if jog and (motion is not None or dwell):
            return self._error(16)
        if jog and feed is None:
            return self._error(22)
        if dwell:
            if dwell_s is None:
                return self._error(28)
            self._waiting_sync = True  # `ok` when the planner has drained
            return b""
        if not jog:
            self._absolute = absolute
            if feed is not None:
                self._feed_mm_per_min = feed
            if motion is not None:
                self._modal_motion = motion
        if x is None:
            return b"ok\r\n"
        end_of_queue = self._queue[-1].target_x_mm if self._queue else self.machine_x_mm
        target = x if (absolute or machine_coords) else end_of_queue + x
        rate = feed if jog else (self.settings.get(110, 500.0) if self._modal_motion == 0 else self._feed_mm_per_min)
        if rate is None:
            return self._error(22)
        if self.settings.get(20) and not -self.settings.get(130, 200.0) <= target <= 0.0:
            if jog:
                return self._error(15)
            return self.trigger_alarm(2)  # limits_soft_check: no `ok`, reset needed
        self._queue.append(_Segment(target, rate, jog))
        if self.state == "Idle":
            self.state = "Jog" if jog else "Run"
            self._moving_from = None
        return b"ok\r\n"


class SimGrblPty:
    """Serves a `SimGrbl` on a pseudo-terminal from a thread; `port` is the tty path for pyserial.

    `link_path` (optional) is kept pointing at the current pty, like a udev
    `/dev/serial/by-id/...` link, so `unplug()`/`replug()` keep one port name.
    """

    def __init__(
        self, sim: SimGrbl | None = None, *, speedup: float = 1.0, link_path: str | Path | None = None
    ) -> None:
        self.sim = sim if sim is not None else SimGrbl(speedup=speedup)
        self._link = Path(link_path) if link_path is not None else None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self._tty_name = ""
        self.muted = False

    @property
    def port(self) -> str:
        return str(self._link) if self._link is not None else self._tty_name

    def _master_fd(self) -> int:
        if self._master is None:
            raise OSError(f"the simulated GRBL pty {self.port or '(not started)'} is not open: call start() first")
        return self._master

    def start(self) -> SimGrblPty:
        """Open a pty, power the controller up (banner) and serve it."""
        master, slave = os.openpty()
        self._master, self._slave = master, slave
        tty.setraw(slave)
        self._tty_name = os.ttyname(slave)
        if self._link is not None:
            if self._link.is_symlink() or self._link.exists():
                self._link.unlink()
            self._link.symlink_to(self._tty_name)
        with self._lock:
            os.write(master, self.sim.power_up())
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f"sim-grbl {self._tty_name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pty: to the host the port has vanished."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    unplug = stop

    def replug(self) -> SimGrblPty:
        """Plug back in: a fresh pty (same `link_path`) and a controller that has just powered up."""
        self.stop()
        self.muted = False
        return self.start()

    def inject(self, data: bytes) -> None:
        """Put raw bytes on the line toward the host (noise, a wrong-baud device)."""
        with self._lock:
            os.write(self._master_fd(), data)

    def mute(self, muted: bool = True) -> None:
        """Stop answering (hung firmware) while keeping the port open."""
        self.muted = muted

    def trigger_alarm(self, code: int) -> None:
        with self._lock:
            os.write(self._master_fd(), self.sim.trigger_alarm(code))

    def __enter__(self) -> SimGrblPty:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
        if self._link is not None and self._link.is_symlink():
            self._link.unlink()

    def _serve(self) -> None:
        master = self._master_fd()
        while not self._stop.is_set():
            try:
                readable, _, _ = select.select([master], [], [], 0.005)
            except (OSError, ValueError):
                return
            data = b""
            if readable:
                try:
                    data = os.read(master, 4096)
                except OSError:
                    time.sleep(0.005)  # no host has the tty open right now
                    continue
            with self._lock:
                if self.muted:
                    continue
                out = self.sim.receive(data) if data else self.sim.tick()
                if out:
                    try:
                        os.write(master, out)
                    except OSError:
                        return
