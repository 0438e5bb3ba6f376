"""`mca capture`: take N shots (or download shots taken on the camera) into a folder with a catalog."""

from __future__ import annotations

from pathlib import Path

import typer


def capture(
    camera: str | None = typer.Option(
        None, "--camera", "-c", help="auto, sim, usb:BUS:ADDR or ptpip:HOST:PORT (default: config, auto)"
    ),
    count: int = typer.Option(1, "--count", "-n", min=1, help="number of shots"),
    interval: float = typer.Option(0.0, "--interval", help="seconds between shot starts"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for the files and catalog.sqlite"),
    process: bool = typer.Option(False, "--process", help="run the depth pipeline on each shot"),
    profile: str | None = typer.Option(None, "--profile", help="processing profile (default: config, paper-70d)"),
    record: Path | None = typer.Option(None, "--record", help="rerun recording FILE.rrd for --process"),
    tethered: bool = typer.Option(
        False, "--tethered", help="download shots taken with the camera's shutter button until Ctrl-C"
    ),
    delete_after_verify: bool = typer.Option(
        False, "--delete-after-verify", help="delete each file from the card once verified on disk"
    ),
    capture_target: str = typer.Option("card", "--target", help="card or ram"),
) -> None:
    """Capture with a tethered camera; every shot is verified, fsynced and catalogued in OUT/catalog.sqlite."""
    import threading

    from mca.capture.config import ConfigError, fill_from_config
    from mca.capture.tether import TetherSession, camera_factory
    from mca.devices.ptp.transport import TransportError

    try:
        chosen = fill_from_config(camera=camera, profile=profile)
        camera, profile = chosen["camera"], chosen["profile"]
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc

    try:
        factory = camera_factory(camera)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc

    def progress(done: int, total: int) -> None:
        if done == total:
            typer.echo(f"  downloaded {total / 1e6:.1f} MB", err=True)

    session = TetherSession(
        factory,
        out,
        delete_after_verify=delete_after_verify,
        process=process,
        profile=profile,
        record=record,
        log=lambda m: typer.echo(f"  {m}", err=True),
        progress=progress,
        capture_target=capture_target,
    )
    stop = threading.Event()
    try:
        session.connect()
        earlier = process_unfinished(session) if process else []
        if tethered:
            typer.echo("waiting for shots from the camera's shutter button; Ctrl-C to stop", err=True)
            try:
                results = session.tethered(stop.is_set)
            except KeyboardInterrupt:
                stop.set()
                results = []
        else:
            results = session.capture(count, interval)
        results = earlier + results
        for r in results:
            typer.echo(f"shot {r.shot_id}: {r.status} {r.path or ''} {r.message}".rstrip())
    except TransportError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    finally:
        session.close()
    failed = [r for r in results if r.status in ("failed", "captured")]
    if failed:
        raise typer.Exit(1)


def process_unfinished(session) -> list:
    """Process the shots an earlier run downloaded but did not finish processing (killed, disk full)."""
    results = []
    for row in session.catalog.unprocessed():
        typer.echo(f"  processing {row.file_name} (shot {row.id}), left unprocessed by an earlier run", err=True)
        results.append(session._process(row.id, session.out_dir / row.file_name))
    return results


def register(app: typer.Typer) -> None:
    app.command("capture")(capture)
