"""The next photograph of a batch read on a helper thread while this one is processed (`mca process -j 1`).

A capture's read (LibRaw's unpack and the half-resolution planes, about 0.5-0.9 s at 20 MP) runs on one core,
and LibRaw lets go of the interpreter while it decodes; the pipeline leaves the other core idle for part of
its time. `ReadAhead.start` reads a file on a daemon thread, under the read policy the batch gives its files
(`capture.raw.read_policy`); `ReadAhead.read` hands that result to `process_file` for the same file, and reads
afresh in every other case:

- another file, or none started;
- the file changed since (device, inode, size or modification time differ from what they were when the read
  began and when it ended): the planes would not be those of the bytes `process_file` hashes;
- the read failed: the file is read again in the caller, whose error names the file and what to do, as
  without a read-ahead.

So a read-ahead can make a batch faster, never different: every file's planes are those `read_input` gives
for its bytes. At most one read is held; starting another lets the first go.
"""

from __future__ import annotations

import os
import stat
import threading
from collections.abc import Callable
from pathlib import Path

from mca.capture.api import LoadedInput, read_input
from mca.capture.raw import read_policy

StatKey = tuple[int, int, int, int]


def _key(info: os.stat_result) -> StatKey:
    return (info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns)


def stat_key(path: str | os.PathLike[str]) -> StatKey | None:
    """(device, inode, size, modification time in ns) of `path`, None when it cannot be stat'ed: two equal keys
    are the same bytes, short of a rewrite in place that keeps the size and the time (within the file system's
    resolution, or set back)."""
    try:
        return _key(os.stat(path))
    except OSError:
        return None


class _Slot:
    """One read on its thread: the file, its stat before the read, and the result or the failure."""

    def __init__(
        self, path: Path, before: StatKey, reader: Callable[[Path], LoadedInput], max_megapixels: float | None
    ) -> None:
        self.path = path
        self.before = before
        self.after: StatKey | None = None
        self.loaded: LoadedInput | None = None
        self.failed = False
        self._reader = reader
        self._max_megapixels = max_megapixels
        self.thread = threading.Thread(target=self._run, name="mca-read-ahead", daemon=True)

    def _run(self) -> None:
        try:
            with read_policy(max_megapixels=self._max_megapixels, photograph=True):
                self.loaded = self._reader(self.path)
        except BaseException:  # the caller reads again and reports it in its own words
            self.failed = True
        self.after = stat_key(self.path)


class ReadAhead:
    """At most one photograph read ahead of its turn (module docstring); `read` is `read_input` for the caller."""

    def __init__(self, reader: Callable[[Path], LoadedInput] = read_input) -> None:
        self._reader = reader
        self._slot: _Slot | None = None
        self._lock = threading.Lock()
        self.used = 0  # reads handed over (tests, benchmarks)

    def start(self, path: str | os.PathLike[str], max_megapixels: float | None = None) -> None:
        """Begin reading `path` on a helper thread (under `read_policy(max_megapixels, photograph=True)`); nothing
        for what is not a regular file (a FIFO would never answer; the caller skips it with the reason)."""
        try:
            info = os.stat(path)
        except OSError:
            info = None
        if info is None or not stat.S_ISREG(info.st_mode):
            self.discard()
            return
        slot = _Slot(Path(path), _key(info), self._reader, max_megapixels)
        with self._lock:
            self._slot = slot
        slot.thread.start()

    def discard(self) -> None:
        """Let go of any read (its thread ends on its own)."""
        with self._lock:
            self._slot = None

    def read(self, path: str | os.PathLike[str]) -> LoadedInput:
        """`read_input(path)`: the read begun by `start` when it is of this very file, unchanged, and succeeded;
        else a fresh read here (which raises what `read_input` raises)."""
        path = Path(path)
        with self._lock:
            slot, self._slot = self._slot, None
        if slot is not None and slot.path == path:
            slot.thread.join()
            unchanged = slot.before == slot.after == stat_key(path)
            if unchanged and not slot.failed and slot.loaded is not None:
                self.used += 1
                return slot.loaded
        return self._reader(path)


__all__ = ["ReadAhead", "StatKey", "stat_key"]
