"""The application side of `mca evaluate`: the paper's Table 2 over the simulated paper scenes, and rendered real
scenes scored per pixel (`--rgbd`); progress by callback, errors as `EvaluateError`."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

Say = Callable[[str], None]


class EvaluateError(ValueError):
    """An evaluation that cannot run as asked (bad profile or scale, unknown scene, no renders); says what to do."""


def _quiet(text: str) -> None:
    return None


# --- Table 2: the paper scenes ---------------------------------------------------------------------------------------


@dataclass
class Table2Run:
    """The evaluated paper scenes (`processing.evaluate.SceneEvaluation`s) and how they were rendered."""

    evaluations: list[Any]
    methods: list[str]  # "ours", then the peers
    profile_name: str
    optics: Any  # the `SimulationOptics` of the renders
    scale: float
    seed: int


def evaluate_table2(
    profile: str = "paper-70d",
    scene: str = "all",
    *,
    scale: float = 1.0,
    seed: int = 0,
    renders: Path | None = None,
    peers: bool = True,
    on_progress: Say = _quiet,
) -> Table2Run:
    """Render each paper scene (noise, Bayer mosaic) or read it from the `renders` cache, run the pipeline and
    the peers (StereoSGBM, integer WTA) on the same planes, and score them against the truth (Table 2)."""
    from mca.devices.profiles import load_profile
    from mca.devices.sim.render import SensorModel, SimulationOptics, render
    from mca.devices.sim.scenes import paper_scene, scene_names
    from mca.processing.camera import ProfileError
    from mca.processing.evaluate import bayer_planes, evaluate_scene
    from mca.processing.peers import colour_line_wta, sgbm_disparity
    from mca.processing.pipeline import (
        RGGB_HALF_RES_OFFSETS_PX,
        align_channel_samples,
        default_disparity_range_px,
        run_pipeline,
    )

    try:
        camera = load_profile(profile)
        optics = SimulationOptics.from_profile(camera, scale)
    except (ProfileError, ValueError) as exc:
        raise EvaluateError(str(exc)) from None
    names = scene_names() if scene == "all" else [scene]
    unknown = [n for n in names if n not in scene_names()]
    if unknown:
        raise EvaluateError(f"unknown scene {unknown[0]!r}; choose one of {', '.join(scene_names())} or all")
    sensor = SensorModel()
    evaluations = []
    methods = ["ours"] + (["sgbm", "wta"] if peers else [])
    for name in names:
        if renders is not None:
            truth, truth_labels, planes = cached_paper_scene(renders, name, camera, optics, scale, seed, on_progress)
        else:
            rendering = render(paper_scene(name, optics.focus_distance_mm), optics, sensor, seed=seed)
            truth, truth_labels = rendering.truth, rendering.labels
            planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
        start = time.perf_counter()
        result = run_pipeline(
            planes, optics.aperture, optics.mca, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX
        )
        seconds = time.perf_counter() - start
        peer_maps = {}
        if peers:
            aligned = align_channel_samples(planes, RGGB_HALF_RES_OFFSETS_PX)
            low, high = default_disparity_range_px(optics.aperture, optics.mca, truth_labels.shape)
            range_proc = (low / 2.0, high / 2.0)
            peer_maps["sgbm"] = sgbm_disparity(aligned, optics.aperture, range_proc) * 2.0
            peer_maps["wta"] = colour_line_wta(aligned, optics.aperture, range_proc) * 2.0
        evaluations.append(evaluate_scene(truth, truth_labels, result, optics.mca, peer_maps, seconds))
        on_progress(f"{name}: {len(result.regions)} regions in {seconds:.2f} s")
    return Table2Run(evaluations, methods, camera.name, optics, scale, seed)


def table2_heading(run: Table2Run) -> str:
    """The line above the printed Table 2: profile, render and processing sizes, units and sign."""
    optics = run.optics
    return (
        f"profile {run.profile_name}, render {optics.width_px}x{optics.height_px} (scale {run.scale}), "
        f"processing {optics.width_px // 2}x{optics.height_px // 2}; ΔD in mm, + = farther than focus"
    )


def format_table2(run: Table2Run) -> str:
    """Table 2 as printed: per scene and object, every method's estimate and errors, and the summary."""
    from mca.processing.evaluate import format_table

    return str(format_table(run.evaluations, run.methods))


def table2_document(
    evaluations: list[Any], methods: list[str], profile_name: str, optics: Any, scale: float, seed: int
) -> dict[str, Any]:
    """`mca evaluate --json`: Table 2 as data: per scene and object the true and estimated inter-object depth
    ΔD (mm) and the errors of every method, region counts, the order check, and the summary over scenes."""
    import dataclasses

    from mca.capture.outputs import json_safe
    from mca.processing.evaluate import summarise

    scenes = []
    for e in evaluations:
        objects = [
            {
                "label": r.label,
                "name": r.name,
                "true_mm": r.true_mm,
                "estimates_mm": dict(r.estimates_mm),
                "abs_error_mm": {m: r.abs_error_mm(m) for m in methods if m in r.estimates_mm},
                "rel_error": {m: r.rel_error(m) for m in methods if m in r.estimates_mm},
            }
            for r in e.rows
        ]
        scenes.append(
            {
                "scene": e.scene,
                "objects": objects,
                "region_count": e.region_count,
                "true_region_count": e.true_region_count,
                "order_correct": e.order_correct,
                "seconds": e.seconds,
                "notes": list(e.notes),
            }
        )
    return json_safe(
        {
            "profile": profile_name,
            "render": {"width_px": optics.width_px, "height_px": optics.height_px, "scale": scale, "seed": seed},
            "methods": methods,
            "scenes": scenes,
            "summary": dataclasses.asdict(summarise(evaluations, methods)),
        }
    )


def cached_paper_scene(
    folder: Path, name: str, camera: Any, optics: Any, scale: float, seed: int, on_progress: Say = _quiet
) -> tuple[dict[str, Any], Any, Any]:
    """(truth, labels, half-resolution planes) of a paper scene from `folder` (CR2 + truth/, as `mca simulate`
    writes them), rendered and written there first when missing or made with another size or seed."""
    import json

    import cv2
    import numpy as np

    from mca.capture.raw import read_raw
    from mca.capture.simulated_shots import TRUTH_DIR, write_capture
    from mca.devices.sim.world import render_scene

    cr2 = folder / f"{name}.CR2"
    truth_path = folder / TRUTH_DIR / f"{name}.truth.json"
    labels_path = folder / TRUTH_DIR / f"{name}.labels.png"
    truth = None
    if cr2.is_file() and truth_path.is_file() and labels_path.is_file():
        truth = json.loads(truth_path.read_text(encoding="utf-8"))
        size = (truth.get("optics", {}).get("width_px"), truth.get("optics", {}).get("height_px"))
        if truth.get("seed") != seed or size != (optics.width_px, optics.height_px):
            truth = None
    if truth is None:
        on_progress(f"{name}: rendering into {folder} ...")
        write_capture(render_scene(name, camera, size=scale, seed=seed), camera, folder)
        truth = json.loads(truth_path.read_text(encoding="utf-8"))
    labels = cv2.imread(str(labels_path), cv2.IMREAD_UNCHANGED)
    planes = np.asarray(read_raw(cr2).planes, np.float32)
    return truth, labels, planes


# --- rendered real scenes, per pixel ---------------------------------------------------------------------------------


@dataclass
class RgbdRun:
    """Every render's `RgbdRow`, the methods in column order, and how long it took."""

    rows: list[Any]
    methods: list[str]
    seconds: float


def evaluate_rgbd_folder(
    root: str | Path,
    *,
    peers: bool = True,
    bando: str | None = None,
    keep_outputs: str | Path | None = None,
    only: tuple[str, ...] | None = None,
    on_row: Callable[[Any], None] | None = None,
    on_progress: Say = _quiet,
) -> RgbdRun:
    """Every rendered real scene under `root` through the pipeline as `mca process` runs it, beside the
    colour-line WTA and Bando 2008's program (`bando`, else $MCA_BANDO_BIN; a note when it is not built)."""
    from mca.capture.peer_bando import ENV_VARIABLE, find_bando
    from mca.capture.rgbd_evaluation import evaluate_rgbd, find_renders

    try:
        find_renders(root)
    except FileNotFoundError as exc:
        raise EvaluateError(str(exc)) from None
    binary = find_bando(bando) if peers else None
    if peers and binary is None:
        where = f"--bando {bando}" if bando else f"${ENV_VARIABLE}"
        on_progress(f"note: Bando 2008's program not found ({where}): its column says 'not built'")
    started = time.perf_counter()
    rows, methods = evaluate_rgbd(
        root,
        peers=peers,
        bando_binary=binary,
        keep_outputs=keep_outputs,
        only=only,
        on_row=on_row,
        on_progress=on_progress,
    )
    return RgbdRun(rows, methods, time.perf_counter() - started)


def rgbd_document(run: RgbdRun) -> dict[str, Any]:
    """`mca evaluate --rgbd --json`: the report of `rgbd_report`, made JSON-safe."""
    from mca.capture.outputs import json_safe
    from mca.capture.rgbd_evaluation import rgbd_report

    return json_safe(rgbd_report(run.rows, run.methods))


def format_rgbd(run: RgbdRun) -> str:
    """The per-pixel figures as printed: per render, then median and worst per group and overall."""
    from mca.processing.evaluate import format_rgbd_table

    return str(format_rgbd_table(run.rows, run.methods))


RGBD_LEGEND = (
    "red-blue disparity in px of the render; bad-N: share of truth-valid pixels off by more than N px "
    "(no value = bad); edge: within 5 px of a true depth edge; far: more than 20 px from every one; |dZ|: "
    "median depth error; rel dD: median relative inter-object error (pixels >= 25 mm off focus); slope: of the "
    "estimated against the true disparity where within 3 px (1 = not compressed); s: seconds (ours: the pipeline)"
)
