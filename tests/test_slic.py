"""Our SLIC (`processing.slic`) against scikit-image's `slic`, the independent reference: the same labels,
pixel for pixel, on real photographs, on flat colours (where many distances tie) and on noise."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.segmentation import slic

from mca.processing.slic import slic_labels
from mca.processing.surfaces import SurfaceParams, superpixels

MIDDLEBURY = Path(__file__).resolve().parents[2] / "shared" / "data" / "middlebury"


def reference(image: np.ndarray, n_segments: int, compactness: float, iterations: int) -> np.ndarray:
    return slic(
        image,
        n_segments=n_segments,
        compactness=compactness,
        max_num_iter=iterations,
        start_label=0,
        channel_axis=-1,
    )


def photograph(scene: str, width: int) -> np.ndarray:
    path = MIDDLEBURY / scene / "im.png"
    if not path.exists():
        pytest.skip(f"Middlebury photographs not found at {MIDDLEBURY} (kept out of the repository)")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
    height = image.shape[0] * width // image.shape[1]
    return np.ascontiguousarray(cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA))


def flat_blocks(shape: tuple[int, int]) -> np.ndarray:
    """Blocks of four flat colours: every colour distance inside a block is the same, so pixels halfway
    between two centres tie exactly and only the order of the offers decides."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    palette = np.array([[0.8, 0.2, 0.1], [0.1, 0.6, 0.3], [0.2, 0.3, 0.9], [0.9, 0.9, 0.2]], np.float32)
    return palette[((yy // 37) + 2 * (xx // 53)) % 4]


@pytest.mark.parametrize(
    ("scene", "width", "segments", "compactness", "iterations"),
    [("Art", 400, 300, 10.0, 10), ("Reindeer", 333, 150, 4.0, 4), ("Laundry", 517, 480, 20.0, 7)],
)
def test_the_labels_of_a_photograph_are_scikit_images(scene, width, segments, compactness, iterations):
    image = photograph(scene, width)
    ours = slic_labels(image, segments, compactness, iterations)
    assert np.array_equal(ours, reference(image, segments, compactness, iterations))


def test_flat_colours_break_ties_as_scikit_image_does():
    """Blocks of flat colour (clusters emptied on the way), and one flat colour, where a pixel halfway between
    two grid seeds is offered the same distance by both: the earlier cluster keeps it (taking it at equal
    distance gives other labels on all three flat images)."""
    image = flat_blocks((211, 305))
    assert np.array_equal(slic_labels(image, 120, 10.0, 10), reference(image, 120, 10.0, 10))
    for shape, segments in (((100, 100), 4), ((120, 90), 12), ((64, 200), 8)):
        flat = np.full(shape + (3,), 0.4, np.float32)
        assert np.array_equal(slic_labels(flat, segments, 10.0, 10), reference(flat, segments, 10.0, 10)), shape


def test_noise_and_a_narrow_image_give_scikit_images_labels():
    rng = np.random.default_rng(3)
    noise = rng.random((97, 203, 3)).astype(np.float32)
    assert np.array_equal(slic_labels(noise, 60, 10.0, 10), reference(noise, 60, 10.0, 10))
    strip = np.ascontiguousarray(noise[:, :9])  # narrower than a grid step: one column of seeds
    assert np.array_equal(slic_labels(strip, 12, 10.0, 10), reference(strip, 12, 10.0, 10))


def test_the_surfaces_take_the_same_superpixels_as_before():
    """`surfaces.superpixels` on a real photograph: the labels scikit-image's slic gives, numbered densely."""
    image = photograph("Art", 300)
    params = SurfaceParams()
    count = int(round(image.shape[0] * image.shape[1] / params.superpixel_px))
    expected = reference(image, count, params.compactness, params.slic_iterations)
    _, dense = np.unique(expected, return_inverse=True)
    assert np.array_equal(superpixels(image, params), dense.reshape(expected.shape).astype(np.int32))


def test_bad_images_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="RGB"):
        slic_labels(np.zeros((10, 10), np.float32), 4, 10.0, 10)
    with pytest.raises(ValueError, match="float32"):
        slic_labels(np.zeros((10, 10, 3)), 4, 10.0, 10)
    bad = np.zeros((10, 10, 3), np.float32)
    bad[2, 3, 1] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        slic_labels(bad, 4, 10.0, 10)
