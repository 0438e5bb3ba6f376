"""The 3D scene of a recording: accurate-depth planes as coloured meshes, through the one camera model.

Every vertex is back-projected by `processing.pinhole.PinholeCamera` with processing-pixel edges from
`processing.pinhole.processing_pixel_edges`, so the meshes agree with scene.ply and scene.glb.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from mca.capture.recording.display import resize, unpremultiplied_rgba8
from mca.processing.colour import CameraColour
from mca.processing.pinhole import PinholeCamera, processing_pixel_edges

if TYPE_CHECKING:
    from mca.processing.optics import MCAOptics

PLANE_MESH_CELLS = 96  # accurate-depth plane meshes: grid cells across the width
MAX_POINTS = 200_000  # point cloud subsampled to at most this many points


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
    xs = processing_pixel_edges(origin_px[0] + np.minimum(np.arange(gw + 1) * step, w), pixel_scale)
    ys = processing_pixel_edges(origin_px[1] + np.minimum(np.arange(gh + 1) * step, h), pixel_scale)
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


def surface_distance(
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
