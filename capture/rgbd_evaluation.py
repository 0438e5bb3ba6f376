"""`mca evaluate --rgbd`: our pipeline and its peers on rendered real scenes, scored per pixel against the truth.

A render folder (written by `mca simulate --from-rgbd ...`) holds captures and, in `truth/`,
each capture's `<name>.json`, `<name>.disparity.tiff` (red-blue px, NaN unknown),
`<name>.distance.tiff` (mm) and `<name>.profile.toml` (the profile focused as rendered).
Folders below the given one are found too; each is a group (e.g. `tuning`, `held-out`) with
its own median and worst.

Methods:
- `ours`: the capture through `process_file`, exactly as `mca process FILE --profile truth/<name>.profile.toml`
  runs it (read_input, the optics, the default pipeline), scored on the depth map it writes
  (depth.tiff), turned back into red-blue disparity by the same optics (exact, eqs. 2 and 13/14);
- `ours-raw`: the pipeline's per-pixel disparity before region models (`DepthResult.raw_disparity_px`);
- `wta`: colour-line winner-takes-all, 15x15 window, 81 steps over the same search range
  (`processing.peers.colour_line_wta_subpixel`);
- `bando`: Bando et al. 2008's released program (`capture.peer_bando`), when built.
The peers run on the same planes the pipeline gets (Bayer planes moved to common sample
positions); their answers are cached in `.peers/` of the render folder, keyed by what decides them: the planes
they were given, the search range, the method's parameters and its code (`peer_code_digest`: our modules it runs,
numpy's and OpenCV's versions, the program's bytes). A second evaluation only reruns `ours`; a change to a
peer's code or to how a capture is read makes the peer run again.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.capture.simulated_shots import TRUTH_DIR
from mca.processing.evaluate import (
    FAR_FROM_EDGE_PX,
    PixelMetrics,
    RgbdRow,
    depth_edge_band,
    depth_edges,
    pixel_metrics,
)

METHODS = ("ours", "ours-raw", "wta", "bando")
PEER_CACHE_DIR = ".peers"
WTA_WINDOW_PX = 15
WTA_STEPS = 81


@dataclass
class RenderEntry:
    """One capture of a render folder and where its truth lies."""

    name: str
    group: str  # folder relative to the evaluated root ("." for the root itself)
    image_path: Path
    truth_dir: Path
    truth: dict[str, Any]

    def truth_file(self, key: str) -> Path:
        return self.truth_dir / self.truth["files"][key]


def find_renders(root: str | Path) -> list[RenderEntry]:
    """Every RGB-D capture under `root` (the folder and its subfolders) with its truth, sorted by group, name.

    Raises FileNotFoundError naming the folder when it holds none."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder; render one with `mca simulate --from-rgbd-tree`")
    entries = []
    for truth_path in sorted(root.rglob(f"{TRUTH_DIR}/*.json")):
        try:
            truth = json.loads(truth_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(truth, dict) or truth.get("kind") != "rgbd":
            continue
        folder = truth_path.parent.parent
        group = folder.relative_to(root).as_posix()
        entries.append(RenderEntry(truth["scene"], group, folder / truth["image"], truth_path.parent, truth))
    if not entries:
        raise FileNotFoundError(
            f"{root}: no rendered scene (no {TRUTH_DIR}/*.json of an RGB-D render); "
            "render some with `mca simulate --from-rgbd-tree ../shared/data/middlebury --out DIR`"
        )
    return sorted(entries, key=lambda e: (e.group, e.name))


def _read_float_tiff(path: Path) -> np.ndarray:
    import tifffile

    return np.asarray(tifffile.imread(path), np.float32)


@dataclass
class Estimate:
    """One method's answer at the input size: red-blue disparity (px) and distance (mm), NaN = no value."""

    disparity_px: np.ndarray
    distance_mm: np.ndarray | None
    seconds: float


@dataclass
class _Context:
    """What the methods share for one capture: the loaded input, its optics and search range."""

    loaded: Any
    optics: Any
    range_input_px: tuple[float, float]
    aligned: np.ndarray | None = None

    def planes(self) -> np.ndarray:
        """The planes at processing resolution with the Bayer sample offsets removed (what the peers see)."""
        if self.aligned is None:
            from mca.capture.api import bayer_channel_offsets_px
            from mca.devices.sim.render import shift_image

            planes = np.asarray(self.loaded.planes, np.float32)
            offsets = None
            if self.loaded.frame.half_resolution:
                offsets = bayer_channel_offsets_px(self.loaded.metadata.get("cfa_pattern"))
            if offsets is not None:
                import cv2

                margin = 8
                moved = []
                for c, (dx, dy) in enumerate(offsets):
                    padded = cv2.copyMakeBorder(planes[..., c], margin, margin, margin, margin, cv2.BORDER_REFLECT_101)
                    moved.append(shift_image(padded, (-dx, -dy))[margin:-margin, margin:-margin])
                planes = np.dstack(moved).astype(np.float32)
            self.aligned = planes
        return self.aligned


def _context(entry: RenderEntry, profile: Any) -> _Context:
    from mca.capture.pipeline_app import read_input
    from mca.processing.optics import MCAOptics
    from mca.processing.pipeline import default_disparity_range_px

    loaded = read_input(entry.image_path)
    optics = MCAOptics.from_profile(profile, pixel_pitch_mm=loaded.pixel_pitch_mm or profile.pixel_pitch_mm)
    width, height = loaded.input_size_px
    low, high = default_disparity_range_px(profile.aperture, optics, (height, width))
    return _Context(loaded, optics, (float(low), float(high)))


def _to_input(array: np.ndarray, pixel_scale: float, size: tuple[int, int]) -> np.ndarray:
    from mca.capture.pipeline_app import upsample_nearest

    return np.asarray(upsample_nearest(np.asarray(array, np.float32), pixel_scale, size), np.float32)


def run_ours(entry: RenderEntry, profile: Any, out_root: Path) -> tuple[Estimate, Estimate | None]:
    """Our pipeline through `process_file` (as `mca process`); returns the written depth map's estimate and the
    per-pixel raw disparity's (None when the result has none). Raises RuntimeError with the failure's reason."""
    from mca.capture.pipeline_app import process_file
    from mca.processing.pipeline import run_pipeline

    captured: dict[str, Any] = {}

    def pipeline(planes: np.ndarray, aperture: Any, optics: Any, **kwargs: Any) -> Any:
        started = time.perf_counter()
        result = run_pipeline(planes, aperture, optics, **kwargs)
        captured.update(result=result, optics=optics, seconds=time.perf_counter() - started)
        return result

    outcome = process_file(entry.image_path, out_root, profile, force=True, pipeline=pipeline)
    if outcome.status != "done":
        raise RuntimeError(outcome.reason or outcome.status)
    result, optics = captured["result"], captured["optics"]
    size = (int(entry.truth["optics"]["width_px"]), int(entry.truth["optics"]["height_px"]))
    written = out_root / outcome.output_dir.name / "depth.tiff"
    distance = _read_float_tiff(written) if written.is_file() else _to_input(result.depth_mm, result.pixel_scale, size)
    distance = np.where(np.isfinite(distance) & (distance > 0), distance, np.nan).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        disparity = np.asarray(optics.disparity_px_at_distance(distance.astype(np.float64)), np.float32)
    ours = Estimate(disparity, distance, captured["seconds"])
    raw = getattr(result, "raw_disparity_px", None)
    ours_raw = None
    if raw is not None:
        raw_input = _to_input(raw, result.pixel_scale, size)
        with np.errstate(invalid="ignore", divide="ignore"):
            raw_distance = np.asarray(optics.distance_mm(raw_input.astype(np.float64)), np.float32)
        raw_distance[~np.isfinite(raw_input)] = np.nan
        ours_raw = Estimate(raw_input, raw_distance, captured["seconds"])
    return ours, ours_raw


@dataclass
class KeptRun:
    """One render through the default pipeline in-process, its run kept for the stages' intermediate maps."""

    run: Any  # `processing.pipeline.finished_run`'s run: dense, surfaces, small, aperture, to_input, ...
    result: Any  # the `DepthResult` it made
    truth_px: np.ndarray  # the truth's red-blue disparity in input px (NaN unknown)


def run_kept(image_path: str | Path, truth_dir: str | Path, truth: dict[str, Any]) -> KeptRun | str:
    """`mca process`'s pipeline on one render (`capture.api.run_depth`, the render's own profile from its truth/)
    with its run kept (`pipeline.finished_run`), for the benchmarks that score the stages' maps; a sentence saying
    why not when the render is larger than the analysis grid or a Bayer input (its maps are then not on the
    truth's grid)."""
    from mca.capture import api
    from mca.capture.pipeline_app import read_input
    from mca.devices.profiles import load_profile_file
    from mca.processing import pipeline as pl

    truth_root = Path(truth_dir)
    truth_px = _read_float_tiff(truth_root / truth["files"]["disparity_px"])
    profile = load_profile_file(truth_root / truth["files"]["profile"])
    loaded = read_input(Path(image_path))
    if max(loaded.planes.shape[:2]) > pl.PipelineParams().analysis_max_side_px or loaded.pixel_scale != 1:
        return "larger than the analysis grid (or a Bayer input): its maps are not on the truth's grid"
    kept: dict[str, Any] = {}

    def pipeline(planes: np.ndarray, aperture: Any, optics: Any, **kwargs: Any) -> Any:
        kept["run"] = pl.finished_run(planes, aperture, optics, **kwargs)
        return kept["run"].result()

    result = api.run_depth(loaded, profile, pipeline=pipeline)
    run = kept["run"]
    if run.factor != 1 or run.dense.disparity_px.shape != truth_px.shape:
        return f"analysed on a grid {run.factor}x smaller than the truth's"
    return KeptRun(run, result, truth_px)


def score_renders(
    score: Callable[[str, str, dict[str, Any]], Any], argv: list[str] | None, description: str
) -> list[tuple[RenderEntry, Any]]:
    """A benchmark's command line over renders: `RENDERS [--names A,B] [--workers N]` parsed from `argv`, and
    `score(image_path, truth_dir, truth)` (a module-level function) run on each render found under RENDERS, N at
    a time in processes; each render with what its score returned, in `find_renders`' order."""
    import argparse
    from concurrent.futures import ProcessPoolExecutor

    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("renders", type=Path)
    parser.add_argument("--names", default="", help="comma-separated parts of render names to keep")
    parser.add_argument("--workers", type=int, default=2, help="renders scored at once (processes)")
    args = parser.parse_args(argv)
    entries = find_renders(args.renders)
    wanted = [n for n in args.names.split(",") if n]
    entries = [e for e in entries if not wanted or any(n in e.name for n in wanted)]
    jobs = [(str(e.image_path), str(e.truth_dir), e.truth) for e in entries]
    if not jobs:
        return []
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        return list(zip(entries, pool.map(score, *zip(*jobs))))


def print_scores(
    pairs: list[tuple[RenderEntry, Any]], columns: tuple[str, ...], width: int, note: str = ""
) -> list[dict[str, float]]:
    """Print `score_renders`' outcomes, one row per render (`columns` of each figures dict, `width` characters
    each; a sentence where a render was skipped) under a header ending in `note`; returns the figures scored."""
    print(f"{'render':28s} " + " ".join(f"{c:>{width}s}" for c in columns) + note)
    scored = []
    for entry, outcome in pairs:
        label = f"{entry.group}/{entry.name}"[-28:]
        if isinstance(outcome, str):
            print(f"{label:28s} skipped: {outcome}")
            continue
        scored.append(outcome)
        print(f"{label:28s} " + " ".join(f"{outcome[c]:{width}.1f}" for c in columns), flush=True)
    return scored


def _mca_imports(module: str) -> set[str]:
    """`module` and every `mca` module it imports, directly or through others, at the top or inside a function
    (read from the source, not imported)."""
    seen: set[str] = set()
    pending = [module]
    while pending:
        name = pending.pop()
        spec = importlib.util.find_spec(name) if name not in seen else None
        if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
            continue
        seen.add(name)
        tree = ast.parse(Path(spec.origin).read_bytes(), spec.origin)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                pending += [a.name for a in node.names if a.name.split(".")[0] == "mca"]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "mca":
                # `from mca.x import y`: y is a module of package mca.x or a name in mca.x; find_spec tells
                pending.append(node.module or "")
                pending += [f"{node.module}.{a.name}" for a in node.names if _is_module(f"{node.module}.{a.name}")]
    return seen


def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # a name inside a module, not a submodule
        return False


def peer_code_digest(module: str, binary: Path | None = None) -> str:
    """What a peer's answer depends on besides its input and parameters: the source of `module` and of every
    `mca` module it reaches, numpy's and OpenCV's versions (OpenCV 5 resamples differently from 4) and, for
    an external program, its bytes (read again whenever its size or time changes: a program rebuilt during a
    long evaluation is not taken for the old one)."""
    digest = hashlib.sha256(_source_digest(module).encode())
    if binary is not None:
        status = Path(binary).stat()
        digest.update(_file_digest(str(binary), status.st_size, status.st_mtime_ns).encode())
    return digest.hexdigest()


@functools.cache
def _source_digest(module: str) -> str:
    """The digest of `module`'s source and every `mca` module it reaches, with numpy's and OpenCV's versions (once
    per process: the modules a process has imported do not change under it)."""
    import cv2

    digest = hashlib.sha256(f"numpy {np.__version__}; opencv {cv2.__version__}".encode())
    for name in sorted(_mca_imports(module)):
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin is not None
        digest.update(name.encode() + b"\0" + Path(spec.origin).read_bytes() + b"\0")
    return digest.hexdigest()


@functools.cache
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    """The digest of a file's bytes, once per (path, size, modification time)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _cache_key(entry: RenderEntry, method: str, context: _Context, params: dict[str, Any], code: str) -> str:
    planes = np.ascontiguousarray(context.planes())
    key = {
        "image": entry.image_path.name,
        "planes": hashlib.sha256(planes.tobytes()).hexdigest() + str(planes.shape) + str(planes.dtype),
        "method": method,
        "range": [round(v, 6) for v in context.range_input_px],
        "params": params,
        "code": code,
    }
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode("utf-8")).hexdigest()[:16]


def _cached_peer(
    entry: RenderEntry,
    method: str,
    context: _Context,
    params: dict[str, Any],
    code: str,
    compute: Callable[[], tuple],
) -> Estimate:
    """A peer's disparity (input px) from the cache, or computed and cached; distance from the same optics.
    `code`: `peer_code_digest` of what computes it."""
    from mca.capture.outputs import atomic_path

    cache = entry.image_path.parent / PEER_CACHE_DIR
    path = cache / f"{entry.name}.{method}.{_cache_key(entry, method, context, params, code)}.npz"
    disparity = None
    if path.is_file():
        try:
            with np.load(path) as data:
                disparity, seconds = data["disparity_px"], float(data["seconds"])
        except (OSError, ValueError, KeyError):
            disparity = None
    if disparity is None:
        processing_disparity, seconds = compute()
        scale = context.loaded.pixel_scale
        disparity = _to_input(processing_disparity * np.float32(scale), scale, context.loaded.input_size_px)
        cache.mkdir(parents=True, exist_ok=True)
        for stale in cache.glob(f"{entry.name}.{method}.*.npz"):
            stale.unlink(missing_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.savez_compressed(handle, disparity_px=disparity, seconds=np.float64(seconds))
    with np.errstate(invalid="ignore", divide="ignore"):
        distance = np.asarray(context.optics.distance_mm(disparity.astype(np.float64)), np.float32)
    distance[~np.isfinite(disparity)] = np.nan
    return Estimate(np.asarray(disparity, np.float32), distance, seconds)


def run_wta(entry: RenderEntry, profile: Any, context: _Context) -> Estimate:
    from mca.processing.peers import colour_line_wta_subpixel

    scale = context.loaded.pixel_scale
    low, high = (v / scale for v in context.range_input_px)

    def compute() -> tuple[np.ndarray, float]:
        started = time.perf_counter()
        disparity = colour_line_wta_subpixel(
            context.planes(), profile.aperture, (low, high), window_px=WTA_WINDOW_PX, steps=WTA_STEPS
        )
        return disparity, time.perf_counter() - started

    params = {"window": WTA_WINDOW_PX, "steps": WTA_STEPS}
    return _cached_peer(entry, "wta", context, params, peer_code_digest("mca.processing.peers"), compute)


def run_bando_peer(entry: RenderEntry, profile: Any, context: _Context, binary: Path) -> Estimate:
    from mca.capture.peer_bando import HALF_WINDOW, run_bando

    scale = context.loaded.pixel_scale
    low, high = (v / scale for v in context.range_input_px)

    def compute() -> tuple[np.ndarray, float]:
        answer = run_bando(binary, context.planes(), profile.aperture, (low, high))
        return answer.disparity_px, answer.seconds

    params = {"binary": str(binary), "half_window": HALF_WINDOW}
    code = peer_code_digest("mca.capture.peer_bando", Path(binary))
    return _cached_peer(entry, "bando", context, params, code, compute)


def evaluate_rgbd(
    root: str | Path,
    *,
    peers: bool = True,
    bando_binary: Path | None = None,
    keep_outputs: str | Path | None = None,
    only: tuple[str, ...] | None = None,
    on_row: Callable[[RgbdRow], None] | None = None,
    on_progress: Callable[[str], None] | None = None,
) -> tuple[list[RgbdRow], list[str]]:
    """Score every render under `root`; returns the rows and the method names in column order.

    A render that cannot be read or processed gets a status instead of figures for the method that
    failed; the others go on. `keep_outputs` keeps `mca process`'s output folders there (else a
    temporary folder is used and removed)."""
    from mca.capture.peer_bando import BandoGeometryError
    from mca.devices.profiles import load_profile_file

    entries = find_renders(root)
    if only:
        wanted = {n.lower() for n in only}
        entries = [e for e in entries if e.name.lower() in wanted or e.name.split("-")[0].lower() in wanted]
    methods = ["ours", "ours-raw"] + (["wta", "bando"] if peers else [])
    rows = []
    with tempfile.TemporaryDirectory(prefix="mca-evaluate-") as scratch:
        out_root = Path(keep_outputs) if keep_outputs is not None else Path(scratch)
        for entry in entries:
            row = RgbdRow(entry.name, entry.group, {}, summary=_describe(entry.truth))
            if on_progress is not None:
                on_progress(f"{entry.group}/{entry.name}: {row.summary}")
            try:
                profile = load_profile_file(entry.truth_file("profile"))
                true_d = _read_float_tiff(entry.truth_file("disparity_px"))
                true_z = _read_float_tiff(entry.truth_file("distance_mm"))
            except (OSError, ValueError, KeyError) as exc:
                for method in methods:
                    row.status[method] = f"truth unreadable: {exc}"
                rows.append(row)
                if on_row is not None:
                    on_row(row)
                continue
            focus = float(entry.truth["focus_distance_mm"])
            edges = depth_edges(true_d)  # once, for both bands
            band = depth_edge_band(true_d, edges=edges)
            far = ~depth_edge_band(true_d, band_px=FAR_FROM_EDGE_PX, edges=edges)
            estimates: dict[str, Estimate | None] = {}
            try:
                estimates["ours"], estimates["ours-raw"] = run_ours(entry, profile, out_root)
                if estimates["ours-raw"] is None:
                    row.status["ours-raw"] = "the result has no raw disparity"
            except Exception as exc:  # a failing render is reported, the others go on
                row.status["ours"] = row.status["ours-raw"] = f"failed: {exc}"
            if peers:
                try:
                    context = _context(entry, profile)
                except Exception as exc:
                    row.status["wta"] = row.status["bando"] = f"input unreadable: {exc}"
                    context = None
                if context is not None:
                    try:
                        estimates["wta"] = run_wta(entry, profile, context)
                    except Exception as exc:
                        row.status["wta"] = f"failed: {exc}"
                    if bando_binary is None:
                        row.status["bando"] = "not built"
                    else:
                        try:
                            estimates["bando"] = run_bando_peer(entry, profile, context, bando_binary)
                        except BandoGeometryError as exc:
                            row.status["bando"] = f"n/a: {exc}"
                        except Exception as exc:
                            row.status["bando"] = f"failed: {exc}"
            for method, estimate in estimates.items():
                if estimate is None:
                    continue
                if estimate.disparity_px.shape != true_d.shape:
                    row.status[method] = (
                        f"size {estimate.disparity_px.shape[::-1]} differs from the truth {true_d.shape[::-1]}"
                    )
                    continue
                row.metrics[method] = pixel_metrics(
                    estimate.disparity_px, estimate.distance_mm, true_d, true_z, focus, band, far
                )
                row.seconds[method] = estimate.seconds
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows, methods


def _describe(truth: dict[str, Any]) -> str:
    from mca.capture.simulated_shots import describe_rgbd_truth

    try:
        return describe_rgbd_truth(truth)
    except (KeyError, TypeError, ValueError):
        return ""


def rgbd_report(rows: list[RgbdRow], methods: list[str]) -> dict[str, Any]:
    """The JSON document of `mca evaluate --rgbd --json`: per render, per group and overall summaries."""
    from mca.processing.evaluate import summarise_rgbd

    groups = sorted({r.group for r in rows})
    return {
        "methods": methods,
        "figures": list(PixelMetrics.FIELDS),
        "renders": [
            {
                "name": r.name,
                "group": r.group,
                "summary": r.summary,
                "metrics": {m: r.metrics[m].as_dict() for m in methods if m in r.metrics},
                "status": {m: r.status[m] for m in methods if m in r.status},
                "seconds": {m: r.seconds[m] for m in methods if m in r.seconds},
            }
            for r in rows
        ],
        "groups": {g: summarise_rgbd([r for r in rows if r.group == g], methods) for g in groups},
        "all": summarise_rgbd(rows, methods),
    }
