"""`devices.cameras.open_camera(spec)`: cameras by name, the simulated EOS 70D through the same call as a real one.

The application opens every camera through it; `sim` is the simulated body photographing the simulated
world (the paper's scenes, `devices.sim.world`).
"""

from __future__ import annotations

import re

import pytest

from mca.devices.cameras import SPECS, make_sim_rig, open_camera
from mca.devices.ptp.transport import TransportError


def test_sim_opens_the_simulated_eos_70d_through_the_real_ptp_stack() -> None:
    factory = open_camera("sim", timeout_s=2.0)
    camera = factory()
    try:
        assert camera.info.model == "Canon EOS 70D" and camera.is_eos
        assert camera.policy.transaction_timeout_s == 2.0
        captured = camera.capture()
        assert captured.filename.upper().endswith(".CR2") and captured.size_bytes > 0
    finally:
        camera.close()
    again = factory()  # the same simulated body, opened again (as after a pulled cable)
    try:
        assert factory.rig.camera.exposures == 1  # type: ignore[attr-defined]
    finally:
        again.close()


def test_a_sim_scenario_names_its_fault_plan() -> None:
    assert open_camera("sim:none").rig.scenario == "none"  # type: ignore[attr-defined]
    with pytest.raises(ValueError):
        open_camera("sim:no-such-scenario")


def test_a_rig_handed_in_is_the_one_opened() -> None:
    rig = make_sim_rig()
    assert open_camera("sim", rig=rig).rig is rig  # type: ignore[attr-defined]


def test_names_that_are_no_camera_are_refused_with_the_accepted_forms() -> None:
    opener = open_camera
    with pytest.raises(ValueError, match=r"unknown camera 'canon'.*auto, sim, sim:SCENARIO, usb:BUS:ADDR or ptpip"):
        opener("canon")
    with pytest.raises(ValueError, match=re.escape("PTP/IP port must be a number, got 'x' in 'ptpip:127.0.0.1:x'")):
        opener("ptpip:127.0.0.1:x")
    assert "usb:BUS:ADDR" in SPECS


def test_a_usb_address_with_no_camera_is_a_transport_error_when_opened() -> None:
    factory = open_camera("usb:999:999")  # parsing opens nothing; opening looks on the bus
    with pytest.raises((TransportError, ValueError)):
        factory()
