"""`mca simulate`: render MCA photographs with known depth: the paper's Fig. 4 scenes, or real RGB-D photographs."""

from __future__ import annotations

from pathlib import Path

import typer


def _numbers(text: str, what: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        typer.echo(f"error: {what} must be integers separated by commas, got {text!r}", err=True)
        raise typer.Exit(2) from None


def register(app: typer.Typer) -> None:
    @app.command("simulate")
    def simulate(
        scene: str = typer.Option("all", "--scene", "-s", help="paper-a ... paper-g, or all."),
        profile: str = typer.Option("paper-70d", "--profile", "-p", help="Built-in profile name or TOML file."),
        out: str = typer.Option(
            ..., "--out", "-o", help="Folder for the captures; their ground truth goes to OUT/truth/."
        ),
        size: str = typer.Option(
            "full", "--size", help="Paper scenes: full (the profile's image size) or small (1/4)."
        ),
        seed: int = typer.Option(0, "--seed", help="Seed of the sensor noise."),
        from_rgbd: tuple[str, str] | None = typer.Option(
            None,
            "--from-rgbd",
            help="IMAGE DISPARITY: render a real photograph (8-bit sRGB) with its disparity map (0 = unknown; "
            "scale from SOURCE.txt beside it, else --disparity-scale).",
        ),
        from_rgbd_tree: str = typer.Option(
            None,
            "--from-rgbd-tree",
            help="A Middlebury-style tree (<Scene>/im.png, disp.png, SOURCE.txt): every scene, once per seed of "
            "--seeds, with realism drawn at random from the seed.",
        ),
        dev_set: bool = typer.Option(
            False,
            "--dev-set",
            help="With --from-rgbd-tree: the development set (docs/evaluation.md): OUT/tuning, OUT/held-out "
            "(2 seeds each, 1368 px wide) and OUT/20mp (one scene at 20 MP through CR2).",
        ),
        fmt: str = typer.Option("tiff", "--format", help="RGB-D renders: tiff (16-bit linear RGB) or cr2 (RGGB)."),
        scale: float = typer.Option(None, "--scale", help="RGB-D: resize the photograph by this factor first."),
        width: int = typer.Option(
            None, "--width", help="RGB-D tree: resize every scene to this width (default 1368; 0 = own size)."
        ),
        full_size: bool = typer.Option(
            False, "--full-size", help="RGB-D: crop to the profile's aspect and render at its full size (20 MP)."
        ),
        near_mm: float = typer.Option(None, "--near-mm", help="RGB-D: distance of the nearest valid disparity."),
        far_mm: float = typer.Option(None, "--far-mm", help="RGB-D: distance of the farthest valid disparity."),
        focus_mm: float = typer.Option(None, "--focus-mm", help="RGB-D: focus distance (default: the profile's)."),
        disparity_scale: float = typer.Option(
            None, "--disparity-scale", help="RGB-D: stored disparity value / this = px (default: SOURCE.txt or 1)."
        ),
        iso: float = typer.Option(100.0, "--iso", help="RGB-D single image: ISO (noise level)."),
        crosstalk: float = typer.Option(
            0.0, "--crosstalk", help="RGB-D single image: leak into each colour from the other filters (0 = off)."
        ),
        vignetting: str = typer.Option("none", "--vignetting", help="RGB-D single image: none, cos4 or poly."),
        name: str = typer.Option(None, "--name", help="RGB-D single image: name of the capture (default: the folder)."),
        seeds: str = typer.Option("1,2", "--seeds", help="RGB-D tree: the seeds, each one render per scene."),
        scenes: str = typer.Option(None, "--scenes", help="RGB-D tree: only these scenes (comma-separated)."),
        force: bool = typer.Option(False, "--force", help="RGB-D tree: render again what is already rendered."),
    ) -> None:
        """Simulate MCA photographs (thin lens, three filters, occlusion, noise, 14-bit) with their ground truth.

        Paper scenes (default): the seven scenes of the paper's Fig. 4 as CR2s. --from-rgbd IMAGE DISPARITY:
        one real photograph with known depth. --from-rgbd-tree DIR: every scene of a Middlebury-style tree
        with randomised realism (docs/simulator.md); add --dev-set for the development set."""
        from mca.devices.profiles import load_profile
        from mca.processing.camera import ProfileError

        try:
            camera_profile = load_profile(profile)
            out_dir = Path(out)
            out_dir.mkdir(parents=True, exist_ok=True)
        except ProfileError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        except OSError as exc:
            typer.echo(f"error: cannot create the output folder {out}: {exc.strerror}", err=True)
            raise typer.Exit(2) from None
        if fmt not in ("tiff", "cr2"):
            typer.echo("error: --format must be tiff or cr2", err=True)
            raise typer.Exit(2) from None
        if from_rgbd_tree is not None:
            _tree(
                camera_profile,
                Path(from_rgbd_tree),
                out_dir,
                dev_set=dev_set,
                fmt=fmt,
                scale=scale,
                width=width,
                full_size=full_size,
                seeds=_numbers(seeds, "--seeds"),
                scenes=tuple(s for s in scenes.split(",") if s) if scenes else None,
                force=force,
            )
            return
        if from_rgbd is not None and from_rgbd[0] is not None:
            _single(
                camera_profile,
                Path(from_rgbd[0]),
                Path(from_rgbd[1]),
                out_dir,
                fmt=fmt,
                scale=scale,
                full_size=full_size,
                near_mm=near_mm,
                far_mm=far_mm,
                focus_mm=focus_mm,
                disparity_scale=disparity_scale,
                iso=iso,
                crosstalk=crosstalk,
                vignetting=vignetting,
                seed=seed,
                name=name,
            )
            return
        _paper(camera_profile, scene, out_dir, size, seed)


def _paper(camera_profile, scene: str, out_dir: Path, size: str, seed: int) -> None:
    import time

    from mca.capture.simulated_shots import write_capture
    from mca.devices.sim.scenes import scene_names
    from mca.devices.sim.world import SIZES, render_scene

    names = scene_names() if scene == "all" else [scene]
    unknown = [n for n in names if n not in scene_names()]
    if unknown:
        typer.echo(f"error: unknown scene '{unknown[0]}'; choose one of {', '.join(scene_names())} or all", err=True)
        raise typer.Exit(2) from None
    if size not in SIZES:
        typer.echo(f"error: --size must be one of {', '.join(SIZES)}", err=True)
        raise typer.Exit(2) from None
    for number, name in enumerate(names, 1):
        typer.echo(f"[{number}/{len(names)}] {name}: rendering ({size}) ...", nl=False)
        started = time.perf_counter()
        try:
            capture = render_scene(name, camera_profile, size=size, seed=seed)
        except ValueError as exc:
            typer.echo("")
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        rendered = time.perf_counter()
        paths = write_capture(capture, camera_profile, out_dir)
        typer.echo(
            f" {rendered - started:.1f} s, written in {time.perf_counter() - rendered:.1f} s: "
            f"{paths['cr2'].name} ({len(capture.truth['objects'])} objects)"
        )
    typer.echo(f"done: {len(names)} scene(s) in {out_dir} (truth in {out_dir / 'truth'})")


def _single(
    camera_profile,
    image: Path,
    disparity: Path,
    out_dir: Path,
    *,
    fmt: str,
    scale: float | None,
    full_size: bool,
    near_mm: float | None,
    far_mm: float | None,
    focus_mm: float | None,
    disparity_scale: float | None,
    iso: float,
    crosstalk: float,
    vignetting: str,
    seed: int,
    name: str | None,
) -> None:
    from mca.capture.simulated_shots import (
        describe_rgbd_truth,
        read_rgbd_source,
        render_rgbd_capture,
        resize_rgbd,
        write_rgbd_capture,
    )
    from mca.devices.sim.render import SensorModel
    from mca.devices.sim.render_rgbd import DepthRange, Realism

    if camera_profile.lens is None:
        typer.echo(f"error: profile '{camera_profile.name}' has no lens; use one with optics (paper-70d)", err=True)
        raise typer.Exit(2) from None
    focus = focus_mm if focus_mm is not None else camera_profile.lens.focus_distance_mm
    near = near_mm if near_mm is not None else focus - 150.0
    far = far_mm if far_mm is not None else focus + 300.0
    try:
        depth_range = DepthRange(near, far)
        if not 0.0 <= crosstalk < 0.5:
            raise ValueError(f"--crosstalk must be in [0, 0.5), got {crosstalk}")
        leak = crosstalk / 2.0
        matrix = None
        if crosstalk > 0:
            matrix = tuple(
                (
                    1.0 - crosstalk if i == 0 else leak,
                    1.0 - crosstalk if i == 1 else leak,
                    1.0 - crosstalk if i == 2 else leak,
                )
                for i in range(3)
            )
        realism = Realism(sensor=SensorModel(iso=iso), crosstalk=matrix, vignetting=vignetting)
        source = read_rgbd_source(image, disparity, disparity_scale, name=name)
        if full_size:
            aspect = camera_profile.width_px / camera_profile.height_px
            h, w = source.valid.shape
            source = resize_rgbd(source, camera_profile.width_px / min(w, h * aspect), crop_aspect=aspect)
        else:
            source = resize_rgbd(source, scale if scale is not None else 1.0)
        capture = render_rgbd_capture(
            source,
            camera_profile,
            fmt=fmt,
            focus_distance_mm=focus,
            depth_range=depth_range,
            realism=realism,
            seed=seed,
            name=name,
        )
        paths = write_rgbd_capture(capture, out_dir)
    except (ValueError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"{paths['image'].name}: {describe_rgbd_truth(capture.truth)}; {capture.seconds:.1f} s")
    typer.echo(f"truth in {out_dir / 'truth'}; process it with --profile {paths['profile']}")


def _tree(
    camera_profile,
    tree: Path,
    out_dir: Path,
    *,
    dev_set: bool,
    fmt: str,
    scale: float | None,
    width: int | None,
    full_size: bool,
    seeds: tuple[int, ...],
    scenes: tuple[str, ...] | None,
    force: bool,
) -> None:
    import time

    from mca.capture.simulated_shots import (
        DEV_FULL_SCENE,
        DEV_HELD_OUT_SCENES,
        DEV_SEEDS,
        DEV_TUNING_SCENES,
        DEV_WIDTH_PX,
        find_rgbd_scenes,
        render_rgbd_tree,
    )

    if not tree.is_dir() or not find_rgbd_scenes(tree):
        typer.echo(f"error: {tree}: no scene folder with im.png and disp.png", err=True)
        raise typer.Exit(2) from None
    if camera_profile.lens is None:
        typer.echo(f"error: profile '{camera_profile.name}' has no lens; use one with optics (paper-70d)", err=True)
        raise typer.Exit(2) from None
    jobs: list[tuple[str, tuple[str, ...] | None, tuple[int, ...], str, int | None, bool]]
    if dev_set:
        jobs = [
            ("tuning", DEV_TUNING_SCENES, DEV_SEEDS, "tiff", DEV_WIDTH_PX, False),
            ("held-out", DEV_HELD_OUT_SCENES, DEV_SEEDS, "tiff", DEV_WIDTH_PX, False),
            ("20mp", (DEV_FULL_SCENE,), DEV_SEEDS[:1], "cr2", None, True),
        ]
    else:
        target = DEV_WIDTH_PX if width is None else (width or None)
        jobs = [(".", scenes, seeds, fmt, target, full_size)]
    started = time.perf_counter()
    failures = []
    counts = {"rendered": 0, "cached": 0, "failed": 0}
    for folder, names, job_seeds, job_fmt, job_width, job_full in jobs:
        destination = out_dir / folder

        def report(outcome, folder=folder) -> None:
            counts[outcome.status] += 1
            where = f"{folder}/" if folder != "." else ""
            if outcome.status == "failed":
                failures.append(f"{where}{outcome.name}: {outcome.reason}")
                typer.echo(f"{where}{outcome.name}: FAILED: {outcome.reason}", err=True)
            else:
                took = f"{outcome.seconds:.1f} s: " if outcome.status == "rendered" else ""
                typer.echo(f"{where}{outcome.name}: {outcome.status}, {took}{outcome.summary}")

        render_rgbd_tree(
            tree,
            destination,
            camera_profile,
            seeds=job_seeds,
            scenes=names,
            fmt=job_fmt,
            scale=scale if not dev_set else None,
            width_px=job_width,
            full_size=job_full,
            force=force,
            on_outcome=report,
        )
    typer.echo(
        f"done in {time.perf_counter() - started:.0f} s: {counts['rendered']} rendered, {counts['cached']} kept, "
        f"{counts['failed']} failed, in {out_dir}"
    )
    if failures:
        typer.echo("failed:\n  " + "\n  ".join(failures), err=True)
        raise typer.Exit(1)
