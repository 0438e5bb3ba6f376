"""The pipeline's numba kernels give the same bits whether compiled in this process or loaded from numba's cache.

A batch's workers load the kernels their parent (or an earlier run) compiled and cached, so a kernel whose
compiled and cached forms round differently makes two workers disagree with one. That happened under numba 0.60
with fastmath's re-association and contraction flags (`processing/jit.py`). Here two fresh `mca process` runs
share an empty cache directory: the first, with two workers, compiles every kernel in the workers and writes the
cache; the second, in one process, loads it. Their outputs must be identical, bit for bit.

The first run is also a fresh install's first batch: compiling in a pool worker once stopped every file with
numba's "Cannot set NUMBA_NUM_THREADS ... once the threads have been launched" (`capture/pool_worker.py`).
"""

from __future__ import annotations

import os
import subprocess
import sys

from test_batch import assert_same_outputs
from test_process import make_cr2, make_png


def test_compiled_and_cached_kernels_give_the_same_outputs(tmp_path):
    inputs = tmp_path / "in"
    inputs.mkdir()
    make_cr2(inputs / "c1.CR2", 64, 80)
    make_png(inputs / "p1.png", 40, 56)
    cache = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "RERUN_ANALYTICS": "0"}
    mca = [sys.executable, "-m", "mca"]
    for run, workers in (("compiled", "2"), ("cached", "1")):
        done = subprocess.run(
            [*mca, "process", str(inputs), "-o", str(tmp_path / run), "--profile", "paper-70d", "--workers", workers],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        if run == "compiled":  # the second run must find every kernel in the cache, not compile them again
            cached = sorted(p.name.split("-")[0] for p in cache.rglob("*.nbi"))
            assert any(name.startswith("cost._cost_map") for name in cached), cached
            assert any(name.startswith("sampling._remap_linear") for name in cached), cached
    assert_same_outputs(tmp_path / "compiled", tmp_path / "cached")
