"""The 2.1D sketch on synthetic MCA images: regions, same-colour objects at different depths, occlusion order."""

from __future__ import annotations

import cv2
import numpy as np

from mca.capture.profiles import load_profile
from mca.processing.disparity import channel_shifts, estimate_disparity
from mca.processing.sketch import SketchParams, adjacency, build_sketch, weighted_median_by_label

APERTURE = load_profile("paper-70d").aperture


def texture(shape, seed, colour):
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), 2.0)
    noise /= noise.std()
    return np.clip(1.0 + 0.3 * noise, 0.1, 3.0)[..., None] * np.asarray(colour, np.float32)


def render_layers(layers, shape):
    """Back-to-front layers (rgb, alpha, disparity): each channel displaced by d * s_c, then composited."""
    height, width = shape
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    shifts = channel_shifts(APERTURE)
    out = np.zeros((height, width, 3), np.float32)
    for rgb, alpha, d in layers:
        for c in range(3):
            mx, my = xs - np.float32(d * shifts[c, 0]), ys - np.float32(d * shifts[c, 1])
            colour = cv2.remap(
                np.ascontiguousarray(rgb[..., c]), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
            cover = cv2.remap(alpha, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            out[..., c] = out[..., c] * (1 - cover) + colour * cover
    return out


def two_boxes_scene():
    """A grey wall at +6 px, two boxes of the same red at -2 px (left) and +2.5 px (right), the left one
    overlapping the right one, and a green box in focus."""
    shape = (240, 360)
    wall = (texture(shape, 1, (0.45, 0.43, 0.40)), np.ones(shape, np.float32), 6.0)
    right = np.zeros(shape, np.float32)
    right[60:180, 150:290] = 1
    left = np.zeros(shape, np.float32)
    left[90:200, 60:190] = 1
    green = np.zeros(shape, np.float32)
    green[20:70, 250:340] = 1
    layers = [
        wall,
        (texture(shape, 2, (0.8, 0.2, 0.15)), right, 2.5),
        (texture(shape, 3, (0.8, 0.2, 0.15)), left, -2.0),
        (texture(shape, 4, (0.2, 0.6, 0.25)), green, 0.0),
    ]
    return render_layers(layers, shape), {
        "left": (125, 145),
        "right": (250, 100),
        "green": (295, 45),
        "wall": (30, 220),
    }


def test_weighted_median_by_label():
    labels = np.array([0, 0, 0, 1, 1, 2])
    values = np.array([1.0, 5.0, 2.0, 7.0, 3.0, 4.0])
    weights = np.array([1.0, 1.0, 10.0, 1.0, 3.0, 1.0])
    assert np.allclose(weighted_median_by_label(labels, values, weights, 4)[:3], [2.0, 3.0, 4.0])


def test_adjacency_counts_boundary_length():
    labels = np.array([[1, 1, 2], [1, 1, 2], [3, 3, 3]])
    edges = adjacency(labels)
    assert edges[(1, 2)] == 2 and edges[(1, 3)] == 2 and edges[(2, 3)] == 1


def test_sketch_separates_same_colour_objects_and_orders_them():
    planes, points = two_boxes_scene()
    disparity = estimate_disparity(planes, APERTURE, (-6.0, 9.0))
    sketch = build_sketch(planes, APERTURE, disparity, SketchParams())
    ids = {name: int(sketch.labels[y, x]) for name, (x, y) in points.items()}
    assert len(set(ids.values())) == 4, ids  # the two red boxes stay apart
    assert len(sketch.regions) <= 5  # at most one rim fragment left (see docs)
    d = {name: sketch.region(i).disparity_px for name, i in ids.items()}
    assert abs(d["left"] + 2.0) < 0.3 and abs(d["right"] - 2.5) < 0.3 and abs(d["wall"] - 6.0) < 0.4
    assert sketch.focus_region == ids["green"]
    rank = {name: sketch.order[i] for name, i in ids.items()}
    assert rank["left"] < rank["green"] < rank["right"] < rank["wall"]
    assert ids["right"] in sketch.occludes[ids["left"]]  # the near box occludes the far one
    assert ids["left"] not in sketch.occludes[ids["right"]]
