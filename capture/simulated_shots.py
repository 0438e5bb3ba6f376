"""Simulated photographs on disk: `mca simulate`'s folders of captures and their truth files.

The simulated world itself (scenes, textures, the renderers, the CR2 writer, the simulated EOS 70D and
rail) lives in `devices/sim/`; this module writes what it renders. `mca simulate` calls `write_capture` (paper scenes) and `render_rgbd_capture`/`write_rgbd_capture`/
`render_rgbd_tree` (real photographs with known depth, `devices.sim.render_rgbd`). Ground truth
goes into a `truth/` subfolder beside the captures. Files are written atomically (temporary name in the
destination folder, then `os.replace`).
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.devices.sim.cr2 import Cr2Metadata, cr2_bytes
from mca.devices.sim.world import SimulatedCapture, capture_cr2_bytes
from mca.processing.camera import CameraProfile

TRUTH_DIR = "truth"  # ground truth lives in this subfolder of a render folder, where `mca process DIR` never looks


def write_cr2(
    path: str | os.PathLike[str],
    mosaic: np.ndarray,
    *,
    black_level: int = 2048,
    white_level: int = 15000,
    metadata: Cr2Metadata | None = None,
    bits_per_sample: int = 14,
    preview: bool = True,
) -> Path:
    """Write `mosaic` (H, W) uint16 RGGB as a Canon CR2 at `path`, atomically; returns the path.

    The file appears under its final name only once complete (written to a
    temporary name in the same folder, then renamed).
    """
    from mca.capture.outputs import write_bytes_atomic

    data = cr2_bytes(
        mosaic,
        black_level=black_level,
        white_level=white_level,
        metadata=metadata,
        bits_per_sample=bits_per_sample,
        preview=preview,
    )
    return write_bytes_atomic(Path(path), data)


def truth_json(truth: dict[str, Any]) -> str:
    """The truth dictionary as JSON text (numpy scalars converted, floats kept exact, non-finite as null)."""
    from mca.capture.outputs import json_safe

    return json.dumps(json_safe(truth), indent=2) + "\n"


def write_capture(capture: SimulatedCapture, profile: CameraProfile, out_dir: str | Path) -> dict[str, Path]:
    """Write `<scene>.CR2` into `out_dir` and its truth into `out_dir/truth/`: `<scene>.truth.json`,
    `<scene>.depth.tiff` and `<scene>.labels.png` (a subfolder, so that `mca process out_dir` sees only
    photographs). The CR2 is written last."""
    import cv2
    import tifffile

    from mca.capture.outputs import write_bytes_atomic

    out = Path(out_dir)
    truth_dir = out / TRUTH_DIR
    truth_dir.mkdir(parents=True, exist_ok=True)
    name = capture.scene
    paths = {}
    paths["truth"] = write_bytes_atomic(truth_dir / f"{name}.truth.json", truth_json(capture.truth).encode("utf-8"))
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer,
        capture.depth_mm.astype(np.float32),
        compression="zlib",
        metadata={"unit": "mm", "what": "distance from the lens of the front-most surface"},
    )
    paths["depth"] = write_bytes_atomic(truth_dir / f"{name}.depth.tiff", buffer.getvalue())
    ok, png = cv2.imencode(".png", capture.labels.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise OSError(f"could not encode the label image of scene '{name}' as PNG")
    paths["labels"] = write_bytes_atomic(truth_dir / f"{name}.labels.png", png.tobytes())
    paths["cr2"] = write_bytes_atomic(out / f"{name}.CR2", capture_cr2_bytes(capture, profile))
    return paths


# --- real photographs with known depth (RGB-D scenes, e.g. Middlebury) -------------------------------------------

RGBD_FORMATS = ("tiff", "cr2")
# The development set (docs/evaluation.md): tuned on the first group, figures reported on the second.
DEV_TUNING_SCENES = ("Art", "Cones", "Dolls", "Laundry", "Moebius", "Venus")
DEV_HELD_OUT_SCENES = ("Books", "Reindeer", "Teddy")
DEV_SEEDS = (1, 2)
DEV_WIDTH_PX = 1368  # dev renders are a quarter of the 70D's width (its pitch x 4), every scene resized to it
DEV_FULL_SCENE = "Art"  # rendered once more at the full 20 MP through CR2 (speed of the pipeline)
# How a render's pixels sit on the sensor. "frame": the photograph spans the whole sensor width (the pitch is the
# sensor's width over the image's; the file names the camera, as `mca process` then reads it). "native": each pixel
# of the photograph is one photosite of the body (its pixel_pitch_mm): a window of the sensor at full resolution, as a
# renderer that takes a photograph as it is and the camera's photosites would make it. At the same distances its
# disparities in pixels are width-of-sensor / width-of-image times larger (4x for a 1368-px render of the 70D), and
# so are its defocus discs: the regime of renders made by other code (docs/evaluation.md, twenty-ninth stop). The
# file then names no camera, so `mca process` takes the profile's pitch (`capture.api.optics_for`), and the render's
# profile states it with the render's size.
RENDER_PITCHES = ("frame", "native")


@dataclass
class RgbdSource:
    """An RGB-D scene as read from disk: sRGB image, stereo disparity (px of the image, larger = nearer)."""

    name: str
    image_srgb: np.ndarray  # (H, W, 3) float32 in [0, 1], R G B
    disparity: np.ndarray  # (H, W) float32 true stereo disparity in px of this image
    valid: np.ndarray  # (H, W) bool, False where the disparity is unknown
    image_path: Path
    disparity_path: Path
    disparity_scale: float  # stored value / this = disparity in px


@dataclass
class RgbdCapture:
    """One rendered capture of an RGB-D scene, ready to be written."""

    name: str
    image_bytes: bytes
    suffix: str  # ".tiff" or ".CR2"
    distance_mm: np.ndarray
    disparity_px: np.ndarray
    truth: dict[str, Any]
    profile_toml: str
    seconds: float


def middlebury_scale(source_text: str) -> float | None:
    """The disparity scale factor a Middlebury SOURCE.txt states ("Disparity scale factor: 4"), or None."""
    import re

    match = re.search(r"disparity scale factor\s*[:=]\s*([0-9]+(?:\.[0-9]+)?)", source_text, re.IGNORECASE)
    return float(match.group(1)) if match else None


def read_rgbd_source(
    image_path: str | Path, disparity_path: str | Path, disparity_scale: float | None = None, name: str | None = None
) -> RgbdSource:
    """Read an 8-bit sRGB image and its disparity map (0 = unknown); the scale comes from SOURCE.txt beside the
    disparity map when not given (1 when there is none). Raises ValueError naming the file on bad input."""
    import cv2

    image_path, disparity_path = Path(image_path), Path(disparity_path)
    if disparity_scale is None:
        source = disparity_path.parent / "SOURCE.txt"
        disparity_scale = middlebury_scale(source.read_text(errors="replace")) if source.is_file() else None
        if disparity_scale is None:
            disparity_scale = 1.0
    if not disparity_scale > 0:
        raise ValueError(f"{disparity_path}: the disparity scale must be positive, got {disparity_scale}")
    image = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{image_path}: cannot be read as an image; give an 8-bit sRGB PNG")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.dtype != np.uint8:
        raise ValueError(f"{image_path}: expected 8-bit sRGB samples, got {image.dtype}")
    disparity = cv2.imread(str(disparity_path), cv2.IMREAD_UNCHANGED)
    if disparity is None:
        raise ValueError(f"{disparity_path}: cannot be read as an image; give a grey disparity PNG (0 = unknown)")
    if disparity.ndim == 3:
        disparity = disparity[..., 0]
    if disparity.shape != image.shape[:2]:
        raise ValueError(
            f"{disparity_path}: {disparity.shape[1]}x{disparity.shape[0]} does not match the image "
            f"{image_path} ({image.shape[1]}x{image.shape[0]})"
        )
    valid = disparity > 0
    if valid.sum() < 2:
        raise ValueError(f"{disparity_path}: fewer than two pixels of known disparity")
    rgb = image[..., 2::-1].astype(np.float32) / np.float32(255.0)
    return RgbdSource(
        name=name or image_path.parent.name or image_path.stem,
        image_srgb=rgb,
        disparity=disparity.astype(np.float32) / np.float32(disparity_scale),
        valid=valid,
        image_path=image_path,
        disparity_path=disparity_path,
        disparity_scale=float(disparity_scale),
    )


def resize_rgbd(source: RgbdSource, scale: float, crop_aspect: float | None = None) -> RgbdSource:
    """The scene at `scale` times its size (area averaging down, bicubic up; disparity by nearest neighbour and
    its values scaled), optionally first cropped about the centre to width/height = `crop_aspect`."""
    import cv2

    image, disparity, valid = source.image_srgb, source.disparity, source.valid
    if crop_aspect is not None:
        h, w = valid.shape
        if w / h > crop_aspect:
            cw = int(round(h * crop_aspect))
            box = (slice(None), slice((w - cw) // 2, (w - cw) // 2 + cw))
        else:
            ch = int(round(w / crop_aspect))
            box = (slice((h - ch) // 2, (h - ch) // 2 + ch), slice(None))
        image, disparity, valid = image[box], disparity[box], valid[box]
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    if scale != 1.0:
        h, w = valid.shape
        size = (max(2, int(round(w * scale))), max(2, int(round(h * scale))))
        interpolation = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_CUBIC
        image = np.clip(cv2.resize(image, size, interpolation=interpolation), 0.0, 1.0)
        disparity = cv2.resize(disparity, size, interpolation=cv2.INTER_NEAREST) * np.float32(size[0] / w)
        valid = cv2.resize(valid.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    h, w = valid.shape
    h2, w2 = h - h % 2, w - w % 2  # an even size: a Bayer mosaic and the half-resolution planes need one
    return RgbdSource(
        source.name,
        np.ascontiguousarray(image[:h2, :w2]),
        np.ascontiguousarray(disparity[:h2, :w2]),
        np.ascontiguousarray(valid[:h2, :w2]),
        source.image_path,
        source.disparity_path,
        source.disparity_scale,
    )


def sensor_width_mm(profile: CameraProfile) -> float:
    """Width of the sensor an image spans, as `mca process` takes it for a render written by us.

    Our files name the profile's camera model; the reader then takes the pitch as the body's sensor
    width (capture/sensors.py) over the image's long side, for RGB images and downscaled raws alike,
    and the body's photosite pitch for a full-size raw. Without a known body: the profile's pitch times
    its width.
    """
    from mca.capture.sensors import sensor_for

    spec = sensor_for(profile.model, "Canon")
    if spec is not None:
        return spec.width_mm
    if profile.pixel_pitch_mm is None or not profile.width_px:
        raise ValueError(f"profile '{profile.name}' gives neither a known camera body nor pitch and width")
    return profile.pixel_pitch_mm * profile.width_px


def check_render_pitch(profile: CameraProfile, pitch: str, fmt: str) -> None:
    """Refuse a pitch `mca process` could not read back as rendered (`RENDER_PITCHES`)."""
    if pitch not in RENDER_PITCHES:
        raise ValueError(f"pitch must be one of {', '.join(RENDER_PITCHES)}, got {pitch!r}")
    if pitch != "native":
        return
    if fmt != "tiff":
        raise ValueError(
            "--pitch native renders a window of the sensor at the body's pitch, which a CR2 cannot carry (a raw is "
            "the body's whole frame or a downscaled one): use --format tiff"
        )
    if profile.pixel_pitch_mm is None:
        raise ValueError(f"profile '{profile.name}' gives no camera.pixel_pitch_mm for --pitch native")


def check_render_size(profile: CameraProfile, width_px: int, height_px: int, fmt: str) -> None:
    """Refuse sizes whose file `mca process` would read with another pitch or orientation than rendered."""
    from mca.capture.api import DOWNSCALED_RAW_RATIO
    from mca.capture.sensors import sensor_for

    if width_px < height_px:
        raise ValueError(
            f"render {width_px}x{height_px} is portrait; the reader takes the long side as the sensor width: "
            "rotate the scene to landscape"
        )
    spec = sensor_for(profile.model, "Canon")
    if (
        fmt == "cr2"
        and spec is not None
        and width_px != spec.width_px
        and width_px * DOWNSCALED_RAW_RATIO > spec.width_px
    ):
        raise ValueError(
            f"a CR2 {width_px} px wide is read with the full-size photosite pitch of the {spec.model}: "
            f"render it {spec.width_px} px wide or at most {int(spec.width_px / DOWNSCALED_RAW_RATIO)} px"
        )
    if fmt == "cr2" and (width_px < 22 or height_px < 22):
        raise ValueError(f"a CR2 needs at least 22x22 pixels, got {width_px}x{height_px}")


def profile_toml(profile: CameraProfile, sensor_distance_mm: float, size_px: tuple[int, int] | None = None) -> str:
    """The profile as a file with its lens focused as rendered (d_ls); the camera's photosite pitch and size stay
    the body's: `mca process` takes a render's pixel pitch from the file (its model and size). `size_px`
    (width, height): the render's own size instead, for a window of the sensor at the body's pitch (a file that
    names no camera, whose pixels are then the profile's `pixel_pitch_mm`, with no note that they may not be)."""
    ap = profile.aperture
    lines = [f'name = "{profile.name}-render"', "[camera]", f'model = "{profile.model}"']
    if profile.pixel_pitch_mm is not None:
        lines.append(f"pixel_pitch_mm = {profile.pixel_pitch_mm!r}")
    if size_px is not None:
        lines += [f"width_px = {size_px[0]}", f"height_px = {size_px[1]}"]
    elif profile.width_px and profile.height_px:
        lines += [f"width_px = {profile.width_px}", f"height_px = {profile.height_px}"]
    if profile.lens is not None:
        lines += ["[lens]", f"focal_length_mm = {profile.lens.focal_length_mm!r}"]
        lines.append(f"sensor_distance_mm = {sensor_distance_mm!r}")
        if profile.lens.f_number is not None:
            lines.append(f"f_number = {profile.lens.f_number!r}")
    lines += [
        "[aperture]",
        f"filter_diameter_mm = {ap.filter_diameter_mm!r}",
        f"red = [{ap.red_mm[0]!r}, {ap.red_mm[1]!r}]",
        f"green = [{ap.green_mm[0]!r}, {ap.green_mm[1]!r}]",
        f"blue = [{ap.blue_mm[0]!r}, {ap.blue_mm[1]!r}]",
    ]
    if ap.diameter_mm is not None:
        lines.append(f"diameter_mm = {ap.diameter_mm!r}")
    return "\n".join(lines) + "\n"


def render_rgbd_capture(
    source: RgbdSource,
    profile: CameraProfile,
    *,
    fmt: str = "tiff",
    focus_distance_mm: float | None = None,
    depth_range: Any = None,
    realism: Any = None,
    seed: int = 0,
    name: str | None = None,
    extra_truth: dict[str, Any] | None = None,
    pitch: str = "frame",
) -> RgbdCapture:
    """Render `source` (already at the render size) as the profile's MCA camera focused at `focus_distance_mm`
    (default: the profile's), its valid disparity mapped onto `depth_range` (default: 150 mm before to 300 mm
    behind the focus plane), as a 16-bit linear TIFF ("tiff") or a CR2 ("cr2"); `pitch` one of `RENDER_PITCHES`
    (see there)."""
    import time

    from mca.devices.sim.render_rgbd import DepthRange, Realism, render_rgbd, rgbd_optics

    if fmt not in RGBD_FORMATS:
        raise ValueError(f"format must be one of {', '.join(RGBD_FORMATS)}, got {fmt!r}")
    if profile.lens is None:
        raise ValueError(f"profile '{profile.name}' has no lens: pick one with optics (e.g. paper-70d)")
    started = time.perf_counter()
    h, w = source.valid.shape
    check_render_pitch(profile, pitch, fmt)
    check_render_size(profile, w, h, fmt)
    focus = float(focus_distance_mm) if focus_distance_mm is not None else profile.lens.focus_distance_mm
    depth_range = depth_range if depth_range is not None else DepthRange(focus - 150.0, focus + 300.0)
    realism = realism if realism is not None else Realism()
    native = pitch == "native"
    if native:
        assert profile.pixel_pitch_mm is not None  # check_render_pitch refused a profile without it
        width_mm = profile.pixel_pitch_mm * w
    else:
        width_mm = sensor_width_mm(profile)
    optics = rgbd_optics(profile, w, h, focus, width_mm)
    rendering = render_rgbd(
        source.image_srgb,
        source.disparity,
        source.valid,
        optics,
        depth_range,
        realism,
        output="mosaic" if fmt == "cr2" else "rgb",
        seed=seed,
    )
    sensor = realism.sensor
    if fmt == "cr2":
        from mca.devices.sim.cr2 import Cr2Metadata, cr2_bytes

        metadata = Cr2Metadata(
            model=profile.model,
            iso=int(round(sensor.iso)),
            f_number=float(profile.lens.f_number) if profile.lens.f_number else 1.8,
            focal_length_mm=optics.focal_length_mm,
            focus_distance_m=focus / 1000.0,
        )
        data = cr2_bytes(
            rendering.image_dn, black_level=sensor.black_level, white_level=sensor.white_level, metadata=metadata
        )
        suffix = ".CR2"
    else:
        from mca.devices.sim.render_rgbd import dn_to_linear16

        data = linear_tiff_bytes(dn_to_linear16(rendering.image_dn, sensor), None if native else profile.model)
        suffix = ".tiff"
    label = name or source.name
    truth = {
        "scene": label,
        "kind": "rgbd",
        "profile": profile.name,
        "image": label + suffix,
        "format": fmt,
        "pitch": pitch,
        "source": {
            "image": str(source.image_path),
            "disparity": str(source.disparity_path),
            "disparity_scale": source.disparity_scale,
        },
    }
    truth.update(extra_truth or {})
    truth.update(rendering.truth)
    truth["files"] = {
        "distance_mm": f"{label}.distance.tiff",
        "disparity_px": f"{label}.disparity.tiff",
        "profile": f"{label}.profile.toml",
    }
    return RgbdCapture(
        name=label,
        image_bytes=data,
        suffix=suffix,
        distance_mm=rendering.distance_mm,
        disparity_px=rendering.disparity_px,
        truth=truth,
        profile_toml=profile_toml(profile, optics.sensor_distance_mm, (w, h) if native else None),
        seconds=time.perf_counter() - started,
    )


def linear_tiff_bytes(rgb16: np.ndarray, model: str | None) -> bytes:
    """A 16-bit linear RGB TIFF naming the camera (Make/Model), so that `mca process` knows the sensor it spans;
    with `model` None it names none (a window of the sensor at the body's pitch: the profile's pitch applies)."""
    import tifffile

    tags = []
    if model is not None:
        make = model.split()[0] if model.split() else "Canon"
        tags = [(271, "s", 0, make, True), (272, "s", 0, model, True)]
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, np.ascontiguousarray(rgb16, dtype=np.uint16), photometric="rgb", metadata=None, extratags=tags
    )
    return buffer.getvalue()


def write_rgbd_capture(capture: RgbdCapture, out_dir: str | Path) -> dict[str, Path]:
    """Write the capture into `out_dir` and its truth into `out_dir/truth/`: `<name>.json` (description),
    `<name>.distance.tiff` (mm, NaN unknown), `<name>.disparity.tiff` (red-blue px of the render, NaN unknown),
    `<name>.profile.toml` (the profile as focused for this render). The image is written last."""
    from mca.capture.outputs import write_bytes_atomic, write_tiff_float32

    out = Path(out_dir)
    truth_dir = out / TRUTH_DIR
    truth_dir.mkdir(parents=True, exist_ok=True)
    name = capture.name
    paths = {
        "distance": write_tiff_float32(truth_dir / f"{name}.distance.tiff", capture.distance_mm),
        "disparity": write_tiff_float32(truth_dir / f"{name}.disparity.tiff", capture.disparity_px),
        "profile": write_bytes_atomic(truth_dir / f"{name}.profile.toml", capture.profile_toml.encode("utf-8")),
        "truth": write_bytes_atomic(truth_dir / f"{name}.json", truth_json(capture.truth).encode("utf-8")),
    }
    paths["image"] = write_bytes_atomic(out / f"{name}{capture.suffix}", capture.image_bytes)
    return paths


def find_rgbd_scenes(tree: str | Path) -> list[Path]:
    """Scene folders under `tree` holding im.png and disp.png (the tree itself when it is one), sorted by name."""
    root = Path(tree)
    if (root / "im.png").is_file() and (root / "disp.png").is_file():
        return [root]
    return sorted(p for p in root.iterdir() if p.is_dir() and (p / "im.png").is_file() and (p / "disp.png").is_file())


@dataclass
class TreeOutcome:
    """What became of one (scene, seed) of a folder render."""

    name: str
    status: str  # "rendered", "cached" or "failed"
    seconds: float = 0.0
    summary: str = ""
    reason: str | None = None


def render_rgbd_tree(
    tree: str | Path,
    out_dir: str | Path,
    profile: CameraProfile,
    *,
    seeds: tuple[int, ...] = DEV_SEEDS,
    scenes: tuple[str, ...] | None = None,
    fmt: str = "tiff",
    scale: float | None = None,
    width_px: int | None = DEV_WIDTH_PX,
    full_size: bool = False,
    force: bool = False,
    on_outcome: Any = None,
    pitch: str = "frame",
) -> list[TreeOutcome]:
    """Render every scene of a Middlebury-style tree once per seed into `out_dir`, with realism drawn at random
    from the seed (focus, depth range, ISO, exposure, crosstalk, vignetting; `draw_scene_settings`).

    Size: `scale` times the scene's size when given, else resized to `width_px` wide (None: its own size);
    `full_size` crops to the profile's aspect and renders at the profile's full size. `pitch` one of
    `RENDER_PITCHES` ("native" renders are named `<Scene>-s<seed>-native`). Renders whose truth and image exist
    are kept (cached) unless `force`. A scene that fails is reported and the rest go on.
    """
    import time

    from mca.devices.sim.render_rgbd import draw_scene_settings

    outcomes = []
    folders = find_rgbd_scenes(tree)
    if scenes is not None:
        wanted = {s.lower() for s in scenes}
        folders = [f for f in folders if f.name.lower() in wanted]
    for folder in folders:
        for seed in seeds:
            name = f"{folder.name}-s{seed}" + ("-20mp" if full_size else "") + ("-native" if pitch == "native" else "")
            suffix = ".CR2" if fmt == "cr2" else ".tiff"
            out = Path(out_dir)
            if not force and (out / TRUTH_DIR / f"{name}.json").is_file() and (out / f"{name}{suffix}").is_file():
                outcome = TreeOutcome(name, "cached", summary="kept (already rendered)")
            else:
                started = time.perf_counter()
                try:
                    source = read_rgbd_source(folder / "im.png", folder / "disp.png", name=folder.name)
                    if full_size:
                        if not profile.width_px or not profile.height_px:
                            raise ValueError(f"profile '{profile.name}' has no image size for a full-size render")
                        aspect = profile.width_px / profile.height_px
                        h, w = source.valid.shape
                        cropped_w = min(w, h * aspect)
                        factor = profile.width_px / cropped_w
                        source = resize_rgbd(source, factor, crop_aspect=aspect)
                    else:
                        width = source.valid.shape[1]
                        factor = scale if scale is not None else (width_px / width if width_px else 1.0)
                        source = resize_rgbd(source, factor)
                    # one stream per (scene, seed): a scene's draw does not depend on which others are rendered
                    rng = np.random.default_rng([seed, _stable_hash(folder.name)])
                    draw = draw_scene_settings(rng)
                    capture = render_rgbd_capture(
                        source,
                        profile,
                        fmt=fmt,
                        focus_distance_mm=draw.focus_distance_mm,
                        depth_range=draw.depth_range,
                        realism=draw.realism,
                        seed=int(rng.integers(2**31)),
                        name=name,
                        extra_truth={"draw": draw.as_dict(), "draw_seed": seed, "source_scale": factor},
                        pitch=pitch,
                    )
                    write_rgbd_capture(capture, out)
                    outcome = TreeOutcome(
                        name, "rendered", time.perf_counter() - started, summary=describe_rgbd_truth(capture.truth)
                    )
                except (ValueError, OSError) as exc:
                    outcome = TreeOutcome(name, "failed", time.perf_counter() - started, reason=str(exc))
            outcomes.append(outcome)
            if on_outcome is not None:
                on_outcome(outcome)
    return outcomes


def _stable_hash(text: str) -> int:
    import zlib

    return zlib.crc32(text.encode("utf-8"))


def describe_rgbd_truth(truth: dict[str, Any]) -> str:
    """One line saying what a render got: size, focus, depth range, disparity range and realism."""
    realism = truth.get("realism", {})
    sensor = realism.get("sensor", {})
    low, high = truth.get("disparity_range_px") or (float("nan"), float("nan"))
    crosstalk = realism.get("crosstalk")
    leak = 0.0 if crosstalk is None else max(1.0 - crosstalk[i][i] for i in range(3))
    placement = truth.get("draw", {}).get("focus_placement")
    optics = truth.get("optics", {})
    return (
        f"{optics.get('width_px')}x{optics.get('height_px')} {truth.get('format')}, focus "
        f"{truth['focus_distance_mm']:.0f} mm{f' ({placement})' if placement else ''}, "
        f"{truth['near_mm']:.0f}..{truth['far_mm']:.0f} mm, disparity {low:+.1f}..{high:+.1f} px, "
        f"ISO {sensor.get('iso', 0):.0f}, exposure {sensor.get('exposure', 0):.2f}, "
        f"crosstalk {'off' if crosstalk is None else f'{100 * leak:.0f} %'}, vignetting {realism.get('vignetting')}"
    )
