"""Live-view benchmark: frames per second of `mca capture --live` against the simulated 70D, at the 70D's
live-view size (960 x 540), preview included, logged to a rerun file.

Run: `.venv/bin/python benchmarks/bench_live.py [--runs 5] [--frames 40]`. Prints the median over runs of the
frame rate (whole loop: GetViewFinderData over the simulated USB stack, JPEG decode, disparity preview,
rerun logging) and of the preview alone; asserts nothing about time.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("RERUN_ANALYTICS", "0")

from mca.capture.live import run_live
from mca.devices.cameras import make_sim_rig, open_camera


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    rig = make_sim_rig(lambda i: ("IMG.CR2", b"II*\x00"))
    factory = open_camera("sim", rig=rig)
    rates, previews = [], []
    with tempfile.TemporaryDirectory() as tmp:
        run_live(factory, record=Path(tmp) / "warm.rrd", frames=2)  # renders the simulated scene once
        for run in range(args.runs):
            stats = run_live(factory, record=Path(tmp) / f"live{run}.rrd", frames=args.frames)
            rates.append(stats.frames_per_s)
            previews.append(stats.preview_ms_median)
            print(
                f"run {run + 1}: {stats.frames} frames of {stats.width_px}x{stats.height_px} px, "
                f"{stats.frames_per_s:.1f} frames/s, preview {stats.preview_ms_median:.1f} ms"
            )
    print(f"cores available: {len(os.sched_getaffinity(0))}")
    print(f"live view, median over {args.runs} runs: {statistics.median(rates):.1f} frames/s (target >= 5)")
    print(f"disparity preview alone, median: {statistics.median(previews):.1f} ms per frame")


if __name__ == "__main__":
    main()
