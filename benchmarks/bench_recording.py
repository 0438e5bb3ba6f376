"""Benchmark: the cost of recording a 20 MP capture with rerun, as pipeline time with recording over without.

A synthetic EOS 70D capture (5472 x 3648 input pixels, half-resolution Bayer planes 2736 x 1824)
of three textured planes at different distances goes through `processing.pipeline.run_pipeline`
alone, and through the same call wrapped the way `mca process --record` wraps it (RerunRecorder,
begin_shot, log_input, the stages' record/timing calls, log_result, close). Runs alternate; the
medians and their ratio are printed (the issue's target: ratio <= 1.3). Without the pipeline, the
recorder is driven with a synthetic 20 MP DepthResult and only the recording time is printed.

The recorder's own time (inside its calls) is printed too: on a shared machine it is the steadier figure.

Run: .venv/bin/python benchmarks/bench_recording.py [--runs 3]
Prints figures only; nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np

from mca.capture.recording import RerunRecorder
from mca.devices.profiles import load_profile
from mca.processing.optics import MCAOptics

INPUT_W, INPUT_H = 5472, 3648
PLANE_W, PLANE_H = INPUT_W // 2, INPUT_H // 2


def _texture(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """Band-limited colour texture in [0.05, 0.95]: something the disparity search can lock onto."""
    small = rng.random((shape[0] // 4, shape[1] // 4, 3), dtype=np.float32)
    big = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return np.clip(0.05 + 0.9 * cv2.GaussianBlur(big, (0, 0), 1.5), 0.0, 1.0)


def synthetic_planes(profile, optics: MCAOptics) -> np.ndarray:
    """Half-resolution planes of a background and two boxes, each channel displaced by its region's disparity."""
    from mca.processing.disparity import shift_channels

    rng = np.random.default_rng(0)
    planes = np.zeros((PLANE_H, PLANE_W, 3), np.float32)
    layers = [((0, 0, PLANE_W, PLANE_H), 1150.0), ((300, 250, 1300, 1200), 1000.0), ((1500, 700, 2500, 1600), 900.0)]
    for (x0, y0, x1, y1), distance_mm in layers:  # back to front
        disparity_plane_px = float(optics.disparity_px_at_distance(distance_mm)) / 2.0
        texture = _texture(rng, (PLANE_H, PLANE_W))
        cover = np.zeros((PLANE_H, PLANE_W, 3), np.float32)
        cover[y0:y1, x0:x1] = 1.0
        # channel c of a point at disparity d appears displaced by -d * s_c: undo `shift_channels`
        texture = shift_channels(texture, profile.aperture, -disparity_plane_px)
        cover = shift_channels(cover, profile.aperture, -disparity_plane_px)
        planes = texture * cover + planes * (1.0 - cover)
    return planes


def _frame(planes: np.ndarray, pitch_mm: float):
    from mca.capture.raw import RawFrame, RawMetadata

    meta = RawMetadata(
        make="Canon", model="Canon EOS 70D", capture_time=datetime(2024, 1, 1, 12, 0, 0), photosite_pitch_mm=pitch_mm
    )
    return RawFrame(
        planes=planes,
        pixel_pitch_mm=2 * pitch_mm,
        source_format="cr2",
        metadata=meta,
        path=Path("synthetic-20MP.CR2"),
        half_resolution=True,
    )


class _Clock:
    """Wall time spent inside the recorder, by call."""

    def __init__(self) -> None:
        self.parts: dict[str, float] = {}

    def timed(self, name: str, fn, *args, **kwargs):
        start = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.parts[name] = self.parts.get(name, 0.0) + time.perf_counter() - start


class _TimedRecorder:
    """Forwards to the RerunRecorder, timing its record/timing calls."""

    def __init__(self, inner: RerunRecorder, clock: _Clock) -> None:
        self.inner, self.clock = inner, clock

    def record(self, stage: str, **items) -> None:
        self.clock.timed("record()", self.inner.record, stage, **items)

    def timing(self, stage: str, seconds: float) -> None:
        self.clock.timed("timing()", self.inner.timing, stage, seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    profile = load_profile("paper-70d")
    pitch = profile.pixel_pitch_mm
    optics = MCAOptics.from_profile(profile, pixel_pitch_mm=pitch)
    planes = synthetic_planes(profile, optics)
    frame = _frame(planes, pitch)
    try:
        from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX, run_pipeline
    except ImportError:
        run_pipeline = None
    print(
        f"recording cost, {INPUT_W}x{INPUT_H} input ({PLANE_W}x{PLANE_H} planes), {os.cpu_count()} CPUs, "
        f"{args.runs} runs each"
    )
    with tempfile.TemporaryDirectory() as tmp:
        if run_pipeline is None:
            _recorder_only(Path(tmp), frame, profile, optics, args.runs)
            return
        without, with_recording, recording_parts, sizes = [], [], [], []

        def pipeline_alone() -> None:
            start = time.perf_counter()
            run_pipeline(planes, profile.aperture, optics, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX)
            without.append(time.perf_counter() - start)

        start = time.perf_counter()
        import rerun  # noqa: F401  (import and warm-up outside the timed runs, like a long-running process)

        run_pipeline(planes, profile.aperture, optics, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX)
        print(f"  warm-up run (and import rerun) {time.perf_counter() - start:.2f} s, not counted")
        for run in range(args.runs):
            if run % 2 == 0:  # alternate which goes first, so drift of a shared machine hits both alike
                pipeline_alone()
            clock = _Clock()
            path = Path(tmp) / f"run{run}.rrd"
            start = time.perf_counter()
            recorder = clock.timed("RerunRecorder()", RerunRecorder, path)
            clock.timed("begin_shot()", recorder.begin_shot, run, "synthetic", datetime(2024, 1, 1), profile)
            clock.timed("log_input()", recorder.log_input, frame)
            result = run_pipeline(
                planes,
                profile.aperture,
                optics,
                pixel_scale=2.0,
                channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX,
                recorder=_TimedRecorder(recorder, clock),
            )
            clock.timed("log_result()", recorder.log_result, result, profile, optics)
            clock.timed("close()", recorder.close)
            with_recording.append(time.perf_counter() - start)
            recording_parts.append(clock.parts)
            sizes.append(path.stat().st_size)
            if run % 2 == 1:
                pipeline_alone()
            print(
                f"  run {run}: pipeline {without[-1]:.2f} s, with recording {with_recording[-1]:.2f} s "
                f"({len(result.regions)} regions, {len(result.layers)} layers)"
            )
        base, recorded = statistics.median(without), statistics.median(with_recording)
        print(f"pipeline alone        median {base:.2f} s (min {min(without):.2f}, max {max(without):.2f})")
        print(
            f"pipeline + recording  median {recorded:.2f} s (min {min(with_recording):.2f}, "
            f"max {max(with_recording):.2f})"
        )
        own = statistics.median(sum(p.values()) for p in recording_parts)
        print(f"ratio                 {recorded / base:.2f}  (target <= 1.3; wall clock, noisy on a shared machine)")
        print(f"recorder's own time   median {own:.2f} s: ratio 1 + {own:.2f} / {base:.2f} = {1 + own / base:.3f}")
        print(f"recording file        {statistics.median(sizes) / 1e6:.1f} MB")
        print("time inside the recorder (median per call kind):")
        for name in recording_parts[0]:
            print(f"  {name:16s} {statistics.median(p.get(name, 0.0) for p in recording_parts):.3f} s")


def _recorder_only(folder: Path, frame, profile, optics: MCAOptics, runs: int) -> None:
    """No pipeline here: time the recorder alone on a synthetic 20 MP DepthResult."""
    from mca.processing.result import DepthResult, MultiPlaneImage, Region

    h, w = PLANE_H, PLANE_W
    labels = np.ones((h, w), np.uint16)
    labels[250:1200, 300:1300] = 2
    labels[700:1600, 1500:2500] = 3
    distance = {1: 1150.0, 2: 1000.0, 3: 900.0}
    disparity = {i: float(optics.disparity_px_at_distance(d)) for i, d in distance.items()}
    disp = np.zeros((h, w), np.float32)
    for i, d in disparity.items():
        disp[labels == i] = d
    regions = [
        Region(
            id=i,
            pixels=int((labels == i).sum()),
            order=o,
            occludes=[1] if i > 1 else [],
            disparity_px=disparity[i],
            distance_mm=distance[i],
        )
        for i, o in ((1, 2), (2, 1), (3, 0))
    ]
    layers = [
        MultiPlaneImage(i, np.dstack([frame.planes, (labels == i).astype(np.float32)]), None, None, disparity[i])
        for i in (1, 2, 3)
    ]
    result = DepthResult(
        labels,
        disp,
        disp,
        np.ones((h, w), np.float32),
        optics.distance_mm(disp).astype(np.float32),
        frame.planes,
        regions,
        2,
        layers,
        pixel_scale=2.0,
    )
    times = []
    for run in range(runs):
        start = time.perf_counter()
        with RerunRecorder(folder / f"r{run}.rrd") as recorder:
            recorder.begin_shot(run, "synthetic", datetime(2024, 1, 1), profile)
            recorder.log_input(frame)
            recorder.log_result(result, profile, optics)
        times.append(time.perf_counter() - start)
    print("processing.pipeline is not available: recording time alone, synthetic 20 MP DepthResult")
    print(f"recording             median {statistics.median(times):.2f} s (min {min(times):.2f}, max {max(times):.2f})")


if __name__ == "__main__":
    main()
