"""Tethered shooting: open a camera by name, capture, download safely into a folder, catalog, and reconnect.

Each shot is downloaded to a temporary name, its size checked against the
camera's ObjectInfo, fsynced and renamed; `catalog.sqlite` records it. File
names from the camera are untrusted and sanitised. After a disconnect the
session reconnects and fetches what the catalog says is missing.

The shutter is released once per requested shot and never again by the
session: a release the camera refused is reported (nothing was taken), and a
release whose answer was lost is followed by looking for the new file (on a
reconnected camera too). Only what is safe to repeat is retried. Errors that
end a run are `TetherError`s with a message a user can act on.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import signal
import sqlite3
import stat
import threading
import time
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from mca.capture.catalog import Catalog
from mca.capture.file_names import FilenamePattern
from mca.capture.hooks import HookScript
from mca.capture.memory import keep_freed_memory
from mca.devices.cameras import CameraFactory
from mca.devices.ptp.camera import (
    MAX_OBJECT_BYTES,
    Camera,
    CameraNotReady,
    CapturedObject,
    CaptureError,
    CaptureTicket,
    DeviceBusyError,
    PropertyNotReported,
    PtpError,
    ReleaseRefused,
    ReleaseUncertain,
)
from mca.devices.ptp.codec import ProtocolError
from mca.devices.ptp.codes import ObjectFormat
from mca.devices.ptp.policy import DEFAULT_POLICY, PtpPolicy
from mca.devices.ptp.transport import DeviceDisconnected, TransportError

MAX_FILENAME_CHARS = 100
RETRIES = 6
RAW_SUFFIXES = (".CR2", ".CR3", ".DNG", ".TIF", ".TIFF")


class TetherError(TransportError):
    """A tethered run cannot go on; the message names the camera or folder and what to do.

    A `TransportError`, so callers that stop on link failures (the calibration sweep) stop on these too.
    """


# -- Ctrl-C between two writes that belong together ------------------------
class DeferredInterrupt:
    """Within `with DeferredInterrupt() as d:` a Ctrl-C (SIGINT) is held back until the block ends, then raised
    (`KeyboardInterrupt`, or the handler that was installed); `d.requested` says one arrived, so a wait inside
    can end early. For the few steps that must not be split: a file taken from the camera's event queue and
    its catalog row, a file renamed into place and its row saying so. Outside the main thread it does nothing
    (signals reach only the main thread)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None
        self._active = False

    def __enter__(self) -> DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self._note)
            self._active = True
        return self

    def _note(self, signum: int, frame: Any) -> None:
        self.requested = True

    def __exit__(self, *exc: object) -> None:
        if not self._active:
            return
        signal.signal(signal.SIGINT, self._previous)
        self._active = False
        if self.requested and exc[0] is None:
            if callable(self._previous):
                self._previous(signal.SIGINT, None)
            elif self._previous == signal.SIG_DFL:
                raise KeyboardInterrupt


# -- untrusted names --------------------------------------------------------
_UNSAFE = re.compile(r"[^A-Za-z0-9._+\-]")


def sanitize_filename(name: str, taken: set[str] | None = None) -> str:
    """A safe local file name for a name a camera sent: no separators, no `..`, no control characters.

    Collisions with `taken` (names already used, compared case-insensitively) get a `_N` suffix.
    """
    text = unicodedata.normalize("NFKC", name or "")
    text = text.replace("\\", "/").split("/")[-1]
    text = "".join(ch for ch in text if ch.isprintable())
    text = _UNSAFE.sub("_", text)
    text = re.sub(r"\.{2,}", ".", text).strip(". ")
    if not text:
        text = "shot"
    stem, dot, ext = text.rpartition(".")
    if not dot:
        stem, ext = text, ""
    ext = ext[:10]
    stem = stem[: MAX_FILENAME_CHARS - len(ext) - 8] or "shot"
    candidate = f"{stem}.{ext}" if ext else stem
    lowered = {t.lower() for t in (taken or set())}
    n = 1
    while candidate.lower() in lowered:
        candidate = f"{stem}_{n}.{ext}" if ext else f"{stem}_{n}"
        n += 1
    return candidate


def _safe_target(out_dir: Path, name: str) -> Path:
    target = (out_dir / name).resolve()
    if target.parent != out_dir.resolve():
        raise ValueError(f"refusing to write {name!r} outside {out_dir}")
    return target


# -- the session ------------------------------------------------------------
@dataclass(frozen=True)
class ShotResult:
    """What became of one file: `status` is downloaded, processed, captured (on the card, download pending),
    failed, or refused (the camera took no picture)."""

    shot_id: int | None
    path: Path | None
    status: str
    message: str = ""
    size_bytes: int | None = None  # of the file on disk
    download_s: float | None = None  # how long its download took


class _HashingWriter:
    def __init__(self, fh: Any) -> None:
        self.fh, self.sha, self.size_bytes = fh, hashlib.sha256(), 0

    def write(self, piece: Any) -> int:
        self.fh.write(piece)
        self.sha.update(piece)
        self.size_bytes += len(piece)
        return len(piece)


class TetherSession:
    """Drives one camera for a capture run; survives busy answers, stalls, broken containers and disconnects."""

    def __init__(
        self,
        factory: CameraFactory,
        out_dir: Path,
        *,
        delete_after_verify: bool = False,
        process: bool = False,
        profile: str | None = None,
        quality: str = "full",
        record: Path | None = None,
        log: Callable[[str], None] = lambda msg: None,
        progress: Callable[[int, int], None] | None = None,
        capture_target: str | None = "card",
        policy: PtpPolicy = DEFAULT_POLICY,
        filename_pattern: FilenamePattern | None = None,
        hook: HookScript | None = None,
        on_result: Callable[[ShotResult], None] | None = None,
    ) -> None:
        self.factory = factory
        self.out_dir = Path(out_dir)
        self.policy = policy
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            probe = self.out_dir / ".mca-write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise TetherError(
                f"cannot use {self.out_dir} as the output folder: {exc.strerror or exc}; "
                "choose a folder you can write to with --out"
            ) from exc
        try:
            self.catalog = Catalog(self.out_dir / "catalog.sqlite")
        except (sqlite3.Error, OSError) as exc:
            raise TetherError(
                f"cannot open the catalog {self.out_dir / 'catalog.sqlite'}: {exc}; "
                "move the damaged file aside (the shots next to it are untouched) and run again"
            ) from exc
        self.delete_after_verify = delete_after_verify
        self.process = process
        self.profile = profile
        self.quality = quality  # with `process`: "full" or "preview" (capture.api.QUALITIES)
        self.record = record
        self.log = log
        self.recording_error: str | None = None  # set by close() when the recording could not be written out
        self.progress = progress
        self.capture_target = capture_target
        self.filename_pattern = filename_pattern
        self.hook = hook
        self.on_result = on_result  # told of every file's outcome as it lands (the CLI prints each shot)
        self.camera: Camera | None = None
        self.reconnects = 0
        self.results: list[ShotResult] = []  # every file of this run, in order (also after Ctrl-C)
        self.shot_ids: list[int] = []  # catalog rows made or touched by this run
        self._seen: set[tuple[str, int, bool]] = set()  # (camera file name, handle, in RAM) stored this run
        self._profile_obj: Any = None
        self._recorder: Any = None
        self._release_id: int | None = None  # this run's release in flight (catalog table `releases`)

    # connection ------------------------------------------------------------
    def connect(self) -> Camera:
        last: Exception | None = None
        for attempt in range(self.policy.reconnect_attempts):
            try:
                cam = self.factory()
                if cam.is_eos and self.capture_target:
                    cam.set_property("capturetarget", self.capture_target)
                self.camera = cam
                self.recover_missing()
                return cam
            except (TransportError, ProtocolError, PtpError, PropertyNotReported) as exc:
                last = exc
                self._drop_camera()
                time.sleep(min(2.0, 0.05 * 2**attempt))
        raise TetherError(
            f"could not connect to the camera after {self.policy.reconnect_attempts} attempts: {last}; "
            "check the cable and that the camera is on"
        )

    def _drop_camera(self) -> None:
        if self.camera is not None:
            try:
                self.camera.transport.close()
            except Exception:
                pass
        self.camera = None

    def _cam(self) -> Camera:
        return self.camera if self.camera is not None else self.connect()

    def _live_recorder(self) -> Any:
        """One recording for the whole session (`--record`): every shot on its `shot` timeline."""
        if self.record is None:
            return None
        if self._recorder is None:
            from mca.capture.recording import RerunRecorder

            Path(self.record).parent.mkdir(parents=True, exist_ok=True)
            self._recorder = RerunRecorder(Path(self.record), application_id="mca")
        return self._recorder

    def close(self) -> None:
        """Close the recording, the camera and the catalog. A recording cut short by a full disk is reported
        through `log` and kept in `recording_error` (the shots and the catalog are safe); the rest still closes."""
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            try:
                recorder.close()
            except OSError as exc:  # RecordingWriteError: names the .rrd file and what to do
                self.recording_error = str(exc)
                self.log(f"error: {exc}")
        if self.camera is not None:
            try:
                self.camera.close()
            except Exception:
                pass
            self.camera = None
        self.catalog.close()

    def _retrying(self, what: str, fn: Callable[[Camera], Any]) -> Any:
        """Run `fn(camera)` (something safe to repeat), retrying after busy answers and link faults and
        reconnecting after disconnects. A definite error answer from the camera ends it with `TetherError`."""
        last: Exception | None = None
        for attempt in range(RETRIES):
            cam = self._cam()
            try:
                return fn(cam)
            except DeviceBusyError as exc:
                last = exc
                self.log(f"{what}: camera busy, retrying")
                time.sleep(min(1.0, 0.02 * 2**attempt))
            except PtpError as exc:
                raise TetherError(f"{what}: {exc}") from exc
            except DeviceDisconnected as exc:
                last = exc
                self.log(f"{what}: {exc}; reconnecting")
                self._drop_camera()
                self.reconnects += 1
            except (ProtocolError, TransportError) as exc:
                last = exc
                self.log(f"{what}: {exc}; resetting the link")
                if not cam.transport.can_resume or cam.transport.__class__.__name__ == "PtpIpTransport":
                    self._drop_camera()  # a TCP stream cannot be resynchronised
                    self.reconnects += 1
        raise TetherError(f"{what} failed after {RETRIES} attempts: {last}")

    # shots -----------------------------------------------------------------
    def _trigger(self) -> CaptureTicket:
        """Release the shutter once. Failures before the release are retried; the release itself never is."""
        last: Exception | None = None
        for attempt in range(RETRIES):
            cam = self._cam()
            try:
                return cam.trigger(before_release=self._note_release)
            except (ReleaseRefused, ReleaseUncertain):
                raise
            except CameraNotReady as exc:
                last = exc
                self.log("the camera is busy; waiting before the release")
                time.sleep(min(1.0, 0.05 * 2**attempt))
            except PtpError as exc:
                last = exc
                self.log(f"before the release: {exc}; trying again")
                time.sleep(min(1.0, 0.05 * 2**attempt))
            except DeviceDisconnected as exc:
                last = exc
                self.log(f"before the release: {exc}; reconnecting")
                self._drop_camera()
                self.reconnects += 1
            except (ProtocolError, TransportError) as exc:
                last = exc
                self.log(f"before the release: {exc}; resetting the link")
                if not cam.transport.can_resume or cam.transport.__class__.__name__ == "PtpIpTransport":
                    self._drop_camera()
                    self.reconnects += 1
        raise TetherError(f"could not get the camera ready to shoot: {last}")

    def _note_release(self, ticket: CaptureTicket) -> None:
        """Before the shutter goes: note the release and the card as it is, so that a run killed before the new
        files are catalogued leaves a trace the next connection follows (`_adopt_released`)."""
        if ticket.card_handles is None:
            return  # shots to the camera's RAM: lost with the session, nothing to find on the card later
        try:
            if self._release_id is not None:  # an attempt that stopped before its release
                self.catalog.release_done(self._release_id)
                self._release_id = None
            self._release_id = self.catalog.add_release(ticket.serial_number, ticket.card_handles)
        except sqlite3.Error as exc:
            raise ReleaseRefused(f"not released: the catalog cannot note the release ({exc})") from exc

    def _release_finished(self) -> None:
        if self._release_id is not None:
            self.catalog.release_done(self._release_id)
            self._release_id = None

    def capture(self, count: int = 1, interval_s: float = 0.0) -> list[ShotResult]:
        """Take `count` pictures: one release each; every file a release made is downloaded (RAW+JPEG: both)."""
        results: list[ShotResult] = []
        for i in range(count):
            started = time.monotonic()
            results += self.capture_one()
            if i + 1 < count and interval_s > 0:
                time.sleep(max(0.0, interval_s - (time.monotonic() - started)))
        return results

    def capture_one(self) -> list[ShotResult]:
        try:
            ticket = self._trigger()
        except ReleaseRefused as exc:
            self.log(str(exc))
            self._release_finished()
            return [self._note(ShotResult(None, None, "refused", str(exc)))]
        except ReleaseUncertain as exc:
            self.log(str(exc))
            ticket = exc.ticket
            if self.camera is not None and not self.camera.transport.can_resume:
                self._drop_camera()
        try:
            objects = self._retrying("waiting for the new file", lambda cam: cam.wait_for_capture(ticket))
        except CaptureError as exc:
            self.log(str(exc))  # the release row stays: the next connection looks for what it made
            return [self._note(ShotResult(None, None, "failed", str(exc)))]
        with DeferredInterrupt():  # the files the release made and their catalog rows, with no Ctrl-C between
            catalogued = [(obj, self._catalogue(obj)) for obj in objects]
            catalogued += self._catalogue_unclaimed()
            self._release_finished()
        return [self._note(self._fetch(shot_id, obj)) for obj, shot_id in catalogued if shot_id is not None]

    def _catalogue_unclaimed(self) -> list[tuple[CapturedObject, int | None]]:
        """Files that appeared without our release (the camera's own shutter button) are kept too."""
        cam = self.camera
        out = []
        while cam is not None and cam.unclaimed:
            obj = cam.unclaimed.pop(0)
            out.append((obj, self._catalogue(obj)))
        return out

    def tethered(self, stop: Callable[[], bool], *, max_shots: int | None = None) -> list[ShotResult]:
        """Download each shot taken with the camera's own shutter button until `stop()` (or `max_shots`)."""
        results: list[ShotResult] = []
        while not stop() and (max_shots is None or len(results) < max_shots):
            # a file taken from the camera's event queue gets its catalog row before a Ctrl-C is let through
            with DeferredInterrupt() as held:
                obj = self._retrying(
                    "waiting for a shot", lambda cam: cam.wait_for_object(0.5, stop=lambda: stop() or held.requested)
                )
                shot_id = self._catalogue(obj) if obj is not None else None
            if obj is not None and shot_id is not None:
                results.append(self._note(self._fetch(shot_id, obj)))
        return results

    def _note(self, result: ShotResult) -> ShotResult:
        self.results.append(result)
        if self.on_result is not None:
            self.on_result(result)
        return result

    def _catalogue(self, obj: CapturedObject) -> int | None:
        """The catalog row of a new file (None: this run has it already)."""
        key = (obj.filename, obj.handle, obj.in_ram)
        if key in self._seen:
            return None
        self._seen.add(key)
        serial = self._cam().serial_number
        shot_id = self.catalog.add_captured(serial, obj.filename, obj.handle, obj.size_bytes)
        self.shot_ids.append(shot_id)
        return shot_id

    def _fetch(self, shot_id: int, obj: CapturedObject) -> ShotResult:
        started = time.monotonic()
        try:
            path = self._retrying(f"download of {obj.filename}", lambda cam: self._download(cam, shot_id, obj))
        except (TetherError, ValueError, OSError) as exc:
            message = _describe(exc, self.out_dir)
            if not obj.in_ram:  # the file is still on the card: the next run (or reconnect) fetches it
                self.catalog.note(shot_id, f"download pending: {message}")
                return ShotResult(shot_id, None, "captured", f"still on the camera's card: {message}")
            self.catalog.mark_failed(shot_id, message)
            return ShotResult(shot_id, None, "failed", message)
        took_s = time.monotonic() - started
        size = path.stat().st_size if path.is_file() else None
        if not self._run_hook(shot_id, path):
            return ShotResult(shot_id, path, "downloaded", "the hook script moved or deleted it", size, took_s)
        if self.process and self.catalog.get(shot_id).status == "downloaded" and _is_raw(path):
            return replace(self._process(shot_id, path), size_bytes=size, download_s=took_s)
        return ShotResult(shot_id, path, "downloaded", "", size, took_s)

    def _run_hook(self, shot_id: int, path: Path) -> bool:
        """Run `--hook-script` with ACTION=download for a stored file; False when the file is gone after it."""
        if self.hook is None:
            return True
        failure = self.hook.run(
            "download",
            str(path),
            {"MCA_SHOT_ID": str(shot_id), "MCA_CATALOG": str(self.catalog.path), "MCA_OUT_DIR": str(self.out_dir)},
        )
        if failure is not None:
            self.log(str(failure))
        if path.is_file():
            return True
        from mca.capture.hooks import HookFailure

        gone = HookFailure("download", str(path), "the file is no longer there after the hook ran (moved or deleted)")
        self.hook.failures.append(gone)
        self.log(str(gone))
        return False

    def _download(self, cam: Camera, shot_id: int, obj: CapturedObject) -> Path:
        row = self.catalog.get(shot_id)
        if row.status != "captured" and row.file_name:  # a reconnect already fetched it
            return self.out_dir / row.file_name
        handle = obj.handle
        if obj.in_ram:
            expected = obj.size_bytes
        else:
            handle = self._find_on_card(cam, obj)
            expected = cam.object_info(handle).compressed_size_bytes
        if not 0 < expected <= MAX_OBJECT_BYTES:
            raise ValueError(
                f"{cam.name} reports {expected} bytes for {obj.filename!r}; refusing (limit {MAX_OBJECT_BYTES})"
            )
        wanted = obj.filename
        if self.filename_pattern is not None:
            wanted = self.filename_pattern.name_for(shot_id, obj.filename)
        listed = self.catalog.file_names()
        orphan = _unlisted_file(self.out_dir, sanitize_filename(wanted, listed), expected)
        name = sanitize_filename(wanted, listed | set(os.listdir(self.out_dir)))
        final = _safe_target(self.out_dir, name)
        tmp = _safe_target(self.out_dir, f".{name}.part")
        renamed = False
        with contextlib.ExitStack() as held:
            try:
                with open(tmp, "wb") as fh:
                    writer = _HashingWriter(fh)
                    cam.download(handle, expected, writer, progress=self.progress)  # type: ignore[arg-type]
                    fh.flush()
                    os.fsync(fh.fileno())
                if writer.size_bytes != expected or tmp.stat().st_size != expected:
                    raise ProtocolError(
                        f"{cam.name} sent {writer.size_bytes} bytes for {obj.filename!r}, ObjectInfo says {expected}"
                    )
                held.enter_context(DeferredInterrupt())  # the file in place and its row saying so: not split
                if orphan is not None and _sha256_file(orphan) == writer.sha.hexdigest():
                    # a run killed (kill -9) after renaming this very file into place and before its row said so:
                    # the file is this shot's, byte for byte; it takes its row, and no second copy is kept
                    tmp.unlink()
                    final, name = orphan, orphan.name
                else:
                    os.replace(tmp, final)
                renamed = True
            finally:
                if not renamed:
                    tmp.unlink(missing_ok=True)  # a full disk or a failed link leaves no .part behind
            dir_fd = os.open(self.out_dir, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
            digest = writer.sha.hexdigest()
            self.catalog.mark_downloaded(shot_id, name, expected, digest)
        if obj.in_ram:
            cam.transfer_complete(handle)
        elif self.delete_after_verify and _sha256_file(final) == digest:
            cam.delete(handle)
        return final

    def _find_on_card(self, cam: Camera, obj: CapturedObject) -> int:
        """The handle of the shot now (handles may change across reconnects): by handle, else by file name."""
        try:
            info = cam.object_info(obj.handle)
            if info.filename == obj.filename:
                return obj.handle
        except PtpError:
            pass
        for handle, info in cam.files():
            if info.filename == obj.filename and info.object_format != ObjectFormat.ASSOCIATION:
                return handle
        raise ValueError(f"{obj.filename!r} is no longer on the camera's card")

    def recover_missing(self) -> list[ShotResult]:
        """After (re)connecting: download every shot the catalog says was captured but never reached the disk."""
        cam = self.camera
        if cam is None:
            return []
        self._adopt_released(cam)
        results = []
        for row in self.catalog.missing(cam.serial_number):
            obj = CapturedObject(row.camera_handle or 0, row.camera_filename, row.size_bytes or 0, 0, 0, False)
            self.log(f"fetching {row.camera_filename} (shot {row.id}) that an earlier run left on the card")
            if row.id not in self.shot_ids:
                self.shot_ids.append(row.id)
            self._seen.add((obj.filename, obj.handle, False))
            results.append(self._note(self._fetch(row.id, obj)))
        return results

    def _adopt_released(self, cam: Camera) -> None:
        """Catalog the files of releases an earlier run made but never catalogued (killed or interrupted between
        the release and the catalog row): files on the card that were not there before such a release and that
        the catalog does not know. `recover_missing` then downloads them like any other pending shot."""
        pending = [
            (rid, before) for rid, before in self.catalog.pending_releases(cam.serial_number) if rid != self._release_id
        ]
        if not pending:
            return
        card = [(h, info) for h, info in cam.files() if info.object_format != ObjectFormat.ASSOCIATION]
        for release_id, before in pending:
            for handle, info in card:
                if handle in before or self.catalog.has_camera_file(cam.serial_number, info.filename):
                    continue
                self.log(f"cataloguing {info.filename}: released by an earlier run that stopped before noting it")
                self.catalog.add_captured(cam.serial_number, info.filename, handle, info.compressed_size_bytes)
            self.catalog.release_done(release_id)

    def _process(self, shot_id: int, path: Path) -> ShotResult:
        try:
            from mca.capture import pipeline_app
            from mca.devices.profiles import DEFAULT_PROFILE, load_profile
        except ImportError as exc:
            msg = f"not processed: the processing pipeline is not available ({exc})"
            self.catalog.note(shot_id, msg)
            return ShotResult(shot_id, path, "downloaded", msg)
        try:
            if self._profile_obj is None:
                self._profile_obj = load_profile(self.profile or DEFAULT_PROFILE)
            outcome = pipeline_app.process_file(
                path,
                self.out_dir,
                self._profile_obj,
                recorder=self._live_recorder(),
                shot_index=shot_id,
                quality=self.quality,
            )
        except Exception as exc:
            outcome = None
            reason = f"processing failed: {exc}"
        else:
            reason = getattr(outcome, "reason", None) or ""
        keep_freed_memory()  # the next shot reuses this one's memory (capture/memory.py)
        if outcome is None or getattr(outcome, "status", "done") == "failed":
            msg = reason if reason.startswith("processing failed") else f"processing failed: {reason}"
            self.catalog.mark_failed(shot_id, msg)
            return ShotResult(shot_id, path, "failed", msg)
        result_path = str(getattr(outcome, "output_dir", outcome))
        self.catalog.mark_processed(shot_id, result_path)
        return ShotResult(shot_id, path, "processed", result_path)

    # the run's summary -----------------------------------------------------
    def summary_rows(self) -> list[Any]:
        """The catalog rows of this run, including shots still in flight (captured, not yet on disk)."""
        out = []
        for shot_id in self.shot_ids:
            try:
                out.append(self.catalog.get(shot_id))
            except KeyError:
                continue
        return out


def _is_raw(path: Path) -> bool:
    return path.suffix.upper() in RAW_SUFFIXES


def _describe(exc: BaseException, out_dir: Path) -> str:
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return f"the disk holding {out_dir} is full; free space and run again (the file stays on the card)"
    if isinstance(exc, OSError) and exc.errno in (errno.EACCES, errno.EROFS, errno.EPERM):
        return f"cannot write into {out_dir}: {exc.strerror}"
    return str(exc)


def _unlisted_file(out_dir: Path, name: str, size_bytes: int) -> Path | None:
    """`out_dir/name` when it is a regular file of `size_bytes` (a shot's download that lost its catalog row: the
    caller compares the bytes), else None. `name` is one the catalog does not list."""
    try:
        found = os.lstat(out_dir / name)  # not followed: a link is not a download
    except OSError:
        return None
    if not stat.S_ISREG(found.st_mode) or found.st_size != size_bytes:
        return None
    return _safe_target(out_dir, name)


def _sha256_file(path: Path) -> str:
    sha = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            sha.update(block)
    return sha.hexdigest()
