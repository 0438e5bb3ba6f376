"""Benchmark: a simulated 20 MP capture (half-resolution Bayer planes 2736x1824) through the pipeline, stage
timings and peak memory, beside one StereoSGBM pass on the same planes. Prints figures, asserts nothing.

    .venv/bin/python benchmarks/bench_pipeline.py [--scene paper-e] [--runs 3] [--scale 1.0]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import statistics
import time


def _child(planes, scene: str, scale: float, runs: int, queue) -> None:
    from mca.devices.profiles import load_profile
    from mca.devices.sim.render import SimulationOptics
    from mca.processing.peers import sgbm_disparity
    from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX, default_disparity_range_px, run_pipeline

    optics = SimulationOptics.from_profile(load_profile("paper-70d"), scale)
    base_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    timings, totals, cpus, sgbm = [], [], [], []
    regions = 0

    def cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    for _ in range(runs):
        start, cpu_start = time.perf_counter(), cpu_s()
        result = run_pipeline(
            planes, optics.aperture, optics.mca, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX
        )
        totals.append(time.perf_counter() - start)
        cpus.append(cpu_s() - cpu_start)
        timings.append(result.timings_s)
        regions = len(result.regions)
        del result
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    low, high = default_disparity_range_px(optics.aperture, optics.mca, (optics.height_px, optics.width_px))
    for _ in range(runs):
        start = time.perf_counter()
        sgbm_disparity(planes, optics.aperture, (low / 2, high / 2))
        sgbm.append(time.perf_counter() - start)
    queue.put((timings, totals, cpus, sgbm, regions, base_kb, peak_kb))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scene", default="paper-e")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--scale", type=float, default=1.0)
    args = parser.parse_args()

    from mca.devices.profiles import load_profile
    from mca.devices.sim.render import SensorModel, SimulationOptics, render
    from mca.devices.sim.scenes import paper_scene
    from mca.processing.evaluate import bayer_planes

    optics = SimulationOptics.from_profile(load_profile("paper-70d"), args.scale)
    sensor = SensorModel()
    start = time.perf_counter()
    rendering = render(paper_scene(args.scene, optics.focus_distance_mm), optics, sensor, seed=0)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    print(
        f"rendered {args.scene} {optics.width_px}x{optics.height_px} in {time.perf_counter() - start:.1f} s; "
        f"planes {planes.shape[1]}x{planes.shape[0]}"
    )
    queue = mp.get_context("spawn").Queue()
    process = mp.get_context("spawn").Process(target=_child, args=(planes, args.scene, args.scale, args.runs, queue))
    process.start()
    timings, totals, cpus, sgbm, regions, base_kb, peak_kb = queue.get()
    process.join()
    print(
        f"pipeline: {regions} regions, median of {args.runs} runs: total {statistics.median(totals):.2f} s "
        f"(CPU {statistics.median(cpus):.2f} s over all threads; a CPU close to the total on 2 cores means the "
        f"machine was busy with something else)"
    )
    for stage in timings[0]:
        if stage != "total":
            note = "  (part of depth)" if stage == "boundaries" else ""
            print(f"  {stage:<13} {statistics.median(t[stage] for t in timings):6.3f} s{note}")
    print(
        f"peak memory of the pipeline process: {peak_kb / 1024:.0f} MiB "
        f"({(peak_kb - base_kb) / 1024:.0f} MiB above its start with the planes loaded)"
    )
    print(f"StereoSGBM (one pass, widest pair, same planes): median {statistics.median(sgbm):.2f} s")


if __name__ == "__main__":
    main()
