"""Benchmark: encoding a 20 MP EOS 70D mosaic as CR2 (target: median under 2 s on 2 cores), and reading it back.

Run: .venv/bin/python benchmarks/bench_cr2.py [--runs 5]
Prints figures only; nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from mca.capture.raw import read_raw
from mca.devices.sim.cr2 import EOS_70D_ACTIVE_HEIGHT_PX, EOS_70D_ACTIVE_WIDTH_PX, cr2_bytes


def _scene_mosaic(rng: np.random.Generator) -> np.ndarray:
    """A smooth gradient with photon-like noise: closer to a photograph than uniform noise."""
    h, w = EOS_70D_ACTIVE_HEIGHT_PX, EOS_70D_ACTIVE_WIDTH_PX
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    signal = 2048 + 9000 * (0.5 + 0.5 * np.sin(x / 300) * np.cos(y / 200))
    return np.clip(signal + rng.normal(0, 30, size=(h, w)), 0, 16383).astype(np.uint16)


def _median_s(fn, runs: int) -> tuple[float, list[float], float]:
    """Median wall time, all wall times, and median CPU time (all threads) of `fn`, in seconds."""
    times, cpu = [], []
    for _ in range(runs):
        c, t = time.process_time(), time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return statistics.median(times), times, statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    mosaics = {
        "uniform 14-bit noise (worst case)": rng.integers(
            0, 1 << 14, size=(EOS_70D_ACTIVE_HEIGHT_PX, EOS_70D_ACTIVE_WIDTH_PX), dtype=np.uint16
        ),
        "smooth scene + noise": _scene_mosaic(rng),
    }
    print(
        f"CR2 encode, {EOS_70D_ACTIVE_WIDTH_PX}x{EOS_70D_ACTIVE_HEIGHT_PX} mosaic, {os.cpu_count()} CPUs, {args.runs} runs"
    )
    for name, mosaic in mosaics.items():
        for preview in (False, True):
            size = len(cr2_bytes(mosaic, preview=preview))
            med, times, cpu = _median_s(lambda m=mosaic, p=preview: cr2_bytes(m, preview=p), args.runs)
            print(
                f"  {name:36s} preview={preview!s:5s} median {med:.2f} s "
                f"(min {min(times):.2f}, max {max(times):.2f}; CPU {cpu:.2f} s), file {size / 1e6:.1f} MB"
            )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "IMG_0001.CR2"
        path.write_bytes(cr2_bytes(mosaics["smooth scene + noise"]))
        med, times, cpu = _median_s(lambda: read_raw(path), args.runs)
        print(
            f"read_raw of that file (LibRaw decode + planes): median {med:.2f} s (min {min(times):.2f}, max {max(times):.2f}; CPU {cpu:.2f} s)"
        )
    print(f"load average while running: {os.getloadavg()[0]:.1f} (figures are only comparable on an idle machine)")


if __name__ == "__main__":
    main()
