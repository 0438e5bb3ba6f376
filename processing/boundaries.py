"""Region boundaries moved onto the objects' edges: each pixel of a narrow band along a boundary goes to the
neighbouring region whose colour, seen at that region's own disparity, it matches best.

The superpixels cut the image along the edges of an image aligned with the dense disparity, which near an
occluding edge is uncertain (the matching windows straddle it): the regions' outlines there are ragged by a
few pixels. Once every region has its model (plane or surface), the question for a pixel near a boundary is
a colour question that the MCA makes precise: aligned with the right region's disparity, the pixel's three
channels show one colour that matches that region's nearby interior; aligned with the wrong one, its channels
are torn apart (colour fringes) and match neither. For each region k the planes are re-aligned with k's model
over k's neighbourhood, k's local colour distribution (mean and variance) is taken over its interior pixels (box filters), and each
band pixel within reach of k is scored by its negative log-likelihood under it (a textured region's spread of
colours is expected, a flat region's is not). The band pixel takes the best-scoring region.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.disparity import channel_shifts, parallel_map, warp_channels
from mca.processing.features import percentile


@dataclass(frozen=True)
class BoundaryParams:
    """Parameters of the boundary snap (pixels of the grid it runs on)."""

    band_px: int = 4  # pixels this close to a region boundary may change region
    window_px: int = 21  # local colours of a region: its interior within this window (radius > 2 bands)
    passes: int = 2
    noise_var: float = 1e-4  # floor of a region's local colour variance (display values in [0, 1])


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def _appearance(linear: np.ndarray, white: float) -> np.ndarray:
    """Chromaticity (2) and log luminance (1) of linear RGB: a texture's shading moves the last only."""
    rgb = np.maximum(linear / np.float32(white), 1e-3)
    total = rgb.sum(axis=2)
    out = np.empty_like(rgb)
    out[..., 0] = rgb[..., 0] / total
    out[..., 1] = rgb[..., 2] / total
    out[..., 2] = np.float32(0.1) * np.log(total)
    return out


def snap_boundaries(
    planes: np.ndarray,
    aperture: FilterAperture,
    labels: np.ndarray,
    models: dict[int, np.ndarray],
    params: BoundaryParams = BoundaryParams(),
) -> np.ndarray:
    """Labels (H, W, ids >= 1) with their boundary bands reassigned (see the module docstring).

    planes: (H, W, 3) linear planes; models: region id -> its disparity (H, W) float32 (extended beyond the
    region, e.g. its plane) on the same grid."""
    original = labels.astype(np.int32)
    labels = original.copy()
    height, width = labels.shape
    white = percentile(planes, 99.5) or 1.0
    shifts = channel_shifts(aperture)
    reach = float(np.abs(shifts).max())
    ids = [int(i) for i in np.unique(labels) if int(i) in models]
    box = (params.window_px, params.window_px)
    reach_px = params.band_px + params.window_px // 2 + 1  # how far a region's scoring reaches beyond it
    channels = cv2.split(np.asarray(planes, dtype=np.float32))  # split once for every region's warp
    for _ in range(params.passes):
        edge = np.zeros((height, width), bool)
        edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
        edge[1:] |= labels[1:] != labels[:-1]
        band = _dilate(edge, params.band_px)
        if not band.any():
            break
        best = np.full((height, width), np.inf, np.float32)
        choice = labels.copy()

        def score_of(k: int, labels: np.ndarray = labels, band: np.ndarray = band) -> tuple | None:
            """Region k's scores over its grown box (None: nothing to score); reads only, so regions score side
            by side."""
            full_mask = labels == k
            rows, cols = np.flatnonzero(full_mask.any(axis=1)), np.flatnonzero(full_mask.any(axis=0))
            if rows.size == 0:
                return None
            # the region's box grown by the reach (an elliptic dilation's box is the grown box): all below
            # happens in it, where it equals the same work done on the whole frame
            y0, y1 = max(int(rows[0]) - reach_px, 0), min(int(rows[-1]) + 1 + reach_px, height)
            x0, x1 = max(int(cols[0]) - reach_px, 0), min(int(cols[-1]) + 1 + reach_px, width)
            mask = full_mask[y0:y1, x0:x1]
            near = _dilate(mask, params.band_px + 1) & band[y0:y1, x0:x1]
            if not near.any():
                return None
            core = (mask & ~band[y0:y1, x0:x1]).astype(np.float32)
            model = models[k][y0:y1, x0:x1]
            pad = int(np.ceil(float(np.abs(model).max()) * reach)) + 2
            if pad > max(height, width):
                return None
            warped = warp_channels(planes, aperture, model, origin_xy=(int(x0), int(y0)), channels=channels)
            aligned = _appearance(warped, white)
            count = cv2.boxFilter(core, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
            total = cv2.boxFilter(aligned * core[..., None], -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
            usable = near & (count >= 0.15 * params.window_px**2)
            squares = cv2.boxFilter(
                np.sum(aligned * aligned, axis=2) * core, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT
            )
            n = np.maximum(count, 1.0)
            mean = total / n[..., None]
            variance = np.maximum(squares / n - np.sum(mean * mean, axis=2), 0.0) / 3.0 + params.noise_var
            # negative log-likelihood under the region's local colour distribution (isotropic Gaussian)
            score = 0.5 * np.sum((aligned - mean) ** 2, axis=2) / variance + 1.5 * np.log(variance)
            score = cv2.blur(np.where(np.isfinite(score), score, 1e3).astype(np.float32), (3, 3))
            return y0, y1, x0, x1, np.where(usable, score, np.inf).astype(np.float32)

        # scored side by side, merged in the order of the ids (the same labels as one region after another)
        for k, scored in zip(ids, parallel_map(score_of, ids), strict=True):
            if scored is None:
                continue
            y0, y1, x0, x1, score = scored
            crop_best = best[y0:y1, x0:x1]
            better = score < crop_best
            crop_best[better] = score[better]
            choice[y0:y1, x0:x1][better] = k
        changed = band & np.isfinite(best) & (choice != labels)
        if not changed.any():
            break
        labels[changed] = choice[changed]
    lost = np.setdiff1d(np.unique(original), np.unique(labels))
    if lost.size:  # a region is never snapped away entirely: it keeps its own pixels
        back = np.isin(original, lost)
        labels[back] = original[back]
    return labels
