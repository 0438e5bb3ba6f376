"""`mca camera ...`: list cameras, show one's info, get/set its properties, check it (doctor), serve the simulated EOS 70D."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NoReturn

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


def _fail(exc: Any) -> NoReturn:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(getattr(exc, "exit_code", 1)) from exc


def _open(spec: str | None, debug_logfile: Path | None = None, ctx: typer.Context | None = None) -> Any:
    """Open the camera `spec` names (None: the config file's `camera`, else auto), logging PTP to a file if asked."""
    from mca.capture.camera_app import CameraSetupError, choose_camera, open_chosen

    try:
        choice = choose_camera(spec, debug_logfile, "mca camera")
        if choice.traffic is not None and ctx is not None:
            ctx.call_on_close(choice.traffic.close)  # when the command ends, however it ends
        return open_chosen(choice)
    except CameraSetupError as exc:
        _fail(exc)


@camera_app.command("list")
def list_cameras(
    sim: bool = typer.Option(False, "--sim", help="also list the simulated EOS 70D"), as_json: bool = JSON_OPTION
) -> None:
    """List PTP cameras on USB (Canon first)."""
    from mca.capture.camera_app import list_cameras as find

    rows, warning = find(sim)
    if warning is not None:
        typer.echo(f"warning: {warning}", err=True)
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
    from mca.capture.camera_app import CameraSetupError, camera_info, info_lines

    cam = _open(camera, debug_logfile, ctx)
    try:
        document = camera_info(cam)
    except CameraSetupError as exc:
        _fail(exc)
    finally:
        cam.close()
    if as_json:
        _echo_json(document)
        return
    for line in info_lines(document):
        typer.echo(line)


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
    from mca.capture.camera_app import CameraSetupError, camera_properties, property_lines, set_camera_property

    if action not in (None, "get", "set") or (action and not name) or (action == "set" and value is None):
        typer.echo("usage: mca camera config [get NAME | set NAME VALUE]", err=True)
        raise typer.Exit(2)
    cam = _open(camera, debug_logfile, ctx)
    try:
        if action == "set":
            listed = set_camera_property(cam, str(name), str(value))
        else:
            listed = camera_properties(cam, name)
    except CameraSetupError as exc:
        _fail(exc)
    finally:
        cam.close()
    if as_json:
        _echo_json(listed)
        return
    for line in property_lines(listed, with_allowed=action != "set"):
        typer.echo(line)


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
    from mca.capture.camera_app import CameraSetupError, diagnose_camera
    from mca.capture.doctor import write_report

    cam = _open(camera, ctx=ctx)
    try:
        result = diagnose_camera(cam, live_view)
    except CameraSetupError as exc:
        _fail(exc)
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
    from mca.capture.camera_app import CameraSetupError, sim_server, sim_server_banner

    try:
        server = sim_server(ptpip, serial, scenario)
    except CameraSetupError as exc:
        _fail(exc)
    typer.echo(sim_server_banner(server), err=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass


def register(app: typer.Typer) -> None:
    app.add_typer(camera_app, name="camera")
