"""The Fig. 4 scenes reproduce Table 1's depths and the occlusions the paper describes, and `mca simulate` writes them."""

from __future__ import annotations

import json

import pytest

from mca.devices.profiles import load_profile
from mca.devices.sim.render import SimulationOptics, scene_truth, truth_rasters
from mca.devices.sim.scenes import TABLE1_INTER_OBJECT_DEPTH_MM, paper_scene, scene_names

PROFILE = load_profile("paper-70d")
TINY = SimulationOptics.from_profile(PROFILE, 0.125)


def _truth(name: str) -> dict:
    scene = paper_scene(name, TINY.focus_distance_mm)
    _depth, labels, masks = truth_rasters(scene, TINY)
    return scene_truth(scene, TINY, labels, masks)


@pytest.mark.parametrize("name", scene_names())
def test_scene_matches_table1_and_is_visible(name: str) -> None:
    truth = _truth(name)
    table = TABLE1_INTER_OBJECT_DEPTH_MM[name]
    frame = TINY.width_px * TINY.height_px
    for obj in truth["objects"]:
        assert obj["visible_px"] > 0.01 * frame, f"{obj['name']} is too small or hidden"
        if obj["slant"] is not None:
            assert obj["slant"]["from_inter_object_depth_mm"] == pytest.approx(table["A"])
            assert obj["slant"]["to_inter_object_depth_mm"] == pytest.approx(table["B"])
        else:
            assert obj["inter_object_depth_mm"] == pytest.approx(table[obj["paper_label"]])
        # An occluder is nearer than what it occludes.
        for other in obj["occludes"]:
            hidden = next(o for o in truth["objects"] if o["id"] == other)
            assert obj["distance_mm"] < hidden["distance_mm"]
    assert truth["background"]["inter_object_depth_mm"] > max(o["inter_object_depth_mm"] for o in truth["objects"])


def test_occlusions_described_by_the_paper() -> None:
    def occludes(name: str) -> dict[str, set[str]]:
        truth = _truth(name)
        by_id = {o["id"]: o["paper_label"] for o in truth["objects"]}
        return {o["paper_label"]: {by_id[i] for i in o["occludes"]} for o in truth["objects"]}

    assert occludes("paper-a") == {k: set() for k in "ABCDE"}  # no overlap
    b = occludes("paper-b")
    assert b["A"] == {"C"} and b["B"] == {"C"}  # blue and green over orange
    e = occludes("paper-e")
    assert {"A", "C", "D"} == {k for k, v in e.items() if "E" in v}  # red tomato, carrot, green tomato over spatula
    f = occludes("paper-f")
    assert f["C"] == {"B"} and f["B"] == {"A"}
    g = occludes("paper-g")
    assert g["C"] == {"A-B"}  # the carrot hides the knife's middle


def test_same_colour_objects_exist() -> None:
    for name in ("paper-a", "paper-c", "paper-d", "paper-e"):
        colours = [o["colour"] for o in _truth(name)["objects"]]
        assert len(set(colours)) < len(colours), name


def test_mca_simulate_writes_the_files(tmp_path) -> None:
    from typer.testing import CliRunner

    from mca.capture.cli import app

    result = CliRunner().invoke(app, ["simulate", "--scene", "paper-g", "--out", str(tmp_path), "--size", "small"])
    assert result.exit_code == 0, result.output
    assert "[1/1] paper-g" in result.output
    # the photograph alone in the folder, its truth in truth/ (where `mca process DIR` does not look)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paper-g.CR2", "truth"]
    for suffix in (".truth.json", ".depth.tiff", ".labels.png"):
        assert (tmp_path / "truth" / f"paper-g{suffix}").is_file()
    from mca.capture.batch import discover_inputs

    assert discover_inputs([tmp_path]) == [tmp_path / "paper-g.CR2"]
    truth = json.loads((tmp_path / "truth" / "paper-g.truth.json").read_text())
    assert truth["focus_distance_mm"] == pytest.approx(1000.5703, abs=1e-3)
    knife = next(o for o in truth["objects"] if o["slant"])
    assert knife["slant"]["axis"] == "x"
    assert not list(tmp_path.glob(".*")) and not list((tmp_path / "truth").glob(".*"))  # no temporary files left
    bad = CliRunner().invoke(app, ["simulate", "--scene", "paper-z", "--out", str(tmp_path)])
    assert bad.exit_code == 2 and "unknown scene" in bad.output
