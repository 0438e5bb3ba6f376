"""`mca capture`: take N shots (or download shots taken on the camera) into a folder with a catalog; or live view."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

EXIT_INTERRUPTED = 130


def _summary(session, interrupted: bool, err: bool = False) -> int:
    """Print every file of the run, including the ones in flight; return how many did not reach the disk.

    With `err` (`--json`) the lines go to stderr, leaving stdout to the JSON document."""
    rows = session.summary_rows()
    problems = 0
    for row in rows:
        status, message = row.status, row.message or ""
        if status == "captured":
            status = "captured (download pending)"
            message = message or "still on the camera's card; the next `mca capture` run fetches it"
        if row.status in ("captured", "failed"):
            problems += 1
        typer.echo(f"shot {row.id}: {status} {row.file_name or row.camera_filename} {message}".rstrip(), err=err)
    for result in session.results:
        if result.shot_id is None:  # a release the camera refused, or one that made no file
            problems += 1
            typer.echo(f"release: {result.status}: {result.message}".rstrip(), err=err)
    hook = getattr(session, "hook", None)
    for failure in hook.failures if hook is not None else []:
        problems += 1
        typer.echo(f"hook: {failure}", err=err)
    done = sum(1 for r in rows if r.status in ("downloaded", "processed"))
    typer.echo(
        f"{done} of {len(rows)} file(s) on disk in {session.out_dir}" + (" (interrupted)" if interrupted else ""),
        err=True,
    )
    return problems


def shot_line(result: Any) -> str:
    """One line per file as it lands: shot number, file, size, the time it landed and how long the download took."""
    import datetime

    name = result.path.name if result.path is not None else "-"
    size = f"{result.size_bytes / 1e6:.2f} MB" if result.size_bytes is not None else "-"
    took = f" (download {result.download_s:.1f} s)" if result.download_s is not None else ""
    at = datetime.datetime.now().strftime("%H:%M:%S")
    detail = f" {result.message}" if result.message and result.status != "processed" else ""
    if result.status == "processed":
        detail = f" -> {result.message}"
    return f"shot {result.shot_id}: {name}  {size}  at {at}{took}  {result.status}{detail}".rstrip()


class DownloadBar:
    """A download progress bar on stderr (rich), fed by the session's `progress(done, total)` calls."""

    def __init__(self) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

        self._progress = Progress(
            TextColumn("download"),
            BarColumn(),
            DownloadColumn(),
            TransferSpeedColumn(),
            console=Console(stderr=True),
            transient=False,
        )
        self._task: Any = None

    def __call__(self, done: int, total: int) -> None:
        if self._task is None:
            self._progress.start()
            self._task = self._progress.add_task("download", total=total)
        self._progress.update(self._task, completed=done, total=total)
        if done >= total:
            self._progress.stop()
            self._progress.remove_task(self._task)
            self._task = None

    def close(self) -> None:
        if self._task is not None:
            self._progress.stop()
            self._task = None


def capture_document(session: Any, interrupted: bool) -> dict[str, Any]:
    """`mca capture --json`: every file of the run with its catalog row, refused releases, hook failures."""
    from mca.capture.outputs import json_safe

    shots = []
    for row in session.summary_rows():
        path = session.out_dir.resolve() / row.file_name if row.file_name else None
        shots.append(
            {
                "id": row.id,
                "camera_filename": row.camera_filename,
                "file": str(path) if path is not None else None,
                "size_bytes": row.size_bytes,
                "sha256": row.sha256,
                "status": row.status,
                "message": row.message,
                "captured_at": row.captured_at,
                "downloaded_at": row.downloaded_at,
                "processed_at": row.processed_at,
                "result": str(session.out_dir.resolve() / row.result_path) if row.result_path else None,
            }
        )
    hook = getattr(session, "hook", None)
    return json_safe(
        {
            "out_dir": str(session.out_dir.resolve()),
            "catalog": str(session.catalog.path.resolve()),
            "shots": shots,
            "releases": [{"status": r.status, "message": r.message} for r in session.results if r.shot_id is None],
            "hook_failures": [str(f) for f in (hook.failures if hook is not None else [])],
            "on_disk": sum(1 for s in shots if s["status"] in ("downloaded", "processed")),
            "interrupted": interrupted,
        }
    )


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
    import threading

    from mca.capture.config import ConfigError, fill_from_config
    from mca.capture.tether import TetherError, TetherSession
    from mca.devices.cameras import open_camera
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

    from mca.capture.file_names import FilenamePattern, FilenamePatternError
    from mca.capture.hooks import HookScript

    try:
        pattern = FilenamePattern.parse(filename) if filename is not None else None
        hook = HookScript(hook_script) if hook_script is not None else None
    except (FilenamePatternError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    traffic = None
    if debug_logfile is not None:
        from mca.devices.ptp.traffic_log import TrafficLogFile

        try:
            traffic = TrafficLogFile(str(debug_logfile), header=f"mca capture --camera {camera}")
        except OSError as exc:
            typer.echo(f"error: --debug-logfile {debug_logfile}: {exc.strerror or exc}", err=True)
            raise typer.Exit(2) from exc
        ctx.call_on_close(traffic.close)
    try:
        factory = open_camera(camera, traffic_log=traffic.write if traffic is not None else None)
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

    bar = DownloadBar()

    def landed(result: Any) -> None:
        if result.shot_id is not None:
            typer.echo(shot_line(result), err=as_json)

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
            progress=bar,
            capture_target=capture_target,
            filename_pattern=pattern,
            hook=hook,
            on_result=landed,
        )
    except TetherError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    stop = threading.Event()
    interrupted = False
    problems = 0
    hook_started = False
    try:
        if hook is not None:
            failure = hook.run("init")
            if failure is not None:  # as gphoto2: a failing init stops the run before anything is taken
                raise TetherError(f"{failure}; nothing was taken")
            hook_started = True
        session.connect()
        if process:
            process_unfinished(session)
        if hook is not None:
            hook.run("start")
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
        bar.close()
        try:
            if hook is not None and hook_started:
                hook.run("stop")
            problems += _summary(session, interrupted, err=as_json)
            if as_json:
                import json

                typer.echo(json.dumps(capture_document(session, interrupted), indent=2))
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
