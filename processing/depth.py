"""Depth from region disparities: inter-image depth (eq. 2), inter-object depth (eqs. 13/14), distance, dense map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mca.processing.optics import MCAOptics


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


def depth_map_mm(disparity_px: np.ndarray, optics: MCAOptics, valid: np.ndarray | None = None) -> np.ndarray:
    """Dense distance from the lens (mm, float32) for a disparity map in input pixels; NaN where not `valid`."""
    inter_image = optics.inter_image_depth_mm(disparity_px.astype(np.float64))  # eq. 2
    distance = optics.focus_distance_mm + optics.inter_object_depth_mm(inter_image)  # eqs. 13/14
    distance = distance.astype(np.float32)
    if valid is not None:
        distance[~valid] = np.nan
    return distance
