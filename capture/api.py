"""The Python entry points: one photograph (a file, or arrays in a `RawFrame`) and a camera profile in, a `DepthResult` out.

`mca process` runs the very same functions (`capture.pipeline_app.process_file` calls `run_depth`),
so the API and the command line cannot drift apart. What they take care of, which a bare call of
`processing.pipeline.run_pipeline` leaves to its caller:

* **plane pitch vs input pitch**: a Bayer raw's planes are half resolution (`pixel_scale` 2), while
  disparities, the optics and the pinhole are in input-image pixels (the photosite pitch);
* **downscaled raws** (Canon mRAW/sRAW, the simulator's small frames): a raw much narrower than its
  body's sensor spans the same sensor with larger pixels (`input_pixel_pitch_mm`);
* **Bayer channel offsets**: the R and B samples of a 2x2 quad sit a quarter plane pixel off the G
  centre; without `channel_offsets_px` that offset reads as disparity (~7 mm at the paper's setup).

Example (README, "Use from Python")::

    import mca
    result = mca.depth_from_file("IMG_0001.CR2", "paper-70d")
    result.depth_mm          # (H, W) mm at processing resolution; result.pixel_scale input px per pixel
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.capture.raw import RawFrame, read_raw
from mca.processing.camera import CameraProfile
from mca.processing.colour import CameraColour
from mca.processing.optics import MCAOptics
from mca.processing.pinhole import PinholeCamera
from mca.processing.result import DepthResult, Recorder

PipelineFunction = Callable[..., DepthResult]
QUALITIES = ("full", "preview")  # `--quality`: the evaluated defaults, or the faster setting for live use
DOWNSCALED_RAW_RATIO = 1.5  # a raw this much narrower than its body's active area is a downscaled one


@dataclass
class LoadedInput:
    """An input photograph ready for the pipeline."""

    frame: RawFrame  # what the recorder logs
    planes: np.ndarray  # (H, W, 3) float32 linear camera RGB at processing resolution
    pixel_scale: float  # input-image pixels per processing pixel
    input_size_px: tuple[int, int]  # (width, height) of the input image
    pixel_pitch_mm: float | None  # pitch of one input-image pixel, when known
    metadata: dict[str, Any]

    @property
    def colour(self) -> CameraColour:
        """Camera RGB to sRGB for the displayed images (as-shot white balance and colour matrix)."""
        return self.frame.colour


def input_pixel_pitch_mm(frame: RawFrame, input_width_px: int) -> float | None:
    """Pitch of one input-image pixel on the sensor, when the file says which body took it.

    A raw carries its body's photosite pitch; but a raw far narrower than that body's sensor
    (Canon mRAW/sRAW, the simulator's `--size small`) spans the same sensor with fewer, larger
    pixels, so its pitch is the sensor width over its width, as for RGB images.
    """
    scale = 2.0 if frame.half_resolution else 1.0
    pitch = frame.pixel_pitch_mm / scale if frame.pixel_pitch_mm else None
    if frame.half_resolution and pitch is not None:
        from mca.capture.sensors import sensor_for

        spec = sensor_for(frame.metadata.model, frame.metadata.make)
        if spec is not None and spec.width_px >= DOWNSCALED_RAW_RATIO * input_width_px:
            pitch = spec.width_mm / input_width_px
    return pitch


def bayer_channel_offsets_px(cfa_pattern: str | None) -> tuple[tuple[float, float], ...] | None:
    """(dx, dy) of the R, G, B samples from the centre of their 2x2 block, in half-resolution pixels.

    `cfa_pattern` names the colours of the top-left 2x2 row by row ("RGGB" gives red at (-0.25, -0.25),
    the mean of the greens at the centre, blue at (+0.25, +0.25)); None when it is not a Bayer pattern.
    """
    if not cfa_pattern or sorted(cfa_pattern.upper()) != ["B", "G", "G", "R"]:
        return None
    sites: dict[str, list[tuple[int, int]]] = {"R": [], "G": [], "B": []}
    for index, letter in enumerate(cfa_pattern.upper()):
        sites[letter].append((index % 2, index // 2))
    return tuple(
        (float(np.mean([x for x, _ in sites[c]]) - 0.5) / 2.0, float(np.mean([y for _, y in sites[c]]) - 0.5) / 2.0)
        for c in "RGB"
    )


def prepare(frame: RawFrame) -> LoadedInput:
    """A frame as the pipeline takes it: its planes, input pixels per plane pixel, input size and pitch."""
    planes = np.asarray(frame.planes, dtype=np.float32)
    if planes.ndim != 3 or planes.shape[2] != 3:
        raise ValueError(f"{frame.path}: planes must be (H, W, 3) linear R, G, B, got shape {planes.shape}")
    height, width = planes.shape[:2]
    scale = 2.0 if frame.half_resolution else 1.0
    size = (int(round(width * scale)), int(round(height * scale)))
    return LoadedInput(
        frame=frame,
        planes=planes,
        pixel_scale=scale,
        input_size_px=size,
        pixel_pitch_mm=input_pixel_pitch_mm(frame, size[0]),
        metadata=dataclasses.asdict(frame.metadata),
    )


def read_input(path: str | os.PathLike[str]) -> LoadedInput:
    """Read any photograph `read_raw` reads; Bayer raws give half-resolution planes (pixel_scale 2).

    Raises `capture.raw.RawReadError` naming the file when it cannot be read.
    """
    return prepare(read_raw(path))


def resolve_profile(profile: str | os.PathLike[str] | CameraProfile) -> CameraProfile:
    """A `CameraProfile` as given, or loaded from a built-in name ("paper-70d") or a TOML path."""
    if isinstance(profile, CameraProfile):
        return profile
    from mca.devices.profiles import load_profile

    return load_profile(os.fspath(profile))


def optics_for(profile: CameraProfile, loaded: LoadedInput) -> MCAOptics | None:
    """MCAOptics in input-image pixels, or None when the profile has no lens data (disparity-only results).

    The input pixel's pitch comes from the file when it says which body took it, else from the profile.
    """
    if profile.lens is None:
        return None
    pitch = loaded.pixel_pitch_mm or profile.pixel_pitch_mm
    if pitch is None:
        return None
    return MCAOptics.from_profile(profile, pixel_pitch_mm=pitch)


def pitch_note(profile: CameraProfile, loaded: LoadedInput) -> str | None:
    """A sentence for the user when the input-pixel pitch is an assumption that may be wrong: the file names no
    camera body we know, so its pitch is the profile's, and its size is not the sensor's the profile states.
    That pitch is right for a crop at full resolution and wrong by the scale for a downscaled frame (distances
    come out that many times too near or too far), and nothing in the file tells the two apart. None otherwise."""
    if loaded.pixel_pitch_mm is not None or profile.lens is None or profile.pixel_pitch_mm is None:
        return None
    if profile.width_px is None or profile.height_px is None:
        return None
    width, height = loaded.input_size_px
    if (width, height) == (profile.width_px, profile.height_px):
        return None
    pitch = profile.pixel_pitch_mm
    downscaled = pitch * profile.width_px / width
    return (
        f"gives no pixel pitch (it names no camera body mca knows) and is {width}x{height} pixels, not the "
        f"{profile.width_px}x{profile.height_px} of profile {profile.name}'s sensor: each pixel was taken as "
        f"{pitch:.6g} mm (the profile's pixel_pitch_mm), right for a crop at full resolution. If the image is "
        f"the whole frame scaled down, its pixels are {downscaled:.6g} mm and the distances are off: process it "
        "with a profile whose pixel_pitch_mm is that"
    )


def camera_for(optics: MCAOptics | None, loaded: LoadedInput) -> PinholeCamera | None:
    """The pinhole of every 3D output of this input (processing/pinhole.py), None without optics."""
    if optics is None:
        return None
    return PinholeCamera.from_optics(optics.pixel_pitch_mm, optics.sensor_distance_mm, *loaded.input_size_px)


def pipeline_options(loaded: LoadedInput) -> dict[str, Any]:
    """The keyword arguments of `run_pipeline` that follow from the input itself (the Bayer channel offsets).

    Refuses a half-resolution frame whose colour-filter pattern is unknown: its R and B samples sit a
    quarter plane pixel off the centre in a direction only the pattern tells, and guessing would shift
    every depth.
    """
    if not loaded.frame.half_resolution:
        return {}
    pattern = loaded.metadata.get("cfa_pattern")
    offsets = bayer_channel_offsets_px(pattern)
    if offsets is None:
        raise ValueError(
            f"{loaded.frame.path}: half-resolution Bayer planes need their colour-filter pattern "
            f"(cfa_pattern such as 'RGGB', got {pattern!r}); without it the Bayer sample offsets read as disparity"
        )
    return {"channel_offsets_px": offsets}


def check_quality(quality: str) -> str:
    """`quality` when it is one of `QUALITIES`, else a ValueError that lists them."""
    if quality not in QUALITIES:
        raise ValueError(f"quality must be one of {', '.join(QUALITIES)}, not {quality!r}")
    return quality


def pipeline_params(quality: str = "full") -> Any:
    """The `processing.pipeline.PipelineParams` of a quality setting ("full": the evaluated defaults, "preview")."""
    from mca.processing.pipeline import PipelineParams

    return PipelineParams.for_quality(check_quality(quality))


def run_depth(
    loaded: LoadedInput,
    profile: CameraProfile,
    *,
    optics: MCAOptics | None = None,
    pipeline: PipelineFunction | None = None,
    recorder: Recorder | None = None,
    quality: str = "full",
) -> DepthResult:
    """Run the depth pipeline on a prepared input with everything the input implies; the one place that does.

    `optics` defaults to `optics_for(profile, loaded)`; `pipeline` replaces
    `processing.pipeline.run_pipeline` (tests); `recorder` receives each stage's results; `quality`
    ("full" or "preview") picks the pipeline's parameters (`pipeline_params`).
    """
    params = pipeline_params(quality)
    if optics is None:
        optics = optics_for(profile, loaded)
    if pipeline is None:
        from mca.processing.pipeline import run_pipeline

        pipeline = run_pipeline
    result = pipeline(
        loaded.planes,
        profile.aperture,
        optics,
        pixel_scale=loaded.pixel_scale,
        recorder=recorder,
        params=params,
        **pipeline_options(loaded),
    )
    if not np.isclose(result.pixel_scale, loaded.pixel_scale):
        result = dataclasses.replace(result, pixel_scale=loaded.pixel_scale)
    return result


def depth_from_frame(
    frame: RawFrame,
    profile: str | os.PathLike[str] | CameraProfile,
    *,
    recorder: Recorder | None = None,
    quality: str = "full",
) -> DepthResult:
    """Depth of a photograph already in memory (`read_raw`'s result, or `RawFrame.from_planes(...)` of arrays).

    `profile` is a `CameraProfile`, a built-in name or a profile TOML path. The result is at processing
    resolution: `result.pixel_scale` input pixels per result pixel, disparities in input pixels, depths in
    mm from the lens (None without lens data). The same function `mca process` runs; `quality` "preview" is
    the faster setting for live use (its accuracy beside "full" in docs/evaluation.md).
    """
    chosen = resolve_profile(profile)
    return run_depth(prepare(frame), chosen, recorder=recorder, quality=quality)


def depth_from_file(
    path: str | os.PathLike[str],
    profile: str | os.PathLike[str] | CameraProfile,
    *,
    recorder: Recorder | None = None,
    quality: str = "full",
) -> DepthResult:
    """Depth of the photograph at `path` (CR2, DNG, TIFF, PNG, JPEG, PPM): see `depth_from_frame`."""
    return depth_from_frame(read_raw(Path(path)), profile, recorder=recorder, quality=quality)


__all__ = [
    "QUALITIES",
    "LoadedInput",
    "bayer_channel_offsets_px",
    "camera_for",
    "check_quality",
    "depth_from_file",
    "depth_from_frame",
    "input_pixel_pitch_mm",
    "optics_for",
    "pipeline_options",
    "pipeline_params",
    "pitch_note",
    "prepare",
    "read_input",
    "resolve_profile",
    "run_depth",
]
