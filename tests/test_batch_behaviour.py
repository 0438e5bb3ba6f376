"""Batches and watch mode, behaviour the README promises: `--workers N` runs N worker processes, watch mode
takes a file only once it is complete (not empty, not still growing) and again once re-shot, a bad file never
stops a batch, Ctrl-C keeps what finished, discovery passes over what is not a photograph and says why.
The depth pipeline is the stand-in of test_process (fast); what is checked is the batch machinery.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from test_process import fake_pipeline, make_png, make_tiff

from mca.capture import batch
from mca.capture.batch import BatchError, LineProgress, Task, discover, make_runner, print_summary, run_batch
from mca.capture.read_ahead import stat_key
from mca.devices.profiles import load_profile

PROFILE = load_profile("paper-70d")


def pid_pipeline(planes, aperture, optics, **options):
    """The stand-in pipeline, leaving a file named after the process that ran it (MCA_TEST_PIDS folder)."""
    folder = Path(os.environ["MCA_TEST_PIDS"])
    (folder / f"{os.getpid()}-{time.monotonic_ns()}").touch()
    time.sleep(0.4)  # long enough that the pool hands the next file to another worker
    return fake_pipeline(planes, aperture, optics, **options)


def interrupting_pipeline(planes, aperture, optics, **options):
    """Ctrl-C during the second file."""
    interrupting_pipeline.calls += 1  # type: ignore[attr-defined]
    if interrupting_pipeline.calls == 2:  # type: ignore[attr-defined]
        raise KeyboardInterrupt
    return fake_pipeline(planes, aperture, optics, **options)


def inputs(folder: Path, count: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        make_png(folder / f"shot{i}.png", 24, 32)
    return folder


def test_workers_n_runs_the_files_in_n_other_processes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pids = tmp_path / "pids"
    pids.mkdir()
    monkeypatch.setenv("MCA_TEST_PIDS", str(pids))
    report = run_batch([inputs(tmp_path / "in", 4)], tmp_path / "out", PROFILE, workers=2, pipeline=pid_pipeline)
    assert [o.status for o in report.outcomes] == ["done"] * 4, [o.reason for o in report.outcomes]
    seen = {int(p.name.split("-")[0]) for p in pids.iterdir()}
    assert len(list(pids.iterdir())) == 4
    assert len(seen) == 2 and os.getpid() not in seen
    # one worker: all in this process
    for p in pids.iterdir():
        p.unlink()
    run_batch([tmp_path / "in"], tmp_path / "out1", PROFILE, workers=1, pipeline=pid_pipeline)
    assert {int(p.name.split("-")[0]) for p in pids.iterdir()} == {os.getpid()}


def test_make_runner_picks_the_runner_for_the_options(tmp_path: Path) -> None:
    inline = make_runner(tmp_path, PROFILE, workers=1)
    assert isinstance(inline, batch.InlineRunner) and inline.capacity == 1
    pool = make_runner(tmp_path, PROFILE, workers=3)
    try:
        assert isinstance(pool, batch.PoolRunner) and pool.capacity == 3
    finally:
        pool.close()
    with pytest.raises(BatchError, match="--workers must be at least 1, got 0"):
        make_runner(tmp_path, PROFILE, workers=0)


def test_a_file_is_stable_only_when_complete_and_unchanged_for_the_settle_time(tmp_path: Path) -> None:
    def stable(path: Path, seen: dict[Path, tuple[int, int, float]], settle_s: float) -> bool:
        return batch._stable(path, stat_key(path), seen, settle_s)  # as the watch loop calls it: one stat a look

    path = tmp_path / "a.png"
    seen: dict[Path, tuple[int, int, float]] = {}
    assert not stable(tmp_path / "missing.png", seen, 0.0)
    path.write_bytes(b"")
    assert not stable(path, seen, 0.0)  # first look: remembered
    assert not stable(path, seen, 0.0)  # empty: never complete
    path.write_bytes(b"12345")
    assert not stable(path, seen, 0.0)  # changed since the last look
    assert stable(path, seen, 0.0)
    assert not stable(path, seen, 3600.0)  # not yet settled for an hour
    path.write_bytes(b"123456")
    assert not stable(path, seen, 0.0)
    seen[path] = (seen[path][0], seen[path][1], seen[path][2] - 5.0)  # looked at 5 s ago, unchanged since
    assert stable(path, seen, 5.0)
    assert not stable(path, {path: (6, path.stat().st_mtime_ns, time.monotonic())}, 5.0)


def _watch_while(folder: Path, out: Path, writer: Callable[[threading.Event], None], sink: Callable[[str], None]):
    """`run_batch --watch` on `folder` (quick polls, 0.3 s settle, stops 2 s after the last activity) while
    `writer(done_once)` changes it on a thread; `done_once` is set when the first file has finished."""
    done_once = threading.Event()

    class Progress(LineProgress):
        def finished(self, task, outcome):
            super().finished(task, outcome)
            done_once.set()

    thread = threading.Thread(target=writer, args=(done_once,))
    thread.start()
    report = run_batch(
        [folder],
        out,
        PROFILE,
        watch=True,
        watch_timeout_s=2.0,
        poll_interval_s=0.1,
        settle_s=0.3,
        pipeline=fake_pipeline,
        progress=Progress(sink),
    )
    thread.join()
    return report


def _after(event: threading.Event) -> None:
    """Until `event` is set (30 s at most), and a little longer."""
    deadline = time.monotonic() + 30
    while not event.is_set() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.2)


def test_watch_takes_an_empty_file_only_once_it_is_written_and_a_reshot_file_again(tmp_path: Path) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    late = folder / "late.png"
    late.write_bytes(b"")  # the camera created the file; its bytes come later
    lines: list[str] = []

    def writer(done_once: threading.Event) -> None:
        time.sleep(0.8)
        make_png(tmp_path / "staging.png", 24, 32)
        os.replace(tmp_path / "staging.png", late)
        _after(done_once)
        make_tiff(tmp_path / "staging.tiff", 20, 28)  # re-shot: new content under the same name
        os.replace(tmp_path / "staging.tiff", late)

    report = _watch_while(folder, tmp_path / "out", writer, lines.append)
    statuses = [o.status for o in report.outcomes]
    assert statuses == ["done", "done"], [o.reason for o in report.outcomes]
    assert all(o.input_path.name == "late.png" for o in report.outcomes)
    assert not report.interrupted
    assert lines[0].startswith("[1/1] done    late.png")


def test_watch_takes_a_file_replaced_by_one_of_the_same_size_and_time_again(tmp_path: Path) -> None:
    """A re-shot file that keeps the old one's size and modification time (a copy tool that preserves times) is
    still another file: it is taken again by its inode, as the read-ahead tells files apart."""
    folder = tmp_path / "in"
    folder.mkdir()
    shot = make_tiff(folder / "shot.tiff", 20, 28)
    kept: list[tuple[int, int]] = []

    def writer(done_once: threading.Event) -> None:
        _after(done_once)
        old = shot.stat()
        kept.append((old.st_size, old.st_mtime_ns))
        data = bytearray(shot.read_bytes())
        data[-1] ^= 0xFF  # the last pixel's last byte: the same size, other content
        staging = tmp_path / "staging.tiff"
        staging.write_bytes(bytes(data))
        os.utime(staging, ns=(old.st_atime_ns, old.st_mtime_ns))
        os.replace(staging, shot)

    report = _watch_while(folder, tmp_path / "out", writer, lambda line: None)
    assert [o.status for o in report.outcomes] == ["done", "done"], [o.reason for o in report.outcomes]
    now = shot.stat()
    assert kept == [(now.st_size, now.st_mtime_ns)]  # the case meant: size and time as they were


def test_a_bad_file_fails_with_its_reason_and_the_batch_goes_on(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    folder = inputs(tmp_path / "in", 2)
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 20)
    lines: list[str] = []
    report = run_batch([folder], tmp_path / "out", PROFILE, pipeline=fake_pipeline, progress=LineProgress(lines.append))
    assert sorted(o.status for o in report.outcomes) == ["done", "done", "failed"]
    (failed,) = report.failed
    assert failed.input_path.name == "broken.png" and "broken.png" in failed.reason
    assert report.count("done") == 2 and report.count("failed") == 1 and report.count("skipped") == 0
    assert len(lines) == 3 and all(line.startswith(("[1/3]", "[2/3]", "[3/3]")) for line in lines)
    assert any(" failed  broken.png" in line and "broken.png:" in line for line in lines)
    assert any(" done    shot0.png" in line and "2 regions" in line for line in lines)
    print_summary(report)
    out, err = capsys.readouterr()
    assert "2 done, 0 skipped, 1 failed" in out
    assert "failed files:" in err and failed.reason in err
    # a second run: the finished files are skipped as finished (not as passed over), the bad one fails again
    again = run_batch([folder], tmp_path / "out", PROFILE, pipeline=fake_pipeline)
    assert sorted(o.status for o in again.outcomes) == ["failed", "skipped", "skipped"]
    print_summary(again)
    out, err = capsys.readouterr()
    assert "skipped files (not taken as photographs)" not in err


def test_ctrl_c_keeps_what_finished_and_lists_the_rest(tmp_path: Path) -> None:
    folder = inputs(tmp_path / "in", 3)
    interrupting_pipeline.calls = 0  # type: ignore[attr-defined]
    report = run_batch([folder], tmp_path / "out", PROFILE, pipeline=interrupting_pipeline)
    assert report.interrupted
    assert [o.status for o in report.outcomes] == ["done", "failed", "failed"]
    assert all("interrupted (Ctrl-C)" in o.reason for o in report.outcomes[1:])
    assert {o.input_path.name for o in report.outcomes[1:]} == {"shot1.png", "shot2.png"}


def test_batches_that_cannot_start_say_why(tmp_path: Path) -> None:
    with pytest.raises(BatchError, match=r"no such file or folder: .*nowhere; check the path"):
        run_batch([tmp_path / "nowhere"], tmp_path / "out", PROFILE)
    (tmp_path / "empty").mkdir()
    with pytest.raises(BatchError, match=r"no input files found in .*empty; give files or folders holding"):
        run_batch([tmp_path / "empty"], tmp_path / "out", PROFILE)
    with pytest.raises(BatchError, match="live recorder"):
        run_batch([tmp_path / "empty"], tmp_path / "out", PROFILE, workers=2, recorder=object())
    (tmp_path / "file").write_text("x")
    with pytest.raises(BatchError):
        run_batch([tmp_path / "empty"], tmp_path / "file" / "out", PROFILE)
    # watch mode on an empty folder waits, then stops after the timeout without error
    report = run_batch(
        [tmp_path / "empty"], tmp_path / "out", PROFILE, watch=True, watch_timeout_s=0.3, poll_interval_s=0.05
    )
    assert report.outcomes == []


def test_discovery_passes_over_what_is_not_a_photograph_and_says_why(tmp_path: Path) -> None:
    folder = inputs(tmp_path / "in", 2)
    (folder / ".hidden.png").write_bytes(b"x")
    (folder / "notes.txt").write_text("x")
    os.mkfifo(folder / "pipe.png")
    (folder / "dir.png").mkdir()
    (folder / "dangling.png").symlink_to(folder / "missing.png")
    (folder / "loop.png").symlink_to(folder / "loop.png")
    (folder / "again.png").symlink_to(folder / "shot0.png")  # the same file twice: taken once
    truth = tmp_path / "sim" / "truth"
    truth.mkdir(parents=True)
    make_png(truth / "depth.png", 8, 8)
    found = discover([folder, folder / "shot1.png", truth, truth / "depth.png", tmp_path / "explicit.txt"])
    assert [p.name for p in found.inputs] == ["again.png", "shot1.png", "explicit.txt"]
    reasons = {p.name: r for p, r in found.skipped}
    assert "a FIFO (named pipe)" in reasons["pipe.png"]
    assert "a folder" in reasons["dir.png"]
    assert "symbolic link to a missing file" in reasons["dangling.png"]
    assert "loops back on itself" in reasons["loop.png"]
    assert "ground truth" in reasons["truth"] and "ground truth" in reasons["depth.png"]
    assert all(str(p) in r for p, r in found.skipped)
    assert batch.discover_inputs([folder]) == found.inputs[:2]


def test_files_sharing_a_name_get_their_own_folders(tmp_path: Path) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    make_png(folder / "a.png", 24, 32)
    make_tiff(folder / "a.tiff", 24, 32)
    report = run_batch([folder], tmp_path / "out", PROFILE, workers=2, pipeline=fake_pipeline)
    assert sorted(o.output_dir.name for o in report.outcomes) == ["a", "a-2"]
    assert all((o.output_dir / "result.json").is_file() for o in report.outcomes)
    assert batch.assign_name(folder / "a b?.png") == batch.assign_name(folder / "a b?.tiff")


def test_tasks_keep_their_recording_place(tmp_path: Path) -> None:
    task = Task(tmp_path / "x.png", "x", tmp_path / "x" / "recording.rrd", shot_index=3, recording_id="r")
    assert batch._key(task) == "3-x"
    failed = batch.runner_failed(tmp_path, task, "why")
    assert failed.status == "failed" and failed.reason == f"{tmp_path / 'x.png'}: why"


def test_defaults_and_values(tmp_path: Path) -> None:
    from dataclasses import FrozenInstanceError

    from mca.capture.pipeline_app import FileOutcome

    assert isinstance(make_runner(tmp_path, PROFILE), batch.InlineRunner)  # one worker unless asked
    task = Task(tmp_path / "x.png", "x")
    with pytest.raises(FrozenInstanceError):
        task.out_name = "y"  # type: ignore[misc]
    lines: list[str] = []
    progress = LineProgress(lines.append)
    progress.finished(task, FileOutcome(task.input_path, "done", tmp_path, 1.25, regions=3))
    assert lines == ["[1/0] done    x.png 1.2 s 3 regions"]  # nothing discovered yet: a total of 0
