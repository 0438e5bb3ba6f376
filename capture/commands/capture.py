"""`mca capture`: take N shots (or download shots taken on the camera) into a folder with a catalog; or live view."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

EXIT_INTERRUPTED = 130


def _summary(session, interrupted: bool) -> int:
    """Print every file of the run, including the ones in flight; return how many did not reach the disk."""
    rows = session.summary_rows()
    problems = 0
    for row in rows:
        status, message = row.status, row.message or ""
        if status == "captured":
            status = "captured (download pending)"
            message = message or "still on the camera's card; the next `mca capture` run fetches it"
        if row.status in ("captured", "failed"):
            problems += 1
        typer.echo(f"shot {row.id}: {status} {row.file_name or row.camera_filename} {message}".rstrip())
    for result in session.results:
        if result.shot_id is None:  # a release the camera refused, or one that made no file
            problems += 1
            typer.echo(f"release: {result.status}: {result.message}".rstrip())
    done = sum(1 for r in rows if r.status in ("downloaded", "processed"))
    typer.echo(
        f"{done} of {len(rows)} file(s) on disk in {session.out_dir}" + (" (interrupted)" if interrupted else ""),
        err=True,
    )
    return problems


def capture(
    camera: str | None = typer.Option(
        None, "--camera", "-c", help="auto, sim, sim:SCENARIO, usb:BUS:ADDR or ptpip:HOST:PORT (default: config, auto)"
    ),
    count: int = typer.Option(1, "--count", "-n", min=1, help="number of shots"),
    interval: float = typer.Option(0.0, "--interval", help="seconds between shot starts"),
    out: Path | None = typer.Option(None, "--out", "-o", help="folder for the files and catalog.sqlite"),
    process: bool = typer.Option(False, "--process", help="run the depth pipeline on each shot"),
    quality: str = typer.Option(
        "full",
        "--quality",
        metavar="full|preview",
        help="with --process: full (the evaluated settings) or preview (faster, for a first look); "
        "--live always shows its own quick preview",
    ),
    profile: str | None = typer.Option(None, "--profile", help="processing profile (default: config, paper-70d)"),
    record: Path | None = typer.Option(None, "--record", help="rerun recording FILE.rrd (--process, --live)"),
    tethered: bool = typer.Option(
        False, "--tethered", help="download shots taken with the camera's shutter button until Ctrl-C"
    ),
    delete_after_verify: bool = typer.Option(
        False, "--delete-after-verify", help="delete each file from the card once verified on disk"
    ),
    capture_target: str = typer.Option("card", "--target", help="card or ram"),
    live: bool = typer.Option(False, "--live", help="live view with a disparity preview in the rerun viewer"),
    frames: int | None = typer.Option(None, "--frames", min=1, help="with --live: stop after this many frames"),
    serve: bool = typer.Option(False, "--serve", help="with --live: stream to a local web viewer (127.0.0.1)"),
) -> None:
    """Capture with a tethered camera; every shot is verified, fsynced and catalogued in OUT/catalog.sqlite."""
    import threading

    from mca.capture.config import ConfigError, fill_from_config
    from mca.capture.tether import TetherError, TetherSession, camera_factory
    from mca.devices.ptp.transport import TransportError

    try:
        chosen = fill_from_config(camera=camera, profile=profile)
        camera, profile = chosen["camera"], chosen["profile"]
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc

    from mca.capture.api import check_quality

    try:
        check_quality(quality)
    except ValueError as exc:
        typer.echo(f"error: --quality: {exc}", err=True)
        raise typer.Exit(2) from exc

    try:
        factory = camera_factory(camera)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc

    if live:
        from mca.capture.live import LiveError, run_live

        if record is None and not serve:
            typer.echo("error: --live needs --record FILE.rrd or --serve (where should the preview go?)", err=True)
            raise typer.Exit(2)
        try:
            stats = run_live(
                factory,
                profile_name=profile,
                record=record,
                serve=serve,
                frames=frames,
                log=lambda m: typer.echo(m, err=True),
            )
        except (LiveError, TetherError, TransportError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from exc
        typer.echo(
            f"live view: {stats.frames} frames of {stats.width_px}x{stats.height_px} px, "
            f"{stats.frames_per_s:.1f} frames/s (preview {stats.preview_ms_median:.1f} ms median)"
        )
        return
    if out is None:
        typer.echo("error: --out DIR is required (the folder for the files and catalog.sqlite)", err=True)
        raise typer.Exit(2)

    def progress(done: int, total: int) -> None:
        if done == total:
            typer.echo(f"  downloaded {total / 1e6:.1f} MB", err=True)

    try:
        session = TetherSession(
            factory,
            out,
            delete_after_verify=delete_after_verify,
            process=process,
            profile=profile,
            quality=quality,
            record=record,
            log=lambda m: typer.echo(f"  {m}", err=True),
            progress=progress,
            capture_target=capture_target,
        )
    except TetherError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    stop = threading.Event()
    interrupted = False
    problems = 0
    try:
        session.connect()
        if process:
            process_unfinished(session)
        if tethered:
            typer.echo("waiting for shots from the camera's shutter button; Ctrl-C to stop", err=True)
            session.tethered(stop.is_set)
        else:
            session.capture(count, interval)
    except KeyboardInterrupt:
        stop.set()
        interrupted = True
        typer.echo("stopping (Ctrl-C)", err=True)
    except (TetherError, TransportError) as exc:
        typer.echo(f"error: {exc}", err=True)
        problems += 1
    finally:
        try:
            problems += _summary(session, interrupted)
        finally:
            session.close()
    if problems:
        raise typer.Exit(1)
    if interrupted and not tethered:
        raise typer.Exit(EXIT_INTERRUPTED)


def process_unfinished(session: Any) -> None:
    """Process the shots an earlier run downloaded but did not finish processing (killed, a full disk): their
    files are on disk, the catalog lists them as downloaded or failed after the download (issue 13)."""
    from mca.capture.tether import RAW_SUFFIXES

    for row in session.catalog.unprocessed():
        path = session.out_dir / row.file_name
        if path.suffix.upper() not in RAW_SUFFIXES:
            continue  # the JPEG of a RAW+JPEG pair is kept, not processed
        typer.echo(f"  processing {row.file_name} (shot {row.id}), left unprocessed by an earlier run", err=True)
        if row.id not in session.shot_ids:
            session.shot_ids.append(row.id)
        session._process(row.id, path)


def register(app: typer.Typer) -> None:
    app.command("capture")(capture)
