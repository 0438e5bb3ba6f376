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
