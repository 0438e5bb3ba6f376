"""The bench rail interface: what a calibration sweep may ask of any linear stage, and the errors it raises."""

from __future__ import annotations

import abc
from dataclasses import dataclass
from types import TracebackType


@dataclass(frozen=True)
class RailStatus:
    """One status reading of the rail."""

    state: str  # controller state: Idle, Run, Hold, Home, Alarm, Jog, Door, ...
    position_mm: float  # along the rail, measured from the home switch
    machine_x_mm: float  # the controller's own coordinate (GRBL MPos X)
    feed_mm_per_min: float

    @property
    def idle(self) -> bool:
        return self.state == "Idle"


class RailError(Exception):
    """A rail fault a user can act on: names the port, what happened and what to do next."""

    def __init__(self, port: str, problem: str, hint: str) -> None:
        self.port = port
        self.problem = problem
        self.hint = hint
        super().__init__(f"rail at {port}: {problem}. {hint}")


class RailDisconnected(RailError):
    """The serial port could not be opened or vanished (cable pulled, controller powered off)."""


class RailTimeout(RailError):
    """The controller did not answer, or did not finish a motion, in time."""


class RailProtocolError(RailError):
    """Bytes on the line that are not GRBL 1.1 (wrong baud rate, wrong device, electrical noise)."""


class RailAlarm(RailError):
    """The controller raised `ALARM:N` or is locked in its alarm state."""

    def __init__(self, port: str, problem: str, hint: str, alarm_code: int | None) -> None:
        self.alarm_code = alarm_code
        super().__init__(port, problem, hint)


class RailCommandError(RailError):
    """The controller rejected a command with `error:N`, or the command was refused before sending."""

    def __init__(self, port: str, problem: str, hint: str, error_code: int | None = None) -> None:
        self.error_code = error_code
        super().__init__(port, problem, hint)


class Rail(abc.ABC):
    """A single-axis linear stage positioned in mm from its home switch.

    A calibration sweep needs only: `home()`, `move_to(mm)` (returns once the
    stage is idle at the target, with the position read back), `status()`,
    and after a fault `reconnect()` then `home()` before resuming.
    """

    port: str

    @property
    @abc.abstractmethod
    def travel_mm(self) -> float:
        """Usable travel: positions from 0 to this many mm from the home switch."""

    @abc.abstractmethod
    def home(self, timeout_s: float | None = None) -> RailStatus:
        """Run the homing cycle; return once idle at the switch (clears the power-up alarm lock)."""

    @abc.abstractmethod
    def start_move(self, position_mm: float, feed_mm_per_min: float | None = None) -> None:
        """Queue an absolute move and return once the controller accepted it (does not wait)."""

    @abc.abstractmethod
    def wait_until_idle(self, target_mm: float | None = None, timeout_s: float = 60.0) -> RailStatus:
        """Poll status until Idle (and at `target_mm`, when given); raise RailTimeout/RailAlarm otherwise."""

    @abc.abstractmethod
    def status(self) -> RailStatus:
        """Read the state and the position right now."""

    @abc.abstractmethod
    def unlock(self) -> RailStatus:
        """Leave an alarm without homing (position kept as the controller believes it)."""

    @abc.abstractmethod
    def halt(self) -> None:
        """Feed hold: decelerate to a stop, keeping the position."""

    @abc.abstractmethod
    def reconnect(self) -> RailStatus:
        """Close and reopen the port (after a RailDisconnected or RailTimeout); home again before moving."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the port (idempotent)."""

    def move_to(
        self, position_mm: float, feed_mm_per_min: float | None = None, timeout_s: float | None = None
    ) -> RailStatus:
        """Move to `position_mm`, wait until idle there, and return the status read back."""
        self.start_move(position_mm, feed_mm_per_min)
        return self.wait_until_idle(target_mm=position_mm, timeout_s=timeout_s or 120.0)

    def position_mm(self) -> float:
        return self.status().position_mm

    def __enter__(self) -> Rail:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
