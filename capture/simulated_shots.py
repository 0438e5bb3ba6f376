"""Simulated photographs: render a scene through a profile's optics, package it as a CR2 and write its truth files.

The simulated camera and the calibration sweep call `render_scene` and `capture_cr2_bytes`;
`mca simulate` calls `write_capture`. Files are written atomically (temporary name in the
destination folder, then `os.replace`).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.processing.camera import CameraProfile
from mca.processing.scenes import paper_scene
from mca.processing.simulate import Scene, SensorModel, SimulationOptics, render

# Render sizes: the fraction of the profile's image size (pixel pitch scales to match).
SIZES: dict[str, float] = {"full": 1.0, "small": 0.25}


@dataclass
class SimulatedCapture:
    """One simulated photograph and its ground truth (see `processing.simulate.Rendering`)."""

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
    from mca.capture.cr2 import Cr2Metadata, cr2_bytes

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


def truth_json(truth: dict[str, Any]) -> str:
    """The truth dictionary as JSON text (numpy scalars converted, floats kept exact, non-finite as null)."""
    from mca.capture.outputs import json_safe

    return json.dumps(json_safe(truth), indent=2) + "\n"


def write_capture(capture: SimulatedCapture, profile: CameraProfile, out_dir: str | Path) -> dict[str, Path]:
    """Write `<scene>.CR2`, `<scene>.truth.json`, `<scene>.depth.tiff` and `<scene>.labels.png` into `out_dir`."""
    import cv2
    import tifffile

    from mca.capture.outputs import write_bytes_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = capture.scene
    paths = {}
    paths["cr2"] = write_bytes_atomic(out / f"{name}.CR2", capture_cr2_bytes(capture, profile))
    paths["truth"] = write_bytes_atomic(out / f"{name}.truth.json", truth_json(capture.truth).encode("utf-8"))
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer,
        capture.depth_mm.astype(np.float32),
        compression="zlib",
        metadata={"unit": "mm", "what": "distance from the lens of the front-most surface"},
    )
    paths["depth"] = write_bytes_atomic(out / f"{name}.depth.tiff", buffer.getvalue())
    ok, png = cv2.imencode(".png", capture.labels.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise OSError(f"could not encode the label image of scene '{name}' as PNG")
    paths["labels"] = write_bytes_atomic(out / f"{name}.labels.png", png.tobytes())
    return paths
