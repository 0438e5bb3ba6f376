"""Scenes for the simulator: the paper's Fig. 4 rows a-g with Table 1's inter-object depths, and calibration targets.

Distances in Table 1 are inter-object depths from the focus plane (mm, + = farther);
a scene is built for a focus distance and places each object at focus + depth.
Shapes are drawn in frame units (x right, y down, 1 = frame height, frame 1.5 wide).
The background is a textured wall `BACKGROUND_DEPTH_MM` behind the focus plane.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from mca.devices.sim.render import Layer, Scene, Shape, Slant
from mca.devices.sim.textures import Texture

FRAME_WIDTH = 1.5  # frame units; the height is 1
BACKGROUND_DEPTH_MM = 500.0  # the wall, behind the focus plane

# Linear reflectances in the red, green and blue filter bands; every band keeps some signal so that
# every object shows texture through all three filters (disparity needs it).
COLOURS: dict[str, tuple[float, float, float]] = {
    "terracotta": (0.66, 0.32, 0.18),
    "red": (0.78, 0.17, 0.14),
    "orange": (0.88, 0.46, 0.13),
    "yellow": (0.82, 0.74, 0.16),
    "green": (0.20, 0.60, 0.22),
    "dark green": (0.16, 0.42, 0.18),
    "blue": (0.15, 0.30, 0.72),
    "purple": (0.46, 0.20, 0.62),
    "white": (0.82, 0.82, 0.80),
    "wood": (0.62, 0.43, 0.24),
    "steel": (0.56, 0.58, 0.62),
    "bottle green": (0.22, 0.52, 0.30),
    "wall": (0.46, 0.43, 0.39),
}


# --- silhouettes -------------------------------------------------------------------------------------------


def _rotate(points: np.ndarray, centre: tuple[float, float], angle_deg: float) -> np.ndarray:
    if not angle_deg:
        return points
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    c = np.asarray(centre)
    return (points - c) @ rot.T + c


def _arc(cx: float, cy: float, rx: float, ry: float, start_deg: float, end_deg: float, n: int) -> np.ndarray:
    t = np.radians(np.linspace(start_deg, end_deg, n))
    return np.stack([cx + rx * np.cos(t), cy + ry * np.sin(t)], axis=1)


def ellipse(cx: float, cy: float, rx: float, ry: float, angle_deg: float = 0.0) -> Shape:
    """An ellipse (tomato, pot rim...) centred at (cx, cy), radii rx, ry, rotated clockwise on screen."""
    return Shape((_rotate(_arc(cx, cy, rx, ry, 0, 360, 160)[:-1], (cx, cy), angle_deg),))


def _rounded_rect_points(cx: float, cy: float, w: float, h: float, r: float) -> np.ndarray:
    r = min(r, w / 2, h / 2)
    x0, x1, y0, y1 = cx - w / 2 + r, cx + w / 2 - r, cy - h / 2 + r, cy + h / 2 - r
    return np.concatenate(
        [
            _arc(x1, y1, r, r, 0, 90, 12),
            _arc(x0, y1, r, r, 90, 180, 12),
            _arc(x0, y0, r, r, 180, 270, 12),
            _arc(x1, y0, r, r, 270, 360, 12),
        ]
    )


def rounded_rect(cx: float, cy: float, w: float, h: float, r: float = 0.02, angle_deg: float = 0.0) -> Shape:
    """A rounded rectangle (block, cup body, spatula head)."""
    return Shape((_rotate(_rounded_rect_points(cx, cy, w, h, r), (cx, cy), angle_deg),))


def pot(cx: float, bottom_y: float, height: float, top_width: float) -> Shape:
    """A flower pot: a tapered body under a wider rim."""
    rim_h = 0.16 * height
    body_top = bottom_y - height + rim_h
    body = np.array(
        [
            [cx - 0.5 * top_width * 0.92, body_top],
            [cx + 0.5 * top_width * 0.92, body_top],
            [cx + 0.34 * top_width, bottom_y],
            [cx - 0.34 * top_width, bottom_y],
        ]
    )
    rim = _rounded_rect_points(cx, bottom_y - height + rim_h / 2, top_width, rim_h, 0.008)
    return Shape((body, rim))


def bottle(cx: float, bottom_y: float, height: float, width: float) -> Shape:
    """A bottle: round-shouldered body, neck and cap."""
    body_top = bottom_y - 0.58 * height
    neck_w = 0.34 * width
    neck_bottom = bottom_y - 0.76 * height
    top = bottom_y - height
    right = np.concatenate(
        [
            _arc(cx + width / 2 - 0.04 * height, bottom_y - 0.04 * height, 0.04 * height, 0.04 * height, 90, 0, 8),
            np.array([[cx + width / 2, body_top]]),
            _arc(cx + neck_w / 2, body_top, width / 2 - neck_w / 2, body_top - neck_bottom, 0, -90, 12),
            np.array(
                [
                    [cx + neck_w / 2, top + 0.05 * height],
                    [cx + neck_w / 2 + 0.01, top + 0.05 * height],
                    [cx + neck_w / 2 + 0.01, top],
                ]
            ),
        ]
    )
    left = right[::-1].copy()
    left[:, 0] = 2 * cx - left[:, 0]
    return Shape((np.concatenate([right, left]),))


def cup(cx: float, bottom_y: float, height: float, top_width: float, handle: str = "right") -> Shape:
    """A cup: a slightly tapered body and a ring handle."""
    bottom_w = 0.78 * top_width
    top = bottom_y - height
    body = np.array(
        [
            [cx - top_width / 2, top],
            [cx + top_width / 2, top],
            [cx + bottom_w / 2, bottom_y],
            [cx - bottom_w / 2, bottom_y],
        ]
    )
    side = 1.0 if handle == "right" else -1.0
    hx = cx + side * 0.44 * top_width
    hy = top + 0.45 * height
    outer = _arc(hx, hy, 0.22 * height, 0.28 * height, -90, 90, 24)
    inner = _arc(hx, hy, 0.12 * height, 0.17 * height, 90, -90, 24)
    ring = np.concatenate([outer, inner])
    if side < 0:
        ring[:, 0] = 2 * hx - ring[:, 0]
    return Shape((body, ring))


def _stroke(
    x0: float, y0: float, x1: float, y1: float, profile: Callable[[np.ndarray], np.ndarray], n: int = 64
) -> np.ndarray:
    """A polygon along the segment (x0, y0)-(x1, y1) whose half-width at parameter t in [0, 1] is profile(t)."""
    t = np.linspace(0.0, 1.0, n)
    d = np.array([x1 - x0, y1 - y0])
    length = float(np.hypot(*d))
    u = d / length
    normal = np.array([-u[1], u[0]])
    centre = np.array([x0, y0]) + t[:, None] * d
    half = profile(t)[:, None]
    return np.concatenate([centre + half * normal, (centre - half * normal)[::-1]])


def carrot(top_x: float, top_y: float, tip_x: float, tip_y: float, width: float) -> Shape:
    """A carrot: a tapered root from a rounded top to a point."""
    return Shape(
        (
            _stroke(
                top_x,
                top_y,
                tip_x,
                tip_y,
                lambda t: 0.5 * width * np.sqrt(np.clip(1 - t, 0, 1)) * np.minimum(1.0, 0.6 + 8 * t),
            ),
        )
    )


def knife(handle_x: float, handle_y: float, tip_x: float, tip_y: float, width: float) -> Shape:
    """A kitchen knife: handle at one end, a blade tapering to the tip."""

    def profile(t: np.ndarray) -> np.ndarray:
        handle = np.where(t < 0.33, 0.36 * width, 0.0)
        blade = np.where(t >= 0.33, 0.5 * width * np.clip((1 - t) / 0.67, 0, 1) ** 0.35, 0.0)
        return np.maximum(handle + blade, 0.004)

    return Shape((_stroke(handle_x, handle_y, tip_x, tip_y, profile, 96),))


def spatula(end_x: float, end_y: float, head_x: float, head_y: float, handle_width: float, head_width: float) -> Shape:
    """A wooden spatula: a long handle widening into a flat head."""

    def profile(t: np.ndarray) -> np.ndarray:
        widen = np.clip((t - 0.62) / 0.12, 0.0, 1.0)
        half = 0.5 * (handle_width + (head_width - handle_width) * widen)
        return np.where(t > 0.96, half * np.sqrt(np.clip((1 - t) / 0.04, 0.05, 1)), half)

    return Shape((_stroke(end_x, end_y, head_x, head_y, profile, 128),))


# --- scenes ------------------------------------------------------------------------------------------------


def _object(
    id: int,
    name: str,
    colour: str,
    distance_mm: float,
    shape: Shape,
    photograph: str,
    paper_label: str | None,
    tile: float = 0.12,
    contrast: float = 0.32,
    slant: Slant | None = None,
) -> Layer:
    offset = ((id * 0.137) % 1.0, (id * 0.291) % 1.0)
    return Layer(
        id=id,
        name=name,
        colour=colour,
        reflectance=COLOURS[colour],
        distance_mm=distance_mm,
        texture=Texture(photograph, tile, contrast, offset),
        shape=shape,
        slant=slant,
        paper_label=paper_label,
    )


def _wall(focus_mm: float) -> Layer:
    return Layer(
        id=0,
        name="wall",
        colour="wall",
        reflectance=COLOURS["wall"],
        distance_mm=focus_mm + BACKGROUND_DEPTH_MM,
        texture=Texture("brick", 0.25, 0.35),
    )


def _paper_a(focus: float) -> Scene:
    depths = (90.0, 60.0, 30.0, 0.0, -30.0)
    objects = []
    for i, depth in enumerate(depths):
        size = 1000.0 / (1000.0 + depth)  # nearer pots look a little larger
        shape = pot(0.17 + 0.29 * i, 0.62 + 0.06 * i, 0.34 * size, 0.25 * size)
        objects.append(
            _object(
                i + 1,
                f"pot {'ABCDE'[i]}",
                "terracotta",
                focus + depth,
                shape,
                ("gravel", "coffee", "gravel", "brick", "coffee")[i],
                "ABCDE"[i],
                0.1 + 0.02 * i,
            )
        )
    return Scene(
        "paper-a",
        "Fig. 4 row a: five similar terracotta pots one behind the other, 3 cm apart, no overlap",
        tuple(objects),
        _wall(focus),
    )


def _paper_b(focus: float) -> Scene:
    objects = (
        _object(1, "blue block", "blue", focus + 35.0, rounded_rect(0.40, 0.56, 0.26, 0.34, 0.015), "grass", "A"),
        _object(2, "green block", "green", focus + 35.0, rounded_rect(1.10, 0.56, 0.26, 0.34, 0.015), "gravel", "B"),
        _object(
            3,
            "orange block",
            "orange",
            focus + 75.0,
            rounded_rect(0.75, 0.40, 0.86, 0.20, 0.012),
            "astronaut",
            "C",
            0.3,
        ),
        _object(4, "red block", "red", focus + 0.0, rounded_rect(0.75, 0.80, 0.30, 0.26, 0.015), "coffee", "D", 0.25),
    )
    return Scene(
        "paper-b",
        "Fig. 4 row b: blue and green blocks 3.5 cm behind focus, an orange block 7.5 cm behind "
        "overlapped by the blue block at one end and the green block at the other, a red block in focus",
        objects,
        _wall(focus),
    )


def _paper_c(focus: float) -> Scene:
    depths = (-60.0, -30.0, 0.0, 30.0, 60.0, 90.0)
    colours = ("red", "yellow", "green", "blue", "orange", "red")
    photos = ("gravel", "grass", "coffee", "brick", "astronaut", "chelsea")
    objects = []
    for i, depth in enumerate(depths):
        # A (nearest) at the bottom right; each block overlaps the next farther one on its left.
        k = 5 - i
        objects.append(
            _object(
                i + 1,
                f"{colours[i]} block {'ABCDEF'[i]}",
                colours[i],
                focus + depth,
                rounded_rect(0.18 + 0.228 * k, 0.36 + 0.07 * k, 0.26, 0.34, 0.015),
                photos[i],
                "ABCDEF"[i],
                0.14,
            )
        )
    return Scene(
        "paper-c",
        "Fig. 4 row c: six colour blocks one behind the other, 3 cm apart, two of them red",
        tuple(objects),
        _wall(focus),
    )


def _paper_d(focus: float) -> Scene:
    depths = (160.0, 90.0, 0.0, -80.0)
    colours = ("bottle green", "bottle green", "dark green", "bottle green")
    objects = []
    for i, depth in enumerate(depths):
        size = 1000.0 / (1000.0 + depth)
        objects.append(
            _object(
                i + 1,
                f"bottle {'ABCD'[i]}",
                colours[i],
                focus + depth,
                bottle(0.24 + 0.34 * i, 0.90, 0.70 * size, 0.22 * size),
                ("gravel", "grass", "gravel", "coffee")[i],
                "ABCD"[i],
                0.11,
            )
        )
    return Scene(
        "paper-d",
        "Fig. 4 row d: four similar green bottles one behind the other, 7, 9 and 8 cm apart",
        tuple(objects),
        _wall(focus),
    )


def _paper_e(focus: float) -> Scene:
    objects = (
        _object(1, "red tomato", "red", focus - 35.0, ellipse(0.46, 0.40, 0.13, 0.12), "moon", "A", 0.2, 0.4),
        _object(2, "red tomato", "red", focus - 40.0, ellipse(0.20, 0.78, 0.12, 0.11), "gravel", "B", 0.12),
        _object(3, "orange carrot", "orange", focus + 0.0, carrot(0.80, 0.14, 0.93, 0.94, 0.15), "grass", "C"),
        _object(4, "green tomato", "green", focus + 40.0, ellipse(1.20, 0.60, 0.14, 0.13), "coffee", "D", 0.2),
        _object(
            5,
            "wooden spatula",
            "wood",
            focus + 102.0,
            spatula(0.05, 0.30, 1.44, 0.62, 0.07, 0.22),
            "brick",
            "E",
            0.1,
            0.35,
        ),
    )
    return Scene(
        "paper-e",
        "Fig. 4 row e: a wooden spatula overlapped by a red tomato, an orange carrot and a green "
        "tomato, with a second red tomato 0.5 cm from the first",
        objects,
        _wall(focus),
    )


def _paper_f(focus: float) -> Scene:
    objects = (
        _object(1, "white cup", "white", focus + 170.0, cup(0.52, 0.70, 0.46, 0.42), "gravel", "A", 0.12),
        _object(2, "blue cup", "blue", focus + 65.0, cup(0.82, 0.80, 0.38, 0.34), "grass", "B", 0.12),
        _object(3, "red cup", "red", focus + 0.0, cup(1.08, 0.90, 0.30, 0.27), "coffee", "C", 0.2),
    )
    return Scene(
        "paper-f",
        "Fig. 4 row f: three cups of different colour and size overlapping, 6.5 and 10.5 cm apart",
        objects,
        _wall(focus),
    )


def _paper_g(focus: float) -> Scene:
    knife_shape = knife(0.10, 0.47, 1.40, 0.56, 0.10)
    slant = Slant(focus - 30.0, focus + 100.0, "x")  # a flat blade: 1/distance affine along x
    objects = (
        _object(1, "knife", "steel", slant.middle_mm, knife_shape, "gravel", "A-B", 0.1, 0.3, slant=slant),
        _object(2, "orange carrot", "orange", focus + 0.0, carrot(0.70, 0.12, 0.86, 0.92, 0.16), "grass", "C"),
    )
    return Scene(
        "paper-g",
        "Fig. 4 row g: a knife slanted along the optical axis, its left end 3 cm in front of the "
        "focus plane and its tip 10 cm behind, its middle behind a carrot in focus",
        objects,
        _wall(focus),
    )


PAPER_SCENES: dict[str, Callable[[float], Scene]] = {
    "paper-a": _paper_a,
    "paper-b": _paper_b,
    "paper-c": _paper_c,
    "paper-d": _paper_d,
    "paper-e": _paper_e,
    "paper-f": _paper_f,
    "paper-g": _paper_g,
}

# Table 1 ground truth, inter-object depth in mm from the focus plane, by paper label (for tests and docs).
TABLE1_INTER_OBJECT_DEPTH_MM: dict[str, dict[str, float]] = {
    "paper-a": {"A": 90, "B": 60, "C": 30, "D": 0, "E": -30},
    "paper-b": {"A": 35, "B": 35, "C": 75, "D": 0},
    "paper-c": {"A": -60, "B": -30, "C": 0, "D": 30, "E": 60, "F": 90},
    "paper-d": {"A": 160, "B": 90, "C": 0, "D": -80},
    "paper-e": {"A": -35, "B": -40, "C": 0, "D": 40, "E": 102},
    "paper-f": {"A": 170, "B": 65, "C": 0},
    "paper-g": {"A": -30, "B": 100, "C": 0},
}


def scene_names() -> list[str]:
    return list(PAPER_SCENES)


def paper_scene(name: str, focus_distance_mm: float) -> Scene:
    """The scene of Fig. 4 row `name` ("paper-a".."paper-g") for a camera focused at `focus_distance_mm`."""
    try:
        build = PAPER_SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene '{name}'; choose one of {', '.join(PAPER_SCENES)}") from None
    return build(focus_distance_mm)


def target_scene(
    distance_mm: float,
    *,
    photograph: str = "gravel",
    tile_height: float = 0.15,
    coverage: float = 1.0,
    background_distance_mm: float | None = None,
) -> Scene:
    """A calibration target: one textured fronto-parallel plane at `distance_mm` (object id 1).

    With `coverage` < 1 the target is a centred rectangle covering that fraction of the frame's
    width and height, in front of a wall at `background_distance_mm` (default: 500 mm behind it).
    """
    if coverage >= 1.0:
        shape = rounded_rect(FRAME_WIDTH / 2, 0.5, FRAME_WIDTH + 0.4, 1.4, 0.0)
        background = None
    else:
        shape = rounded_rect(FRAME_WIDTH / 2, 0.5, FRAME_WIDTH * coverage, coverage, 0.0)
        wall_mm = background_distance_mm if background_distance_mm is not None else distance_mm + 500.0
        background = Layer(0, "wall", "wall", COLOURS["wall"], wall_mm, Texture("brick", 0.25, 0.35))
    target = Layer(
        1,
        "target",
        "white",
        (0.7, 0.7, 0.7),
        distance_mm,
        Texture(photograph, tile_height, 0.35),
        shape=shape,
        paper_label=None,
    )
    return Scene(
        f"target-{distance_mm:.1f}mm", f"textured fronto-parallel target at {distance_mm:.1f} mm", (target,), background
    )
