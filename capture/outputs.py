"""Writers for the per-shot output files (TIFF, PNG, JSON, PLY point cloud, glTF binary planes), all atomic.

Every writer puts its bytes under a temporary name in the destination folder and
renames it over the final name with `os.replace`, so a reader (or a resumed batch)
never sees half a file: either the old file, the new one, or none. A writer that
fails leaves no temporary file behind. The PLY and GLB formats are written by the
small encoders below, and read back by their twins (`read_ply`, `read_glb`) which
the tests and `mca` tools use to check them.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import struct
import uuid
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.processing import colour

TEMP_SUFFIX = ".tmp"


# --- atomic file creation -------------------------------------------------------------------------------------------


def temporary_name(path: Path) -> Path:
    """A hidden, unique name beside `path` for writing it before the final rename."""
    return path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}{TEMP_SUFFIX}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it to `path`, on failure delete it.

    For writers that insist on a file name (tifffile): `with atomic_path(p) as tmp: write(tmp)`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically (temporary file in the same folder, flushed, then os.replace)."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    return path


# --- images ---------------------------------------------------------------------------------------------------------


# The sRGB curve has one home, processing/colour.py; these names stay for the writers' callers.
linear_to_srgb8 = colour.linear_to_srgb8
srgb_to_linear = colour.srgb_decode


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_COLOUR_TYPES = {1: 0, 3: 2, 4: 6}  # samples per pixel -> PNG colour type (grey, RGB, RGBA)
PNG_DEFLATE_LEVEL = 1  # zlib level: the fastest; Up filtering does most of the work
DEFLATE_SEGMENT_BYTES = 1 << 20  # compressed independently (full flush), so zero runs are reused


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


_ADLER_BASE = 65521  # Adler-32's modulus (RFC 1950)


def _adler32_zeros(adler: int, count: int) -> int:
    """`zlib.adler32(bytes(count), adler)` without the bytes: zeros leave the sum A as it is and add A to the
    running sum B once per byte."""
    a, b = adler & 0xFFFF, adler >> 16
    return (((b + count * a) % _ADLER_BASE) << 16) | a


def _row_bytes(image: np.ndarray) -> np.ndarray:
    """(H, row bytes) uint8 view of an image's samples as PNG stores them (16-bit big-endian)."""
    samples = image.astype(">u2") if image.dtype == np.uint16 else image
    return np.ascontiguousarray(samples).reshape(samples.shape[0], -1).view(np.uint8)


def _zero_rows(rows: np.ndarray) -> np.ndarray:
    """Which rows of (H, row bytes) uint8 are all zero."""
    words = rows.view(np.uint64) if rows.shape[1] % 8 == 0 else rows
    return np.asarray(~words.any(axis=1), dtype=bool)


def _png_idat(window: np.ndarray, origin_px: tuple[int, int], canvas_px: tuple[int, int]) -> bytes:
    """The zlib stream (RFC 1950) of the filtered scanlines (PNG spec 9) of a canvas of `canvas_px` (H, W) pixels
    that is zero everywhere but where `window` lies, its top-left pixel at `origin_px` (row, column).

    Rows with data take filter Up (type 2), which removes the vertical redundancy of photos and upsampled maps;
    zero rows take None (type 0), so they are zero bytes. The stream is deflated in independent segments of whole
    rows (`DEFLATE_SEGMENT_BYTES`), each ending with a full flush (byte-aligned, no back references across it),
    then an empty final block: a segment of zero rows is the same bytes wherever it lies and is deflated once
    (`_deflated_zeros`). Segment by segment, only the rows that cross the window are ever made: a layer of a
    20 MP capture (2736 x 1824 RGBA) is its region's rows, not 20 MB of RGBA and as much again of scanlines. Same
    input, same bytes.
    """
    height, width = canvas_px
    top, left = origin_px
    rows = _row_bytes(window)
    pixel_bytes = rows.shape[1] // window.shape[1]
    row_bytes = width * pixel_bytes
    first_col = 1 + left * pixel_bytes  # the window's first byte in a scanline (after the filter type)
    last_col = first_col + rows.shape[1]
    zero = _zero_rows(rows)
    line_bytes = row_bytes + 1
    rows_per_segment = max(1, DEFLATE_SEGMENT_BYTES // line_bytes)
    parts = [b"\x78\x01"]
    adler = 1
    for start in range(0, height, rows_per_segment):
        stop = min(start + rows_per_segment, height)
        lo, hi = max(start, top), min(stop, top + rows.shape[0])  # the canvas rows of this segment in the window
        size = (stop - start) * line_bytes
        if lo >= hi or zero[lo - top : hi - top].all():
            parts.append(_deflated_zeros(size))
            adler = _adler32_zeros(adler, size)
            continue
        lines = np.zeros((stop - start, line_bytes), np.uint8)
        inside = lines[lo - start : hi - start]
        current = rows[lo - top : hi - top]
        data = inside[:, first_col:last_col]
        if lo > top:  # Up: each row less the row above it, whose bytes are zero above the window
            np.subtract(current, rows[lo - top - 1 : hi - top - 1], out=data)
        else:
            data[0] = current[0]
            np.subtract(current[1:], current[:-1], out=data[1:])
        empty = zero[lo - top : hi - top]
        data[empty] = 0
        inside[~empty, 0] = 2
        compressor = zlib.compressobj(PNG_DEFLATE_LEVEL, zlib.DEFLATED, -15, 9, zlib.Z_RLE)
        parts.append(compressor.compress(lines.data) + compressor.flush(zlib.Z_FULL_FLUSH))
        adler = zlib.adler32(lines.data, adler)
    parts.append(b"\x03\x00")  # empty final fixed-Huffman block
    parts.append(struct.pack(">I", adler))
    return b"".join(parts)


@functools.lru_cache(maxsize=32)
def _deflated_zeros(size: int) -> bytes:
    compressor = zlib.compressobj(PNG_DEFLATE_LEVEL, zlib.DEFLATED, -15, 9, zlib.Z_RLE)
    return compressor.compress(bytes(size)) + compressor.flush(zlib.Z_FULL_FLUSH)


PNG_SRGB_INTENT_PERCEPTUAL = 0
PNG_GAMA_SRGB = 45455  # gAMA of sRGB, 1/2.2 x 100000, written beside sRGB as the PNG spec recommends (11.3.3.5)
# cHRM of sRGB: white point and primaries x, y times 100000 (PNG spec 11.3.3.5)
PNG_CHRM_SRGB = (31270, 32900, 64000, 33000, 30000, 60000, 15000, 6000)


def _png_text_chunk(keyword: str, text: str) -> bytes:
    """An iTXt chunk (UTF-8, uncompressed): keyword, then the text; keywords are 1-79 Latin-1 characters."""
    key = keyword.encode("latin-1")
    if not 1 <= len(key) <= 79:
        raise ValueError(f"PNG text keyword must be 1-79 characters, got {keyword!r}")
    return _png_chunk(b"iTXt", key + b"\0\0\0\0\0" + text.encode("utf-8"))


def encode_png(
    image: np.ndarray,
    *,
    srgb: bool = False,
    text: dict[str, str] | None = None,
    origin_px: tuple[int, int] = (0, 0),
    canvas_px: tuple[int, int] | None = None,
) -> bytes:
    """PNG bytes of a uint8/uint16 image: (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA.

    `srgb=True` marks the samples as sRGB (sRGB chunk, with the gAMA and cHRM a decoder without sRGB
    support falls back on); `text` adds one iTXt chunk per item (e.g. "Description", "Software").
    With `canvas_px` (H, W), `image` is a window of a larger picture that is zero everywhere else, its top-left
    pixel at `origin_px` (row, column): the PNG is of the whole canvas (a layer's region and its fringe), and the
    same bytes as of the canvas made in full.

    Written here rather than by OpenCV: Up-filtered rows and zlib level 1 with run-length matching
    encode a 20 MP layer several times faster at a similar size, and zlib releases the GIL, so
    independent files encode in parallel threads.
    """
    image = np.ascontiguousarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"PNG holds uint8 or uint16 samples, got {image.dtype}")
    channels = 1 if image.ndim == 2 else image.shape[2] if image.ndim == 3 else 0
    if channels not in PNG_COLOUR_TYPES or (image.ndim == 3 and channels == 1) or 0 in image.shape:
        raise ValueError(f"PNG image must be (H, W), (H, W, 3) or (H, W, 4), got shape {image.shape}")
    height, width = canvas_px if canvas_px is not None else image.shape[:2]
    top, left = origin_px
    if top < 0 or left < 0 or top + image.shape[0] > height or left + image.shape[1] > width:
        raise ValueError(
            f"a PNG window of {image.shape[1]}x{image.shape[0]} px at row {top}, column {left} does not fit its "
            f"canvas of {width}x{height} px"
        )
    header = struct.pack(">IIBBBBB", width, height, 8 * image.dtype.itemsize, PNG_COLOUR_TYPES[channels], 0, 0, 0)
    chunks = [PNG_SIGNATURE, _png_chunk(b"IHDR", header)]
    if srgb:
        chunks += [
            _png_chunk(b"sRGB", bytes([PNG_SRGB_INTENT_PERCEPTUAL])),
            _png_chunk(b"gAMA", struct.pack(">I", PNG_GAMA_SRGB)),
            _png_chunk(b"cHRM", struct.pack(">8I", *PNG_CHRM_SRGB)),
        ]
    for keyword, value in (text or {}).items():
        chunks.append(_png_text_chunk(keyword, value))
    chunks += [_png_chunk(b"IDAT", _png_idat(image, (top, left), (height, width))), _png_chunk(b"IEND", b"")]
    return b"".join(chunks)


def write_png(path: str | Path, image: np.ndarray, *, srgb: bool = False, text: dict[str, str] | None = None) -> Path:
    """Write a uint8/uint16 grey, RGB or RGBA image as PNG, atomically (see `encode_png` for the chunks)."""
    return write_bytes_atomic(path, encode_png(image, srgb=srgb, text=text))


def read_png_text(data: bytes) -> dict[str, str]:
    """The tEXt/iTXt (uncompressed) chunks of PNG bytes, keyword -> text, and which of sRGB/gAMA/cHRM are present."""
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG file")
    found: dict[str, str] = {}
    at = len(PNG_SIGNATURE)
    while at + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[at : at + 8])
        body = data[at + 8 : at + 8 + length]
        if kind == b"tEXt":
            key, _, value = body.partition(b"\0")
            found[key.decode("latin-1")] = value.decode("latin-1")
        elif kind == b"iTXt":
            key, _, rest = body.partition(b"\0")
            if rest[:1] == b"\0":  # uncompressed
                _lang, _, rest = rest[2:].partition(b"\0")
                _translated, _, value = rest.partition(b"\0")
                found[key.decode("latin-1")] = value.decode("utf-8")
        elif kind in (b"sRGB", b"gAMA", b"cHRM"):
            found[f"chunk:{kind.decode()}"] = body.hex()
        elif kind == b"IEND":
            break
        at += 12 + length
    return found


TIFF_DEFLATE_LEVEL = 1  # a 20 MP per-pixel depth map: 13-18 MB of 80; level 6: 28 % smaller, 1.5-3x the time
TIFF_STRIPS = 32  # strips per map, compressed on several threads (one strip: 0.7 s at 20 MP, 32 on 2 threads: 0.3 s)


TIFF_TAG_GDAL_METADATA = 42112  # GDAL's XML metadata (units, descriptions), ASCII
TIFF_TAG_GDAL_NODATA = 42113  # GDAL's nodata value, ASCII


def gdal_metadata_xml(unit: str, description: str, items: dict[str, str] | None = None) -> str:
    """The GDAL_METADATA tag's XML: the band's unit type and description, plus dataset items."""
    from xml.sax.saxutils import escape, quoteattr

    lines = ["<GDALMetadata>"]
    for name, value in (items or {}).items():
        lines.append(f"  <Item name={quoteattr(name)}>{escape(value)}</Item>")
    lines.append(f'  <Item name="DESCRIPTION" sample="0" role="description">{escape(description)}</Item>')
    lines.append(f'  <Item name="UNITTYPE" sample="0" role="unittype">{escape(unit)}</Item>')
    lines.append("</GDALMetadata>")
    return "\n".join(lines)


def compression_threads() -> int:
    """Threads for compressing one file: the processing's own count (`processing.disparity.helper_threads`:
    this process's share of the cores in a batch worker, `capture.threads.limit_threads`; else its cores, at
    most 4)."""
    from mca.processing.disparity import helper_threads  # (OpenCV loads with it: not at this module's import)

    return helper_threads()


def write_tiff_float32(
    path: str | Path,
    image: np.ndarray,
    *,
    description: dict[str, Any] | None = None,
    unit: str | None = None,
    software: str | None = None,
    nodata: float | None = None,
) -> Path:
    """Write a 2-D array as a single-page float32 TIFF (NaN kept), deflate-compressed in `TIFF_STRIPS` strips
    on `compression_threads()` threads, atomically.

    `description` goes into ImageDescription as JSON; `software` into Software; `unit` (with the
    description's "meaning") into GDAL_METADATA and `nodata` into GDAL_NODATA ("nan" for NaN), the
    tags GDAL, QGIS and rasterio read.
    """
    import tifffile

    array = np.ascontiguousarray(image, dtype=np.float32)
    if array.ndim != 2:
        raise ValueError(f"expected a 2-D map, got shape {array.shape}")
    extratags: list[tuple[int, str, int, str, bool]] = []
    if unit is not None:
        meaning = str((description or {}).get("meaning", ""))
        xml = gdal_metadata_xml(unit, meaning)
        extratags.append((TIFF_TAG_GDAL_METADATA, "s", 0, xml, True))
    if nodata is not None:
        extratags.append((TIFF_TAG_GDAL_NODATA, "s", 0, "nan" if math.isnan(nodata) else repr(float(nodata)), True))
    with atomic_path(path) as tmp:
        tifffile.imwrite(
            tmp,
            array,
            photometric="minisblack",
            compression="zlib",
            compressionargs={"level": TIFF_DEFLATE_LEVEL},
            rowsperstrip=max(1, -(-array.shape[0] // TIFF_STRIPS)),
            maxworkers=compression_threads(),
            description=None if description is None else json.dumps(json_safe(description), ensure_ascii=True),
            metadata=None,
            software=software,
            extratags=extratags,
        )
    return Path(path)


# --- JSON -----------------------------------------------------------------------------------------------------------


def json_safe(value: Any) -> Any:
    """Plain JSON types: numpy scalars and arrays unpacked, tuples to lists, NaN and infinities to null."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        return json_safe(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, (str, int, bool)):
        return value
    return str(value)


def write_json(path: str | Path, data: Any) -> Path:
    """Write `data` as indented UTF-8 JSON (NaN written as null), atomically."""
    text = json.dumps(json_safe(data), indent=2, allow_nan=False, ensure_ascii=False) + "\n"
    return write_bytes_atomic(path, text.encode("utf-8"))


# --- PLY point cloud ------------------------------------------------------------------------------------------------

PLY_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}


def encode_ply(points_mm: np.ndarray, colours_rgb8: np.ndarray, comments: tuple[str, ...] = ()) -> bytes:
    """Binary little-endian PLY of N coloured points: (N, 3) float coordinates and (N, 3) uint8 RGB."""
    points = np.asarray(points_mm, dtype=np.float32).reshape(-1, 3)
    colours = np.asarray(colours_rgb8, dtype=np.uint8).reshape(-1, 3)
    if len(points) != len(colours):
        raise ValueError(f"{len(points)} points but {len(colours)} colours")
    vertices = np.empty(len(points), dtype=PLY_VERTEX)
    vertices["x"], vertices["y"], vertices["z"] = points[:, 0], points[:, 1], points[:, 2]
    vertices["red"], vertices["green"], vertices["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in comments]
    header += [f"element vertex {len(points)}"]
    header += [
        f"property {'float' if vertices.dtype[name].kind == 'f' else 'uchar'} {name}" for name in PLY_VERTEX.names or ()
    ]
    header += ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes()


def write_ply(
    path: str | Path, points_mm: np.ndarray, colours_rgb8: np.ndarray, comments: tuple[str, ...] = ()
) -> Path:
    """Write coloured points as a binary little-endian PLY, atomically."""
    return write_bytes_atomic(path, encode_ply(points_mm, colours_rgb8, comments))


def read_ply(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Read a binary little-endian PLY with one vertex element of scalar properties: (structured array, comments)."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary_little_endian 1.0 PLY is read here")
    count, fields, comments, element = 0, [], [], None
    for line in lines[1:]:
        words = line.split()
        if words[0] == "comment":
            comments.append(line[len("comment ") :])
        elif words[0] == "element":
            if element is not None:
                raise ValueError(f"{path}: more than one element; only a vertex list is read here")
            element, count = words[1], int(words[2])
        elif words[0] == "property":
            if words[1] == "list":
                raise ValueError(f"{path}: list properties are not read here")
            fields.append((words[2], _PLY_TYPES[words[1]]))
    body = data[end + len(b"end_header\n") :]
    dtype = np.dtype(fields)
    if len(body) != count * dtype.itemsize:
        raise ValueError(f"{path}: {len(body)} bytes of data for {count} vertices of {dtype.itemsize} bytes")
    return np.frombuffer(body, dtype=dtype, count=count), comments


# --- glTF 2.0 binary (GLB) with one textured quad per plane ---------------------------------------------------------

GLB_MAGIC = 0x46546C67  # b"glTF"
GLB_CHUNK_JSON = 0x4E4F534A  # b"JSON"
GLB_CHUNK_BIN = 0x004E4942  # b"BIN\0"
_FLOAT, _UNSIGNED_SHORT = 5126, 5123
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_COMPONENT_DTYPES = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}


@dataclass(frozen=True)
class TexturedQuad:
    """A flat quadrilateral in the scene frame (metres, glTF axes: x right, y up, the camera looking down -z):
    corners top-left, top-right, bottom-right, bottom-left as seen in the image; `texture_png` covers it
    with the image's top-left at the top-left corner."""

    name: str
    corners_m: np.ndarray  # (4, 3) float
    texture_png: bytes
    extras: dict[str, Any] | None = None


def _pad4(data: bytes, fill: bytes = b"\0") -> bytes:
    return data + fill * (-len(data) % 4)


@dataclass(frozen=True)
class GltfCamera:
    """A glTF perspective camera at the origin looking down -z (the camera that took the photograph)."""

    yfov_rad: float
    aspect_ratio: float
    znear_m: float = 0.05
    name: str = "camera"
    extras: dict[str, Any] | None = None


def encode_glb(
    quads: list[TexturedQuad],
    *,
    camera: GltfCamera | None = None,
    root_name: str = "scene",
    generator: str = "mca-appliance capture.outputs",
    asset_extras: dict[str, Any] | None = None,
) -> bytes:
    """glTF 2.0 binary: one unlit, double-sided, alpha-blended textured quad per entry, under one root node.

    Vertex positions are the quads' corners as given: metres in glTF's frame (y up, looking down -z);
    no node carries a transform. `camera` adds a camera node at the origin (glTF cameras look down
    their node's -z with +y up, which is the photograph's camera in this frame).
    """
    blob = bytearray()
    buffer_views: list[dict[str, Any]] = []
    accessors: list[dict[str, Any]] = []

    def view(data: bytes, target: int | None) -> int:
        offset = len(blob)
        blob.extend(_pad4(data))
        entry: dict[str, Any] = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if target is not None:
            entry["target"] = target
        buffer_views.append(entry)
        return len(buffer_views) - 1

    def accessor(array: np.ndarray, kind: str, component: int, target: int, bounds: bool) -> int:
        entry: dict[str, Any] = {
            "bufferView": view(array.tobytes(), target),
            "componentType": component,
            "count": int(array.shape[0]),
            "type": kind,
        }
        if bounds:
            values = array.reshape(array.shape[0], -1)
            entry["min"] = [float(v) for v in values.min(axis=0)]
            entry["max"] = [float(v) for v in values.max(axis=0)]
        accessors.append(entry)
        return len(accessors) - 1

    texcoords = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype="<f4")
    indices = np.array([0, 3, 2, 0, 2, 1], dtype="<u2")  # counter-clockwise seen from the camera
    meshes, materials, textures, images, nodes = [], [], [], [], []
    for quad in quads:
        corners = np.asarray(quad.corners_m, dtype="<f4").reshape(4, 3)
        if not np.isfinite(corners).all():
            raise ValueError(f"quad '{quad.name}' has non-finite corners")
        position = accessor(corners, "VEC3", _FLOAT, _ARRAY_BUFFER, bounds=True)
        uv = accessor(texcoords, "VEC2", _FLOAT, _ARRAY_BUFFER, bounds=False)
        index = accessor(indices, "SCALAR", _UNSIGNED_SHORT, _ELEMENT_ARRAY_BUFFER, bounds=True)
        images.append({"bufferView": view(quad.texture_png, None), "mimeType": "image/png", "name": quad.name})
        textures.append({"source": len(images) - 1, "sampler": 0})
        materials.append(
            {
                "name": quad.name,
                "doubleSided": True,
                "alphaMode": "BLEND",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": len(textures) - 1},
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
                "extensions": {"KHR_materials_unlit": {}},
            }
        )
        meshes.append(
            {
                "name": quad.name,
                "primitives": [
                    {
                        "attributes": {"POSITION": position, "TEXCOORD_0": uv},
                        "indices": index,
                        "material": len(materials) - 1,
                    }
                ],
            }
        )
        node: dict[str, Any] = {"name": quad.name, "mesh": len(meshes) - 1}
        if quad.extras:
            node["extras"] = json_safe(quad.extras)
        nodes.append(node)
    cameras = []
    if camera is not None:
        cameras.append(
            {
                "name": camera.name,
                "type": "perspective",
                "perspective": {
                    "yfov": float(camera.yfov_rad),
                    "aspectRatio": float(camera.aspect_ratio),
                    "znear": float(camera.znear_m),
                },
            }
        )
        camera_node: dict[str, Any] = {"name": camera.name, "camera": 0}
        if camera.extras:
            camera_node["extras"] = json_safe(camera.extras)
        nodes.append(camera_node)
    root: dict[str, Any] = {"name": root_name}
    if nodes:
        root["children"] = list(range(1, len(nodes) + 1))
    asset: dict[str, Any] = {"version": "2.0", "generator": generator}
    if asset_extras:
        asset["extras"] = json_safe(asset_extras)
    gltf: dict[str, Any] = {
        "asset": asset,
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [root] + nodes,
    }
    if cameras:
        gltf["cameras"] = cameras
    if quads:
        gltf.update(
            {
                "extensionsUsed": ["KHR_materials_unlit"],
                "meshes": meshes,
                "materials": materials,
                "textures": textures,
                "images": images,
                "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}],
                "accessors": accessors,
                "bufferViews": buffer_views,
                "buffers": [{"byteLength": len(blob)}],
            }
        )
    json_chunk = _pad4(json.dumps(gltf, separators=(",", ":")).encode("utf-8"), b" ")
    chunks = struct.pack("<II", len(json_chunk), GLB_CHUNK_JSON) + json_chunk
    if blob:
        chunks += struct.pack("<II", len(blob), GLB_CHUNK_BIN) + bytes(blob)
    return struct.pack("<III", GLB_MAGIC, 2, 12 + len(chunks)) + chunks


def write_glb(path: str | Path, quads: list[TexturedQuad], **options: Any) -> Path:
    """Write textured quads as a glTF 2.0 binary file (see `encode_glb`), atomically."""
    return write_bytes_atomic(path, encode_glb(quads, **options))


def read_glb(path: str | Path) -> tuple[dict[str, Any], bytes]:
    """Parse a GLB file: (the glTF JSON, the BIN chunk); checks the header, chunk types and lengths."""
    data = Path(path).read_bytes()
    if len(data) < 20:
        raise ValueError(f"{path}: {len(data)} bytes is too short for a GLB file")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2:
        raise ValueError(f"{path}: not a glTF 2.0 binary (magic {magic:#x}, version {version})")
    if length != len(data):
        raise ValueError(f"{path}: header says {length} bytes, file has {len(data)}")
    json_length, json_type = struct.unpack_from("<II", data, 12)
    if json_type != GLB_CHUNK_JSON or json_length % 4:
        raise ValueError(f"{path}: first chunk must be JSON with a length multiple of 4")
    gltf = json.loads(data[20 : 20 + json_length].decode("utf-8"))
    offset = 20 + json_length
    binary = b""
    if offset < len(data):
        bin_length, bin_type = struct.unpack_from("<II", data, offset)
        if bin_type != GLB_CHUNK_BIN or offset + 8 + bin_length != len(data):
            raise ValueError(f"{path}: second chunk must be BIN and end the file")
        binary = data[offset + 8 :]
    return gltf, binary


def glb_accessor(gltf: dict[str, Any], binary: bytes, index: int) -> np.ndarray:
    """The array behind accessor `index` (tightly packed views only), shaped (count, components)."""
    acc = gltf["accessors"][index]
    buffer_view = gltf["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(_COMPONENT_DTYPES[acc["componentType"]])
    components = _COMPONENTS[acc["type"]]
    start = buffer_view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    size = acc["count"] * components * dtype.itemsize
    if start + size > buffer_view.get("byteOffset", 0) + buffer_view["byteLength"] or start + size > len(binary):
        raise ValueError(f"accessor {index} reaches past its buffer view")
    return np.frombuffer(binary, dtype=dtype, count=acc["count"] * components, offset=start).reshape(-1, components)


def glb_image(gltf: dict[str, Any], binary: bytes, index: int) -> bytes:
    """The encoded bytes of image `index` (stored in a buffer view)."""
    buffer_view = gltf["bufferViews"][gltf["images"][index]["bufferView"]]
    start = buffer_view.get("byteOffset", 0)
    return binary[start : start + buffer_view["byteLength"]]
