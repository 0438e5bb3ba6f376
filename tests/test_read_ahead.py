"""The next photograph of a one-worker batch is read while this one is processed (`capture.read_ahead`): the batch
gets the same planes, files and failures as without it, and a file changed after its read is read again."""

from __future__ import annotations

import hashlib
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_process import fake_pipeline, make_cr2, make_png

from mca.capture import batch
from mca.capture.api import read_input
from mca.capture.raw import RawReadError, read_policy
from mca.capture.read_ahead import ReadAhead
from mca.devices.profiles import load_profile

PROFILE = load_profile("paper-70d")


class RecordingReader:
    """`read_input` that notes which file it read on which thread."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str]] = []

    def __call__(self, path: Path):
        self.calls.append((path.name, threading.current_thread().name))
        return read_input(path)


def test_the_file_read_ahead_is_handed_over_once_read_on_the_helper_thread(tmp_path: Path) -> None:
    path = make_png(tmp_path / "a.png")
    reader = RecordingReader()
    ahead = ReadAhead(reader)
    ahead.start(path)
    loaded = ahead.read(path)
    assert reader.calls == [("a.png", "mca-read-ahead")]
    assert ahead.used == 1
    np.testing.assert_array_equal(loaded.planes, read_input(path).planes)
    ahead.read(path)  # handed over once: the next read is the caller's own
    assert reader.calls[-1] == ("a.png", threading.current_thread().name)


def test_another_file_is_read_by_the_caller(tmp_path: Path) -> None:
    first, second = make_png(tmp_path / "a.png"), make_png(tmp_path / "b.png", 40, 56)
    reader = RecordingReader()
    ahead = ReadAhead(reader)
    ahead.start(first)
    assert ahead.read(second).planes.shape[:2] == (40, 56)
    assert reader.calls[-1] == ("b.png", threading.current_thread().name)
    assert ahead.used == 0


def test_a_file_changed_after_its_read_is_read_again(tmp_path: Path) -> None:
    path = make_png(tmp_path / "a.png", 48, 64)
    ahead = ReadAhead()
    ahead.start(path)
    ahead._slot.thread.join()  # the read is done, then the photograph is taken again under the same name
    make_png(path, 40, 56)
    os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))  # a later mtime even on a coarse clock
    assert ahead.read(path).planes.shape[:2] == (40, 56)
    assert ahead.used == 0


def test_a_failed_read_ahead_gives_the_callers_own_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.CR2"
    path.write_bytes(b"II*\0" + b"\0" * 64)
    ahead = ReadAhead()
    ahead.start(path)
    with pytest.raises(RawReadError, match=r"broken\.CR2"), read_policy(photograph=True):
        ahead.read(path)


def test_the_read_ahead_honours_the_batch_pixel_limit(tmp_path: Path) -> None:
    path = make_cr2(tmp_path / "a.CR2")  # 64 x 96 = 0.006 MP
    ahead = ReadAhead()
    ahead.start(path, max_megapixels=0.001)
    ahead._slot.thread.join()
    assert ahead._slot.failed  # refused on the helper thread as the batch would refuse it
    with pytest.raises(RawReadError, match="over the limit"), read_policy(max_megapixels=0.001, photograph=True):
        ahead.read(path)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_is_never_read_ahead(tmp_path: Path) -> None:
    fifo = tmp_path / "shot.png"
    os.mkfifo(fifo)
    ahead = ReadAhead()
    ahead.start(fifo)  # would block for ever on a FIFO nobody writes to
    assert ahead._slot is None


def _sha(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != "result.json"
    }


def _run_inline(files: list[Path], out: Path, pipeline, read_ahead: bool = True) -> tuple[list, int]:
    job = batch._Job(out_root=out, profile=PROFILE, force=False, pipeline=pipeline)
    runner = batch.InlineRunner(job)
    if not read_ahead:
        runner.read_ahead.start = lambda *args, **kwargs: None  # type: ignore[method-assign]
    for f in files:
        runner.submit(batch.Task(input_path=f, out_name=f.stem))
    outcomes = []
    while runner.queue:
        outcomes += [o for _, o in runner.wait(0.0)]
    runner.close()
    return outcomes, runner.read_ahead.used


def test_a_batch_with_read_ahead_writes_what_it_writes_without(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    files = [make_png(tmp_path / "in" / f"shot{i}.png", 48 + 8 * i, 64) for i in range(3)]
    ahead, used = _run_inline(files, tmp_path / "ahead", fake_pipeline)
    plain, unused = _run_inline(files, tmp_path / "plain", fake_pipeline, read_ahead=False)
    assert [o.status for o in ahead] == [o.status for o in plain] == ["done"] * 3
    assert (used, unused) == (2, 0)  # the second and third files came from the read-ahead
    for a, p in zip(ahead, plain, strict=True):
        assert _sha(a.output_dir) == _sha(p.output_dir)


def test_a_photograph_replaced_while_the_one_before_is_processed_gives_its_new_planes(tmp_path: Path) -> None:
    """Shot b is read ahead while a is processed, then taken again under the same name: b's result is the new one."""
    (tmp_path / "in").mkdir()
    a, b = make_png(tmp_path / "in" / "a.png", 48, 64), make_png(tmp_path / "in" / "b.png", 48, 64)
    seen: list[tuple[int, int]] = []
    runner_box: list[batch.InlineRunner] = []

    def pipeline(planes, aperture, optics, **options):
        seen.append(planes.shape[:2])
        result = fake_pipeline(planes, aperture, optics, **options)  # its dense stage done: b's read begins
        if len(seen) == 1:  # processing a: let b's read-ahead finish, then replace b
            slot = runner_box[0].read_ahead._slot
            assert slot is not None and slot.path == b
            slot.thread.join()
            make_png(b, 40, 56)
            os.utime(b, ns=(time.time_ns(), time.time_ns() + 10**9))
        return result

    job = batch._Job(out_root=tmp_path / "out", profile=PROFILE, force=False, pipeline=pipeline)
    runner = batch.InlineRunner(job)
    runner_box.append(runner)
    for f in (a, b):
        runner.submit(batch.Task(input_path=f, out_name=f.stem))
    outcomes = [o for _ in range(2) for _, o in runner.wait(0.0)]
    assert [o.status for o in outcomes] == ["done", "done"]
    assert seen == [(48, 64), (40, 56)]
    assert runner.read_ahead.used == 0


def test_a_bad_file_in_a_batch_fails_with_its_reason_and_the_batch_goes_on(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    good = make_png(tmp_path / "in" / "a.png")
    bad = tmp_path / "in" / "b.CR2"
    bad.write_bytes(b"II*\0" + b"\0" * 64)
    last = make_png(tmp_path / "in" / "c.png")
    outcomes, _ = _run_inline([good, bad, last], tmp_path / "out", fake_pipeline)
    assert [o.status for o in outcomes] == ["done", "failed", "done"]
    assert "b.CR2" in (outcomes[1].reason or "")


def test_a_one_worker_batch_reads_each_next_file_ahead(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Through `run_batch` (what `mca process DIR` runs): the driver hands the runner one file at a time and tells
    it which comes next; every file but the first is then read ahead, and the outputs are as without it."""
    made: list[ReadAhead] = []

    class Counting(ReadAhead):
        def __init__(self) -> None:
            super().__init__()
            made.append(self)

    monkeypatch.setattr(batch, "ReadAhead", Counting)
    (tmp_path / "in").mkdir()
    for i in range(3):
        make_png(tmp_path / "in" / f"shot{i}.png", 48 + 8 * i, 64)
    report = batch.run_batch([tmp_path / "in"], tmp_path / "out", PROFILE, workers=1, pipeline=fake_pipeline)
    assert [o.status for o in report.outcomes] == ["done"] * 3
    assert [r.used for r in made] == [2]
    files, _ = _run_inline(sorted((tmp_path / "in").iterdir()), tmp_path / "plain", fake_pipeline, read_ahead=False)
    for a, p in zip(sorted(report.outcomes, key=lambda o: o.input_path.name), files, strict=True):
        assert _sha(a.output_dir) == _sha(p.output_dir)
