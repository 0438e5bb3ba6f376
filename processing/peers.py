"""Peer methods run on the same MCA planes for comparison: OpenCV StereoSGBM and integer colour-line WTA."""

from __future__ import annotations

import math

import cv2
import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.disparity import DisparityParams, estimate_disparity


def _to_uint8(channel: np.ndarray) -> np.ndarray:
    """Contrast-normalise one channel to 8 bits (the channels of an MCA image differ in level and gain)."""
    log = np.log1p(np.clip(channel, 0.0, None) * 32.0 / (float(np.percentile(channel, 99.5)) or 1.0))
    low, high = np.percentile(log, (0.5, 99.5))
    return np.clip((log - low) / max(high - low, 1e-6) * 255.0, 0, 255).astype(np.uint8)


def sgbm_disparity(
    planes: np.ndarray, aperture: FilterAperture, range_px: tuple[float, float], block_px: int = 7
) -> np.ndarray:
    """OpenCV StereoSGBM between the two channels of the widest filter pair, the images rotated so that the
    pair's baseline is horizontal. Returns the widest-pair disparity (px of `planes`, + = farther), NaN invalid.

    For a farther object the first filter's channel moves along +baseline and the second's the other
    way, so the first channel is the left image: left(x) matches right(x - d).
    """
    first, second = aperture.widest_pair
    order = {"red": 0, "green": 1, "blue": 2}
    (ax, ay), (bx, by) = aperture.shift_per_disparity(first), aperture.shift_per_disparity(second)
    angle = math.degrees(math.atan2(ay - by, ax - bx))  # image angle of the baseline (y down)
    height, width = planes.shape[:2]
    centre = (width / 2.0, height / 2.0)
    rotate = cv2.getRotationMatrix2D(centre, angle, 1.0)  # baseline -> +x
    left = cv2.warpAffine(_to_uint8(planes[..., order[first]]), rotate, (width, height), flags=cv2.INTER_LINEAR)
    right = cv2.warpAffine(_to_uint8(planes[..., order[second]]), rotate, (width, height), flags=cv2.INTER_LINEAR)
    low = int(math.floor(range_px[0])) - 1
    count = int(math.ceil((range_px[1] - low + 1) / 16.0)) * 16
    matcher = cv2.StereoSGBM_create(  # type: ignore[attr-defined,unused-ignore]
        minDisparity=low,
        numDisparities=count,
        blockSize=block_px,
        P1=8 * block_px * block_px,
        P2=32 * block_px * block_px,
        uniquenessRatio=5,
        speckleWindowSize=0,
        mode=cv2.STEREO_SGBM_MODE_SGBM,
    )
    raw = matcher.compute(left, right).astype(np.float32) / 16.0
    raw[raw < low] = np.nan
    back = cv2.invertAffineTransform(rotate)
    valid = cv2.warpAffine(np.isfinite(raw).astype(np.float32), back, (width, height), flags=cv2.INTER_NEAREST)
    disparity = cv2.warpAffine(np.nan_to_num(raw), back, (width, height), flags=cv2.INTER_NEAREST)
    disparity[valid < 0.5] = np.nan
    return disparity


def colour_line_wta(
    planes: np.ndarray, aperture: FilterAperture, range_px: tuple[float, float], window_px: int = 15
) -> np.ndarray:
    """Bando et al. 2008 without their graph cut: integer winner-takes-all of the colour-line measure."""
    result = estimate_disparity(
        planes, aperture, range_px, DisparityParams(window_px=window_px, step_px=1.0, subpixel=False)
    )
    return result.disparity_px


def colour_line_cost(planes: np.ndarray, window_px: int) -> np.ndarray:
    """Bando et al.'s colour-alignment measure per pixel: det(C) / (C_rr C_gg C_bb) of the 3x3 colour covariance
    C over a `window_px` square window (0 = the colours lie on a line, 1 = uncorrelated)."""
    size = (window_px, window_px)
    x = [np.asarray(planes[..., c], np.float64) for c in range(3)]
    mean = [cv2.boxFilter(c, cv2.CV_64F, size, borderType=cv2.BORDER_REFLECT) for c in x]

    def cov(i: int, j: int) -> np.ndarray:
        return cv2.boxFilter(x[i] * x[j], cv2.CV_64F, size, borderType=cv2.BORDER_REFLECT) - mean[i] * mean[j]

    rr, gg, bb = cov(0, 0), cov(1, 1), cov(2, 2)
    rg, rb, gb = cov(0, 1), cov(0, 2), cov(1, 2)
    det = rr * (gg * bb - gb * gb) - rg * (rg * bb - gb * rb) + rb * (rg * gb - gg * rb)
    return (det / (np.maximum(rr, 0.0) * np.maximum(gg, 0.0) * np.maximum(bb, 0.0) + 1e-10)).astype(np.float32)


def colour_line_wta_subpixel(
    planes: np.ndarray,
    aperture: FilterAperture,
    range_px: tuple[float, float],
    *,
    window_px: int = 15,
    steps: int = 81,
) -> np.ndarray:
    """Winner-takes-all of the colour-line measure over `steps` evenly spaced disparities in `range_px`
    (widest-pair px of `planes`): each channel is sampled where a point of that disparity images it
    (bilinear, along its own filter direction), the cost evaluated over a `window_px` window, the best
    step kept. No smoothing, no sub-step refinement: the plain local peer of issue 12 (15x15, 81 steps).
    Self-contained, so that it stays the same whatever the pipeline's own disparity search becomes."""
    planes = np.asarray(planes, np.float32)
    height, width = planes.shape[:2]
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    best_cost = np.full((height, width), np.inf, np.float32)
    best = np.full((height, width), np.nan, np.float32)
    directions = [aperture.shift_per_disparity(c) for c in ("red", "green", "blue")]
    for disparity in np.linspace(range_px[0], range_px[1], steps):
        shifted = np.empty_like(planes)
        for c, (sx, sy) in enumerate(directions):
            dx, dy = sx * disparity, sy * disparity
            if dx == 0 and dy == 0:
                shifted[..., c] = planes[..., c]
                continue
            shifted[..., c] = cv2.remap(
                planes[..., c],
                xs + np.float32(dx),
                ys + np.float32(dy),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REFLECT,
            )
        cost = colour_line_cost(shifted, window_px)
        better = cost < best_cost
        best_cost[better] = cost[better]
        best[better] = np.float32(disparity)
    return best
