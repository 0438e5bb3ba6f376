"""The GRBL 1.1 codec: messages parsed from firmware text, garbage refused, rail/machine mapping."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mca.devices.rail import grbl_protocol as gp


def test_status_report_from_grbl_docs_parses_state_position_and_feed() -> None:
    report = gp.parse_line("<Idle|MPos:10.000,0.000,0.000|FS:0,0>")
    assert report == gp.StatusReport(state="Idle", mpos_mm=(10.0, 0.0, 0.0), feed_mm_per_min=0.0)
    run = gp.parse_line("<Hold:1|MPos:-5.250,0.000,0.000|FS:600,0|WCO:0.000,0.000,0.000>")
    assert (run.state, run.substate, run.mpos_mm[0], run.feed_mm_per_min) == ("Hold", 1, -5.25, 600.0)
    assert run.wco_mm == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("ok", gp.Ok()),
        ("error:15", gp.ErrorReply(15)),
        ("ALARM:2", gp.AlarmMessage(2)),
        ("Grbl 1.1h ['$' for help]", gp.Banner("1.1h")),
        ("[MSG:'$H'|'$X' to unlock]", gp.Feedback("MSG:'$H'|'$X' to unlock")),
        ("$130=300.000", gp.SettingLine(130, 300.0)),
    ],
)
def test_each_grbl_message_kind_is_recognised(line: str, expected: gp.GrblMessage) -> None:
    assert gp.parse_line(line) == expected


def test_codes_carry_grbl_meanings() -> None:
    assert "travel" in gp.ErrorReply(15).message
    assert "alarm" in gp.ErrorReply(9).message
    assert "soft limit" in gp.AlarmMessage(2).message
    assert "hard limit" in gp.AlarmMessage(1).message


@pytest.mark.parametrize("line", ["hello", "<Dancing|MPos:0,0,0>", "<Idle|MPos:a,b,c>", "okay", "error:x"])
def test_lines_grbl_never_sends_are_protocol_errors(line: str) -> None:
    with pytest.raises(gp.GrblProtocolError):
        gp.parse_line(line)


def test_splitter_handles_crlf_across_chunks_and_refuses_binary_and_endless_lines() -> None:
    splitter = gp.LineSplitter()
    assert splitter.feed(b"o") == []
    assert splitter.feed(b"k\r\n<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r") == [
        "ok",
        "<Idle|MPos:0.000,0.000,0.000|FS:0,0>",
    ]
    with pytest.raises(gp.GrblProtocolError, match="non-ASCII"):
        splitter.feed(b"\xff\xfe\x01\r\n")
    with pytest.raises(gp.GrblProtocolError, match="no line ending"):
        gp.LineSplitter(max_line_bytes=16).feed(b"x" * 17)


def test_move_command_is_absolute_machine_coordinates() -> None:
    assert gp.move_command(-120.0, 600) == b"G90 G53 G1 X-120.000 F600\n"
    with pytest.raises(ValueError):
        gp.move_command(1.0, 0)


def test_rail_position_is_distance_from_home_switch_for_both_homing_directions() -> None:
    toward_positive = gp.GrblAxisSettings(max_travel_mm=300.0, homing_dir_mask=0)
    toward_negative = gp.GrblAxisSettings(max_travel_mm=300.0, homing_dir_mask=1)
    assert gp.machine_x_mm(0.0, toward_positive) == 0.0 and gp.machine_x_mm(300.0, toward_positive) == -300.0
    assert gp.machine_x_mm(0.0, toward_negative) == -300.0 and gp.machine_x_mm(300.0, toward_negative) == 0.0


@given(st.floats(0.0, 1000.0), st.floats(1.0, 1000.0), st.integers(0, 7))
def test_rail_and_machine_coordinates_round_trip(position_mm: float, travel_mm: float, mask: int) -> None:
    axis = gp.GrblAxisSettings(max_travel_mm=travel_mm, homing_dir_mask=mask)
    assert gp.rail_mm(gp.machine_x_mm(position_mm, axis), axis) == pytest.approx(position_mm, abs=1e-9)


def test_settings_listing_maps_to_axis_settings() -> None:
    axis = gp.GrblAxisSettings.from_settings({10: 1, 20: 1, 22: 1, 23: 1, 27: 2.0, 110: 3000, 130: 250})
    assert axis.soft_limits and axis.homing_enabled and axis.homes_toward_negative
    assert (axis.homing_pulloff_mm, axis.max_rate_mm_per_min, axis.max_travel_mm) == (2.0, 3000, 250)
