"""The bench rail: a `Rail` interface, the GRBL-over-serial stage, and `open_rail` choosing a real port or `sim`."""

from __future__ import annotations

from mca.devices.rail.base import (
    Rail,
    RailAlarm,
    RailCommandError,
    RailDisconnected,
    RailError,
    RailProtocolError,
    RailStatus,
    RailTimeout,
)
from mca.devices.rail.grbl import GrblRail

SIM = "sim"

__all__ = [
    "SIM",
    "GrblRail",
    "Rail",
    "RailAlarm",
    "RailCommandError",
    "RailDisconnected",
    "RailError",
    "RailProtocolError",
    "RailStatus",
    "RailTimeout",
    "open_rail",
]


def open_rail(spec: str, *, sim_speedup: float = 1.0, **options: object) -> GrblRail:
    """Open the rail named by `spec`: a serial port (`/dev/ttyUSB0`, any pyserial URL) or `sim`.

    `sim` starts the simulated GRBL controller on a pseudo-terminal in a thread and
    talks to it through pyserial exactly as to a real port; closing the rail stops it.
    `sim_speedup` makes simulated motion that many times faster than real time.
    """
    if spec != SIM:
        return GrblRail(spec, **options)  # type: ignore[arg-type]
    from mca.devices.sim.grbl import SimGrblPty

    runner = SimGrblPty(speedup=sim_speedup)
    runner.start()
    try:
        rail = GrblRail(runner.port, on_close=runner.stop, **options)  # type: ignore[arg-type]
    except BaseException:
        runner.stop()
        raise
    rail.simulator = runner  # type: ignore[attr-defined]
    return rail
