"""Headless batches of `process_file`: discovery, a local process pool or a Dask cluster, watch mode, progress, summary.

One driver loop (`run_batch`) serves every way of running: it finds the inputs,
hands them to a runner (in this process, a spawn-context process pool, or a Dask
distributed client), keeps at most the runner's capacity in flight, reports
progress, and returns every file's `FileOutcome`. A bad file never stops the batch;
a folder already holding the result of the same photograph with the same settings is
skipped unless forced. Files that are not photographs to take (FIFOs and other non-regular
files, anything in a `truth/` folder of `mca simulate`) are skipped with the reason.
"""

from __future__ import annotations

import concurrent.futures
import errno
import multiprocessing
import os
import shutil
import stat
import sys
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from mca.capture.memory import keep_freed_memory
from mca.capture.output_folders import OutputFolderError, output_name_for, prepare_root
from mca.capture.pipeline_app import (
    RECORDING_NAME,
    STAGES,
    SUPPORTED_SUFFIXES,
    FileOutcome,
    PipelineFunction,
    output_dir_for,
    process_file,
)
from mca.capture.pool_worker import init_pool_worker, stage_queue
from mca.capture.read_ahead import ReadAhead, StatKey, stat_key
from mca.capture.threads import threads_per_worker
from mca.processing.camera import CameraProfile


class BatchError(RuntimeError):
    """A batch that cannot start (no inputs, unreachable cluster); the message says what to do."""


@dataclass(frozen=True)
class Task:
    """One input file and where its outputs go."""

    input_path: Path
    out_name: str
    record_path: Path | None = None
    shot_index: int = 0  # position on the recording's shot timeline
    recording_id: str | None = None  # shared by the files of one batch: one recording, many shots


# --- discovery ------------------------------------------------------------------------------------------------------


TRUTH_FOLDER = "truth"  # where `mca simulate` keeps ground truth: never photographs to process
TRUTH_REASON = "ground truth written by `mca simulate` (a truth/ folder), not a photograph; skipped"


@dataclass
class Discovery:
    """What `discover` found: the inputs to process, and the files passed over with the reason."""

    inputs: list[Path] = field(default_factory=list)
    skipped: list[tuple[Path, str]] = field(default_factory=list)


def _non_regular_reason(path: Path) -> str | None:
    """Why a folder entry with a photograph's suffix is not taken, or None for a regular file."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return f"{path}: is a symbolic link that loops back on itself; skipped"
        if path.is_symlink():
            return f"{path}: is a symbolic link to a missing file; skipped"
        return f"{path}: cannot be read ({exc.strerror}); skipped"
    if stat.S_ISREG(mode):
        return None
    kind = {stat.S_IFIFO: "a FIFO (named pipe)", stat.S_IFSOCK: "a socket", stat.S_IFDIR: "a folder"}.get(
        stat.S_IFMT(mode), "a device"
    )
    return f"{path}: is {kind}, not a photograph file; skipped"


def _candidates(source: Path, found: Discovery) -> list[Path]:
    if os.path.isdir(source):
        if source.name == TRUTH_FOLDER:
            found.skipped.append((source, f"{source}: {TRUTH_REASON}"))
            return []
        taken = []
        for path in sorted(source.iterdir()):
            if path.name.startswith(".") or path.suffix.lower() not in SUPPORTED_SUFFIXES:
                continue
            reason = _non_regular_reason(path)
            if reason is None:
                taken.append(path)
            else:
                found.skipped.append((path, reason))
        return taken
    if source.parent.name == TRUTH_FOLDER:
        found.skipped.append((source, f"{source}: {TRUTH_REASON}"))
        return []
    return [source]  # an explicit file is always tried: a wrong one fails (or is skipped) with its reason


def discover(sources: Iterable[str | Path]) -> Discovery:
    """Input files: explicit files as given, folders' supported files (not recursive, hidden ones skipped);
    entries that are not regular files and `truth/` folders are listed as skipped, with the reason."""
    found = Discovery()
    seen: set[str] = set()
    for source in sources:
        for path in _candidates(Path(source), found):
            key = os.path.realpath(path)  # never raises, even for a symbolic-link loop
            if key not in seen:
                seen.add(key)
                found.inputs.append(path)
    return found


def discover_inputs(sources: Iterable[str | Path]) -> list[Path]:
    """Input files: explicit files as given, folders' supported files (not recursive, hidden ones skipped)."""
    return discover(sources).inputs


def assign_name(path: Path, taken: dict[str, Path] | None = None) -> str:
    """The preferred output folder name for `path`: its stem, made safe (`output_folders.output_name_for`).

    Inputs sharing a stem share the preferred name; `process_file` gives each photograph its own
    folder (`NAME`, `NAME-2`, ... in the order they are processed), found again by path or content
    on later runs. `taken` is accepted for compatibility and ignored.
    """
    return output_name_for(path)


# --- runners --------------------------------------------------------------------------------------------------------


class Runner(Protocol):
    """Runs tasks somewhere; `wait` returns the finished ones (possibly none before `timeout_s`)."""

    capacity: int

    def submit(self, task: Task) -> None: ...

    def expect(self, path: Path | None) -> None: ...

    def wait(self, timeout_s: float) -> list[tuple[Task, FileOutcome]]: ...

    def cancel(self) -> list[Task]: ...

    def close(self) -> None: ...


@dataclass
class _Job:
    out_root: Path
    profile: CameraProfile
    force: bool
    pipeline: PipelineFunction | None
    on_stage: Callable[[Task, str], None] | None = None  # progress display, called in this process
    recorder: Any = None  # a live recorder (inline runner only)
    max_megapixels: float | None = None  # the pixel limit of the inputs (None: capture.raw's default)
    quality: str = "full"  # `--quality`: the pipeline's parameters (capture.api.QUALITIES)

    def kwargs(self, task: Task) -> dict[str, Any]:
        kwargs: dict[str, Any] = {
            "max_megapixels": self.max_megapixels,
            "quality": self.quality,
            "force": self.force,
            "record_path": task.record_path,
            "out_name": task.out_name,
            "shot_index": task.shot_index,
            "recording_id": task.recording_id,
        }
        if self.recorder is not None:
            kwargs["recorder"] = self.recorder
        if self.pipeline is not None:
            kwargs["pipeline"] = self.pipeline
        return kwargs

    def failed(self, task: Task, reason: str) -> FileOutcome:
        return runner_failed(self.out_root, task, reason)


# The stage after which the inline runner reads the next file. The dense search keeps 1.8 of 2 cores busy, the
# stages after it 1.0-1.4: a read during the search competes with its two threads (of two rounds of six files, one
# came out slower, one faster); after it, the read takes the idle core (both rounds faster; docs/batch.md).
READ_AHEAD_AFTER = "disparity"


class InlineRunner:
    """Runs each task in this process, one at a time (`--workers 1`). Once a file's dense search is done, the
    next file is read on a helper thread while this one is finished (`capture.read_ahead`)."""

    capacity = 1

    def __init__(self, job: _Job) -> None:
        self.job = job
        self.queue: deque[Task] = deque()
        self.read_ahead = ReadAhead()
        self.upcoming: Path | None = None  # the file the batch takes next (`expect`), when not submitted yet

    def submit(self, task: Task) -> None:
        self.queue.append(task)

    def expect(self, path: Path | None) -> None:
        """The batch's next file after those submitted (None: none known yet): the one to read ahead."""
        self.upcoming = path

    def wait(self, timeout_s: float) -> list[tuple[Task, FileOutcome]]:
        if not self.queue:
            return []
        task = self.queue.popleft()
        report = self.job.on_stage

        def on_stage(stage: str) -> None:
            upcoming = self.queue[0].input_path if self.queue else self.upcoming
            if stage == READ_AHEAD_AFTER and upcoming is not None:
                self.read_ahead.start(upcoming, self.job.max_megapixels)
            if report is not None:
                report(task, stage)

        outcome = process_file(
            task.input_path,
            self.job.out_root,
            self.job.profile,
            on_stage=on_stage,
            reader=self.read_ahead.read,
            **self.job.kwargs(task),
        )
        keep_freed_memory()  # the next capture reuses this one's memory (capture/memory.py)
        return [(task, outcome)]

    def cancel(self) -> list[Task]:
        cancelled = list(self.queue)
        self.queue.clear()
        self.read_ahead.discard()
        return cancelled

    def close(self) -> None:
        self.read_ahead.discard()


def _key(task: Task) -> str:
    """A name for the task unique within its batch (several inputs may share a preferred folder name)."""
    return f"{task.shot_index}-{task.out_name}"


def worker_threads(workers: int) -> int | None:
    """Compute threads for each of `workers` pool processes: the cores shared out (`threads_per_worker`), or
    $MCA_WORKER_THREADS when set (0: no limit, every library sizes itself to the whole machine)."""
    given = os.environ.get("MCA_WORKER_THREADS", "").strip()
    if given:
        try:
            return max(0, int(given)) or None
        except ValueError:
            raise BatchError(f"MCA_WORKER_THREADS={given!r}: give a whole number of threads (0: no limit)") from None
    return threads_per_worker(workers)


def _pool_process_file(
    input_path: Path, out_root: Path, profile: CameraProfile, key: str, **kwargs: Any
) -> FileOutcome:
    """`process_file` in a pool worker, announcing its stages as (key, stage) on the pool's queue."""
    queue = stage_queue()
    on_stage = None if queue is None else (lambda stage: queue.put((key, stage)))
    try:
        return process_file(input_path, out_root, profile, on_stage=on_stage, **kwargs)
    finally:
        keep_freed_memory()  # the worker's next capture reuses this one's memory (capture/memory.py)
        if queue is not None:
            queue.put((key, None))  # the end of this file's stages: they reach the parent before it (one feeder)


class PoolRunner:
    """A spawn-context process pool on the local cores (`--workers N`)."""

    def __init__(self, job: _Job, workers: int) -> None:
        self.job = job
        self.capacity = workers
        context = multiprocessing.get_context("spawn")
        self.stages = context.Queue() if job.on_stage is not None else None
        self.threads = worker_threads(workers)
        self.executor = concurrent.futures.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=init_pool_worker,  # its share of the cores, set before the pipeline loads
            initargs=(self.stages, self.threads),
        )
        self.futures: dict[concurrent.futures.Future, Task] = {}
        self.by_key: dict[str, Task] = {}
        self.ended: set[str] = set()  # keys whose stages have all arrived (the worker's end marker)

    def submit(self, task: Task) -> None:
        future = self.executor.submit(
            _pool_process_file,
            task.input_path,
            self.job.out_root,
            self.job.profile,
            _key(task),
            **self.job.kwargs(task),
        )
        self.futures[future] = task
        self.by_key[_key(task)] = task

    def expect(self, path: Path | None) -> None:
        """Nothing: each worker reads its own file, on its one core."""

    def _drain_stages(self, block_s: float = 0.0) -> None:
        """Hand the stages that have arrived to the display; with `block_s`, wait that long for the next one."""
        import queue as queue_module

        while self.stages is not None and self.job.on_stage is not None:
            try:
                key, stage = self.stages.get(timeout=block_s) if block_s > 0 else self.stages.get_nowait()
            except (queue_module.Empty, OSError, EOFError, ValueError):
                return
            block_s = 0.0
            if stage is None:
                self.ended.add(key)
                continue
            task = self.by_key.get(key)
            if task is not None:
                self.job.on_stage(task, stage)

    def _await_stages(self, tasks: list[Task], limit_s: float = 2.0) -> None:
        """Wait until every stage of `tasks` (finished) has reached the display. A worker's stages travel on the
        stage queue's feeder thread, its result on another pipe: the result can arrive first, and a stage arriving
        after its file's result was dropped (a two-worker batch showed "read, disparity" without "write"). A
        worker that died sends no end marker: then this gives up after `limit_s`."""
        if self.stages is None or self.job.on_stage is None:
            return
        deadline = time.monotonic() + limit_s
        while any(_key(t) not in self.ended for t in tasks) and time.monotonic() < deadline:
            self._drain_stages(block_s=max(0.01, min(0.1, deadline - time.monotonic())))

    def wait(self, timeout_s: float) -> list[tuple[Task, FileOutcome]]:
        if not self.futures:
            return []
        deadline = time.monotonic() + timeout_s
        while True:
            self._drain_stages()
            slice_s = max(0.0, min(0.1, deadline - time.monotonic())) if self.stages is not None else timeout_s
            done, _ = concurrent.futures.wait(
                list(self.futures), timeout=slice_s, return_when=concurrent.futures.FIRST_COMPLETED
            )
            if done or time.monotonic() >= deadline:
                break
        self._drain_stages()
        self._await_stages([self.futures[future] for future in done])
        finished = []
        for future in done:
            task = self.futures.pop(future)
            self.by_key.pop(_key(task), None)
            self.ended.discard(_key(task))
            try:
                finished.append((task, future.result()))
            except concurrent.futures.process.BrokenProcessPool:
                finished.append(
                    (
                        task,
                        self.job.failed(
                            task,
                            "a worker process died (crashed or ran out of memory) while this batch ran; "
                            "rerun to retry, or use fewer --workers",
                        ),
                    )
                )
            except BaseException as exc:
                finished.append((task, self.job.failed(task, f"{type(exc).__name__}: {exc}")))
        return finished

    def cancel(self) -> list[Task]:
        cancelled = [task for future, task in self.futures.items() if future.cancel()]
        return cancelled

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)
        if self.stages is not None:
            self.stages.close()
            self.stages.join_thread()


class DaskRunner:
    """The same tasks on a Dask distributed cluster (`--cluster tcp://HOST:8786`); inputs and outputs on a shared
    filesystem, the package installed on every worker."""

    def __init__(self, job: _Job, address: str, connect_timeout_s: float = 10.0) -> None:
        try:
            from distributed import Client
        except ImportError as exc:
            raise BatchError("--cluster needs dask distributed: pip install 'mca-appliance[cluster]'") from exc
        self.job = job
        self.address = address
        try:
            self.client = Client(address, timeout=f"{connect_timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise BatchError(
                f"cannot reach the Dask scheduler at {address} ({exc}); start one with "
                f"`dask scheduler` and workers with `dask worker {address}` (see docs/batch.md)"
            ) from exc
        from distributed import as_completed

        threads = sum(self.client.nthreads().values())
        self.capacity = max(2, 2 * threads)
        self.futures: dict[Any, Task] = {}
        self.completed = as_completed(loop=self.client.loop)

    def submit(self, task: Task) -> None:
        future = self.client.submit(
            process_file,
            task.input_path,
            self.job.out_root,
            self.job.profile,
            pure=False,
            key=f"mca-process-{task.out_name}-{os.urandom(4).hex()}",
            **self.job.kwargs(task),
        )
        self.futures[future] = task
        self.completed.add(future)

    def expect(self, path: Path | None) -> None:
        """Nothing: the cluster's workers read their own files."""

    def wait(self, timeout_s: float) -> list[tuple[Task, FileOutcome]]:
        if not self.futures:
            return []
        deadline = time.monotonic() + timeout_s
        done = self.completed.next_batch(block=False)
        while not done and time.monotonic() < deadline:
            time.sleep(0.02)
            done = self.completed.next_batch(block=False)
        finished = []
        for future in done:
            task = self.futures.pop(future, None)
            if task is None:
                continue
            try:
                finished.append((task, future.result()))
            except (ImportError, ModuleNotFoundError) as exc:
                finished.append(
                    (
                        task,
                        self.job.failed(
                            task,
                            f"a Dask worker could not import the appliance ({exc}); install mca-appliance on every "
                            "worker (docs/batch.md)",
                        ),
                    )
                )
            except Exception as exc:
                finished.append((task, self.job.failed(task, f"on the Dask cluster: {type(exc).__name__}: {exc}")))
        return finished

    def cancel(self) -> list[Task]:
        cancelled = list(self.futures.values())
        self.completed.clear()
        self.client.cancel(list(self.futures))
        self.futures.clear()
        return cancelled

    def close(self) -> None:
        self.client.close()


# --- progress -------------------------------------------------------------------------------------------------------


class Progress(Protocol):
    def discovered(self, total: int) -> None: ...

    def started(self, task: Task) -> None: ...

    def stage(self, task: Task, stage: str) -> None: ...

    def finished(self, task: Task, outcome: FileOutcome) -> None: ...

    def close(self) -> None: ...

    wants_stages: bool


class SilentProgress:
    wants_stages = False

    def discovered(self, total: int) -> None: ...

    def started(self, task: Task) -> None: ...

    def stage(self, task: Task, stage: str) -> None: ...

    def finished(self, task: Task, outcome: FileOutcome) -> None: ...

    def close(self) -> None: ...


class LineProgress:
    """One plain line per finished file (for logs, pipes and CI)."""

    wants_stages = False

    def __init__(self, write: Callable[[str], None] = print) -> None:
        self.write = write
        self.total = 0
        self.count = 0

    def discovered(self, total: int) -> None:
        self.total = total

    def started(self, task: Task) -> None:
        return None

    def stage(self, task: Task, stage: str) -> None:
        return None

    def finished(self, task: Task, outcome: FileOutcome) -> None:
        self.count += 1
        detail = (
            outcome.reason
            if outcome.status == "failed"
            else (f"{outcome.regions} regions" if outcome.regions is not None else "")
        )
        self.write(
            f"[{self.count}/{self.total}] {outcome.status:<7} {task.input_path.name} "
            f"{outcome.seconds:.1f} s {detail}".rstrip()
        )

    def close(self) -> None:
        return None


class RichProgress:
    """An overall bar plus one row per file in flight, advancing through the pipeline stages (terminals)."""

    wants_stages = True

    def __init__(self, console: Any = None) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, SpinnerColumn, TextColumn, TimeElapsedColumn
        from rich.progress import Progress as RichBar

        self.bar = RichBar(
            SpinnerColumn(),
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
        )
        self.bar.start()
        self.overall = self.bar.add_task("all files", total=0)
        self.rows: dict[Task, Any] = {}

    def discovered(self, total: int) -> None:
        self.bar.update(self.overall, total=total)

    def started(self, task: Task) -> None:
        self.rows[task] = self.bar.add_task(f"  {task.input_path.name}", total=len(STAGES))

    def stage(self, task: Task, stage: str) -> None:
        row = self.rows.get(task)
        if row is not None:
            self.bar.update(row, advance=1, description=f"  {task.input_path.name}: {stage}")

    def finished(self, task: Task, outcome: FileOutcome) -> None:
        row = self.rows.pop(task, None)
        if row is not None:
            self.bar.remove_task(row)
        self.bar.advance(self.overall)
        if outcome.status == "failed":
            self.bar.console.print(f"[red]failed[/red] {outcome.reason}", highlight=False, markup=True)

    def close(self) -> None:
        self.bar.stop()


# --- the driver loop ------------------------------------------------------------------------------------------------


@dataclass
class BatchReport:
    """Every file's outcome, in the order they finished, plus the merged recording if one was asked for."""

    outcomes: list[FileOutcome] = field(default_factory=list)
    recording: Path | None = None
    recording_error: str | None = None  # the recording could not be written (the results are unaffected)
    interrupted: bool = False

    @property
    def failed(self) -> list[FileOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def count(self, status: str) -> int:
        return sum(1 for o in self.outcomes if o.status == status)


def make_runner(
    out_root: Path,
    profile: CameraProfile,
    *,
    workers: int = 1,
    cluster: str | None = None,
    force: bool = False,
    pipeline: PipelineFunction | None = None,
    on_stage: Callable[[Task, str], None] | None = None,
    recorder: Any = None,
    max_megapixels: float | None = None,
    quality: str = "full",
) -> Runner:
    """The runner for the options: a Dask client for `cluster`, else a process pool, or inline for one worker.

    `on_stage(task, stage)` hears each file's stages (not from a Dask cluster).
    """
    job = _Job(
        out_root=out_root,
        profile=profile,
        force=force,
        pipeline=pipeline,
        on_stage=on_stage,
        recorder=recorder,
        max_megapixels=max_megapixels,
        quality=quality,
    )
    if cluster:
        return DaskRunner(job, cluster)
    if workers < 1:
        raise BatchError(f"--workers must be at least 1, got {workers}")
    return InlineRunner(job) if workers == 1 else PoolRunner(job, workers)


def _stable(path: Path, key: StatKey | None, seen: dict[Path, tuple[int, int, float]], settle_s: float) -> bool:
    """True once the file's size and modification time (from its `stat_key`, None when it cannot be stat'ed)
    have not changed for `settle_s` seconds."""
    if key is None:
        return False
    size, mtime_ns = key[2], key[3]
    now = time.monotonic()
    previous = seen.get(path)
    if previous is None or previous[:2] != (size, mtime_ns):
        seen[path] = (size, mtime_ns, now)
        return False
    return size > 0 and now - previous[2] >= settle_s


def run_batch(
    sources: list[Path],
    out_root: Path,
    profile: CameraProfile,
    *,
    workers: int = 1,
    cluster: str | None = None,
    force: bool = False,
    record: Path | None = None,
    watch: bool = False,
    watch_timeout_s: float | None = None,
    poll_interval_s: float = 1.0,
    settle_s: float = 2.0,
    progress: Progress | None = None,
    pipeline: PipelineFunction | None = None,
    recorder: Any = None,
    max_megapixels: float | None = None,
    quality: str = "full",
) -> BatchReport:
    """Process every input under `sources` into `out_root`; with `watch`, keep processing files as they arrive.

    Watch mode polls the folders every `poll_interval_s`, takes a file once its size and time stamp
    have not changed for `settle_s` seconds, and stops on Ctrl-C or after `watch_timeout_s` without a new or running file.
    With `record`, each file records into `<out>/<name>/recording.rrd`, merged into `record` at the end
    as one recording whose `shot` timeline steps through the files. A live `recorder` (e.g. one
    serving a web viewer) receives every shot; it needs the files processed here, one at a time.
    A file changed after it was taken (watch mode) is taken again once settled. `max_megapixels`
    limits the inputs' size (default: `capture.raw.default_max_megapixels()`); `quality` ("full" or
    "preview") picks the pipeline's parameters.

    Raises `BatchError` before anything is processed when a source does not exist or the output
    folder cannot be created.
    """
    if recorder is not None and (workers > 1 or cluster):
        raise BatchError(
            "a live recorder (--serve) needs the files processed here one at a time: "
            "drop --workers/--cluster, or use --record and open the file afterwards"
        )
    missing = [str(s) for s in sources if not os.path.lexists(s)]
    if missing:
        raise BatchError(f"no such file or folder: {', '.join(missing)}; check the path")
    # absolute: cluster workers see the same shared paths; realpath never raises, even for a symbolic-link loop
    sources = [Path(os.path.realpath(s)) for s in sources]
    try:
        out_root = prepare_root(out_root)
    except OutputFolderError as exc:
        raise BatchError(str(exc)) from None
    progress = progress or SilentProgress()
    report = BatchReport()
    runner = make_runner(
        out_root,
        profile,
        workers=workers,
        cluster=cluster,
        force=force,
        pipeline=pipeline,
        on_stage=progress.stage if getattr(progress, "wants_stages", False) else None,
        recorder=recorder,
        max_megapixels=max_megapixels,
        quality=quality,
    )
    recording_id = batch_recording_id(Path(record)) if record is not None else None
    parts = out_root / f".mca-recording-parts-{uuid.uuid4().hex[:12]}" if record is not None else None
    names: dict[str, Path] = {}
    known: dict[Path, StatKey | None] = {}  # path -> (device, inode, size, mtime) when taken
    passed_over: set[Path] = set()
    shots = 0
    sizes: dict[Path, tuple[int, int, float]] = {}
    queue: deque[Task] = deque()
    in_flight = 0
    busy_names: set[str] = set()
    flying: list[Task] = []  # submitted, not finished
    last_activity = time.monotonic()
    finished_tasks: list[Task] = []

    def look() -> None:
        nonlocal last_activity, shots
        new = False
        found = discover(sources)
        for path, reason in found.skipped:
            if path in passed_over:
                continue
            passed_over.add(path)
            task = Task(path, path.name)
            outcome = FileOutcome(path, "skipped", out_root, reason=reason)
            report.outcomes.append(outcome)
            progress.discovered(len(known) + len(passed_over))
            progress.finished(task, outcome)
        for path in found.inputs:
            key = stat_key(path)  # once per file and look
            if path in known and (not watch or known[path] == key):
                continue  # taken already, and not changed since (a re-shot file is taken again)
            if watch and not _stable(path, key, sizes, settle_s):
                last_activity = time.monotonic()  # still arriving: keep waiting for it
                continue
            known[path] = key
            name = assign_name(path, names)
            queue.append(
                Task(
                    path,
                    name,
                    parts / f"{shots:06d}-{name}.rrd" if parts is not None else None,
                    shot_index=shots,
                    recording_id=recording_id,
                )
            )
            shots += 1
            new = True
        if new:
            last_activity = time.monotonic()
            progress.discovered(len(known) + len(passed_over))

    try:
        look()
        if not watch and not known and not passed_over:
            raise BatchError(
                "no input files found in "
                + ", ".join(str(s) for s in sources)
                + f"; give files or folders holding {', '.join(sorted(SUPPORTED_SUFFIXES))}"
            )
        while True:
            while queue and in_flight < runner.capacity:
                # inputs sharing a folder name go one after the other: the names they get do not depend on timing
                task = next((t for t in queue if t.out_name not in busy_names), None)
                if task is None:
                    break
                queue.remove(task)
                busy_names.add(task.out_name)
                flying.append(task)
                runner.submit(task)
                progress.started(task)
                in_flight += 1
            if in_flight:
                runner.expect(queue[0].input_path if queue else None)  # the inline runner reads it ahead
                for task, outcome in runner.wait(poll_interval_s if watch else 0.5):
                    in_flight -= 1
                    busy_names.discard(task.out_name)
                    flying.remove(task)
                    report.outcomes.append(outcome)
                    finished_tasks.append(task)
                    progress.finished(task, outcome)
                    last_activity = time.monotonic()
            elif not watch or (watch_timeout_s is not None and time.monotonic() - last_activity > watch_timeout_s):
                break
            else:
                time.sleep(poll_interval_s)
            if watch:
                look()
    except KeyboardInterrupt:
        report.interrupted = True
        runner.cancel()
        for task in flying + list(queue):  # the files in flight too: their results were not kept
            report.outcomes.append(
                runner_failed(
                    out_root, task, "interrupted (Ctrl-C) before it finished; rerun the same command to finish it"
                )
            )
        queue.clear()
    finally:
        progress.close()
        runner.close()

    if record is not None and parts is not None:
        try:
            report.recording = merge_batch_recordings(finished_tasks, report.outcomes, Path(record), parts)
        except BatchError as exc:
            report.recording_error = str(exc)
    return report


def runner_failed(out_root: Path, task: Task, reason: str) -> FileOutcome:
    return FileOutcome(
        task.input_path,
        "failed",
        output_dir_for(task.input_path, out_root, task.out_name),
        reason=f"{task.input_path}: {reason}",
    )


def batch_recording_id(record: Path) -> str:
    """The rerun recording id of a batch's `--record` file: the same for every run into that file, so a resumed
    batch's new shots and the shots kept from the earlier run are one recording (one `shot` timeline)."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, "mca-batch-recording:" + os.path.realpath(record)))


def merge_batch_recordings(
    tasks: list[Task], outcomes: list[FileOutcome], out_path: Path, parts: Path | None = None
) -> Path | None:
    """Merge the recordings of the files this batch processed, in shot order, into `out_path`: the one copy.

    Each file records into its own part (`Task.record_path`, in the hidden folder `parts`); once merged the
    parts are deleted, so every shot's recording is stored once, in `out_path`. Shots this batch skipped
    (unchanged since an earlier run) are in the earlier `out_path` when it exists: it is merged in too (same
    recording id, `batch_recording_id`). Result folders of older versions that hold a `recording.rrd` of
    their own are merged for their skipped shots when there is no earlier `out_path`. If the merge fails
    the parts are kept and the error names them.
    """
    status = {o.input_path: o for o in outcomes}
    new_parts = sorted(
        (
            t.record_path
            for t in tasks
            if t.record_path is not None
            and t.input_path in status
            and status[t.input_path].status == "done"
            and t.record_path.is_file()
        ),
        key=lambda p: p.name,
    )
    skipped = [o for o in outcomes if o.status == "skipped" and any(t.input_path == o.input_path for t in tasks)]
    earlier: list[Path] = []
    if skipped and out_path.is_file():
        earlier = [out_path]
    elif skipped:  # an older layout: each result folder kept its own recording
        earlier = sorted(
            (o.output_dir / RECORDING_NAME for o in skipped if (o.output_dir / RECORDING_NAME).is_file()),
            key=lambda p: p.parent.name,
        )
    paths = earlier + new_parts
    if not paths:
        if parts is not None:
            shutil.rmtree(parts, ignore_errors=True)  # only parts of failed files, if any
        return None
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        if paths == new_parts and len(new_parts) == 1:
            os.replace(new_parts[0], out_path)  # one shot: its part is the recording
        else:
            from mca.capture.recording import merge_recordings

            merge_recordings(paths, out_path)
    except (OSError, RuntimeError) as exc:
        where = f"; the recordings of the shots are kept in {parts}" if parts is not None and new_parts else ""
        raise BatchError(f"cannot write the recording {out_path}: {exc}{where}") from exc
    if parts is not None:
        shutil.rmtree(parts, ignore_errors=True)
    return out_path


# --- the summary ----------------------------------------------------------------------------------------------------


def print_summary(report: BatchReport, console: Any = None) -> None:
    """A table of every file, totals, and the failures with their reasons in full."""
    from rich.console import Console
    from rich.table import Table

    if console is None:
        console = Console() if sys.stdout.isatty() else Console(width=160)
    table = Table(title="mca process", show_lines=False)
    for column in ("file", "status", "seconds", "regions", "output"):
        table.add_column(column, overflow="fold")
    style = {"done": "green", "skipped": "cyan", "failed": "red"}
    for outcome in sorted(report.outcomes, key=lambda o: str(o.input_path)):
        table.add_row(
            outcome.input_path.name,
            f"[{style[outcome.status]}]{outcome.status}[/]",
            f"{outcome.seconds:.1f}",
            "" if outcome.regions is None else str(outcome.regions),
            str(outcome.output_dir),
        )
    console.print(table)
    console.print(
        f"{report.count('done')} done, {report.count('skipped')} skipped, {report.count('failed')} failed"
        + (" (stopped by Ctrl-C)" if report.interrupted else ""),
        highlight=False,
    )
    if report.recording is not None:
        console.print(f"recording: {report.recording}", highlight=False)
    _print_notes(report.outcomes)
    passed_over = [o for o in report.outcomes if o.status == "skipped" and not _finished_before(o)]
    if passed_over:
        print("skipped files (not taken as photographs):", file=sys.stderr)
        for outcome in passed_over:
            print(f"  {outcome.reason}", file=sys.stderr)
    if report.failed:
        print("failed files:", file=sys.stderr)
        for outcome in report.failed:
            print(f"  {outcome.reason}", file=sys.stderr)


def _print_notes(outcomes: list[FileOutcome]) -> None:
    """The notes of done files (result.json's `notes`), each once, with the files it concerns."""
    files: dict[str, list[str]] = {}
    for outcome in outcomes:
        for note in outcome.notes:
            files.setdefault(note, []).append(outcome.input_path.name)
    for note, names in files.items():
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        print(f"note: {shown}: {note}", file=sys.stderr)


def _finished_before(outcome: FileOutcome) -> bool:
    """A skip because the result is already there (the routine case), not because the file was passed over."""
    return (outcome.reason or "").startswith("already finished")


__all__ = [
    "BatchError",
    "BatchReport",
    "Discovery",
    "LineProgress",
    "RichProgress",
    "SilentProgress",
    "Task",
    "assign_name",
    "discover",
    "discover_inputs",
    "make_runner",
    "print_summary",
    "run_batch",
]


# --- the application side of `mca process` --------------------------------------------------------------------------


@dataclass(frozen=True)
class ProcessSettings:
    """`mca process`'s options checked and completed from the config file: what `run_batch` is then given."""

    profile: CameraProfile
    out: Path
    workers: int
    max_megapixels: float
    quality: str


def process_settings(
    inputs: list[Path],
    *,
    out: Path | None = None,
    profile: str | None = None,
    workers: int | None = None,
    max_megapixels: float | None = None,
    quality: str = "full",
    record: Path | None = None,
    serve: bool = False,
    cluster: str | None = None,
) -> ProcessSettings:
    """Fill the options left out from the config file and check them all before anything is processed.

    Raises `BatchError` naming the option, file or folder at fault (a bad config file, an unknown profile,
    a missing input, an `--out` that is a file, a `--record` that is not .rrd, `--serve` with workers)."""
    from mca.capture.api import check_quality
    from mca.capture.config import ConfigError, fill_from_config
    from mca.capture.profile_app import resolve_profile
    from mca.capture.raw import default_max_megapixels, parse_megapixels
    from mca.processing.camera import ProfileError

    try:
        chosen = fill_from_config(profile=profile, workers=workers, output_dir=out)
        camera_profile = resolve_profile(str(chosen["profile"]))
        limit = (
            default_max_megapixels() if max_megapixels is None else parse_megapixels(max_megapixels, "--max-megapixels")
        )
    except (ConfigError, ProfileError, ValueError) as exc:
        raise BatchError(str(exc)) from None
    try:
        check_quality(quality)
    except ValueError as exc:
        raise BatchError(f"--quality: {exc}") from None
    out_dir, worker_count = Path(chosen["output_dir"]), int(chosen["workers"])
    missing = [str(p) for p in inputs if not p.exists() and not p.is_symlink()]
    if missing:
        raise BatchError(f"no such file or folder: {', '.join(missing)}; check the path")
    if out_dir.exists() and not out_dir.is_dir():
        raise BatchError(f"--out {out_dir} is a file; give a folder for the outputs")
    if record is not None and record.suffix != ".rrd":
        raise BatchError(f"--record {record}: give a .rrd file name")
    if serve and (worker_count > 1 or cluster):
        raise BatchError(
            "--serve streams from this process, one file at a time: drop --workers/--cluster, "
            "or use --record and open the file with `mca view` afterwards"
        )
    return ProcessSettings(camera_profile, out_dir, worker_count, limit, quality)


def choose_progress(quiet: bool, write: Callable[[str], None]) -> Progress:
    """Progress for `mca process`: none when `quiet`, a rich display on a terminal, else one line per file."""
    if quiet:
        return SilentProgress()
    if sys.stdout.isatty():
        return RichProgress()
    return LineProgress(write)


def report_document(report: BatchReport) -> dict[str, Any]:
    """`mca process --json`: every file's outcome, in input order, the totals and the merged recording."""
    from mca.capture.outputs import json_safe

    files = [
        {
            "input": str(o.input_path),
            "status": o.status,
            "output_dir": str(o.output_dir),
            "result": str(o.output_dir / "result.json") if o.status != "failed" else None,
            "seconds": round(o.seconds, 3),
            "regions": o.regions,
            "reason": o.reason,
        }
        for o in sorted(report.outcomes, key=lambda o: str(o.input_path))
    ]
    totals = {status: report.count(status) for status in ("done", "skipped", "failed")}
    return json_safe(
        {
            "files": files,
            "totals": totals,
            "recording": report.recording,
            "recording_error": report.recording_error,
            "interrupted": report.interrupted,
        }
    )


def stop_on_sigterm() -> None:
    """Make SIGTERM (systemctl stop, kill) end this process like Ctrl-C does: through its `finally` blocks."""
    import signal

    def interrupted(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, interrupted)


def open_live_viewer(bind: str) -> Any:
    """A `RerunRecorder` serving a web viewer on `bind` for `mca process --serve`, with SIGTERM made a Ctrl-C
    so that a service stop reaches the caller's `finally` (else the viewer server is orphaned).

    Raises `BatchError` when the viewer cannot start."""
    from mca.capture.recording import RerunRecorder

    stop_on_sigterm()
    try:
        return RerunRecorder(None, serve=True, bind=bind)
    except RuntimeError as exc:
        raise BatchError(str(exc)) from None


def serve_until_interrupted(poll_s: float = 1.0) -> None:
    """Keep this process (and the viewer it serves) alive until Ctrl-C or SIGTERM."""
    try:
        while True:
            time.sleep(poll_s)
    except KeyboardInterrupt:
        pass
