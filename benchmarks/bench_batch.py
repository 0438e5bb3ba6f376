"""Benchmark: `mca process` over a folder of simulated 20 MP CR2s with 1 and 2 workers.

Prints files per minute, the scaling efficiency (throughput with N workers / N x throughput
with one) and the peak resident memory of any one process (a worker). Each configuration runs
as its own `mca process` subprocess, several times; medians are reported. Asserts nothing.

    .venv/bin/python benchmarks/bench_batch.py [--files 20] [--runs 2] [--size full]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def make_inputs(folder: Path, count: int, size: str) -> None:
    from mca.devices.profiles import load_profile
    from mca.devices.sim.scenes import scene_names
    from mca.devices.sim.world import capture_cr2_bytes, render_scene

    profile = load_profile("paper-70d")
    scenes = scene_names()
    folder.mkdir(parents=True, exist_ok=True)
    cache: dict[str, bytes] = {}
    for index in range(count):
        scene = scenes[index % len(scenes)]
        if scene not in cache:
            cache[scene] = capture_cr2_bytes(render_scene(scene, profile, size=size, seed=index), profile)
        (folder / f"shot_{index:03d}.CR2").write_bytes(cache[scene])
        print(f"\r  inputs: {index + 1}/{count}", end="", flush=True)
    print()


# Runs `mca process` and prints the largest peak RSS among the processes it started (workers included):
# a fresh wrapper per run, so one configuration's peak does not carry over into the next.
WRAPPER = """
import resource, subprocess, sys
subprocess.run(sys.argv[1:], check=False, stdout=subprocess.DEVNULL)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def run_once(inputs: Path, workers: int) -> tuple[float, float]:
    """Seconds for one `mca process` run and the peak RSS (MiB) of the largest process it started."""
    out = Path(tempfile.mkdtemp(prefix="bench-batch-out-"))
    started = time.perf_counter()
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            WRAPPER,
            sys.executable,
            "-m",
            "mca",
            "process",
            str(inputs),
            "--out",
            str(out),
            "--workers",
            str(workers),
            "--quiet",
        ],
        check=False,
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - started
    shutil.rmtree(out, ignore_errors=True)
    return seconds, int(done.stdout.strip().splitlines()[-1]) / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=20)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--size", default="full", help="full (20 MP), small, or a scale")
    args = parser.parse_args()
    size: str | float = args.size
    try:
        size = float(args.size)
    except ValueError:
        pass

    work = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    try:
        print(f"making {args.files} simulated CR2s ({args.size}) in {work}")
        make_inputs(work / "in", args.files, size)
        print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
        rates: dict[int, float] = {}
        for workers in (1, 2):
            times, peaks = [], []
            for run in range(args.runs):
                seconds, peak = run_once(work / "in", workers)
                times.append(seconds)
                peaks.append(peak)
                print(f"  workers={workers} run {run + 1}: {seconds:6.1f} s")
            median = statistics.median(times)
            rates[workers] = args.files / median * 60.0
            print(
                f"workers={workers}: median {median:.1f} s, {rates[workers]:.1f} files/min, "
                f"peak memory of one process {max(peaks):.0f} MiB"
            )
        print(
            f"scaling efficiency with 2 workers: {rates[2] / (2 * rates[1]):.2f} "
            f"(speed-up {rates[2] / rates[1]:.2f}x on {os.cpu_count()} cores)"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
