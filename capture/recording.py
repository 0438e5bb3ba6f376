"""Rerun recordings of the pipeline: every stage of a shot logged to an .rrd file (or a local web viewer), and merged.

`RerunRecorder` implements the `processing.result.Recorder` protocol and adds the
application's own calls around a run of the pipeline::

    recorder = RerunRecorder(Path("out/c.rrd"))
    recorder.begin_shot(0, "paper-c", capture_time, profile)
    recorder.log_input(frame)                      # raw colour planes, the input as the camera produced it
    result = run_pipeline(..., recorder=recorder)  # stages call record() and timing()
    recorder.log_result(result, profile, optics)   # regions, order, depth, multi-plane images, 3D scene
    recorder.close()

Entity paths (all per shot, on the `shot` sequence timeline and the `capture_time` timeline):

    shot/input                   EncodedImage   the input image as the camera produced it (display size, JPEG)
    shot/raw/{red,green,blue}    EncodedImage   the raw colour planes (grey JPEG)
    shot/channels/before         EncodedImage   red plane in red, blue plane in cyan: the MCA misalignment
    shot/channels/after          EncodedImage   the same after re-alignment (the all-in-focus image)
    shot/disparity/region_model  Image (F32)    disparity of the region model, input px, + = farther
    shot/disparity/per_pixel     Image (F32)    per-pixel disparity estimate, input px
    shot/disparity/confidence    Image (F32)    confidence in [0, 1]
    shot/segmentation            SegmentationImage + AnnotationContext (region id -> "#id 1234 mm")
    shot/occlusion_order         TextDocument   markdown table, front to back
    shot/occlusion_graph         GraphNodes + GraphEdges (an edge a -> b: a occludes b)
    shot/depth                   DepthImage     distance from the lens in mm (meter=1000), 0 = unknown
    shot/all_in_focus            EncodedImage   fringes removed
    shot/multi_plane/NN          Image (RGBA) + Transform3D  the multi-plane images, nearest first, each
                                 cropped to where it is opaque and translated to its place
    shot/profile                 TextDocument   the camera profile used
    shot/summary                 TextDocument   shot name, time, timings
    shot/segmentation/sketch     SegmentationImage  the 2.1D sketch's regions on the analysis grid
    shot/stages/<stage>/<item>   Image/Scalars/TextDocument  anything else a stage reported through record()
    world                        ViewCoordinates RUB (static): the scene frame of scene.ply and scene.glb,
                                 metres, x right, y up, the camera at the origin looking down -z (glTF)
    world/camera                 Pinhole        f = d_ls / pitch px, principal point at the centre, camera_xyz RUB
    world/camera/image           EncodedImage   the input, seen through the pinhole
    world/points                 Points3D       coloured point cloud: scene.ply's points (subsampled)
    world/planes/NN              Mesh3D         the accurate-depth planes, coloured, on their (slanted) surfaces

The colours of every displayed image are the camera's (`capture.raw.RawFrame.colour`: as-shot white
balance and colour matrix); the 3D coordinates come from the one camera model, `processing.pinhole`.
    timings/<stage>              Scalars        seconds per stage

Nothing here is imported by `processing`; rerun itself is imported only when a recorder is made.
Usage analytics of rerun stay off: see `disable_rerun_analytics`.
"""

from __future__ import annotations

import atexit
import json
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mca.processing.colour import CameraColour
from mca.processing.pinhole import PinholeCamera

if TYPE_CHECKING:
    from mca.processing.camera import CameraProfile
    from mca.processing.optics import MCAOptics
    from mca.processing.result import DepthResult

# --- rerun's usage analytics: off, before rerun is ever imported ----------------------------------------------------
#
# rerun 0.41 (crates/utils/re_analytics, native pipeline) sends usage events unless the user's
# analytics config (~/.config/rerun/analytics.json, written by `rerun analytics disable`) says
# `analytics_enabled: false`, or the environment has `CI` set; `FORCE_RERUN_ANALYTICS` overrides
# both. The SDK's OpenTelemetry tracing is active only with `TELEMETRY_ENABLED=true`.

_ANALYTICS_ENV_DONE = False
_ANALYTICS_CONFIG_DONE = False


def quiet_rerun_environment(environ: os._Environ[str] | dict[str, str] = os.environ) -> None:
    """Set the environment so that rerun (SDK and viewer) reports nothing: call before `import rerun`.

    Removes `FORCE_RERUN_ANALYTICS` (which would override the opt-out) and sets
    `TELEMETRY_ENABLED=false` (the SDK's OpenTelemetry export).
    """
    environ.pop("FORCE_RERUN_ANALYTICS", None)
    environ["TELEMETRY_ENABLED"] = "false"


def rerun_analytics_config_path(environ: Mapping[str, str] = os.environ) -> Path:
    """Where rerun keeps its analytics opt-out on Linux (directories::ProjectDirs: $XDG_CONFIG_HOME/rerun)."""
    base = environ.get("XDG_CONFIG_HOME") or str(Path(environ.get("HOME", str(Path.home()))) / ".config")
    if sys.platform == "darwin":
        base = str(Path.home() / "Library" / "Application Support")
    return Path(base) / "rerun" / "analytics.json"


def rerun_analytics_disabled(environ: Mapping[str, str] = os.environ) -> bool:
    """True when rerun's own config says analytics are off."""
    try:
        config = json.loads(rerun_analytics_config_path(environ).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(config, dict) and config.get("analytics_enabled") is False


def child_environment() -> dict[str, str]:
    """The environment for a `rerun` child process (viewer, server, `rerun rrd`): analytics off.

    `CI=1` is added only when the config-file opt-out could not be confirmed (e.g. a read-only
    home): it is the one environment variable rerun itself reads to stay quiet.
    """
    env = dict(os.environ)
    quiet_rerun_environment(env)
    if not rerun_analytics_disabled(env):
        env["CI"] = "1"
    return env


def disable_rerun_analytics() -> None:
    """Make sure no rerun usage data leaves the bench; cheap after the first call.

    Sets the environment (`quiet_rerun_environment`) and, once per machine, records the opt-out
    in rerun's own config with `rerun analytics disable` (what rerun documents for opting out).
    """
    global _ANALYTICS_ENV_DONE, _ANALYTICS_CONFIG_DONE
    if not _ANALYTICS_ENV_DONE:
        quiet_rerun_environment()
        _ANALYTICS_ENV_DONE = True
    if _ANALYTICS_CONFIG_DONE:
        return
    _ANALYTICS_CONFIG_DONE = True
    if rerun_analytics_disabled():
        return
    exe = rerun_executable()
    if exe is None:
        return
    env = dict(os.environ)
    env["CI"] = "1"  # the opt-out command itself must not report
    try:
        subprocess.run(
            [exe, "analytics", "disable"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        pass


quiet_rerun_environment()
_ANALYTICS_ENV_DONE = True


def rerun_executable() -> str | None:
    """Path of the `rerun` command-line binary matching the SDK (the one the rerun-sdk wheel ships), or None.

    The binary itself rather than the Python wrapper script in the venv's bin/, so that signals
    (Ctrl-C, terminate) reach the viewer directly.
    """
    try:
        import rerun_cli  # the wheel's package holding the binary

        bundled = Path(rerun_cli.__file__).parent / "rerun"
        if bundled.is_file() and os.access(bundled, os.X_OK):
            return str(bundled)
    except ImportError:
        pass
    beside = Path(sys.executable).parent / "rerun"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    return shutil.which("rerun")


# --- images for display ---------------------------------------------------------------------------------------------

DISPLAY_MEGAPIXELS = 1.5  # 2D images are shown at about this size
MAX_POINTS = 200_000  # point cloud subsampled to at most this many points
MULTI_PLANE_MEGAPIXELS = 1.0  # the frame the RGBA multi-plane images are placed in (each is cropped)
PLANE_MESH_CELLS = 96  # accurate-depth plane meshes: grid cells across the width
JPEG_QUALITY = 85

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


def display_size(width_px: int, height_px: int, megapixels: float = DISPLAY_MEGAPIXELS) -> tuple[int, int]:
    """(width, height) no larger than `megapixels`, same aspect ratio, never upscaled."""
    area = width_px * height_px
    limit = megapixels * 1e6
    if area <= limit:
        return width_px, height_px
    scale = math.sqrt(limit / area)
    return max(1, int(width_px * scale)), max(1, int(height_px * scale))


def resize(image: np.ndarray, size: tuple[int, int], *, nearest: bool = False) -> np.ndarray:
    """Resize to (width, height): area averaging when shrinking, nearest for label maps."""
    import cv2

    if image.shape[1] == size[0] and image.shape[0] == size[1]:
        return image
    if nearest:
        return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)
    src = image
    if src.dtype not in (np.uint8, np.uint16, np.float32):
        src = src.astype(np.float32)
    shrinking = size[0] < image.shape[1]
    return cv2.resize(src, size, interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


def to_srgb8(linear: np.ndarray, colour: CameraColour | None = None) -> np.ndarray:
    """Linear light in [0, 1] (float) to 8-bit sRGB, through `colour` (camera RGB to sRGB) for RGB images;
    uint8 input is taken as already encoded."""
    if linear.dtype == np.uint8:
        return linear
    if linear.dtype == np.uint16:
        return (linear >> 8).astype(np.uint8)
    from mca.processing.colour import linear_to_srgb8

    if colour is not None and linear.ndim >= 1 and linear.shape[-1] == 3:
        return colour.to_srgb8(linear)
    return linear_to_srgb8(linear)


def normalised(plane: np.ndarray) -> np.ndarray:
    """A plane scaled to [0, 1] by its 99.5th percentile (raw planes come in sensor units)."""
    plane = np.nan_to_num(plane.astype(np.float32, copy=False), nan=0.0)
    sample = plane[:: max(1, plane.shape[0] // 256), :: max(1, plane.shape[1] // 256)]
    top = float(np.percentile(sample, 99.5)) if sample.size else 1.0
    return np.clip(plane / top, 0.0, 1.0) if top > 0 else np.zeros_like(plane)


def misalignment_overlay(planes: np.ndarray) -> np.ndarray:
    """Red plane in red, blue plane in green and blue: where the MCA displaced them, red/cyan fringes show."""
    red = to_srgb8(normalised(planes[..., 0]))
    blue = to_srgb8(normalised(planes[..., 2]))
    return np.dstack([red, blue, blue])


def _jpeg(rr: Any, image8: np.ndarray) -> Any:
    """A compressed image archetype for a uint8 grey or RGB image."""
    return rr.Image(np.ascontiguousarray(image8)).compress(jpeg_quality=JPEG_QUALITY)


def _region_colour(region_id: int) -> tuple[int, int, int]:
    """A stable, distinct colour per region id (golden-ratio hues)."""
    import colorsys

    hue = (region_id * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def _short(value: Any) -> str:
    """A compact cell for a markdown table."""
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.4g}"
    if isinstance(value, (tuple, list)) and all(isinstance(v, (int, float, np.number)) for v in value):
        return "(" + ", ".join(f"{float(v):.4g}" for v in value) + ")"
    return str(value).replace("|", "\\|")


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def occlusion_order_markdown(result: DepthResult) -> str:
    """The regions front to back as a markdown table (what the viewer shows as the occlusion order)."""
    lines = [
        "| rank | region | pixels | distance mm | ΔD mm | Δd mm | disparity px | occludes | in focus | confidence |",
        "|---:|---:|---:|---:|---:|---:|---:|---|:---:|---:|",
    ]
    for region in sorted(result.regions, key=lambda r: r.order):
        occludes = ", ".join(f"#{i}" for i in region.occludes) or "-"
        focus = "yes" if region.in_focus or region.id == result.focus_region else ""
        lines.append(
            f"| {region.order} | #{region.id} | {region.pixels} | {_fmt(region.distance_mm)} | "
            f"{_fmt(region.inter_object_depth_mm)} | {_fmt(region.inter_image_depth_mm, 4)} | "
            f"{_fmt(region.disparity_px, 2)} | {occludes} | {focus} | {_fmt(region.confidence, 2)} |"
        )
    if not result.regions:
        lines.append("| - | - | - | - | - | - | - | - | - | - |")
    return "\n".join(lines)


def profile_markdown(profile: CameraProfile | None) -> str:
    """The camera profile as a markdown document."""
    if profile is None:
        return "# Profile\n\nnone given"
    ap = profile.aperture
    first, second = ap.widest_pair
    rows = [
        ("name", profile.name),
        ("source", profile.source or "-"),
        ("camera", profile.model),
        ("pixel pitch", f"{profile.pixel_pitch_mm} mm" if profile.pixel_pitch_mm else "unknown"),
        ("image size", f"{profile.width_px or '?'} x {profile.height_px or '?'} px"),
        (
            "filters (x, y) mm",
            f"red {ap.red_mm}, green {ap.green_mm}, blue {ap.blue_mm}; diameter {ap.filter_diameter_mm} mm",
        ),
        ("d_a", f"{ap.baseline_mm:.3f} mm ({first}-{second})"),
    ]
    if profile.lens is not None:
        rows += [
            ("focal length f", f"{profile.lens.focal_length_mm} mm"),
            ("sensor distance d_ls", f"{profile.lens.sensor_distance_mm:.4f} mm"),
            ("focus distance", f"{profile.lens.focus_distance_mm:.2f} mm"),
        ]
        if profile.pixel_pitch_mm:
            rows.append(
                ("focal length in px", f"{profile.lens.sensor_distance_mm / profile.pixel_pitch_mm:.1f} (d_ls / pitch)")
            )
    else:
        rows.append(("lens", "none: disparities in pixels only"))
    body = "\n".join(f"| {k} | {v} |" for k, v in rows)
    return f"# Camera profile `{profile.name}`\n\n| field | value |\n|---|---|\n{body}\n"


def front_to_back(result: DepthResult) -> list[Any]:
    """The multi-plane images nearest first (by the region's rank, else by disparity: smaller is nearer)."""
    rank = {r.id: r.order for r in result.regions}
    return sorted(result.layers, key=lambda layer: (rank.get(layer.region_id, math.inf), layer.disparity_px))


def layer_windows(result: DepthResult, margin_px: int = 8) -> dict[int, tuple[slice, slice]]:
    """Bounding box (rows, cols) of each region's label, padded by `margin_px`: where its layer can be opaque."""
    from scipy import ndimage

    labels = np.asarray(result.labels)
    h, w = labels.shape
    windows = {}
    for index, box in enumerate(ndimage.find_objects(labels.astype(np.int32, copy=False))):
        if box is not None:
            rows, cols = box
            windows[index + 1] = (
                slice(max(0, rows.start - margin_px), min(h, rows.stop + margin_px)),
                slice(max(0, cols.start - margin_px), min(w, cols.stop + margin_px)),
            )
    return windows


def opaque_window(alpha: np.ndarray) -> tuple[slice, slice] | None:
    """Bounding box of alpha > 0, or None when the layer is empty (full scan: the fallback of `layer_windows`)."""
    rows, cols = np.flatnonzero(alpha.any(axis=1)), np.flatnonzero(alpha.any(axis=0))
    if not len(rows):
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def layer_rgba_crop(layer: Any, window: tuple[slice, slice]) -> np.ndarray:
    """`layer.rgba[window]`, without the full-size float RGBA when the pipeline built the layer lazily.

    `processing.result.MultiPlaneImage.rgba` of a layer with a (display image, labels) source is
    display x mask with alpha = mask (mask = labels == region id); the same arithmetic on the window
    alone gives the same values.
    """
    rows, cols = window
    source = layer.lazy_source
    if source is not None:
        display, labels = source
        alpha = (np.asarray(labels)[rows, cols] == layer.region_id).astype(np.float32)
        rgba = np.empty(alpha.shape + (4,), np.float32)
        np.multiply(np.asarray(display)[rows, cols], alpha[..., None], out=rgba[..., :3])
        rgba[..., 3] = alpha
        return rgba
    return np.asarray(layer.rgba)[rows, cols]


def unpremultiplied_rgba8(rgba: np.ndarray, colour: CameraColour | None = None) -> np.ndarray:
    """A float RGBA layer (camera RGB premultiplied by alpha, as `processing.mpi` makes them) as 8-bit sRGB + alpha."""
    alpha = np.clip(np.nan_to_num(rgba[..., 3:4]), 0.0, 1.0)
    straight = np.where(alpha > 0, rgba[..., :3] / np.maximum(alpha, 1e-6), 0.0).astype(np.float32)
    return np.concatenate([to_srgb8(straight, colour), np.round(alpha * 255).astype(np.uint8)], axis=2)


def plane_mesh(
    rgba: np.ndarray,
    distance_mm_at: Callable[[np.ndarray, np.ndarray], np.ndarray],
    camera: PinholeCamera,
    pixel_scale: float,
    cells_across: int = PLANE_MESH_CELLS,
    *,
    origin_px: tuple[int, int] = (0, 0),
    full_width_px: int | None = None,
    colour: CameraColour | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A coloured grid mesh over the opaque part of one multi-plane image, on its surface in the scene frame.

    `rgba` is at processing resolution (`pixel_scale` input px per pixel), premultiplied, possibly a
    crop whose top-left corner is `origin_px` (x, y) in a frame `full_width_px` wide (the grid step is
    that width over `cells_across`). Each vertex (u, v) (input px, pixel centres at integers) is
    back-projected by `camera` at `distance_mm_at(u, v)` mm: a constant for a fronto-parallel region,
    its fitted plane for a slanted one. Returns (vertices (N, 3) metres in the scene frame (glTF axes),
    triangles (M, 3) uint32, colours (N, 4) uint8).
    """
    h, w = rgba.shape[:2]
    step = max(1, int(math.ceil((full_width_px or w) / cells_across)))
    gw, gh = int(math.ceil(w / step)), int(math.ceil(h / step))
    small = resize(rgba.astype(np.float32, copy=False), (gw, gh))
    cell_on = small[..., 3] > 0.5
    # vertices at cell corners (gw + 1) x (gh + 1): processing-pixel edges, in input pixels (centres at integers)
    xs = (origin_px[0] + np.minimum(np.arange(gw + 1) * step, w)) * pixel_scale - 0.5
    ys = (origin_px[1] + np.minimum(np.arange(gh + 1) * step, h)) * pixel_scale - 0.5
    gx, gy = np.meshgrid(xs, ys)
    distances = np.broadcast_to(np.asarray(distance_mm_at(gx, gy), dtype=np.float64), gx.shape)
    vertices = camera.back_project_scene_m(gx.ravel(), gy.ravel(), distances.ravel()).astype(np.float32)
    # corner colours: average of the neighbouring cells (edge-padded)
    rgb = unpremultiplied_rgba8(small, colour)[..., :3]
    padded = np.pad(rgb.astype(np.float32), ((1, 1), (1, 1), (0, 0)), mode="edge")
    corner = (padded[:-1, :-1] + padded[1:, :-1] + padded[:-1, 1:] + padded[1:, 1:]) / 4.0
    colours = np.concatenate(
        [corner.reshape(-1, 3), np.full((corner.shape[0] * corner.shape[1], 1), 255.0)], axis=1
    ).astype(np.uint8)
    cy, cx = np.nonzero(cell_on)
    top_left = cy * (gw + 1) + cx
    top_right, bottom_left, bottom_right = top_left + 1, top_left + gw + 1, top_left + gw + 2
    triangles = np.concatenate(
        [np.stack([top_left, bottom_left, top_right], axis=1), np.stack([top_right, bottom_left, bottom_right], axis=1)]
    ).astype(np.uint32)
    return vertices, triangles, colours


def _surface_distance(
    region: Any, distance_mm: float, optics: MCAOptics | None
) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Distance (mm) of a region's surface at input pixels (u, v): its slant plane through the optics, else constant."""
    slant = getattr(region, "slant", None)
    if slant is not None and optics is not None:
        a, b, c = slant

        def on_plane(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            distances = np.asarray(optics.distance_mm(a * u + b * v + c), dtype=np.float64)
            return np.where(np.isfinite(distances) & (distances > 0), distances, distance_mm)

        return on_plane
    return lambda u, v: np.full(np.shape(u), distance_mm, dtype=np.float64)


# --- the recorder ---------------------------------------------------------------------------------------------------


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
        self._server: subprocess.Popen[bytes] | None = None
        self._stream = rr.RecordingStream(application_id, recording_id=recording_id)
        self._stream.set_log_tick_enabled(False)
        sinks: list[Any] = []
        if self.recording_path is not None:
            self.recording_path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.recording_path)))
        if serve:
            url = self._start_server(bind, grpc_port, web_port)
            sinks.append(rr.GrpcSink(url))
        self._stream.set_sinks(*sinks, default_blueprint=default_blueprint())
        self._stream.log("world", rr.ViewCoordinates.RUB, static=True)  # glTF's axes, as scene.ply and scene.glb
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

    # -- serving ---------------------------------------------------------------------------------------------------

    def _start_server(self, bind: str, grpc_port: int | None, web_port: int | None) -> str:
        exe = rerun_executable()
        if exe is None:
            raise RuntimeError("--serve needs the `rerun` command of rerun-sdk; reinstall with `pip install rerun-sdk`")
        grpc_port = choose_port(bind, grpc_port, DEFAULT_GRPC_PORT, "the data port (--grpc-port)")
        web_port = choose_port(bind, web_port, DEFAULT_WEB_PORT, "the web viewer port (--web-port)", {grpc_port})
        command = [exe, "--serve-web", "--bind", bind, "--port", str(grpc_port), "--web-viewer-port", str(web_port)]
        self._server = subprocess.Popen(
            die_with_parent(command),
            env=child_environment(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        atexit.register(self._stop_server)
        host = "127.0.0.1" if bind in ("0.0.0.0", "::", "127.0.0.1") else bind
        grpc_url = f"rerun+http://{host}:{grpc_port}/proxy"
        try:
            for port in (grpc_port, web_port):
                _wait_for_port(host, port, self._server, timeout_s=10.0)
        except BaseException:
            self._stop_server()
            raise
        from urllib.parse import quote

        self.viewer_url = f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}"
        self.ports = (grpc_port, web_port)
        return grpc_url

    def _stop_server(self) -> None:
        """Stop the viewer server this recorder started (idempotent)."""
        server, self._server = self._server, None
        if server is None:
            return
        atexit.unregister(self._stop_server)
        if server.poll() is None:
            server.terminate()
            try:
                server.wait(timeout=5)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait(timeout=5)

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
                rows = "\n".join(f"| {k} | {_short(v)} |" for k, v in value.items())
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
        self._input_jpeg = _jpeg(self._rr, to_srgb8(small, self._colour))
        self._stream.log("shot/input", self._input_jpeg)
        for index, channel in enumerate(("red", "green", "blue")):
            self._stream.log(f"shot/raw/{channel}", _jpeg(self._rr, to_srgb8(normalised(small[..., index]))))
        self._stream.log("shot/channels/before", _jpeg(self._rr, misalignment_overlay(small)))
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
        self._stream.log("shot/all_in_focus", _jpeg(rr, to_srgb8(aif_small, self._colour)))
        self._stream.log("shot/channels/after", _jpeg(rr, misalignment_overlay(aif_small)))

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
                    color=_region_colour(region.id),
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
                        f"#{r.id} {_fmt(r.distance_mm, 0)} mm"
                        if r.distance_mm is not None
                        else f"#{r.id} {r.disparity_px:+.1f} px"
                        for r in regions
                    ],
                    colors=[_region_colour(r.id) for r in regions],
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
            distance_mm_at = _surface_distance(region, distance_mm, optics)
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
        return _jpeg(self._rr, to_srgb8(small, self._colour))

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
            self._stream.log(path, _jpeg(rr, to_srgb8(resize(value, size))))
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
        """Write out everything (the file gets its footer) and stop the local viewer server, if any."""
        if self._closed:
            return
        self._closed = True
        try:
            self._stream.flush()
            self._stream.disconnect()
        finally:
            self._stop_server()  # even when the file could not be written (a full disk); the browser keeps its data

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


DEFAULT_GRPC_PORT = 9876  # rerun's own defaults
DEFAULT_WEB_PORT = 9090


def port_in_use(host: str, port: int) -> bool:
    """True when `port` cannot be bound on `host` (another program listens there)."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return True
    return False


def free_port(host: str) -> int:
    """A port the system says is free on `host` now."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def choose_port(
    host: str, wanted: int | None, default: int, what: str, taken: set[int] | frozenset = frozenset()
) -> int:
    """`wanted` if free (else an error naming it), or `default` if free, or a free port."""
    if wanted is not None:
        if wanted in taken or port_in_use(host, wanted):
            raise RuntimeError(
                f"port {wanted} on {host} is already in use (another `mca --serve`, `mca view --web` or rerun "
                f"viewer?); choose another for {what}, or leave it out to take a free one"
            )
        return wanted
    if default not in taken and not port_in_use(host, default):
        return default
    while True:
        port = free_port(host)
        if port not in taken:
            return port


def die_with_parent(command: list[str]) -> list[str]:
    """`command` run so that the kernel stops it when this process dies, however it dies (Linux `setpriv`)."""
    setpriv = shutil.which("setpriv") if sys.platform.startswith("linux") else None
    if setpriv is None:
        return command
    return [setpriv, "--pdeathsig", "TERM", "--", *command]


def _wait_for_port(host: str, port: int, process: subprocess.Popen[bytes], timeout_s: float) -> None:
    """Wait until the server `process` listens on `port`; the port was free before it started, so a listener
    there is the server (checked to be still running), not somebody else's."""
    import socket

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(
                f"the rerun server exited (code {process.returncode}) before listening on {host}:{port}; "
                "is the port in use? Choose another"
            )
        try:
            with socket.create_connection((host, port), timeout=0.2):
                pass
        except OSError:
            time.sleep(0.1)
            continue
        if process.poll() is None:
            return
    raise RuntimeError(f"the rerun server did not listen on {host}:{port} within {timeout_s:.0f} s")


def _as_mapping(meta: Any) -> dict[str, Any]:
    if isinstance(meta, Mapping):
        return dict(meta)
    if hasattr(meta, "__dataclass_fields__"):
        from dataclasses import asdict

        return asdict(meta)
    return {"metadata": meta}


# --- blueprint and merging ------------------------------------------------------------------------------------------


def default_blueprint() -> Any:
    """The layout a newcomer sees: input | regions | depth, then the 3D scene, the order and the timings."""
    import rerun.blueprint as rrb

    top = rrb.Horizontal(
        rrb.Spatial2DView(origin="shot/input", name="Input (as the camera produced it)"),
        rrb.Spatial2DView(origin="shot", contents=["+ $origin/all_in_focus", "+ $origin/segmentation"], name="Regions"),
        rrb.Spatial2DView(origin="shot/depth", name="Depth (mm)"),
    )
    middle = rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="3D scene (m)"),
        rrb.Tabs(
            rrb.TextDocumentView(origin="shot/occlusion_order", name="Occlusion order"),
            rrb.GraphView(origin="shot/occlusion_graph", name="Occlusion graph"),
            rrb.TextDocumentView(origin="shot/summary", name="Summary"),
            rrb.TextDocumentView(origin="shot/profile", name="Profile"),
            rrb.TextDocumentView(origin="shot/input_metadata", name="Input file"),
        ),
        rrb.TimeSeriesView(origin="timings", name="Timings (s)"),
        column_shares=[2, 1.3, 1],
    )
    bottom = rrb.Tabs(
        rrb.Grid(
            rrb.Spatial2DView(origin="shot/raw/red", name="Raw red"),
            rrb.Spatial2DView(origin="shot/raw/green", name="Raw green"),
            rrb.Spatial2DView(origin="shot/raw/blue", name="Raw blue"),
            name="Raw planes",
        ),
        rrb.Horizontal(
            rrb.Spatial2DView(origin="shot/channels/before", name="Misalignment before"),
            rrb.Spatial2DView(origin="shot/channels/after", name="After re-alignment"),
            name="Channels",
        ),
        rrb.Horizontal(
            rrb.Spatial2DView(origin="shot/disparity/region_model", name="Disparity, region model (px)"),
            rrb.Spatial2DView(origin="shot/disparity/per_pixel", name="Disparity, per pixel (px)"),
            rrb.Spatial2DView(origin="shot/disparity/confidence", name="Confidence"),
            name="Disparity",
        ),
        rrb.Spatial2DView(origin="shot/multi_plane", name="Multi-plane images (toggle layers)"),
        rrb.Spatial2DView(origin="shot/stages", name="Stages"),
    )
    return rrb.Blueprint(rrb.Vertical(top, middle, bottom, row_shares=[3, 3, 2]), collapse_panels=False)


def merge_recordings(paths: list[Path], out_path: Path) -> None:
    """Merge several .rrd files into one (`rerun rrd merge`); each shot keeps its own recording inside."""
    if not paths:
        raise ValueError("merge_recordings needs at least one recording")
    missing = [str(p) for p in paths if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(f"no such recording: {', '.join(missing)}")
    exe = rerun_executable()
    if exe is None:
        raise RuntimeError("merging recordings needs the `rerun` command of rerun-sdk; reinstall rerun-sdk")
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.{os.getpid()}.tmp.rrd")
    proc = subprocess.run(
        [exe, "rrd", "merge", *[str(p) for p in paths], "-o", str(tmp)],
        env=child_environment(),
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"rerun rrd merge failed for {', '.join(map(str, paths))}: {proc.stderr.strip()[-500:]}")
    os.replace(tmp, out_path)
