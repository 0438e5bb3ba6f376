"""A recording that cannot be written out (a full disk) ends with an error naming the file and what to do.

Three disks: a fake one (rerun's file writer failing as it does when the disk fills: the stream's
flush raises, the disk has no space left), /dev/full (every write fails with ENOSPC: rerun cannot
even write the file's header), and, when this process may make a mount namespace, a real 300 kB
tmpfs that fills up while a shot is being recorded.
"""

from __future__ import annotations

import errno
import os
import shutil
import sqlite3
import subprocess
import sys
import textwrap
from collections import namedtuple
from datetime import datetime
from pathlib import Path

import pytest
from test_recording import PROFILE, RERUN

import mca.capture.recording.recorder as recorder_module
from mca.capture.recording import RecordingWriteError, RerunRecorder

pytestmark = pytest.mark.skipif(RERUN is None, reason="the rerun CLI of rerun-sdk is not installed")

DiskUsage = namedtuple("DiskUsage", "total used free")


class FailingStream:
    """The recorder's stream, with `flush` failing as rerun's does once its file writer has given up."""

    def __init__(self, stream: object, failure: BaseException) -> None:
        self._stream, self._failure = stream, failure

    def flush(self, *args: object, **kwargs: object) -> None:
        raise self._failure

    def __getattr__(self, name: str) -> object:
        return getattr(self._stream, name)


def assert_clear(error: RecordingWriteError, path: Path) -> None:
    message = str(error)
    assert message.startswith(f"{path}: the recording could not be written completely")
    assert "full" in message and "Free some space and run again" in message
    assert "Traceback" not in message and "shut down prematurely" not in message
    assert error.errno == errno.ENOSPC and error.filename == str(path)  # the application's full-disk handlers see it


@pytest.mark.parametrize(
    "failure",
    [
        RuntimeError("File-writer thread shut down prematurely"),  # what rerun 0.41 raises on a full disk
        OSError(errno.ENOSPC, "No space left on device"),
    ],
    ids=["rerun-writer-gave-up", "write-enospc"],
)
def test_close_on_a_full_disk_names_the_file_and_what_to_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: BaseException
) -> None:
    path = tmp_path / "shots" / "all.rrd"
    recorder = RerunRecorder(path)
    recorder.begin_shot(0, "full", datetime(2024, 1, 1), PROFILE)
    real_usage = shutil.disk_usage
    monkeypatch.setattr(
        recorder_module.shutil,
        "disk_usage",
        lambda folder: DiskUsage(1 << 30, 1 << 30, 0) if Path(folder) == path.parent else real_usage(folder),
    )
    recorder._stream = FailingStream(recorder._stream, failure)  # type: ignore[assignment]
    with pytest.raises(RecordingWriteError) as caught:
        recorder.close()
    assert_clear(caught.value, path)
    assert "0 bytes free" in str(caught.value)
    recorder.close()  # closing again is a no-op, not a second error


def test_a_writer_failure_on_a_disk_with_room_is_not_called_a_full_disk(tmp_path: Path) -> None:
    path = tmp_path / "x.rrd"
    recorder = RerunRecorder(path)
    recorder._stream = FailingStream(recorder._stream, RuntimeError("File-writer thread shut down prematurely"))  # type: ignore[assignment]
    with pytest.raises(RecordingWriteError) as caught:
        recorder.close()
    message = str(caught.value)
    assert message.startswith(f"{path}: the recording could not be written completely (File-writer thread")
    assert "full" not in message and "writable" in message and caught.value.errno == errno.EIO


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full on this system")
def test_a_recording_on_dev_full_fails_at_once_with_the_clear_error() -> None:
    with pytest.raises(RecordingWriteError) as caught:
        RerunRecorder(Path("/dev/full"))
    assert_clear(caught.value, Path("/dev/full"))


def test_the_application_reports_it_as_a_full_disk(tmp_path: Path) -> None:
    from mca.capture.pipeline_app import user_message

    error = RecordingWriteError.from_failure(tmp_path / "a.rrd", OSError(errno.ENOSPC, "No space left on device"))
    message = user_message(tmp_path / "IMG_1.CR2", error)
    assert "disk is full" in message and str(tmp_path / "a.rrd") in message and "Free some space" in message


def test_a_tether_session_reports_the_cut_recording_and_still_closes(tmp_path: Path) -> None:
    """`mca capture --record` on a full disk: the message, no traceback; the catalog is closed all the same."""
    from mca.capture.tether import TetherSession

    logged: list[str] = []
    session = TetherSession(lambda: None, tmp_path / "out", log=logged.append, record=tmp_path / "out" / "s.rrd")
    recorder = session._live_recorder()
    recorder._stream = FailingStream(recorder._stream, OSError(errno.ENOSPC, "No space left on device"))
    session.close()
    assert session.recording_error is not None and session.recording_error.startswith(str(tmp_path / "out" / "s.rrd"))
    assert logged == [f"error: {session.recording_error}"]
    with pytest.raises(sqlite3.ProgrammingError):  # the catalog was closed
        session.catalog.rows()


REAL_DISK = textwrap.dedent(
    """
    import subprocess, sys
    from datetime import datetime
    from pathlib import Path
    sys.path.insert(0, sys.argv[2])
    from test_recording import PROFILE, synthetic_result
    from mca.capture.recording import RecordingWriteError, RerunRecorder
    from mca.processing.optics import MCAOptics

    folder = Path(sys.argv[1])
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(folder)], check=True)
    optics = MCAOptics.from_profile(PROFILE)
    recorder = RerunRecorder(folder / "big.rrd")
    try:
        for shot in range(6):
            recorder.begin_shot(shot, f"shot{shot}", datetime(2024, 1, 1), PROFILE)
            recorder.log_result(synthetic_result(300, 400, optics), PROFILE, optics)
        recorder.close()
        print("CLOSED WITHOUT ERROR")
    except RecordingWriteError as exc:
        print("ERRNO", exc.errno)
        print("MESSAGE", exc)
    """
)


def test_a_real_disk_filling_up_while_recording(tmp_path: Path) -> None:
    unshare = shutil.which("unshare")
    if unshare is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare(1) to mount a small tmpfs in a namespace of its own")
    folder = tmp_path / "disk"
    folder.mkdir()
    done = subprocess.run(
        [unshare, "-m", sys.executable, "-c", REAL_DISK, str(folder), str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if "Operation not permitted" in done.stderr or "mount:" in done.stderr:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()[-200:]}")
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"ERRNO {errno.ENOSPC}" in done.stdout, done.stdout + done.stderr[-2000:]
    message = done.stdout.split("MESSAGE ", 1)[1].strip()
    assert message.startswith(f"{folder / 'big.rrd'}: the recording could not be written completely: the disk")
    assert "Free some space and run again" in message
