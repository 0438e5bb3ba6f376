"""The application functions behind the `mca` commands, called directly (no CliRunner): what they return, write
and raise. The commands themselves (options, printing, exit codes) are tested through the CLI elsewhere."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from mca.devices.sim.eos70d.responder import default_frame_source


@pytest.fixture
def fast_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulated body "photographs" small deterministic files (the rendering is tested elsewhere)."""
    from mca.devices.sim import world

    monkeypatch.setattr(world, "scene_frame_source", lambda *a, **k: default_frame_source)


# --- simulate -------------------------------------------------------------------------------------------------------


def _two_plane_source(folder: Path, near_value: int = 40, far_value: int = 20) -> tuple[Path, Path]:
    """A textured 160 x 96 photograph whose left half has stereo disparity `near_value`, its right half `far_value`."""
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.integers(0, 256, (96, 160, 3)).astype(np.uint8), (0, 0), 1.5)
    disparity = np.full((96, 160), far_value, np.uint8)
    disparity[:, :80] = near_value
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "im.png"), image)
    cv2.imwrite(str(folder / "disp.png"), disparity)
    return folder / "im.png", folder / "disp.png"


def test_simulate_rgbd_writes_the_capture_with_the_depth_the_disparity_asks_for(tmp_path: Path) -> None:
    from mca.capture.simulate_app import RgbdOptions, simulate_rgbd
    from mca.devices.profiles import load_profile, load_profile_file
    from mca.processing.optics import MCAOptics

    image, disparity = _two_plane_source(tmp_path / "src")
    profile = load_profile("paper-70d")
    options = RgbdOptions(near_mm=900.0, far_mm=1300.0, focus_mm=1000.0, disparity_scale=1.0, name="planes")
    done = simulate_rgbd(profile, image, disparity, tmp_path / "out", options)

    assert done.paths["image"] == tmp_path / "out" / "planes.tiff" and done.paths["image"].stat().st_size > 0
    assert "160x96 tiff" in done.summary and done.seconds >= 0
    distance = tifffile.imread(done.paths["distance"])
    assert distance.shape == (96, 160)
    # the larger stereo disparity is the nearer plane: the depth range's ends, pixel for pixel
    np.testing.assert_allclose(distance[:, :70], 900.0, rtol=1e-4)
    np.testing.assert_allclose(distance[:, 90:], 1300.0, rtol=1e-4)
    truth = json.loads(done.paths["truth"].read_text())
    assert truth["focus_distance_mm"] == pytest.approx(1000.0)
    # the disparity truth agrees with the paper's optics of the focused profile written beside it (eqs. 13/14),
    # in pixels of the render (the sensor's width over 160 pixels)
    focused = load_profile_file(done.paths["profile"])
    optics = MCAOptics.from_profile(focused)
    render_px_per_sensor_px = focused.pixel_pitch_mm / truth["optics"]["pixel_pitch_mm"]
    red_blue = tifffile.imread(done.paths["disparity"])
    for column, distance_mm in ((10, 900.0), (150, 1300.0)):
        expected = optics.from_distance(distance_mm).disparity_px * render_px_per_sensor_px
        assert abs(red_blue[48, column]) == pytest.approx(abs(expected), rel=0.01), (distance_mm, expected)
    assert red_blue[48, 10] * red_blue[48, 150] < 0  # one plane in front of the focus, one behind


def test_simulate_rgbd_rejects_bad_options_naming_them(tmp_path: Path) -> None:
    from mca.capture.simulate_app import RgbdOptions, SimulateError, crosstalk_matrix, simulate_rgbd
    from mca.devices.profiles import load_profile

    image, disparity = _two_plane_source(tmp_path / "src")
    profile = load_profile("paper-70d")
    with pytest.raises(SimulateError, match=r"--crosstalk must be in \[0, 0.5\), got 0.6"):
        simulate_rgbd(profile, image, disparity, tmp_path / "out", RgbdOptions(crosstalk=0.6))
    with pytest.raises(SimulateError, match=r"no-such\.png"):
        simulate_rgbd(profile, tmp_path / "no-such.png", disparity, tmp_path / "out")
    assert not (tmp_path / "out").exists()  # nothing half-written
    matrix = np.array(crosstalk_matrix(0.1))
    np.testing.assert_allclose(matrix.sum(axis=1), 1.0)  # light is moved between colours, not lost
    np.testing.assert_allclose(np.diag(matrix), 0.9)
    assert crosstalk_matrix(0.0) is None


def test_simulate_setup_and_paper_scene_errors(tmp_path: Path) -> None:
    from mca.capture.simulate_app import SimulateError, parse_integers, prepare_simulation, simulate_paper

    assert parse_integers("1, 2,3", "--seeds") == (1, 2, 3)
    with pytest.raises(SimulateError, match="--seeds must be integers"):
        parse_integers("1,x", "--seeds")
    with pytest.raises(SimulateError, match="--format must be tiff or cr2"):
        prepare_simulation("paper-70d", tmp_path / "a", "png")
    with pytest.raises(SimulateError, match="neither a built-in profile"):
        prepare_simulation("no-such-profile", tmp_path / "b")
    profile, out = prepare_simulation("paper-70d", tmp_path / "c")
    assert out.is_dir() and profile.name == "paper-70d"
    started = []
    with pytest.raises(SimulateError, match="unknown scene 'paper-z'"):
        simulate_paper(profile, "paper-z", out, on_start=lambda *a: started.append(a))
    with pytest.raises(SimulateError, match="--size must be one of"):
        simulate_paper(profile, "paper-a", out, size="huge")
    assert started == [] and list(out.iterdir()) == []


def test_simulate_rgbd_tree_reports_each_scene_and_keeps_what_is_rendered(tmp_path: Path) -> None:
    from mca.capture.simulate_app import SimulateError, TreeOptions, simulate_rgbd_tree
    from mca.devices.profiles import load_profile

    _two_plane_source(tmp_path / "tree" / "Planes")
    (tmp_path / "tree" / "Planes" / "SOURCE.txt").write_text("Disparity scale factor: 1\n")
    profile = load_profile("paper-70d")
    heard = []
    options = TreeOptions(seeds=(3,), width_px=0)
    summary = simulate_rgbd_tree(profile, tmp_path / "tree", tmp_path / "out", options, lambda p, o: heard.append(o))
    assert summary.counts == {"rendered": 1, "cached": 0, "failed": 0} and summary.failures == []
    assert [(o.name, o.status) for o in heard] == [("Planes-s3", "rendered")]
    assert (tmp_path / "out" / "truth" / "Planes-s3.distance.tiff").is_file()
    again = simulate_rgbd_tree(profile, tmp_path / "tree", tmp_path / "out", options)
    assert again.counts["cached"] == 1 and again.counts["rendered"] == 0
    with pytest.raises(SimulateError, match=r"no scene folder with im\.png and disp\.png"):
        simulate_rgbd_tree(profile, tmp_path / "out", tmp_path / "elsewhere")


# --- evaluate -------------------------------------------------------------------------------------------------------


def test_evaluate_rgbd_folder_scores_a_tiny_render(tmp_path: Path) -> None:
    from mca.capture.evaluation_app import evaluate_rgbd_folder, format_rgbd, rgbd_document
    from mca.capture.simulate_app import TreeOptions, simulate_rgbd_tree
    from mca.devices.profiles import load_profile

    _two_plane_source(tmp_path / "tree" / "Planes")
    (tmp_path / "tree" / "Planes" / "SOURCE.txt").write_text("Disparity scale factor: 1\n")
    simulate_rgbd_tree(
        load_profile("paper-70d"), tmp_path / "tree", tmp_path / "renders", TreeOptions(seeds=(1,), width_px=0)
    )
    notes, rows = [], []
    run = evaluate_rgbd_folder(tmp_path / "renders", peers=False, on_progress=notes.append, on_row=rows.append)
    assert run.methods == ["ours", "ours-raw"] and [r.name for r in run.rows] == ["Planes-s1"] and rows == run.rows
    figures = run.rows[0].metrics["ours"]
    assert 0.0 <= figures.bad_1 <= figures.bad_05 <= 1.0 and 0.0 < figures.coverage <= 1.0
    document = rgbd_document(run)
    assert document["renders"][0]["metrics"]["ours"]["bad_1"] == pytest.approx(figures.bad_1)
    assert "Planes-s1" in format_rgbd(run)
    json.dumps(document, allow_nan=False)  # JSON-safe


def test_evaluate_errors_name_what_is_wrong(tmp_path: Path) -> None:
    from mca.capture.evaluation_app import EvaluateError, evaluate_rgbd_folder, evaluate_table2

    with pytest.raises(EvaluateError, match="no rendered scene"):
        evaluate_rgbd_folder(tmp_path)
    with pytest.raises(EvaluateError, match="unknown scene 'paper-q'"):
        evaluate_table2(scene="paper-q", scale=0.1)
    with pytest.raises(EvaluateError, match="neither a built-in profile"):
        evaluate_table2("nope")


# --- review ---------------------------------------------------------------------------------------------------------


def test_review_rows_notes_and_document_from_result_folders(tmp_path: Path) -> None:
    from mca.capture.review import format_table, review_document, review_notes, review_rows

    (tmp_path / "IMG_1").mkdir()
    result = {
        "status": "done",
        "capture": {"capture_time": "2026-01-02T03:04:05"},
        "regions": [{"distance_mm": 812.4}, {"distance_mm": 1520.0}, {"distance_mm": float("nan")}],
    }
    (tmp_path / "IMG_1" / "result.json").write_text(json.dumps(result))
    (tmp_path / "IMG_1" / "recording.rrd").write_bytes(b"rrd")
    (tmp_path / "IMG_2").mkdir()
    (tmp_path / "IMG_2" / "depth.tiff").write_bytes(b"partial")
    (tmp_path / "IMG_3").mkdir()
    (tmp_path / "IMG_3" / "result.json").write_text("[1, 2")
    rows = review_rows(tmp_path)
    by_shot = {r.shot: r for r in rows}
    assert by_shot["IMG_1"].regions == 3 and by_shot["IMG_1"].time == "2026-01-02 03:04:05"
    assert (by_shot["IMG_1"].nearest_mm, by_shot["IMG_1"].farthest_mm) == (812.4, 1520.0)
    assert by_shot["IMG_1"].recordings == ["IMG_1/recording.rrd"]
    assert by_shot["IMG_2"].status == "unfinished" and by_shot["IMG_3"].status == "unreadable"
    notes = review_notes(rows)
    assert any(n.startswith("IMG_3: ") and "result.json" in n for n in notes)
    assert notes[-1] == "open a recording with: mca view DIR/<recording>.rrd"
    assert [d["shot"] for d in review_document(rows)] == ["IMG_1", "IMG_2", "IMG_3"]
    table = format_table(rows)
    assert "812 mm" in table and "1520 mm" in table


# --- config, profiles, optics ---------------------------------------------------------------------------------------


def test_set_config_values_rejects_a_bad_key_naming_it_and_writes_nothing(tmp_path: Path) -> None:
    from mca.capture.config import ConfigError, set_config_values

    path = tmp_path / "config.toml"
    with pytest.raises(ConfigError) as info:
        set_config_values(path, ["camera=sim", "colour=blue"])
    assert info.value.key == "colour" and str(path) in str(info.value)
    with pytest.raises(ConfigError, match="'workers': must be a whole number"):
        set_config_values(path, ["workers=two"])
    with pytest.raises(ConfigError, match="is not KEY=VALUE"):
        set_config_values(path, ["camera"])
    assert not path.exists()  # all of them or none


def test_set_config_values_writes_what_the_loader_reads_back(tmp_path: Path) -> None:
    from mca.capture.config import config_document, config_lines, load_config, set_config_values, settable_config_path

    path = tmp_path / "config.toml"
    written = set_config_values(path, ["camera=sim", "workers=3", "output_dir=results"])
    assert written["workers"] == 3 and Path(str(written["output_dir"])).is_absolute()
    set_config_values(path, ["rail=sim"])  # keeps the earlier keys
    config = load_config(env={"MCA_CONFIG": str(path)})
    assert (config.camera, config.workers, config.rail) == ("sim", 3, "sim")
    assert config.output_dir == Path(str(written["output_dir"]))
    document = config_document(config)
    assert document["values"]["workers"] == 3 and document["sources"]["camera"] == str(path)
    assert document["sources"]["profile"] == "default"
    assert any(line.startswith("workers = 3") and line.endswith(f"# {path}") for line in config_lines(config))
    assert settable_config_path(env={"MCA_CONFIG": str(path)}) == path
    assert settable_config_path(system=True, env={"MCA_CONFIG": str(path)}) == Path("/etc/mca/config.toml")
    assert settable_config_path(env={"XDG_CONFIG_HOME": str(tmp_path)}) == tmp_path / "mca" / "config.toml"


def test_convert_optics_round_trips_through_every_quantity() -> None:
    from mca.capture.profile_app import convert_optics
    from mca.devices.profiles import load_profile
    from mca.processing.optics import MCAOptics

    from_disparity = convert_optics("paper-70d", disparity_px=8.0)
    back = convert_optics("paper-70d", distance_mm=from_disparity["distance_mm"])
    assert back["disparity_px"] == pytest.approx(8.0, abs=1e-3)
    via_image = convert_optics("paper-70d", inter_image_depth_mm=from_disparity["inter_image_depth_mm"])
    assert via_image["distance_mm"] == pytest.approx(from_disparity["distance_mm"], rel=1e-6)
    optics = MCAOptics.from_profile(load_profile("paper-70d"))
    focus = convert_optics("paper-70d", distance_mm=optics.focus_distance_mm)
    assert focus["disparity_px"] == pytest.approx(0.0, abs=1e-6)  # the focus plane has no disparity (eq. 2)
    with pytest.raises(ValueError, match="give exactly one of"):
        convert_optics("paper-70d", disparity_px=1.0, distance_mm=900.0)
    with pytest.raises(ValueError, match="--distance-mm must exceed the focal length"):
        convert_optics("paper-70d", distance_mm=1.0)


def test_profiles_are_described_and_resolved() -> None:
    from mca.capture.profile_app import describe_profile, profile_list_lines, resolve_profile
    from mca.devices.profiles import builtin_names, load_profile

    profile = load_profile("paper-70d")
    text = describe_profile("paper-70d")
    assert f"{profile.aperture.baseline_mm:.3f} mm between the" in text and "(eq. 8)" in text
    assert [line.split()[0] for line in profile_list_lines()] == builtin_names()
    none = resolve_profile("none")
    assert none.lens is None and none.aperture == profile.aperture and none.name == "none"
    assert resolve_profile(None).name == "paper-70d"


# --- process --------------------------------------------------------------------------------------------------------


def test_process_settings_check_every_option_before_anything_runs(tmp_path: Path, monkeypatch) -> None:
    from mca.capture.batch import BatchError, process_settings

    monkeypatch.setenv("MCA_CONFIG", str(tmp_path / "config.toml"))
    (tmp_path / "config.toml").write_text(f'workers = 2\noutput_dir = "{tmp_path / "out"}"\n')
    photo = tmp_path / "a.png"
    photo.write_bytes(b"x")
    settings = process_settings([photo], profile="none", max_megapixels=5)
    assert (settings.workers, settings.out, settings.max_megapixels) == (2, tmp_path / "out", 5.0)
    assert settings.profile.lens is None
    with pytest.raises(BatchError, match=r"no such file or folder: .*missing\.png"):
        process_settings([tmp_path / "missing.png"])
    with pytest.raises(BatchError, match="--quality: quality must be one of full, preview"):
        process_settings([photo], quality="best")
    with pytest.raises(BatchError, match=r"give a \.rrd file name"):
        process_settings([photo], record=tmp_path / "x.txt")
    with pytest.raises(BatchError, match="--serve streams from this process"):
        process_settings([photo], serve=True)  # the config's 2 workers
    with pytest.raises(BatchError, match=f"--out {photo} is a file"):
        process_settings([photo], out=photo)


def test_report_document_lists_outcomes_in_input_order(tmp_path: Path) -> None:
    from mca.capture.batch import BatchReport, report_document
    from mca.capture.pipeline_app import FileOutcome

    report = BatchReport(
        outcomes=[
            FileOutcome(tmp_path / "b.png", "failed", tmp_path / "out" / "b", 0.5, reason="bad"),
            FileOutcome(tmp_path / "a.png", "done", tmp_path / "out" / "a", 1.23456, regions=4),
        ]
    )
    document = report_document(report)
    assert [f["input"] for f in document["files"]] == [str(tmp_path / "a.png"), str(tmp_path / "b.png")]
    assert document["files"][0]["result"] == str(tmp_path / "out" / "a" / "result.json")
    assert document["files"][0]["seconds"] == 1.235 and document["files"][1]["result"] is None
    assert document["totals"] == {"done": 1, "skipped": 0, "failed": 1}


# --- view -----------------------------------------------------------------------------------------------------------


def test_plan_viewer_checks_recordings_and_display(tmp_path: Path) -> None:
    from mca.capture.viewer import ViewerError, plan_viewer

    with pytest.raises(ViewerError, match="no such recording") as missing:
        plan_viewer([tmp_path / "none.rrd"])
    assert missing.value.exit_code == 2
    recording = tmp_path / "a.rrd"
    recording.write_bytes(b"rrd")
    with pytest.raises(ViewerError, match="No display here") as headless:
        plan_viewer([recording], environ={})
    assert headless.value.exit_code == 1 and "mca view" in str(headless.value)


# --- camera and capture ---------------------------------------------------------------------------------------------


def test_camera_app_opens_the_simulated_body_and_reads_and_sets_properties(fast_frames) -> None:
    from mca.capture.camera_app import (
        CameraSetupError,
        camera_info,
        camera_properties,
        choose_camera,
        info_lines,
        open_chosen,
        set_camera_property,
    )

    with pytest.raises(CameraSetupError) as bad:
        choose_camera("bogus")
    assert bad.value.exit_code == 2 and "unknown camera 'bogus'" in str(bad.value)
    cam = open_chosen(choose_camera("sim"))
    try:
        info = camera_info(cam)
        assert info["model"].endswith("EOS 70D") and info["serial_number"]
        assert info_lines(info)[1] == f"model:        {info['manufacturer']} {info['model']}"
        iso = camera_properties(cam, "iso")["iso"]
        other = next(v for v in iso["allowed"] if v != iso["value"])
        assert set_camera_property(cam, "iso", other)["iso"]["value"] == other
        assert camera_properties(cam, "iso")["iso"]["value"] == other
        with pytest.raises(CameraSetupError, match="colourfulness"):
            camera_properties(cam, "colourfulness")
    finally:
        cam.close()


def test_a_capture_run_lands_its_shots_and_documents_them(tmp_path: Path, fast_frames) -> None:
    from mca.capture.camera_app import choose_camera
    from mca.capture.tether import TetherSession
    from mca.capture.tether_run import CaptureOptions, capture_document, run_capture, run_summary, shot_line

    landed = []
    session = TetherSession(choose_camera("sim").factory, tmp_path, on_result=landed.append)
    try:
        outcome = run_capture(session, None, CaptureOptions(count=2))
        summary = run_summary(session, outcome.interrupted)
        document = capture_document(session, outcome.interrupted)
    finally:
        session.close()
    assert outcome.error is None and not outcome.interrupted
    assert summary.problems == 0 and summary.footer == f"2 of 2 file(s) on disk in {tmp_path}"
    assert [s["status"] for s in document["shots"]] == ["downloaded", "downloaded"] and document["on_disk"] == 2
    for shot in document["shots"]:
        path = Path(shot["file"])
        assert path.is_file() and path.stat().st_size == shot["size_bytes"]
        import hashlib

        assert hashlib.sha256(path.read_bytes()).hexdigest() == shot["sha256"]
    lines = [shot_line(r) for r in landed if r.shot_id is not None]
    assert len(lines) == 2 and all(Path(s["file"]).name in line for s, line in zip(document["shots"], lines))


def test_prepare_capture_names_the_bad_option(tmp_path: Path) -> None:
    from mca.capture.tether_run import CaptureSetupError, prepare_capture

    with pytest.raises(CaptureSetupError, match="--quality"):
        prepare_capture("sim", "paper-70d", quality="fast")
    with pytest.raises(CaptureSetupError, match="unknown camera 'bogus'"):
        prepare_capture("bogus", "paper-70d")
    with pytest.raises(CaptureSetupError, match="no-such-hook"):
        prepare_capture("sim", "paper-70d", hook_script=tmp_path / "no-such-hook")
    setup = prepare_capture("sim", "paper-70d", filename="bench-%04n.%C")
    assert setup.profile == "paper-70d" and setup.pattern is not None and setup.camera.spec == "sim"


def test_result_summary_lists_regions_near_to_far(tmp_path: Path) -> None:
    from mca.capture.tether_run import result_summary

    result = {
        "regions": [
            {"id": 2, "order": 1, "disparity_px": 3.5, "distance_mm": 1400.0, "inter_object_depth_mm": 400.0},
            {"id": 1, "order": 0, "disparity_px": 0.0, "distance_mm": 1000.0, "inter_object_depth_mm": 0.0},
        ],
        "focus_region": 1,
        "timings_s": {"read": 0.5, "pipeline": 2.0, "write": 0.25, "total": 2.0},
    }
    (tmp_path / "result.json").write_text(json.dumps(result))
    lines = result_summary(tmp_path)
    assert lines[0].startswith("    region  1 order 0") and "in focus" in lines[0]
    assert "1400.0 mm from the lens" in lines[1]
    assert lines[-1] == "    processed in 2.75 s"  # read + pipeline + write, the pipeline's total not twice
    assert result_summary(tmp_path / "none") == [f"    no result.json in {tmp_path / 'none'}"]


# --- calibration ----------------------------------------------------------------------------------------------------


def test_plan_calibration_checks_the_sweep_and_pairs_the_simulated_camera_with_the_simulated_rail(
    tmp_path: Path,
) -> None:
    from mca.capture.calibration import CalibrationRequest, CalibrationUsageError, plan_calibration

    with pytest.raises(CalibrationUsageError, match="step"):
        plan_calibration(CalibrationRequest(out=tmp_path / "c.toml", camera="sim", rail="sim", step_mm=0))
    with pytest.raises(CalibrationUsageError, match=r"sim-deviation|BASELINE"):
        plan_calibration(CalibrationRequest(out=tmp_path / "c.toml", camera="sim", rail="sim", sim_deviation="x"))
    setup = plan_calibration(CalibrationRequest(out=tmp_path / "c.toml", camera="sim", rail="sim", step_mm=50))
    assert setup.directory == tmp_path / "c-sweep" and setup.bench is not None
    assert setup.plan.positions_mm[0] == -100.0 and len(setup.plan.positions_mm) == 6
    assert math.isclose(setup.plan.target_distance_at_zero_mm, setup.nominal.focus_distance_mm - 100.0)
    with pytest.raises(CalibrationUsageError, match="use --rail sim with it"):  # before any rail is opened
        plan_calibration(CalibrationRequest(out=tmp_path / "c.toml", camera="sim", rail="/dev/ttyUSB7"))
    assert not (tmp_path / "c.toml").exists() and not setup.directory.exists()
