"""Rail faults end in a clear RailError naming the port, and the rail reconnects to resume a sweep."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from mca.devices.rail import (
    GrblRail,
    RailAlarm,
    RailDisconnected,
    RailError,
    RailProtocolError,
    RailTimeout,
)
from mca.devices.sim.grbl import SimGrbl, SimGrblPty


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimGrblPty]:
    with SimGrblPty(SimGrbl(speedup=50.0), link_path=tmp_path / "ttyRAIL") as runner:
        yield runner


@pytest.fixture
def rail(sim: SimGrblPty) -> Iterator[GrblRail]:
    with GrblRail(sim.port, poll_interval_s=0.01, answer_timeout_s=0.3, connect_timeout_s=0.6) as stage:
        stage.home()
        yield stage


def test_port_vanishing_mid_sweep_then_reconnect_and_resume(rail: GrblRail, sim: SimGrblPty) -> None:
    done_mm = [rail.move_to(20.0, feed_mm_per_min=3000).position_mm]
    rail.start_move(250.0, feed_mm_per_min=300)
    sim.unplug()  # cable pulled while moving
    with pytest.raises(RailDisconnected) as caught:
        rail.wait_until_idle(target_mm=250.0, timeout_s=5.0)
    message = str(caught.value)
    assert sim.port in message and "reconnect" in message
    with pytest.raises(RailDisconnected, match="closed"):
        rail.status()

    sim.replug()  # same port name (udev-style link); the controller has power-cycled
    assert rail.reconnect().state == "Alarm"
    rail.home()
    for target_mm in (40.0, 60.0):  # the sweep resumes after the last done position
        done_mm.append(rail.move_to(target_mm, feed_mm_per_min=3000).position_mm)
    assert done_mm == pytest.approx([20.0, 40.0, 60.0], abs=1e-3)
    assert sim.sim.power_up_count == 2


def test_soft_limit_alarm_is_a_rail_alarm_and_unlock_keeps_position(rail: GrblRail, sim: SimGrblPty) -> None:
    rail.move_to(30.0, feed_mm_per_min=3000)
    sim.sim.settings[130] = 100.0  # the controller's travel shrank behind the driver's back
    with pytest.raises(RailAlarm, match="ALARM:2") as caught:
        rail.move_to(150.0)
    assert caught.value.alarm_code == 2 and sim.port in str(caught.value)
    assert rail.unlock().state == "Idle"
    assert rail.position_mm() == pytest.approx(30.0, abs=1e-3)


def test_hard_limit_alarm_during_a_move_stops_the_wait(rail: GrblRail, sim: SimGrblPty) -> None:
    rail.start_move(250.0, feed_mm_per_min=300)
    sim.trigger_alarm(1)
    with pytest.raises(RailAlarm, match="home") as caught:
        rail.wait_until_idle(target_mm=250.0, timeout_s=5.0)
    assert caught.value.alarm_code in (1, None)
    assert rail.home().idle  # resets out of the critical state, then homes


def test_silent_controller_times_out_naming_the_port(rail: GrblRail, sim: SimGrblPty) -> None:
    sim.mute()
    with pytest.raises(RailTimeout, match="no answer") as caught:
        rail.status()
    assert sim.port in str(caught.value) and "115200" in str(caught.value)
    sim.mute(False)
    assert rail.reconnect().idle


def test_silent_port_at_connect_times_out(sim: SimGrblPty) -> None:
    sim.mute()
    with pytest.raises(RailTimeout, match="no answer from a GRBL controller"):
        GrblRail(sim.port, connect_timeout_s=0.4)


@pytest.mark.parametrize("noise", [b"\xff\xfe\x00\x13\x80\r\n", b"hello from a barcode scanner\r\n"])
def test_garbage_on_the_line_is_a_protocol_error(rail: GrblRail, sim: SimGrblPty, noise: bytes) -> None:
    sim.inject(noise)
    with pytest.raises(RailProtocolError, match="baud rate") as caught:
        rail.status()
    assert sim.port in str(caught.value)
    assert rail.reconnect().idle


def test_missing_port_is_a_disconnect_error(tmp_path: Path) -> None:
    port = str(tmp_path / "ttyUSB9")
    with pytest.raises(RailDisconnected, match="cannot open") as caught:
        GrblRail(port)
    assert caught.value.port == port and isinstance(caught.value, RailError)
