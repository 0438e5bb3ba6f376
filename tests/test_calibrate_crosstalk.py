"""Crosstalk measured at the bench: `processing.calibration.measure_leak` on shots of the grey target that the
simulated renderer (devices/sim/render.py, which mixes the filters' light at each Bayer site) made with a known
matrix, and `mca calibrate` taking it out before the lens fit."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from test_recording import rrd_print
from typer.testing import CliRunner

from mca.capture import calibration as cal
from mca.capture.cli import app
from mca.devices.profiles import load_profile, load_profile_file
from mca.processing.calibration import (
    BAYER_RED_FROM_BLUE_PX,
    LeakEstimate,
    baseline_direction,
    combine_leaks,
    measure_leak,
    target_disparity_px,
    unmix_sites,
)
from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX

PROFILE = load_profile("paper-70d")
OFF_DIAGONAL = ~np.eye(3, dtype=bool)


def _leaking(rng: np.random.Generator, most: float) -> np.ndarray:
    """A sensor channel <- filter matrix with a different leak in every entry (rows sum to 1)."""
    matrix = np.where(OFF_DIAGONAL, rng.uniform(0.0, most, (3, 3)), 0.0)
    return matrix + np.diag(1.0 - matrix.sum(axis=1))


def _planes(distance_mm: float, crosstalk: np.ndarray | None, seed: int = 5) -> np.ndarray:
    """The half-resolution Bayer planes (R, mean G, B) of the simulated target at `distance_mm`."""
    from mca.devices.sim.render import SimulationOptics
    from mca.devices.sim.scenes import target_scene
    from mca.devices.sim.world import render_scene

    optics = SimulationOptics.from_profile(PROFILE, 0.25)
    if crosstalk is not None:
        leak = tuple(tuple(float(v) for v in row) for row in crosstalk)
        optics = dataclasses.replace(optics, aperture=dataclasses.replace(optics.aperture, crosstalk=leak))
    mosaic = render_scene(target_scene(distance_mm), PROFILE, optics=optics, seed=seed).mosaic.astype(np.float32)
    green = 0.5 * (mosaic[0::2, 1::2] + mosaic[1::2, 0::2])
    return np.dstack([mosaic[0::2, 0::2], green, mosaic[1::2, 1::2]])


def _unit_columns(matrix: np.ndarray) -> np.ndarray:
    return matrix / np.diag(matrix)[None, :]


FOCUS_MM = PROFILE.lens.focus_distance_mm if PROFILE.lens is not None else 1000.0


@pytest.mark.parametrize("distance_mm", [FOCUS_MM - 300.0, FOCUS_MM + 300.0])
def test_one_shot_far_from_focus_reads_every_entry_of_an_uneven_leak(distance_mm: float) -> None:
    truth = _leaking(np.random.default_rng(7), 0.06)
    estimate = measure_leak(_planes(distance_mm, truth), channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX)
    assert estimate.separation_px >= 3.0
    error = np.abs(estimate.matrix - _unit_columns(truth))[OFF_DIAGONAL]
    assert error.max() < 0.012, np.round(estimate.matrix, 4)
    assert np.allclose(np.diag(estimate.matrix), 1.0)


def test_a_camera_without_crosstalk_reads_none() -> None:
    estimate = measure_leak(_planes(FOCUS_MM - 300.0, None), channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX)
    assert np.abs(estimate.matrix[OFF_DIAGONAL]).max() < 0.008, np.round(estimate.matrix, 4)


def test_near_focus_the_copies_overlap_and_the_shot_is_not_used() -> None:
    truth = _leaking(np.random.default_rng(7), 0.06)
    near = measure_leak(_planes(FOCUS_MM + 60.0, truth), channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX)
    assert near.separation_px < 3.0
    assert combine_leaks([near]) is None
    far = LeakEstimate(np.eye(3), 5.0, np.zeros((3, 2)))
    combined = combine_leaks([near, far])
    assert combined is not None
    matrix, shots, spread = combined
    assert np.array_equal(matrix, far.matrix) and shots == 1 and spread == 0.0  # the far shot alone


def test_taking_the_leak_out_gives_the_disparity_of_a_shot_without_one() -> None:
    """The same target, noise and lens with and without a 6 % leak: the leak pulls the measured red-blue
    disparity towards zero; unmixed on the channels' own sites (`unmix_sites`) it reads what the clean shot
    reads."""
    truth = _leaking(np.random.default_rng(3), 0.06)
    distance = FOCUS_MM - 100.0
    direction = baseline_direction(PROFILE.aperture)

    def disparity(planes: np.ndarray) -> float:
        return target_disparity_px(
            planes[..., 0], planes[..., 2], direction, bayer_offset_px=BAYER_RED_FROM_BLUE_PX
        ).disparity_px

    clean = disparity(_planes(distance, None))
    leaky = _planes(distance, truth)
    assert abs(disparity(leaky) - clean) > 0.1  # the leak's bias: what the fit must not see
    assert disparity(unmix_sites(leaky, truth, RGGB_HALF_RES_OFFSETS_PX)) == pytest.approx(clean, abs=0.02)


def test_unmix_sites_refuses_a_matrix_it_cannot_invert() -> None:
    with pytest.raises(ValueError, match=r"the crosstalk .* cannot be inverted: measure it again"):
        unmix_sites(np.zeros((8, 8, 3), np.float32), np.ones((3, 3)), None)


def test_sim_deviation_takes_an_optional_leak() -> None:
    assert cal.SimDeviation.parse("1.03,1.02,0.3").crosstalk() is None
    leak = cal.SimDeviation.parse("1.03,1.02,0.3,0.06").crosstalk()
    assert leak is not None and np.allclose(np.sum(leak, axis=1), 1.0) and leak[0][1] == pytest.approx(0.03)
    with pytest.raises(ValueError, match="LEAK"):
        cal.SimDeviation.parse("1.03,1.02,0.3,0.7")


@pytest.mark.parametrize("leak", [0.06, 0.0])
def test_calibrate_measures_the_leak_and_takes_it_out_only_when_it_helps(tmp_path: Path, leak: float) -> None:
    """A sweep far enough from focus for the copies to part at its near end. With a 6 % leak the fit left with
    it is off by a tenth of the residual; taken out, the profile carries the measured matrix and its depths
    match the simulated lens within a millimetre. Without a leak the noise-level reading is not written."""
    out = tmp_path / "cal.toml"
    args = ["calibrate", "--camera", "sim", "--rail", "sim", "--from", "-200", "--to", "100", "--step", "50"]
    args += ["--profile", "paper-70d", "--out", str(out), "--sim-deviation", f"1.03,1.02,0.3,{leak}", "--json"]
    args += ["--record", str(tmp_path / "cal.rrd")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout[result.stdout.index("{") :])
    assert document["crosstalk_shots"] >= 1
    measured = np.asarray(document["crosstalk"])
    truth = np.asarray(document["sim_crosstalk"])
    assert np.abs(measured - truth)[OFF_DIAGONAL].max() < 0.012
    written = load_profile_file(out).aperture.crosstalk
    if leak:
        assert document["crosstalk_applied"]
        assert document["residual_without_crosstalk_px"] > 5 * document["residual_rms_px"]
        assert document["sim_model_error_mm"] < 1.0
        assert written is not None and np.allclose(written, measured, atol=1e-4)
        entities = rrd_print(tmp_path / "cal.rrd")  # the report's matrix in the recording, for review
        assert "TextDocument" in entities.get("/shot/stages/calibration/crosstalk", set()), entities.keys()
        # a shot spoilt since the sweep is skipped with its name, and the others still read
        sweep = tmp_path / "cal-sweep"
        store = cal.CalibrationStore(sweep / "catalog.sqlite")
        points = store.points()
        store.close()
        first = sweep / points[0].file_name  # the nearest position: the farthest from focus
        first.write_bytes(first.read_bytes()[:1000])
        said: list[str] = []
        matrix, shots, _ = cal.measure_sweep_crosstalk(points, sweep, PROFILE, said.append)
        assert any(points[0].file_name in line and "skipped" in line for line in said), said
        assert shots == document["crosstalk_shots"] - 1 and (matrix is None) == (shots == 0)
    else:
        assert not document["crosstalk_applied"] and written is None
        assert document["sim_model_error_mm"] < 0.1
