"""What the viewer shows of a shot: images at display size in sRGB, markdown tables, multi-plane image crops."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from mca.processing.colour import CameraColour

if TYPE_CHECKING:
    from mca.processing.camera import CameraProfile
    from mca.processing.result import DepthResult


DISPLAY_MEGAPIXELS = 1.5  # 2D images are shown at about this size
MULTI_PLANE_MEGAPIXELS = 1.0  # the frame the RGBA multi-plane images are placed in (each is cropped)
JPEG_QUALITY = 85


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


def jpeg(rr: Any, image8: np.ndarray) -> Any:
    """A compressed image archetype for a uint8 grey or RGB image."""
    return rr.Image(np.ascontiguousarray(image8)).compress(jpeg_quality=JPEG_QUALITY)


def region_colour(region_id: int) -> tuple[int, int, int]:
    """A stable, distinct colour per region id (golden-ratio hues)."""
    import colorsys

    hue = (region_id * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def table_cell(value: Any) -> str:
    """A compact cell for a markdown table."""
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.4g}"
    if isinstance(value, (tuple, list)) and all(isinstance(v, (int, float, np.number)) for v in value):
        return "(" + ", ".join(f"{float(v):.4g}" for v in value) + ")"
    return str(value).replace("|", "\\|")


def fmt_number(value: float | None, digits: int = 1) -> str:
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
            f"| {region.order} | #{region.id} | {region.pixels} | {fmt_number(region.distance_mm)} | "
            f"{fmt_number(region.inter_object_depth_mm)} | {fmt_number(region.inter_image_depth_mm, 4)} | "
            f"{fmt_number(region.disparity_px, 2)} | {occludes} | {focus} | {fmt_number(region.confidence, 2)} |"
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
    from mca.processing.labels import label_boxes

    labels = np.asarray(result.labels)
    h, w = labels.shape
    windows = {}
    for index, box in enumerate(label_boxes(labels)):
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
