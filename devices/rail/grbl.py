"""A GRBL 1.1 linear stage over a serial port (pyserial): the real-device side of the `Rail` interface."""

from __future__ import annotations

import collections
import time
from collections.abc import Callable

from mca.devices.rail import grbl_protocol as gp
from mca.devices.rail.base import (
    Rail,
    RailAlarm,
    RailCommandError,
    RailDisconnected,
    RailProtocolError,
    RailStatus,
    RailTimeout,
)

_PORT_HINT = "Check the USB cable and the controller's power, then reconnect (`Rail.reconnect()`)"
_SILENT_HINT = (
    "Check that the controller is powered, runs GRBL 1.1 at 115200 baud, and that no other "
    "program (a G-code sender) holds the port"
)
_GARBAGE_HINT = "Check the baud rate (GRBL uses 115200) and that this port is the GRBL controller, then reconnect"
_ERROR_HINTS: dict[int, str] = {
    5: "Enable homing with `$22=1` (see docs/rail.md) or unlock with `$X` and position by hand",
    8: "Wait until the rail is idle, then retry",
    9: (
        "The controller is locked (alarm state after a reset or power-up): home it first "
        "(`mca rail home`, `mca rail move --home`, Rail.home())"
    ),
    15: "Choose a target inside the travel ($130)",
    22: "Give a feed rate (`--feed`)",
}
_ALARM_HINT = (
    "Run `mca rail home` (Rail.home()); for a soft-limit alarm (2) `Rail.unlock()` keeps the "
    "position. Then resume the sweep"
)


# Half the 0.001 mm resolution of the G-code sent: a target this close beyond an end counts as that end.
TRAVEL_EDGE_TOLERANCE_MM = 0.0005


class GrblRail(Rail):
    """A GRBL 1.1 controller driving one axis (X) of a bench rail.

    `port` is anything `serial.serial_for_url` opens: `/dev/ttyUSB0`, a pty from
    `devices.sim.grbl`, or `loop://`. Positions are mm from the home switch,
    mapped onto GRBL's machine coordinates with the controller's own `$$`
    settings (`$130` travel, `$23` homing direction).
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = gp.BAUD_RATE,
        answer_timeout_s: float = 2.0,
        connect_timeout_s: float = 4.0,
        poll_interval_s: float = 0.2,
        default_feed_mm_per_min: float = 600.0,
        position_tolerance_mm: float = 0.005,
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.port = port
        self.baudrate = baudrate
        self.answer_timeout_s = answer_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self.poll_interval_s = poll_interval_s
        self.default_feed_mm_per_min = default_feed_mm_per_min
        self.position_tolerance_mm = position_tolerance_mm
        self._on_close = on_close
        self._serial = None
        self._splitter = gp.LineSplitter()
        self._pending: collections.deque[gp.GrblMessage] = collections.deque()
        self.axis = gp.GrblAxisSettings()
        self.banner: str | None = None
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    # -- Rail interface -------------------------------------------------------------------
    @property
    def travel_mm(self) -> float:
        return self.axis.max_travel_mm

    def home(self, timeout_s: float | None = None) -> RailStatus:
        if timeout_s is None:
            seek_s = 60.0 * self.axis.max_travel_mm / max(self.axis.max_rate_mm_per_min, 1.0)
            timeout_s = max(60.0, 3.0 * seek_s)
        if self.status().state == "Alarm":
            self._soft_reset()  # after a limit alarm GRBL takes no line until reset; nothing moves
        self._command("$H", timeout_s)
        return self.wait_until_idle(timeout_s=self.answer_timeout_s * 2)

    def start_move(self, position_mm: float, feed_mm_per_min: float | None = None) -> None:
        feed = self.default_feed_mm_per_min if feed_mm_per_min is None else feed_mm_per_min
        if not feed > 0:
            raise RailCommandError(self.port, f"feed {feed} mm/min is not positive", _ERROR_HINTS[22])
        if -TRAVEL_EDGE_TOLERANCE_MM <= position_mm < 0.0:
            position_mm = 0.0  # a rounding error at the home end (e.g. -1e-9 from a sweep's arithmetic)
        elif self.travel_mm < position_mm <= self.travel_mm + TRAVEL_EDGE_TOLERANCE_MM:
            position_mm = self.travel_mm  # 300.0000001 on a 300 mm rail is the end of the rail
        if not 0.0 <= position_mm <= self.travel_mm:
            raise RailCommandError(
                self.port,
                f"target {position_mm:.3f} mm is outside the travel 0..{self.travel_mm:.3f} mm",
                _ERROR_HINTS[15],
            )
        target_x = gp.machine_x_mm(position_mm, self.axis)
        self._command(gp.move_command(target_x, feed).decode("ascii").strip(), self.answer_timeout_s)

    def move_to(
        self, position_mm: float, feed_mm_per_min: float | None = None, timeout_s: float | None = None
    ) -> RailStatus:
        if timeout_s is None:
            feed = min(feed_mm_per_min or self.default_feed_mm_per_min, self.axis.max_rate_mm_per_min)
            timeout_s = 10.0 + 2.0 * 60.0 * self.travel_mm / max(feed, 1e-3)
        self.start_move(position_mm, feed_mm_per_min)
        return self.wait_until_idle(target_mm=position_mm, timeout_s=timeout_s)

    def wait_until_idle(self, target_mm: float | None = None, timeout_s: float = 60.0) -> RailStatus:
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.status()
            if status.state == "Alarm":
                raise RailAlarm(self.port, f"controller in alarm at {status.position_mm:.3f} mm", _ALARM_HINT, None)
            at_target = target_mm is None or abs(status.position_mm - target_mm) <= self.position_tolerance_mm
            if status.idle and at_target:
                return status
            if time.monotonic() >= deadline:
                where = "" if target_mm is None else f" on the way to {target_mm:.3f} mm"
                raise RailTimeout(
                    self.port,
                    f"still {status.state} at {status.position_mm:.3f} mm after {timeout_s:.1f} s{where}",
                    "Check for a feed hold or a stalled carriage; resume with `~` or home and retry",
                )
            time.sleep(self.poll_interval_s)

    def status(self) -> RailStatus:
        report = self._query_status(self.answer_timeout_s)
        return self._rail_status(report)

    def unlock(self) -> RailStatus:
        self._soft_reset()
        self._command("$X", self.answer_timeout_s)
        return self.status()

    def halt(self) -> None:
        self._write(gp.FEED_HOLD)

    def resume(self) -> None:
        """Cycle start (`~`): continue a motion stopped by `halt()`."""
        self._write(gp.CYCLE_START)

    def reconnect(self) -> RailStatus:
        self._close_port()
        self._connect()
        return self.status()

    def close(self) -> None:
        self._close_port()
        on_close, self._on_close = self._on_close, None
        if on_close is not None:
            on_close()

    # -- connection -----------------------------------------------------------------------
    def _connect(self) -> None:
        import serial

        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=0.02, write_timeout=self.answer_timeout_s
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise RailDisconnected(
                self.port,
                f"cannot open the port ({exc})",
                "Check that the controller is plugged in and the path is right "
                "(`ls /dev/ttyUSB* /dev/ttyACM*`), and that you may use it (group dialout)",
            ) from exc
        self._splitter.clear()
        self._pending.clear()
        # An Arduino resets when the port opens and needs ~1-2 s before it answers;
        # poll `?` until a status report arrives.
        report = self._query_status(self.connect_timeout_s, repeat_s=0.25, first_contact=True)
        if report.state == "Alarm":
            # A limit alarm blocks every line until reset; a reset in Alarm moves nothing.
            self._soft_reset()
        self.axis = gp.GrblAxisSettings.from_settings(self._read_settings())
        if not self.axis.status_report_mask & 1:
            raise RailCommandError(
                self.port,
                "the controller reports work positions ($10 bit 0 is 0)",
                "Set `$10=1` so status reports carry the machine position (docs/rail.md)",
            )

    def _close_port(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            try:
                port.close()
            except Exception:
                pass

    def _read_settings(self) -> dict[int, float]:
        settings: dict[int, float] = {}
        for message in self._command("$$", self.answer_timeout_s):
            if isinstance(message, gp.SettingLine):
                settings[message.number] = message.value
        return settings

    def _soft_reset(self) -> None:
        self._write(gp.SOFT_RESET)
        deadline = time.monotonic() + self.connect_timeout_s
        while True:
            message = self._next_message(deadline, "the banner after a soft reset (ctrl-x)")
            if isinstance(message, gp.Banner):
                self.banner = message.version
                return

    # -- line traffic ---------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        import serial

        if self._serial is None:
            raise RailDisconnected(self.port, "the port is closed", "Call `Rail.reconnect()`")
        try:
            self._serial.write(data)
            self._serial.flush()
        except serial.SerialTimeoutException as exc:
            raise RailTimeout(self.port, "the controller does not take bytes (write timed out)", _SILENT_HINT) from exc
        except (serial.SerialException, OSError) as exc:
            self._close_port()
            raise RailDisconnected(self.port, f"the port vanished while writing ({exc})", _PORT_HINT) from exc

    def _next_message(self, deadline: float, waiting_for: str) -> gp.GrblMessage:
        import serial

        while not self._pending:
            if self._serial is None:
                raise RailDisconnected(self.port, "the port is closed", "Call `Rail.reconnect()`")
            try:
                data = self._serial.read(max(1, self._serial.in_waiting))
            except (serial.SerialException, OSError) as exc:
                self._close_port()
                raise RailDisconnected(
                    self.port, f"the port vanished while waiting for {waiting_for} ({exc})", _PORT_HINT
                ) from exc
            if data:
                try:
                    for line in self._splitter.feed(data):
                        self._pending.append(gp.parse_line(line))
                except gp.GrblProtocolError as exc:
                    self._splitter.clear()
                    self._pending.clear()
                    raise RailProtocolError(
                        self.port, f"garbage on the line while waiting for {waiting_for}: {exc}", _GARBAGE_HINT
                    ) from exc
            elif time.monotonic() >= deadline:
                raise RailTimeout(self.port, f"no answer while waiting for {waiting_for}", _SILENT_HINT)
        return self._pending.popleft()

    def _command(self, line: str, timeout_s: float) -> list[gp.GrblMessage]:
        """Send one line; return the messages before its `ok`; raise on `error:N` or `ALARM:N`."""
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + timeout_s
        collected: list[gp.GrblMessage] = []
        while True:
            message = self._next_message(deadline, f"the answer to {line!r}")
            if isinstance(message, gp.Ok):
                return collected
            if isinstance(message, gp.ErrorReply):
                raise RailCommandError(
                    self.port,
                    f"{line!r} rejected with error:{message.code} ({message.message})",
                    _ERROR_HINTS.get(message.code, "See docs/rail.md for the GRBL settings expected"),
                    message.code,
                )
            self._raise_on_alarm(message, line)
            collected.append(message)

    def _query_status(
        self, timeout_s: float, repeat_s: float | None = None, first_contact: bool = False
    ) -> gp.StatusReport:
        # A report still queued from an earlier, repeated `?` would be stale.
        self._pending = collections.deque(m for m in self._pending if not isinstance(m, gp.StatusReport))
        self._write(gp.STATUS_QUERY)
        start = time.monotonic()
        deadline = start + timeout_s
        last_ask = start
        while True:
            step_deadline = min(deadline, last_ask + repeat_s) if repeat_s else deadline
            try:
                message = self._next_message(step_deadline, "a status report ('?')")
            except RailTimeout:
                if time.monotonic() >= deadline:
                    if first_contact:
                        raise RailTimeout(
                            self.port, f"no answer from a GRBL controller within {timeout_s:.1f} s", _SILENT_HINT
                        ) from None
                    raise
                self._write(gp.STATUS_QUERY)
                last_ask = time.monotonic()
                continue
            if isinstance(message, gp.StatusReport):
                return message
            if isinstance(message, gp.Banner):
                self.banner = message.version
            elif not first_contact:
                self._raise_on_alarm(message, "?")

    def _raise_on_alarm(self, message: gp.GrblMessage, during: str) -> None:
        if isinstance(message, gp.AlarmMessage):
            raise RailAlarm(
                self.port, f"ALARM:{message.code} ({message.message}) during {during!r}", _ALARM_HINT, message.code
            )

    def _rail_status(self, report: gp.StatusReport) -> RailStatus:
        if report.mpos_mm is None:
            raise RailCommandError(
                self.port, "status report carries no machine position (MPos)", "Set `$10=1` (docs/rail.md)"
            )
        machine_x = report.mpos_mm[0]
        return RailStatus(
            state=report.state,
            position_mm=gp.rail_mm(machine_x, self.axis) + 0.0,
            machine_x_mm=machine_x,
            feed_mm_per_min=report.feed_mm_per_min or 0.0,
        )
