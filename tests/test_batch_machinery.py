"""The batch machinery with the stand-in pipeline of test_process (tiny inputs, no depth processing): stage progress
from this process and from pool workers, the worker thread share, a Dask cluster in this process, the rich display,
the summary's lists, what the merged recording is made of, and files passed over while watching.
"""

from __future__ import annotations

import io
import os
import threading
from pathlib import Path

import pytest
from test_process import fake_pipeline, make_png

from mca.capture import batch
from mca.capture.batch import BatchError, BatchReport, Task, make_runner, print_summary, run_batch
from mca.capture.pipeline_app import FileOutcome
from mca.devices.profiles import load_profile

PROFILE = load_profile("paper-70d")
BROKEN_PNG = b"\x89PNG\r\n\x1a\n" + b"\0" * 20


class StageLog:
    """A progress display that keeps everything it hears."""

    wants_stages = True

    def __init__(self) -> None:
        self.stages: list[tuple[str, str]] = []
        self.totals: list[int] = []
        self.began: list[str] = []
        self.finished_files: list[tuple[str, str]] = []
        self.closed = False

    def discovered(self, total: int) -> None:
        self.totals.append(total)

    def started(self, task: Task) -> None:
        self.began.append(task.input_path.name)

    def stage(self, task: Task, stage: str) -> None:
        self.stages.append((task.input_path.name, stage))

    def finished(self, task: Task, outcome: FileOutcome) -> None:
        self.finished_files.append((task.input_path.name, outcome.status))

    def close(self) -> None:
        self.closed = True


def folder_of(tmp_path: Path, count: int, broken: bool = False) -> Path:
    folder = tmp_path / "in"
    folder.mkdir(exist_ok=True)
    for i in range(count):
        make_png(folder / f"s{i}.png", 24, 32)
    if broken:
        (folder / "broken.png").write_bytes(BROKEN_PNG)
    return folder


# --------------------------------------------------------------------------- stages and runners


@pytest.mark.parametrize("workers", [1, 2])
def test_every_file_reports_its_stages_in_order_from_wherever_it_runs(tmp_path: Path, workers: int) -> None:
    log = StageLog()
    report = run_batch(
        [folder_of(tmp_path, 2, broken=True)],
        tmp_path / "out",
        PROFILE,
        workers=workers,
        pipeline=fake_pipeline,
        progress=log,
    )
    assert sorted((o.input_path.name, o.status) for o in report.outcomes) == [
        ("broken.png", "failed"),
        ("s0.png", "done"),
        ("s1.png", "done"),
    ]
    assert sorted(log.finished_files) == sorted((o.input_path.name, o.status) for o in report.outcomes)
    for name in ("s0.png", "s1.png"):
        assert [s for n, s in log.stages if n == name] == ["read", "disparity", "write"]
    assert not [s for n, s in log.stages if n == "broken.png" and s != "read"]  # it never got past reading
    assert log.totals[-1] == 3 and log.closed


def test_a_display_without_stages_hears_none(tmp_path: Path) -> None:
    heard: list[str] = []

    class Quiet(StageLog):
        wants_stages = False

        def stage(self, task: Task, stage: str) -> None:
            heard.append(stage)

    for workers in (1,):  # a pool without a stage queue: test_waiting_on_the_pool_...[False]
        report = run_batch(
            [folder_of(tmp_path, 1)],
            tmp_path / f"out{workers}",
            PROFILE,
            workers=workers,
            pipeline=fake_pipeline,
            progress=Quiet(),
        )
        assert [o.status for o in report.outcomes] == ["done"], [o.reason for o in report.outcomes]
    assert heard == []


def test_the_inline_runner_runs_in_submission_order_and_cancels_what_waits(tmp_path: Path) -> None:
    folder = folder_of(tmp_path, 3)
    runner = make_runner(tmp_path / "out", PROFILE, workers=1, pipeline=fake_pipeline)
    tasks = [Task(folder / f"s{i}.png", f"s{i}", shot_index=i) for i in range(3)]
    assert runner.wait(0.1) == []  # nothing submitted
    for task in tasks:
        runner.submit(task)
    (first, outcome), *rest = runner.wait(0.1)
    assert first is tasks[0] and rest == [] and outcome.status == "done"
    assert runner.cancel() == tasks[1:]
    assert runner.wait(0.1) == []


def test_the_worker_thread_share_can_be_set_in_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from mca.capture.threads import threads_per_worker

    monkeypatch.delenv("MCA_WORKER_THREADS", raising=False)
    assert batch.worker_threads(2) == threads_per_worker(2)
    for given, expected in (("3", 3), (" 5 ", 5), ("0", None), ("-2", None)):
        monkeypatch.setenv("MCA_WORKER_THREADS", given)
        assert batch.worker_threads(2) == expected
    monkeypatch.setenv("MCA_WORKER_THREADS", "many")
    with pytest.raises(BatchError, match=r"MCA_WORKER_THREADS='many': give a whole number of threads \(0: no limit\)"):
        batch.worker_threads(2)


class LiveRecorder:
    """Stands in for a live viewer's recorder: keeps the calls process_file makes."""

    def __init__(self) -> None:
        self.shots: list[tuple[int, str]] = []
        self.results = 0

    def begin_shot(self, index: int, name: str, capture_time: object, profile: object) -> None:
        self.shots.append((index, name))

    def log_input(self, frame: object) -> None: ...

    def record(self, stage: str, **items: object) -> None: ...

    def timing(self, stage: str, seconds: float) -> None: ...

    def log_result(self, result: object, profile: object, optics: object) -> None:
        self.results += 1


def test_a_live_recorder_receives_every_shot_in_order(tmp_path: Path) -> None:
    recorder = LiveRecorder()
    report = run_batch([folder_of(tmp_path, 3)], tmp_path / "out", PROFILE, recorder=recorder, pipeline=fake_pipeline)
    assert [o.status for o in report.outcomes] == ["done"] * 3
    assert recorder.shots == [(0, "s0"), (1, "s1"), (2, "s2")] and recorder.results == 3


@pytest.mark.parametrize("hears_stages", [False, True])
def test_waiting_on_the_pool_returns_once_a_file_finishes(tmp_path: Path, hears_stages: bool) -> None:
    """`wait(timeout)` returns the finished files as soon as there are some, not an empty list while one runs."""
    folder = folder_of(tmp_path, 1)
    heard: list[str] = []
    on_stage = (lambda task, stage: heard.append(stage)) if hears_stages else None
    runner = make_runner(tmp_path / "out", PROFILE, workers=2, pipeline=fake_pipeline, on_stage=on_stage)
    try:
        runner.submit(Task(folder / "s0.png", "s0"))
        finished = runner.wait(60.0)
        assert [(t.out_name, o.status) for t, o in finished] == [("s0", "done")]
        assert heard == (["read", "disparity", "write"] if hears_stages else [])
        # a task that raises in its worker (an input that is not a path) is that file's failure, with the error
        runner.submit(Task(None, "none", shot_index=1))  # type: ignore[arg-type]
        ((task, outcome),) = runner.wait(60.0)
        assert task.out_name == "none" and outcome.status == "failed" and "Error" in (outcome.reason or "")
        assert runner.wait(0.1) == []
    finally:
        runner.close()


# --------------------------------------------------------------------------- a Dask cluster in this process


def test_a_dask_cluster_runs_the_batch_and_a_bad_file_fails_alone(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed", reason="dask[distributed] is the 'cluster' extra")
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None
    ) as cluster:
        runner = make_runner(tmp_path / "o", PROFILE, cluster=cluster.scheduler_address)
        try:
            assert isinstance(runner, batch.DaskRunner) and runner.capacity == 2  # twice its one thread
        finally:
            runner.close()
        report = run_batch(
            [folder_of(tmp_path, 3, broken=True)],
            tmp_path / "out",
            PROFILE,
            cluster=cluster.scheduler_address,
            pipeline=fake_pipeline,
        )
    statuses = sorted((o.input_path.name, o.status) for o in report.outcomes)
    assert statuses == [("broken.png", "failed"), ("s0.png", "done"), ("s1.png", "done"), ("s2.png", "done")]
    assert all((tmp_path / "out" / f"s{i}" / "result.json").is_file() for i in range(3))


RELEASE = threading.Event()  # the Dask worker runs in this process: the pipeline waits for the test


def held_pipeline(planes, aperture, optics, **options):
    """The stand-in pipeline, held until the test sets RELEASE."""
    RELEASE.wait(60)
    return fake_pipeline(planes, aperture, optics, **options)


def test_waiting_on_a_dask_cluster_returns_nothing_until_a_file_finishes(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed", reason="dask[distributed] is the 'cluster' extra")
    folder = folder_of(tmp_path, 1)
    RELEASE.clear()
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None
    ) as cluster:
        runner = make_runner(tmp_path / "out", PROFILE, cluster=cluster.scheduler_address, pipeline=held_pipeline)
        try:
            assert runner.wait(0.05) == []  # nothing submitted
            runner.submit(Task(folder / "s0.png", "s0"))
            assert runner.wait(0.2) == []  # running, held: nothing finished within the timeout
            RELEASE.set()
            finished: list = []
            for _ in range(600):
                finished += runner.wait(0.1)
                if finished:
                    break
            assert [(t.out_name, o.status) for t, o in finished] == [("s0", "done")]
        finally:
            RELEASE.set()
            runner.close()


def test_an_unreachable_dask_scheduler_is_a_batch_error_with_advice(tmp_path: Path) -> None:
    pytest.importorskip("distributed", reason="dask[distributed] is the 'cluster' extra")
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    job = batch._Job(tmp_path, PROFILE, False, fake_pipeline)
    with pytest.raises(BatchError, match=rf"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}.*dask scheduler"):
        batch.DaskRunner(job, f"tcp://127.0.0.1:{port}", connect_timeout_s=0.5)


# --------------------------------------------------------------------------- displays and the summary


def test_the_rich_display_counts_every_file_and_prints_the_failures(tmp_path: Path) -> None:
    from rich.console import Console

    out = io.StringIO()
    advanced: dict[str, float] = {}

    class Display(batch.RichProgress):
        def finished(self, task: Task, outcome: FileOutcome) -> None:
            row = self.rows.get(task)
            if row is not None:  # how far the file's row got before it is removed
                advanced[task.input_path.name] = next(t.completed for t in self.bar.tasks if t.id == row)
            super().finished(task, outcome)

    display = Display(Console(file=out, width=200, force_terminal=False))
    report = run_batch(
        [folder_of(tmp_path, 2, broken=True)], tmp_path / "out", PROFILE, pipeline=fake_pipeline, progress=display
    )
    overall = display.bar.tasks[0]
    assert (overall.total, overall.completed) == (3, 3)
    assert display.rows == {}  # every file's row removed when it finished
    assert advanced == {"s0.png": 3, "s1.png": 3, "broken.png": 0}  # one step per stage heard
    (failed,) = report.failed
    assert "failed" in out.getvalue() and failed.reason is not None
    assert "broken.png" in out.getvalue()


def test_the_summary_lists_passed_over_and_failed_files_with_their_reasons(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    folder = folder_of(tmp_path, 1, broken=True)
    os.mkfifo(folder / "pipe.png")
    log = StageLog()
    report = run_batch([folder], tmp_path / "out", PROFILE, pipeline=fake_pipeline, progress=log)
    assert sorted((o.input_path.name, o.status) for o in report.outcomes) == [
        ("broken.png", "failed"),
        ("pipe.png", "skipped"),
        ("s0.png", "done"),
    ]
    assert ("pipe.png", "skipped") in log.finished_files and log.totals[-1] == 3
    print_summary(report)
    out, err = capsys.readouterr()
    assert "1 done, 1 skipped, 1 failed" in out and "stopped by Ctrl-C" not in out
    assert all(column in out for column in ("file", "status", "seconds", "regions", "output"))
    (row,) = [line for line in out.splitlines() if "s0.png" in line]  # one row per file: status, regions, folder
    assert "done" in row and " 2 " in row and str(tmp_path / "out" / "s0") in row
    (row,) = [line for line in out.splitlines() if "pipe.png" in line]
    assert "skipped" in row
    passed, failed = err.split("failed files:")
    assert "skipped files (not taken as photographs):" in passed and "a FIFO (named pipe)" in passed
    assert "broken.png" in failed and "pipe.png" not in failed
    interrupted = BatchReport(outcomes=[], recording=tmp_path / "all.rrd", interrupted=True)
    print_summary(interrupted)
    out, err = capsys.readouterr()
    assert "0 done, 0 skipped, 0 failed (stopped by Ctrl-C)" in out and f"recording: {tmp_path / 'all.rrd'}" in out
    assert err == ""
    from rich.console import Console  # on a terminal: the counts and the recording's path print unstyled, to copy

    terminal = io.StringIO()
    print_summary(interrupted, Console(file=terminal, force_terminal=True, width=200, color_system="standard"))
    lines = terminal.getvalue().splitlines()
    assert f"recording: {tmp_path / 'all.rrd'}" in lines and "0 done, 0 skipped, 0 failed (stopped by Ctrl-C)" in lines


def test_watch_passes_over_a_new_non_photograph_once(tmp_path: Path) -> None:
    """A FIFO appearing in a watched folder is reported once as skipped, not at every look."""
    folder = folder_of(tmp_path, 1)
    os.mkfifo(folder / "pipe.png")
    report = run_batch(
        [folder],
        tmp_path / "out",
        PROFILE,
        watch=True,
        watch_timeout_s=0.6,
        poll_interval_s=0.05,
        settle_s=0.1,
        pipeline=fake_pipeline,
    )
    assert sorted((o.input_path.name, o.status) for o in report.outcomes) == [
        ("pipe.png", "skipped"),
        ("s0.png", "done"),
    ]


# --------------------------------------------------------------------------- what the merged recording is made of


@pytest.fixture()
def merges(monkeypatch: pytest.MonkeyPatch) -> list[tuple[list[Path], Path]]:
    """Stands in for the rerun merge: records what it was asked to merge and writes the parts' bytes, in order."""
    import mca.capture.recording as recording

    calls: list[tuple[list[Path], Path]] = []

    def merge(paths: list[Path], out_path: Path) -> None:
        calls.append((list(paths), out_path))
        out_path.write_bytes(b"".join(p.read_bytes() for p in paths))

    monkeypatch.setattr(recording, "merge_recordings", merge)
    return calls


def _shot(tmp_path: Path, parts: Path, index: int, status: str) -> tuple[Task, FileOutcome]:
    name = f"f{index}"
    task = Task(tmp_path / f"{name}.png", name, parts / f"{index:06d}-{name}.rrd", shot_index=index)
    if status == "done":
        task.record_path.parent.mkdir(parents=True, exist_ok=True)  # type: ignore[union-attr]
        task.record_path.write_bytes(f"<{name}>".encode())  # type: ignore[union-attr]
    return task, FileOutcome(task.input_path, status, tmp_path / "out" / name, reason=None)


def test_the_shots_done_are_merged_in_shot_order_and_the_parts_removed(tmp_path: Path, merges: list) -> None:
    parts = tmp_path / "out" / ".mca-recording-parts-x"
    shots = [_shot(tmp_path, parts, i, s) for i, s in [(2, "done"), (0, "done"), (1, "failed"), (3, "done")]]
    tasks, outcomes = [t for t, _ in shots], [o for _, o in shots]
    merged = batch.merge_batch_recordings(tasks, outcomes, tmp_path / "rec" / "all.rrd", parts)
    assert merged == tmp_path / "rec" / "all.rrd"
    assert [p.name for p in merges[0][0]] == ["000000-f0.rrd", "000002-f2.rrd", "000003-f3.rrd"]
    assert merged.read_bytes() == b"<f0><f2><f3>"
    assert not parts.exists()


def test_one_shot_is_its_own_recording(tmp_path: Path, merges: list) -> None:
    parts = tmp_path / "out" / ".mca-recording-parts-x"
    task, outcome = _shot(tmp_path, parts, 0, "done")
    merged = batch.merge_batch_recordings([task], [outcome], tmp_path / "all.rrd", parts)
    assert merged is not None and merged.read_bytes() == b"<f0>" and merges == [] and not parts.exists()


def test_shots_skipped_as_finished_come_from_the_earlier_recording(tmp_path: Path, merges: list) -> None:
    parts = tmp_path / "out" / ".mca-recording-parts-x"
    out_path = tmp_path / "all.rrd"
    out_path.write_bytes(b"<earlier>")
    new, new_outcome = _shot(tmp_path, parts, 1, "done")
    old, old_outcome = _shot(tmp_path, parts, 0, "skipped")
    batch.merge_batch_recordings([old, new], [old_outcome, new_outcome], out_path, parts)
    assert [p.name for p in merges[0][0]] == ["all.rrd", "000001-f1.rrd"]
    assert out_path.read_bytes() == b"<earlier><f1>"
    # no earlier merged file: the result folders' own recordings (an older layout), by folder name
    out_path.unlink()
    merges.clear()
    for name in ("f0", "f9"):
        (tmp_path / "out" / name).mkdir(parents=True, exist_ok=True)
        (tmp_path / "out" / name / "recording.rrd").write_bytes(f"[{name}]".encode())
    old9, old9_outcome = _shot(tmp_path, parts, 9, "skipped")
    newer, newer_outcome = _shot(tmp_path, parts, 1, "done")
    batch.merge_batch_recordings([old9, old, newer], [old9_outcome, old_outcome, newer_outcome], out_path, parts)
    assert out_path.read_bytes() == b"[f0][f9]<f1>"


def test_files_passed_over_do_not_bring_back_an_earlier_recording(tmp_path: Path, merges: list) -> None:
    """Only shots skipped as finished come from the earlier recording: a FIFO passed over is no such shot."""
    parts = tmp_path / "out" / ".mca-recording-parts-x"
    out_path = tmp_path / "all.rrd"
    out_path.write_bytes(b"<earlier>")
    task, outcome = _shot(tmp_path, parts, 0, "done")
    fifo = FileOutcome(tmp_path / "pipe.png", "skipped", tmp_path / "out", reason="a FIFO; skipped")
    batch.merge_batch_recordings([task], [fifo, outcome], out_path, parts)
    assert out_path.read_bytes() == b"<f0>" and merges == []


def test_nothing_to_merge_writes_nothing(tmp_path: Path, merges: list) -> None:
    parts = tmp_path / "out" / ".mca-recording-parts-x"
    task, outcome = _shot(tmp_path, parts, 0, "failed")
    parts.mkdir(parents=True)
    (parts / "000000-f0.rrd").write_bytes(b"half")  # the part of a file that failed
    assert batch.merge_batch_recordings([task], [outcome], tmp_path / "all.rrd", parts) is None
    assert not parts.exists() and not (tmp_path / "all.rrd").exists() and merges == []


def test_a_merge_that_fails_keeps_the_parts_and_names_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import mca.capture.recording as recording

    def broken(paths: list[Path], out_path: Path) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(recording, "merge_recordings", broken)
    parts = tmp_path / "out" / ".mca-recording-parts-x"
    shots = [_shot(tmp_path, parts, i, "done") for i in range(2)]
    with pytest.raises(BatchError, match=rf"cannot write the recording .*all.rrd: disk full; .*kept in {parts}"):
        batch.merge_batch_recordings([t for t, _ in shots], [o for _, o in shots], tmp_path / "all.rrd", parts)
    assert sorted(p.name for p in parts.iterdir()) == ["000000-f0.rrd", "000001-f1.rrd"]


def test_a_batch_with_record_hands_its_parts_to_the_merge(tmp_path: Path, merges: list) -> None:
    """run_batch gives every file a part in one hidden folder, in shot order, and a failed merge is reported, not
    raised: the results stay."""
    pytest.importorskip("rerun")
    folder = folder_of(tmp_path, 2, broken=True)
    record = tmp_path / "all.rrd"
    report = run_batch([folder], tmp_path / "out", PROFILE, record=record, pipeline=fake_pipeline)
    assert report.recording == record and report.recording_error is None
    ((paths, out_path),) = merges
    assert out_path == record and [p.name.split("-", 1)[1] for p in paths] == ["s0.rrd", "s1.rrd"]
    assert len({p.parent for p in paths}) == 1 and paths[0].parent.name.startswith(".mca-recording-parts-")
    assert not paths[0].parent.exists()
    assert batch.batch_recording_id(record) == batch.batch_recording_id(tmp_path / "." / "all.rrd")
