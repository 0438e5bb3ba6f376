"""Depth from region disparities: inter-image depth (eq. 2), inter-object depth (eqs. 13/14), distance, dense map."""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from mca.processing.optics import (
    MCAOptics,
    inter_image_depth_mm,
    inter_object_depth_far_mm,
    inter_object_depth_near_mm,
)


@dataclass(frozen=True)
class RegionDepth:
    """The depth chain of one region (or one point), signs: + = farther than the focus plane."""

    disparity_px: float  # widest filter pair, input-image pixels
    inter_image_depth_mm: float  # Δd, eq. 2
    inter_object_depth_mm: float  # ΔD, eq. 13 (far side) / eq. 14 (near side)
    distance_mm: float  # from the lens: focus distance + ΔD


def region_depth(disparity_px: float, optics: MCAOptics) -> RegionDepth:
    """Disparity (input px) -> Δd (eq. 2) -> ΔD (eqs. 13/14) -> distance from the lens."""
    inter_image = float(optics.inter_image_depth_mm(float(disparity_px)))  # eq. 2
    inter_object = float(optics.inter_object_depth_mm(inter_image))  # eqs. 13/14
    return RegionDepth(float(disparity_px), inter_image, inter_object, optics.focus_distance_mm + inter_object)


@nb.njit(cache=True, parallel=True)
def _distance_kernel(disparity, pitch_mm, sensor_mm, filters_mm, focal_mm, focus_mm, valid, use_valid, out):
    h, w = disparity.shape
    for y in nb.prange(h):
        for x in range(w):
            if use_valid and not valid[y, x]:
                out[y, x] = np.nan
                continue
            inter_image = inter_image_depth_mm(np.float64(disparity[y, x]) * pitch_mm, sensor_mm, filters_mm)  # eq. 2
            if inter_image >= 0:
                inter_object = inter_object_depth_far_mm(inter_image, sensor_mm, focal_mm)  # eq. 13
            else:  # NaN too, as np.where's false branch: eq. 14 keeps it NaN
                inter_object = -inter_object_depth_near_mm(-inter_image, sensor_mm, focal_mm)  # eq. 14
            out[y, x] = focus_mm + inter_object


def depth_map_mm(disparity_px: np.ndarray, optics: MCAOptics, valid: np.ndarray | None = None) -> np.ndarray:
    """Dense distance from the lens (mm, float32) for a disparity map in input pixels; NaN where not `valid`.

    Per pixel, in float64, the formulas of `MCAOptics.distance_mm` (eqs. 2 and 13/14); one compiled pass, no
    full-size float64 temporaries."""
    disparity = np.asarray(disparity_px)
    out = np.empty(disparity.shape, np.float32)
    width = disparity.shape[-1] if disparity.ndim else 1
    rows = np.ascontiguousarray(disparity).reshape(-1, width)  # any shape, as rows
    mask = np.ones((1, 1), bool) if valid is None else np.asarray(valid, bool).reshape(-1, width)
    _distance_kernel(
        rows,
        float(optics.pixel_pitch_mm),
        float(optics.sensor_distance_mm),
        float(optics.filter_centre_distance_mm),
        float(optics.focal_length_mm),
        float(optics.focus_distance_mm),
        mask,
        valid is not None,
        out.reshape(-1, width),
    )
    return out
