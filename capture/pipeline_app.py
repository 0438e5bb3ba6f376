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
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.capture import output_folders, outputs
from mca.capture.raw import (
    IMAGE_EXTENSIONS,
    RAW_EXTENSIONS,
    NotARegularFileError,
    RawFrame,
    RawReadError,
    read_policy,
    read_raw,
)
from mca.processing.camera import CameraProfile
from mca.processing.result import DepthResult

SUPPORTED_SUFFIXES = frozenset(RAW_EXTENSIONS) | frozenset(IMAGE_EXTENSIONS)  # what `read_raw` reads
RESULT_NAME = output_folders.RESULT_NAME
RECORDING_NAME = "recording.rrd"
RESULTS_FORMAT = 1  # part of the settings key: raise it when the outputs change, to redo finished folders
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


@dataclass
class LoadedInput:
    """An input file ready for the pipeline."""

    frame: RawFrame  # what the recorder logs
    planes: np.ndarray  # (H, W, 3) float32 linear RGB at processing resolution
    pixel_scale: float  # input-image pixels per processing pixel
    input_size_px: tuple[int, int]  # (width, height) of the input image
    pixel_pitch_mm: float | None  # pitch of one input-image pixel, when known
    metadata: dict[str, Any]


# --- reading --------------------------------------------------------------------------------------------------------


DOWNSCALED_RAW_RATIO = 1.5  # a raw this much narrower than its body's active area is a downscaled one


def input_pixel_pitch_mm(frame: RawFrame, input_width_px: int) -> float | None:
    """Pitch of one input-image pixel on the sensor, when the file says which body took it.

    A raw carries its body's photosite pitch; but a raw far narrower than that body's sensor
    (Canon mRAW/sRAW, the simulator's `--size small`) spans the same sensor with fewer, larger
    pixels, so its pitch is the sensor width over its width, as for RGB images.
    """
    scale = 2.0 if frame.half_resolution else 1.0
    pitch = frame.pixel_pitch_mm / scale if frame.pixel_pitch_mm else None
    if frame.half_resolution and pitch is not None:
        from mca.capture.sensors import sensor_for

        spec = sensor_for(frame.metadata.model, frame.metadata.make)
        if spec is not None and spec.width_px >= DOWNSCALED_RAW_RATIO * input_width_px:
            pitch = spec.width_mm / input_width_px
    return pitch


def read_input(path: Path) -> LoadedInput:
    """Read any photograph `read_raw` reads; Bayer raws give half-resolution planes (pixel_scale 2).

    Raises `capture.raw.RawReadError` naming the file when it cannot be read.
    """
    frame = read_raw(path)
    planes = np.asarray(frame.planes, dtype=np.float32)
    height, width = planes.shape[:2]
    scale = 2.0 if frame.half_resolution else 1.0
    size = (int(round(width * scale)), int(round(height * scale)))
    return LoadedInput(
        frame=frame,
        planes=planes,
        pixel_scale=scale,
        input_size_px=size,
        pixel_pitch_mm=input_pixel_pitch_mm(frame, size[0]),
        metadata=dataclasses.asdict(frame.metadata),
    )


def bayer_channel_offsets_px(cfa_pattern: str | None) -> tuple[tuple[float, float], ...] | None:
    """(dx, dy) of the R, G, B samples from the centre of their 2x2 block, in half-resolution pixels.

    `cfa_pattern` names the colours of the top-left 2x2 row by row ("RGGB" gives red at (-0.25, -0.25),
    the mean of the greens at the centre, blue at (+0.25, +0.25)); None when it is not a Bayer pattern.
    """
    if not cfa_pattern or sorted(cfa_pattern.upper()) != ["B", "G", "G", "R"]:
        return None
    sites: dict[str, list[tuple[int, int]]] = {"R": [], "G": [], "B": []}
    for index, letter in enumerate(cfa_pattern.upper()):
        sites[letter].append((index % 2, index // 2))
    return tuple(
        (float(np.mean([x for x, _ in sites[c]]) - 0.5) / 2.0, float(np.mean([y for _, y in sites[c]]) - 0.5) / 2.0)
        for c in "RGB"
    )


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
    rows = np.minimum(((np.arange(size_px[1]) + 0.5) / pixel_scale).astype(np.intp), height - 1)
    cols = np.minimum(((np.arange(size_px[0]) + 0.5) / pixel_scale).astype(np.intp), width - 1)
    return array[rows[:, None], cols[None, :]]


@dataclass(frozen=True)
class Pinhole:
    """Back-projection of input-image pixels: x = (u - cx) * pitch * Z / d_ls (camera frame, x right, y down, mm)."""

    pixel_pitch_mm: float  # pitch of one input-image pixel
    sensor_distance_mm: float  # the paper's d_ls
    width_px: int
    height_px: int

    @property
    def centre_px(self) -> tuple[float, float]:
        """Principal point: the image centre, in pixel-centre coordinates."""
        return ((self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0)

    def back_project(self, u_px: np.ndarray, v_px: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points in mm for pixel coordinates and distances along the optical axis."""
        cx, cy = self.centre_px
        scale = self.pixel_pitch_mm / self.sensor_distance_mm
        return np.stack([(u_px - cx) * scale * z_mm, (v_px - cy) * scale * z_mm, z_mm], axis=-1)


def scene_points(
    depth_mm: np.ndarray,
    colours_rgb8: np.ndarray,
    pixel_scale: float,
    camera: Pinhole,
    max_points: int = MAX_PLY_POINTS,
) -> tuple[np.ndarray, np.ndarray]:
    """Coloured camera-frame points of every known-depth pixel, on a regular stride so at most `max_points`."""
    valid = np.isfinite(depth_mm) & (depth_mm > 0)
    stride = max(1, math.ceil(math.sqrt(int(valid.sum()) / max_points)))
    while int(valid[::stride, ::stride].sum()) > max_points:
        stride += 1
    sub = valid[::stride, ::stride]
    rows, cols = np.nonzero(sub)
    rows, cols = rows * stride, cols * stride
    u = (cols + 0.5) * pixel_scale - 0.5  # pixel centres in input-image coordinates
    v = (rows + 0.5) * pixel_scale - 0.5
    points = camera.back_project(u, v, depth_mm[rows, cols].astype(np.float64))
    return points.astype(np.float32), colours_rgb8[rows, cols]


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


def _layer_rgba8(layer: Any, srgb8_of: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """A layer (premultiplied linear RGB, alpha in [0, 1]) as 8-bit sRGB with 8-bit alpha.

    Only the bounding box of the layer's non-zero pixels is converted; outside it every byte is 0,
    as the conversion gives for 0. A layer the pipeline built lazily from a (display image, labels)
    source (`processing.result.MultiPlaneImage.rgba`: display x mask, alpha = mask) takes its colours
    from the display image converted once for all layers (`srgb8_of`, cached by the caller), instead
    of a full-size float RGBA array per layer; sRGB of display x 1 is sRGB of display, of x 0 is 0.
    """
    source = layer.lazy_source
    if source is not None:
        display, labels = source
        mask = np.asarray(labels) == layer.region_id
        out = np.zeros(mask.shape + (4,), np.uint8)
        box = _box_of(mask)
        if box is not None:
            inside, sub = out[box], mask[box]
            np.copyto(inside[..., :3], srgb8_of(display)[box], where=sub[..., None])
            inside[..., 3] = sub.view(np.uint8) * np.uint8(255)
        return out
    rgba = np.asarray(layer.rgba)
    out = np.zeros(rgba.shape[:2] + (4,), np.uint8)
    box = _box_of((rgba != 0).any(axis=2))
    if box is not None:
        crop = rgba[box]
        out[box][..., :3] = outputs.linear_to_srgb8(crop[..., :3])
        out[box][..., 3] = _alpha8(crop[..., 3])
    return out


def region_boxes(labels: np.ndarray) -> list[tuple[slice, slice] | None]:
    """Bounding boxes of the regions: boxes[id - 1] bounds region id (None when it has no pixel)."""
    from scipy import ndimage

    return ndimage.find_objects(np.asarray(labels).astype(np.int32, copy=False))


def region_quads(
    result: DepthResult,
    textures_png: dict[int, bytes],
    all_in_focus8: np.ndarray,
    camera: Pinhole,
    boxes: list[tuple[slice, slice] | None] | None = None,
) -> list[outputs.TexturedQuad]:
    """One quad per region with a distance, front to back: its bounding box back-projected at its distance.

    `textures_png[id]` is the region's layer cropped to its box, as PNG; a region without one is
    textured with the all-in-focus image under its mask.
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
        # pixel edges in input-image coordinates; the centre of pixel u sits at edge u + 0.5
        left, right = c0 * result.pixel_scale - 0.5, c1 * result.pixel_scale - 0.5
        top, bottom = r0 * result.pixel_scale - 0.5, r1 * result.pixel_scale - 0.5
        u = np.array([left, right, right, left])
        v = np.array([top, top, bottom, bottom])
        corners = camera.back_project(u, v, np.full(4, float(z)))
        quads.append(
            outputs.TexturedQuad(
                name=f"region {region.id}",
                corners_mm=corners,
                texture_png=texture,
                extras={"region_id": region.id, "order": region.order, "distance_mm": float(z)},
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


def write_outputs(
    out_dir: Path,
    result: DepthResult,
    loaded: LoadedInput,
    labels_input: np.ndarray,
    camera: Pinhole | None,
    *,
    threads: int = WRITE_THREADS,
) -> list[str]:
    """Write every output except result.json; returns their names relative to `out_dir`.

    `labels_input` is the region map at input resolution; `camera` is None in disparity-only mode.
    Independent files are encoded and written by `threads` worker threads; every file's bytes are
    the same whatever the number of threads or the order they finish in.
    """
    from concurrent.futures import Future, ThreadPoolExecutor

    size = loaded.input_size_px
    scale = result.pixel_scale
    with_scene = camera is not None and result.depth_mm is not None
    layers = ordered_layers(result)
    boxes = region_boxes(result.labels) if with_scene else []
    textured: set[int] = set()  # the first layer of a region textures its quad in the GLB

    with ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix="mca-write") as pool:
        # Tasks run first in, first out, and a task only waits for ones submitted before it: no deadlock.
        conversions: dict[int, Future] = {}

        def srgb8_of(linear: np.ndarray) -> np.ndarray:
            return conversions[id(linear)].result()

        def convert(linear: np.ndarray) -> None:
            if id(linear) not in conversions:
                conversions[id(linear)] = pool.submit(outputs.linear_to_srgb8, linear)

        convert(result.all_in_focus)
        for layer in layers:
            if layer.lazy_source is not None:
                convert(layer.lazy_source[0])

        def write_depth() -> list[Path]:
            written = []
            if with_scene:
                depth = np.asarray(result.depth_mm, dtype=np.float32)
            else:
                depth = np.full(result.labels.shape, np.nan, dtype=np.float32)
                written.append(
                    outputs.write_tiff_float32(
                        out_dir / "disparity.tiff",
                        upsample_nearest(np.asarray(result.disparity_px, np.float32), scale, size),
                    )
                )
            written.append(outputs.write_tiff_float32(out_dir / "depth.tiff", upsample_nearest(depth, scale, size)))
            return written

        def write_layer(index: int, layer: Any, box: tuple[slice, slice] | None) -> tuple[Path, bytes | None]:
            rgba8 = _layer_rgba8(layer, srgb8_of)
            png = outputs.encode_png(rgba8)
            path = outputs.write_bytes_atomic(out_dir / "layers" / f"{index:02d}.png", png)
            if box is None:
                return path, None
            crop = rgba8[box]
            return path, png if crop.shape == rgba8.shape else outputs.encode_png(crop)  # a full-frame box: same PNG

        def write_scene_ply() -> Path:
            depth = np.asarray(result.depth_mm, dtype=np.float32)
            points, colours = scene_points(depth, srgb8_of(result.all_in_focus), scale, camera)
            return outputs.write_ply(
                out_dir / "scene.ply",
                points,
                colours,
                comments=("mca-appliance scene: camera frame, x right, y down, z along the optical axis, millimetres",),
            )

        # the longest tasks first, so that neither thread is left with a long one at the end
        all_in_focus_task = pool.submit(
            lambda: outputs.write_png(out_dir / "all_in_focus.png", srgb8_of(result.all_in_focus))
        )
        regions_task = pool.submit(outputs.write_png, out_dir / "regions.png", labels_input.astype(np.uint16))
        depth_task = pool.submit(write_depth)
        layer_tasks = []
        for index, layer in enumerate(layers):
            box = None
            if with_scene and layer.region_id not in textured and 0 < layer.region_id <= len(boxes):
                textured.add(layer.region_id)
                box = boxes[layer.region_id - 1]
            layer_tasks.append((layer.region_id, pool.submit(write_layer, index, layer, box)))
        ply_task = pool.submit(write_scene_ply) if with_scene else None

        paths: list[Path] = depth_task.result() + [regions_task.result(), all_in_focus_task.result()]
        textures: dict[int, bytes] = {}
        for region_id, task in layer_tasks:
            path, texture = task.result()
            paths.append(path)
            if texture is not None:
                textures[region_id] = texture
        if with_scene:
            paths.append(ply_task.result())
            quads = region_quads(result, textures, srgb8_of(result.all_in_focus), camera, boxes)
            paths.append(outputs.write_glb(out_dir / "scene.glb", quads))
    return [path.relative_to(out_dir).as_posix() for path in paths]


def ordered_layers(result: DepthResult) -> list:
    """The multi-plane images front to back: by their region's occlusion order, then by disparity."""
    order = {region.id: region.order for region in result.regions}
    return sorted(result.layers, key=lambda layer: (order.get(layer.region_id, len(order)), layer.disparity_px))


def result_document(
    input_path: Path,
    profile: CameraProfile,
    result: DepthResult,
    loaded: LoadedInput,
    labels_input: np.ndarray,
    optics: Any,
    written: list[str],
    timings_s: dict[str, float],
) -> dict[str, Any]:
    """The content of result.json (see docs/outputs.md); region pixels are counted at input resolution."""
    counts = np.bincount(
        labels_input.ravel().astype(np.intp), minlength=max([r.id for r in result.regions], default=0) + 1
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
    return {
        "input": str(input_path),
        "profile": profile.name,
        "focus_region": None if result.focus_region is None else int(result.focus_region),
        "regions": regions,
        "timings_s": {k: round(float(v), 6) for k, v in timings_s.items()},
        "status": "done",
        "mode": mode,
        "units": {
            "depth.tiff": "mm from the lens along the optical axis, NaN unknown"
            + (" (all NaN: no lens data)" if mode == "disparity-only" else ""),
            "disparity_px": "input-image pixels between the widest filter pair, + = farther than focus",
            "distance_mm": "mm from the lens",
            "inter_image_depth_mm": "mm, image side (eq. 2)",
            "inter_object_depth_mm": "mm from the focus plane, object side (eqs. 13/14)",
            "scene": "camera frame, x right, y down, z forward, mm",
        },
        "input_size_px": list(loaded.input_size_px),
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
        "layers_order": LAYER_ORDER,
        "capture": outputs.json_safe(loaded.metadata),
        "outputs": written + [RESULT_NAME],
    }


# --- the unit of work -----------------------------------------------------------------------------------------------


def _optics_for(profile: CameraProfile, loaded: LoadedInput):
    """MCAOptics in input-image pixels, or None when the profile has no lens data (disparity-only results)."""
    if profile.lens is None:
        return None
    pitch = loaded.pixel_pitch_mm or profile.pixel_pitch_mm
    if pitch is None:
        return None
    from mca.processing.optics import MCAOptics

    return MCAOptics.from_profile(profile, pixel_pitch_mm=pitch)


def _default_pipeline() -> PipelineFunction:
    from mca.processing.pipeline import run_pipeline

    return run_pipeline


StageCallback = Callable[[str], None]
# What a file goes through, in order: the pipeline's stages (processing/pipeline.py) between reading and writing.
STAGES = ("read", "planes", "disparity", "sketch", "refine", "depth", "all_in_focus", "mpi", "write")


def _announce(on_stage: StageCallback | None, stage: str) -> None:
    """Tell a progress display that `stage` finished; a broken display never fails a file."""
    if on_stage is not None:
        with contextlib.suppress(Exception):
            on_stage(stage)


class _StageTimer:
    """Forwards to a recorder, remembers each stage's timing and announces it to a progress display."""

    def __init__(self, inner: Any = None, on_stage: StageCallback | None = None) -> None:
        self.inner = inner
        self.on_stage = on_stage
        self.timings_s: dict[str, float] = {}

    def record(self, stage: str, **items: Any) -> None:
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


def settings_key(profile: CameraProfile) -> str:
    """sha256 of what decides the outputs besides the photograph: the profile's values and the results format.

    The version of mca is not part of it: after an upgrade, `--force` recomputes finished folders.
    """
    described = dataclasses.asdict(profile)
    described.pop("source", None)  # where the profile file lies does not change the result
    payload = {"format": RESULTS_FORMAT, "profile": outputs.json_safe(described)}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode("utf-8")).hexdigest()


def _unchanged_reason(
    document: dict[str, Any] | None, source: output_folders.SourceId, key: str, profile: CameraProfile, folder: Path
) -> str | None:
    """Why the finished result in `folder` can stand for this input, or None when it must be made again."""
    if document is None:
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
    """
    started = time.perf_counter()
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
        except RawReadError as reason:
            return outcome("failed", reason=str(reason))
        except Exception:
            pass
        return outcome("failed", reason=user_message(input_path, exc))
    out_dir = planned
    try:
        root = output_folders.prepare_root(out_root)
        with output_folders.claim_folder(root, planned.name, source) as claim:
            out_dir = claim.final
            if not force:
                reason = _unchanged_reason(claim.existing_result(), source, settings_key(profile), profile, out_dir)
                if reason is not None:
                    return outcome("skipped", out_dir, reason=reason)
            staging = claim.new_staging()
            try:
                with read_policy(max_megapixels=max_megapixels, photograph=True):
                    regions = _process(
                        input_path,
                        staging,
                        profile,
                        _staged_record_path(record_path, planned, out_dir, staging),
                        pipeline,
                        on_stage,
                        shot_index=shot_index,
                        recording_id=recording_id,
                        live_recorder=recorder,
                    )
                _stamp_result(staging / RESULT_NAME, source, settings_key(profile))
                claim.commit(staging)
            finally:
                claim.discard(staging)  # gone after a commit; after a failure the previous result stays
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # one bad file must never stop a batch: report it, keep going
        return outcome("failed", out_dir, reason=user_message(input_path, exc))
    return outcome("done", out_dir, regions=regions)


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
) -> int:
    run = pipeline or _default_pipeline()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    loaded = read_input(input_path)
    timings["read"] = time.perf_counter() - t0
    _announce(on_stage, "read")
    optics = _optics_for(profile, loaded)

    with contextlib.ExitStack() as stack:
        recorder = live_recorder
        if recorder is None and record_path is not None:
            from mca.capture.recording import RerunRecorder

            Path(record_path).parent.mkdir(parents=True, exist_ok=True)
            recorder = RerunRecorder(Path(record_path), application_id="mca", recording_id=recording_id)
            stack.callback(recorder.close)
        if recorder is not None:
            recorder.begin_shot(shot_index, input_path.stem, _capture_time(loaded.metadata), profile)
            recorder.log_input(loaded.frame)
        timer = _StageTimer(recorder, on_stage)
        t0 = time.perf_counter()
        extra: dict[str, Any] = {}
        if loaded.frame.half_resolution:
            offsets = bayer_channel_offsets_px(loaded.metadata.get("cfa_pattern"))
            if offsets is not None:  # Bayer sample positions are not disparity
                extra["channel_offsets_px"] = offsets
        result = run(loaded.planes, profile.aperture, optics, pixel_scale=loaded.pixel_scale, recorder=timer, **extra)
        timings.update(timer.timings_s)
        timings.update({k: float(v) for k, v in (result.timings_s or {}).items()})
        timings["pipeline"] = time.perf_counter() - t0
        if recorder is not None:
            recorder.log_result(result, profile, optics)

    if not math.isclose(result.pixel_scale, loaded.pixel_scale):
        result = dataclasses.replace(result, pixel_scale=loaded.pixel_scale)
    camera = None
    if optics is not None:
        camera = Pinhole(optics.pixel_pitch_mm, optics.sensor_distance_mm, *loaded.input_size_px)

    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / RESULT_NAME).unlink(missing_ok=True)  # unfinished from here until the new one lands
    _clean_folder(out_dir)
    labels_input = upsample_nearest(np.asarray(result.labels), result.pixel_scale, loaded.input_size_px)
    written = write_outputs(out_dir, result, loaded, labels_input, camera)
    if record_path is not None and Path(record_path).parent == out_dir:
        written.append(Path(record_path).name)
    timings["write"] = time.perf_counter() - t0
    _announce(on_stage, "write")
    document = result_document(input_path, profile, result, loaded, labels_input, optics, written, timings)
    outputs.write_json(out_dir / RESULT_NAME, document)
    return len(result.regions)


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
