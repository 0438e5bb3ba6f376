"""What a batch's pool worker sets up before anything heavy loads: its share of the cores and its stage queue.

A spawned worker imports its initializer's module before it runs the initializer. This module imports nothing
that loads numba, OpenCV or the pipeline, so `limit_threads` runs first and numba sizes its pool to the worker's
share (`capture/threads.py`). From `capture.batch`, which loads the pipeline, numba would take the whole machine
in every worker, and, on a fresh install whose numba cache is still empty, refuse the new thread count at its
first compile ("Cannot set NUMBA_NUM_THREADS ... once the threads have been launched"): every file of the first
`--workers 2` batch failed so until the eleventh stop.
"""

from __future__ import annotations

from typing import Any

from mca.capture.threads import limit_threads

_stage_queue: Any = None  # in a pool worker: where its stage announcements go


def init_pool_worker(queue: Any, threads: int | None = None) -> None:
    """The initializer of `capture.batch`'s pool: `limit_threads(threads)` (unless None), `queue` kept for
    `stage_queue`."""
    global _stage_queue
    _stage_queue = queue
    if threads:
        limit_threads(threads)


def stage_queue() -> Any:
    """In a pool worker: the queue `init_pool_worker` was given (None elsewhere)."""
    return _stage_queue


__all__ = ["init_pool_worker", "stage_queue"]
