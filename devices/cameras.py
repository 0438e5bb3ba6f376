"""Cameras by name: `open_camera(spec)` for `auto`, `sim[:SCENARIO]`, `usb:BUS:ADDR` and `ptpip:HOST[:PORT]`.

The camera's counterpart of `devices.rail.open_rail`: the simulated EOS 70D is reached through the
very call a real body is (as python-can's `virtual` bus or pyserial's `loop://`), and behind it runs
the real PTP stack over a pure-Python pyusb backend. `open_camera` returns a factory rather than a
camera, so that a tethering session can open the camera again after a pulled cable.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from mca.devices.ptp.camera import Camera
from mca.devices.ptp.policy import DEFAULT_POLICY, PtpPolicy
from mca.devices.ptp.transport import TransportError

CameraFactory = Callable[[], Camera]

SPECS = "auto, sim, sim:SCENARIO, usb:BUS:ADDR or ptpip:HOST:PORT"
PTPIP_DEFAULT_PORT = 15740


@dataclass
class SimRig:
    """The simulated camera and the USB backend it is reached through (kept so a reconnect finds it again)."""

    camera: Any
    backend: Any
    scenario: str = "none"


def make_sim_rig(
    frame_source: Callable[[int], Any] | None = None,
    *,
    faults: Any = None,
    pace_bytes_per_s: float | None = None,
    scenario: str | None = None,
    live_view_source: Callable[[int], bytes] | None = None,
) -> SimRig:
    """The simulated EOS 70D on a simulated USB bus; `scenario` names a fault scenario (`faults.SCENARIOS`).

    Without `frame_source` / `live_view_source` the simulated body photographs the simulated world: the MCA
    simulator's rendering of the paper's scenes (`devices.sim.world.scene_frame_source`, rendered when a shot
    is taken, at `MCA_SIM_SIZE`) and one rendered scene in live view (`scene_live_view_source`).
    """
    from mca.devices.sim import world
    from mca.devices.sim.eos70d.faults import scenario as named_scenario
    from mca.devices.sim.eos70d.responder import SimEos70D
    from mca.devices.sim.eos70d.usb_backend import SimUsbBackend

    chosen = named_scenario(scenario or "none")
    sim = SimEos70D(
        frame_source or world.scene_frame_source(),
        behaviour=chosen.behaviour,
        live_view_source=live_view_source or world.scene_live_view_source(),
    )
    plan = faults if faults is not None else chosen.faults
    return SimRig(sim, SimUsbBackend(sim, faults=plan, pace_bytes_per_s=pace_bytes_per_s), chosen.name)


def policy_for(timeout_s: float | None, policy: PtpPolicy | None) -> PtpPolicy:
    """`policy` (default: `DEFAULT_POLICY`) with its transaction timeout replaced by `timeout_s`, when given."""
    chosen = policy or DEFAULT_POLICY
    if timeout_s is not None:
        chosen = replace(chosen, transaction_timeout_s=timeout_s)
    return chosen


def is_sim(spec: str) -> bool:
    """True for `sim` and `sim:SCENARIO`."""
    return spec == "sim" or spec.startswith("sim:")


def open_camera(
    spec: str,
    *,
    rig: SimRig | None = None,
    timeout_s: float | None = None,
    policy: PtpPolicy | None = None,
    traffic_log: Callable[[str], None] | None = None,
) -> CameraFactory:
    """A function that opens the camera named by `auto`, `sim[:SCENARIO]`, `usb:BUS:ADDR` or `ptpip:HOST[:PORT]`.

    `rig` is the simulated camera `sim` opens (default: a new one photographing the simulated world,
    `make_sim_rig(scenario=...)`);
    `timeout_s` overrides the policy's transaction timeout (tests shorten it); `traffic_log(line)` receives
    every PTP transaction and event of every connection it opens (`devices.ptp.traffic_log`). A spec that
    names no camera is a `ValueError` that lists the accepted forms.
    """
    from mca.devices.ptp.transport_usb import UsbTransport, find_cameras, open_usb

    chosen = policy_for(timeout_s, policy)

    def logged(transport: Any) -> Any:
        if traffic_log is None:
            return transport
        from mca.devices.ptp.traffic_log import log_traffic, timestamp

        traffic_log(f"{timestamp()} # connected to {spec} ({type(transport).__name__})")
        return log_traffic(transport, traffic_log)

    if is_sim(spec):
        sim_rig = rig or make_sim_rig(scenario=spec.partition(":")[2] or None)

        def open_sim() -> Camera:
            if not sim_rig.backend.connected:
                sim_rig.backend.replug()  # the simulated photographer plugs the cable back in
            cams = find_cameras(sim_rig.backend)
            return Camera.open(logged(UsbTransport(cams[0], policy=chosen)), policy=chosen)

        open_sim.rig = sim_rig  # type: ignore[attr-defined]
        return open_sim
    if spec.startswith("ptpip:"):
        from mca.devices.ptp.transport_ptpip import PtpIpTransport

        host, _, port = spec[len("ptpip:") :].partition(":")
        try:
            port_number = int(port or PTPIP_DEFAULT_PORT)
        except ValueError as exc:
            raise ValueError(f"PTP/IP port must be a number, got {port!r} in {spec!r}") from exc
        return lambda: Camera.open(
            logged(PtpIpTransport(host or "127.0.0.1", port_number, policy=chosen)), policy=chosen
        )
    if spec.startswith("usb:"):
        return lambda: Camera.open(logged(open_usb(spec, policy=chosen)), policy=chosen)
    if spec == "auto":

        def open_auto() -> Camera:
            cams = find_cameras()
            if not cams:
                raise TransportError(
                    "no PTP camera on USB: connect and switch on the EOS 70D, "
                    "or use `--camera sim` for the simulated one"
                )
            return Camera.open(logged(UsbTransport(cams[0], policy=chosen)), policy=chosen)

        return open_auto
    raise ValueError(f"unknown camera {spec!r}: use {SPECS}")
