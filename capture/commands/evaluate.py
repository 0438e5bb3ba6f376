"""`mca evaluate`: the simulated paper scenes through the pipeline and two peers, printed as the paper's Table 2."""

from __future__ import annotations

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
        peers: bool = typer.Option(True, "--peers/--no-peers", help="Also run StereoSGBM and integer WTA."),
    ) -> None:
        """Render each scene with the simulator (noise, Bayer mosaic), run the pipeline and print per object
        the true and estimated inter-object depth with absolute and relative errors (Table 2), the region
        count and whether the front-to-back order is right, beside the peers run on the same planes."""
        import time

        from mca.capture.profiles import load_profile
        from mca.processing.camera import ProfileError
        from mca.processing.evaluate import bayer_planes, evaluate_scene, format_table
        from mca.processing.peers import colour_line_wta, sgbm_disparity
        from mca.processing.pipeline import (
            RGGB_HALF_RES_OFFSETS_PX,
            align_channel_samples,
            default_disparity_range_px,
            run_pipeline,
        )
        from mca.processing.scenes import paper_scene, scene_names
        from mca.processing.simulate import SensorModel, SimulationOptics, render

        try:
            camera = load_profile(profile)
            optics = SimulationOptics.from_profile(camera, scale)
        except (ProfileError, ValueError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2)
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
            rendering = render(paper_scene(name, optics.focus_distance_mm), optics, sensor, seed=seed)
            planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
            start = time.perf_counter()
            result = run_pipeline(
                planes, optics.aperture, optics.mca, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX
            )
            seconds = time.perf_counter() - start
            peer_maps = {}
            if peers:
                aligned = align_channel_samples(planes, RGGB_HALF_RES_OFFSETS_PX)
                low, high = default_disparity_range_px(optics.aperture, optics.mca, rendering.mosaic.shape)
                range_proc = (low / 2.0, high / 2.0)
                peer_maps["sgbm"] = sgbm_disparity(aligned, optics.aperture, range_proc) * 2.0
                peer_maps["wta"] = colour_line_wta(aligned, optics.aperture, range_proc) * 2.0
            evaluations.append(
                evaluate_scene(rendering.truth, rendering.labels, result, optics.mca, peer_maps, seconds)
            )
            typer.echo(f"{name}: {len(result.regions)} regions in {seconds:.2f} s", err=True)
        typer.echo(
            f"profile {camera.name}, render {optics.width_px}x{optics.height_px} (scale {scale}), "
            f"processing {optics.width_px // 2}x{optics.height_px // 2}; ΔD in mm, + = farther than focus"
        )
        typer.echo(format_table(evaluations, methods))
