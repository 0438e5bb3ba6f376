"""Benchmark: one simulated 20 MP CR2 through `process_file`, decode to written outputs, beside one StereoSGBM pass.

A simulated EOS 70D capture (5472 x 3648, `mca simulate --scene paper-c --profile paper-70d`) is
processed by `capture.pipeline_app.process_file` in a fresh process per run (so each run's peak
RSS, `ru_maxrss`, is its own), without and with recording (`--record`), runs alternating. Printed:
medians of the stage timings from result.json (read, the pipeline's stages, write), the wall time
of `process_file`, its CPU time, the peak RSS, the output files' sizes, the wall time of the whole
`mca process` command (interpreter start and imports included), and one StereoSGBM pass
(`processing.peers.sgbm_disparity`, widest pair) on the same planes, with our total over it.

Issue 4's target: <= 2 s wall from decode to written outputs per 20 MP capture on the 2-core
machine, peak memory <= 3 GB. On a shared machine the CPU seconds are the steadier figure.

    .venv/bin/python benchmarks/bench_process.py [--runs 3] [--scene paper-c] [--profile paper-70d]

Prints figures only; nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

STAGE_ORDER = ("read", "planes", "disparity", "sketch", "refine", "depth", "all_in_focus", "mpi", "pipeline", "write")


def _process_child(cr2: str, out: str, profile_name: str, record: bool, queue) -> None:
    """One `process_file` in a fresh process: its timings, wall and CPU time, peak RSS and output sizes."""
    from mca.capture.pipeline_app import RESULT_NAME, process_file
    from mca.capture.profiles import load_profile

    profile = load_profile(profile_name)
    record_path = Path(out) / "recording.rrd" if record else None
    cpu, wall = time.process_time(), time.perf_counter()
    outcome = process_file(cr2, out, profile, force=True, record_path=record_path)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    if outcome.status != "done":
        queue.put({"error": outcome.reason})
        return
    document = json.loads((outcome.output_dir / RESULT_NAME).read_text())
    sizes = {
        p.relative_to(outcome.output_dir).as_posix(): p.stat().st_size
        for p in sorted(outcome.output_dir.rglob("*"))
        if p.is_file()
    }
    if record_path is not None and record_path.is_file():
        sizes["(recording) " + record_path.name] = record_path.stat().st_size
    queue.put(
        {
            "timings": document["timings_s"],
            "wall": wall,
            "cpu": cpu,
            "sizes": sizes,
            "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        }
    )


def _sgbm_child(cr2: str, profile_name: str, runs: int, queue) -> None:
    """StereoSGBM on the very planes `process_file` reads from the CR2, with the pipeline's search range."""
    from mca.capture.pipeline_app import _optics_for, read_input
    from mca.capture.profiles import load_profile
    from mca.processing.peers import sgbm_disparity
    from mca.processing.pipeline import default_disparity_range_px

    profile = load_profile(profile_name)
    loaded = read_input(Path(cr2))
    optics = _optics_for(profile, loaded)
    width, height = loaded.input_size_px
    low, high = default_disparity_range_px(profile.aperture, optics, (height, width))
    scale = loaded.pixel_scale  # the range is in input pixels, SGBM works on the planes
    seconds = []
    for _ in range(runs):
        start = time.perf_counter()
        sgbm_disparity(loaded.planes, profile.aperture, (low / scale, high / scale))
        seconds.append(time.perf_counter() - start)
    queue.put(seconds)


def _in_child(target, *args):
    context = mp.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=target, args=args + (queue,))
    process.start()
    result = queue.get()
    process.join()
    return result


def _median(values) -> float:
    return statistics.median(list(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--scene", default="paper-c")
    parser.add_argument("--profile", default="paper-70d")
    args = parser.parse_args()

    from mca.capture.profiles import load_profile
    from mca.capture.simulated_shots import render_scene, write_capture

    with tempfile.TemporaryDirectory(prefix="bench_process_") as tmp:
        start = time.perf_counter()
        capture = render_scene(args.scene, load_profile(args.profile), size="full", seed=0)
        cr2 = str(write_capture(capture, load_profile(args.profile), Path(tmp) / "in")["cr2"])
        print(
            f"simulated {args.scene} ({args.profile}) in {time.perf_counter() - start:.1f} s: "
            f"{Path(cr2).name}, {Path(cr2).stat().st_size / 1e6:.1f} MB"
        )

        runs: dict[bool, list[dict]] = {False: [], True: []}
        cli_walls = []
        for _ in range(args.runs):
            for record in (False, True):
                result = _in_child(_process_child, cr2, str(Path(tmp) / f"out-{int(record)}"), args.profile, record)
                if "error" in result:
                    sys.exit(f"process_file failed: {result['error']}")
                runs[record].append(result)
            start = time.perf_counter()
            subprocess.run(
                [
                    str(Path(sys.executable).with_name("mca")),
                    "process",
                    cr2,
                    "--out",
                    str(Path(tmp) / "out-cli"),
                    "--profile",
                    args.profile,
                    "--force",
                    "-q",
                ],
                check=True,
                stdout=subprocess.DEVNULL,
            )
            cli_walls.append(time.perf_counter() - start)
        sgbm = _in_child(_sgbm_child, cr2, args.profile, args.runs)

    print(f"\nprocess_file, decode to written outputs, median of {args.runs} runs (seconds):")
    print(f"  {'stage':<14} {'plain':>8} {'--record':>9}")
    stages = [s for s in STAGE_ORDER if s in runs[False][0]["timings"]]
    stages += [s for s in runs[False][0]["timings"] if s not in stages and s != "total"]
    for stage in stages:
        plain = _median(r["timings"].get(stage, float("nan")) for r in runs[False])
        recorded = _median(r["timings"].get(stage, float("nan")) for r in runs[True])
        print(f"  {stage:<14} {plain:8.3f} {recorded:9.3f}")
    plain_wall = _median(r["wall"] for r in runs[False])
    record_wall = _median(r["wall"] for r in runs[True])
    print(
        f"  {'total (wall)':<14} {plain_wall:8.3f} {record_wall:9.3f}   runs: "
        f"{[round(r['wall'], 2) for r in runs[False]]} / {[round(r['wall'], 2) for r in runs[True]]}"
    )
    print(
        f"  {'total (CPU)':<14} {_median(r['cpu'] for r in runs[False]):8.3f} "
        f"{_median(r['cpu'] for r in runs[True]):9.3f}   (2 cores: CPU can exceed wall)"
    )
    print(
        f"  {'peak RSS MiB':<14} {_median(r['peak_mib'] for r in runs[False]):8.0f} "
        f"{_median(r['peak_mib'] for r in runs[True]):9.0f}   (whole process, ru_maxrss)"
    )
    print(
        f"mca process (the command, interpreter start and imports included): median {_median(cli_walls):.2f} s "
        f"wall, runs {[round(w, 2) for w in cli_walls]}"
    )
    print("outputs (bytes):")
    for name, size in runs[True][-1]["sizes"].items():
        print(f"  {name:<26} {size:>12,}")
    sgbm_s = _median(sgbm)
    print(f"StereoSGBM (one pass, widest pair, same planes): median {sgbm_s:.3f} s, runs {[round(s, 3) for s in sgbm]}")
    print(
        f"ours / StereoSGBM: {plain_wall / sgbm_s:.2f}x (process_file wall), "
        f"{_median(r['timings']['pipeline'] for r in runs[False]) / sgbm_s:.2f}x (pipeline alone), "
        f"{record_wall / sgbm_s:.2f}x (with --record)"
    )


if __name__ == "__main__":
    main()
