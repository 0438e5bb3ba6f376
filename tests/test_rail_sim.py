"""The simulated GRBL firmware stepped with a fake clock: replies, alarms, limits and motion at the feed rate."""

from __future__ import annotations

import pytest

from mca.devices.rail import grbl_protocol as gp
from mca.devices.sim.grbl import SimGrbl


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def lines(data: bytes) -> list[str]:
    return gp.LineSplitter().feed(data)


def status(sim: SimGrbl) -> gp.StatusReport:
    (line,) = [entry for entry in lines(sim.receive(b"?")) if entry.startswith("<")]
    return gp.parse_status(line)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def homed(clock: FakeClock) -> SimGrbl:
    sim = SimGrbl(clock=clock)
    sim.power_up()
    assert lines(sim.receive(b"$H\n")) == []  # `ok` only once the cycle is over
    assert status(sim).state == "Home"
    clock.now_s += 60.0
    assert lines(sim.tick()) == ["ok"]
    return sim


def test_power_up_prints_banner_and_locks_until_homed(clock: FakeClock) -> None:
    sim = SimGrbl(clock=clock)
    assert lines(sim.power_up()) == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert status(sim).state == "Alarm"
    assert lines(sim.receive(b"G1 X-10 F600\n")) == ["error:9"]
    assert lines(sim.receive(b"$X\n")) == ["[MSG:Caution: Unlocked]", "ok"]
    assert status(sim).state == "Idle"


def test_homing_sets_machine_position_to_minus_pulloff(homed: SimGrbl) -> None:
    report = status(homed)
    assert (report.state, report.mpos_mm) == ("Idle", (-1.0, 0.0, 0.0))


def test_motion_advances_at_the_commanded_feed(homed: SimGrbl, clock: FakeClock) -> None:
    assert lines(homed.receive(b"G90 G53 G1 X-61.000 F600\n")) == ["ok"]
    clock.now_s += 1.0  # 600 mm/min = 10 mm/s
    report = status(homed)
    assert report.state == "Run" and report.feed_mm_per_min == 600
    assert report.mpos_mm[0] == pytest.approx(-11.0)
    clock.now_s += 10.0
    assert status(homed).mpos_mm[0] == pytest.approx(-61.0) and status(homed).state == "Idle"


def test_speedup_scales_simulated_time() -> None:
    clock = FakeClock()
    sim = SimGrbl(clock=clock, speedup=10.0)
    sim.power_up()
    sim.receive(b"$X\nG1 X-100 F600\n")
    clock.now_s += 0.5  # 5 s of simulated motion
    assert status(sim).mpos_mm[0] == pytest.approx(-50.0)


def test_feed_above_max_rate_is_capped(homed: SimGrbl, clock: FakeClock) -> None:
    homed.receive(b"G1 X-201 F99999\n")
    clock.now_s += 1.0  # $110 = 3000 mm/min = 50 mm/s
    assert status(homed).mpos_mm[0] == pytest.approx(-51.0)


def test_g1_beyond_soft_limits_raises_alarm_2_and_needs_reset(homed: SimGrbl, clock: FakeClock) -> None:
    assert lines(homed.receive(b"G1 X-400 F600\n")) == ["ALARM:2", "[MSG:Reset to continue]"]
    assert lines(homed.receive(b"$X\n")) == []  # critical event: lines wait for a reset
    assert lines(homed.receive(gp.SOFT_RESET)) == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert lines(homed.receive(b"$X\n")) == ["[MSG:Caution: Unlocked]", "ok"]
    assert status(homed).mpos_mm[0] == pytest.approx(-1.0)  # position retained


def test_jog_beyond_travel_is_error_15(homed: SimGrbl) -> None:
    assert lines(homed.receive(b"$J=G90 X-400 F600\n")) == ["error:15"]
    assert lines(homed.receive(b"$J=G90 X-5 F600\n")) == ["ok"]
    assert status(homed).state == "Jog"


def test_setting_changes_and_their_errors(homed: SimGrbl) -> None:
    assert lines(homed.receive(b"$130=100\n")) == ["ok"]
    assert "$130=100" in lines(homed.receive(b"$$\n"))
    assert lines(homed.receive(b"$999=1\n")) == ["error:3"]
    assert lines(homed.receive(b"$Q\n")) == ["error:3"]
    assert lines(homed.receive(b"$22=0\n$H\n")) == ["ok", "error:5"]


def test_gcode_errors(homed: SimGrbl) -> None:
    assert lines(homed.receive(b"G1 X-5\n")) == ["error:22"]  # no feed yet
    assert lines(homed.receive(b"G7 X-5\n")) == ["error:20"]
    assert lines(homed.receive(b"G1 X\n")) == ["error:2"]
    assert lines(homed.receive(b"X" * 100 + b"\n")) == ["error:11"]


def test_feed_hold_resume_and_reset_during_motion(homed: SimGrbl, clock: FakeClock) -> None:
    homed.receive(b"G1 X-101 F600\n")
    clock.now_s += 1.0
    assert lines(homed.receive(gp.FEED_HOLD)) == []
    held = status(homed)
    clock.now_s += 5.0
    assert (held.state, held.substate) == ("Hold", 1) and status(homed).mpos_mm == held.mpos_mm
    homed.receive(gp.CYCLE_START)
    clock.now_s += 1.0
    assert status(homed).mpos_mm[0] == pytest.approx(-21.0)
    assert lines(homed.receive(gp.SOFT_RESET))[0] == "ALARM:3"
    assert status(homed).state == "Alarm"


def test_dwell_answers_once_motion_is_done(homed: SimGrbl, clock: FakeClock) -> None:
    assert lines(homed.receive(b"G1 X-11 F600\nG4 P0\n")) == ["ok"]
    clock.now_s += 2.0
    assert lines(homed.tick()) == ["ok"]
