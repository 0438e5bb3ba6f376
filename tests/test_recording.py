"""Rerun recordings read back with rerun's own tooling: every stage present with the right archetype and shape.

Recordings are checked with `rerun rrd verify`, `rerun rrd print` (entity -> archetypes) and the
SDK's reader `rerun.chunk.RrdReader` (image sizes, values); inputs are a small CR2 written by
`devices.sim.cr2.write_cr2` and a small PNG, both read by the real `capture.raw.read_raw`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr

from mca.capture.recording import (
    RerunRecorder,
    child_environment,
    disable_rerun_analytics,
    display_size,
    merge_recordings,
    plane_mesh,
    quiet_rerun_environment,
    rerun_analytics_config_path,
    rerun_analytics_disabled,
    rerun_executable,
)
from mca.devices.profiles import load_profile
from mca.processing.optics import MCAOptics
from mca.processing.result import DepthResult, MultiPlaneImage, Region

RERUN = rerun_executable()
pytestmark = pytest.mark.skipif(
    RERUN is None and not os.environ.get("CI"), reason="the rerun CLI of rerun-sdk is not installed"
)

PROFILE = load_profile("paper-70d")

# what the done-when asks `rerun rrd print` to list, with the archetype each must carry
EXPECTED = {
    "/shot/input": "EncodedImage",
    "/shot/raw/red": "EncodedImage",
    "/shot/raw/green": "EncodedImage",
    "/shot/raw/blue": "EncodedImage",
    "/shot/channels/before": "EncodedImage",
    "/shot/channels/after": "EncodedImage",
    "/shot/disparity/region_model": "Image",
    "/shot/disparity/per_pixel": "Image",
    "/shot/disparity/confidence": "Image",
    "/shot/segmentation": "SegmentationImage",
    "/shot/occlusion_order": "TextDocument",
    "/shot/occlusion_graph": "GraphNodes",
    "/shot/depth": "DepthImage",
    "/shot/multi_plane/00": "Image",
    "/shot/multi_plane/02": "Image",
    "/shot/profile": "TextDocument",
    "/world": "ViewCoordinates",
    "/world/camera": "Pinhole",
    "/world/camera/image": "EncodedImage",
    "/world/points": "Points3D",
    "/world/planes/00": "Mesh3D",
    "/timings/disparity": "Scalars",
    "/timings/sketch": "Scalars",
}


def synthetic_result(height: int, width: int, optics: MCAOptics | None, pixel_scale: float = 1.0) -> DepthResult:
    """Three regions: left half at -5 px, right half at +8 px, a box in front at +2 px... built by hand."""
    labels = np.zeros((height, width), np.uint16)
    labels[:, : width // 2] = 1
    labels[:, width // 2 :] = 2
    labels[height // 4 : height // 2, width // 4 : width // 2] = 3
    disparity = {1: -5.0, 2: 8.0, 3: -9.0}
    order = {3: 0, 1: 1, 2: 2}
    occludes = {3: [1], 1: [2], 2: []}
    disparity_px = np.zeros((height, width), np.float32)
    for region_id, value in disparity.items():
        disparity_px[labels == region_id] = value
    depth = None if optics is None else optics.distance_mm(disparity_px).astype(np.float32)
    rng = np.random.default_rng(3)
    colour = rng.random((height, width, 3), dtype=np.float32)
    regions = []
    for region_id in (1, 2, 3):
        distance = None if optics is None else float(optics.distance_mm(disparity[region_id]))
        regions.append(
            Region(
                id=region_id,
                pixels=int((labels == region_id).sum()),
                order=order[region_id],
                occludes=occludes[region_id],
                disparity_px=disparity[region_id],
                distance_mm=distance,
                confidence=0.9,
            )
        )
    layers = [
        MultiPlaneImage(
            region_id=r.id,
            rgba=np.dstack([colour, (labels == r.id).astype(np.float32)]),
            inter_image_depth_mm=None,
            inter_object_depth_mm=None,
            disparity_px=r.disparity_px,
        )
        for r in sorted(regions, key=lambda r: r.order)
    ]
    return DepthResult(
        labels=labels,
        disparity_px=disparity_px,
        raw_disparity_px=disparity_px + 0.25,
        confidence=np.full((height, width), 0.75, np.float32),
        depth_mm=depth,
        all_in_focus=colour,
        regions=regions,
        focus_region=None,
        layers=layers,
        pixel_scale=pixel_scale,
        timings_s={"disparity": 0.5, "sketch": 0.25},
    )


def make_cr2(path: Path, height: int = 96, width: int = 144) -> Path:
    from mca.capture.simulated_shots import write_cr2
    from mca.devices.sim.cr2 import Cr2Metadata

    rng = np.random.default_rng(1)
    mosaic = (2048 + rng.random((height, width)) * 10000).astype(np.uint16)
    meta = Cr2Metadata(capture_time=datetime(2024, 5, 6, 7, 8, 9))
    return write_cr2(path, mosaic, metadata=meta, preview=False)


def make_png(path: Path, height: int = 90, width: int = 120) -> Path:
    rng = np.random.default_rng(2)
    image = (rng.random((height, width, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(path), image)
    return path


def rrd_print(path: Path) -> dict[str, set[str]]:
    """Entity path -> archetype names, parsed from `rerun rrd print` (one line per chunk)."""
    proc = subprocess.run(
        [RERUN, "rrd", "print", str(path)], capture_output=True, text=True, check=True, env=child_environment()
    )
    entities: dict[str, set[str]] = {}
    for match in re.finditer(r"- (/\S*) - data columns: \[([^\]]*)\]", proc.stdout):
        names = {column.split(":")[0] for column in match.group(2).split()}
        entities.setdefault(match.group(1), set()).update(names)
    return entities


def rrd_verify(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([RERUN, "rrd", "verify", str(path)], capture_output=True, text=True, env=child_environment())


def read_columns(path: Path) -> dict[str, dict[str, list]]:
    """Entity path -> column name -> values (all rows), read with the SDK's own RRD reader."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    table: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = table.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            column = batch.column(name)
            if pa.types.is_timestamp(column.type) or pa.types.is_duration(column.type):
                column = column.cast(pa.int64())  # nanoseconds
            columns.setdefault(name, []).extend(column.to_pylist())
    return table


def one(columns: dict[str, dict[str, list]], entity: str, column: str):
    """The single instance of a component in the first row of `entity`."""
    row = columns[entity][column][0]
    assert isinstance(row, list) and len(row) == 1, (entity, column, row)
    return row[0]


def record_shot(path: Path, input_path: Path) -> tuple[DepthResult, object]:
    from mca.capture.raw import read_raw

    frame = read_raw(input_path)
    scale = 2.0 if frame.half_resolution else 1.0
    pitch = frame.pixel_pitch_mm / scale if frame.pixel_pitch_mm else PROFILE.pixel_pitch_mm
    optics = MCAOptics.from_profile(PROFILE, pixel_pitch_mm=pitch)
    h, w = frame.planes.shape[:2]
    result = synthetic_result(h, w, optics, pixel_scale=scale)
    with RerunRecorder(path) as recorder:
        recorder.begin_shot(0, input_path.stem, frame.metadata.capture_time, PROFILE)
        recorder.log_input(frame)
        recorder.record("disparity", cost_min=np.ones((h, w), np.float32), candidates=17, converged=True)
        recorder.timing("disparity", 0.5)
        recorder.log_result(result, PROFILE, optics)
    return result, frame


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, DepthResult, object]]:
    folder = tmp_path_factory.mktemp("recordings")
    out = {}
    for kind, source in (("cr2", make_cr2(folder / "paper-c.CR2")), ("png", make_png(folder / "scene.png"))):
        path = folder / f"{kind}.rrd"
        result, frame = record_shot(path, source)
        out[kind] = (path, result, frame)
    return out


@pytest.mark.parametrize("kind", ["cr2", "png"])
def test_recording_verifies_and_lists_every_stage(recordings, kind: str) -> None:
    path = recordings[kind][0]
    verify = rrd_verify(path)
    assert verify.returncode == 0, verify.stderr
    entities = rrd_print(path)
    for entity, archetype in EXPECTED.items():
        assert archetype in entities.get(entity, set()), f"{entity}: expected {archetype}, got {entities.get(entity)}"
    assert "AnnotationContext" in entities["/shot/segmentation"]
    assert "GraphEdges" in entities["/shot/occlusion_graph"]
    assert "Image" in entities["/shot/stages/disparity/cost_min"]
    assert "Scalars" in entities["/shot/stages/disparity/candidates"]
    # the words the done-when looks for in `rerun rrd print`
    listing = " ".join(f"{e} {' '.join(a)}" for e, a in entities.items())
    for word in (
        "raw",
        "channels",
        "disparity",
        "segmentation",
        "depth",
        "multi_plane",
        "Pinhole",
        "points",
        "Scalars",
    ):
        assert word in listing


@pytest.mark.parametrize("kind", ["cr2", "png"])
def test_images_have_the_display_size_of_the_input(recordings, kind: str) -> None:
    path, _result, frame = recordings[kind]
    scale = 2.0 if frame.half_resolution else 1.0
    h, w = frame.planes.shape[:2]
    width, height = display_size(int(w * scale), int(h * scale))
    columns = read_columns(path)
    for entity, archetype in (
        ("/shot/segmentation", "SegmentationImage"),
        ("/shot/depth", "DepthImage"),
        ("/shot/disparity/region_model", "Image"),
        ("/shot/disparity/confidence", "Image"),
    ):
        fmt = one(columns, entity, f"{archetype}:format")
        assert (fmt["width"], fmt["height"]) == (width, height), entity
    for entity in ("/shot/input", "/shot/raw/red", "/shot/channels/after"):
        blob = bytes(one(columns, entity, "EncodedImage:blob"))
        decoded = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
        assert decoded.shape[:2] == (height, width), entity
        assert one(columns, entity, "EncodedImage:media_type") == "image/jpeg"
    labels = np.frombuffer(bytes(one(columns, "/shot/segmentation", "SegmentationImage:buffer")), np.uint16)
    assert set(np.unique(labels)) == {1, 2, 3}
    assert len(columns["/shot/multi_plane/00"]["Image:format"]) == 1
    assert "/shot/multi_plane/03" not in columns


def test_multi_plane_images_are_cropped_and_put_in_place(recordings) -> None:
    path, result, _frame = recordings["png"]  # 90 x 120 planes: the multi-plane frame is the processing grid
    columns = read_columns(path)
    h, w = result.labels.shape
    nearest = one(columns, "/shot/multi_plane/00", "Image:format")  # region 3, the box in front
    x0, y0 = max(0, w // 4 - 8), max(0, h // 4 - 8)
    assert one(columns, "/shot/multi_plane/00", "Transform3D:translation") == pytest.approx([x0, y0, 0])
    assert (nearest["width"], nearest["height"]) == (w // 2 + 8 - x0, h // 2 + 8 - y0)
    rgba = np.frombuffer(bytes(one(columns, "/shot/multi_plane/00", "Image:buffer")), np.uint8)
    rgba = rgba.reshape(nearest["height"], nearest["width"], 4)
    assert rgba[..., 3].max() == 255 and rgba[..., 3].min() == 0  # the box and the margin around it


def test_depth_is_in_mm_with_meter_1000_and_matches_the_regions(recordings) -> None:
    path, result, _ = recordings["png"]
    columns = read_columns(path)
    assert one(columns, "/shot/depth", "DepthImage:meter") == pytest.approx(1000.0)
    depth = np.frombuffer(bytes(one(columns, "/shot/depth", "DepthImage:buffer")), np.float32)
    expected = sorted(r.distance_mm for r in result.regions)
    assert depth.min() == pytest.approx(expected[0], rel=1e-4)
    assert depth.max() == pytest.approx(expected[-1], rel=1e-4)
    assert 900 < expected[0] < expected[-1] < 1200  # around the 1000 mm focus plane of paper-70d


def test_pinhole_uses_d_ls_over_pitch_and_the_image_centre(recordings) -> None:
    path, _result, frame = recordings["cr2"]
    columns = read_columns(path)
    matrix = np.array(one(columns, "/world/camera", "Pinhole:image_from_camera")).reshape(3, 3).T  # column-major
    width, height = one(columns, "/world/camera", "Pinhole:resolution")
    input_width = frame.planes.shape[1] * 2
    pitch = frame.pixel_pitch_mm / 2
    focal_px = PROFILE.lens.sensor_distance_mm / pitch * width / input_width
    assert matrix[0, 0] == pytest.approx(focal_px, rel=1e-5)
    assert matrix[1, 1] == pytest.approx(focal_px, rel=1e-5)
    assert (matrix[0, 2], matrix[1, 2]) == pytest.approx((width / 2, height / 2))


def test_points_and_planes_sit_at_the_region_distances(recordings) -> None:
    path, result, _ = recordings["png"]
    columns = read_columns(path)
    points = np.array(columns["/world/points"]["Points3D:positions"][0])
    assert points.ndim == 2 and points.shape[1] == 3 and 0 < len(points) <= 200_000
    # the scene frame of scene.ply and scene.glb: metres, y up, the camera looking down -z
    assert one(columns, "/world", "ViewCoordinates:xyz") == list(rr.ViewCoordinates.RUB.as_arrow_array()[0].as_py())
    distances_m = sorted(r.distance_mm / 1000 for r in result.regions)
    assert -points[:, 2].max() == pytest.approx(distances_m[0], rel=1e-4)
    assert -points[:, 2].min() == pytest.approx(distances_m[-1], rel=1e-4)
    nearest = min(result.regions, key=lambda r: r.order)
    plane = np.array(columns["/world/planes/00"]["Mesh3D:vertex_positions"][0])
    assert np.allclose(-plane[:, 2], nearest.distance_mm / 1000, rtol=1e-5)


def test_timings_are_scalars_per_stage_and_the_order_table_lists_regions_front_to_back(recordings) -> None:
    path, _result, _ = recordings["cr2"]
    columns = read_columns(path)
    assert columns["/timings/disparity"]["Scalars:scalars"][0] == [0.5]
    assert columns["/timings/sketch"]["Scalars:scalars"][0] == [0.25]
    assert "shot" in columns["/timings/disparity"] and "capture_time" in columns["/timings/disparity"]
    table = one(columns, "/shot/occlusion_order", "TextDocument:text")
    ranks = [int(m) for m in re.findall(r"^\| (\d+) \| #", table, flags=re.M)]
    ids = [int(m) for m in re.findall(r"^\| \d+ \| #(\d+)", table, flags=re.M)]
    assert ranks == [0, 1, 2] and ids == [3, 1, 2]
    edges = columns["/shot/occlusion_graph"]["GraphEdges:edges"][0]
    assert sorted((e["first"], e["second"]) for e in edges) == [("1", "2"), ("3", "1")]
    assert "paper-70d" in one(columns, "/shot/profile", "TextDocument:text")


def test_two_recorders_coexist_and_merge(tmp_path: Path) -> None:
    optics = MCAOptics.from_profile(PROFILE)
    first, second = RerunRecorder(tmp_path / "a.rrd"), RerunRecorder(tmp_path / "b.rrd")
    for index, recorder in enumerate((first, second)):
        recorder.begin_shot(index, f"shot{index}", datetime(2024, 1, 1, 12, index), PROFILE)
    first.log_result(synthetic_result(40, 60, optics), PROFILE, optics)
    second.log_result(synthetic_result(30, 50, None), PROFILE, None)  # disparity only: no depth, no points
    first.close()
    second.close()
    a, b = read_columns(tmp_path / "a.rrd"), read_columns(tmp_path / "b.rrd")
    assert "/shot/depth" in a and "/shot/depth" not in b and "/world/points" not in b
    assert one(b, "/shot/segmentation", "SegmentationImage:format")["width"] == 50
    merged = tmp_path / "merged.rrd"
    merge_recordings([tmp_path / "a.rrd", tmp_path / "b.rrd"], merged)
    assert rrd_verify(merged).returncode == 0
    from rerun.chunk import RrdReader

    assert len(RrdReader(merged).recordings()) == 2
    with pytest.raises(FileNotFoundError):
        merge_recordings([tmp_path / "missing.rrd"], tmp_path / "x.rrd")


def test_a_merge_interrupted_half_way_leaves_no_half_written_file(tmp_path: Path, monkeypatch) -> None:
    """Ctrl-C while `rerun rrd merge` writes: its temporary output is removed, the parts and any earlier merge stay."""
    from mca.capture.recording import merge

    parts = [tmp_path / "a.rrd", tmp_path / "b.rrd"]
    for part in parts:
        part.write_bytes(b"part")
    merged = tmp_path / "merged.rrd"
    merged.write_bytes(b"an earlier merge")

    def interrupted(command, **kwargs):
        Path(command[command.index("-o") + 1]).write_bytes(b"half")  # the merge had begun writing
        raise KeyboardInterrupt

    monkeypatch.setattr(merge, "rerun_executable", lambda: "rerun")
    monkeypatch.setattr(merge.subprocess, "run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        merge.merge_recordings(parts, merged)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.rrd", "b.rrd", "merged.rrd"]
    assert merged.read_bytes() == b"an earlier merge"


def test_plane_mesh_covers_only_the_opaque_part() -> None:
    from mca.processing.pinhole import PinholeCamera

    rgba = np.zeros((40, 80, 4), np.float32)
    rgba[:20, :40] = (0.5, 0.5, 0.5, 1.0)
    camera = PinholeCamera(100.0, 81, 41)  # principal point (40, 20): pixel edges -0.5 .. 79.5
    vertices, triangles, colours = plane_mesh(
        rgba, lambda u, v: np.full(np.shape(u), 2000.0), camera, pixel_scale=1.0, cells_across=8
    )
    used = vertices[np.unique(triangles)]
    assert np.allclose(used[:, 2], -2.0)  # 2 m in front of the camera, which looks down -z
    assert used[:, 0].min() == pytest.approx(-40.5 * 2.0 / 100) and used[:, 0].max() == pytest.approx(-0.5 * 0.02)
    assert used[:, 1].max() == pytest.approx(20.5 * 2.0 / 100) and used[:, 1].min() == pytest.approx(0.5 * 0.02)
    assert len(triangles) == 2 * 2 * 4  # a quarter of the 8 x 4 cells (10 px each), two triangles each
    assert colours.shape == (len(vertices), 4)
    # a slanted surface: each vertex at its own distance, all of them on one 3D plane
    slanted, _, _ = plane_mesh(rgba, lambda u, v: 1000.0 / (1.0 - 0.001 * u), camera, pixel_scale=1.0, cells_across=8)
    centred = slanted - slanted.mean(axis=0)
    assert np.linalg.svd(centred, compute_uv=False)[-1] < 1e-5 * np.linalg.norm(centred)
    assert np.ptp(slanted[:, 2]) > 0.01


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_serve_streams_to_a_local_web_viewer_bound_to_localhost(tmp_path: Path) -> None:
    import urllib.request

    grpc_port, web_port = _free_port(), _free_port()
    recorder = RerunRecorder(tmp_path / "live.rrd", serve=True, grpc_port=grpc_port, web_port=web_port)
    try:
        assert recorder.viewer_url.startswith(f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1")
        if shutil.which("ss"):
            listening = subprocess.run(["ss", "-ltn"], capture_output=True, text=True).stdout
            assert f"127.0.0.1:{grpc_port}" in listening and f"127.0.0.1:{web_port}" in listening
            assert f"0.0.0.0:{web_port}" not in listening and f"*:{web_port}" not in listening
        recorder.begin_shot(0, "live", None, PROFILE)
        optics = MCAOptics.from_profile(PROFILE)
        recorder.log_result(synthetic_result(30, 40, optics), PROFILE, optics)
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=10) as page:
            assert page.status == 200
    finally:
        recorder.close()
    assert rrd_verify(tmp_path / "live.rrd").returncode == 0


def test_recorder_needs_a_destination() -> None:
    with pytest.raises(ValueError, match="recording path"):
        RerunRecorder(None)


def test_analytics_stay_off(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    env = {"FORCE_RERUN_ANALYTICS": "1", "HOME": str(tmp_path)}
    quiet_rerun_environment(env)
    assert "FORCE_RERUN_ANALYTICS" not in env and env["TELEMETRY_ENABLED"] == "false"
    config = rerun_analytics_config_path({"XDG_CONFIG_HOME": str(tmp_path)})
    assert config == tmp_path / "rerun" / "analytics.json"
    assert not rerun_analytics_disabled({"XDG_CONFIG_HOME": str(tmp_path)})
    config.parent.mkdir(parents=True)
    config.write_text('{"analytics_enabled": false}')
    assert rerun_analytics_disabled({"XDG_CONFIG_HOME": str(tmp_path)})
    # a child of a machine whose opt-out cannot be confirmed still stays quiet (rerun's CI switch)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "nowhere"))
    monkeypatch.setenv("FORCE_RERUN_ANALYTICS", "1")
    child = child_environment()
    assert child["CI"] == "1" and "FORCE_RERUN_ANALYTICS" not in child
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))  # opt-out confirmed: the environment is left as it is
    monkeypatch.delenv("CI", raising=False)
    assert "CI" not in child_environment()


def test_disable_rerun_analytics_writes_rerun_own_opt_out(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import mca.capture.recording.rerun_env as recording

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.setattr(recording, "_ANALYTICS_CONFIG_DONE", False)
    disable_rerun_analytics()
    assert rerun_analytics_disabled()
    written = (tmp_path / "config" / "rerun" / "analytics.json").read_text().replace(" ", "")
    assert '"analytics_enabled":false' in written


# --- through the application: process_file with --record -----------------------------------------------------------


def _fake_pipeline(planes, aperture, optics, *, pixel_scale=1.0, recorder=None, **_: object) -> DepthResult:
    h, w = planes.shape[:2]
    if recorder is not None:
        recorder.record("disparity", disparity_px=np.zeros((h, w), np.float32), confidence=np.ones((h, w), np.float32))
        recorder.timing("disparity", 0.01)
    return synthetic_result(h, w, optics, pixel_scale=pixel_scale)


@pytest.mark.parametrize("maker,name", [(make_cr2, "paper-c.CR2"), (make_png, "scene.png")])
def test_process_file_records_a_verifiable_recording(tmp_path: Path, maker, name: str) -> None:
    from mca.capture.pipeline_app import process_file

    source = maker(tmp_path / name)
    record = tmp_path / "out" / "c.rrd"
    outcome = process_file(source, tmp_path / "out", PROFILE, record_path=record, pipeline=_fake_pipeline)
    assert outcome.status == "done", outcome.reason
    assert rrd_verify(record).returncode == 0
    entities = rrd_print(record)
    for entity in (
        "/shot/raw/red",
        "/shot/channels/before",
        "/shot/disparity/region_model",
        "/shot/segmentation",
        "/shot/depth",
        "/shot/multi_plane/00",
        "/world/camera",
        "/world/points",
        "/timings/disparity",
    ):
        assert entity in entities, entity
    assert "Pinhole" in entities["/world/camera"]


@pytest.mark.slow
@pytest.mark.parametrize("maker,name,size", [(make_cr2, "paper-c.CR2", (192, 288)), (make_png, "scene.png", (96, 144))])
def test_real_pipeline_recording_verifies(tmp_path: Path, maker, name: str, size: tuple[int, int]) -> None:
    from mca.capture.pipeline_app import process_file

    source = maker(tmp_path / name, *size)  # both give 96 x 144 planes
    record = tmp_path / "out" / "c.rrd"
    outcome = process_file(source, tmp_path / "out", PROFILE, record_path=record)
    assert outcome.status == "done", outcome.reason
    timings = json.loads((outcome.output_dir / "result.json").read_text())["timings_s"]
    assert timings["kernels"] >= 0.0 and {"read", "pipeline", "write"} <= set(timings)
    assert rrd_verify(record).returncode == 0
    entities = rrd_print(record)
    for entity in (
        "/shot/raw/red",
        "/shot/channels/before",
        "/shot/channels/after",
        "/shot/disparity/region_model",
        "/shot/disparity/confidence",
        "/shot/segmentation",
        "/shot/segmentation/sketch",
        "/world/camera",
    ):
        assert entity in entities, entity
    assert any(e.startswith("/shot/stages/disparity/") for e in entities), sorted(entities)
    for stage in ("planes", "disparity", "surfaces", "sketch", "refine", "boundaries", "depth", "all_in_focus", "mpi"):
        assert "Scalars" in entities[f"/timings/{stage}"], stage
    assert "/shot/stages/planes/planes" not in entities  # shown from the frame already, not logged twice
