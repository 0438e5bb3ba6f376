"""`mca simulate`: render the paper's Fig. 4 scenes as CR2 photographs with their ground truth."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    @app.command("simulate")
    def simulate(
        scene: str = typer.Option("all", "--scene", "-s", help="paper-a ... paper-g, or all."),
        profile: str = typer.Option("paper-70d", "--profile", "-p", help="Built-in profile name or TOML file."),
        out: str = typer.Option(
            ..., "--out", "-o", help="Folder for <scene>.CR2, .truth.json, .depth.tiff, .labels.png."
        ),
        size: str = typer.Option("full", "--size", help="full (the profile's image size) or small (1/4)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the sensor noise."),
    ) -> None:
        """Simulate MCA photographs (thin lens, three filters, occlusion, noise, 14-bit RGGB) of known scenes."""
        import time
        from pathlib import Path

        from mca.capture.profiles import load_profile
        from mca.capture.simulated_shots import SIZES, render_scene, write_capture
        from mca.processing.camera import ProfileError
        from mca.processing.scenes import scene_names

        names = scene_names() if scene == "all" else [scene]
        unknown = [n for n in names if n not in scene_names()]
        if unknown:
            typer.echo(
                f"error: unknown scene '{unknown[0]}'; choose one of {', '.join(scene_names())} or all", err=True
            )
            raise typer.Exit(2)
        if size not in SIZES:
            typer.echo(f"error: --size must be one of {', '.join(SIZES)}", err=True)
            raise typer.Exit(2)
        try:
            camera_profile = load_profile(profile)
            out_dir = Path(out)
            out_dir.mkdir(parents=True, exist_ok=True)
        except ProfileError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2)
        except OSError as exc:
            typer.echo(f"error: cannot create the output folder {out}: {exc.strerror}", err=True)
            raise typer.Exit(2)
        for number, name in enumerate(names, 1):
            typer.echo(f"[{number}/{len(names)}] {name}: rendering ({size}) ...", nl=False)
            started = time.perf_counter()
            try:
                capture = render_scene(name, camera_profile, size=size, seed=seed)
            except ValueError as exc:
                typer.echo("")
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(2)
            rendered = time.perf_counter()
            paths = write_capture(capture, camera_profile, out_dir)
            typer.echo(
                f" {rendered - started:.1f} s, written in {time.perf_counter() - rendered:.1f} s: "
                f"{paths['cr2'].name} ({len(capture.truth['objects'])} objects)"
            )
        typer.echo(f"done: {len(names)} scene(s) in {out_dir}")
