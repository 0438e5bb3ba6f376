"""The accurate-depth pipeline: one MCA capture's colour planes in, the 2.1D sketch, depths and 3D images out.

The paper's steps (sections IV-V), each a stage reported to the recorder under this name:

- "planes":       the (H, W, 3) float32 linear planes at processing resolution, channels moved to common
                  sample positions when `channel_offsets_px` is given, and the filters' crosstalk taken
                  out when the aperture gives it (`remove_crosstalk`).
- "disparity":    dense per-pixel disparity (`processing.dense`) on the analysis grid (the planes reduced
                  to at most `analysis_max_side_px`): disparity_px in INPUT px, confidence in [0, 1],
                  analysis_scale (processing px per analysis px), search_range_px.
- "surfaces":     superpixels with a slanted plane each, chosen with their neighbours
                  (`processing.surfaces`): labels, count.
- "sketch":       the 2.1D sketch (`processing.sketch`): labels (analysis grid, region ids 1..L), aligned
                  (the fringe-free image it was cut on), region_count, focus_region, order {id: rank},
                  occludes {id: [ids]}.
- "refine":       each region's disparity refined on the raw cost with all its pixels (`processing.refine`):
                  disparity_px {id: value at the centroid, input px}, planar {id: bool}, offset_px {id: shift}.
                  The occlusions are decided again with the refined planes (`sketch.plane_occlusions`).
- "depth":        per pixel at processing resolution: labels (uint16), disparity_px (input px), depth_mm
                  (eq. 2 -> eqs. 13/14 -> distance; absent without optics), regions (list of `Region`).
- "all_in_focus": image: the channels re-aligned pixel by pixel so that the fringes vanish (section V-A).
- "mpi":          layers: one multi-plane image per region at Δd (eq. 3) and ΔD (eq. 16), back to front.

`Recorder.timing(stage, seconds)` is called after each stage with its wall-clock time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from mca.processing.boundaries import BoundaryParams, snap_boundaries
from mca.processing.camera import FilterAperture
from mca.processing.chromatic import NO_LATERAL_COLOUR, LateralColour, estimate_lateral_colour, remove_lateral_colour
from mca.processing.cost import CostInput, cost_input
from mca.processing.dense import DenseDisparity, DenseParams, estimate_dense, quick_disparity
from mca.processing.depth import depth_map_mm, region_depth
from mca.processing.disparity import parallel_map, warp_channels
from mca.processing.features import display_gamma
from mca.processing.labels import label_boxes
from mca.processing.mpi import all_in_focus, multi_plane_images
from mca.processing.optics import MCAOptics
from mca.processing.refine import Refinement, RefineParams, refine_regions
from mca.processing.result import DepthResult, NullRecorder, Recorder, Region
from mca.processing.sketch import Sketch, SketchParams, SketchRegion, build_sketch, plane_occlusions
from mca.processing.surfaces import SurfaceParams, Surfaces, build_surfaces, plane_map

# Position of each channel's samples relative to the centre of its 2x2 RGGB block, in half-resolution
# (processing) pixels, for planes taken straight from an RGGB mosaic: red at (0, 0), the mean of the two
# greens at the centre, blue at (1, 1) of each block. Pass as `channel_offsets_px` so that the Bayer
# offsets are not mistaken for disparity (half a pixel of red-blue offset is ~7 mm at the paper's setup).
RGGB_HALF_RES_OFFSETS_PX: tuple[tuple[float, float], ...] = ((-0.25, -0.25), (0.0, 0.0), (0.25, 0.25))

# Search range when optics are known: from half the focus distance (but at least 1.2 focal lengths) out to
# infinity, whose disparity is finite (eq. 11 with the image at the focal plane); the scene's own range is
# found inside it (`processing.dense.occupied_range`).
NEAREST_FRACTION_OF_FOCUS = 0.5
NEAREST_FOCAL_LENGTHS = 1.2
INFINITY_MARGIN_PX = 0.5  # kept below the disparity of infinity (no distance lies beyond it)


@dataclass(frozen=True)
class PipelineParams:
    """Knobs of the whole pipeline; defaults are those the evaluation and the tests use."""

    analysis_max_side_px: int = 1400  # dense disparity, surfaces and sketch run on a grid at most this large
    dense: DenseParams = field(default_factory=DenseParams)
    surfaces: SurfaceParams = field(default_factory=SurfaceParams)
    sketch: SketchParams = field(default_factory=SketchParams)
    # what weighs a pixel's dense disparity in the surfaces: "texture" (texture beside the image's median),
    # "signal" (its window's signal-to-noise weight, `features.signal_weight`), "confidence", "none"
    evidence: str = "texture"
    refine: RefineParams | None = field(default_factory=RefineParams)  # None: the surfaces' disparity as it is
    boundaries: BoundaryParams | None = field(default_factory=BoundaryParams)  # None: superpixel outlines as they are
    # measure the lens's lateral colour in each capture and take it out first (`processing.chromatic`) even
    # where the profile does not ask for it (`aperture.lateral_colour`); off: see docs/pipeline.md, known gaps
    lateral_colour: bool = False

    @classmethod
    def for_quality(cls, quality: str) -> PipelineParams:
        """`full` (the defaults, as evaluated) or `preview` (live use: a coarser analysis grid and superpixels,
        a coarser refinement, no boundary snap; accuracy beside the full setting in docs/evaluation.md)."""
        if quality == "full":
            return cls()
        if quality == "preview":
            return cls(
                # a 20 MP capture's 2736-px planes go to a grid 6x smaller (456 px, as 1368-px renders, whose
                # figures docs/evaluation.md gives); 4 SLIC iterations: disparity and regions in under 0.5 s
                analysis_max_side_px=512,
                surfaces=SurfaceParams(superpixel_px=400, sweeps=5, slic_iterations=4),
                refine=RefineParams(coarse_step_px=0.75, fine_step_px=0.25),
                boundaries=None,
            )
        raise ValueError(f"quality must be 'full' or 'preview', not {quality!r}")


@dataclass
class _Timer:
    recorder: Recorder
    timings: dict[str, float] = field(default_factory=dict)

    def stage(self, name: str) -> _Stage:
        return _Stage(self, name)


class _Stage:
    def __init__(self, timer: _Timer, name: str) -> None:
        self.timer, self.name = timer, name

    def __enter__(self) -> _Stage:
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        seconds = time.perf_counter() - self.start
        self.timer.timings[self.name] = seconds
        if exc[0] is None:
            self.timer.recorder.timing(self.name, seconds)


def default_disparity_range_px(
    aperture: FilterAperture, optics: MCAOptics | None, shape_px: tuple[int, int]
) -> tuple[float, float]:
    """Search range in input pixels. With optics: from max(0.5 focus, 1.2 f) to just short of infinity.
    Without: from the frame size, -4 % .. +5 % of the longer side (covers the authors' range for the
    bando2008 photographs with room on both sides)."""
    if optics is not None:
        focus = optics.focus_distance_mm
        nearest = max(NEAREST_FRACTION_OF_FOCUS * focus, NEAREST_FOCAL_LENGTHS * optics.focal_length_mm)
        low = float(optics.disparity_px_at_distance(nearest))
        infinity = float(optics.disparity_px(optics.sensor_distance_mm - optics.focal_length_mm))
        return (min(low, 0.0), max(infinity - INFINITY_MARGIN_PX, 0.0))
    side = float(max(shape_px))
    return (-max(6.0, 0.04 * side), max(10.0, 0.05 * side))


def catmull_rom_kernel(shift_px: float) -> np.ndarray:
    """Odd-length, centred correlation kernel that samples a row at x + shift_px (Catmull-Rom, Keys a = -0.5).

    Unlike OpenCV's INTER_CUBIC (Keys a = -0.75, which reproduces constants but not ramps), this cubic
    reproduces linear and quadratic signals exactly, so a constant shift moves the content by exactly
    `shift_px`: OpenCV's cubic moves it by 0.297 px for 0.25 px at low frequencies (sum_k w_k k), which
    made the Bayer correction overshoot and every in-focus object read ~0.1-0.2 px near."""
    base = int(np.floor(shift_px))
    t = shift_px - base
    a = -0.5
    weights = []
    for x in (t + 1.0, t, 1.0 - t, 2.0 - t):  # distances to the taps at base-1, base, base+1, base+2
        x = abs(x)
        weights.append(
            (a + 2) * x**3 - (a + 3) * x**2 + 1
            if x <= 1
            else a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a
            if x < 2
            else 0.0
        )
    first = base - 1
    span = max(abs(first), abs(first + 3))
    kernel = np.zeros(2 * span + 1, np.float32)
    kernel[span + first : span + first + 4] = weights
    return kernel


def align_channel_samples(planes: np.ndarray, offsets_px: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Resample each channel so that its samples sit at the pixel centres (separable Catmull-Rom cubic:
    a constant shift is one 4-tap filter per axis, exact in position; see `catmull_rom_kernel`)."""
    channels = cv2.split(np.asarray(planes, dtype=np.float32))

    def one(c: int) -> np.ndarray:
        dx, dy = offsets_px[c]
        if dx == 0 and dy == 0:
            return channels[c]
        # sample at (x - dx, y - dy): the channel's content moves by (+dx, +dy) onto the pixel centres
        return cv2.sepFilter2D(
            channels[c], cv2.CV_32F, catmull_rom_kernel(-dx), catmull_rom_kernel(-dy), borderType=cv2.BORDER_REPLICATE
        )

    return cv2.merge(parallel_map(one, range(3)))


def remove_crosstalk(
    planes: np.ndarray,
    crosstalk: tuple[tuple[float, float, float], ...],
    what: str = "aperture.crosstalk",
    remedy: str = "check the profile's matrix",
) -> np.ndarray:
    """The filter images behind (H, W, 3) sensor planes mixed by `crosstalk` (sensor channel <- filter, the
    profile's `aperture.crosstalk`): each pixel's colour times the inverse matrix. A matrix that cannot be
    inverted is a ValueError naming it as `what`, with `remedy` (a measured matrix has another remedy than a
    profile's).

    Leaked light is a faint copy of another filter's image at that filter's displacement: left in, it pulls each
    channel towards the others and every disparity towards zero (5 % less at 6 % leak on the rendered scenes).
    """
    matrix = np.asarray(crosstalk, np.float64)
    if abs(np.linalg.det(matrix)) < 1e-6:
        raise ValueError(f"{what} {matrix.tolist()} cannot be inverted: {remedy}")
    unmix = np.linalg.inv(matrix).astype(np.float32)
    h, w, _ = planes.shape
    return np.ascontiguousarray((planes.reshape(-1, 3) @ unmix.T).reshape(h, w, 3), dtype=np.float32)


def rescale_plane(plane: tuple[float, float, float] | np.ndarray, factor: float) -> np.ndarray:
    """A disparity plane on a grid -> the same plane on a grid `factor` times finer, disparity in the finer
    grid's pixels (pixel centres: x_coarse = (x_fine + 0.5) / factor - 0.5)."""
    a, b, c = (float(v) for v in plane)
    return np.array([a, b, factor * c + (a + b) * 0.5 * (1.0 - factor)])


def _analysis_grid(planes: np.ndarray, max_side_px: int) -> tuple[np.ndarray, int]:
    h, w = planes.shape[:2]
    factor = max(1, int(np.ceil(max(h, w) / max_side_px)))
    if factor == 1:
        return planes, 1
    return cv2.resize(planes, (w // factor, h // factor), interpolation=cv2.INTER_AREA), factor


def run_pipeline(
    planes: np.ndarray,
    aperture: FilterAperture,
    optics: MCAOptics | None,
    *,
    pixel_scale: float = 1.0,
    disparity_range_px: tuple[float, float] | None = None,
    recorder: Recorder | None = None,
    channel_offsets_px: tuple[tuple[float, float], ...] | None = None,
    params: PipelineParams = PipelineParams(),
) -> DepthResult:
    """Recover regions, their occlusion order and per-pixel depths from one MCA capture (paper sections IV-V).

    planes: (H, W, 3) float32 linear RGB at processing resolution; pixel_scale: input-image pixels per
    processing pixel (2 for half-resolution Bayer planes); disparity_range_px: search range in input
    pixels (default: `default_disparity_range_px`). All disparities reported are between the widest
    filter pair in input-image pixels, + = farther than focus; `optics` (with the input pixel pitch)
    turns them into depths, without it depths stay None. See the module docstring for the stages.
    """
    return finished_run(
        planes,
        aperture,
        optics,
        pixel_scale=pixel_scale,
        disparity_range_px=disparity_range_px,
        recorder=recorder,
        channel_offsets_px=channel_offsets_px,
        params=params,
    ).result()


def finished_run(
    planes: np.ndarray,
    aperture: FilterAperture,
    optics: MCAOptics | None,
    *,
    pixel_scale: float = 1.0,
    disparity_range_px: tuple[float, float] | None = None,
    recorder: Recorder | None = None,
    channel_offsets_px: tuple[tuple[float, float], ...] | None = None,
    params: PipelineParams = PipelineParams(),
) -> _Run:
    """`run_pipeline` keeping the run: every stage's intermediate results (the dense map, the surfaces, the
    sketch) beside `.result()` (benchmarks/surface_floors.py scores them)."""
    if planes.ndim != 3 or planes.shape[2] != 3:
        raise ValueError(f"planes must be (H, W, 3), got shape {planes.shape}")
    run = _Run(
        np.ascontiguousarray(planes, dtype=np.float32),
        aperture,
        optics,
        pixel_scale,
        disparity_range_px,
        recorder if recorder is not None else NullRecorder(),
        channel_offsets_px,
        params,
    )
    started = time.perf_counter()
    for name, stage in _STAGES:
        with run.timer.stage(name):
            stage(run)
    run.timer.timings["total"] = time.perf_counter() - started
    return run


def load_kernels(aperture: FilterAperture, optics: MCAOptics | None = None, quality: str = "full") -> float:
    """Run the pipeline once on a small synthetic capture, so that every compiled kernel it takes is loaded
    (from numba's cache, or compiled on the very first run). Returns the seconds it took.

    A fresh process spends about half a second loading kernels the first time each is called; `mca process`
    does this on a helper thread while the photograph is being read (`capture.pipeline_app`), so that the
    pipeline then finds them loaded. The search spans a few candidates only (`_KERNEL_RANGE_PX`): the kernels
    are the same for any range, and this runs on the critical path whenever it outlasts the read. Nothing of it
    is kept: the answers are the same with or without it."""
    started = time.perf_counter()
    rng = np.random.default_rng(0)
    texture = rng.random((_KERNEL_SHAPE[0], _KERNEL_SHAPE[1], 3)).astype(np.float32)
    planes = cv2.GaussianBlur(texture, (0, 0), 1.5) + np.float32(0.2)
    params = PipelineParams.for_quality(quality)
    result = run_pipeline(planes, aperture, optics, disparity_range_px=_KERNEL_RANGE_PX, params=params)
    label_boxes(result.labels)  # the outputs' region boxes
    return time.perf_counter() - started


_KERNEL_SHAPE = (192, 256)  # large enough for every stage to run its kernels (quarter size >= 24 px)
# A few candidates are enough to call every kernel: the optics' own range at this size would be ~100 of them,
# and computing their costs took about a second of the warm-up, on the critical path of every `mca process`.
_KERNEL_RANGE_PX = (-2.0, 2.0)


@dataclass
class _Run:
    """One capture on its way through the stages: what came in, then what each stage made."""

    planes: np.ndarray
    aperture: FilterAperture
    optics: MCAOptics | None
    pixel_scale: float
    disparity_range_px: tuple[float, float] | None
    recorder: Recorder
    channel_offsets_px: tuple[tuple[float, float], ...] | None
    params: PipelineParams
    timer: _Timer = field(init=False)
    lateral_colour: LateralColour = field(init=False, default=NO_LATERAL_COLOUR)
    # disparity
    small: np.ndarray = field(init=False)  # the analysis grid
    factor: int = field(init=False)  # processing px per analysis px
    to_input: float = field(init=False)  # input px per analysis px
    inputs: CostInput = field(init=False)  # the analysis grid's feature bands and noise, made once
    dense: DenseDisparity = field(init=False)
    # surfaces, sketch
    aligned: np.ndarray = field(init=False)
    surfaces: Surfaces = field(init=False)
    surface_disparity: np.ndarray = field(init=False)
    sketch: Sketch = field(init=False)
    focus_id: int | None = field(init=False)
    # refine, boundaries
    refinement: Refinement = field(init=False)
    region_labels: np.ndarray = field(init=False)
    # depth, all in focus, mpi
    labels16: np.ndarray = field(init=False)
    model_proc: np.ndarray = field(init=False)
    model_in: np.ndarray = field(init=False)
    depth: np.ndarray | None = field(init=False)
    raw_in: np.ndarray = field(init=False)  # the dense disparity at processing resolution, input px
    confidence_full: np.ndarray = field(init=False)
    regions: list[Region] = field(init=False)
    sharp: np.ndarray = field(init=False)
    layers: list = field(init=False)

    def __post_init__(self) -> None:
        self.timer = _Timer(self.recorder)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.planes.shape[0], self.planes.shape[1])

    def result(self) -> DepthResult:
        return DepthResult(
            labels=self.labels16,
            disparity_px=self.model_in,
            raw_disparity_px=self.raw_in,
            confidence=self.confidence_full,
            depth_mm=self.depth,
            all_in_focus=self.sharp,
            regions=self.regions,
            focus_region=self.focus_id,
            layers=self.layers,
            pixel_scale=self.pixel_scale,
            timings_s=self.timer.timings,
            lateral_colour=self.lateral_colour,
        )


def _planes(run: _Run) -> None:
    if run.channel_offsets_px is not None:
        run.planes = align_channel_samples(run.planes, run.channel_offsets_px)
    if run.aperture.crosstalk is not None:
        run.planes = remove_crosstalk(run.planes, run.aperture.crosstalk)
    run.recorder.record("planes", planes=run.planes, pixel_scale=run.pixel_scale)


def _disparity(run: _Run) -> None:
    wanted = run.aperture.lateral_colour
    measure = run.params.lateral_colour or wanted == "measure"
    if isinstance(wanted, tuple) and not measure:  # calibrated, in parts per thousand
        run.lateral_colour = LateralColour.from_ppt(*wanted)
        run.planes = remove_lateral_colour(run.planes, run.lateral_colour)
    run.small, run.factor = _analysis_grid(run.planes, run.params.analysis_max_side_px)
    run.to_input = float(run.factor * run.pixel_scale)
    height, width = run.shape
    range_in = run.disparity_range_px or default_disparity_range_px(
        run.aperture, run.optics, (int(height * run.pixel_scale), int(width * run.pixel_scale))
    )
    range_an = (range_in[0] / run.to_input, range_in[1] / run.to_input)
    quick = None
    if measure:
        # read on the analysis grid (the magnifications hold at every size) on tiles of one depth (the quick
        # search's), taken out at every size; the quick search serves the dense one's range too
        quick = quick_disparity(run.small, run.aperture, range_an, run.params.dense)
        run.lateral_colour = estimate_lateral_colour(run.small, run.aperture, disparity_px=quick)
        run.planes = remove_lateral_colour(run.planes, run.lateral_colour)
        run.small = remove_lateral_colour(run.small, run.lateral_colour)
    refine = run.params.refine
    run.inputs = cost_input(run.small, run.params.dense.noise_model or (refine is not None and refine.noise_model))
    run.dense = estimate_dense(run.small, run.aperture, range_an, run.params.dense, run.inputs, quick)
    low, high = run.dense.search_range_px
    run.recorder.record(
        "disparity",
        disparity_px=run.dense.disparity_px * np.float32(run.to_input),
        confidence=run.dense.confidence,
        analysis_scale=float(run.factor),
        search_range_px=(low * run.to_input, high * run.to_input),
        lateral_colour=run.lateral_colour.describe(),
    )


def _surfaces(run: _Run) -> None:
    run.aligned = display_gamma(warp_channels(run.small, run.aperture, run.dense.disparity_px))
    evidence = _evidence(
        run.inputs, run.dense, run.params.evidence, run.params.dense.half_weight_snr, run.params.dense.signal_channels
    )
    run.surfaces = build_surfaces(run.aligned, run.dense.disparity_px, run.params.surfaces, evidence=evidence)
    run.recorder.record("surfaces", labels=run.surfaces.labels, count=run.surfaces.count)


def _sketch(run: _Run) -> None:
    run.surface_disparity = run.surfaces.disparity()
    run.sketch = build_sketch(run.surfaces, run.surface_disparity, run.dense.confidence, run.params.sketch)
    run.focus_id = _focus_region(run.sketch, run.params.sketch.focus_tolerance_px, run.to_input)
    run.recorder.record(
        "sketch",
        labels=run.sketch.labels,
        aligned=run.aligned,
        region_count=len(run.sketch.regions),
        focus_region=run.focus_id,
        order=run.sketch.order,
        occludes=run.sketch.occludes,
    )


def _refine_stage(run: _Run) -> None:
    if run.params.refine is None:
        run.refinement = _no_refinement(run.sketch, run.surface_disparity)
    else:
        refine = run.params.refine
        noise = run.inputs.noise if refine.noise_model else None
        run.refinement = refine_regions(
            run.inputs.stacked,
            run.aperture,
            run.sketch.labels,
            run.surface_disparity,
            refine,
            noise=noise,
            inputs=run.inputs,
        )
    # nothing after the refinement reads the cost's feature bands: let them go before the full-size stages
    # (at 20 MP about 100 MB, and the process's peak is in the stages that follow, beside the outputs' encoding)
    del run.inputs
    run.sketch = _refined_sketch(run.sketch, run.refinement, run.params.sketch.occlusion_margin_px)
    run.recorder.record(
        "refine",
        disparity_px={r.id: r.disparity_px * run.to_input for r in run.sketch.regions},
        planar={i: p is not None for i, p in run.refinement.planes.items()},
        offset_px=run.refinement.offsets_px,
    )


def _boundaries(run: _Run) -> None:
    run.region_labels = run.sketch.labels
    if run.params.boundaries is not None:
        models = _region_models(run.sketch, run.refinement.disparity_px)
        run.region_labels = snap_boundaries(run.small, run.aperture, run.sketch.labels, models, run.params.boundaries)
    changed = int((run.region_labels != run.sketch.labels).sum())
    run.recorder.record("boundaries", labels=run.region_labels, changed_px=changed)


def _depth(run: _Run) -> None:
    factor, sketch = run.factor, run.sketch
    superpixels_full = _upsample_labels(run.surfaces.labels, factor, run.shape)
    labels16 = sketch.superpixel_region[superpixels_full].astype(np.uint16)
    model_proc = _model_at_processing(run.surfaces, sketch, run.refinement, superpixels_full, labels16, factor)
    if run.region_labels is not sketch.labels:
        snapped = _upsample_labels(run.region_labels, factor, run.shape).astype(np.uint16)
        moved = snapped != labels16
        if moved.any():
            plane_of = np.zeros((max([int(snapped.max())] + [r.id for r in sketch.regions]) + 1, 3))
            for r in sketch.regions:
                plane_of[r.id] = rescale_plane(r.plane, factor) if factor > 1 else r.plane
            plane_map(snapped, plane_of, out=model_proc, where=moved)
        labels16 = snapped
    run.labels16, run.model_proc = labels16, model_proc
    run.model_in = model_proc * np.float32(run.pixel_scale)
    run.depth = depth_map_mm(run.model_in, run.optics) if run.optics is not None else None
    run.raw_in = _upsample(run.dense.disparity_px, run.shape) * np.float32(run.to_input)
    run.confidence_full = _upsample(run.dense.confidence, run.shape)
    run.regions = _regions(sketch, run.optics, factor, run.pixel_scale, run.focus_id)
    items: dict[str, object] = dict(labels=run.labels16, disparity_px=run.model_in, regions=run.regions)
    if run.depth is not None:
        items["depth_mm"] = run.depth
    run.recorder.record("depth", **items)


def _all_in_focus(run: _Run) -> None:
    run.sharp = all_in_focus(run.planes, run.aperture, run.model_proc)
    run.recorder.record("all_in_focus", image=run.sharp)


def _mpi(run: _Run) -> None:
    by_id = {r.id: r for r in run.regions}
    run.layers = multi_plane_images(
        run.sharp,
        run.labels16,
        [r.id for r in run.regions],
        {i: by_id[i].disparity_px for i in by_id},
        {i: by_id[i].inter_image_depth_mm for i in by_id},
        {i: by_id[i].inter_object_depth_mm for i in by_id},
    )
    run.recorder.record("mpi", layers=run.layers)


# The paper's steps, in order (the module docstring says what each records).
_STAGES: tuple[tuple[str, Callable[[_Run], None]], ...] = (
    ("planes", _planes),
    ("disparity", _disparity),
    ("surfaces", _surfaces),
    ("sketch", _sketch),
    ("refine", _refine_stage),
    ("boundaries", _boundaries),
    ("depth", _depth),
    ("all_in_focus", _all_in_focus),
    ("mpi", _mpi),
)


def _region_models(sketch: Sketch, refined: np.ndarray) -> dict[int, np.ndarray]:
    """Each region's disparity over the whole grid: its refined model inside, its plane outside."""
    h, w = sketch.labels.shape
    xs = np.arange(w, dtype=np.float32)[None, :]
    ys = np.arange(h, dtype=np.float32)[:, None]
    models = {}
    for r in sketch.regions:
        a, b, c = (np.float32(v) for v in r.plane)
        models[r.id] = np.where(sketch.labels == r.id, refined, a * xs + b * ys + c).astype(np.float32)
    return models


def _evidence(
    inputs: CostInput, dense: DenseDisparity, kind: str, half_snr: float, channels: str = "second"
) -> np.ndarray | None:
    """How much each pixel's dense disparity is worth: how much of its window is signal rather than noise
    (`features.signal_weight`, half at `half_snr`, of `channels`; "signal", when the inputs carry the noise model, else as
    "texture"), its texture relative to the image's median texture (saturating at 1), or the dense confidence.

    What "signal" is for: on a photograph of texture-less surfaces the median window holds noise alone, and beside
    that median noise looks like texture, so a wall's noisy disparities weigh as much as the edges that know its
    disparity. It is an option, off: it split `dog.png`'s regions (docs/evaluation.md)."""
    if kind == "none":
        return None
    if kind == "confidence":
        return dense.confidence
    if kind == "signal" and inputs.noise is not None and half_snr > 0:
        return inputs.signal_weight(9, half_snr, channels)
    energy = inputs.texture_energy(9)
    return np.clip(energy / (float(np.median(energy)) + 1e-9), 0.0, 1.0).astype(np.float32)


def _no_refinement(sketch: Sketch, disparity: np.ndarray) -> Refinement:
    ids = [r.id for r in sketch.regions]
    return Refinement(disparity, dict.fromkeys(ids), dict.fromkeys(ids, (0.0, 0.0, 0.0)), dict.fromkeys(ids, 0.0))


def _refined_sketch(sketch: Sketch, refinement: Refinement, margin_px: float) -> Sketch:
    """The sketch's regions with their refined planes (planar regions) or shifted levels (curved ones), and the
    occlusions those planes make along the region boundaries (`sketch.plane_occlusions`)."""
    regions = []
    for r in sketch.regions:
        plane = refinement.planes.get(r.id)
        if plane is None:
            da, db, dc = refinement.corrections.get(r.id, (0.0, 0.0, 0.0))
            plane = (r.plane[0] + da, r.plane[1] + db, r.plane[2] + dc)
        a, b, c = plane
        x, y = r.centroid_xy
        if not r.slanted:  # a fronto-parallel region: one level, the plane's at the centroid
            a, b, c = 0.0, 0.0, a * x + b * y + c
        regions.append(
            SketchRegion(
                id=r.id,
                pixels=r.pixels,
                plane=(a, b, c),
                slanted=r.slanted,
                centroid_xy=r.centroid_xy,
                disparity_px=a * x + b * y + c,
                confidence=r.confidence,
            )
        )
    ranked = sorted(regions, key=lambda region: region.disparity_px)
    order = {region.id: rank for rank, region in enumerate(ranked)}
    occludes, pair_gap = plane_occlusions(sketch.labels, regions, margin_px)
    return Sketch(sketch.labels, regions, order, occludes, sketch.superpixel_region, pair_gap)


def _model_at_processing(
    surfaces: object,
    sketch: Sketch,
    refinement: Refinement,
    superpixels_full: np.ndarray,
    labels_full: np.ndarray,
    factor: int,
) -> np.ndarray:
    """Per-pixel disparity (processing px) at processing resolution: the refined plane of a planar region, the
    surfaces' planes shifted by the region's refinement in a curved one."""
    planes = surfaces.planes  # type: ignore[attr-defined]
    region_of = sketch.superpixel_region
    shifted = planes + np.array(
        [refinement.corrections.get(int(region_of[i]), (0.0, 0.0, 0.0)) for i in range(planes.shape[0])]
    )
    planes_proc = np.stack([rescale_plane(p, factor) for p in shifted]) if factor > 1 else shifted
    model = plane_map(superpixels_full, planes_proc)
    count = int(labels_full.max()) + 1
    region_planes = np.zeros((count, 3))
    planar = np.zeros(count, bool)
    for rid, plane in refinement.planes.items():
        if plane is not None and rid < count:
            region_planes[rid] = rescale_plane(plane, factor)
            planar[rid] = True
    if planar.any():
        plane_map(labels_full, region_planes, out=model, where=planar[labels_full])
    return model


def _upsample_labels(labels: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    if factor == 1 and labels.shape == shape:
        return labels
    return cv2.resize(labels.astype(np.int32), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)


def _upsample(array: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if array.shape == shape:
        return array.astype(np.float32, copy=True)
    return cv2.resize(array.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def _focus_region(sketch: Sketch, tolerance_px: float, to_input: float) -> int | None:
    """The region nearest the focus plane, when its disparity is within the tolerance (input px, >= 1)."""
    if not sketch.regions:
        return None
    best = min(sketch.regions, key=lambda r: abs(r.disparity_px))
    if abs(best.disparity_px) * to_input > max(tolerance_px * to_input, 1.0):
        return None
    return best.id


def _regions(
    sketch: Sketch, optics: MCAOptics | None, factor: int, pixel_scale: float, focus_id: int | None
) -> list[Region]:
    """The sketch's regions in input pixels, with their depth chain (eqs. 2, 13/14) and occlusions."""
    to_input = factor * pixel_scale
    regions = []
    for r in sketch.regions:
        centre_in = ((r.centroid_xy[0] + 0.5) * to_input - 0.5, (r.centroid_xy[1] + 0.5) * to_input - 0.5)
        plane_in = rescale_plane(r.plane, to_input)
        disparity_in = float(plane_in[0] * centre_in[0] + plane_in[1] * centre_in[1] + plane_in[2])
        chain = region_depth(disparity_in, optics) if optics is not None else None
        regions.append(
            Region(
                id=r.id,
                pixels=int(r.pixels * factor * factor),
                order=sketch.order[r.id],
                occludes=list(sketch.occludes.get(r.id, [])),
                disparity_px=disparity_in,
                inter_image_depth_mm=chain.inter_image_depth_mm if chain else None,
                inter_object_depth_mm=chain.inter_object_depth_mm if chain else None,
                distance_mm=chain.distance_mm if chain else None,
                slant=tuple(float(v) for v in plane_in) if r.slanted else None,  # type: ignore[arg-type]
                in_focus=(r.id == focus_id),
                confidence=r.confidence,
            )
        )
    regions.sort(key=lambda region: region.order)
    return regions
