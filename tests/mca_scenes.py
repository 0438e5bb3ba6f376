"""Small MCA images made in the tests from first principles: each channel of a textured layer is displaced by
d * s_c (s_c from the filter geometry) and the layers are composited back to front. Independent of the
project's simulator (`devices.sim.render`) and renderer (`devices.sim.render_rgbd`)."""

from __future__ import annotations

import cv2
import numpy as np

from mca.processing.camera import CHANNELS, FilterAperture


def shifts_of(aperture: FilterAperture) -> np.ndarray:
    return np.array([aperture.shift_per_disparity(c) for c in CHANNELS], dtype=np.float64)


def texture(
    shape: tuple[int, int], seed: int, colour=(0.6, 0.4, 0.3), blur_px: float = 1.5, contrast: float = 0.35
) -> np.ndarray:
    """A random band-limited texture of mean `colour` (linear RGB)."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), blur_px)
    noise /= noise.std()
    return (np.clip(1.0 + contrast * noise, 0.05, 3.0)[..., None] * np.asarray(colour, np.float32)).astype(np.float32)


def render_layers(layers, shape, aperture: FilterAperture) -> np.ndarray:
    """Back-to-front layers (rgb (H, W, 3), alpha (H, W), disparity: a number or an (H, W) map): channel c of a
    layer point with disparity d is seen d * s_c away, then the layer is composited over what lies behind."""
    height, width = shape
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    shifts = shifts_of(aperture)
    out = np.zeros((height, width, 3), np.float32)
    for rgb, alpha, d in layers:
        d = np.broadcast_to(np.asarray(d, np.float32), shape)
        for c in range(3):
            mx = xs - d * np.float32(shifts[c, 0])
            my = ys - d * np.float32(shifts[c, 1])
            colour = cv2.remap(
                np.ascontiguousarray(rgb[..., c]), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )  # exact in position (OpenCV cubic is not)
            cover = cv2.remap(np.ascontiguousarray(alpha), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            out[..., c] = out[..., c] * (1 - cover) + colour * cover
    return out


def two_boxes_scene(aperture: FilterAperture):
    """A grey wall at +6 px, two boxes of the same red at -2 px (left) and +2.5 px (right), the left one
    overlapping the right one, and a green box in focus. Returns the image and a point inside each object."""
    shape = (240, 360)
    wall = (texture(shape, 1, (0.45, 0.43, 0.40), blur_px=2.0, contrast=0.3), np.ones(shape, np.float32), 6.0)
    right = np.zeros(shape, np.float32)
    right[60:180, 150:290] = 1
    left = np.zeros(shape, np.float32)
    left[90:200, 60:190] = 1
    green = np.zeros(shape, np.float32)
    green[20:70, 250:340] = 1
    layers = [
        wall,
        (texture(shape, 2, (0.8, 0.2, 0.15), blur_px=2.0, contrast=0.3), right, 2.5),
        (texture(shape, 3, (0.8, 0.2, 0.15), blur_px=2.0, contrast=0.3), left, -2.0),
        (texture(shape, 4, (0.2, 0.6, 0.25), blur_px=2.0, contrast=0.3), green, 0.0),
    ]
    points = {"left": (125, 145), "right": (250, 100), "green": (295, 45), "wall": (30, 220)}
    truth = {"left": -2.0, "right": 2.5, "green": 0.0, "wall": 6.0}
    return render_layers(layers, shape, aperture), points, truth
