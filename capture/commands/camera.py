"""`mca camera ...`: list cameras, show one's info, get/set its properties, check it (doctor), serve the simulated EOS 70D."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

camera_app = typer.Typer(
    help="Tethered camera: list, info, config, doctor, and the simulated EOS 70D.", no_args_is_help=True
)

CAMERA_OPTION = typer.Option(
    None, "--camera", "-c", help="auto, sim, sim:SCENARIO, usb:BUS:ADDR or ptpip:HOST:PORT (default: config, auto)"
)
JSON_OPTION = typer.Option(False, "--json", help="print the result as JSON")
LOGFILE_OPTION = typer.Option(
    None, "--debug-logfile", metavar="FILE", help="append every PTP transaction and event to FILE"
)


def _echo_json(document: Any) -> None:
    import json

    from mca.capture.outputs import json_safe

    typer.echo(json.dumps(json_safe(document), indent=2))


def _open(spec: str | None, debug_logfile: Path | None = None, ctx: typer.Context | None = None):
    """Open the camera `spec` names (None: the config file's `camera`, else auto), logging PTP to a file if asked."""
    from mca.capture.config import ConfigError, fill_from_config
    from mca.devices.cameras import open_camera
    from mca.devices.ptp.camera import PropertyNotReported, PtpError
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.transport import TransportError

    try:
        spec = str(fill_from_config(camera=spec)["camera"])
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    traffic = None
    if debug_logfile is not None:
        from mca.devices.ptp.traffic_log import TrafficLogFile

        try:
            traffic = TrafficLogFile(str(debug_logfile), header=f"mca camera --camera {spec}")
        except OSError as exc:
            typer.echo(f"error: --debug-logfile {debug_logfile}: {exc.strerror or exc}", err=True)
            raise typer.Exit(2) from exc
        if ctx is not None:
            ctx.call_on_close(traffic.close)  # when the command ends, however it ends
    try:
        return open_camera(spec, traffic_log=traffic.write if traffic is not None else None)()
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    except (TransportError, ProtocolError, PtpError, PropertyNotReported) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc


@camera_app.command("list")
def list_cameras(
    sim: bool = typer.Option(False, "--sim", help="also list the simulated EOS 70D"), as_json: bool = JSON_OPTION
) -> None:
    """List PTP cameras on USB (Canon first)."""
    from mca.devices.ptp.transport import TransportError
    from mca.devices.ptp.transport_usb import find_cameras

    found: list[Any] = []
    try:
        found = list(find_cameras())
    except TransportError as exc:
        typer.echo(f"warning: {exc}", err=True)
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
    if as_json:
        _echo_json({"cameras": rows})
        return
    if not rows:
        typer.echo("no PTP camera found (switch it on and connect it; `--camera sim` uses the simulated one)")
        return
    for d in rows:
        typer.echo(f"{d['port']}\t{d['manufacturer']} {d['product']}\tserial {d['serial_number']}")


@camera_app.command("info")
def info(
    ctx: typer.Context,
    camera: str | None = CAMERA_OPTION,
    as_json: bool = JSON_OPTION,
    debug_logfile: Path | None = LOGFILE_OPTION,
) -> None:
    """Model, firmware, serial number, storages and capture method."""
    from mca.devices.ptp.camera import PtpError
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.transport import TransportError

    cam = _open(camera, debug_logfile, ctx)
    try:
        i = cam.info
        if as_json:
            _echo_json(
                {
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
            )
            return
        typer.echo(f"camera:       {cam.name}")
        typer.echo(f"model:        {i.manufacturer} {i.model}")
        typer.echo(f"firmware:     {i.device_version}")
        typer.echo(f"serial:       {i.serial_number}")
        typer.echo(f"capture:      {'Canon EOS remote release' if cam.is_eos else 'PTP InitiateCapture'}")
        for sid, s in cam.storages().items():
            typer.echo(
                f"storage 0x{sid:08X}: {s.description} {s.volume_label} "
                f"{s.free_space_bytes / 1e9:.1f} of {s.max_capacity_bytes / 1e9:.1f} GB free"
            )
    except (TransportError, ProtocolError, PtpError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    finally:
        cam.close()


@camera_app.command("config")
def config(
    ctx: typer.Context,
    action: str | None = typer.Argument(None, help="get or set; omit to list every property"),
    name: str | None = typer.Argument(None, help="iso, shutterspeed, aperture, capturetarget, imageformat"),
    value: str | None = typer.Argument(None, help="the new value (for set)"),
    camera: str | None = CAMERA_OPTION,
    as_json: bool = JSON_OPTION,
    debug_logfile: Path | None = LOGFILE_OPTION,
) -> None:
    """Show or change camera properties by human name."""
    from mca.devices.ptp.camera import PropertyNotReported, PtpError
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.properties import PROPERTIES, UnknownPropertyName
    from mca.devices.ptp.transport import TransportError

    if action not in (None, "get", "set") or (action and not name) or (action == "set" and value is None):
        typer.echo("usage: mca camera config [get NAME | set NAME VALUE]", err=True)
        raise typer.Exit(2)
    cam = _open(camera, debug_logfile, ctx)
    try:
        if action == "set":
            try:
                pv = cam.set_property(str(name), str(value))
            except (UnknownPropertyName, PropertyNotReported, ValueError, PtpError) as exc:
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(2) from exc
            if as_json:
                _echo_json({pv.name: {"value": pv.value, "allowed": list(pv.allowed)}})
            else:
                typer.echo(f"{pv.name} = {pv.value}")
            return
        names = [name] if name else list(PROPERTIES)
        listed: dict[str, Any] = {}
        for n in names:
            try:
                pv = cam.get_property(n)
            except (UnknownPropertyName, PropertyNotReported) as exc:
                if name:
                    typer.echo(f"error: {exc}", err=True)
                    raise typer.Exit(2) from exc
                continue
            listed[pv.name] = {"value": pv.value, "allowed": list(pv.allowed)}
            if as_json:
                continue
            typer.echo(f"{pv.name} = {pv.value}")
            if pv.allowed:
                typer.echo(f"  allowed: {', '.join(pv.allowed)}")
        if as_json:
            _echo_json(listed)
    except (TransportError, ProtocolError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    finally:
        cam.close()


@camera_app.command("doctor")
def doctor(
    ctx: typer.Context,
    camera: str | None = CAMERA_OPTION,
    report: Path | None = typer.Option(
        None, "--report", help="where to write the report (default: ./mca-doctor-SERIAL-TIME.txt)"
    ),
    live_view: bool = typer.Option(False, "--live-view", help="also fetch one live-view frame"),
) -> None:
    """Check a camera: what it reports on the wire, what this stack will use, and anything unexpected.

    The report is printed and written to a file you can attach to a bug report.
    """
    from mca.capture.doctor import diagnose, write_report
    from mca.devices.ptp.camera import PtpError
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.transport import TransportError

    cam = _open(camera, ctx=ctx)
    try:
        usb = getattr(cam.transport, "info", None)
        ids = (usb.vendor_id, usb.product_id) if usb is not None else None
        result = diagnose(cam, usb_ids=ids, live_view=live_view)
    except (TransportError, ProtocolError, PtpError) as exc:
        typer.echo(f"error: the camera stopped answering during the check: {exc}", err=True)
        raise typer.Exit(1) from exc
    finally:
        cam.close()
    typer.echo(result.text(), nl=False)
    try:
        path = write_report(result, report)
    except OSError as exc:
        typer.echo(f"error: cannot write the report: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(f"report written to {path}", err=True)


@camera_app.command("serve-sim")
def serve_sim(
    ptpip: str = typer.Option("127.0.0.1:15740", "--ptpip", help="loopback HOST:PORT to listen on"),
    serial: str = typer.Option("SIM70D0000001", help="serial number the simulated camera reports"),
    scenario: str = typer.Option("none", "--scenario", help="a fault scenario of the simulated body"),
) -> None:
    """Serve the simulated EOS 70D over PTP/IP (for gphoto2 and other PTP/IP initiators) until Ctrl-C."""
    from mca.devices.sim.eos70d.faults import scenario as named_scenario
    from mca.devices.sim.eos70d.ptpip_server import PtpIpServer, parse_address
    from mca.devices.sim.eos70d.responder import SimEos70D
    from mca.devices.sim.world import scene_frame_source

    try:
        chosen = named_scenario(scenario)
        host, port = parse_address(ptpip)
        sim = SimEos70D(scene_frame_source(), serial_number=serial, behaviour=chosen.behaviour)
        server = PtpIpServer(sim, host, port, faults=chosen.faults)
    except (OSError, ValueError) as exc:
        typer.echo(f"error: cannot serve the simulated camera on {ptpip}: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(
        f"simulated Canon EOS 70D on ptpip:{server.address} (gphoto2 --port ptpip:{server.host}"
        f"{'' if server.port == 15740 else f':{server.port}:{server.port}'}); Ctrl-C to stop",
        err=True,
    )
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass


def register(app: typer.Typer) -> None:
    app.add_typer(camera_app, name="camera")
