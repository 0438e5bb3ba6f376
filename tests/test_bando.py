"""Real colour-filtered-aperture photographs of Bando et al. 2008 (read from ../shared/data, never committed).

Units: our disparity is between the widest filter pair (red-blue), which for that camera is
2 d, d being the per-channel shift of the authors' NOTICE (books ~ +4 d = +8 px, wall ~ +6 d = +12 px).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.processing.pipeline import run_pipeline

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "bando2008"


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    return np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4).astype(np.float32)


@pytest.fixture(scope="module")
def dog():
    path = DATA / "dog.png"
    if not path.exists():
        pytest.skip(f"Bando 2008 sample photographs not found at {DATA} (kept out of the repository)")
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
    return run_pipeline(srgb_to_linear(image), load_profile("bando2008").aperture, None)


def patch(result, x: int, y: int, size: int = 15) -> float:
    return float(np.median(result.disparity_px[y - size : y + size, x - size : x + size]))


def region_at(result, x: int, y: int):
    region_id = int(result.labels[y, x])
    return next(r for r in result.regions if r.id == region_id)


def test_dog_in_focus_books_then_wall(dog):
    dog_px = region_at(dog, 420, 300).disparity_px  # the toy dog's body (a region: the fur is not one plane)
    books_px = patch(dog, 650, 300)  # the books to its right
    wall_px = patch(dog, 150, 100)  # the far background
    assert abs(dog_px) < 0.5  # widest pair; |d| < 0.25 in the authors' units
    assert abs(patch(dog, 420, 300)) < 1.25  # its chest, nearer than its ears: within 0.6 of the authors' d
    assert dog_px < books_px < wall_px  # books nearer than the background, both behind the dog
    assert 5.0 < books_px < 12.0 and 10.0 < wall_px < 17.0  # ~ 2 x (4, 6) of the NOTICE


def test_dog_region_is_the_focus_region(dog):
    region_id = int(dog.labels[300, 420])
    region = next(r for r in dog.regions if r.id == region_id)
    assert abs(region.disparity_px) < 0.5
    assert region.distance_mm is None  # no optics for this camera: pixels only


# Points on each object of dog.png (input pixels, x, y), each at least 10 px inside the object: the dog's body and
# ears, the books, the wall's patterned cloth and its lighter sheet, the red and the blue cookie box
DOG_OBJECTS = {
    "dog": [(420, 300), (305, 235), (540, 200)],
    "books": [(650, 310), (620, 420)],
    "wall": [(150, 100), (650, 40)],
    "boxes": [(150, 250), (200, 420)],
}


def object_failures(labels: np.ndarray, objects: dict[str, list[tuple[int, int]]]) -> list[str]:
    """What is wrong with `labels` for `objects`: a region holding points of two objects ("wall+dog"), an object
    whose points lie in more than one region ("books split"); empty when every object is one region of its own."""
    failures = []
    owner: dict[int, str] = {}
    for name, xys in objects.items():
        for x, y in xys:
            first = owner.setdefault(int(labels[y, x]), name)
            if first != name:
                failures.append(f"{name}+{first} at {(x, y)}")
    for name, xys in objects.items():
        if len({int(labels[y, x]) for x, y in xys}) != 1:
            failures.append(f"{name} split")
    return failures


def test_dog_books_wall_and_boxes_are_one_region_each(dog):
    """No region holds two of the objects, and each object's points are one region (the wall's patterned cloth and
    lighter sheet, and the red and the blue cookie box, join in the same-depth pass: their planes meet within
    0.2 px). `benchmarks/bando_stability.py` counts how often this holds under input noise."""
    assert object_failures(dog.labels, DOG_OBJECTS) == []


def test_sheep_regions_corrections_stay_within_what_the_refinement_searched(monkeypatch):
    """The refinement fits each region's correction to its cells' cost minima, which lie within the offsets it
    searched (+-1.5 px, then +-0.3 px). On `sheep.png` a small region at the top left had cells whose centroids lay
    a few pixels apart: the plane through them sloped 0.58 px per px and reached -17 and +11 px at the region's
    corners, a streak across the dense map. Corrections now stay within twice each pass's range everywhere in
    the region's bounding box."""
    import cv2

    from mca.processing import pipeline, refine

    path = DATA / "sheep.png"
    if not path.exists():
        pytest.skip(f"Bando 2008 sample photographs not found at {DATA} (kept out of the repository)")
    seen = {}

    def spy(bands, aperture, labels, model, params, **kwargs):
        seen["labels"], seen["params"] = labels, params
        seen["out"] = refine.refine_regions(bands, aperture, labels, model, params, **kwargs)
        return seen["out"]

    monkeypatch.setattr(pipeline, "refine_regions", spy)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
    run_pipeline(srgb_to_linear(image), load_profile("bando2008").aperture, None)
    labels, params = seen["labels"], seen["params"]
    limit = 2 * params.search_px + 2 * (2 * params.fine_step_px)
    reach = {}
    for rid, (a, b, c) in seen["out"].corrections.items():
        ys, xs = np.nonzero(labels == rid)
        corners = np.array([[x, y] for x in (xs.min(), xs.max()) for y in (ys.min(), ys.max())], np.float64)
        reach[rid] = float(np.abs(corners @ np.array([a, b]) + c).max())
    assert reach and max(reach.values()) <= limit, reach


# The main object of each of the other three photographs, and points off it (input pixels, x, y)
MAIN_OBJECTS = {
    "sheep.png": {"object": [(150, 300), (450, 200), (290, 165), (300, 420)], "off": [(560, 50), (600, 300)]},
    "chair.png": {"object": [(350, 200), (420, 380), (280, 300), (360, 150)], "off": [(100, 300), (100, 40)]},
    "bonsai.png": {"object": [(300, 200), (500, 280), (200, 300)], "off": [(250, 50), (650, 350), (50, 150)]},
}


def main_object_failures(labels: np.ndarray, points: dict[str, list[tuple[int, int]]]) -> list[str]:
    """What is wrong with `labels` for a photograph's main object (`MAIN_OBJECTS`): its points in more than one
    region, or its region holding a point off it; empty when neither."""
    regions = {int(labels[y, x]) for x, y in points["object"]}
    failures = [f"object split into {len(regions)}"] if len(regions) != 1 else []
    failures += [f"object holds {(x, y)}" for x, y in points["off"] if int(labels[y, x]) in regions]
    return failures


@pytest.mark.parametrize("name", sorted(MAIN_OBJECTS))
def test_each_photographs_main_object_is_one_region(name):
    """The sheep (body, head, ear, legs' top), the chair's back and the bonsai's crown: each one region, which
    holds none of the points on the background behind it."""
    import cv2

    path = DATA / name
    if not path.exists():
        pytest.skip(f"Bando 2008 sample photographs not found at {DATA} (kept out of the repository)")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
    result = run_pipeline(srgb_to_linear(image), load_profile("bando2008").aperture, None)
    assert main_object_failures(result.labels, MAIN_OBJECTS[name]) == []


def test_the_object_checks_name_what_is_wrong():
    """The checks above and `benchmarks/bando_stability.py` read these helpers: each kind of failure is named."""
    labels = np.zeros((50, 50), np.int32)
    labels[:, 25:] = 1
    objects = {"a": [(5, 5), (10, 40)], "b": [(30, 5), (40, 40)]}
    assert object_failures(labels, objects) == []
    labels[40:, 30:] = 0  # b's second point now in a's region
    assert object_failures(labels, objects) == ["b+a at (40, 40)", "b split"]
    labels[40:, 30:] = 2  # ... or in a region of its own
    assert object_failures(labels, objects) == ["b split"]
    points = {"object": [(5, 5), (10, 40)], "off": [(30, 5), (20, 20)]}
    assert main_object_failures(labels, points) == ["object holds (20, 20)"]
    assert main_object_failures(labels, {"object": [(5, 5), (30, 5)], "off": []}) == ["object split into 2"]
