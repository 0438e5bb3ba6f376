"""The application side of `mca camera` (and the camera of `mca capture`): the camera a spec or the config names,
its info and properties as data, the doctor's check, and the simulated EOS 70D served over PTP/IP."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class CameraSetupError(RuntimeError):
    """A camera that cannot be opened or used as asked; `exit_code` 2 for a usage error, 1 for the camera's."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


@dataclass
class CameraChoice:
    """The camera spec in effect (the option, else the config's), its factory, and the PTP traffic log if any."""

    spec: str
    factory: Callable[[], Any]
    traffic: Any = None  # a `TrafficLogFile` to close when the command ends


def choose_camera(spec: str | None, debug_logfile: Path | None = None, command: str = "mca camera") -> CameraChoice:
    """The factory of the camera `spec` names (None: the config file's `camera`, else auto), logging every PTP
    transaction to `debug_logfile` if given (its header says `command --camera SPEC`)."""
    from mca.capture.config import ConfigError, fill_from_config
    from mca.devices.cameras import open_camera

    try:
        spec = str(fill_from_config(camera=spec)["camera"])
    except ConfigError as exc:
        raise CameraSetupError(str(exc)) from exc
    traffic = None
    if debug_logfile is not None:
        from mca.devices.ptp.traffic_log import TrafficLogFile

        try:
            traffic = TrafficLogFile(str(debug_logfile), header=f"{command} --camera {spec}")
        except OSError as exc:
            raise CameraSetupError(f"--debug-logfile {debug_logfile}: {exc.strerror or exc}") from exc
    try:
        factory = open_camera(spec, traffic_log=traffic.write if traffic is not None else None)
    except ValueError as exc:
        if traffic is not None:
            traffic.close()
        raise CameraSetupError(str(exc)) from exc
    return CameraChoice(spec, factory, traffic)


def open_chosen(choice: CameraChoice) -> Any:
    """Open the chosen camera (a PTP session); a `CameraSetupError` (exit code 1) when it does not answer."""
    from mca.devices.ptp.camera import PropertyNotReported, PtpError
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.transport import TransportError

    try:
        return choice.factory()
    except ValueError as exc:
        raise CameraSetupError(str(exc)) from exc
    except (TransportError, ProtocolError, PtpError, PropertyNotReported) as exc:
        raise CameraSetupError(str(exc), exit_code=1) from exc


def camera_errors() -> tuple[type[BaseException], ...]:
    """The errors of a camera that stops answering mid-command (transport, protocol, PTP response)."""
    from mca.devices.ptp.camera import PtpError
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.transport import TransportError

    return (TransportError, ProtocolError, PtpError)


def list_cameras(sim: bool = False) -> tuple[list[dict[str, Any]], str | None]:
    """PTP cameras on USB (Canon first), plus the simulated EOS 70D with `sim`: (rows, a warning or None)."""
    from mca.devices.ptp.transport import TransportError
    from mca.devices.ptp.transport_usb import find_cameras

    found: list[Any] = []
    warning = None
    try:
        found = list(find_cameras())
    except TransportError as exc:
        warning = str(exc)
    if sim:
        from mca.devices.cameras import make_sim_rig

        found += [
            dict(port="sim", manufacturer=c.manufacturer, product=c.product, serial_number=c.serial_number)
            for c in find_cameras(make_sim_rig().backend)
        ]
    rows = [
        c
        if isinstance(c, dict)
        else dict(port=c.port, manufacturer=c.manufacturer, product=c.product, serial_number=c.serial_number)
        for c in found
    ]
    return rows, warning


def camera_info(cam: Any) -> dict[str, Any]:
    """`mca camera info`: model, firmware, serial number, capture method and storages of an open camera.

    A camera that stops answering raises `CameraSetupError` (exit code 1)."""
    try:
        return _camera_info(cam)
    except camera_errors() as exc:
        raise CameraSetupError(str(exc), exit_code=1) from exc


def _camera_info(cam: Any) -> dict[str, Any]:
    i = cam.info
    return {
        "camera": cam.name,
        "manufacturer": i.manufacturer,
        "model": i.model,
        "firmware": i.device_version,
        "serial_number": i.serial_number,
        "capture": "Canon EOS remote release" if cam.is_eos else "PTP InitiateCapture",
        "storages": [
            {
                "id": f"0x{sid:08X}",
                "description": s.description,
                "volume_label": s.volume_label,
                "free_bytes": s.free_space_bytes,
                "capacity_bytes": s.max_capacity_bytes,
            }
            for sid, s in cam.storages().items()
        ],
    }


def info_lines(info: dict[str, Any]) -> list[str]:
    """`camera_info` as the lines `mca camera info` prints."""
    lines = [
        f"camera:       {info['camera']}",
        f"model:        {info['manufacturer']} {info['model']}",
        f"firmware:     {info['firmware']}",
        f"serial:       {info['serial_number']}",
        f"capture:      {info['capture']}",
    ]
    lines += [
        f"storage {s['id']}: {s['description']} {s['volume_label']} "
        f"{s['free_bytes'] / 1e9:.1f} of {s['capacity_bytes'] / 1e9:.1f} GB free"
        for s in info["storages"]
    ]
    return lines


def camera_properties(cam: Any, name: str | None = None) -> dict[str, dict[str, Any]]:
    """Property `name` (or every known one the camera reports) as {name: {"value", "allowed"}}.

    An unknown name, or `name` not reported by the camera, raises `CameraSetupError` (exit code 2)."""
    from mca.devices.ptp.camera import PropertyNotReported
    from mca.devices.ptp.properties import PROPERTIES, UnknownPropertyName

    listed: dict[str, dict[str, Any]] = {}
    for n in [name] if name else list(PROPERTIES):
        try:
            pv = cam.get_property(n)
        except (UnknownPropertyName, PropertyNotReported) as exc:
            if name:
                raise CameraSetupError(str(exc)) from exc
            continue
        except camera_errors() as exc:
            raise CameraSetupError(str(exc), exit_code=1) from exc
        listed[pv.name] = {"value": pv.value, "allowed": list(pv.allowed)}
    return listed


def set_camera_property(cam: Any, name: str, value: str) -> dict[str, dict[str, Any]]:
    """Set property `name` by its human name and value; returns it as `camera_properties` does."""
    from mca.devices.ptp.camera import PropertyNotReported, PtpError
    from mca.devices.ptp.properties import UnknownPropertyName

    try:
        pv = cam.set_property(name, value)
    except (UnknownPropertyName, PropertyNotReported, ValueError, PtpError) as exc:
        raise CameraSetupError(str(exc)) from exc
    except camera_errors() as exc:
        raise CameraSetupError(str(exc), exit_code=1) from exc
    return {pv.name: {"value": pv.value, "allowed": list(pv.allowed)}}


def property_lines(listed: dict[str, dict[str, Any]], with_allowed: bool = True) -> list[str]:
    """`name = value` per property, each followed by its allowed values when asked."""
    lines = []
    for name, entry in listed.items():
        lines.append(f"{name} = {entry['value']}")
        if with_allowed and entry["allowed"]:
            lines.append(f"  allowed: {', '.join(entry['allowed'])}")
    return lines


def diagnose_camera(cam: Any, live_view: bool = False) -> Any:
    """The doctor's check of an open camera (`capture.doctor.diagnose`), with the USB ids where it has them.

    A camera that stops answering raises `CameraSetupError` (exit code 1)."""
    from mca.capture.doctor import diagnose

    try:
        usb = getattr(cam.transport, "info", None)
        ids = (usb.vendor_id, usb.product_id) if usb is not None else None
        return diagnose(cam, usb_ids=ids, live_view=live_view)
    except camera_errors() as exc:
        raise CameraSetupError(f"the camera stopped answering during the check: {exc}", exit_code=1) from exc


def sim_server(ptpip: str = "127.0.0.1:15740", serial: str = "SIM70D0000001", scenario: str = "none") -> Any:
    """A `PtpIpServer` of the simulated EOS 70D on the loopback HOST:PORT `ptpip`, with a named fault scenario."""
    from mca.devices.sim.eos70d.faults import scenario as named_scenario
    from mca.devices.sim.eos70d.ptpip_server import PtpIpServer, parse_address
    from mca.devices.sim.eos70d.responder import SimEos70D
    from mca.devices.sim.world import scene_frame_source

    try:
        chosen = named_scenario(scenario)
        host, port = parse_address(ptpip)
        sim = SimEos70D(scene_frame_source(), serial_number=serial, behaviour=chosen.behaviour)
        return PtpIpServer(sim, host, port, faults=chosen.faults)
    except (OSError, ValueError) as exc:
        raise CameraSetupError(f"cannot serve the simulated camera on {ptpip}: {exc}") from exc


def sim_server_banner(server: Any) -> str:
    """Where the simulated camera listens, and the gphoto2 port that reaches it."""
    return (
        f"simulated Canon EOS 70D on ptpip:{server.address} (gphoto2 --port ptpip:{server.host}"
        f"{'' if server.port == 15740 else f':{server.port}:{server.port}'}); Ctrl-C to stop"
    )
