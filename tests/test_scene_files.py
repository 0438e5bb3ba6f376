"""The files of one capture agree and describe themselves, checked with independent readers and validators.

PLY and GLB opened together in trimesh align; the recording's point cloud is scene.ply's; result.json's
intrinsics project the points back onto their pixels; depth.tiff, the PNGs, scene.glb and the .rrd pass
tiffinfo, pngcheck, pygltflib and the Khronos glTF validator, and `rerun rrd verify`.
"""

from __future__ import annotations

import json
import subprocess

import cv2
import numpy as np
import pytest
import tifffile
import trimesh
from sim_capture import make_capture
from tools import gltf_validator, require

import mca
from mca.capture import outputs


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory):
    return make_capture(tmp_path_factory.mktemp("scene"))


def _ray_triangle_distances(directions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Distance along unit rays from the origin to each triangle (Moller-Trumbore), NaN where a ray misses it."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = b - a, c - a
    p = np.cross(directions[:, None, :], e2[None])
    det = np.einsum("rtk,tk->rt", p, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = -a[None]  # origin - a
        u = np.einsum("rtk,rtk->rt", np.broadcast_to(s, p.shape), p) * inv
        q = np.cross(np.broadcast_to(s, p.shape), e1[None])
        v = np.einsum("rk,rtk->rt", directions, q) * inv
        t = np.einsum("tk,rtk->rt", e2, q) * inv
    inside = (np.abs(det) > 1e-12) & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > 0)
    return np.where(inside, t, np.nan)


@pytest.fixture(scope="module")
def document(capture) -> dict:
    return json.loads((capture.out_dir / "result.json").read_text())


def test_ply_and_glb_align_in_trimesh(capture) -> None:
    cloud = trimesh.load(capture.out_dir / "scene.ply")
    scene = trimesh.load(capture.out_dir / "scene.glb")
    assert isinstance(cloud, trimesh.PointCloud) and isinstance(scene, trimesh.Scene)
    points = np.asarray(cloud.vertices)
    assert np.all(points[:, 2] < 0)  # in front of the camera, which looks down -z
    quads = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    rng = np.random.default_rng(0)
    sample = points[rng.choice(len(points), size=min(1500, len(points)), replace=False)]
    directions = sample / np.linalg.norm(sample, axis=1, keepdims=True)
    distance = np.linalg.norm(sample, axis=1)
    hit_distances = _ray_triangle_distances(directions, np.asarray(quads.triangles))  # (rays, triangles)
    # each point lies on (within the relief of its region, the dense depth about the region's plane) one of the
    # quads the ray through it meets: same surface, same units, same axes
    found = (np.abs(hit_distances - distance[:, None]) < 1e-2 * distance[:, None]).any(axis=1)
    assert found.mean() > 0.95, f"{(~found).sum()} of {len(sample)} PLY points on no GLB quad"
    # the two files' extents agree too (metres, about a metre away): the farthest fronto-parallel quad is the
    # farthest surface; a slanted quad spans its region's bounding box, whose corners can lie beyond the region.
    # The farthest points are taken as their 0.1 % quantile: the dense depth's relief about a region's plane puts
    # single pixels a few centimetres beyond it (paper-g's wall: its plane at 1.514 m, one pixel at 1.564 m, the
    # 0.1 % quantile at 1.516 m, under the lowest declared versions)
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(capture.out_dir / "scene.glb"))
    flat = [
        gltf.accessors[gltf.meshes[n.mesh].primitives[0].attributes.POSITION]
        for n in gltf.nodes
        if n.mesh is not None and n.extras and not n.extras.get("slanted")
    ]
    farthest = float(np.quantile(points[:, 2], 0.001))
    assert 0.9 < -farthest < 2.0 and min(a.min[2] for a in flat) == pytest.approx(farthest, abs=0.05)
    assert max(a.max[2] for a in flat) < points[:, 2].max() + 0.05  # no fronto-parallel quad nearer than a point


def test_glb_camera_and_result_json_intrinsics_are_the_photographs(capture, document) -> None:
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(capture.out_dir / "scene.glb"))
    camera = document["camera"]
    width, height = camera["image_size_px"]
    assert camera["distortion"] is None and "pixel centres at integer" in camera["pixel_convention"]
    assert (width, height) == tuple(document["input_size_px"])
    f = camera["focal_length_px"]
    assert f == pytest.approx(document["optics"]["sensor_distance_mm"] / document["pixel_pitch_mm"])
    assert camera["K"] == [[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]]
    node = next(n for n in gltf.nodes if n.camera is not None)
    perspective = gltf.cameras[node.camera].perspective
    assert perspective.yfov == pytest.approx(2 * np.arctan(height / 2 / f))
    assert perspective.aspectRatio == pytest.approx(width / height)
    assert node.matrix is None and node.translation is None and node.rotation is None  # at the origin, looking -z
    # K projects scene.ply's points back onto pixels whose region has that distance
    vertices, _ = outputs.read_ply(capture.out_dir / "scene.ply")
    points = np.stack([vertices["x"], -vertices["y"], -vertices["z"]], axis=1).astype(float) * 1000  # optical, mm
    uvw = points @ np.array(camera["K"]).T
    u, v = np.round(uvw[:, 0] / uvw[:, 2]).astype(int), np.round(uvw[:, 1] / uvw[:, 2]).astype(int)
    labels = cv2.imread(str(capture.out_dir / "regions.png"), cv2.IMREAD_UNCHANGED)
    distance = {r["id"]: r["distance_mm"] for r in document["regions"]}
    slanted = {r["id"] for r in document["regions"] if r["slant"]}
    region = labels[v, u]
    flat = ~np.isin(region, list(slanted))
    # within the relief of a fronto-parallel region about its distance: the dense depth varies inside a region,
    # at this 0.15 scale by a few tenths of a per cent (the wall 1511-1523 mm about 1517 mm, 5th-95th
    # percentile), while a point projected onto the wrong region would be off by the regions' separation (2 %+)
    relief = np.abs(points[flat, 2] / np.array([distance[i] for i in region[flat]]) - 1)
    assert np.median(relief) < 5e-3 and np.mean(relief < 1e-2) > 0.95
    # and exactly the depth map's value at the pixel it projects to
    depth = tifffile.imread(capture.out_dir / "depth.tiff")
    if depth.shape == labels.shape:
        assert np.allclose(points[:, 2], depth[v, u], rtol=1e-4)


def test_the_recording_holds_scene_plys_points(capture) -> None:
    from test_recording import read_columns, rrd_verify

    assert rrd_verify(capture.recording).returncode == 0
    columns = read_columns(capture.recording)
    recorded = np.array(columns["/world/points"]["Points3D:positions"][0], np.float32)
    vertices, _ = outputs.read_ply(capture.out_dir / "scene.ply")
    ply = np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1)
    assert len(ply) <= 200_000  # under both limits: the same stride, the same points
    np.testing.assert_array_equal(recorded, ply)


def test_depth_tiff_describes_itself_to_tiffinfo(capture) -> None:
    tiffinfo = require("tiffinfo", "apt-get install libtiff-tools")
    out = subprocess.run([tiffinfo, str(capture.out_dir / "depth.tiff")], capture_output=True, text=True, check=True)
    description = json.loads(out.stdout.split("ImageDescription: ", 1)[1].split("\n  ", 1)[0])
    assert description["unit"] == "mm" and description["nodata"] == "NaN" and "distance" in description["meaning"]
    assert description["software"] == f"mca-appliance {mca.__version__}" and description["profile"] == "paper-70d"
    assert description["camera"]["K"] and description["optics"]["sensor_distance_mm"] > 0
    assert f"Software: mca-appliance {mca.__version__}" in out.stdout
    assert "GDAL NoDataValue: nan" in out.stdout and 'role="unittype">mm<' in out.stdout
    assert "Sample Format: IEEE floating point" in out.stdout


def test_pngs_pass_pngcheck_with_srgb_and_text_chunks(capture) -> None:
    pngcheck = require("pngcheck", "apt-get install pngcheck")
    images = [capture.out_dir / "all_in_focus.png", capture.out_dir / "regions.png"]
    images += sorted((capture.out_dir / "layers").glob("*.png"))
    for path in images:
        out = subprocess.run([pngcheck, "-vt", str(path)], capture_output=True, text=True)
        assert out.returncode == 0 and "No errors detected" in out.stdout, out.stdout
        chunks = outputs.read_png_text(path.read_bytes())
        assert chunks["Software"] == f"mca-appliance {mca.__version__}" and chunks["Description"]
        assert ("chunk:sRGB" in chunks) == (path.name != "regions.png"), path  # labels are numbers, not colours


def test_every_png_names_the_photograph_it_came_from(capture) -> None:
    """The region map, the all-in-focus image and every layer carry the input's path in their Source text chunk (an
    edit of the layer writer at the twenty-eighth stop shadowed that path with the layer's own pixel source, and no
    test saw it)."""
    from pathlib import Path

    images = [capture.out_dir / "all_in_focus.png", capture.out_dir / "regions.png"]
    images += sorted((capture.out_dir / "layers").glob("*.png"))
    assert len(images) > 2
    for path in images:
        source = outputs.read_png_text(path.read_bytes())["Source"]
        assert Path(source).resolve() == capture.cr2.resolve(), (path.name, source[:80])


def test_layer_alpha_is_anti_aliased(capture) -> None:
    layer = cv2.imread(str(capture.out_dir / "layers" / "00.png"), cv2.IMREAD_UNCHANGED)
    alpha = layer[..., 3]
    partial = (alpha > 0) & (alpha < 255)
    assert partial.any() and (alpha == 255).any() and (alpha == 0).any()
    opaque = alpha == 255
    edge = cv2.dilate(opaque.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~opaque
    assert partial[edge].mean() > 0.95  # the pixels around the region fade out rather than cut off


def test_result_json_and_glb_name_their_schema_and_software(capture, document) -> None:
    import pygltflib

    assert document["schema_version"] >= 2 and document["software"] == f"mca-appliance {mca.__version__}"
    assert "y up" in document["units"]["scene"]
    gltf = pygltflib.GLTF2().load(str(capture.out_dir / "scene.glb"))
    assert gltf.asset.generator == f"mca-appliance {mca.__version__}" and gltf.asset.version == "2.0"


def test_khronos_gltf_validator_finds_no_error(capture) -> None:
    node, package = gltf_validator()
    script = (
        "const v = require(process.argv[1]); const fs = require('fs');"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])))"
        ".then(r => { console.log(JSON.stringify(r.issues)); })"
        ".catch(e => { console.error(e); process.exit(2); });"
    )
    out = subprocess.run(
        [node, "-e", script, str(package), str(capture.out_dir / "scene.glb")], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    issues = json.loads(out.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


def test_the_catalog_names_the_software_that_wrote_it(tmp_path) -> None:
    import sqlite3

    from mca.capture.catalog import Catalog

    Catalog(tmp_path / "catalog.sqlite").close()
    with sqlite3.connect(tmp_path / "catalog.sqlite") as db:
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        assert db.execute("SELECT version FROM software WHERE name = 'mca-appliance'").fetchone() == (mca.__version__,)
