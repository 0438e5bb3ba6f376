"""The simulated world's camera side: what the simulated EOS 70D photographs and shows in live view.

A shot is the MCA simulator's rendering (`render.py`) of one of the paper's Fig. 4 scenes (`scenes.py`)
through a camera profile's optics, packed as the CR2 a 70D writes (`cr2.py`). `scene_frame_source` and
`scene_live_view_source` are what `devices.cameras.open_camera("sim")` gives the simulated body, so the
application reaches the simulated world through the same call as a real camera.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mca.devices.sim.render import Scene, SensorModel, SimulationOptics, render
from mca.devices.sim.scenes import paper_scene, scene_names
from mca.processing.camera import CameraProfile

DEFAULT_PROFILE = "paper-70d"  # the body and lens the simulated EOS 70D is: the paper's prototype

# Render sizes: the fraction of the profile's image size (pixel pitch scales to match).
SIZES: dict[str, float] = {"full": 1.0, "small": 0.25}


@dataclass
class SimulatedCapture:
    """One simulated photograph and its ground truth (see `devices.sim.render.Rendering`)."""

    scene: str
    mosaic: np.ndarray  # (H, W) uint16 RGGB, black level included
    planes_linear: np.ndarray  # (H/2, W/2, 3) float32, noise-free, (value - black) / (white - black)
    truth: dict[str, Any]
    depth_mm: np.ndarray  # (H, W) float32 distance of the front-most surface
    labels: np.ndarray  # (H, W) uint16 object ids, 0 = background
    sensor: SensorModel
    optics: SimulationOptics


def size_scale(size: str | float) -> float:
    """The scale of a named size ("full", "small") or a number in (0, 1]."""
    if isinstance(size, str):
        if size not in SIZES:
            raise ValueError(f"unknown size '{size}'; choose one of {', '.join(SIZES)} or a scale in (0, 1]")
        return SIZES[size]
    return float(size)


def render_scene(
    scene: str | Scene,
    profile: CameraProfile,
    *,
    size: str | float = "full",
    seed: int | None = 0,
    optics: SimulationOptics | None = None,
    sensor: SensorModel | None = None,
    cosited: bool = False,
) -> SimulatedCapture:
    """Render a named paper scene ("paper-a".."paper-g") or a `Scene` as the profile's camera would take it.

    `optics` overrides the profile's nominal optics (e.g. `SimulationOptics.from_profile(p, s).perturbed(...)`
    for a lens that deviates from its profile); `size` is then ignored.
    """
    used_optics = optics if optics is not None else SimulationOptics.from_profile(profile, size_scale(size))
    used_sensor = sensor if sensor is not None else SensorModel()
    if isinstance(scene, str):
        scene = paper_scene(scene, used_optics.focus_distance_mm)
    rendering = render(scene, used_optics, used_sensor, seed=seed, cosited=cosited)
    truth = {
        "scene": rendering.truth["scene"],
        "profile": profile.name,
        "scale": used_optics.height_px / profile.height_px if profile.height_px else None,
    }
    truth.update({k: v for k, v in rendering.truth.items() if k not in truth})
    return SimulatedCapture(
        scene=scene.name,
        mosaic=rendering.mosaic,
        planes_linear=rendering.planes_linear,
        truth=truth,
        depth_mm=rendering.depth_mm,
        labels=rendering.labels,
        sensor=used_sensor,
        optics=used_optics,
    )


def capture_cr2_bytes(capture: SimulatedCapture, profile: CameraProfile) -> bytes:
    """The simulated photograph as the bytes of a Canon CR2 (what the simulated EOS hands over PTP)."""
    from mca.devices.sim.cr2 import Cr2Metadata, cr2_bytes

    lens = profile.lens
    metadata = Cr2Metadata(
        model=profile.model,
        iso=int(round(capture.sensor.iso)),
        f_number=float(lens.f_number) if lens is not None and lens.f_number else 1.8,
        focal_length_mm=capture.optics.focal_length_mm,
        focus_distance_m=capture.optics.focus_distance_mm / 1000.0,
    )
    return cr2_bytes(
        capture.mosaic,
        black_level=capture.sensor.black_level,
        white_level=capture.sensor.white_level,
        metadata=metadata,
    )


def scene_frame_source(size: str | float | None = None, profile_name: str = DEFAULT_PROFILE) -> Callable[[int], Any]:
    """The frame source of `--camera sim`: what the simulated EOS 70D "photographs" (index -> (name, bytes)).

    Shot N is the MCA simulator's rendering of the paper's Fig. 4 scene number N (paper-a ... paper-g,
    cycling), written as a Canon EOS 70D CR2, deterministic for a given index. `size` is "full"
    (5472 x 3648, the default), "small" or a scale in (0, 1]; the environment variable
    `MCA_SIM_SIZE` sets it for a whole session (the tests use "small").
    """
    from mca.devices.profiles import load_profile

    chosen_size = size if size is not None else os.environ.get("MCA_SIM_SIZE", "full")
    try:
        chosen_size = float(chosen_size)
    except (TypeError, ValueError):
        pass
    profile = load_profile(profile_name)
    scenes = scene_names()

    def frame(index: int) -> tuple[str, bytes]:
        scene = scenes[(index - 1) % len(scenes)]
        capture = render_scene(scene, profile, size=chosen_size, seed=index)
        return f"IMG_{index:04d}.CR2", capture_cr2_bytes(capture, profile)

    return frame


def scene_live_view_source(
    profile_name: str = DEFAULT_PROFILE, scene: str = "paper-a", size_px: tuple[int, int] = (960, 540)
) -> Callable[[int], bytes]:
    """Live-view JPEGs of the simulated 70D: the MCA simulator's rendering of `scene` at live-view size.

    Rendered once, on the first frame asked for (the 70D's live view is 960 x 540; the 3:2 rendering is
    cropped to 16:9 in the middle), then served for every frame.
    """
    cache: dict[str, bytes] = {}

    def frame(index: int) -> bytes:
        if "jpeg" not in cache:
            from mca.devices.profiles import load_profile
            from mca.processing.colour import linear_to_srgb8

            profile = load_profile(profile_name)
            width, height = size_px
            scale = 2.0 * width / (profile.width_px or 5472)  # the planes come at half the sensor's resolution
            capture = render_scene(scene, profile, size=min(1.0, scale), seed=1)
            planes = capture.planes_linear
            full_h = round(planes.shape[0] * width / planes.shape[1])
            rgb = cv2.resize(planes, (width, full_h), interpolation=cv2.INTER_AREA)
            top = max(0, (full_h - height) // 2)
            rgb = linear_to_srgb8(np.clip(rgb[top : top + height], 0.0, 1.0))
            ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
            if not ok:
                raise RuntimeError("could not encode the simulated live-view frame")
            cache["jpeg"] = encoded.tobytes()
        return cache["jpeg"]

    return frame
