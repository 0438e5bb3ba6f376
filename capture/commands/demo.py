"""`mca demo`: the main job end to end — tethered capture, accurate-depth processing and a rerun recording."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def _summarise(result_dir: str) -> list[str]:
    result_file = Path(result_dir) / "result.json"
    if not result_file.exists():
        return [f"    no result.json in {result_dir}"]
    result = json.loads(result_file.read_text())
    lines = []
    for region in sorted(result.get("regions", []), key=lambda r: r.get("order", 0)):
        distance = region.get("distance_mm")
        depth = region.get("inter_object_depth_mm")
        where = (
            f"{distance:8.1f} mm from the lens ({depth:+7.1f} mm from focus)"
            if distance is not None and depth is not None
            else "distance unknown"
        )
        slant = " slanted" if region.get("slant") else ""
        focus = " in focus" if region.get("id") == result.get("focus_region") else ""
        lines.append(
            f"    region {region['id']:2d} order {region['order']}: disparity {region['disparity_px']:+6.2f} px, "
            f"{where}{focus}{slant}"
        )
    timings = result.get("timings_s", {})
    # the pipeline's stages are also summed in its "total" and in "pipeline": count each second once
    whole = [timings[k] for k in ("read", "pipeline", "write") if k in timings]
    total = sum(whole) if "pipeline" in timings else sum(timings.values())
    lines.append(f"    processed in {total:.2f} s")
    return lines


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
        from mca.capture.tether import TetherError, TetherSession
        from mca.devices.cameras import make_sim_rig, open_camera
        from mca.devices.ptp.transport import TransportError
        from mca.devices.sim.world import scene_frame_source

        try:
            chosen = fill_from_config(camera=camera, profile=profile)
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        camera, profile = str(chosen["camera"]), str(chosen["profile"])

        spec = camera
        if camera == "auto":
            try:
                from mca.devices.ptp.transport_usb import find_cameras

                spec = "auto" if find_cameras() else "sim"
            except Exception:
                spec = "sim"
        if spec == "sim":
            try:
                size_value: str | float = float(size)
            except ValueError:
                size_value = size
            factory = open_camera("sim", rig=make_sim_rig(scene_frame_source(size_value)))
            typer.echo(f"camera: simulated Canon EOS 70D ({size} frames of the paper's Fig. 4 scenes)", err=True)
        else:
            factory = open_camera(spec)
            typer.echo(f"camera: {spec}", err=True)

        recording = out / "demo.rrd"
        try:
            session = TetherSession(
                factory,
                out / "shots",
                process=True,
                profile=profile,
                record=recording,
                log=lambda m: typer.echo(f"  {m}", err=True),
            )
        except TetherError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
        try:
            session.connect()
            results = session.capture(count, 0.0)
        except (TransportError, TetherError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from exc
        finally:
            session.close()

        failed = 0
        for shot in results:
            typer.echo(f"shot {shot.shot_id}: {shot.status} {shot.path.name if shot.path else ''}")
            if shot.status == "processed":
                for line in _summarise(shot.message):
                    typer.echo(line)
            else:
                failed += 1
                typer.echo(f"    {shot.message}")
        typer.echo(f"\nshots and results: {out / 'shots'} (catalog.sqlite lists every shot)")
        if recording.exists():
            typer.echo(
                f"recording: {recording}  — open it with `mca view {recording}` "
                "(or copy it to a machine with a display and run `rerun demo.rrd`)"
            )
        if failed:
            raise typer.Exit(1)
