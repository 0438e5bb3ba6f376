"""The GRBL rail driven through pyserial on a real pseudo-terminal served by the simulated controller."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from mca.devices.rail import GrblRail, RailCommandError, open_rail
from mca.devices.sim.grbl import SimGrbl, SimGrblPty


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimGrblPty]:
    with SimGrblPty(SimGrbl(speedup=50.0), link_path=tmp_path / "ttyRAIL") as runner:
        yield runner


@pytest.fixture
def rail(sim: SimGrblPty) -> Iterator[GrblRail]:
    with GrblRail(sim.port, poll_interval_s=0.01, answer_timeout_s=1.0) as stage:
        yield stage


def test_connect_reads_settings_and_finds_the_power_up_lock(rail: GrblRail) -> None:
    assert rail.travel_mm == 300.0 and rail.axis.soft_limits and rail.axis.homing_enabled
    assert rail.status().state == "Alarm"


def test_home_then_sweep_reads_back_each_position(rail: GrblRail) -> None:
    homed = rail.home()
    assert homed.idle and homed.position_mm == pytest.approx(1.0)  # pull-off from the switch ($27)
    for target_mm in (10.0, 55.5, 120.0, 0.0):
        reached = rail.move_to(target_mm, feed_mm_per_min=3000)
        assert reached.idle and reached.position_mm == pytest.approx(target_mm, abs=1e-3)
        assert reached.machine_x_mm == pytest.approx(-target_mm, abs=1e-3)
        assert rail.position_mm() == pytest.approx(target_mm, abs=1e-3)


def test_motion_takes_time_and_halt_keeps_the_position(rail: GrblRail) -> None:
    rail.home()
    rail.start_move(300.0, feed_mm_per_min=300)  # 60 s of simulated motion, 1.2 s at 50x
    moving = rail.status()
    assert moving.state == "Run" and 1.0 <= moving.position_mm < 300.0
    assert moving.feed_mm_per_min == 300
    rail.halt()
    first = rail.status()
    second = rail.status()
    assert first.state == "Hold" and first.position_mm == second.position_mm < 300.0
    rail.resume()
    assert rail.status().state == "Run"


def test_targets_outside_travel_are_refused_before_sending(rail: GrblRail, sim: SimGrblPty) -> None:
    rail.home()
    with pytest.raises(RailCommandError, match=r"outside the travel 0\.\.300\.000 mm") as caught:
        rail.start_move(301.0)
    assert sim.port in str(caught.value)
    assert rail.status().idle  # nothing was sent, no alarm


def test_moving_while_locked_names_the_remedy(rail: GrblRail) -> None:
    with pytest.raises(RailCommandError, match=r"error:9.*mca rail home") as caught:
        rail.move_to(10.0)
    assert caught.value.error_code == 9


def test_open_rail_sim_serves_a_pty_and_stops_it_on_close() -> None:
    rail = open_rail("sim", sim_speedup=50.0, poll_interval_s=0.01)
    runner = rail.simulator  # type: ignore[attr-defined]
    try:
        assert rail.port.startswith("/dev/pts/")
        rail.home()
        assert rail.move_to(42.0, feed_mm_per_min=3000).position_mm == pytest.approx(42.0, abs=1e-3)
    finally:
        rail.close()
    assert runner._thread is None and runner._master is None
