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
        "1.03,1.02,0.3", "--sim-deviation", help="simulated lens: BASELINE_FACTOR,FOCUS_FACTOR,OFFSET_PX"
    ),
    sim_scale: float = typer.Option(0.25, "--sim-scale", help="simulated render size (fraction of the profile's)"),
    record: Path | None = typer.Option(None, "--record", help="also log the fit into a rerun FILE.rrd"),
    as_json: bool = typer.Option(False, "--json", help="print the fit as one JSON object (progress on stderr)"),
) -> None:
    """Calibrate an MCA lens on the bench: the fitted profile's depths match the rail's known distances."""
    import json

    import cv2

    from mca.capture import calibration as cal
    from mca.devices.cameras import make_sim_rig, open_camera
    from mca.devices.profiles import load_profile
    from mca.devices.rail import RailError, open_rail
    from mca.processing.calibration import CalibrationFitError, fit_lens, plot_fit
    from mca.processing.camera import ProfileError, profile_from_mapping

    def fail(message: str, code: int = 1) -> NoReturn:
        typer.echo(f"error: {message}", err=True)
        raise typer.Exit(code)

    def say(text: str) -> None:  # the report: on stdout, or on stderr when stdout carries the JSON
        typer.echo(text, err=as_json)

    from mca.capture.config import ConfigError, fill_from_config

    try:
        chosen = fill_from_config(camera=camera, rail=rail, profile=profile_name)
    except ConfigError as exc:
        fail(str(exc), 2)
    camera, rail, profile_name = str(chosen["camera"]), str(chosen["rail"]), str(chosen["profile"])

    try:
        profile = load_profile(profile_name)
        nominal = cal.nominal_lens(profile, offset_px)
    except (ProfileError, ValueError) as exc:
        fail(str(exc), 2)
    at_zero = target_distance_at_zero if target_distance_at_zero is not None else nominal.focus_distance_mm + from_mm
    try:
        plan = cal.SweepPlan(from_mm, to_mm, step_mm, at_zero, rail_start)
        deviation = cal.SimDeviation.parse(sim_deviation)
    except ValueError as exc:
        fail(str(exc), 2)
    directory = shots_dir if shots_dir is not None else out.with_name(out.stem + "-sweep")

    bench = None
    if camera == "sim":
        bench = cal.SimBench(profile, plan, deviation, scale=sim_scale)
        factory = open_camera("sim", rig=make_sim_rig(bench.frame))
    else:
        try:
            factory = open_camera(camera)
        except ValueError as exc:
            fail(str(exc), 2)
    say(
        f"sweep {from_mm:+.1f} .. {to_mm:+.1f} mm step {step_mm} mm: {len(plan.positions_mm)} positions, "
        f"target at {at_zero:.1f} mm from the lens with the rail at 0; shots in {directory}"
    )
    try:
        options = {"sim_speedup": 200.0, "poll_interval_s": 0.01} if rail == "sim" else {}
        with open_rail(rail, **options) as bench_rail:
            if bench is not None and rail == "sim":
                bench.rail_runner = bench_rail.simulator  # type: ignore[attr-defined]
            elif bench is not None:
                fail("--camera sim photographs the simulated rail only: use --rail sim with it", 2)
            outcome = cal.run_sweep(
                plan,
                profile,
                directory,
                camera_factory=factory,
                rail=bench_rail,
                log=lambda m: typer.echo(f"  {m}", err=True),
                feed_mm_per_min=feed,
            )
    except RailError as exc:
        fail(f"{exc} Nothing was shot at this run's remaining positions; rerun to resume.")
    except cal.CalibrationError as exc:
        fail(str(exc))

    points = outcome.points
    try:
        fit = fit_lens([p.distance_mm for p in points], [p.disparity_px for p in points], nominal)
    except CalibrationFitError as exc:
        fail(f"{exc} ({len(points)} points in {directory})")
    text = cal.calibrated_profile_toml(profile, fit, plan, shots_dir=str(directory))
    import tomllib

    profile_from_mapping(tomllib.loads(text), str(out))  # the loader accepts what we write
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    plot = plot_fit(fit, truth=bench.truth if bench is not None else None)
    plot_path = out.with_suffix(".png")
    cv2.imwrite(str(plot_path), plot)

    f, s = fit.fitted, fit.sigma
    say(
        f"fit over {len(points)} positions ({len(outcome.shot_positions_mm)} shot now): residual rms "
        f"{fit.residual_rms_px:.4f} px, max depth error {fit.max_depth_error_mm:.3f} mm"
    )
    rows = [
        (
            "d_a (red-blue) mm",
            fit.nominal.filter_centre_distance_mm,
            f.filter_centre_distance_mm,
            s.get("filter_centre_distance_mm"),
            bench.truth.filter_centre_distance_mm if bench else None,
        ),
        (
            "d_ls mm",
            fit.nominal.sensor_distance_mm,
            f.sensor_distance_mm,
            s.get("sensor_distance_mm"),
            bench.truth.sensor_distance_mm if bench else None,
        ),
        (
            "focus distance mm",
            fit.nominal.focus_distance_mm,
            f.focus_distance_mm,
            s.get("focus_distance_mm"),
            bench.truth.focus_distance_mm if bench else None,
        ),
        (
            "disparity offset px (fixed)",
            fit.nominal.disparity_offset_px,
            f.disparity_offset_px,
            None,
            bench.truth.disparity_offset_px if bench else None,
        ),
    ]
    header = f"{'':28s}{'nominal':>12s}{'fitted':>12s}{'sigma':>10s}"
    say(header + (f"{'sim truth':>12s}{'error':>9s}" if bench else ""))
    for label, nom, value, sigma, truth in rows:
        line = f"{label:28s}{nom:12.4f}{value:12.4f}{(f'{sigma:.2g}' if sigma is not None else '-'):>10s}"
        if truth is not None:
            error = f"{(value - truth) / truth * 100:+.3f}%" if "px" not in label else f"{value - truth:+.3f}px"
            line += f"{truth:12.4f}{error:>9s}"
        say(line)
    model_error = None
    if bench is not None:
        import numpy as np

        grid = np.linspace(min(p.distance_mm for p in points), max(p.distance_mm for p in points), 101)
        model_error = float(np.abs(np.asarray(f.distance_mm(bench.truth.disparity_px(grid))) - grid).max())
        say(f"depth error of the fitted profile against the simulated lens over the sweep: {model_error:.3f} mm max")
    say(f"wrote {out} and {plot_path}")
    if as_json:
        names = ("filter_centre_distance_mm", "sensor_distance_mm", "focus_distance_mm", "disparity_offset_px")
        document = {
            "profile": str(out),
            "plot": str(plot_path),
            "shots_dir": str(directory),
            "positions": len(points),
            "shot_now": len(outcome.shot_positions_mm),
            "residual_rms_px": fit.residual_rms_px,
            "max_depth_error_mm": fit.max_depth_error_mm,
            "parameters": {
                name: {"nominal": row[1], "fitted": row[2], "sigma": row[3], "sim_truth": row[4]}
                for name, row in zip(names, rows)
            },
            "sim_model_error_mm": model_error,
        }
        from mca.capture.outputs import json_safe

        typer.echo(json.dumps(json_safe(document), indent=2))

    if record is not None:
        try:
            from mca.capture.recording import RerunRecorder
        except ImportError:
            typer.echo("not recorded: capture.recording is not available", err=True)
            return
        with RerunRecorder(record) as recorder:
            recorder.record(
                "calibration",
                plot=cv2.cvtColor(plot, cv2.COLOR_BGR2RGB),
                filter_centre_distance_mm=f.filter_centre_distance_mm,
                sensor_distance_mm=f.sensor_distance_mm,
                focus_distance_mm=f.focus_distance_mm,
                residual_rms_px=fit.residual_rms_px,
                max_depth_error_mm=fit.max_depth_error_mm,
                residuals_px=fit.residuals_px,
                profile=text,
            )
        say(f"recorded in {record}")


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate)
