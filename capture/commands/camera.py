"""`mca camera ...`: list cameras, show one's info, get/set its properties, and serve the simulated EOS 70D."""

from __future__ import annotations

import typer

camera_app = typer.Typer(help="Tethered camera: list, info, config, and the simulated EOS 70D.", no_args_is_help=True)

CAMERA_OPTION = typer.Option("auto", "--camera", "-c", help="auto, sim, usb:BUS:ADDR or ptpip:HOST:PORT")


def _message(exc: Exception) -> str:
    """The text of an error: a KeyError's own message, not its quoted repr."""
    return str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)


def _open(spec: str):
    from mca.capture.tether import camera_factory
    from mca.devices.ptp.transport import TransportError

    try:
        return camera_factory(spec)()
    except (TransportError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc


@camera_app.command("list")
def list_cameras(sim: bool = typer.Option(False, "--sim", help="also list the simulated EOS 70D")) -> None:
    """List PTP cameras on USB (Canon first)."""
    from mca.devices.ptp.transport import TransportError
    from mca.devices.ptp.transport_usb import find_cameras

    found = []
    try:
        found = find_cameras()
    except TransportError as exc:
        typer.echo(f"warning: {exc}", err=True)
    if sim:
        from mca.capture.tether import make_sim_rig

        found += [
            dict(port="sim", manufacturer=c.manufacturer, product=c.product, serial_number=c.serial_number)
            for c in find_cameras(make_sim_rig().backend)
        ]  # type: ignore[misc]
    if not found:
        typer.echo("no PTP camera found (switch it on and connect it; `--camera sim` uses the simulated one)")
        return
    for c in found:
        d = (
            c
            if isinstance(c, dict)
            else dict(port=c.port, manufacturer=c.manufacturer, product=c.product, serial_number=c.serial_number)
        )
        typer.echo(f"{d['port']}\t{d['manufacturer']} {d['product']}\tserial {d['serial_number']}")


@camera_app.command("info")
def info(camera: str = CAMERA_OPTION) -> None:
    """Model, firmware, serial number, storages and capture method."""
    cam = _open(camera)
    try:
        i = cam.info
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
    finally:
        cam.close()


@camera_app.command("config")
def config(
    action: str | None = typer.Argument(None, help="get or set; omit to list every property"),
    name: str | None = typer.Argument(None, help="iso, shutterspeed, aperture, capturetarget, imageformat"),
    value: str | None = typer.Argument(None, help="the new value (for set)"),
    camera: str = CAMERA_OPTION,
) -> None:
    """Show or change camera properties by human name."""
    from mca.devices.ptp.properties import PROPERTIES

    if action not in (None, "get", "set") or (action and not name) or (action == "set" and value is None):
        typer.echo("usage: mca camera config [get NAME | set NAME VALUE]", err=True)
        raise typer.Exit(2)
    cam = _open(camera)
    try:
        if action == "set":
            try:
                pv = cam.set_property(name, value)  # type: ignore[arg-type]
            except (KeyError, ValueError) as exc:
                typer.echo(f"error: {_message(exc)}", err=True)
                raise typer.Exit(2) from exc
            typer.echo(f"{pv.name} = {pv.value}")
            return
        names = [name] if name else list(PROPERTIES)
        for n in names:
            try:
                pv = cam.get_property(n)  # type: ignore[arg-type]
            except KeyError as exc:
                if name:
                    typer.echo(f"error: {_message(exc)}", err=True)
                    raise typer.Exit(2) from exc
                continue
            typer.echo(f"{pv.name} = {pv.value}")
            if pv.allowed:
                typer.echo(f"  allowed: {', '.join(pv.allowed)}")
    finally:
        cam.close()


@camera_app.command("serve-sim")
def serve_sim(
    ptpip: str = typer.Option("127.0.0.1:15740", "--ptpip", help="loopback HOST:PORT to listen on"),
    serial: str = typer.Option("SIM70D0000001", help="serial number the simulated camera reports"),
) -> None:
    """Serve the simulated EOS 70D over PTP/IP (for gphoto2 and other PTP/IP initiators) until Ctrl-C."""
    from mca.capture.tether import default_sim_frame_source
    from mca.devices.sim_eos70d.ptpip_server import PtpIpServer, parse_address
    from mca.devices.sim_eos70d.responder import SimEos70D

    host, port = parse_address(ptpip)
    try:
        server = PtpIpServer(SimEos70D(default_sim_frame_source(), serial_number=serial), host, port)
    except (OSError, ValueError) as exc:
        typer.echo(f"error: cannot listen on {ptpip}: {exc}", err=True)
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
