"""The 3D images as multi-plane images (paper eqs. 3 and 16) and the all-in-focus image with colour fringes removed."""

from __future__ import annotations

import cv2
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.disparity import warp_channels
from mca.processing.features import percentile
from mca.processing.result import MultiPlaneImage


def all_in_focus(planes: np.ndarray, aperture: FilterAperture, disparity_px: np.ndarray) -> np.ndarray:
    """Each channel sampled at x + d(x) s_c with the region-model disparity (processing px): the channels of
    every region are re-aligned, so its colour fringes vanish (section V-A)."""
    image = warp_channels(planes, aperture, disparity_px, cv2.INTER_CUBIC)
    return np.maximum(image, 0.0, out=image)  # cubic overshoot below black


def region_alpha(labels: np.ndarray, region_id: int, feather_px: float = 0.0) -> np.ndarray:
    """Coverage of one region (float32 in [0, 1]), optionally feathered at its boundary."""
    alpha = (labels == region_id).astype(np.float32)
    if feather_px > 0:
        alpha = cv2.GaussianBlur(alpha, (0, 0), feather_px)
    return alpha


def multi_plane_images(
    image: np.ndarray,
    labels: np.ndarray,
    region_ids: list[int],
    disparities_px: dict[int, float],
    inter_image_depths_mm: dict[int, float | None],
    inter_object_depths_mm: dict[int, float | None],
) -> list[MultiPlaneImage]:
    """One RGBA plane per region, ordered back to front (farthest first, ready for `over` compositing).

    The 3D perception image places plane l at its inter-image depth Δd_0l (eq. 3); the accurate
    3D image places the same plane at its inter-object depth ΔD_0l (eq. 16).
    Each plane's RGBA is made when it is read (`MultiPlaneImage.rgba`) from the shared display image and
    label map: building them all up front cost a second and one full-size RGBA copy per region.
    """
    step = max(1, int(np.sqrt(image.shape[0] * image.shape[1] / 250_000)))
    scale = percentile(image[::step, ::step], 99.5) or 1.0
    display = np.multiply(image, np.float32(1.0 / scale), dtype=np.float32)
    np.clip(display, 0.0, 1.0, out=display)
    layers = []
    for region_id in sorted(region_ids, key=lambda i: -disparities_px[i]):
        layers.append(
            MultiPlaneImage(
                region_id,
                None,
                inter_image_depths_mm.get(region_id),
                inter_object_depths_mm.get(region_id),
                disparities_px[region_id],
                source=(display, labels),
            )
        )
    return layers


def composite(layers: list[MultiPlaneImage]) -> np.ndarray:
    """`over` compositing of premultiplied planes given back to front (eq. 3's ⊕)."""
    out = np.zeros(layers[0].rgba.shape[:2] + (3,), np.float32)
    for layer in layers:
        alpha = layer.rgba[..., 3:4]
        out = out * (1.0 - alpha) + layer.rgba[..., :3]
    return out
