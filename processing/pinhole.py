"""The one camera model of every 3D output: a pinhole at the lens, pixel centres at integer coordinates, glTF's axes.

Pixel convention: (u, v) in input-image pixels, u right, v down, with the *centre* of the
top-left pixel at (0, 0) (OpenCV's convention); pixel u covers [u - 0.5, u + 0.5]. The principal
point is the image centre, ((W - 1) / 2, (H - 1) / 2). A processing pixel (row r, column c) of a
grid `pixel_scale` times coarser has its centre at u = (c + 0.5) * pixel_scale - 0.5.

The focal length in pixels is the paper's lens-sensor distance d_ls over the input-pixel pitch
(the thin lens images the focus plane at d_ls; every point is projected through the lens centre).

Two frames:

* the *optical* frame, in mm: x right, y down, z forward along the optical axis (OpenCV);
  `x = (u - cx) Z / f_px`, `y = (v - cy) Z / f_px`, `z = Z` for a point at distance Z from the lens.
* the *scene* frame of every file (scene.ply, scene.glb, the rerun recording's `world`): glTF's,
  metres, x right, y up, the camera at the origin looking down -z. A point of the optical frame
  (x, y, z) mm is (x, -y, -z) / 1000 in the scene frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

MM_PER_M = 1000.0
PIXEL_CONVENTION = "pixel centres at integer coordinates; (0, 0) is the centre of the top-left pixel"
SCENE_FRAME = "metres; x right, y up, camera at the origin looking down -z (glTF)"


def optical_mm_to_scene_m(points_mm: np.ndarray) -> np.ndarray:
    """(..., 3) optical-frame points in mm (x right, y down, z forward) to the scene frame (metres, y up, -z forward)."""
    points = np.asarray(points_mm, dtype=np.float64)
    return points * np.array([1.0, -1.0, -1.0]) / MM_PER_M


def scene_m_to_optical_mm(points_m: np.ndarray) -> np.ndarray:
    """The inverse of `optical_mm_to_scene_m`."""
    points = np.asarray(points_m, dtype=np.float64)
    return points * np.array([1.0, -1.0, -1.0]) * MM_PER_M


def processing_pixel_centres(rows: np.ndarray, cols: np.ndarray, pixel_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Input-image coordinates (u, v) of the centres of processing pixels (rows, cols)."""
    u = (np.asarray(cols, dtype=np.float64) + 0.5) * pixel_scale - 0.5
    v = (np.asarray(rows, dtype=np.float64) + 0.5) * pixel_scale - 0.5
    return u, v


def processing_pixel_edges(indices: np.ndarray, pixel_scale: float) -> np.ndarray:
    """Input-image coordinates of processing-pixel edges: edge i is the leading edge of processing pixel i
    (the trailing edge of pixel i - 1), at i * pixel_scale - 0.5 (pixel centres at integers)."""
    return np.asarray(indices, dtype=np.float64) * pixel_scale - 0.5


def strided_pixels(valid: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the True pixels of `valid` on the smallest regular stride that leaves at most `max_points`."""
    count = int(valid.sum())
    stride = max(1, math.ceil(math.sqrt(count / max(max_points, 1))))
    while int(valid[::stride, ::stride].sum()) > max_points:
        stride += 1
    rows, cols = np.nonzero(valid[::stride, ::stride])
    return rows * stride, cols * stride


@dataclass(frozen=True)
class PinholeCamera:
    """The camera of one input image: focal length in input pixels and the image size."""

    focal_px: float  # d_ls / input-pixel pitch
    width_px: int
    height_px: int

    @classmethod
    def from_optics(
        cls, pixel_pitch_mm: float, sensor_distance_mm: float, width_px: int, height_px: int
    ) -> PinholeCamera:
        """The pinhole of an MCA camera: f = d_ls / pitch, for an input image of width x height pixels."""
        if not pixel_pitch_mm > 0 or not sensor_distance_mm > 0:
            raise ValueError(f"need a positive pitch and d_ls, got {pixel_pitch_mm} mm and {sensor_distance_mm} mm")
        return cls(sensor_distance_mm / pixel_pitch_mm, int(width_px), int(height_px))

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """(cx, cy): the image centre, in the pixel-centre convention."""
        return ((self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0)

    @property
    def K(self) -> np.ndarray:  # the conventional name of the intrinsic matrix
        """The 3x3 intrinsic matrix (pixel-centre convention): [u, v, 1] ~ K [x, y, z] in the optical frame."""
        cx, cy = self.principal_point_px
        return np.array([[self.focal_px, 0.0, cx], [0.0, self.focal_px, cy], [0.0, 0.0, 1.0]])

    @property
    def yfov_rad(self) -> float:
        """Vertical field of view across the image's full height (pixel edges)."""
        return 2.0 * math.atan(self.height_px / 2.0 / self.focal_px)

    def back_project_mm(self, u_px: np.ndarray, v_px: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """(N, 3) optical-frame points in mm of pixels (u, v) at distances z along the optical axis."""
        cx, cy = self.principal_point_px
        z = np.asarray(z_mm, dtype=np.float64)
        u = np.asarray(u_px, dtype=np.float64)
        v = np.asarray(v_px, dtype=np.float64)
        return np.stack([(u - cx) * z / self.focal_px, (v - cy) * z / self.focal_px, z], axis=-1)

    def back_project_scene_m(self, u_px: np.ndarray, v_px: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """(N, 3) scene-frame points in metres (glTF axes) of pixels (u, v) at distances z (mm)."""
        return optical_mm_to_scene_m(self.back_project_mm(u_px, v_px, z_mm))

    def depth_map_points(
        self, depth_mm: np.ndarray, pixel_scale: float, max_points: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Scene-frame points (float32 metres) of the known-depth pixels of a processing-resolution depth map,
        on a regular stride (`strided_pixels`), with their (rows, cols)."""
        depth = np.asarray(depth_mm)
        rows, cols = strided_pixels(np.isfinite(depth) & (depth > 0), max_points)
        u, v = processing_pixel_centres(rows, cols, pixel_scale)
        points = self.back_project_scene_m(u, v, depth[rows, cols].astype(np.float64))
        return points.astype(np.float32), rows, cols

    def project_scene_m(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) pixel coordinates of scene-frame points (the inverse of `back_project_scene_m`)."""
        optical = scene_m_to_optical_mm(points_m)
        cx, cy = self.principal_point_px
        z = optical[..., 2]
        return optical[..., 0] * self.focal_px / z + cx, optical[..., 1] * self.focal_px / z + cy

    def describe(self) -> dict[str, Any]:
        """For result.json: K, distortion, size and the conventions, so that another program can use them."""
        return {
            "model": "pinhole",
            "K": [[float(v) for v in row] for row in self.K],
            "focal_length_px": float(self.focal_px),
            "principal_point_px": [float(v) for v in self.principal_point_px],
            "image_size_px": [int(self.width_px), int(self.height_px)],
            "distortion": None,
            "pixel_convention": PIXEL_CONVENTION,
            "K_frame": "optical: x right, y down, z forward (OpenCV)",
            "scene_frame": SCENE_FRAME,
        }
