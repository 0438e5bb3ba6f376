"""One photograph in, one finished output folder out: read the file, run the depth pipeline, write every output.

`process_file` is the unit of work of `mca process`, of the local process pool and of a
Dask cluster alike: it takes only picklable arguments, writes under `out_root/<name>/`
and never raises for a bad input file (it returns a failed `FileOutcome` naming the file).
A folder counts as finished when its `result.json` exists; that file is written last.
The folder name, the per-folder lock, staging and replace-then-delete are
`capture/output_folders.py`: a result is keyed by the input's content (sha256) and the
settings, so a changed photograph is processed again and an unchanged one skipped, and a
run that fails (a full disk, Ctrl-C) leaves the previous result as it was.
What each output holds is described in docs/outputs.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import errno
import hashlib
import json
import math
import os
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.capture import api, output_folders, outputs
from mca.capture.api import LoadedInput, read_input  # the input's own facts live in capture/api.py
from mca.capture.raw import (
    IMAGE_EXTENSIONS,
    RAW_EXTENSIONS,
    NotARegularFileError,
    RawReadError,
    read_policy,
    read_raw,
)
from mca.processing.camera import CameraProfile
from mca.processing.colour import CameraColour
from mca.processing.pinhole import SCENE_FRAME, PinholeCamera, processing_pixel_edges
from mca.processing.result import DepthResult

SUPPORTED_SUFFIXES = frozenset(RAW_EXTENSIONS) | frozenset(IMAGE_EXTENSIONS)  # what `read_raw` reads
RESULT_NAME = output_folders.RESULT_NAME
RECORDING_NAME = "recording.rrd"
MAX_PLY_POINTS = 1_000_000
LAYER_ORDER = "front-to-back"  # layers/00.png is the nearest plane

PipelineFunction = Callable[..., DepthResult]


@dataclass
class FileOutcome:
    """What became of one input file."""

    input_path: Path
    status: str  # "done", "skipped" (already finished) or "failed"
    output_dir: Path
    seconds: float = 0.0
    reason: str | None = None  # why it failed or was skipped
    regions: int | None = None  # number of regions found, when done
    notes: tuple[str, ...] = ()  # what the user should know about a done file's result (result.json's notes)


# --- reading --------------------------------------------------------------------------------------------------------


def upsample_nearest(array: np.ndarray, pixel_scale: float, size_px: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resampling of a processing-resolution map to the input size (width, height)."""
    height, width = array.shape[:2]
    factor = int(pixel_scale)
    if (
        factor == pixel_scale
        and factor in (2, 4)
        and array.ndim == 2
        and array.dtype in (np.uint16, np.float32)
        and size_px[0] <= width * factor
        and size_px[1] <= height * factor
    ):
        import cv2  # pixel i takes source pixel i // factor, exactly as below, without the index arrays

        enlarged = cv2.resize(
            np.ascontiguousarray(array), (width * factor, height * factor), interpolation=cv2.INTER_NEAREST
        )
        return enlarged[: size_px[1], : size_px[0]]
    rows, cols = _nearest_sources(pixel_scale, size_px, (height, width))
    return array[rows[:, None], cols[None, :]]


def _nearest_sources(
    pixel_scale: float, size_px: tuple[int, int], shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The source row of each input row and the source column of each input column of `upsample_nearest`."""
    height, width = shape
    rows = np.minimum(((np.arange(size_px[1]) + 0.5) / pixel_scale).astype(np.intp), height - 1)
    cols = np.minimum(((np.arange(size_px[0]) + 0.5) / pixel_scale).astype(np.intp), width - 1)
    return rows, cols


def label_pixels_input(labels: np.ndarray, pixel_scale: float, size_px: tuple[int, int], minlength: int) -> np.ndarray:
    """How many input pixels each label covers once `upsample_nearest` brings the processing-resolution `labels`
    to the input size (width, height): counts[id], as np.bincount of the enlarged map, without making it (at
    20 MP that took 0.2 s at the end of `mca process`). A processing pixel counts once per input pixel that
    takes it: (input rows taking its row) x (input columns taking its column)."""
    labels = np.asarray(labels)
    rows, cols = _nearest_sources(pixel_scale, size_px, labels.shape[:2])
    row_takers = np.bincount(rows, minlength=labels.shape[0])
    col_takers = np.bincount(cols, minlength=labels.shape[1])
    weights = np.outer(row_takers, col_takers).ravel().astype(np.float64)  # exact: whole numbers below 2**53
    counts = np.bincount(labels.ravel().astype(np.intp, copy=False), weights=weights, minlength=minlength)
    return np.rint(counts).astype(np.int64)


# The camera of an input image, from the pixel pitch and d_ls: the one model of every 3D output (processing/pinhole.py).
Pinhole = PinholeCamera.from_optics


def scene_points(
    depth_mm: np.ndarray,
    colours_rgb8: np.ndarray,
    pixel_scale: float,
    camera: PinholeCamera,
    max_points: int = MAX_PLY_POINTS,
) -> tuple[np.ndarray, np.ndarray]:
    """Coloured scene-frame points (metres, glTF axes) of every known-depth pixel, on a regular stride.

    The stride is the smallest that leaves at most `max_points` (`PinholeCamera.depth_map_points`, which
    the recording's point cloud uses too, so the two agree point for point where their strides agree).
    """
    points, rows, cols = camera.depth_map_points(depth_mm, pixel_scale, max_points)
    return points, colours_rgb8[rows, cols]


def _alpha8(alpha: np.ndarray) -> np.ndarray:
    """Coverage in [0, 1] to 8-bit alpha, rounded; NaN as 0 (fmax/fmin drop NaN)."""
    clipped = np.fmin(np.fmax(np.asarray(alpha, np.float32), np.float32(0.0)), np.float32(1.0))
    return np.round(clipped * np.float32(255.0)).astype(np.uint8)


def _box_of(mask: np.ndarray) -> tuple[slice, slice] | None:
    """The bounding box of a 2-D mask's True pixels, None when there is none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask[rows[0] : rows[-1] + 1].any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


ALPHA_MARGIN_PX = 3  # how far the fringe reaches beyond the region (where the Gaussian rounds to 0 alpha)
ALPHA_EDGE_PX = 0.7  # sigma (processing px) of the anti-aliased fringe around a layer's region


def layer_alpha(mask: np.ndarray, sigma_px: float = ALPHA_EDGE_PX) -> np.ndarray:
    """Anti-aliased coverage in [0, 1] of a region's mask: 1 on the region, a ramp down to 0 just outside it.

    `max(mask, Gaussian(mask))`: the region's own pixels stay opaque, and the pixels next to it get a
    partial coverage that falls off over about two pixels, so a silhouette is not a staircase of 0 and
    255. Seen from the camera nothing changes where layers meet: the fringe of a nearer layer lies over
    the farther layer's own (opaque) pixels and carries the same colour (every layer takes its colours
    from the one display image), and a farther layer's fringe lies behind the nearer layer.
    """
    import cv2

    mask_f = np.asarray(mask, dtype=np.float32)
    if not mask_f.any():
        return mask_f
    soft = cv2.GaussianBlur(mask_f, (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)
    return np.maximum(mask_f, soft)


def _layer_window(
    layer: Any,
    srgb8_of: Callable[[np.ndarray], np.ndarray],
    colour: CameraColour | None = None,
    boxes: list[tuple[slice, slice] | None] | None = None,
) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """A layer (premultiplied linear camera RGB, alpha in [0, 1]) as 8-bit sRGB with anti-aliased 8-bit alpha, as
    the window that holds all of it: (RGBA window, its top-left (row, column) in the layer, the layer's (H, W)).
    Every byte outside the window is 0; an empty layer's window is its top-left pixel.

    The window is the bounding box of the layer's region grown by `ALPHA_MARGIN_PX` (lazy layers) or of its
    non-zero pixels (eager ones): often a few per cent of the frame, where the whole RGBA of a 20 MP capture's
    layer is 20 MB. A layer the pipeline built lazily from a (display image, labels) source
    (`processing.result.MultiPlaneImage.rgba`: display x mask, alpha = mask) takes its colours from the display
    image converted once for all layers (`srgb8_of`, cached by the caller, white balance and colour matrix
    included), and its alpha from `layer_alpha` of its mask. RGB is stored unpremultiplied (PNG's convention).
    `colour` converts an eager layer's camera RGB (identity when None). `boxes`: the bounding boxes of a lazy
    layer's label image (`region_boxes`), when the caller has them; without them the layer finds its own box in
    the whole label image.
    """
    source = layer.lazy_source
    if source is not None:
        display, labels = source
        labels = np.asarray(labels)
        if boxes is not None:
            found = boxes[layer.region_id - 1] if 0 < layer.region_id <= len(boxes) else None
        else:
            found = _box_of(labels == layer.region_id)
        if found is None:
            return np.zeros((1, 1, 4), np.uint8), (0, 0), labels.shape
        box = _grown(found, labels.shape, ALPHA_MARGIN_PX)
        mask = labels[box] == layer.region_id
        window = np.zeros(mask.shape + (4,), np.uint8)
        alpha8 = _alpha8(layer_alpha(mask))
        np.copyto(window[..., :3], srgb8_of(display)[box], where=(alpha8 > 0)[..., None])
        window[..., 3] = alpha8
        return window, (box[0].start, box[1].start), labels.shape
    rgba = np.asarray(layer.rgba)
    nonzero = _box_of((rgba != 0).any(axis=2))
    if nonzero is None:
        return np.zeros((1, 1, 4), np.uint8), (0, 0), rgba.shape[:2]
    crop = rgba[nonzero]
    window = np.zeros(crop.shape[:2] + (4,), np.uint8)
    alpha = np.clip(np.nan_to_num(crop[..., 3:4]), 0.0, 1.0)
    straight = np.where(alpha > 0, crop[..., :3] / np.maximum(alpha, 1e-6), 0.0)
    window[..., :3] = (colour or CameraColour()).to_srgb8(straight)
    window[..., 3] = _alpha8(crop[..., 3])
    return window, (nonzero[0].start, nonzero[1].start), rgba.shape[:2]


def _window_crop(window: np.ndarray, origin: tuple[int, int], box: tuple[slice, slice]) -> np.ndarray:
    """The part `box` of the canvas that is zero but for `window` at `origin` (row, column)."""
    rows, cols = box
    out = np.zeros((rows.stop - rows.start, cols.stop - cols.start) + window.shape[2:], window.dtype)
    top, left = origin
    y0, y1 = max(rows.start, top), min(rows.stop, top + window.shape[0])
    x0, x1 = max(cols.start, left), min(cols.stop, left + window.shape[1])
    if y0 < y1 and x0 < x1:
        out[y0 - rows.start : y1 - rows.start, x0 - cols.start : x1 - cols.start] = window[
            y0 - top : y1 - top, x0 - left : x1 - left
        ]
    return out


def _grown(box: tuple[slice, slice], shape: tuple[int, ...], margin: int) -> tuple[slice, slice]:
    rows, cols = box
    return (
        slice(max(0, rows.start - margin), min(shape[0], rows.stop + margin)),
        slice(max(0, cols.start - margin), min(shape[1], cols.stop + margin)),
    )


def region_boxes(labels: np.ndarray) -> list[tuple[slice, slice] | None]:
    """Bounding boxes of the regions: boxes[id - 1] bounds region id (None when it has no pixel)."""
    from mca.processing.labels import label_boxes

    return label_boxes(np.asarray(labels))


def region_quads(
    result: DepthResult,
    textures_png: dict[int, bytes],
    all_in_focus8: np.ndarray,
    camera: PinholeCamera,
    boxes: list[tuple[slice, slice] | None] | None = None,
    distance_mm_of: Callable[[np.ndarray], np.ndarray] | None = None,
) -> list[outputs.TexturedQuad]:
    """One quad per region with a distance, front to back: its bounding box back-projected onto its surface.

    A fronto-parallel region's quad stands at the region's distance. A slanted region's corners take
    the distances of its fitted disparity plane (`Region.slant`, a x + b y + c in input pixels) through
    `distance_mm_of` (the optics' disparity-to-distance): the quad lies in the 3D plane the depth map
    shows (disparity affine in the image is 1/distance affine: a plane). Corners are in the scene
    frame (metres, glTF axes). `textures_png[id]` is the region's layer cropped to its box, as PNG; a
    region without one is textured with the all-in-focus image under its mask.
    """
    labels = np.asarray(result.labels)
    boxes = region_boxes(labels) if boxes is None else boxes
    quads = []
    for region in sorted(result.regions, key=lambda r: r.order):
        z = region.distance_mm
        box = boxes[region.id - 1] if 0 < region.id <= len(boxes) else None
        if z is None or not math.isfinite(z) or z <= 0 or box is None:
            continue
        (r0, r1), (c0, c1) = (box[0].start, box[0].stop), (box[1].start, box[1].stop)
        texture = textures_png.get(region.id)
        if texture is None:
            crop = (labels[box] == region.id).astype(np.uint8) * 255
            texture = outputs.encode_png(np.dstack([all_in_focus8[box], crop]))
        # the box's outer pixel edges in input-image coordinates (processing/pinhole.py's convention)
        left, right = processing_pixel_edges(np.array([c0, c1]), result.pixel_scale)
        top, bottom = processing_pixel_edges(np.array([r0, r1]), result.pixel_scale)
        u = np.array([left, right, right, left])
        v = np.array([top, top, bottom, bottom])
        distances = np.full(4, float(z))
        slanted = False
        if region.slant is not None and distance_mm_of is not None:
            slanted = True
            a, b, c = region.slant
            corner_distances = np.asarray(distance_mm_of(a * u + b * v + c), dtype=np.float64)
            if np.all(np.isfinite(corner_distances)) and np.all(corner_distances > 0):
                distances = corner_distances
            else:
                slanted = False
        corners = camera.back_project_scene_m(u, v, distances)
        quads.append(
            outputs.TexturedQuad(
                name=f"region {region.id}",
                corners_m=corners,
                texture_png=texture,
                extras={
                    "region_id": region.id,
                    "order": region.order,
                    "distance_mm": float(z),
                    "corner_distances_mm": [round(float(d), 4) for d in distances],
                    "slanted": bool(slanted),
                },
            )
        )
    return quads


# --- writing --------------------------------------------------------------------------------------------------------


def _number(value: Any) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _capture_time(metadata: dict[str, Any]) -> _dt.datetime | None:
    value = metadata.get("capture_time")
    return value if isinstance(value, _dt.datetime) else None


def _clean_folder(out_dir: Path) -> None:
    """Remove what a killed or previous run left that this run might not overwrite."""
    for folder in (out_dir, out_dir / "layers"):
        if not folder.is_dir():
            continue
        for entry in folder.iterdir():
            if (entry.name.startswith(".") and entry.name.endswith(outputs.TEMP_SUFFIX)) or (
                folder.name == "layers" and entry.suffix == ".png"
            ):
                entry.unlink(missing_ok=True)
    for name in ("depth.tiff", "disparity.tiff", "regions.png", "all_in_focus.png", "scene.ply", "scene.glb"):
        (out_dir / name).unlink(missing_ok=True)


WRITE_THREADS = 2  # PNG/TIFF deflate, sRGB tables and file writes release the GIL: files encode side by side
RESULT_SCHEMA_VERSION = 2  # result.json's layout (docs/outputs.md); raised whenever a field changes meaning


def software() -> str:
    """The software that wrote a file, for its metadata: "mca-appliance <version>"."""
    from mca import __version__

    return f"mca-appliance {__version__}"


def _file_text(what: str, input_path: Path | None) -> dict[str, str]:
    """PNG text chunks: what the image is, the software and the photograph it came from."""
    text = {"Title": what.split(":")[0], "Description": what, "Software": software()}
    if input_path is not None:
        text["Source"] = str(input_path)
    return text


class OutputWriter:
    """Writes one result's files on worker threads while the pipeline is still computing.

    The depth map (or the disparity map without optics) and the region map go to the writer threads
    as soon as the pipeline's "depth" stage hands them to its recorder (`on_record`), while the
    pipeline goes on to the all-in-focus image and the layers; everything else once the result is
    complete (`submit`), and those files encode while a recording logs the result. Every file
    lands atomically (capture/outputs.py: a temporary name, then a rename) and its bytes are the
    same whatever the number of threads, the order they finish in, or whether a file started
    early. Use as a context manager: leaving it waits for every file (also after an error), so
    nothing writes into a staging folder that is being discarded.
    """

    def __init__(
        self,
        out_dir: Path,
        loaded: LoadedInput,
        camera: PinholeCamera | None,
        *,
        optics: Any = None,
        profile: CameraProfile | None = None,
        threads: int = WRITE_THREADS,
    ) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.out_dir = out_dir
        self.loaded = loaded
        self.camera = camera
        self.optics = optics
        self.profile = profile
        self.seconds: dict[str, float] = {}  # thread-seconds per file (all layers summed as "layers/*.png")
        self._pool = ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix="mca-write")
        self._lock = threading.Lock()
        self._early: dict[str, Any] | None = None  # the arrays the depth files were started from, and their tasks
        self._tasks: list[Future] = []  # each gives a Path, in the order of the written list
        self._layer_tasks: list[Future] = []
        self._ply_task: Future | None = None
        self._glb: Callable[[], Path] | None = None
        self._source = getattr(loaded.frame, "path", None)

    def __enter__(self) -> OutputWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self._pool.shutdown(wait=True, cancel_futures=exc[0] is not None)

    # --- what each file holds -----------------------------------------------------------------------------------

    def _timed(self, name: str, function: Callable[..., Any], *args: Any) -> Future:
        def run() -> Any:
            start = time.perf_counter()
            try:
                return function(*args)
            finally:
                with self._lock:
                    self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start

        return self._pool.submit(run)

    def _describe_map(self, meaning: str, unit: str) -> dict[str, Any]:
        return {
            "meaning": meaning,
            "unit": unit,
            "nodata": "NaN",
            "software": software(),
            "input": None if self._source is None else str(self._source),
            "profile": None if self.profile is None else self.profile.name,
            "profile_source": None if self.profile is None else self.profile.source,
            "optics": None if self.optics is None else _optics_document(self.optics),
            "camera": None if self.camera is None else self.camera.describe(),
            "pixel_convention": "row 0 is the top of the image; input-image pixels",
        }

    def _depth_tasks(self, labels: np.ndarray, disparity_px: np.ndarray, depth_mm: np.ndarray | None) -> None:
        """depth.tiff (and disparity.tiff without a scene) and regions.png, from the processing-resolution maps."""
        out_dir, scale, size = self.out_dir, self.loaded.pixel_scale, self.loaded.input_size_px
        with_scene = self.camera is not None and depth_mm is not None
        labels_input = self._pool.submit(upsample_nearest, np.asarray(labels), scale, size)

        def write_regions() -> Path:
            return outputs.write_png(
                out_dir / "regions.png",
                labels_input.result().astype(np.uint16),
                text=_file_text(
                    "region labels: the region id of each input pixel (result.json), 0 = none", self._source
                ),
            )

        def write_disparity() -> Path:
            return outputs.write_tiff_float32(
                out_dir / "disparity.tiff",
                upsample_nearest(np.asarray(disparity_px, np.float32), scale, size),
                description=self._describe_map(
                    "disparity between the images of the widest filter pair, region model; "
                    "+ = farther than the focus plane",
                    "px",
                ),
                unit="px",
                software=software(),
                nodata=math.nan,
            )

        def write_depth() -> Path:
            depth = (
                np.asarray(depth_mm, dtype=np.float32)
                if with_scene
                else np.full(np.asarray(labels).shape, np.nan, dtype=np.float32)
            )
            meaning = "distance from the lens along the optical axis"
            if not with_scene:
                meaning += " (all NaN: no lens data, see disparity.tiff)"
            return outputs.write_tiff_float32(
                out_dir / "depth.tiff",
                upsample_nearest(depth, scale, size),
                description=self._describe_map(meaning, "mm"),
                unit="mm",
                software=software(),
                nodata=math.nan,
            )

        tasks = []
        if not with_scene:
            tasks.append(self._timed("disparity.tiff", write_disparity))
        tasks.append(self._timed("depth.tiff", write_depth))
        tasks.append(self._timed("regions.png", write_regions))
        self._tasks.extend(tasks)

    def on_record(self, stage: str, items: dict[str, Any]) -> None:
        """Hears the pipeline's stages (`_StageTimer`): "depth" starts the depth and region maps."""
        if stage != "depth" or self._early is not None or "labels" not in items or "disparity_px" not in items:
            return
        self._early = {
            "labels": items["labels"],
            "disparity_px": items["disparity_px"],
            "depth_mm": items.get("depth_mm"),
        }
        self._depth_tasks(items["labels"], items["disparity_px"], items.get("depth_mm"))

    def _early_matches(self, result: DepthResult) -> bool:
        early = self._early
        return (
            early is not None
            and early["labels"] is result.labels
            and early["disparity_px"] is result.disparity_px
            and early["depth_mm"] is result.depth_mm
            and bool(np.isclose(result.pixel_scale, self.loaded.pixel_scale))
        )

    def submit(self, result: DepthResult) -> None:
        """Start every file not started yet (all of them when the depth maps did not come early, or changed)."""
        if not self._early_matches(result):
            if self._early is not None:  # the result is not what the early files were made of: make them again
                for task in self._tasks:
                    task.exception()  # wait: the rewrite must land after them
                self._tasks = []
                self._early = None
            self._depth_tasks(result.labels, result.disparity_px, result.depth_mm)
        self._rest_tasks(result)

    def _rest_tasks(self, result: DepthResult) -> None:
        out_dir, loaded, camera, source = self.out_dir, self.loaded, self.camera, self._source
        scale, colour = result.pixel_scale, loaded.colour
        with_scene = camera is not None and result.depth_mm is not None
        layers = ordered_layers(result)
        boxes = region_boxes(result.labels)  # the GLB's textures and the layers' windows (layers cut from these labels)
        textured: set[int] = set()  # the first layer of a region textures its quad in the GLB
        distance_mm_of = getattr(self.optics, "distance_mm", None)
        pool = self._pool
        # Tasks run first in, first out, and a task only waits for ones submitted before it: no deadlock.
        conversions: dict[int, Future] = {}

        def srgb8_of(linear: np.ndarray) -> np.ndarray:
            return conversions[id(linear)].result()

        def convert(linear: np.ndarray) -> None:
            if id(linear) not in conversions:
                conversions[id(linear)] = pool.submit(colour.to_srgb8, linear)

        convert(result.all_in_focus)
        for layer in layers:
            if layer.lazy_source is not None:
                convert(layer.lazy_source[0])

        def write_layer(index: int, layer: Any, box: tuple[slice, slice] | None) -> tuple[Path, bytes | None]:
            lazy = layer.lazy_source
            cut_from_labels = lazy is not None and lazy[1] is result.labels
            window, origin, shape = _layer_window(layer, srgb8_of, colour, boxes if cut_from_labels else None)
            text = _file_text(
                f"layer {index:02d}: multi-plane image of region {layer.region_id}, sRGB, alpha = coverage "
                "(anti-aliased), front to back",
                source,
            )
            png = outputs.encode_png(window, srgb=True, text=text, origin_px=origin, canvas_px=shape)
            path = outputs.write_bytes_atomic(out_dir / "layers" / f"{index:02d}.png", png)
            if box is None:
                return path, None
            crop = _window_crop(window, origin, box)
            # a full-frame box: the same PNG
            return path, png if crop.shape[:2] == tuple(shape) else outputs.encode_png(crop)

        def write_scene_ply() -> Path:
            assert camera is not None
            depth = np.asarray(result.depth_mm, dtype=np.float32)
            points, colours = scene_points(depth, srgb8_of(result.all_in_focus), scale, camera)
            return outputs.write_ply(
                out_dir / "scene.ply",
                points,
                colours,
                comments=(
                    f"mca-appliance scene: {SCENE_FRAME}",
                    "units metres; colours sRGB",
                    f"written by {software()}",
                ),
            )

        # the longest tasks first, so that neither thread is left with a long one at the end
        self._tasks.append(
            self._timed(
                "all_in_focus.png",
                lambda: outputs.write_png(
                    out_dir / "all_in_focus.png",
                    srgb8_of(result.all_in_focus),
                    srgb=True,
                    text=_file_text("all-in-focus image: each region's colour channels re-aligned, sRGB", source),
                ),
            )
        )
        layer_tasks = []
        for index, layer in enumerate(layers):
            box = None
            if with_scene and layer.region_id not in textured and 0 < layer.region_id <= len(boxes):
                textured.add(layer.region_id)
                box = boxes[layer.region_id - 1]
            layer_tasks.append((layer.region_id, self._timed("layers/*.png", write_layer, index, layer, box)))
        ply_task = self._timed("scene.ply", write_scene_ply) if with_scene else None

        def write_glb() -> Path:
            assert camera is not None
            textures: dict[int, bytes] = {}
            for region_id, task in layer_tasks:
                texture = task.result()[1]
                if texture is not None:
                    textures[region_id] = texture
            quads = region_quads(result, textures, srgb8_of(result.all_in_focus), camera, boxes, distance_mm_of)
            gltf_camera = outputs.GltfCamera(
                yfov_rad=camera.yfov_rad,
                aspect_ratio=camera.width_px / camera.height_px,
                extras=camera.describe(),
            )
            return outputs.write_glb(
                out_dir / "scene.glb",
                quads,
                camera=gltf_camera,
                generator=software(),
                asset_extras={"scene_frame": SCENE_FRAME, "input": None if source is None else str(source)},
            )

        self._layer_tasks = [task for _, task in layer_tasks]
        self._ply_task = ply_task
        self._glb = write_glb if with_scene and camera is not None and ply_task is not None else None

    def finish(self) -> list[str]:
        """Wait for every file; their names relative to the output folder (result.json is the caller's)."""
        paths: list[Path] = [task.result() for task in self._tasks]
        paths += [task.result()[0] for task in self._layer_tasks]
        if self._ply_task is not None:
            paths.append(self._ply_task.result())
        if self._glb is not None:
            start = time.perf_counter()
            paths.append(self._glb())
            self.seconds["scene.glb"] = time.perf_counter() - start
        return [path.relative_to(self.out_dir).as_posix() for path in paths]


def write_outputs(
    out_dir: Path,
    result: DepthResult,
    loaded: LoadedInput,
    camera: PinholeCamera | None,
    *,
    optics: Any = None,
    profile: CameraProfile | None = None,
    threads: int = WRITE_THREADS,
) -> list[str]:
    """Write every output except result.json; returns their names relative to `out_dir` (see `OutputWriter`).

    `camera` is None in disparity-only mode; `optics` (an `MCAOptics`) places slanted regions' quads on
    their planes; `profile` goes into depth.tiff's description. Displayed images (all-in-focus, layers,
    GLB textures, point colours) get the input's camera colour (`loaded.colour`: white balance and colour
    matrix).
    """
    with OutputWriter(out_dir, loaded, camera, optics=optics, profile=profile, threads=threads) as writer:
        writer.submit(result)
        return writer.finish()


def _optics_document(optics: Any) -> dict[str, float]:
    return {
        "focal_length_mm": float(optics.focal_length_mm),
        "sensor_distance_mm": float(optics.sensor_distance_mm),
        "filter_centre_distance_mm": float(optics.filter_centre_distance_mm),
        "focus_distance_mm": float(optics.focus_distance_mm),
        "pixel_pitch_mm": float(optics.pixel_pitch_mm),
    }


def ordered_layers(result: DepthResult) -> list:
    """The multi-plane images front to back: by their region's occlusion order, then by disparity."""
    order = {region.id: region.order for region in result.regions}
    return sorted(result.layers, key=lambda layer: (order.get(layer.region_id, len(order)), layer.disparity_px))


def result_document(
    input_path: Path,
    profile: CameraProfile,
    result: DepthResult,
    loaded: LoadedInput,
    optics: Any,
    written: list[str],
    timings_s: dict[str, float],
    *,
    quality: str = "full",
) -> dict[str, Any]:
    """The content of result.json (see docs/outputs.md); region pixels are counted at input resolution.

    `settings` names the quality setting and the pipeline parameters it stands for."""
    counts = label_pixels_input(
        result.labels,
        loaded.pixel_scale,
        loaded.input_size_px,
        minlength=max([r.id for r in result.regions], default=0) + 1,
    )
    layer_names = {
        layer.region_id: f"layers/{i:02d}.png" for i, layer in reversed(list(enumerate(ordered_layers(result))))
    }
    regions = []
    for region in sorted(result.regions, key=lambda r: r.id):
        regions.append(
            {
                "id": int(region.id),
                "pixels": int(counts[region.id]),
                "order": int(region.order),
                "occludes": [int(i) for i in region.occludes],
                "disparity_px": _number(region.disparity_px),
                "inter_image_depth_mm": _number(region.inter_image_depth_mm),
                "inter_object_depth_mm": _number(region.inter_object_depth_mm),
                "distance_mm": _number(region.distance_mm),
                "slant": None if region.slant is None else {"plane": [float(v) for v in region.slant]},
                "in_focus": bool(region.in_focus),
                "confidence": _number(region.confidence),
                "layer": layer_names.get(region.id),
            }
        )
    mode = "distance" if optics is not None and result.depth_mm is not None else "disparity-only"
    camera = api.camera_for(optics, loaded) if mode == "distance" else None
    return {
        "schema_version": RESULT_SCHEMA_VERSION,
        "software": software(),
        "input": str(input_path),
        "profile": profile.name,
        "settings": {
            "quality": quality,
            "pipeline_params": outputs.json_safe(dataclasses.asdict(api.pipeline_params(quality))),
        },
        "focus_region": None if result.focus_region is None else int(result.focus_region),
        "regions": regions,
        "timings_s": {k: round(float(v), 6) for k, v in timings_s.items()},
        "status": "done",
        "notes": [note] if (note := api.pitch_note(profile, loaded)) is not None else [],
        "mode": mode,
        "units": {
            "depth.tiff": "mm from the lens along the optical axis, NaN unknown"
            + (" (all NaN: no lens data)" if mode == "disparity-only" else ""),
            "disparity_px": "input-image pixels between the widest filter pair, + = farther than focus",
            "distance_mm": "mm from the lens",
            "inter_image_depth_mm": "mm, image side (eq. 2)",
            "inter_object_depth_mm": "mm from the focus plane, object side (eqs. 13/14)",
            "scene": SCENE_FRAME + " (scene.ply, scene.glb, the recording's world)",
        },
        "input_size_px": list(loaded.input_size_px),
        "pixel_pitch_source": "file" if loaded.pixel_pitch_mm is not None else "profile",
        "processing_size_px": [int(result.labels.shape[1]), int(result.labels.shape[0])],
        "pixel_scale": float(result.pixel_scale),
        "pixel_pitch_mm": None if optics is None else float(optics.pixel_pitch_mm),
        "optics": None
        if optics is None
        else {
            "focal_length_mm": float(optics.focal_length_mm),
            "sensor_distance_mm": float(optics.sensor_distance_mm),
            "filter_centre_distance_mm": float(optics.filter_centre_distance_mm),
            "focus_distance_mm": float(optics.focus_distance_mm),
        },
        "camera": None if camera is None else camera.describe(),
        "colour": loaded.colour.as_dict(),
        "lateral_colour": {k: round(v, 4) for k, v in result.lateral_colour.describe().items()},
        "layers_order": LAYER_ORDER,
        "capture": outputs.json_safe(loaded.metadata),
        "outputs": written + [RESULT_NAME],
    }


# --- the unit of work -----------------------------------------------------------------------------------------------


def _optics_for(profile: CameraProfile, loaded: LoadedInput):
    """MCAOptics in input-image pixels, or None when the profile has no lens data (see `api.optics_for`)."""
    return api.optics_for(profile, loaded)


_kernels_loading = threading.Lock()
_kernels_thread: threading.Thread | None = None


def _load_kernels_once(profile: CameraProfile, quality: str) -> None:
    """The first time in this process: load the pipeline's compiled kernels (`processing.pipeline.load_kernels`)
    on a daemon thread, so that they load while the first photograph is being read (about half a second
    saved on a one-file `mca process`; a 20 MP CR2's read takes longer than the warm-up). A failure there
    costs nothing: the pipeline loads what it needs. `_wait_for_kernels` waits for it before any pipeline runs."""
    global _kernels_thread
    with _kernels_loading:
        if _kernels_thread is not None:
            return
        _kernels_thread = threading.Thread(target=lambda: _load_kernels(profile, quality), name="mca-load-kernels")
        _kernels_thread.daemon = True
        _kernels_thread.start()


def _wait_for_kernels() -> None:
    """Until the helper of `_load_kernels_once` is done (at once when there is none or it is finished)."""
    thread = _kernels_thread
    if thread is not None:
        thread.join()


def _load_kernels(profile: CameraProfile, quality: str) -> None:
    """The helper's work: `load_kernels` with the profile's aperture, optics (at its own pixel pitch) and
    `quality`."""
    from mca.processing.optics import MCAOptics
    from mca.processing.pipeline import load_kernels

    try:
        optics = None
        if profile.lens is not None and profile.pixel_pitch_mm is not None:
            optics = MCAOptics.from_profile(profile, pixel_pitch_mm=profile.pixel_pitch_mm)
        load_kernels(profile.aperture, optics, quality)
    except Exception:  # only a head start: the pipeline itself reports whatever is really wrong
        pass


def _default_pipeline() -> PipelineFunction:
    from mca.processing.pipeline import run_pipeline

    return run_pipeline


StageCallback = Callable[[str], None]
# What a file goes through, in order: the pipeline's stages (processing/pipeline.py) between reading and writing.
STAGES = (
    "read",
    "planes",
    "disparity",
    "surfaces",
    "sketch",
    "refine",
    "boundaries",
    "depth",
    "all_in_focus",
    "mpi",
    "write",
)


def _announce(on_stage: StageCallback | None, stage: str) -> None:
    """Tell a progress display that `stage` finished; a broken display never fails a file."""
    if on_stage is not None:
        with contextlib.suppress(Exception):
            on_stage(stage)


class _StageTimer:
    """Forwards to a recorder, remembers each stage's timing and announces it to a progress display."""

    def __init__(
        self,
        inner: Any = None,
        on_stage: StageCallback | None = None,
        on_record: Callable[[str, dict[str, Any]], None] | None = None,
    ) -> None:
        self.inner = inner
        self.on_stage = on_stage
        self.on_record = on_record  # e.g. `OutputWriter.on_record`: starts files as their data is ready
        self.timings_s: dict[str, float] = {}

    def record(self, stage: str, **items: Any) -> None:
        if self.on_record is not None:
            self.on_record(stage, items)
        if self.inner is not None:
            self.inner.record(stage, **items)

    def timing(self, stage: str, seconds: float) -> None:
        self.timings_s[stage] = float(seconds)
        if stage in STAGES:
            _announce(self.on_stage, stage)
        if self.inner is not None:
            self.inner.timing(stage, seconds)


def output_dir_for(input_path: Path, out_root: Path, out_name: str | None = None) -> Path:
    """The folder an input is planned to get: OUT/<safe name>; `process_file` may pick `<name>-2`, ... when that
    name belongs to a different photograph (the outcome says where the outputs went)."""
    name = output_folders.safe_folder_name(out_name) if out_name else output_folders.output_name_for(input_path)
    return Path(out_root) / name


def is_finished(out_dir: Path) -> bool:
    """An output folder is finished when its result.json exists (it is written last)."""
    return (out_dir / RESULT_NAME).is_file()


def settings_key(profile: CameraProfile, quality: str = "full") -> str:
    """sha256 of what decides the outputs besides the photograph: the profile's values, the quality setting
    (`--quality`: a preview result never stands for a full one, nor the other way round) and result.json's
    `schema_version` (raising it makes reruns redo finished folders).

    The version of mca is not part of it: after an upgrade, `--force` recomputes finished folders.
    """
    described = dataclasses.asdict(profile)
    described.pop("source", None)  # where the profile file lies does not change the result
    payload: dict[str, Any] = {"format": RESULT_SCHEMA_VERSION, "profile": outputs.json_safe(described)}
    if api.check_quality(quality) != "full":  # "full" keeps the key results had before --quality existed
        payload["quality"] = quality
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode("utf-8")).hexdigest()


def _unchanged_reason(
    document: dict[str, Any] | None,
    source: output_folders.SourceId,
    key: str,
    profile: CameraProfile,
    folder: Path,
    quality: str = "full",
) -> str | None:
    """Why the finished result in `folder` can stand for this input, or None when it must be made again."""
    if document is None:
        return None
    settings = document.get("settings")
    recorded_quality = settings.get("quality", "full") if isinstance(settings, dict) else "full"
    if recorded_quality != quality:  # also guards results whose key predates --quality
        return None
    recorded = document.get("source")
    if isinstance(recorded, dict):
        if recorded.get("sha256") == source.sha256 and document.get("settings_sha256") == key:
            return "already finished for this photograph and settings; use --force to redo"
        return None
    try:  # a result.json of an earlier mca names no content: trust it while the input is older and the profile same
        written_ns = (folder / RESULT_NAME).stat().st_mtime_ns
    except OSError:
        return None
    if document.get("profile") == profile.name and source.mtime_ns <= written_ns:
        return "already finished (by an earlier mca, same profile, input unchanged since); use --force to redo"
    return None


def _stamp_result(path: Path, source: output_folders.SourceId, key: str) -> None:
    """Add what the result was made from to result.json: the input's resolved path, sha256 and size, the settings."""
    document = json.loads(path.read_text(encoding="utf-8"))
    document["source"] = {"path": source.path, "sha256": source.sha256, "size_bytes": source.size_bytes}
    document["settings_sha256"] = key
    outputs.write_json(path, document)


_OPENCV_TEXT = re.compile(r"in function '([^']+)'")


def user_message(input_path: Path, exc: BaseException) -> str:
    """What to tell the user about a failed file: the file, the cause in words, what to do; never a raw
    library assertion."""
    try:
        import cv2

        opencv_error: type[BaseException] | None = cv2.error
    except ImportError:  # pragma: no cover
        opencv_error = None
    if opencv_error is not None and isinstance(exc, opencv_error):
        match = _OPENCV_TEXT.search(str(exc))
        where = f" (in {match.group(1)})" if match else ""
        return (
            f"{input_path}: an image operation failed inside OpenCV{where}; the image may be damaged, too small or "
            "of an unusual shape. Check that it opens in an image viewer; if it does, report this file"
        )
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        where = f" ({exc.filename})" if exc.filename else ""
        return (
            f"{input_path}: the disk is full{where}; nothing finished was lost (the previous result, if any, is "
            "kept). Free some space and rerun"
        )
    if isinstance(exc, MemoryError):
        return f"{input_path}: ran out of memory; process it with fewer --workers or on a machine with more memory"
    if isinstance(exc, OSError) and exc.strerror:
        where = f": {exc.filename}" if exc.filename else ""
        return f"{input_path}: {exc.strerror}{where}"
    message = str(exc) or type(exc).__name__
    if str(input_path) not in message:
        message = f"{input_path}: {type(exc).__name__}: {message}"
    return message


def _staged_record_path(record_path: str | Path | None, planned: Path, final: Path, staging: Path) -> str | Path | None:
    """A per-file recording meant for the output folder is written into the staging folder with the rest."""
    if record_path is None:
        return None
    parent = os.path.realpath(Path(record_path).parent)
    if parent in (os.path.realpath(planned), os.path.realpath(final)):
        return staging / Path(record_path).name
    return record_path


def process_file(
    input_path: str | Path,
    out_root: str | Path,
    profile: CameraProfile,
    *,
    force: bool = False,
    record_path: str | Path | None = None,
    out_name: str | None = None,
    pipeline: PipelineFunction | None = None,
    on_stage: StageCallback | None = None,
    shot_index: int = 0,
    recording_id: str | None = None,
    recorder: Any = None,
    max_megapixels: float | None = None,
    quality: str = "full",
    reader: Callable[[Path], LoadedInput] | None = None,
) -> FileOutcome:
    """Process one photograph into `out_root/<name>/`; never raises for a bad file.

    <name> is the input's stem made safe (or `out_name`), or `<name>-2`, ... when that folder holds
    the result of a different photograph. A folder already holding the result of this photograph
    (same content) with the same settings is skipped unless `force`; otherwise the outputs are
    written into a hidden staging folder and swapped in when complete, so a failure leaves the
    previous result in place. One run at a time works on a folder: another waits for it.
    Non-regular files (FIFOs, devices) are skipped; images that cannot be an MCA photograph
    or exceed `max_megapixels` (default `capture.raw.default_max_megapixels()`) fail with the reason.

    With `record_path`, records the shot with the rerun recorder into that .rrd file, as shot
    number `shot_index` of the recording `recording_id` (files of one batch share it, so their
    merged recording is one timeline of shots). A live `recorder` (a
    `capture.recording.RerunRecorder` kept open by the caller, e.g. one serving a viewer or a
    tethered session) is used instead and left open. `pipeline` replaces
    `processing.pipeline.run_pipeline` (tests); `on_stage(name)` is called as each of `STAGES` finishes.
    `quality` ("full" or "preview", `capture.api.QUALITIES`) picks the pipeline's parameters; it is part of
    the settings key and of result.json's `settings`, so a preview result never passes for a full one.
    `reader` replaces `read_input` (a batch's `capture.read_ahead.ReadAhead.read`, which gives the same planes).
    """
    started = time.perf_counter()
    api.check_quality(quality)
    input_path = Path(input_path)
    planned = output_dir_for(input_path, Path(out_root), out_name)

    def outcome(status: str, out_dir: Path = planned, **fields: Any) -> FileOutcome:
        return FileOutcome(input_path, status, out_dir, time.perf_counter() - started, **fields)

    try:
        source = output_folders.source_identity(input_path)
    except NotARegularFileError as exc:
        return outcome("skipped", reason=str(exc))
    except OSError as exc:
        try:  # read_raw's checks say what is wrong with the file in words
            read_raw(input_path)
        except RawReadError as described:
            return outcome("failed", reason=str(described))
        except Exception:
            pass
        return outcome("failed", reason=user_message(input_path, exc))
    out_dir = planned
    try:
        root = output_folders.prepare_root(out_root)
        with output_folders.claim_folder(root, planned.name, source) as claim:
            out_dir = claim.final
            if not force:
                key = settings_key(profile, quality)
                finished = _unchanged_reason(claim.existing_result(), source, key, profile, out_dir, quality)
                if finished is not None:
                    return outcome("skipped", out_dir, reason=finished)
            staging = claim.staging_path()
            try:
                staging.mkdir()
                with read_policy(max_megapixels=max_megapixels, photograph=True):
                    regions, notes = _process(
                        input_path,
                        staging,
                        profile,
                        _staged_record_path(record_path, planned, out_dir, staging),
                        pipeline,
                        on_stage,
                        shot_index=shot_index,
                        recording_id=recording_id,
                        live_recorder=recorder,
                        quality=quality,
                        reader=reader,
                    )
                _stamp_result(staging / RESULT_NAME, source, settings_key(profile, quality))
                claim.commit(staging)
            finally:
                claim.discard(staging)  # gone after a commit; after a failure the previous result stays
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # one bad file must never stop a batch: report it, keep going
        return outcome("failed", out_dir, reason=user_message(input_path, exc))
    return outcome("done", out_dir, regions=regions, notes=notes)


def _process(
    input_path: Path,
    out_dir: Path,
    profile: CameraProfile,
    record_path: str | Path | None,
    pipeline: PipelineFunction | None,
    on_stage: StageCallback | None,
    *,
    shot_index: int = 0,
    recording_id: str | None = None,
    live_recorder: Any = None,
    quality: str = "full",
    reader: Callable[[Path], LoadedInput] | None = None,
) -> tuple[int, tuple[str, ...]]:
    run = pipeline or _default_pipeline()
    if pipeline is None:
        _load_kernels_once(profile, quality)  # on a helper thread, while the photograph is read
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    loaded = (reader or read_input)(input_path)
    timings["read"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _wait_for_kernels()  # never two parallel kernels at once: numba's fallback thread pool cannot take it
    if pipeline is None:
        timings["kernels"] = time.perf_counter() - t0  # what the warm-up adds once the photograph is read
    _announce(on_stage, "read")
    optics = _optics_for(profile, loaded)
    camera = api.camera_for(optics, loaded)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / RESULT_NAME).unlink(missing_ok=True)  # unfinished from here until the new one lands
    _clean_folder(out_dir)

    with contextlib.ExitStack() as stack:
        # first in, last out: leaving waits for every file, also when the pipeline or the recording fails
        writer = stack.enter_context(OutputWriter(out_dir, loaded, camera, optics=optics, profile=profile))
        recorder = live_recorder
        if recorder is None and record_path is not None:
            from mca.capture.recording import RerunRecorder

            Path(record_path).parent.mkdir(parents=True, exist_ok=True)
            recorder = RerunRecorder(Path(record_path), application_id="mca", recording_id=recording_id)
            stack.callback(recorder.close)
        if recorder is not None:
            recorder.begin_shot(shot_index, input_path.stem, _capture_time(loaded.metadata), profile)
            recorder.log_input(loaded.frame)
        timer = _StageTimer(recorder, on_stage, on_record=writer.on_record)
        t0 = time.perf_counter()
        result = api.run_depth(
            loaded, profile, optics=optics, pipeline=run, recorder=timer, quality=quality
        )  # the Python API's path
        timings.update(timer.timings_s)
        timings.update({k: float(v) for k, v in (result.timings_s or {}).items()})
        timings["pipeline"] = time.perf_counter() - t0
        writer.submit(result)  # the files encode on the writer threads while the recording logs the result
        if recorder is not None:
            t0 = time.perf_counter()
            recorder.log_result(result, profile, optics)
            timings["record"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        written = writer.finish()
        if record_path is not None and Path(record_path).parent == out_dir:
            written.append(Path(record_path).name)
        timings["write"] = time.perf_counter() - t0  # waiting for the files once the pipeline (and recording) ended
        timings.update({f"write {name}": seconds for name, seconds in writer.seconds.items()})
    _announce(on_stage, "write")
    document = result_document(input_path, profile, result, loaded, optics, written, timings, quality=quality)
    outputs.write_json(out_dir / RESULT_NAME, document)
    return len(result.regions), tuple(document["notes"])


__all__ = [
    "RESULT_NAME",
    "SUPPORTED_SUFFIXES",
    "FileOutcome",
    "LoadedInput",
    "Pinhole",
    "is_finished",
    "output_dir_for",
    "process_file",
    "read_input",
    "scene_points",
    "settings_key",
    "upsample_nearest",
    "user_message",
]
