"""The application side of `mca rail`: the bench rail the option or the config names, opened, and its status in words."""

from __future__ import annotations

from typing import Any

from mca.devices.rail import RailError

SIM_SPEEDUP = 20.0  # `--rail sim` moves this many times faster than the real stage would


def open_configured_rail(spec: str | None, sim_speedup: float = SIM_SPEEDUP) -> Any:
    """Open the rail `spec` names (a serial port, a pyserial URL, or `sim`; None: the config file's rail, else sim).

    Raises `ConfigError` for a bad config file and `RailError` when the rail cannot be opened."""
    from mca.capture.config import fill_from_config
    from mca.devices.rail import open_rail

    return open_rail(str(fill_from_config(rail=spec)["rail"]), sim_speedup=sim_speedup)


def describe_status(status: Any) -> str:
    """A rail status as one line: state, position from the home switch, machine X."""
    return (
        f"{status.state} at {status.position_mm:.3f} mm from the home switch (machine X {status.machine_x_mm:.3f} mm)"
    )


__all__ = ["SIM_SPEEDUP", "RailError", "describe_status", "open_configured_rail"]
