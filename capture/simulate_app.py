"""The application side of `mca simulate`: the paper's Fig. 4 scenes, one real RGB-D photograph, or a tree of them,
rendered into a folder of captures with their ground truth; progress by callback, errors as `SimulateError`."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mca.processing.camera import CameraProfile


class SimulateError(ValueError):
    """A simulation that cannot run as asked (bad option, unknown scene, unreadable source); says what to do."""


def parse_integers(text: str, what: str) -> tuple[int, ...]:
    """`"1, 2,3"` -> (1, 2, 3); a `SimulateError` naming the option `what` otherwise."""
    try:
        return tuple(int(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        raise SimulateError(f"{what} must be integers separated by commas, got {text!r}") from None


def prepare_simulation(profile: str, out: str | Path, fmt: str = "tiff") -> tuple[CameraProfile, Path]:
    """The profile by name or path, the output folder (created) and a checked `fmt`; else a `SimulateError`."""
    from mca.devices.profiles import load_profile
    from mca.processing.camera import ProfileError

    try:
        camera_profile = load_profile(profile)
        out_dir = Path(out)
        out_dir.mkdir(parents=True, exist_ok=True)
    except ProfileError as exc:
        raise SimulateError(str(exc)) from None
    except OSError as exc:
        raise SimulateError(f"cannot create the output folder {out}: {exc.strerror}") from None
    if fmt not in ("tiff", "cr2"):
        raise SimulateError("--format must be tiff or cr2")
    return camera_profile, out_dir


def _needs_lens(camera_profile: CameraProfile) -> None:
    if camera_profile.lens is None:
        raise SimulateError(f"profile '{camera_profile.name}' has no lens; use one with optics (paper-70d)")


# --- the paper's scenes ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PaperRender:
    """One paper scene written as a CR2 with its truth."""

    name: str
    cr2: Path
    objects: int  # objects of the scene's ground truth
    render_s: float
    write_s: float


def simulate_paper(
    camera_profile: CameraProfile,
    scene: str,
    out_dir: Path,
    size: str = "full",
    seed: int = 0,
    *,
    on_start: Callable[[int, int, str], None] | None = None,
    on_done: Callable[[PaperRender], None] | None = None,
) -> list[PaperRender]:
    """Render the paper scene `scene` (or `all`) at `size` into `out_dir` (truth in `out_dir/truth`).

    `on_start(number, total, name)` is called before each scene renders, `on_done` after it is written."""
    from mca.capture.simulated_shots import write_capture
    from mca.devices.sim.scenes import scene_names
    from mca.devices.sim.world import SIZES, render_scene

    names = scene_names() if scene == "all" else [scene]
    unknown = [n for n in names if n not in scene_names()]
    if unknown:
        raise SimulateError(f"unknown scene '{unknown[0]}'; choose one of {', '.join(scene_names())} or all")
    if size not in SIZES:
        raise SimulateError(f"--size must be one of {', '.join(SIZES)}")
    done = []
    for number, name in enumerate(names, 1):
        if on_start is not None:
            on_start(number, len(names), name)
        started = time.perf_counter()
        try:
            capture = render_scene(name, camera_profile, size=size, seed=seed)
        except ValueError as exc:
            raise SimulateError(str(exc)) from None
        rendered = time.perf_counter()
        paths = write_capture(capture, camera_profile, out_dir)
        result = PaperRender(
            name, paths["cr2"], len(capture.truth["objects"]), rendered - started, time.perf_counter() - rendered
        )
        done.append(result)
        if on_done is not None:
            on_done(result)
    return done


# --- one real photograph with known depth ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RgbdOptions:
    """How one RGB-D photograph is rendered (`mca simulate --from-rgbd`); None: the profile's or the source's."""

    fmt: str = "tiff"
    scale: float | None = None
    full_size: bool = False
    near_mm: float | None = None  # default: focus - 150 mm
    far_mm: float | None = None  # default: focus + 300 mm
    focus_mm: float | None = None
    disparity_scale: float | None = None  # default: SOURCE.txt beside the image, else 1
    iso: float = 100.0
    crosstalk: float = 0.0
    vignetting: str = "none"
    seed: int = 0
    name: str | None = None
    pitch: str = "frame"  # `simulated_shots.RENDER_PITCHES`: the whole sensor width, or the body's photosites


@dataclass(frozen=True)
class RgbdRender:
    """One rendered RGB-D photograph: its files (image, truth, profile), truth summary and render time."""

    paths: dict[str, Path]
    summary: str
    seconds: float


def crosstalk_matrix(crosstalk: float) -> tuple[tuple[float, float, float], ...] | None:
    """Each colour keeps 1 - `crosstalk` and takes half of `crosstalk` from each other filter; None for 0."""
    if not 0.0 <= crosstalk < 0.5:
        raise ValueError(f"--crosstalk must be in [0, 0.5), got {crosstalk}")
    if crosstalk == 0:
        return None
    leak = crosstalk / 2.0
    return tuple(
        (
            1.0 - crosstalk if i == 0 else leak,
            1.0 - crosstalk if i == 1 else leak,
            1.0 - crosstalk if i == 2 else leak,
        )
        for i in range(3)
    )


def simulate_rgbd(
    camera_profile: CameraProfile, image: Path, disparity: Path, out_dir: Path, options: RgbdOptions = RgbdOptions()
) -> RgbdRender:
    """Render one real photograph (8-bit sRGB) with its disparity map (0 = unknown) into `out_dir`."""
    from mca.capture.simulated_shots import (
        describe_rgbd_truth,
        read_rgbd_source,
        render_rgbd_capture,
        resize_rgbd,
        write_rgbd_capture,
    )
    from mca.devices.sim.render import SensorModel
    from mca.devices.sim.render_rgbd import DepthRange, Realism

    _needs_lens(camera_profile)
    assert camera_profile.lens is not None
    focus = options.focus_mm if options.focus_mm is not None else camera_profile.lens.focus_distance_mm
    near = options.near_mm if options.near_mm is not None else focus - 150.0
    far = options.far_mm if options.far_mm is not None else focus + 300.0
    try:
        depth_range = DepthRange(near, far)
        matrix = crosstalk_matrix(options.crosstalk)
        realism = Realism(sensor=SensorModel(iso=options.iso), crosstalk=matrix, vignetting=options.vignetting)
        source = read_rgbd_source(image, disparity, options.disparity_scale, name=options.name)
        if options.full_size:
            if not camera_profile.width_px or not camera_profile.height_px:
                raise ValueError(f"profile '{camera_profile.name}' has no image size; --full-size needs one")
            aspect = camera_profile.width_px / camera_profile.height_px
            h, w = source.valid.shape
            source = resize_rgbd(source, camera_profile.width_px / min(w, h * aspect), crop_aspect=aspect)
        else:
            source = resize_rgbd(source, options.scale if options.scale is not None else 1.0)
        capture = render_rgbd_capture(
            source,
            camera_profile,
            fmt=options.fmt,
            focus_distance_mm=focus,
            depth_range=depth_range,
            realism=realism,
            seed=options.seed,
            name=options.name,
            pitch=options.pitch,
        )
        paths = write_rgbd_capture(capture, out_dir)
    except (ValueError, OSError) as exc:
        raise SimulateError(str(exc)) from None
    return RgbdRender(paths, describe_rgbd_truth(capture.truth), capture.seconds)


# --- a tree of real photographs ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TreeOptions:
    """How a Middlebury-style tree is rendered (`mca simulate --from-rgbd-tree`)."""

    dev_set: bool = False  # the development set of docs/evaluation.md: tuning, held-out, 20mp and native/
    fmt: str = "tiff"
    scale: float | None = None
    width_px: int | None = None  # None: 1368; 0: each scene's own size
    full_size: bool = False
    seeds: tuple[int, ...] = (1, 2)
    scenes: tuple[str, ...] | None = None
    force: bool = False
    pitch: str = "frame"  # `simulated_shots.RENDER_PITCHES`


@dataclass
class TreeSummary:
    """What became of a tree render: counts by status and the failures (`folder/name: reason`)."""

    counts: dict[str, int] = field(default_factory=lambda: {"rendered": 0, "cached": 0, "failed": 0})
    failures: list[str] = field(default_factory=list)
    seconds: float = 0.0


def _dev_set_overrides(options: TreeOptions) -> list[str]:
    """The options given beside `--dev-set` that it would not use (each differs from its default)."""
    defaults = TreeOptions()
    named = {
        "fmt": "--format",
        "scale": "--scale",
        "width_px": "--width",
        "full_size": "--full-size",
        "seeds": "--seeds",
        "scenes": "--scenes",
        "pitch": "--pitch",
    }
    return [flag for attr, flag in named.items() if getattr(options, attr) != getattr(defaults, attr)]


def simulate_rgbd_tree(
    camera_profile: CameraProfile,
    tree: Path,
    out_dir: Path,
    options: TreeOptions = TreeOptions(),
    on_outcome: Callable[[str, Any], None] | None = None,
) -> TreeSummary:
    """Render every scene of `tree` once per seed into `out_dir` (or the development set's three folders); a
    failed scene is reported and the rest goes on. `on_outcome(prefix, outcome)` hears of each (scene, seed),
    `prefix` being `folder/` in the development set, else empty."""
    from mca.capture.simulated_shots import (
        DEV_FULL_SCENE,
        DEV_HELD_OUT_SCENES,
        DEV_SEEDS,
        DEV_TUNING_SCENES,
        DEV_WIDTH_PX,
        check_render_pitch,
        find_rgbd_scenes,
        render_rgbd_tree,
    )

    if not tree.is_dir() or not find_rgbd_scenes(tree):
        raise SimulateError(f"{tree}: no scene folder with im.png and disp.png")
    _needs_lens(camera_profile)
    jobs: list[tuple[str, tuple[str, ...] | None, tuple[int, ...], str, int | None, bool, str]]
    if options.dev_set:  # its own scenes, seeds, sizes, formats and pitches
        ignored = _dev_set_overrides(options)
        if ignored:
            raise SimulateError(
                f"--dev-set renders its own scenes, seeds, sizes, formats and pitches (docs/evaluation.md); "
                f"drop {', '.join(ignored)}, or leave out --dev-set to render the tree your way"
            )
        jobs = [
            ("tuning", DEV_TUNING_SCENES, DEV_SEEDS, "tiff", DEV_WIDTH_PX, False, "frame"),
            ("held-out", DEV_HELD_OUT_SCENES, DEV_SEEDS, "tiff", DEV_WIDTH_PX, False, "frame"),
            ("20mp", (DEV_FULL_SCENE,), DEV_SEEDS[:1], "cr2", None, True, "frame"),
            # the same scenes and draws on the body's own photosites: 4x the disparities and discs in pixels
            ("native/tuning", DEV_TUNING_SCENES, DEV_SEEDS, "tiff", DEV_WIDTH_PX, False, "native"),
            ("native/held-out", DEV_HELD_OUT_SCENES, DEV_SEEDS, "tiff", DEV_WIDTH_PX, False, "native"),
        ]
    else:
        try:
            check_render_pitch(camera_profile, options.pitch, options.fmt)
        except ValueError as exc:
            raise SimulateError(str(exc)) from None
        target = DEV_WIDTH_PX if options.width_px is None else (options.width_px or None)
        jobs = [(".", options.scenes, options.seeds, options.fmt, target, options.full_size, options.pitch)]
    started = time.perf_counter()
    summary = TreeSummary()
    for folder, names, job_seeds, job_fmt, job_width, job_full, job_pitch in jobs:
        prefix = f"{folder}/" if folder != "." else ""

        def report(outcome: Any, prefix: str = prefix) -> None:
            summary.counts[outcome.status] += 1
            if outcome.status == "failed":
                summary.failures.append(f"{prefix}{outcome.name}: {outcome.reason}")
            if on_outcome is not None:
                on_outcome(prefix, outcome)

        render_rgbd_tree(
            tree,
            out_dir / folder,
            camera_profile,
            seeds=job_seeds,
            scenes=names,
            fmt=job_fmt,
            scale=options.scale,  # None with --dev-set (refused otherwise)
            width_px=job_width,
            full_size=job_full,
            force=options.force,
            on_outcome=report,
            pitch=job_pitch,
        )
    summary.seconds = time.perf_counter() - started
    return summary
