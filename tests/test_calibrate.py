"""Tests of the bench calibration: target disparity, the thin-lens fit, the sweep over the simulated devices, faults."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mca.capture import calibration as cal
from mca.capture.cli import app
from mca.devices.cameras import make_sim_rig, open_camera
from mca.devices.profiles import load_profile, load_profile_file
from mca.devices.rail import open_rail
from mca.processing.calibration import (
    PARAMETERS,
    CalibrationFitError,
    LensModel,
    baseline_direction,
    fit_lens,
    identifiability,
    target_disparity_px,
)

PROFILE = load_profile("paper-70d")
SWEEP_MM = np.arange(-100.0, 151.0, 10.0) + 1000.5703422053223


def _nominal() -> LensModel:
    return cal.nominal_lens(PROFILE)


@pytest.mark.parametrize("distance_mm", [905.0, 1003.0, 1140.0])
def test_target_disparity_matches_the_rendered_truth(distance_mm: float) -> None:
    from mca.devices.sim.render import SimulationOptics
    from mca.devices.sim.scenes import target_scene
    from mca.devices.sim.world import render_scene

    lens = SimulationOptics.from_profile(PROFILE, 0.15).perturbed(baseline_factor=1.03)
    shot = render_scene(target_scene(distance_mm), PROFILE, optics=lens, seed=4)
    mosaic = shot.mosaic.astype(np.float64)
    est = target_disparity_px(mosaic[0::2, 0::2], mosaic[1::2, 1::2], baseline_direction(lens.aperture))
    assert est.disparity_px == pytest.approx(lens.disparity_px(distance_mm), abs=0.02)
    assert abs(est.across_px) < 0.03
    assert est.correlation > 0.95


def test_three_parameters_are_not_identifiable_two_are() -> None:
    three = identifiability(_nominal(), SWEEP_MM, PARAMETERS)
    two = identifiability(_nominal(), SWEEP_MM, PARAMETERS[:2])
    assert three.singular_values[-1] < 1e-6 and not three.identifiable  # A - B/u: rank 2
    assert two.identifiable and two.condition_number < 10
    with pytest.raises(CalibrationFitError, match="not identifiable"):
        fit_lens(SWEEP_MM, _nominal().disparity_px(SWEEP_MM), _nominal(), free=PARAMETERS)


def test_fit_recovers_a_deviating_lens_with_uncertainties() -> None:
    truth = cal.SimDeviation(1.03, 1.02, 0.0).truth(PROFILE)
    rng = np.random.default_rng(1)
    measured = truth.disparity_px(SWEEP_MM) + rng.normal(0, 0.02, SWEEP_MM.size)
    fit = fit_lens(SWEEP_MM, measured, _nominal())
    assert fit.fitted.filter_centre_distance_mm == pytest.approx(truth.filter_centre_distance_mm, rel=1e-3)
    assert fit.fitted.focus_distance_mm == pytest.approx(truth.focus_distance_mm, rel=1e-3)
    assert 0.01 < fit.residual_rms_px < 0.03
    assert fit.sigma["filter_centre_distance_mm"] < 0.01 and fit.sigma["focus_distance_mm"] < 0.1
    assert abs(fit.correlation[0, 1]) < 0.9
    assert fit.max_depth_error_mm < 1.0


def test_an_offset_is_absorbed_into_the_focus_and_depths_stay_exact() -> None:
    truth = cal.SimDeviation(1.03, 1.02, 0.3).truth(PROFILE)
    fit = fit_lens(SWEEP_MM, truth.disparity_px(SWEEP_MM), _nominal())  # offset held at 0
    assert fit.fitted.filter_centre_distance_mm == pytest.approx(truth.filter_centre_distance_mm, rel=5e-4)
    assert fit.fitted.focus_distance_mm == pytest.approx(truth.focus_distance_mm, rel=5e-3)
    assert fit.max_depth_error_mm < 1e-6


def test_calibrated_profile_loads_and_keeps_the_fit(tmp_path: Path) -> None:
    truth = cal.SimDeviation().truth(PROFILE)
    fit = fit_lens(SWEEP_MM, truth.disparity_px(SWEEP_MM) + 0.001 * np.sin(SWEEP_MM), _nominal())
    plan = cal.SweepPlan(-100, 150, 10, 900.57)
    path = tmp_path / "cal.toml"
    path.write_text(cal.calibrated_profile_toml(PROFILE, fit, plan, shots_dir="sweep"))
    loaded = load_profile_file(path)
    assert loaded.aperture.baseline_mm == pytest.approx(fit.fitted.filter_centre_distance_mm, abs=1e-5)
    assert loaded.lens is not None
    assert loaded.lens.sensor_distance_mm == pytest.approx(fit.fitted.sensor_distance_mm, abs=1e-5)
    table = tomllib.loads(path.read_text())["calibration"]
    assert table["points"] == SWEEP_MM.size and table["residual_rms_px"] >= 0
    assert table["sigma_filter_centre_distance_mm"] > 0


def _bench(plan: cal.SweepPlan) -> tuple[cal.SimBench, object]:
    bench = cal.SimBench(PROFILE, plan, cal.SimDeviation(), scale=0.1)
    return bench, open_camera("sim", rig=make_sim_rig(bench.frame))


def _open_sim_rail(bench: cal.SimBench):
    rail = open_rail("sim", sim_speedup=500.0, poll_interval_s=0.005)
    bench.rail_runner = rail.simulator
    return rail


def test_unplugged_rail_stops_with_its_port_and_the_rerun_shoots_only_the_rest(tmp_path: Path) -> None:
    plan = cal.SweepPlan(-100, 150, 50, 900.57)  # 6 positions
    bench, factory = _bench(plan)
    rail = _open_sim_rail(bench)
    port = rail.port

    def unplug_after_two(point: cal.CalibrationPoint) -> None:
        if point.position_mm == -50.0:
            rail.simulator.unplug()

    with pytest.raises(cal.CalibrationError) as info:
        try:
            cal.run_sweep(plan, PROFILE, tmp_path, camera_factory=factory, rail=rail, on_point=unplug_after_two)
        finally:
            rail.close()
    message = str(info.value)
    assert port in message and "rerun" in message and "2 of 6" in message
    assert len(bench.distances_shot_mm) == 2

    rail = _open_sim_rail(bench)  # plugged back in: a freshly powered controller
    with rail:
        outcome = cal.run_sweep(plan, PROFILE, tmp_path, camera_factory=factory, rail=rail)
    assert outcome.shot_positions_mm == [0.0, 50.0, 100.0, 150.0]
    assert [p.position_mm for p in outcome.points] == plan.positions_mm
    assert len(bench.distances_shot_mm) == 6
    # the camera photographed the target where the rail put it
    assert bench.distances_shot_mm == pytest.approx(
        [plan.distance_mm(plan.rail_mm(s)) for s in plan.positions_mm], abs=0.01
    )
    # a third run has nothing to shoot
    rail = _open_sim_rail(bench)
    with rail:
        again = cal.run_sweep(plan, PROFILE, tmp_path, camera_factory=factory, rail=rail)
    assert again.shot_positions_mm == [] and len(again.points) == 6


def test_a_grbl_alarm_mid_sweep_names_the_port(tmp_path: Path) -> None:
    plan = cal.SweepPlan(-100, 0, 50, 900.57)
    bench, factory = _bench(plan)
    rail = _open_sim_rail(bench)

    def alarm(point: cal.CalibrationPoint) -> None:
        rail.simulator.trigger_alarm(1)

    with pytest.raises(cal.CalibrationError, match=r"alarm|ALARM|Alarm") as info:
        try:
            cal.run_sweep(plan, PROFILE, tmp_path, camera_factory=factory, rail=rail, on_point=alarm)
        finally:
            rail.close()
    assert rail.port in str(info.value)


def test_full_command_writes_a_profile_close_to_the_simulated_truth(tmp_path: Path) -> None:
    out = tmp_path / "cal.toml"
    result = CliRunner().invoke(
        app,
        [
            "calibrate",
            "--camera",
            "sim",
            "--rail",
            "sim",
            "--from",
            "-100",
            "--to",
            "150",
            "--step",
            "25",
            "--profile",
            "paper-70d",
            "--out",
            str(out),
            "--sim-scale",
            "0.1",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "sim truth" in result.output
    loaded = load_profile_file(out)
    truth = cal.SimDeviation().truth(PROFILE)
    assert loaded.aperture.baseline_mm == pytest.approx(truth.filter_centre_distance_mm, rel=5e-3)
    assert loaded.lens is not None
    assert loaded.lens.focus_distance_mm == pytest.approx(truth.focus_distance_mm, rel=5e-3)
    assert out.with_suffix(".png").stat().st_size > 1000
    assert (tmp_path / "cal-sweep" / "catalog.sqlite").exists()
