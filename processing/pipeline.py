"""The accurate-depth pipeline: one MCA capture's colour planes in, the 2.1D sketch, depths and 3D images out.

Stages (names as given to the recorder and used as keys of `DepthResult.timings_s`):

- "planes":       planes (H, W, 3) float32 linear RGB at processing resolution, as handed in
                  (after moving the channels to common sample positions when `channel_offsets_px`
                  is given).
- "disparity":    disparity_px (h, w) float32 per-pixel widest-pair disparity in INPUT pixels on
                  the analysis grid, confidence (h, w) float32 in [0, 1], cost (h, w) colour-line
                  measure at the minimum, analysis_scale (processing px per analysis px).
- "sketch":       labels (h, w) int32 region ids 1..L on the analysis grid, aligned (h, w, 3) the
                  fringe-free image the segmentation used, region_count, focus_region, order
                  {id: rank}, occludes {id: [ids]}.
- "refine":       disparity_px {id: value at the region centroid, input px}, slant {id: (a, b, c) or
                  None}, dip {id: cost-dip confidence}.
- "depth":        labels (H, W) uint16, disparity_px (H, W) float32 region model in input px,
                  depth_mm (H, W) float32 distance from the lens (absent without optics), regions
                  (list of `Region`).
- "all_in_focus": image (H, W, 3) float32 linear RGB with the channels re-aligned per region.
- "mpi":          layers (list of `MultiPlaneImage`, back to front).

`Recorder.timing(stage, seconds)` is called after each stage with its wall-clock time.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.depth import depth_map_mm, region_depth
from mca.processing.disparity import DisparityParams, estimate_disparity, parallel_map
from mca.processing.mpi import all_in_focus, multi_plane_images
from mca.processing.optics import MCAOptics
from mca.processing.result import DepthResult, NullRecorder, Recorder, Region
from mca.processing.sketch import (
    BoundaryParams,
    RefineParams,
    SketchParams,
    build_sketch,
    occlusion_aware_weights,
    prepare_refine_level,
    refine_regions,
    rescale_plane,
    snap_boundaries,
)

# Position of each channel's samples relative to the centre of its 2x2 RGGB block, in half-resolution
# (processing) pixels, for planes taken straight from an RGGB mosaic: red at (0, 0), the mean of the two
# greens at the centre, blue at (1, 1) of each block. Pass as `channel_offsets_px` so that the Bayer
# offsets are not mistaken for disparity (half a pixel of red-blue offset is ~7 mm at the paper's setup).
RGGB_HALF_RES_OFFSETS_PX: tuple[tuple[float, float], ...] = ((-0.25, -0.25), (0.0, 0.0), (0.25, 0.25))

# Search range around the focus plane when optics are known (inter-object depth, mm), with margin over
# the -150..+300 mm the appliance is specified for, reaching a wall half a metre behind the focus plane.
DEPTH_RANGE_MM = (-190.0, 600.0)


@dataclass(frozen=True)
class PipelineParams:
    """Knobs of the whole pipeline; defaults are those the evaluation and the tests use."""

    analysis_max_side_px: int = 960  # the per-pixel search and the sketch run on a grid this large
    disparity: DisparityParams = DisparityParams()
    sketch: SketchParams = SketchParams()
    refine: RefineParams = RefineParams()
    occlusion_margin_px: int = 3  # analysis px excluded beside occluders when refining
    boundaries: BoundaryParams | None = BoundaryParams()  # None: labels upsampled by nearest neighbour only


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


class _Background:
    """`function(*args)` on its own thread; `result()` waits for it (and raises what it raised)."""

    def __init__(self, function, *args) -> None:
        self._value, self._error = None, None

        def target() -> None:
            try:
                self._value = function(*args)
            except BaseException as error:
                self._error = error

        self._thread = threading.Thread(target=target, name="mca-refine-level", daemon=True)
        self._thread.start()

    def result(self):
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


def default_disparity_range_px(
    aperture: FilterAperture, optics: MCAOptics | None, shape_px: tuple[int, int]
) -> tuple[float, float]:
    """Search range in input pixels: DEPTH_RANGE_MM around the focus plane with optics, else from the frame
    size (-2 % .. +3.5 % of the longer side, which covers the authors' range for the bando2008 photographs)."""
    if optics is not None:
        focus = optics.focus_distance_mm
        low = float(optics.disparity_px_at_distance(focus + DEPTH_RANGE_MM[0]))
        high = float(optics.disparity_px_at_distance(focus + DEPTH_RANGE_MM[1]))
        return (min(low, high), max(low, high))
    side = float(max(shape_px))
    return (-max(6.0, 0.02 * side), max(10.0, 0.035 * side))


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
    """Recover regions, their occlusion order and depths from one MCA capture (paper sections IV-V).

    planes: (H, W, 3) float32 linear RGB at processing resolution; pixel_scale: input-image pixels per
    processing pixel (2 for half-resolution Bayer planes); disparity_range_px: search range in input
    pixels (default: `default_disparity_range_px`). All disparities reported are between the widest
    filter pair in input-image pixels, + = farther than focus; `optics` (with the input pixel pitch)
    turns them into depths, without it depths stay None. See the module docstring for the stages
    reported to `recorder`.
    """
    recorder = recorder if recorder is not None else NullRecorder()
    timer = _Timer(recorder)
    if planes.ndim != 3 or planes.shape[2] != 3:
        raise ValueError(f"planes must be (H, W, 3), got shape {planes.shape}")
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    height, width = planes.shape[:2]
    total_start = time.perf_counter()

    with timer.stage("planes"):
        if channel_offsets_px is not None:
            planes = align_channel_samples(planes, channel_offsets_px)
        recorder.record("planes", planes=planes, pixel_scale=pixel_scale)

    # --- per-pixel disparity on the analysis grid --------------------------------------------------------------
    with timer.stage("disparity"):
        factor = max(1, int(np.ceil(max(height, width) / params.analysis_max_side_px)))
        if factor > 1:
            small = cv2.resize(planes, (width // factor, height // factor), interpolation=cv2.INTER_AREA)
        else:
            small = planes
        range_in = disparity_range_px or default_disparity_range_px(
            aperture, optics, (int(height * pixel_scale), int(width * pixel_scale))
        )
        to_analysis = 1.0 / (pixel_scale * factor)
        range_an = (range_in[0] * to_analysis - 1.0, range_in[1] * to_analysis + 1.0)
        disparity = estimate_disparity(small, aperture, range_an, params.disparity)
        recorder.record(
            "disparity",
            disparity_px=disparity.disparity_px / np.float32(to_analysis),
            confidence=disparity.confidence,
            cost=disparity.cost,
            analysis_scale=float(factor),
        )

    # --- the 2.1D sketch -------------------------------------------------------------------------------------------
    # the refinement's pyramid level and band-pass need no sketch: made on a thread beside the single-threaded
    # superpixels (joined in "refine")
    refine_level = _Background(prepare_refine_level, planes, params.refine)
    with timer.stage("sketch"):
        sketch = build_sketch(small, aperture, disparity, params.sketch)
        recorder.record(
            "sketch",
            labels=sketch.labels,
            aligned=sketch.aligned,
            region_count=len(sketch.regions),
            focus_region=sketch.focus_region,
            order=sketch.order,
            occludes=sketch.occludes,
        )

    # --- sub-pixel region models on the processing grid ------------------------------------------------------------
    with timer.stage("refine"):
        labels_full = cv2.resize(sketch.labels.astype(np.int32), (width, height), interpolation=cv2.INTER_NEAREST)
        weights_an = occlusion_aware_weights(
            sketch.labels, disparity.confidence, sketch.occludes, params.occlusion_margin_px
        )
        weights_full = cv2.resize(weights_an, (width, height), interpolation=cv2.INTER_LINEAR)
        init = {r.id: rescale_plane(r.plane, float(factor)) for r in sketch.regions}
        slanted = {r.id: r.slanted for r in sketch.regions}
        refine = params.refine
        refine = RefineParams(**{**refine.__dict__, "search_radius_px": max(refine.search_radius_px, 0.5 * factor)})
        planes_proc, dips = refine_regions(
            planes, aperture, labels_full, weights_full, init, slanted, refine, prepared=refine_level.result()
        )
        centroids = {
            r.id: ((r.centroid_xy[0] + 0.5) * factor - 0.5, (r.centroid_xy[1] + 0.5) * factor - 0.5)
            for r in sketch.regions
        }
        planes_in = {i: rescale_plane(p, pixel_scale) for i, p in planes_proc.items()}
        centre_disp = {}
        for i, (a, b, c) in planes_in.items():
            x, y = ((centroids[i][0] + 0.5) * pixel_scale - 0.5, (centroids[i][1] + 0.5) * pixel_scale - 0.5)
            centre_disp[i] = float(a * x + b * y + c)
        recorder.record(
            "refine",
            disparity_px=centre_disp,
            slant={i: (planes_in[i] if slanted[i] else None) for i in planes_in},
            dip=dips,
        )

    # --- depth ---------------------------------------------------------------------------------------------------
    with timer.stage("depth"):
        coef = np.zeros((int(labels_full.max()) + 1, 3), np.float32)
        for i, plane in planes_proc.items():
            coef[i] = plane
        if params.boundaries is not None and factor > 1:
            # region boundaries at processing resolution (the analysis grid's are blocks of `factor` px)
            start = time.perf_counter()
            labels_full = snap_boundaries(
                planes, aperture, labels_full, small, sketch.labels, sketch.aligned, coef, factor, params.boundaries
            )
            timer.timings["boundaries"] = time.perf_counter() - start
        # constant regions: a gather; slanted ones a x + b y + c on their own pixels
        model_proc = np.take(coef[:, 2], labels_full)
        slanted_pixels = {}
        for i, (a, b, c) in planes_proc.items():
            if a != 0.0 or b != 0.0:
                sel = labels_full == i
                ys_sel, xs_sel = np.nonzero(sel)
                model_proc[sel] = (
                    coef[i, 0] * xs_sel.astype(np.float32) + coef[i, 1] * ys_sel.astype(np.float32) + coef[i, 2]
                )
                slanted_pixels[i] = sel
        model_in = model_proc * np.float32(pixel_scale)
        raw_in = cv2.resize(disparity.disparity_px, (width, height), interpolation=cv2.INTER_LINEAR) / np.float32(
            to_analysis
        )
        confidence_full = cv2.resize(disparity.confidence, (width, height), interpolation=cv2.INTER_LINEAR)
        depth = None
        if optics is not None:
            # constant regions: one distance each (a gather); slanted ones pixel by pixel
            per_region = np.full(coef.shape[0], np.nan, np.float32)
            for i, (a, b, c) in planes_proc.items():
                per_region[i] = depth_map_mm(np.array([c * pixel_scale], np.float32), optics)[0]
            depth = per_region[labels_full]
            for sel in slanted_pixels.values():
                depth[sel] = depth_map_mm(model_in[sel], optics)
        # order: by disparity, nearest first (smaller disparity = nearer)
        ranked = sorted(planes_in, key=lambda i: centre_disp[i])
        order = {i: rank for rank, i in enumerate(ranked)}
        focus_id = min(centre_disp, key=lambda i: abs(centre_disp[i])) if centre_disp else None
        focus_tol_in = params.sketch.focus_tolerance_px * factor * pixel_scale
        if focus_id is not None and abs(centre_disp[focus_id]) > max(focus_tol_in, 1.0):
            focus_id = None
        counts = np.bincount(labels_full.ravel(), minlength=int(labels_full.max()) + 1)
        regions = []
        for r in sketch.regions:
            i = r.id
            chain = region_depth(centre_disp[i], optics) if optics is not None else None
            occludes = sorted(j for j in sketch.occludes.get(i, []) if centre_disp[j] > centre_disp[i]) + sorted(
                j for j, backs in sketch.occludes.items() if i in backs and centre_disp[j] > centre_disp[i]
            )
            regions.append(
                Region(
                    id=i,
                    pixels=int(counts[i]),
                    order=order[i],
                    occludes=sorted(set(occludes)),
                    disparity_px=centre_disp[i],
                    inter_image_depth_mm=chain.inter_image_depth_mm if chain else None,
                    inter_object_depth_mm=chain.inter_object_depth_mm if chain else None,
                    distance_mm=chain.distance_mm if chain else None,
                    slant=tuple(float(v) for v in planes_in[i]) if slanted[i] else None,
                    in_focus=(i == focus_id),
                    confidence=float(np.clip(0.5 * r.confidence + 0.5 * dips.get(i, 0.0), 0, 1)),
                )
            )
        regions.sort(key=lambda r: r.order)
        labels16 = labels_full.astype(np.uint16)
        record_items = dict(labels=labels16, disparity_px=model_in, regions=regions)
        if depth is not None:
            record_items["depth_mm"] = depth
        recorder.record("depth", **record_items)

    # --- the 3D images -----------------------------------------------------------------------------------------------
    with timer.stage("all_in_focus"):
        sharp = all_in_focus(planes, aperture, model_proc)
        recorder.record("all_in_focus", image=sharp)
    with timer.stage("mpi"):
        by_id = {r.id: r for r in regions}
        layers = multi_plane_images(
            sharp,
            labels16,
            [r.id for r in regions],
            {i: by_id[i].disparity_px for i in by_id},
            {i: by_id[i].inter_image_depth_mm for i in by_id},
            {i: by_id[i].inter_object_depth_mm for i in by_id},
        )
        recorder.record("mpi", layers=layers)
    timer.timings["total"] = time.perf_counter() - total_start
    return DepthResult(
        labels=labels16,
        disparity_px=model_in,
        raw_disparity_px=raw_in,
        confidence=confidence_full,
        depth_mm=depth,
        all_in_focus=sharp,
        regions=regions,
        focus_region=focus_id,
        layers=layers,
        pixel_scale=pixel_scale,
        timings_s=timer.timings,
    )
