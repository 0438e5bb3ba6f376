"""Benchmark (issue 16): 20 MP captures through `mca process`, stage by stage, beside StereoSGBM and LibRaw's unpack.

Inputs, both 5472 x 3648 CR2s from the simulator:

- `sim`: a paper scene (`mca simulate --scene paper-c`, rendered here in about 10 s);
- `rgbd`: a real photograph with its depth, rendered at 20 MP through the CR2 writer
  (`mca simulate --from-rgbd <middlebury>/Art/im.png .../disp.png --full-size --format cr2`, its
  profile from the render's truth/). That render takes minutes, so it is kept in `--cache`.

For each input, every run (after one warm-up, which fills numba's cache) starts fresh processes for:
`mca process` plain, with `--record`, and with `--quality preview` (wall time of the command,
interpreter start and imports included, and its peak RSS); the stage timings from the result.json
each run writes; one OpenCV StereoSGBM pass on the same Bayer planes with the pipeline's search
range (`processing.peers.sgbm_disparity`); and LibRaw's unpack of the file (`rawpy.imread(...)
.raw_image` copied). The ratios are taken run by run, so that a busy machine slows both sides of
each ratio alike, and their medians printed.

Then the throughput of `mca process` over a folder of `--files` captures (copies of `sim`) with
`--workers 1`, `--workers 2`, and `--workers 2` with every library's threads unlimited
(`MCA_WORKER_THREADS=0`, as before the workers got their share), and the scaling efficiency
t1 / (2 t2).

    .venv/bin/python benchmarks/bench_process.py [--runs 5] [--quick] [--files 20] [--no-batch] [--no-rgbd]

Prints figures only; nothing here asserts a time. On a shared machine the ratios are the figures to compare.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mca.capture.pipeline_app import STAGES

# the progress stages (the wait for the kernels' warm-up after the read), the pipeline's total before the writes
STAGE_ORDER = (STAGES[0], "kernels", *STAGES[1:-1], "pipeline", STAGES[-1])
MCA = str(Path(sys.executable).with_name("mca"))
REPO = Path(__file__).resolve().parents[1]
MIDDLEBURY = REPO.parent / "shared" / "data" / "middlebury"

# Runs a command and prints the peak RSS (KiB) of the largest process it started (workers included).
WRAPPER = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
if done.returncode:
    sys.stderr.write(done.stderr)
print(done.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def run_mca(args: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall seconds and peak RSS (MiB) of one `mca ...` command in a fresh process."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", WRAPPER, MCA, *args],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        check=False,
    )
    wall = time.perf_counter() - start
    code, peak_kib = done.stdout.split()[-2:]
    if int(code) != 0:
        sys.exit(f"mca {' '.join(args)} failed ({code}):\n{done.stderr}")
    return wall, int(peak_kib) / 1024.0


def _peers_child(cr2: str, profile_name: str, queue) -> None:
    """One LibRaw unpack and one StereoSGBM pass (on the planes `mca process` reads, its search range)."""
    import rawpy

    from mca.capture.api import optics_for, read_input
    from mca.devices.profiles import load_profile
    from mca.processing.peers import sgbm_disparity
    from mca.processing.pipeline import default_disparity_range_px

    start = time.perf_counter()
    with rawpy.imread(cr2) as raw:
        raw.raw_image.copy()
    libraw_s = time.perf_counter() - start
    profile = load_profile(profile_name)
    loaded = read_input(Path(cr2))
    optics = optics_for(profile, loaded)
    width, height = loaded.input_size_px
    low, high = default_disparity_range_px(profile.aperture, optics, (height, width))
    scale = loaded.pixel_scale  # the range is in input pixels, SGBM works on the planes
    start = time.perf_counter()
    sgbm_disparity(loaded.planes, profile.aperture, (low / scale, high / scale))
    queue.put({"libraw": libraw_s, "sgbm": time.perf_counter() - start})


def peers(cr2: Path, profile: str) -> dict[str, float]:
    context = mp.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=_peers_child, args=(str(cr2), profile, queue))
    process.start()
    result = queue.get()
    process.join()
    return result


def _median(values) -> float:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else float("nan")


def make_sim(folder: Path, scene: str, scale: float = 1.0) -> tuple[Path, str]:
    from mca.capture.simulated_shots import write_capture
    from mca.devices.profiles import load_profile
    from mca.devices.sim.world import render_scene

    profile = load_profile("paper-70d")
    capture = render_scene(scene, profile, size="full" if scale == 1.0 else scale, seed=0)
    return Path(write_capture(capture, profile, folder)["cr2"]), "paper-70d"


def make_rgbd(cache: Path, scene: str) -> tuple[Path, str]:
    """The 20 MP render of a Middlebury scene, from the cache or rendered into it (minutes)."""
    folder = cache / f"{scene}-20mp"
    cr2, profile = folder / f"{scene}.CR2", folder / "truth" / f"{scene}.profile.toml"
    if cr2.is_file() and profile.is_file():
        return cr2, str(profile)
    source = MIDDLEBURY / scene
    print(f"rendering {scene} at 20 MP into {folder} (minutes; kept for the next run)", flush=True)
    subprocess.run(
        [MCA, "simulate", "--from-rgbd", str(source / "im.png"), str(source / "disp.png")]
        + ["--full-size", "--format", "cr2", "--out", str(folder)],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return cr2, str(profile)


def bench_input(label: str, cr2: Path, profile: str, runs: int, work: Path) -> dict:
    out = work / f"out-{label}"
    common = [str(cr2), "--out", str(out), "--profile", profile, "--force", "-q"]
    variants = {
        "plain": common,
        "--record": common + ["--record", str(work / f"{label}.rrd")],
        "preview": common + ["--quality", "preview"],
    }
    if "--quality" not in subprocess.run([MCA, "process", "--help"], capture_output=True, text=True).stdout:
        del variants["preview"]  # an mca before --quality (a before/after comparison)
    print(f"{label}: {cr2.name}, {cr2.stat().st_size / 1e6:.1f} MB; warm-up run", flush=True)
    run_mca(["process", *common])
    rows: list[dict] = []
    for run in range(runs):
        row: dict = {}
        for name, args in variants.items():
            wall, peak = run_mca(["process", *args])
            document = json.loads((out / cr2.stem / "result.json").read_text())
            row[name] = {"wall": wall, "peak": peak, "timings": document["timings_s"]}
        row.update(peers(cr2, profile))
        rows.append(row)
        walls = ", ".join(f"{name} {row[name]['wall']:.2f} s" for name in variants)
        print(f"  run {run + 1}/{runs}: {walls}, SGBM {row['sgbm']:.2f} s, LibRaw {row['libraw']:.2f} s", flush=True)
    folder = out / cr2.stem
    sizes = {p.relative_to(folder).as_posix(): p.stat().st_size for p in sorted(folder.rglob("*")) if p.is_file()}
    return {"rows": rows, "sizes": sizes}


def report_input(label: str, data: dict, runs: int) -> None:
    rows = data["rows"]
    names = [n for n in ("plain", "--record", "preview") if n in rows[0]]
    print(f"\n== {label}: `mca process`, median of {runs} runs (seconds) ==")
    print(f"  {'stage':<26}" + "".join(f"{n:>10}" for n in names))
    keys = [s for s in STAGE_ORDER if any(s in r[n]["timings"] for r in rows for n in names)]
    extra = sorted({k for r in rows for n in names for k in r[n]["timings"]} - set(keys) - {"total"})
    for key in keys + [k for k in extra if not k.startswith("write ")] + [k for k in extra if k.startswith("write ")]:
        cells = "".join(f"{_median(r[n]['timings'].get(key) for r in rows):10.3f}" for n in names)
        print(f"  {key:<26}{cells}")
    print(f"  {'mca process (wall)':<26}" + "".join(f"{_median(r[n]['wall'] for r in rows):10.3f}" for n in names))
    print(f"  {'peak RSS (MiB)':<26}" + "".join(f"{_median(r[n]['peak'] for r in rows):10.0f}" for n in names))
    print("  ('write <file>': seconds each file took on its writer thread; they overlap one another)")
    sgbm, libraw = _median(r["sgbm"] for r in rows), _median(r["libraw"] for r in rows)
    print(f"  one StereoSGBM pass {sgbm:.3f} s, LibRaw unpack {libraw:.3f} s (medians)")
    for name in names:
        over_sgbm = _median(r[name]["wall"] / r["sgbm"] for r in rows)
        over_libraw = _median(r[name]["wall"] / r["libraw"] for r in rows)
        pipeline = _median(r[name]["timings"].get("pipeline", float("nan")) / r["sgbm"] for r in rows)
        print(
            f"  {name:<9} mca process / SGBM {over_sgbm:5.2f}x  (pipeline alone {pipeline:4.2f}x),  "
            f"/ LibRaw unpack {over_libraw:5.2f}x"
        )
    layers = sum(v for k, v in data["sizes"].items() if k.startswith("layers/"))
    files = ", ".join(f"{k} {v:,}" for k, v in data["sizes"].items() if not k.startswith("layers/"))
    print(f"  outputs (bytes): {files}, layers/ {layers:,}")


def bench_batch(cr2: Path, files: int, work: Path) -> None:
    """`mca process` over `files` copies of `cr2` with 1 and 2 workers (and 2 with unlimited threads)."""
    folder = work / "batch-in"
    folder.mkdir(exist_ok=True)
    for index in range(files):
        target = folder / f"shot_{index:03d}.CR2"
        if not target.exists():
            shutil.copyfile(cr2, target)
    print(f"\n== throughput: `mca process` over {files} copies of {cr2.name} ({os.cpu_count()} cores) ==", flush=True)
    configs = (
        ("--workers 1", 1, {}),
        ("--workers 2", 2, {}),
        ("--workers 2, threads unlimited", 2, {"MCA_WORKER_THREADS": "0"}),
    )
    seconds: dict[str, float] = {}
    for name, workers, env in configs:
        out = work / "batch-out"
        shutil.rmtree(out, ignore_errors=True)
        wall, peak = run_mca(["process", str(folder), "--out", str(out), "--workers", str(workers), "-q"], env)
        seconds[name] = wall
        print(
            f"  {name:<32} {wall:7.1f} s  {files / wall * 60:6.1f} files/min  peak {peak:.0f} MiB per process  "
            f"(load {os.getloadavg()[0]:.1f})",
            flush=True,
        )
    t1 = seconds["--workers 1"]
    for name in ("--workers 2", "--workers 2, threads unlimited"):
        print(f"  scaling efficiency t1 / (2 t2), {name}: {t1 / (2 * seconds[name]):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5, help="timed runs per input (default 5)")
    parser.add_argument("--quick", action="store_true", help="2 runs, a batch of 6 files")
    parser.add_argument("--files", type=int, default=20, help="captures in the throughput batch")
    parser.add_argument("--scene", default="paper-c", help="the simulated paper scene")
    parser.add_argument("--rgbd-scene", default="Art", help="the Middlebury scene rendered at 20 MP")
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "mca-bench", help="keeps the render")
    parser.add_argument("--no-batch", action="store_true")
    parser.add_argument(
        "--batch-scale", type=float, default=1.0, help="size of the batch's captures (1 = 20 MP; 0.5 = 5 MP, quicker)"
    )
    parser.add_argument("--only-batch", action="store_true", help="just the throughput figures")
    parser.add_argument("--no-rgbd", action="store_true")
    args = parser.parse_args()
    runs, files = (2, min(6, args.files)) if args.quick else (args.runs, args.files)

    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="bench_process_") as tmp:
        work = Path(tmp)
        start = time.perf_counter()
        sim, sim_profile = make_sim(work / "sim", args.scene)
        print(f"simulated {args.scene} in {time.perf_counter() - start:.1f} s")
        inputs = [] if args.only_batch else [(f"sim {args.scene}", sim, sim_profile)]
        if not (args.no_rgbd or args.only_batch):
            rgbd, rgbd_profile = make_rgbd(args.cache, args.rgbd_scene)
            inputs.append((f"rgbd {args.rgbd_scene}", rgbd, rgbd_profile))
        results = {label: bench_input(label.split()[0], cr2, prof, runs, work) for label, cr2, prof in inputs}
        for label, data in results.items():
            report_input(label, data, runs)
        if not args.no_batch:
            batch_input = sim
            if args.batch_scale != 1.0:
                batch_input, _ = make_sim(work / "batch-sim", args.scene, args.batch_scale)
            bench_batch(batch_input, files, work)
    print(f"\nload average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
