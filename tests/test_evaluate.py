"""Table 2 evaluation: matching, errors, region count and order on a small simulated scene, and the CLI."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from mca.capture.cli import app
from mca.devices.profiles import load_profile
from mca.devices.sim.render import SensorModel, SimulationOptics, render
from mca.devices.sim.scenes import paper_scene
from mca.processing.evaluate import ObjectRow, SceneEvaluation, bayer_planes, evaluate_scene, format_table, summarise
from mca.processing.peers import colour_line_wta, sgbm_disparity
from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX, align_channel_samples, run_pipeline


def test_rows_and_summary():
    rows = [
        ObjectRow("A", "a", 30.0, {"ours": 31.0, "peer": 27.0}),
        ObjectRow("B", "b", 0.0, {"ours": 0.5, "peer": 0.0}),
    ]
    evaluation = SceneEvaluation("x", rows, 3, 3, True)
    assert np.isclose(rows[0].rel_error("ours"), 1 / 30) and rows[1].rel_error("ours") is None
    summary = summarise([evaluation], ["ours", "peer"])
    assert np.isclose(summary.median_rel["peer"], 0.1) and np.isclose(summary.focus_abs_mm["ours"], 0.5)
    text = format_table([evaluation], ["ours", "peer"])
    assert "focus" in text and "region count right in 1/1" in text


def test_paper_f_beats_the_peers():
    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 0.25)
    sensor = SensorModel()
    rendering = render(paper_scene("paper-f", optics.focus_distance_mm), optics, sensor, seed=2)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    result = run_pipeline(
        planes, optics.aperture, optics.mca, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX
    )
    aligned = align_channel_samples(planes, RGGB_HALF_RES_OFFSETS_PX)
    peers = {
        "sgbm": sgbm_disparity(aligned, optics.aperture, (-8.0, 24.0)) * 2.0,
        "wta": colour_line_wta(aligned, optics.aperture, (-8.0, 24.0)) * 2.0,
    }
    evaluation = evaluate_scene(rendering.truth, rendering.labels, result, optics.mca, peers)
    assert evaluation.region_count == evaluation.true_region_count == 4
    assert evaluation.order_correct
    summary = summarise([evaluation], ["ours", "sgbm", "wta"])
    assert summary.median_rel["ours"] < 0.06
    assert summary.median_rel["ours"] < min(summary.median_rel["sgbm"], summary.median_rel["wta"])


def test_cli_lists_in_help():
    out = CliRunner().invoke(app, ["evaluate", "--help"])
    assert out.exit_code == 0 and "Table 2" in out.output


def test_table_2_reads_the_scenes_from_a_render_folder_and_renders_only_what_is_missing(tmp_path):
    def object_rows(output: str) -> list[str]:  # the Table 2 lines of paper-g, without the timed summary line
        return [line for line in output.splitlines() if line.startswith("paper-g ") and "regions" not in line]

    args = ["evaluate", "--scene", "paper-g", "--scale", "0.125", "--no-peers", "--renders", str(tmp_path)]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    assert "paper-g: rendering into" in first.output
    assert (tmp_path / "paper-g.CR2").is_file() and (tmp_path / "truth" / "paper-g.truth.json").is_file()
    second = CliRunner().invoke(app, args)
    assert second.exit_code == 0, second.output
    assert "rendering into" not in second.output  # read from the folder: the CR2 and truth/
    memory = CliRunner().invoke(app, args[:-2])  # rendered in memory, as without --renders
    assert len(object_rows(first.output)) == 3
    assert object_rows(first.output) == object_rows(second.output) == object_rows(memory.output)
