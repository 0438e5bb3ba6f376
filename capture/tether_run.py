"""The application side of `mca capture` and `mca demo`: a tethered run from an open session to its summary.

The hook script's init/start/stop around the shots, the shots an earlier run left unprocessed, one line per
file as it lands, the summary of every file (including the ones in flight) and the `--json` document.
"""

from __future__ import annotations

import datetime
import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

Say = Callable[[str], None]


def _quiet(text: str) -> None:
    return None


def shot_line(result: Any) -> str:
    """One line per file as it lands: shot number, file, size, the time it landed and how long the download took."""
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


@dataclass
class RunSummary:
    """Every file of a run as lines, how many did not reach the disk (or failed), and the closing count line."""

    lines: list[str] = field(default_factory=list)
    problems: int = 0
    footer: str = ""


def run_summary(session: Any, interrupted: bool) -> RunSummary:
    """Every file of the run, including the ones in flight, refused releases and hook failures."""
    summary = RunSummary()
    rows = session.summary_rows()
    for row in rows:
        status, message = row.status, row.message or ""
        if status == "captured":
            status = "captured (download pending)"
            message = message or "still on the camera's card; the next `mca capture` run fetches it"
        if row.status in ("captured", "failed"):
            summary.problems += 1
        summary.lines.append(f"shot {row.id}: {status} {row.file_name or row.camera_filename} {message}".rstrip())
    for result in session.results:
        if result.shot_id is None:  # a release the camera refused, or one that made no file
            summary.problems += 1
            summary.lines.append(f"release: {result.status}: {result.message}".rstrip())
    hook = getattr(session, "hook", None)
    for failure in hook.failures if hook is not None else []:
        summary.problems += 1
        summary.lines.append(f"hook: {failure}")
    done = sum(1 for r in rows if r.status in ("downloaded", "processed"))
    summary.footer = f"{done} of {len(rows)} file(s) on disk in {session.out_dir}" + (
        " (interrupted)" if interrupted else ""
    )
    return summary


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


def process_unfinished(session: Any, log: Say = _quiet) -> None:
    """Process the shots an earlier run downloaded but did not finish processing (killed, a full disk): their
    files are on disk, the catalog lists them as downloaded or failed after the download (issue 13)."""
    from mca.capture.tether import RAW_SUFFIXES

    for row in session.catalog.unprocessed():
        path = session.out_dir / row.file_name
        if path.suffix.upper() not in RAW_SUFFIXES:
            continue  # the JPEG of a RAW+JPEG pair is kept, not processed
        log(f"  processing {row.file_name} (shot {row.id}), left unprocessed by an earlier run")
        if row.id not in session.shot_ids:
            session.shot_ids.append(row.id)
        session._process(row.id, path)


class CaptureSetupError(ValueError):
    """Options of `mca capture` that cannot make a run (bad config, quality, file-name pattern, hook, camera)."""


@dataclass
class CaptureSetup:
    """`mca capture`'s options checked: the camera (and its traffic log), profile, file-name pattern, hook script."""

    camera: Any  # a `capture.camera_app.CameraChoice`
    profile: str
    pattern: Any = None  # a `FilenamePattern`, or None for the camera's names
    hook: Any = None  # a `HookScript`, or None


def prepare_capture(
    camera: str | None = None,
    profile: str | None = None,
    *,
    quality: str = "full",
    filename: str | None = None,
    hook_script: Path | None = None,
    debug_logfile: Path | None = None,
) -> CaptureSetup:
    """Fill camera and profile from the config and check every option before the camera is opened.

    Raises `CaptureSetupError` naming the option or file at fault."""
    from mca.capture.api import check_quality
    from mca.capture.camera_app import CameraSetupError, choose_camera
    from mca.capture.config import ConfigError, fill_from_config
    from mca.capture.file_names import FilenamePattern, FilenamePatternError
    from mca.capture.hooks import HookScript

    try:
        chosen = fill_from_config(camera=camera, profile=profile)
    except ConfigError as exc:
        raise CaptureSetupError(str(exc)) from exc
    try:
        check_quality(quality)
    except ValueError as exc:
        raise CaptureSetupError(f"--quality: {exc}") from exc
    try:
        pattern = FilenamePattern.parse(filename) if filename is not None else None
        hook = HookScript(hook_script) if hook_script is not None else None
        choice = choose_camera(chosen["camera"], debug_logfile, "mca capture")
    except (FilenamePatternError, ValueError, CameraSetupError) as exc:
        raise CaptureSetupError(str(exc)) from exc
    return CaptureSetup(choice, str(chosen["profile"]), pattern, hook)


@dataclass(frozen=True)
class CaptureOptions:
    """What a run does once connected: `count` shots `interval_s` apart, or shots from the shutter button."""

    count: int = 1
    interval_s: float = 0.0
    tethered: bool = False  # download shots taken with the camera's button until Ctrl-C
    process: bool = False  # also process what an earlier run left unprocessed


@dataclass
class RunOutcome:
    """How a run ended: interrupted (Ctrl-C), or the error that stopped it (None: it ran to the end)."""

    interrupted: bool = False
    error: str | None = None


def run_capture(session: Any, hook: Any, options: CaptureOptions, log: Say = _quiet) -> RunOutcome:
    """Connect and shoot as `options` say, with the hook script's init, start and stop around it.

    A failing init stops the run before anything is taken (as gphoto2 does); Ctrl-C ends it as interrupted;
    a camera or transport error ends it with the error; the hook's stop runs whenever its init did. The
    session stays open: its files, catalog and summary are the caller's to report, then to close."""
    from mca.capture.tether import TetherError
    from mca.devices.ptp.transport import TransportError

    stop = threading.Event()
    outcome = RunOutcome()
    hook_started = False
    try:
        if hook is not None:
            failure = hook.run("init")
            if failure is not None:
                raise TetherError(f"{failure}; nothing was taken")
            hook_started = True
        session.connect()
        if options.process:
            process_unfinished(session, log)
        if hook is not None:
            hook.run("start")
        if options.tethered:
            log("waiting for shots from the camera's shutter button; Ctrl-C to stop")
            session.tethered(stop.is_set)
        else:
            session.capture(options.count, options.interval_s)
    except KeyboardInterrupt:
        stop.set()
        outcome.interrupted = True
        log("stopping (Ctrl-C)")
    except (TetherError, TransportError) as exc:
        outcome.error = str(exc)
    finally:
        if hook is not None and hook_started:
            hook.run("stop")
    return outcome


def capture_json(session: Any, interrupted: bool) -> str:
    """`capture_document` as indented JSON text."""
    return json.dumps(capture_document(session, interrupted), indent=2)


# --- mca demo -------------------------------------------------------------------------------------------------------


def demo_camera(spec: str, size: str = "full") -> tuple[Callable[[], Any], str]:
    """The camera factory of `mca demo` and what it is: `auto` is a USB camera if one is found, else the simulated
    EOS 70D photographing the paper's Fig. 4 scenes at `size` (full, small, or a scale)."""
    from mca.devices.cameras import make_sim_rig, open_camera
    from mca.devices.sim.world import scene_frame_source

    if spec == "auto":
        try:
            from mca.devices.ptp.transport_usb import find_cameras

            spec = "auto" if find_cameras() else "sim"
        except Exception:
            spec = "sim"
    if spec != "sim":
        return open_camera(spec), f"camera: {spec}"
    try:
        size_value: str | float = float(size)
    except ValueError:
        size_value = size
    factory = open_camera("sim", rig=make_sim_rig(scene_frame_source(size_value)))
    return factory, f"camera: simulated Canon EOS 70D ({size} frames of the paper's Fig. 4 scenes)"


def result_summary(result_dir: str | Path) -> list[str]:
    """A processed shot's regions (order, disparity, distance, focus, slant) and its processing time, as lines."""
    result_file = Path(result_dir) / "result.json"
    if not result_file.exists():
        return [f"    no result.json in {result_dir}"]
    result = json.loads(result_file.read_text())
    lines = []
    for region in sorted(result.get("regions", []), key=lambda r: r.get("order", 0)):
        distance = region.get("distance_mm")
        depth = region.get("inter_object_depth_mm")
        where = (
            f"{distance:8.1f} mm from the lens ({depth:+7.1f} mm from focus)"
            if distance is not None and depth is not None
            else "distance unknown"
        )
        slant = " slanted" if region.get("slant") else ""
        focus = " in focus" if region.get("id") == result.get("focus_region") else ""
        lines.append(
            f"    region {region['id']:2d} order {region['order']}: disparity {region['disparity_px']:+6.2f} px, "
            f"{where}{focus}{slant}"
        )
    timings = result.get("timings_s", {})
    # the pipeline's stages are also summed in its "total" and in "pipeline": count each second once
    whole = [timings[k] for k in ("read", "pipeline", "write") if k in timings]
    total = sum(whole) if "pipeline" in timings else sum(timings.values())
    lines.append(f"    processed in {total:.2f} s")
    return lines


def open_demo_session(factory: Callable[[], Any], out: Path, profile: str, log: Say = _quiet) -> Any:
    """The session of `mca demo`: shots and results into `out/shots`, each processed, recorded into
    `out/demo.rrd`. Raises `TetherError` when it cannot start (e.g. the folder cannot be made)."""
    from mca.capture.tether import TetherSession

    return TetherSession(
        factory, out / "shots", process=True, profile=profile, record=out / "demo.rrd", log=lambda m: log(f"  {m}")
    )


def shoot(session: Any, count: int) -> list[Any]:
    """Connect, take `count` shots, close; returns the `ShotResult`s (`TetherError`/`TransportError` if the
    camera stops answering; the session is closed either way)."""
    try:
        session.connect()
        return list(session.capture(count, 0.0))
    finally:
        session.close()
