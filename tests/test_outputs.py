"""The output writers: PLY and GLB parsed back, TIFF/PNG/JSON round trips, atomic writes leave nothing behind."""

from __future__ import annotations

import json
import struct

import cv2
import numpy as np
import pytest
import tifffile

from mca.capture import outputs
from mca.capture.pipeline_app import Pinhole, label_pixels_input, scene_points, upsample_nearest


def _leftovers(folder):
    return [p.name for p in folder.rglob("*") if p.name.endswith(outputs.TEMP_SUFFIX)]


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    points = (rng.normal(size=(1000, 3)) * 100 + [0, 0, 1000]).astype(np.float32)
    colours = rng.integers(0, 256, size=(1000, 3), dtype=np.uint8)
    path = outputs.write_ply(tmp_path / "scene.ply", points, colours, comments=("camera frame, mm",))
    header = path.read_bytes()[:300].split(b"end_header\n")[0].decode()
    assert header.startswith("ply\nformat binary_little_endian 1.0\n")
    assert "element vertex 1000" in header and "property uchar red" in header
    vertices, comments = outputs.read_ply(path)
    assert comments == ["camera frame, mm"]
    np.testing.assert_array_equal(np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1), points)
    np.testing.assert_array_equal(np.stack([vertices["red"], vertices["green"], vertices["blue"]], axis=1), colours)
    # 3 floats + 3 bytes per vertex, nothing more
    assert path.stat().st_size == len(header) + len("end_header\n") + 1000 * 15


def test_ply_rejects_mismatched_colours(tmp_path):
    with pytest.raises(ValueError, match="3 points but 2 colours"):
        outputs.write_ply(tmp_path / "x.ply", np.zeros((3, 3)), np.zeros((2, 3)))
    assert list(tmp_path.iterdir()) == []


def _quad(name, z_mm, half_mm, colour):
    """A square facing the camera, `z_mm` in front of it, in the scene frame (metres, y up, looking down -z)."""
    texture = np.zeros((6, 8, 4), np.uint8)
    texture[..., :3] = colour
    texture[..., 3] = 255
    z, h = -z_mm / 1000, half_mm / 1000
    corners = np.array([[-h, h, z], [h, h, z], [h, -h, z], [-h, -h, z]])  # image top-left, top-right, ...
    return outputs.TexturedQuad(name, corners, outputs.encode_png(texture), extras={"distance_mm": z_mm})


def test_glb_parsed_back(tmp_path):
    quads = [_quad("near", 950.0, 40.0, (255, 0, 0)), _quad("far", 1105.5, 80.0, (0, 0, 255))]
    path = outputs.write_glb(tmp_path / "scene.glb", quads)
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    assert data[16:20] == b"JSON"
    gltf, binary = outputs.read_glb(path)
    assert gltf["asset"]["version"] == "2.0"
    assert len(binary) == gltf["buffers"][0]["byteLength"] and len(binary) % 4 == 0
    root = gltf["nodes"][gltf["scenes"][gltf["scene"]]["nodes"][0]]
    assert "matrix" not in root and "cameras" not in gltf  # positions are metres in glTF's frame as they stand
    assert [gltf["nodes"][i]["name"] for i in root["children"]] == ["near", "far"]
    for view in gltf["bufferViews"]:
        assert view["byteOffset"] % 4 == 0 and view["byteOffset"] + view["byteLength"] <= len(binary)
    for mesh_index, quad in enumerate(quads):
        primitive = gltf["meshes"][mesh_index]["primitives"][0]
        position = gltf["accessors"][primitive["attributes"]["POSITION"]]
        values = outputs.glb_accessor(gltf, binary, primitive["attributes"]["POSITION"])
        np.testing.assert_allclose(values, quad.corners_m, rtol=1e-6)
        assert position["min"] == pytest.approx(values.min(axis=0).tolist())
        assert position["max"] == pytest.approx(values.max(axis=0).tolist())
        indices = outputs.glb_accessor(gltf, binary, primitive["indices"]).ravel()
        assert indices.max() < position["count"]
        uv = outputs.glb_accessor(gltf, binary, primitive["attributes"]["TEXCOORD_0"])
        assert uv.min() == 0.0 and uv.max() == 1.0
        material = gltf["materials"][primitive["material"]]
        image_index = gltf["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]["source"]
        png = outputs.glb_image(gltf, binary, image_index)
        assert png == quad.texture_png
        decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert decoded.shape == (6, 8, 4)
    assert gltf["nodes"][2]["extras"] == {"distance_mm": 1105.5}


def test_glb_without_quads_is_valid(tmp_path):
    gltf, binary = outputs.read_glb(outputs.write_glb(tmp_path / "empty.glb", []))
    assert binary == b"" and gltf["scenes"] == [{"nodes": [0]}]


def test_glb_quad_faces_the_camera():
    # seen from the camera (at the origin, looking down -z) the triangles wind counter-clockwise
    data = outputs.encode_glb([_quad("q", 1000.0, 10.0, (1, 2, 3))])
    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20 : 20 + length])
    binary = data[20 + length + 8 :]
    corners = outputs.glb_accessor(gltf, binary, 0).astype(float)
    tri = corners[outputs.glb_accessor(gltf, binary, 2).ravel()[:3]]
    normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    assert normal[2] > 0


def test_tiff_png_json_round_trip(tmp_path):
    depth = np.array([[1000.5, np.nan], [np.inf, 2.0]], np.float32)
    outputs.write_tiff_float32(tmp_path / "depth.tiff", depth)
    back = tifffile.imread(tmp_path / "depth.tiff")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, depth)
    labels = np.array([[0, 1], [300, 65535]], np.uint16)
    outputs.write_png(tmp_path / "labels.png", labels)
    read = cv2.imread(str(tmp_path / "labels.png"), cv2.IMREAD_UNCHANGED)
    assert read.dtype == np.uint16
    np.testing.assert_array_equal(read, labels)
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[..., 3] = 128
    outputs.write_png(tmp_path / "layer.png", rgba)
    bgra = cv2.imread(str(tmp_path / "layer.png"), cv2.IMREAD_UNCHANGED)
    assert bgra[0, 0].tolist() == [0, 0, 200, 128]
    outputs.write_json(tmp_path / "r.json", {"a": float("nan"), "b": np.float32(1.5), "c": (1, 2), "d": np.arange(2)})
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": None, "b": 1.5, "c": [1, 2], "d": [0, 1]}
    assert _leftovers(tmp_path) == []


def _sparse_canvas(rng, shape, dtype, window_box, channels):
    """A canvas of zeros with content (and two all-zero rows) inside `window_box` only."""
    canvas = np.zeros(shape + ((channels,) if channels else ()), dtype)
    rows, cols = window_box
    high = 65536 if dtype == np.uint16 else 256
    canvas[rows, cols] = rng.integers(0, high, canvas[rows, cols].shape)
    canvas[rows.start] = 0  # the window's first row empty, and one inside it
    canvas[(rows.start + rows.stop) // 2] = 0
    return canvas


@pytest.mark.parametrize(
    "shape, dtype, channels, window_box",
    [
        ((1200, 500), np.uint8, 4, (slice(300, 1000), slice(120, 320))),  # three deflate segments, window in two
        ((1200, 500), np.uint8, 4, (slice(0, 1200), slice(0, 500))),  # the window is the canvas
        ((900, 300), np.uint16, 0, (slice(850, 900), slice(290, 300))),  # at the bottom right corner
        ((700, 640), np.uint8, 3, (slice(0, 5), slice(0, 640))),  # full-width rows at the top
    ],
)
def test_a_png_window_is_the_png_of_its_whole_canvas(shape, dtype, channels, window_box):
    """A layer's PNG is encoded from its region's window: the same bytes as from the whole canvas, and libpng (through
    OpenCV) decodes the canvas."""
    canvas = _sparse_canvas(np.random.default_rng(7), shape, dtype, window_box, channels)
    rows, cols = window_box
    windowed = outputs.encode_png(canvas[rows, cols], origin_px=(rows.start, cols.start), canvas_px=shape)
    assert windowed == outputs.encode_png(canvas)
    decoded = cv2.imdecode(np.frombuffer(windowed, np.uint8), cv2.IMREAD_UNCHANGED)
    if channels:
        decoded = cv2.cvtColor(decoded, cv2.COLOR_BGRA2RGBA if channels == 4 else cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(decoded, canvas)


def test_a_png_window_outside_its_canvas_is_refused():
    with pytest.raises(ValueError, match="a PNG window of 4x3 px at row 8, column 0 does not fit its canvas of 4x10"):
        outputs.encode_png(np.ones((3, 4), np.uint8), origin_px=(8, 0), canvas_px=(10, 4))


@pytest.mark.parametrize("start", [1, 0x12345678, 0xFFF0FFF0])
@pytest.mark.parametrize("count", [0, 1, 65521, 5 * 2**20 + 3])
def test_adler32_of_zeros_is_what_zlib_computes_from_the_zeros(start, count):
    import zlib

    assert outputs._adler32_zeros(start, count) == zlib.adler32(bytes(count), start)


class _LazyLayer:
    """What `_layer_window` reads of a `processing.result.MultiPlaneImage` made from (display image, labels)."""

    def __init__(self, display, labels, region_id):
        self.lazy_source, self.region_id = (display, labels), region_id


@pytest.mark.parametrize("with_boxes", [False, True])
def test_a_layers_window_holds_all_of_the_layer(with_boxes):
    """The window (the region's box grown by the fringe) placed on zeros is the whole layer computed over the whole
    frame: colours where the anti-aliased alpha is above 0, that alpha; for a region in the middle, one touching the
    frame's corner and one that is absent."""
    from mca.capture.pipeline_app import _alpha8, _layer_window, _window_crop, layer_alpha
    from mca.processing.labels import label_boxes

    rng = np.random.default_rng(3)
    labels = np.ones((90, 120), np.uint16)
    labels[30:50, 40:85] = 2
    labels[60:70, 50:60] = 2  # a second part of region 2
    labels[:12, 100:] = 3  # at the top right corner
    display = rng.random((90, 120, 3), dtype=np.float32)

    def srgb8_of(linear):
        return np.round(linear * 255).astype(np.uint8)

    boxes = label_boxes(labels) if with_boxes else None
    for region_id in (1, 2, 3, 4):
        window, (top, left), shape = _layer_window(_LazyLayer(display, labels, region_id), srgb8_of, None, boxes)
        placed = np.zeros(shape + (4,), np.uint8)
        placed[top : top + window.shape[0], left : left + window.shape[1]] = window
        alpha8 = _alpha8(layer_alpha(labels == region_id))
        expected = np.zeros_like(placed)
        expected[..., :3] = np.where((alpha8 > 0)[..., None], srgb8_of(display), 0)
        expected[..., 3] = alpha8
        np.testing.assert_array_equal(placed, expected, err_msg=f"region {region_id}")
        box = (slice(25, 55), slice(35, 95))  # a texture's crop, partly outside the window
        np.testing.assert_array_equal(_window_crop(window, (top, left), box), expected[box])


def test_a_large_map_is_written_in_strips_that_libtiff_reads_back_exactly(tmp_path):
    """The depth map is compressed strip by strip on several threads; OpenCV's libtiff (not the writer's own
    library) reads every strip back to the same floats, NaN included."""
    rng = np.random.default_rng(3)
    depth = (1500.0 + rng.normal(0.0, 40.0, (301, 257))).astype(np.float32)
    depth[5:40, 100:180] = np.nan
    outputs.write_tiff_float32(tmp_path / "depth.tiff", depth)
    with tifffile.TiffFile(tmp_path / "depth.tiff") as tif:
        page = tif.pages[0]
        assert len(page.dataoffsets) == outputs.TIFF_STRIPS - 1  # 301 rows in strips of 10
        assert page.compression == tifffile.COMPRESSION.ADOBE_DEFLATE
    read = cv2.imread(str(tmp_path / "depth.tiff"), cv2.IMREAD_UNCHANGED)
    assert read.dtype == np.float32
    np.testing.assert_array_equal(read, depth)


def test_the_strips_are_compressed_on_the_batch_workers_share_of_the_cores(tmp_path, monkeypatch):
    """A batch worker limited to one thread (`MCA_THREADS`, set by `capture.threads.limit_threads`) compresses on
    one thread, not on every core beside the other workers."""
    from mca.processing import disparity

    calls = []
    real = tifffile.imwrite
    monkeypatch.setattr(tifffile, "imwrite", lambda *a, **k: calls.append(k["maxworkers"]) or real(*a, **k))
    before = disparity.helper_threads()
    try:
        disparity.set_worker_threads(1)  # what `limit_threads` does in a batch worker
        outputs.write_tiff_float32(tmp_path / "a.tiff", np.ones((64, 64), np.float32))
        disparity.set_worker_threads(2)
        outputs.write_tiff_float32(tmp_path / "b.tiff", np.ones((64, 64), np.float32))
    finally:
        disparity.set_worker_threads(before)
    assert calls == [1, 2]
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "a.tiff"), np.ones((64, 64), np.float32))


def test_srgb_curve():
    assert outputs.linear_to_srgb8(np.array([0.0, 0.0031308, 0.2159, 1.0, 2.0])).tolist() == [0, 10, 128, 255, 255]
    np.testing.assert_allclose(outputs.srgb_to_linear(np.array([0.5])), [0.214041], rtol=1e-5)


def test_failed_write_leaves_no_temporary_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    target = tmp_path / "result.json"
    outputs.write_json(target, {"version": 1})
    with pytest.raises(RuntimeError, match="disk full"), outputs.atomic_path(target) as tmp:
        tmp.write_text("half a fi")
        raise RuntimeError("disk full")
    assert json.loads(target.read_text()) == {"version": 1}
    with pytest.raises(TypeError):
        outputs.write_png(tmp_path / "bad.png", np.zeros((2, 2), np.float64))
    with pytest.raises(ValueError):
        outputs.write_tiff_float32(tmp_path / "bad.tiff", np.zeros((2, 2, 2)))

    def no_space(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(outputs.os, "fsync", no_space)
    with pytest.raises(OSError, match="No space"):
        outputs.write_json(target, {"version": 2})
    with pytest.raises(OSError, match="No space"):
        outputs.write_glb(tmp_path / "scene.glb", [])
    assert json.loads(target.read_text()) == {"version": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]


@pytest.mark.parametrize("scale", [1.0, 2.0, 4.0, 1.5, 3.0, 2.5])
def test_label_pixels_input_counts_the_enlarged_map(scale):
    """result.json's region pixels: counted from the processing-resolution labels, the same as counting the
    region map `upsample_nearest` makes (the regions.png one), for whole and fractional scales, input sizes
    cut short of and past the enlarged map, and ids with no pixel."""
    rng = np.random.default_rng(int(scale * 10))
    for _ in range(20):
        h, w = (int(v) for v in rng.integers(1, 25, 2))
        labels = rng.integers(0, 7, (h, w)).astype(np.uint16)
        width = max(1, int(w * scale) + int(rng.integers(-2, 3)))
        height = max(1, int(h * scale) + int(rng.integers(-2, 3)))
        up = upsample_nearest(labels, scale, (width, height))
        expected = np.bincount(up.ravel().astype(np.intp), minlength=9)
        counts = label_pixels_input(labels, scale, (width, height), minlength=9)
        np.testing.assert_array_equal(counts, expected)
        assert counts.sum() == width * height


def test_upsample_and_back_projection():
    labels = np.array([[1, 2], [3, 4]], np.uint16)
    up = upsample_nearest(labels, 2.0, (5, 3))  # odd input size: the last row/column repeats
    assert up.tolist() == [[1, 1, 2, 2, 2], [1, 1, 2, 2, 2], [3, 3, 4, 4, 4]]
    camera = Pinhole(pixel_pitch_mm=0.004, sensor_distance_mm=52.63, width_px=101, height_px=51)
    point = camera.back_project_mm(np.array([100.0]), np.array([0.0]), np.array([1000.0]))[0]
    # 50 px right of the centre at 4 um: 0.2 mm on the sensor, times Z / d_ls (optical frame: y down)
    assert point == pytest.approx([0.2 * 1000 / 52.63, -0.1 * 1000 / 52.63, 1000.0])
    # the files' frame: metres, y up, looking down -z; and back again to the same pixel
    scene = camera.back_project_scene_m(np.array([100.0]), np.array([0.0]), np.array([1000.0]))[0]
    assert scene == pytest.approx([0.2 / 52.63, 0.1 / 52.63, -1.0])
    u, v = camera.project_scene_m(scene)
    assert (u, v) == pytest.approx((100.0, 0.0))
    np.testing.assert_allclose(camera.K, [[52.63 / 0.004, 0, 50], [0, 52.63 / 0.004, 25], [0, 0, 1]])
    depth = np.full((40, 60), 1000.0, np.float32)
    depth[:5] = np.nan
    colours = np.zeros((40, 60, 3), np.uint8)
    points, rgb = scene_points(depth, colours, 1.0, Pinhole(0.004, 52.63, 60, 40), max_points=500)
    assert 0 < len(points) <= 500 and len(rgb) == len(points)
    assert np.allclose(points[:, 2], -1.0)
