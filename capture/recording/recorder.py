"""`RerunRecorder`: every stage of every shot logged into one rerun recording (a file, a local web viewer, or both)."""

from __future__ import annotations

import errno
import math
import re
import shutil
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mca.capture.recording.blueprint import default_blueprint
from mca.capture.recording.display import (
    DISPLAY_MEGAPIXELS,
    MULTI_PLANE_MEGAPIXELS,
    display_size,
    fmt_number,
    front_to_back,
    jpeg,
    layer_rgba_crop,
    layer_windows,
    misalignment_overlay,
    normalised,
    occlusion_order_markdown,
    opaque_window,
    profile_markdown,
    region_colour,
    resize,
    table_cell,
    to_srgb8,
    unpremultiplied_rgba8,
)
from mca.capture.recording.rerun_env import disable_rerun_analytics
from mca.capture.recording.scene import MAX_POINTS, plane_mesh, surface_distance
from mca.capture.recording.serve import ViewerServer, start_viewer_server
from mca.processing.colour import CameraColour
from mca.processing.pinhole import PinholeCamera

if TYPE_CHECKING:
    from mca.processing.camera import CameraProfile
    from mca.processing.optics import MCAOptics
    from mca.processing.result import DepthResult


class RecordingWriteError(OSError):
    """The .rrd file could not be written completely; `str()` names the file, why, and what to do.

    An `OSError` with `errno` ENOSPC when the disk is full (and `filename` the recording), so that the
    application's handlers of a full disk treat it as one.
    """

    def __init__(self, path: Path, error_number: int, message: str) -> None:
        super().__init__(error_number, message, str(path))
        self.path = path
        self.message = message

    def __str__(self) -> str:
        return self.message

    @classmethod
    def from_failure(cls, path: Path, exc: BaseException) -> RecordingWriteError:
        """The error for rerun's failure `exc` writing `path`: a full disk when rerun says so (its file writer
        reports `os error 28`) or when the disk holding the file has (almost) no space left."""
        text = str(exc)
        errno_seen = getattr(exc, "errno", None)
        match = re.search(r"os error (\d+)", text)
        if match:
            errno_seen = int(match.group(1))
        free = _free_bytes(path.parent)
        if errno_seen in (errno.ENOSPC, errno.EDQUOT) or (
            errno_seen is None and free is not None and free < FULL_DISK_BYTES
        ):
            where = f"; {free:,} bytes free" if free is not None else ""
            return cls(
                path,
                errno.ENOSPC,
                f"{path}: the recording could not be written completely: the disk holding it is full{where}. "
                "The file is cut short (rerun opens what it holds); the shot's other results are not affected. "
                "Free some space and run again with --record to record it anew",
            )
        return cls(
            path,
            errno_seen or errno.EIO,
            f"{path}: the recording could not be written completely ({text}). Check that the folder is writable "
            "and its disk healthy, then run again with --record to record it anew",
        )


FULL_DISK_BYTES = 1 << 20  # below a MiB free, a failed write is taken to be a full disk


def _free_bytes(folder: Path) -> int | None:
    try:
        return int(shutil.disk_usage(folder).free)
    except OSError:
        return None


# Items of `processing.pipeline` stages that the recorder shows from the input frame or the DepthResult
# anyway (at display size), so `record` skips them: logging them twice would only cost time and space.
ALREADY_SHOWN = frozenset(
    {
        ("planes", "planes"),  # shot/raw/*, shot/input (log_input)
        ("disparity", "disparity_px"),
        ("disparity", "confidence"),  # shot/disparity/per_pixel, .../confidence
        ("sketch", "aligned"),
        ("sketch", "order"),
        ("sketch", "occludes"),  # shot/channels/after, occlusion_*
        ("depth", "*"),
        ("all_in_focus", "*"),
        ("mpi", "*"),  # shot/segmentation, depth, all_in_focus, multi_plane
    }
)


class RerunRecorder:
    """Records every stage of every shot into one rerun recording: a file, a local web viewer, or both.

    Each recorder owns its `rr.RecordingStream` (no global rerun state), so several coexist.
    `serve=True` starts `rerun --serve-web` bound to `bind` (127.0.0.1 unless told otherwise) and
    streams to it; `viewer_url` then says where to point a browser. Ports left out are 9876 (data)
    and 9090 (web page) when free, else free ones; a port asked for that is in use is an error,
    never a false claim to serve. The server is stopped by `close()`, at interpreter exit, and (on
    Linux) by the kernel when this process dies, even by SIGKILL.
    """

    def __init__(
        self,
        recording_path: Path | None = None,
        *,
        application_id: str = "mca",
        serve: bool = False,
        bind: str = "127.0.0.1",
        grpc_port: int | None = None,
        web_port: int | None = None,
        display_megapixels: float = DISPLAY_MEGAPIXELS,
        recording_id: str | None = None,
    ) -> None:
        if recording_path is None and not serve:
            raise ValueError("RerunRecorder needs a recording path, serve=True, or both")
        disable_rerun_analytics()
        import rerun as rr
        import rerun.blueprint as rrb  # noqa: F401  (fail early if the blueprint API is missing)

        self._rr = rr
        self.recording_path = Path(recording_path) if recording_path is not None else None
        self.display_megapixels = display_megapixels
        self.viewer_url: str | None = None
        self.ports: tuple[int, int] | None = None  # (data, web page) when serving
        self._server: ViewerServer | None = None
        self._stream = rr.RecordingStream(application_id, recording_id=recording_id)
        self._stream.set_log_tick_enabled(False)
        sinks: list[Any] = []
        if self.recording_path is not None:
            self.recording_path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.recording_path)))
        if serve:
            self._server = start_viewer_server(bind, grpc_port, web_port)
            self.viewer_url, self.ports = self._server.viewer_url, self._server.ports
            sinks.append(rr.GrpcSink(self._server.grpc_url))
        try:
            self._stream.set_sinks(*sinks, default_blueprint=default_blueprint())
            self._stream.log("world", rr.ViewCoordinates.RUB, static=True)  # glTF's axes, as scene.ply and .glb
        except (RuntimeError, OSError) as exc:  # the file's header could not be written (a full disk)
            self._stop_server()
            if self.recording_path is None:
                raise
            raise RecordingWriteError.from_failure(self.recording_path, exc) from None
        self._shot_name = ""
        self._shot_time: datetime | None = None
        self._profile: CameraProfile | None = None
        self._display: tuple[int, int] | None = None
        self._input_size: tuple[int, int] | None = None
        self._input_jpeg: Any = None
        self._pitch_mm: float | None = None
        self._colour: CameraColour | None = None
        self._timings: dict[str, float] = {}
        self._closed = False
        self._named = False

    # -- the Recorder protocol -------------------------------------------------------------------------------------

    def record(self, stage: str, **items: Any) -> None:
        """Log what a stage computed under `shot/stages/<stage>/<item>`: images for arrays, scalars for numbers.

        Items that `log_input`/`log_result` show anyway, at display size (`ALREADY_SHOWN`), are not
        logged twice; the sketch's labels go to `shot/segmentation/sketch` (the regions' annotation applies).
        """
        rr = self._rr
        for name, value in items.items():
            if (stage, name) in ALREADY_SHOWN or (stage, "*") in ALREADY_SHOWN:
                continue
            path = f"shot/stages/{stage}/{name}"
            if (stage, name) == ("sketch", "labels") and isinstance(value, np.ndarray) and value.ndim == 2:
                self._stream.log(
                    "shot/segmentation/sketch",
                    rr.SegmentationImage(np.ascontiguousarray(value.astype(np.uint16, copy=False)), opacity=0.6),
                )
            elif isinstance(value, (bool, np.bool_)):
                self._stream.log(path, rr.Scalars(float(value)))
            elif isinstance(value, (int, float, np.integer, np.floating)):
                if math.isfinite(float(value)):
                    self._stream.log(path, rr.Scalars(float(value)))
            elif isinstance(value, str):
                self._stream.log(path, rr.TextDocument(value))
            elif isinstance(value, Mapping) and len(value) <= 4096:
                rows = "\n".join(f"| {k} | {table_cell(v)} |" for k, v in value.items())
                self._stream.log(
                    path, rr.TextDocument(f"| key | value |\n|---|---|\n{rows}\n", media_type=rr.MediaType.MARKDOWN)
                )
            elif isinstance(value, np.ndarray) and value.ndim in (2, 3) and min(value.shape[:2]) > 1:
                self._log_array_image(path, value)
            elif isinstance(value, np.ndarray) and value.size and value.ndim <= 1:
                finite = value[np.isfinite(value)] if value.dtype.kind == "f" else value
                if finite.size == 1:
                    self._stream.log(path, rr.Scalars(float(finite.ravel()[0])))
                elif value.size <= 4096:
                    self._stream.log(path, rr.BarChart(value.astype(np.float64)))

    def timing(self, stage: str, seconds: float) -> None:
        """Log a stage's wall-clock time as the scalar `timings/<stage>` (seconds)."""
        self._timings[stage] = float(seconds)
        self._stream.log(f"timings/{stage}", self._rr.Scalars(float(seconds)))

    # -- the application's calls -----------------------------------------------------------------------------------

    def begin_shot(
        self, shot_index: int, name: str, capture_time: datetime | None, profile: CameraProfile | None
    ) -> None:
        """Start a shot: sets the `shot` and `capture_time` timelines and logs the profile used."""
        rr = self._rr
        self._stream.set_time("shot", sequence=int(shot_index))
        if capture_time is not None:
            stamp = capture_time if capture_time.tzinfo is not None else capture_time.replace(tzinfo=UTC)
            self._stream.set_time("capture_time", timestamp=stamp)
        self._shot_name, self._shot_time, self._profile = name, capture_time, profile
        if not self._named:  # the viewer lists the recording under its first shot's name
            self._stream.send_recording_name(name)
            self._named = True
        self._display = self._input_size = self._input_jpeg = self._colour = None
        self._pitch_mm = profile.pixel_pitch_mm if profile is not None else None
        self._timings = {}
        self._stream.log("shot/profile", rr.TextDocument(profile_markdown(profile), media_type=rr.MediaType.MARKDOWN))

    def log_input(self, frame: Any) -> None:
        """Log the input: the raw colour planes and the image as the camera produced it (both at display size).

        `frame` is a `capture.raw.RawFrame` (or anything with `.planes` (H, W, 3) linear RGB). A Bayer
        raw's planes are at half resolution (`half_resolution`); the input image is shown from them,
        since the display size (about `display_megapixels`) is below even that: demosaicing the full
        frame would cost seconds and show nothing more. Camera RGB is shown through the frame's
        `colour` (as-shot white balance and colour matrix), as every displayed image of the shot.
        """
        planes = np.asarray(frame.planes)
        scale = 2.0 if getattr(frame, "half_resolution", False) else 1.0
        pitch = getattr(frame, "pixel_pitch_mm", None)
        if pitch:
            self._pitch_mm = float(pitch) / scale  # per input-image pixel
        self._input_size = (int(round(planes.shape[1] * scale)), int(round(planes.shape[0] * scale)))
        self._display = display_size(*self._input_size, megapixels=self.display_megapixels)
        small = resize(planes.astype(np.float32, copy=False), self._display)
        self._colour = getattr(frame, "colour", None)
        self._input_jpeg = jpeg(self._rr, to_srgb8(small, self._colour))
        self._stream.log("shot/input", self._input_jpeg)
        for index, channel in enumerate(("red", "green", "blue")):
            self._stream.log(f"shot/raw/{channel}", jpeg(self._rr, to_srgb8(normalised(small[..., index]))))
        self._stream.log("shot/channels/before", jpeg(self._rr, misalignment_overlay(small)))
        meta = getattr(frame, "metadata", None)
        if meta is not None:
            rows = "\n".join(f"| {k} | {v} |" for k, v in _as_mapping(meta).items() if v is not None)
            path = getattr(frame, "path", None)
            self._stream.log(
                "shot/input_metadata",
                self._rr.TextDocument(
                    f"# Input `{path}`\n\n| field | value |\n|---|---|\n{rows}\n",
                    media_type=self._rr.MediaType.MARKDOWN,
                ),
            )

    def log_result(self, result: DepthResult, profile: CameraProfile | None, optics: MCAOptics | None) -> None:
        """Log what the pipeline found: disparity, regions, occlusion order, depth, multi-plane images, the 3D scene."""
        rr = self._rr
        h, w = result.labels.shape
        scale = float(result.pixel_scale)
        input_size = self._input_size or (int(round(w * scale)), int(round(h * scale)))
        display = self._display or display_size(*input_size, megapixels=self.display_megapixels)
        self._display = display

        if self._input_jpeg is None:  # no log_input: show the all-in-focus image as the input
            self._input_jpeg = self._encode_colour(result.all_in_focus)
            self._stream.log("shot/input", self._input_jpeg)
        aif_small = resize(np.asarray(result.all_in_focus, dtype=np.float32), display)
        self._stream.log("shot/all_in_focus", jpeg(rr, to_srgb8(aif_small, self._colour)))
        self._stream.log("shot/channels/after", jpeg(rr, misalignment_overlay(aif_small)))

        for path, array in (
            ("shot/disparity/region_model", result.disparity_px),
            ("shot/disparity/per_pixel", result.raw_disparity_px),
            ("shot/disparity/confidence", result.confidence),
        ):
            self._stream.log(path, rr.Image(np.ascontiguousarray(resize(np.asarray(array, np.float32), display))))

        regions = sorted(result.regions, key=lambda r: r.order)
        infos = [rr.AnnotationInfo(id=0, label="none", color=(0, 0, 0, 0))]
        for region in regions:
            where = (
                f"{region.distance_mm:.0f} mm"
                if region.distance_mm is not None and math.isfinite(region.distance_mm)
                else f"{region.disparity_px:+.2f} px"
            )
            infos.append(
                rr.AnnotationInfo(
                    id=int(region.id),
                    label=f"#{region.id} rank {region.order}: {where}",
                    color=region_colour(region.id),
                )
            )
        self._stream.log("shot/segmentation", rr.AnnotationContext(infos))
        labels = resize(np.ascontiguousarray(result.labels.astype(np.uint16, copy=False)), display, nearest=True)
        self._stream.log("shot/segmentation", rr.SegmentationImage(labels, opacity=0.6))
        self._stream.log(
            "shot/occlusion_order",
            rr.TextDocument(
                f"# Occlusion order of `{self._shot_name}`, front to back\n\n{occlusion_order_markdown(result)}\n",
                media_type=rr.MediaType.MARKDOWN,
            ),
        )
        if regions:
            node_ids = [str(r.id) for r in regions]
            self._stream.log(
                "shot/occlusion_graph",
                rr.GraphNodes(
                    node_ids,
                    labels=[
                        f"#{r.id} {fmt_number(r.distance_mm, 0)} mm"
                        if r.distance_mm is not None
                        else f"#{r.id} {r.disparity_px:+.1f} px"
                        for r in regions
                    ],
                    colors=[region_colour(r.id) for r in regions],
                ),
            )
            edges = [(str(r.id), str(other)) for r in regions for other in r.occludes]
            if edges:
                self._stream.log("shot/occlusion_graph", rr.GraphEdges(edges, graph_type="directed"))

        if result.depth_mm is not None:
            depth = resize(np.asarray(result.depth_mm, dtype=np.float32), display)
            finite = np.isfinite(depth) & (depth > 0)
            depth_mm = np.where(finite, depth, 0.0).astype(np.float32)
            extra: dict[str, Any] = {}
            if finite.any():
                extra["depth_range"] = (float(depth_mm[finite].min()), float(depth_mm[finite].max()))
            self._stream.log("shot/depth", rr.DepthImage(depth_mm, meter=1000.0, colormap="turbo", **extra))

        windows = layer_windows(result)
        self._log_multi_plane(result, windows)

        self._log_scene(result, profile or self._profile, optics, input_size, display, windows)

        for stage, seconds in result.timings_s.items():
            if stage not in self._timings:
                self.timing(stage, seconds)
        self._log_summary(result)

    def _log_scene(
        self,
        result: DepthResult,
        profile: CameraProfile | None,
        optics: MCAOptics | None,
        input_size: tuple[int, int],
        display: tuple[int, int],
        windows: dict[int, tuple[slice, slice]],
    ) -> None:
        """The 3D view in the scene frame of scene.ply and scene.glb: the camera, the point cloud, the planes."""
        rr = self._rr
        pitch = optics.pixel_pitch_mm if optics is not None else self._pitch_mm
        sensor_distance = (
            optics.sensor_distance_mm
            if optics is not None
            else profile.lens.sensor_distance_mm
            if profile is not None and profile.lens
            else None
        )
        if not pitch or not sensor_distance:
            return
        camera = PinholeCamera.from_optics(pitch, sensor_distance, *input_size)
        zoom = display[0] / input_size[0]
        self._stream.log(
            "world/camera",
            rr.Pinhole(
                focal_length=camera.focal_px * zoom,
                width=display[0],
                height=display[1],
                # rerun puts pixel centres at +0.5: the image centre (cx + 0.5) * zoom
                principal_point=(display[0] / 2, display[1] / 2),
                image_plane_distance=0.1,
                camera_xyz=rr.ViewCoordinates.RUB,  # the camera looks down -z with y up, as in glTF
            ),
        )
        if self._input_jpeg is not None:
            self._stream.log("world/camera/image", self._input_jpeg)
        scale = float(result.pixel_scale)

        if result.depth_mm is not None:  # scene.ply's points, on a coarser stride
            points, rows, cols = camera.depth_map_points(result.depth_mm, scale, MAX_POINTS)
            rgb = to_srgb8(np.asarray(result.all_in_focus, dtype=np.float32)[rows, cols], self._colour)
            self._stream.log("world/points", rr.Points3D(points, colors=rgb, radii=rr.Radius.ui_points(2.0)))

        region_by_id = {r.id: r for r in result.regions}
        for index, layer in enumerate(front_to_back(result)):
            region = region_by_id.get(layer.region_id)
            distance_mm = region.distance_mm if region is not None else None
            if (distance_mm is None or not math.isfinite(distance_mm)) and optics is not None:
                distance_mm = float(optics.distance_mm(layer.disparity_px))
            if distance_mm is None or not math.isfinite(distance_mm) or distance_mm <= 0:
                continue
            window = windows.get(layer.region_id) or opaque_window(np.asarray(layer.rgba)[..., 3])
            if window is None:
                continue
            window_rows, window_cols = window
            distance_mm_at = surface_distance(region, distance_mm, optics)
            vertices, triangles, colours = plane_mesh(
                layer_rgba_crop(layer, window),
                distance_mm_at,
                camera,
                scale,
                origin_px=(window_cols.start, window_rows.start),
                full_width_px=result.labels.shape[1],
                colour=self._colour,
            )
            if len(triangles):
                self._stream.log(
                    f"world/planes/{index:02d}",
                    rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles, vertex_colors=colours),
                )

    def _log_multi_plane(self, result: DepthResult, windows: dict[int, tuple[slice, slice]]) -> None:
        """Each multi-plane image cropped to where it is opaque, placed by a 2D translation in a common frame.

        The frame is the processing grid scaled to about `MULTI_PLANE_MEGAPIXELS`; cropping keeps a
        scene of many small regions as cheap as one of a few large ones.
        """
        rr = self._rr
        h, w = result.labels.shape
        frame_w, _ = display_size(w, h, megapixels=MULTI_PLANE_MEGAPIXELS)
        zoom = frame_w / w
        for index, layer in enumerate(front_to_back(result)):
            window = windows.get(layer.region_id) or opaque_window(np.asarray(layer.rgba)[..., 3])
            if window is None:
                continue
            rows, cols = window
            x0, y0 = int(cols.start * zoom), int(rows.start * zoom)
            size = (max(1, int(math.ceil(cols.stop * zoom)) - x0), max(1, int(math.ceil(rows.stop * zoom)) - y0))
            crop = resize(np.ascontiguousarray(layer_rgba_crop(layer, window), dtype=np.float32), size)
            path = f"shot/multi_plane/{index:02d}"
            self._stream.log(path, rr.Transform3D(translation=[float(x0), float(y0), 0.0]))
            self._stream.log(path, rr.Image(unpremultiplied_rgba8(crop, self._colour), color_model="RGBA"))

    def _log_summary(self, result: DepthResult) -> None:
        rr = self._rr
        distances = [
            r.distance_mm for r in result.regions if r.distance_mm is not None and math.isfinite(r.distance_mm)
        ]
        lines = [
            f"# Shot `{self._shot_name}`",
            "",
            f"- capture time: {self._shot_time.isoformat() if self._shot_time else 'unknown'}",
            f"- regions: {len(result.regions)}",
        ]
        if distances:
            lines.append(f"- nearest object: {min(distances):.0f} mm, farthest: {max(distances):.0f} mm")
        if self._timings:
            lines += ["", "| stage | seconds |", "|---|---:|"]
            lines += [f"| {stage} | {seconds:.3f} |" for stage, seconds in self._timings.items()]
            lines.append(f"| **total** | **{sum(self._timings.values()):.3f}** |")
        self._stream.log("shot/summary", rr.TextDocument("\n".join(lines) + "\n", media_type=rr.MediaType.MARKDOWN))

    # -- helpers ---------------------------------------------------------------------------------------------------

    def _encode_colour(self, image: np.ndarray) -> Any:
        """The image at display size as a JPEG archetype (linear float -> sRGB; uint8 kept as encoded)."""
        image = np.asarray(image)
        size = display_size(image.shape[1], image.shape[0], megapixels=self.display_megapixels)
        if self._display is not None:
            size = self._display
        small = resize(image, size)
        if small.ndim == 3 and small.shape[2] == 4:
            small = small[..., :3]
        return jpeg(self._rr, to_srgb8(small, self._colour))

    def _log_array_image(self, path: str, value: np.ndarray) -> None:
        rr = self._rr
        size = display_size(value.shape[1], value.shape[0], megapixels=self.display_megapixels)
        if value.dtype == np.bool_:
            value = value.astype(np.uint8) * 255
        if value.ndim == 2:
            if value.dtype.kind in "iu" and value.dtype.itemsize <= 2 and value.dtype != np.uint8:
                self._stream.log(
                    path, rr.Image(np.ascontiguousarray(resize(value.astype(np.uint16), size, nearest=True)))
                )
            else:
                self._stream.log(path, rr.Image(np.ascontiguousarray(resize(value.astype(np.float32), size))))
        elif value.shape[2] == 3:
            self._stream.log(path, jpeg(rr, to_srgb8(resize(value, size))))
        elif value.shape[2] == 4:
            small = resize(value, size)
            rgba8 = np.concatenate(
                [
                    to_srgb8(small[..., :3]),
                    to_srgb8(small[..., 3:4])
                    if small.dtype == np.uint8
                    else np.round(np.clip(small[..., 3:4], 0, 1) * 255).astype(np.uint8),
                ],
                axis=2,
            )
            self._stream.log(path, rr.Image(rgba8, color_model="RGBA"))

    def flush(self) -> None:
        self._stream.flush()

    def close(self) -> None:
        """Write out everything (the file gets its footer) and stop the local viewer server, if any.

        A recording that could not be written out (a full disk) raises `RecordingWriteError`, which names the
        file and what to do; the server is stopped all the same, and the browser keeps what it received.
        """
        if self._closed:
            return
        self._closed = True
        try:
            self._stream.flush()
            self._stream.disconnect()
        except (RuntimeError, OSError) as exc:  # rerun's file writer gave up: "shut down prematurely"
            if self.recording_path is None:
                raise
            raise RecordingWriteError.from_failure(self.recording_path, exc) from None
        finally:
            self._stop_server()

    def _stop_server(self) -> None:
        if self._server is not None:
            self._server.stop()

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _as_mapping(meta: Any) -> dict[str, Any]:
    if isinstance(meta, Mapping):
        return dict(meta)
    if hasattr(meta, "__dataclass_fields__"):
        from dataclasses import asdict

        return asdict(meta)
    return {"metadata": meta}
