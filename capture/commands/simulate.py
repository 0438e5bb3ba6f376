"""`mca simulate`: render MCA photographs with known depth: the paper's Fig. 4 scenes, or real RGB-D photographs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer


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
            "(2 seeds each, 1368 px wide), OUT/20mp (one scene at 20 MP through CR2) and OUT/native/tuning, "
            "OUT/native/held-out (the same renders at --pitch native).",
        ),
        pitch: str = typer.Option(
            "frame",
            "--pitch",
            help="RGB-D: frame (the image spans the whole sensor; the file names the camera) or native (each "
            "pixel one photosite of the body: a window of the sensor at full resolution, 4x the disparities of a "
            "1368-px frame; TIFF only, naming no camera, so the profile's pixel_pitch_mm applies).",
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
        vignetting: str = typer.Option(
            "none", "--vignetting", help="RGB-D single image: none, cos4 or poly (k2 -0.275, k4 -0.025)."
        ),
        name: str = typer.Option(None, "--name", help="RGB-D single image: name of the capture (default: the folder)."),
        seeds: str = typer.Option("1,2", "--seeds", help="RGB-D tree: the seeds, each one render per scene."),
        scenes: str = typer.Option(None, "--scenes", help="RGB-D tree: only these scenes (comma-separated)."),
        force: bool = typer.Option(False, "--force", help="RGB-D tree: render again what is already rendered."),
    ) -> None:
        """Simulate MCA photographs (thin lens, three filters, occlusion, noise, 14-bit) with their ground truth.

        Paper scenes (default): the seven scenes of the paper's Fig. 4 as CR2s. --from-rgbd IMAGE DISPARITY:
        one real photograph with known depth. --from-rgbd-tree DIR: every scene of a Middlebury-style tree
        with randomised realism (docs/simulator.md); add --dev-set for the development set."""
        from mca.capture.simulate_app import (
            RgbdOptions,
            SimulateError,
            TreeOptions,
            parse_integers,
            prepare_simulation,
            simulate_rgbd,
            simulate_rgbd_tree,
        )

        try:
            camera_profile, out_dir = prepare_simulation(profile, out, fmt)
            if from_rgbd_tree is not None:
                tree_options = TreeOptions(
                    dev_set=dev_set,
                    fmt=fmt,
                    scale=scale,
                    width_px=width,
                    full_size=full_size,
                    seeds=parse_integers(seeds, "--seeds"),
                    scenes=tuple(s for s in scenes.split(",") if s) if scenes else None,
                    force=force,
                    pitch=pitch,
                )
                summary = simulate_rgbd_tree(camera_profile, Path(from_rgbd_tree), out_dir, tree_options, _tree_line)
                _tree_done(summary, out_dir)
            elif from_rgbd is not None and from_rgbd[0] is not None:
                rgbd_options = RgbdOptions(
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
                    pitch=pitch,
                )
                done = simulate_rgbd(camera_profile, Path(from_rgbd[0]), Path(from_rgbd[1]), out_dir, rgbd_options)
                typer.echo(f"{done.paths['image'].name}: {done.summary}; {done.seconds:.1f} s")
                typer.echo(f"truth in {out_dir / 'truth'}; process it with --profile {done.paths['profile']}")
            else:
                _paper(camera_profile, scene, out_dir, size, seed)
        except SimulateError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None


def _paper(camera_profile: Any, scene: str, out_dir: Path, size: str, seed: int) -> None:
    """The paper scenes with one progress line each; a render that fails ends its open line first."""
    from mca.capture.simulate_app import simulate_paper

    open_line = [False]

    def started(number: int, total: int, name: str) -> None:
        typer.echo(f"[{number}/{total}] {name}: rendering ({size}) ...", nl=False)
        open_line[0] = True

    def done(r: Any) -> None:
        typer.echo(f" {r.render_s:.1f} s, written in {r.write_s:.1f} s: {r.cr2.name} ({r.objects} objects)")
        open_line[0] = False

    try:
        rendered = simulate_paper(camera_profile, scene, out_dir, size, seed, on_start=started, on_done=done)
    except ValueError:
        if open_line[0]:
            typer.echo("")
        raise
    typer.echo(f"done: {len(rendered)} scene(s) in {out_dir} (truth in {out_dir / 'truth'})")


def _tree_line(prefix: str, outcome: Any) -> None:
    if outcome.status == "failed":
        typer.echo(f"{prefix}{outcome.name}: FAILED: {outcome.reason}", err=True)
    else:
        took = f"{outcome.seconds:.1f} s: " if outcome.status == "rendered" else ""
        typer.echo(f"{prefix}{outcome.name}: {outcome.status}, {took}{outcome.summary}")


def _tree_done(summary: Any, out_dir: Path) -> None:
    counts = summary.counts
    typer.echo(
        f"done in {summary.seconds:.0f} s: {counts['rendered']} rendered, {counts['cached']} kept, "
        f"{counts['failed']} failed, in {out_dir}"
    )
    if summary.failures:
        typer.echo("failed:\n  " + "\n  ".join(summary.failures), err=True)
        raise typer.Exit(1)
