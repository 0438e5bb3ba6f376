"""`mca capture`: take N shots (or download shots taken on the camera) into a folder with a catalog; or live view.

The run itself is `capture.tether_run` (hook script, unfinished shots, summary, JSON); live view is
`capture.live.run_live`; this module parses the options and prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

EXIT_INTERRUPTED = 130


def capture(
    ctx: typer.Context,
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
    filename: str | None = typer.Option(
        None,
        "--filename",
        metavar="PATTERN",
        help="local file names as in gphoto2: %n shot number (%04n padded), %f camera name, %C suffix, "
        "%Y%m%d-%H%M%S date and time; e.g. 'bench-%04n.%C'",
    ),
    hook_script: Path | None = typer.Option(
        None,
        "--hook-script",
        metavar="FILE",
        help="run FILE as gphoto2 does: ACTION=init|start|download|stop, ARGUMENT=the downloaded file",
    ),
    debug_logfile: Path | None = typer.Option(
        None, "--debug-logfile", metavar="FILE", help="append every PTP transaction and event to FILE"
    ),
    as_json: bool = typer.Option(False, "--json", help="print the run's files as JSON (stdout); lines go to stderr"),
) -> None:
    """Capture with a tethered camera; every shot is verified, fsynced and catalogued in OUT/catalog.sqlite."""
    from mca.capture.tether_run import CaptureOptions, CaptureSetupError, prepare_capture

    try:
        setup = prepare_capture(
            camera,
            profile,
            quality=quality,
            filename=filename,
            hook_script=hook_script,
            debug_logfile=debug_logfile,
        )
    except CaptureSetupError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    if setup.camera.traffic is not None:
        ctx.call_on_close(setup.camera.traffic.close)
    if live:
        _live(setup.camera.factory, setup.profile, record, serve, frames)
        return
    if out is None:
        typer.echo("error: --out DIR is required (the folder for the files and catalog.sqlite)", err=True)
        raise typer.Exit(2)
    session = dict(process=process, profile=setup.profile, quality=quality, record=record, hook=setup.hook)
    session.update(delete_after_verify=delete_after_verify, capture_target=capture_target)
    session.update(filename_pattern=setup.pattern)
    run = CaptureOptions(count=count, interval_s=interval, tethered=tethered, process=process)
    _shoot(setup.camera.factory, out, session, run, as_json)


def _say(text: str) -> None:
    typer.echo(text, err=True)


def _live(factory: Any, profile: str, record: Path | None, serve: bool, frames: int | None) -> None:
    from mca.capture.live import LiveError, run_live
    from mca.capture.tether import TetherError, TransportError

    if record is None and not serve:
        typer.echo("error: --live needs --record FILE.rrd or --serve (where should the preview go?)", err=True)
        raise typer.Exit(2)
    try:
        stats = run_live(factory, profile_name=profile, record=record, serve=serve, frames=frames, log=_say)
    except (LiveError, TetherError, TransportError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    typer.echo(
        f"live view: {stats.frames} frames of {stats.width_px}x{stats.height_px} px, "
        f"{stats.frames_per_s:.1f} frames/s (preview {stats.preview_ms_median:.1f} ms median)"
    )


def _shoot(factory: Any, out: Path, options: dict[str, Any], run: Any, as_json: bool) -> None:
    """The run itself: one line per file as it lands, then the summary (and the JSON document)."""
    from mca.capture.tether import TetherError, TetherSession
    from mca.capture.tether_run import DownloadBar, capture_json, run_capture, run_summary, shot_line

    bar = DownloadBar()

    def landed(result: Any) -> None:
        if result.shot_id is not None:
            typer.echo(shot_line(result), err=as_json)

    try:
        session = TetherSession(factory, out, log=lambda m: _say(f"  {m}"), progress=bar, on_result=landed, **options)
    except TetherError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    try:
        try:
            outcome = run_capture(session, options["hook"], run, log=_say)
        finally:
            bar.close()
        if outcome.error is not None:
            typer.echo(f"error: {outcome.error}", err=True)
        summary = run_summary(session, outcome.interrupted)
        for line in summary.lines:
            typer.echo(line, err=as_json)
        typer.echo(summary.footer, err=True)
        if as_json:
            typer.echo(capture_json(session, outcome.interrupted))
    finally:
        session.close()
    if summary.problems or outcome.error is not None:
        raise typer.Exit(1)
    if outcome.interrupted and not run.tethered:
        raise typer.Exit(EXIT_INTERRUPTED)


def register(app: typer.Typer) -> None:
    app.command("capture")(capture)
