"""`mca evaluate`: the simulated paper scenes as the paper's Table 2, or rendered real scenes scored per pixel (--rgbd)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("evaluate")
    def evaluate(
        scene: str = typer.Option("all", "--scene", "-s", help="paper-a .. paper-g, or 'all'."),
        profile: str = typer.Option("paper-70d", "--profile", "-p", help="Built-in profile name or TOML file."),
        scale: float = typer.Option(
            1.0,
            "--scale",
            help="Render size as a fraction of the profile's sensor "
            "(1.0 = the full 20 MP; smaller is faster, less precise).",
        ),
        seed: int = typer.Option(0, "--seed", help="Seed of the simulated sensor noise."),
        renders: str = typer.Option(
            None,
            "--renders",
            help="Table 2: read the scenes from this folder of `mca simulate` renders (CR2 + truth/), rendering "
            "and writing there the ones missing (a cache: same scale and seed).",
        ),
        peers: bool = typer.Option(
            True,
            "--peers/--no-peers",
            help="Also run the peers (Table 2: StereoSGBM, integer WTA; --rgbd: WTA, Bando).",
        ),
        rgbd: str = typer.Option(
            None,
            "--rgbd",
            help="A folder of rendered real scenes (mca simulate --from-rgbd-tree ...; its subfolders too): "
            "per-pixel figures of the pipeline, run as mca process runs it, and the peers.",
        ),
        bando: str = typer.Option(
            None, "--bando", help="--rgbd: Bando et al. 2008's built program (default: $MCA_BANDO_BIN)."
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the figures as JSON (Table 2 or --rgbd)."),
        json_file: str = typer.Option(None, "--json-file", help="Also write the JSON figures to this file."),
        keep_outputs: str = typer.Option(
            None, "--keep-outputs", help="--rgbd: keep mca process's output folders here."
        ),
        only: str = typer.Option(None, "--only", help="--rgbd: only these renders or scenes (comma-separated)."),
    ) -> None:
        """Table 2 (default): render each paper scene with the simulator (noise, Bayer mosaic), run the pipeline
        and print per object the true and estimated inter-object depth with absolute and relative errors, the
        region count and whether the front-to-back order is right, beside the peers run on the same planes.

        --rgbd DIR: every rendered real scene under DIR through the pipeline exactly as `mca process` runs it,
        scored per pixel (bad-1, bad-0.5, the same near depth edges, depth error, relative inter-object error,
        coverage) beside the colour-line WTA and Bando 2008's program; per scene, then median and worst."""
        if rgbd is not None:
            _evaluate_rgbd(rgbd, peers, bando, as_json, keep_outputs, only, json_file)
            return
        import json
        import time

        from mca.devices.profiles import load_profile
        from mca.devices.sim.render import SensorModel, SimulationOptics, render
        from mca.devices.sim.scenes import paper_scene, scene_names
        from mca.processing.camera import ProfileError
        from mca.processing.evaluate import bayer_planes, evaluate_scene, format_table
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
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        names = scene_names() if scene == "all" else [scene]
        unknown = [n for n in names if n not in scene_names()]
        if unknown:
            typer.echo(
                f"error: unknown scene {unknown[0]!r}; choose one of {', '.join(scene_names())} or all", err=True
            )
            raise typer.Exit(2)
        sensor = SensorModel()
        evaluations = []
        methods = ["ours"] + (["sgbm", "wta"] if peers else [])
        for name in names:
            if renders is not None:
                truth, truth_labels, planes = _cached_paper_scene(Path(renders), name, camera, optics, scale, seed)
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
            typer.echo(f"{name}: {len(result.regions)} regions in {seconds:.2f} s", err=True)
        if as_json or json_file is not None:
            document = table2_document(evaluations, methods, camera.name, optics, scale, seed)
            if json_file is not None:
                from mca.capture.outputs import write_json

                write_json(json_file, document)
            if as_json:
                typer.echo(json.dumps(document, indent=2))
                return
        typer.echo(
            f"profile {camera.name}, render {optics.width_px}x{optics.height_px} (scale {scale}), "
            f"processing {optics.width_px // 2}x{optics.height_px // 2}; ΔD in mm, + = farther than focus"
        )
        typer.echo(format_table(evaluations, methods))


def table2_document(evaluations, methods: list[str], profile_name: str, optics, scale: float, seed: int) -> dict:
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


def _cached_paper_scene(folder: Path, name: str, camera, optics, scale: float, seed: int):
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
        typer.echo(f"{name}: rendering into {folder} ...", err=True)
        write_capture(render_scene(name, camera, size=scale, seed=seed), camera, folder)
        truth = json.loads(truth_path.read_text(encoding="utf-8"))
    labels = cv2.imread(str(labels_path), cv2.IMREAD_UNCHANGED)
    planes = np.asarray(read_raw(cr2).planes, np.float32)
    return truth, labels, planes


def _evaluate_rgbd(
    root: str,
    peers: bool,
    bando: str | None,
    as_json: bool,
    keep_outputs: str | None,
    only: str | None,
    json_file: str | None = None,
) -> None:
    import json
    import time

    from mca.capture.outputs import json_safe
    from mca.capture.peer_bando import ENV_VARIABLE, find_bando
    from mca.capture.rgbd_evaluation import evaluate_rgbd, find_renders, rgbd_report
    from mca.processing.evaluate import format_rgbd_table

    try:
        find_renders(root)
    except FileNotFoundError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    binary = find_bando(bando) if peers else None
    if peers and binary is None:
        where = f"--bando {bando}" if bando else f"${ENV_VARIABLE}"
        typer.echo(f"note: Bando 2008's program not found ({where}): its column says 'not built'", err=True)
    started = time.perf_counter()

    def progress(text: str) -> None:
        typer.echo(text, err=True)

    def finished(row) -> None:
        parts = [f"{m} bad-1 {100 * row.metrics[m].bad_1:.1f}%" for m in row.metrics]
        typer.echo(f"  {'; '.join(parts) or 'no result'}", err=True)

    rows, methods = evaluate_rgbd(
        root,
        peers=peers,
        bando_binary=binary,
        keep_outputs=keep_outputs,
        only=tuple(s for s in only.split(",") if s) if only else None,
        on_row=finished,
        on_progress=progress,
    )
    typer.echo(f"evaluated {len(rows)} render(s) in {time.perf_counter() - started:.0f} s", err=True)
    if json_file is not None:
        from mca.capture.outputs import write_json

        write_json(json_file, rgbd_report(rows, methods))
    if as_json:
        typer.echo(json.dumps(json_safe(rgbd_report(rows, methods)), indent=2))
        return
    typer.echo(
        "red-blue disparity in px of the render; bad-N: share of truth-valid pixels off by more than N px "
        "(no value = bad); edge: within 5 px of a true depth edge; |dZ|: median depth error; rel dD: median "
        "relative inter-object error (pixels >= 25 mm off focus); s: seconds (ours: the pipeline)"
    )
    typer.echo(format_rgbd_table(rows, methods))
