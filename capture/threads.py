"""Thread limits per process: N batch workers on C cores give each worker C // N threads of numba, OpenCV and BLAS.

Every library the pipeline calls sizes its thread pool to the whole machine: numba's `prange`
kernels (`NUMBA_NUM_THREADS`), OpenCV's `parallel_for_` (`cv2.setNumThreads`), OpenBLAS/MKL/OpenMP
(`OPENBLAS_NUM_THREADS`, ...) and the pipeline's own helper threads (`processing.disparity`,
`MCA_THREADS`). With `--workers 2` on 2 cores each worker would run 2 threads of each: 4+ runnable
threads on 2 cores, time lost to switching and to threads waiting for each other at the end of
every parallel loop. `limit_threads` runs in each pool worker before the pipeline is imported
(`capture.pool_worker`, the initializer of `capture.batch`'s pool); benchmarks/bench_process.py measures the effect.
"""

from __future__ import annotations

import os
import sys

# Read by the libraries when they load (numba, OpenBLAS, OpenMP, MKL) and by `processing.disparity` (MCA_THREADS).
THREAD_ENV = ("MCA_THREADS", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    """Threads each of `workers` processes gets so that together they fill `cores` and no more (at least 1)."""
    cores = available_cores() if cores is None else cores
    return max(1, cores // max(1, workers))


def limit_threads(count: int) -> dict[str, int]:
    """Limit this process's compute threads to `count`; returns what was set (library -> threads).

    Environment variables cover libraries not yet loaded; numba, OpenCV, the pipeline's helper
    pool and (with threadpoolctl installed) an already-loaded BLAS are limited directly.
    """
    count = max(1, int(count))
    for name in THREAD_ENV:
        os.environ[name] = str(count)
    applied = {"env": count}
    if "numba" in sys.modules:  # loaded already: its pool exists; set_num_threads limits this thread's use of it
        import numba

        # NUMBA_NUM_THREADS is set on numba.config at run time, out of mypy's sight
        pool = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
        # numba sized its pool by the variable when it loaded and reads it again before every compile: a new
        # value then stops the compile ("Cannot set NUMBA_NUM_THREADS ... once the threads have been launched"),
        # so the variable keeps the pool's size
        os.environ["NUMBA_NUM_THREADS"] = str(pool)
        numba.set_num_threads(min(count, pool))
        applied["numba"] = numba.get_num_threads()
    try:
        import cv2

        cv2.setNumThreads(count)
        applied["opencv"] = cv2.getNumThreads()
    except ImportError:  # pragma: no cover - OpenCV is a dependency
        pass
    disparity = sys.modules.get("mca.processing.disparity")
    if disparity is not None:
        disparity.set_worker_threads(count)
        applied["processing"] = count
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        pass
    else:
        threadpool_limits(count)
        applied["blas"] = count
    return applied


__all__ = ["THREAD_ENV", "available_cores", "limit_threads", "threads_per_worker"]
