"""The whole pipeline on a small simulated paper scene: regions, order, depths, 3D images and the recorder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.devices.sim.render import SensorModel, SimulationOptics, render
from mca.devices.sim.scenes import paper_scene, target_scene
from mca.processing.evaluate import bayer_planes
from mca.processing.mpi import composite
from mca.processing.pipeline import (
    RGGB_HALF_RES_OFFSETS_PX,
    align_channel_samples,
    default_disparity_range_px,
    run_pipeline,
)


class ListRecorder:
    def __init__(self):
        self.stages, self.timings = {}, {}

    def record(self, stage, **items):
        self.stages[stage] = items

    def timing(self, stage, seconds):
        self.timings[stage] = seconds


@pytest.fixture(scope="module")
def paper_a():
    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 0.5)
    sensor = SensorModel()
    rendering = render(paper_scene("paper-a", optics.focus_distance_mm), optics, sensor, seed=3)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    recorder = ListRecorder()
    result = run_pipeline(
        planes,
        optics.aperture,
        optics.mca,
        pixel_scale=2.0,
        channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX,
        recorder=recorder,
    )
    return optics, rendering, result, recorder


def test_search_range_covers_the_specified_depths():
    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 1.0).mca
    low, high = default_disparity_range_px(load_profile("paper-70d").aperture, optics, (3648, 5472))
    assert low <= optics.disparity_px_at_distance(optics.focus_distance_mm - 150) <= -27.0
    assert high >= optics.disparity_px_at_distance(optics.focus_distance_mm + 300) >= 34.0


def test_bayer_alignment_moves_channels_by_exactly_their_offsets():
    # a smooth pattern sampled at the RGGB sites of the half-resolution planes: red 1/4 px up-left, blue 1/4 px
    # down-right of the block centre. OpenCV's INTER_CUBIC (Keys a = -0.75) moved them 0.297 px instead of 0.25
    # (max error 1.0e-2 here), which read as -0.1 to -0.2 px of disparity on every in-focus object
    ys, xs = np.mgrid[0:200, 0:300].astype(np.float64)

    def pattern(x, y):
        return (
            0.5
            + 0.2 * np.sin(2 * np.pi * x / 23 + 0.3)
            + 0.15 * np.cos(2 * np.pi * y / 17)
            + 0.1 * np.sin(2 * np.pi * (x + y) / 11)
        )

    planes = np.dstack([pattern(xs + dx, ys + dy) for dx, dy in RGGB_HALF_RES_OFFSETS_PX]).astype(np.float32)
    aligned = align_channel_samples(planes, RGGB_HALF_RES_OFFSETS_PX)
    error = np.abs(aligned[8:-8, 8:-8] - pattern(xs, ys)[8:-8, 8:-8, None])
    assert error.max() < 2e-3  # 8.4e-4 measured


def test_target_at_the_focus_distance_reads_zero_disparity_through_the_bayer_mosaic():
    # full size, as `mca evaluate`: a textured plane exactly in focus, sampled at its Bayer sites (not cosited)
    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 1.0)
    sensor = SensorModel()
    rendering = render(target_scene(optics.focus_distance_mm), optics, sensor, seed=0)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    recorder = ListRecorder()
    result = run_pipeline(
        planes,
        optics.aperture,
        optics.mca,
        pixel_scale=2.0,
        channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX,
        recorder=recorder,
    )
    per_pixel = recorder.stages["disparity"]["disparity_px"]
    h, w = per_pixel.shape
    # measured +0.010 px on the analysis grid and +0.004 px refined (INTER_CUBIC alignment: -0.19 and -0.12 px)
    assert abs(float(np.median(per_pixel[h // 8 : -h // 8, w // 8 : -w // 8]))) < 0.03
    target = max(result.regions, key=lambda r: r.pixels)
    assert target.in_focus and abs(target.disparity_px) < 0.02
    assert abs(target.inter_object_depth_mm) < 0.15


def test_regions_order_and_depths(paper_a):
    _optics, rendering, result, _ = paper_a
    truth = rendering.truth
    assert len(result.regions) == len(truth["objects"]) + 1  # five pots and the wall
    by_label = {}
    for obj in truth["objects"]:
        mask = rendering.labels[::2, ::2][: result.labels.shape[0], : result.labels.shape[1]] == obj["id"]
        ids, counts = np.unique(result.labels[mask], return_counts=True)
        by_label[obj["paper_label"]] = next(r for r in result.regions if r.id == ids[np.argmax(counts)])
    errors = []
    for obj in truth["objects"]:
        region = by_label[obj["paper_label"]]
        if obj["inter_object_depth_mm"] == 0:
            assert region.in_focus and result.focus_region == region.id
            assert abs(region.inter_object_depth_mm) < 5.0  # at half size; 1.3 mm worst at full size (`mca evaluate`)
        else:
            errors.append(
                abs(region.inter_object_depth_mm - obj["inter_object_depth_mm"]) / abs(obj["inter_object_depth_mm"])
            )
    assert np.median(errors) < 0.06 and max(errors) < 0.2  # at half size
    ranks = [by_label[label].order for label in "EDCBA"]  # E nearest ... A farthest
    assert ranks == sorted(ranks)
    wall = max(result.regions, key=lambda r: r.disparity_px)
    assert wall.order == len(result.regions) - 1
    assert abs(wall.inter_object_depth_mm - 500.0) < 40.0


def test_depth_map_and_units(paper_a):
    optics, _, result, _ = paper_a
    assert result.depth_mm is not None and result.depth_mm.shape == result.labels.shape
    for region in result.regions:
        inside = result.labels == region.id
        assert np.allclose(np.nanmedian(result.depth_mm[inside]), region.distance_mm, atol=3.0)
        assert np.isclose(region.distance_mm, optics.focus_distance_mm + region.inter_object_depth_mm)
    assert result.pixel_scale == 2.0


def test_three_d_images(paper_a):
    _, _, result, _ = paper_a
    assert len(result.layers) == len(result.regions)
    disparities = [layer.disparity_px for layer in result.layers]
    assert disparities == sorted(disparities, reverse=True)  # back to front
    alpha = sum(layer.rgba[..., 3] for layer in result.layers)
    assert np.allclose(alpha, 1.0)  # the planes tile the image
    flat = composite(result.layers)
    assert flat.shape == result.all_in_focus.shape
    for layer in result.layers:
        assert layer.inter_object_depth_mm is not None and layer.inter_image_depth_mm is not None


def test_recorder_and_timings(paper_a):
    _, _, result, recorder = paper_a
    stages = ["planes", "disparity", "surfaces", "sketch", "refine", "boundaries", "depth", "all_in_focus", "mpi"]
    assert list(recorder.stages) == stages
    assert set(stages) <= set(result.timings_s) and "total" in result.timings_s
    assert "confidence" in recorder.stages["disparity"] and "depth_mm" in recorder.stages["depth"]


def test_without_optics_depths_stay_none():
    profile = load_profile("bando2008")
    rng = np.random.default_rng(0)
    planes = np.clip(rng.random((90, 120, 3)).astype(np.float32), 0, 1)
    result = run_pipeline(planes, profile.aperture, None)
    assert result.depth_mm is None
    assert all(r.inter_object_depth_mm is None and r.distance_mm is None for r in result.regions)


def _evaluate_paper_scene(name: str, scale: float, seed: int = 0):
    from mca.processing.evaluate import evaluate_scene

    optics = SimulationOptics.from_profile(load_profile("paper-70d"), scale)
    sensor = SensorModel()
    rendering = render(paper_scene(name, optics.focus_distance_mm), optics, sensor, seed=seed)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    result = run_pipeline(
        planes, optics.aperture, optics.mca, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX
    )
    return evaluate_scene(rendering.truth, rendering.labels, result, optics.mca), result


def test_paper_e_spatula_is_one_region_behind_its_three_occluders():
    """The wooden spatula (+102 mm, wood close to the wall's colour) is cut in three by a tomato and the carrot
    and partly hidden by the other tomato: one region (the sketch joins the parts the occluders cut apart),
    behind all three, at the right depth (full size, as
    `mca evaluate`; at half size the per-region crop refinement reads the tomato D ~8 % far, a known gap
    logged in docs/pipeline.md)."""
    evaluation, _ = _evaluate_paper_scene("paper-e", 1.0)
    assert evaluation.region_count == evaluation.true_region_count == 6  # five objects and the wall
    assert evaluation.order_correct, evaluation.notes  # ranks and every true occlusion
    rows = {r.label: r for r in evaluation.rows}
    assert rows["E"].rel_error("ours") < 0.03
    assert max(r.rel_error("ours") for r in evaluation.rows if r.rel_error("ours") is not None) < 0.05
    assert rows["C"].abs_error_mm("ours") < 2.0  # the carrot, in focus


def test_paper_g_slanted_knife_is_one_plane():
    """The knife (a flat blade from -30 to +100 mm, its middle hidden by the carrot) is one slanted region whose
    plane gives both ends (full size, the issue's setting): the carrot cuts it in two parts that do not touch,
    and the sketch joins them because one plane fits both and they are one colour."""
    evaluation, result = _evaluate_paper_scene("paper-g", 1.0)
    assert evaluation.region_count == evaluation.true_region_count == 3  # knife, carrot, wall
    assert evaluation.order_correct, evaluation.notes
    rows = {r.label: r for r in evaluation.rows}
    assert rows["A"].rel_error("ours") < 0.05 and rows["B"].rel_error("ours") < 0.05
    assert rows["C"].abs_error_mm("ours") < 2.0
    assert sum(r.slant is not None for r in result.regions) == 1


def test_paper_c_blocks_of_one_colour_30_mm_apart_are_two_regions():
    """paper-c's blocks E (+60 mm) and F (+90 mm) overlap and share a colour; the dense disparity smooths the
    1 analysis px step between them into superpixels that lean across it, and the merge alone made them one
    region read at +71.8 mm. The sketch's split at the valley of the region's levels keeps them apart, and the
    refined planes say which block lies over which (full size, as `mca evaluate`)."""
    evaluation, _ = _evaluate_paper_scene("paper-c", 1.0)
    assert evaluation.region_count == evaluation.true_region_count == 7  # six blocks and the wall
    assert evaluation.order_correct, evaluation.notes  # each block over the next, 30 mm (1 analysis px) apart
    rows = {r.label: r for r in evaluation.rows}
    assert rows["E"].rel_error("ours") < 0.03 and rows["F"].rel_error("ours") < 0.03  # 1.2 % and 0.3 %


def _boundary_accuracy(labels: np.ndarray, truth: np.ndarray, width_px: int = 2) -> float:
    """Fraction of the pixels within `width_px` of a true object boundary whose region is (mostly) that object."""
    import cv2

    truth = truth[: labels.shape[0], : labels.shape[1]].astype(np.int64)
    regions, objects = int(labels.max()) + 1, int(truth.max()) + 1
    joint = np.bincount(labels.ravel().astype(np.int64) * objects + truth.ravel(), minlength=regions * objects)
    object_of = joint.reshape(regions, objects).argmax(axis=1)
    kernel = np.ones((2 * width_px + 1, 2 * width_px + 1), np.uint8)
    near = cv2.erode(truth.astype(np.uint16), kernel) != cv2.dilate(truth.astype(np.uint16), kernel)
    return float(np.mean(object_of[labels.astype(np.int64)][near] == truth[near]))


def test_region_boundaries_follow_the_objects_at_processing_resolution():
    """At half size the analysis grid is the processing grid: the superpixels cut along the colour edges of the
    fringe-free image, so the regions follow the objects (pixels within 2 px of a true boundary given the
    right object)."""
    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 0.5)
    sensor = SensorModel()
    rendering = render(paper_scene("paper-a", optics.focus_distance_mm), optics, sensor, seed=3)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    result = run_pipeline(
        planes, optics.aperture, optics.mca, pixel_scale=2.0, channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX
    )
    accuracy = _boundary_accuracy(result.labels, rendering.labels[::2, ::2])
    assert accuracy >= 0.62, accuracy  # 0.68 measured; the rest is the half-occluded strips (docs/pipeline.md)


def test_the_feature_bands_and_noise_of_the_analysis_grid_are_made_once(monkeypatch):
    """The dense search, the texture evidence and the refinement all read the analysis grid's feature bands and
    noise model: one `cost.cost_input` per capture (the dense search's quarter- and half-size levels have their
    own), and the result is the one the stages got when each made its own."""
    import mca.processing.cost as cost

    optics = SimulationOptics.from_profile(load_profile("paper-70d"), 0.2)
    sensor = SensorModel()
    rendering = render(paper_scene("paper-b", optics.focus_distance_mm), optics, sensor, seed=5)
    planes = bayer_planes(rendering.mosaic, sensor.black_level, sensor.white_level)
    shapes, noisy = [], []
    real_bands, real_noise = cost.feature_bands, cost.feature_noise

    def counting_bands(p, *a, **k):
        shapes.append(p.shape[:2])
        return real_bands(p, *a, **k)

    def counting_noise(p, *a, **k):
        noisy.append(p.shape[:2])
        return real_noise(p, *a, **k)

    monkeypatch.setattr(cost, "feature_bands", counting_bands)
    monkeypatch.setattr(cost, "feature_noise", counting_noise)
    recorder = ListRecorder()
    result = run_pipeline(
        planes,
        optics.aperture,
        optics.mca,
        pixel_scale=2.0,
        channel_offsets_px=RGGB_HALF_RES_OFFSETS_PX,
        recorder=recorder,
    )
    grid = recorder.stages["surfaces"]["labels"].shape
    assert shapes.count(grid) == 1 and noisy.count(grid) == 1, (grid, shapes)
    assert len(shapes) == len(set(shapes)) == 3  # the grid, its half for the coarse cost, its quarter for the range
    assert np.isfinite(result.disparity_px).all()


_KERNELS_SCRIPT = """
import sys
import numba
import numpy as np
sys.path.insert(0, sys.argv[1])
from mca_scenes import two_boxes_scene
import mca.processing as package
import pkgutil, importlib
from mca.devices.profiles import load_profile
from mca.processing.optics import MCAOptics
from mca.processing.labels import label_boxes
from mca.processing.pipeline import PipelineParams, load_kernels, run_pipeline

modules = [importlib.import_module(f"mca.processing.{m.name}") for m in pkgutil.iter_modules(package.__path__)]
kernels = {f"{m.__name__}.{k}": v for m in modules for k, v in vars(m).items()
           if isinstance(v, numba.core.registry.CPUDispatcher)}
profile = load_profile("paper-70d")
optics = MCAOptics.from_profile(profile, pixel_pitch_mm=profile.pixel_pitch_mm)
quality = sys.argv[2]
load_kernels(profile.aperture, optics, quality)
before = {name: len(k.signatures) for name, k in kernels.items()}
image, _, _ = two_boxes_scene(profile.aperture)
result = run_pipeline(image, profile.aperture, optics, params=PipelineParams.for_quality(quality))
label_boxes(result.labels)  # what the outputs take after the pipeline
new = [name for name, k in kernels.items() if len(k.signatures) > before[name]]
used = [name for name, n in before.items() if n > 0]
print("NEW", ",".join(new))
print("USED", len(used))
"""


@pytest.mark.parametrize("quality", ["full", "preview"])
def test_load_kernels_loads_every_kernel_the_pipeline_then_takes(tmp_path, quality):
    """`load_kernels` (run by `mca process` on a helper thread while it reads the photograph) on its small
    synthetic capture loads every compiled kernel, for every argument type, that a real capture then calls:
    in a fresh process, the pipeline on a scene of four objects at four depths, with optics, adds none."""
    import subprocess
    import sys

    script = tmp_path / "kernels.py"
    script.write_text(_KERNELS_SCRIPT)
    done = subprocess.run(
        [sys.executable, str(script), str(Path(__file__).parent), quality],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lines = dict(line.split(" ", 1) if " " in line else (line, "") for line in done.stdout.splitlines())
    assert lines["NEW"].strip() == ""
    assert int(lines["USED"]) >= 10  # the dense search, the aggregation, SLIC, the surfaces, the refinement ...


@pytest.mark.parametrize("dtype", [np.int32, np.uint16, np.int64, np.uint8])
def test_label_boxes_are_scipys_find_objects(dtype):
    """`labels.label_boxes` (the layers' and the scene's region boxes) against `scipy.ndimage.find_objects` on random
    label images: ids missing in between, 0 and negative labels that are no region, single rows and columns."""
    from scipy import ndimage

    from mca.processing.labels import label_boxes

    rng = np.random.default_rng(7)
    signed = np.issubdtype(dtype, np.signedinteger)
    for _ in range(60):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        labels = rng.integers(-2 if signed else 0, 9, (h, w)).astype(dtype)
        labels[labels == 4] = 0  # an id with no pixel below the largest
        expected = ndimage.find_objects(np.maximum(labels, 0).astype(np.int32))
        assert label_boxes(labels) == expected
    assert label_boxes(np.zeros((5, 4), dtype)) == []
    corner = np.zeros((6, 7), dtype)
    corner[5, 6] = 2
    assert label_boxes(corner) == [None, (slice(5, 6), slice(6, 7))]


def test_label_boxes_of_zero_based_labels_are_those_of_the_labels_plus_one():
    """`first_label=0` (superpixel indices, the refinement's cells): box k is that of label k, the same as the
    default boxes of the labels + 1; labels below it are no region."""
    from mca.processing.labels import label_boxes

    rng = np.random.default_rng(11)
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(1, 25, 2))
        labels = rng.integers(-1, 7, (h, w)).astype(np.int32)
        assert label_boxes(labels, first_label=0) == label_boxes(labels + 1)
    assert label_boxes(np.full((3, 3), -1, np.int32), first_label=0) == []
    assert label_boxes(np.array([[0, 2]], np.uint16), first_label=0) == [
        (slice(0, 1), slice(0, 1)),
        None,
        (slice(0, 1), slice(1, 2)),
    ]
    assert label_boxes(np.zeros((0, 3), np.uint8), first_label=0) == []
    assert label_boxes(np.array([[5, 3]]), first_label=3) == [
        (slice(0, 1), slice(1, 2)),
        None,
        (slice(0, 1), slice(0, 1)),
    ]
