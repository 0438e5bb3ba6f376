"""`mca calibrate`: sweep a textured target along the bench rail, fit d_a and d_ls, write a calibrated profile."""

from __future__ import annotations

from pathlib import Path
from typing import NoReturn

import typer


def calibrate(
    camera: str | None = typer.Option(
        None, "--camera", "-c", help="auto, sim, usb:BUS:ADDR or ptpip:HOST:PORT (default: config, auto)"
    ),
    rail: str | None = typer.Option(
        None, "--rail", envvar="MCA_RAIL", help="serial port of the GRBL rail, or sim (default: config, sim)"
    ),
    from_mm: float = typer.Option(
        -100.0,
        "--from",
        help="first sweep position, mm (offset from the focus plane with the default --target-distance-at-zero)",
    ),
    to_mm: float = typer.Option(150.0, "--to", help="last sweep position, mm"),
    step_mm: float = typer.Option(10.0, "--step", help="sweep step, mm"),
    profile_name: str | None = typer.Option(
        None, "--profile", help="nominal profile: built-in name or TOML (default: config, paper-70d)"
    ),
    out: Path = typer.Option(..., "--out", "-o", help="calibrated profile TOML to write (plot beside it as .png)"),
    shots_dir: Path | None = typer.Option(
        None, "--dir", help="shots and catalog.sqlite; default OUT stem + '-sweep'. Rerun with the same to resume"
    ),
    target_distance_at_zero: float | None = typer.Option(
        None,
        "--target-distance-at-zero",
        help="target distance from the lens (mm) with the rail at 0 mm; default: the profile's focus distance + --from",
    ),
    rail_start: float = typer.Option(0.0, "--rail-start", help="rail position (mm from home) of --from"),
    offset_px: float = typer.Option(
        0.0, "--disparity-offset-px", help="known red-blue disparity offset (px), held fixed in the fit"
    ),
    feed: float | None = typer.Option(None, "--feed", help="rail feed, mm/min"),
    sim_deviation: str = typer.Option(
        "1.03,1.02,0.3",
        "--sim-deviation",
        help="simulated lens: BASELINE_FACTOR,FOCUS_FACTOR,OFFSET_PX[,LEAK] (LEAK: crosstalk, e.g. 0.06)",
    ),
    crosstalk: bool = typer.Option(
        True,
        "--crosstalk/--no-crosstalk",
        help="measure the crosstalk on the shots far from focus (the target must be grey), take it out before "
        "the fit and write it into the profile",
    ),
    sim_scale: float = typer.Option(0.25, "--sim-scale", help="simulated render size (fraction of the profile's)"),
    record: Path | None = typer.Option(None, "--record", help="also log the fit into a rerun FILE.rrd"),
    as_json: bool = typer.Option(False, "--json", help="print the fit as one JSON object (progress on stderr)"),
) -> None:
    """Calibrate an MCA lens on the bench: the fitted profile's depths match the rail's known distances."""
    import json

    from mca.capture import calibration as cal

    def say(text: str) -> None:  # the report: on stdout, or on stderr when stdout carries the JSON
        typer.echo(text, err=as_json)

    request = cal.CalibrationRequest(
        out=out,
        camera=camera,
        rail=rail,
        profile=profile_name,
        from_mm=from_mm,
        to_mm=to_mm,
        step_mm=step_mm,
        shots_dir=shots_dir,
        target_distance_at_zero_mm=target_distance_at_zero,
        rail_start_mm=rail_start,
        disparity_offset_px=offset_px,
        feed_mm_per_min=feed,
        sim_deviation=sim_deviation,
        sim_scale=sim_scale,
        crosstalk=crosstalk,
    )
    try:
        setup = cal.plan_calibration(request)
        say(setup.describe())
        run = cal.run_calibration(setup, log=lambda m: typer.echo(f"  {m}", err=True))
    except cal.CalibrationUsageError as exc:
        _fail(str(exc), 2)
    except cal.CalibrationError as exc:
        _fail(str(exc))
    for line in run.report_lines():
        say(line)
    if as_json:
        typer.echo(json.dumps(run.document(), indent=2))
    if record is not None:
        try:
            cal.record_calibration(run, record)
        except ImportError:
            typer.echo("not recorded: capture.recording is not available", err=True)
            return
        say(f"recorded in {record}")


def _fail(message: str, code: int = 1) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate)
