"""`mca demo`: the main job end to end — tethered capture, accurate-depth processing and a rerun recording."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Path = typer.Option(Path("demo-out"), "--out", "-o", help="Folder for shots, results and the recording."),
        count: int = typer.Option(3, "--count", "-n", min=1, max=50, help="Number of shots."),
        camera: str | None = typer.Option(
            None,
            "--camera",
            "-c",
            help="sim (simulated EOS 70D), auto (a USB camera if one is found, else sim), "
            "usb:BUS:ADDR or ptpip:HOST:PORT (default: the config file's camera, else auto).",
        ),
        size: str = typer.Option("full", "--size", help="Simulated frame size: full (5472x3648), small, or a scale."),
        profile: str | None = typer.Option(
            None, "--profile", help="Profile used for processing (default: the config file's, else paper-70d)."
        ),
    ) -> None:
        """Shoot COUNT frames, process each into accurate-depth layers and record everything for the rerun viewer.

        Without a camera on USB this uses the simulated EOS 70D, which photographs the paper's
        Fig. 4 scenes through the MCA lens simulator, so each shot has a known ground truth.
        """
        from mca.capture.config import ConfigError, fill_from_config
        from mca.capture.tether import TetherError, TransportError
        from mca.capture.tether_run import demo_camera, open_demo_session, result_summary, shoot

        try:
            chosen = fill_from_config(camera=camera, profile=profile)
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        factory, what = demo_camera(str(chosen["camera"]), size)
        typer.echo(what, err=True)
        try:
            session = open_demo_session(factory, out, str(chosen["profile"]), log=lambda m: typer.echo(m, err=True))
        except TetherError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
        try:
            results = shoot(session, count)
        except (TransportError, TetherError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from exc
        for shot in results:
            typer.echo(f"shot {shot.shot_id}: {shot.status} {shot.path.name if shot.path else ''}")
            lines = result_summary(shot.message) if shot.status == "processed" else [f"    {shot.message}"]
            typer.echo("\n".join(lines))
        typer.echo(f"\nshots and results: {out / 'shots'} (catalog.sqlite lists every shot)")
        recording = out / "demo.rrd"
        if recording.exists():
            typer.echo(
                f"recording: {recording}  — open it with `mca view {recording}` "
                "(or copy it to a machine with a display and run `rerun demo.rrd`)"
            )
        if any(shot.status != "processed" for shot in results):
            raise typer.Exit(1)
