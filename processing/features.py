"""Feature planes for colour alignment: log-compressed colour planes turned into zero-mean band-pass images.

The colour-line cost (`processing.cost`) compares the channels' local structure, not their brightness: each
channel is log-compressed (exposure and shading become offsets) and reduced to three band-pass planes, its
horizontal and vertical derivatives at a fine scale and a difference of Gaussians. Zero local mean lets the
cost use uncentred correlations; the fine blur band-limits the planes for sampling at sub-pixel shifts
(`processing.cost`). `texture_energy` says how much there is to align at each pixel.
"""

from __future__ import annotations

import cv2
import numpy as np

LOG_GAIN = 32.0  # log1p(LOG_GAIN * v / white): nearly logarithmic above 3 % of white, linear below


def log_compress(planes: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear planes -> float32 log1p(32 v / white), white = the 99.5th percentile."""
    white = float(np.percentile(planes, 99.5)) or 1.0
    scaled = np.clip(planes, 0.0, None).astype(np.float32) * np.float32(LOG_GAIN / white)
    return np.log1p(scaled)


def feature_bands(
    planes: np.ndarray, gradient_sigma_px: float = 0.7, dog_sigmas_px: tuple[float, float] = (0.6, 1.5)
) -> list[np.ndarray]:
    """Three (H, W, 3) float32 zero-mean feature planes of linear colour planes: d/dx and d/dy of the
    log planes smoothed by `gradient_sigma_px`, and their difference of Gaussians at `dog_sigmas_px`."""
    log = log_compress(planes)
    gx = np.empty_like(log)
    gy = np.empty_like(log)
    dog = np.empty_like(log)
    for c in range(log.shape[2]):
        plane = np.ascontiguousarray(log[..., c])
        smooth = cv2.GaussianBlur(plane, (0, 0), gradient_sigma_px, borderType=cv2.BORDER_REFLECT)
        gx[..., c] = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) * np.float32(0.125)
        gy[..., c] = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) * np.float32(0.125)
        fine = cv2.GaussianBlur(plane, (0, 0), dog_sigmas_px[0], borderType=cv2.BORDER_REFLECT)
        coarse = cv2.GaussianBlur(plane, (0, 0), dog_sigmas_px[1], borderType=cv2.BORDER_REFLECT)
        dog[..., c] = fine - coarse
    return [gx, gy, dog]


def texture_energy(bands: list[np.ndarray], window_px: int) -> np.ndarray:
    """(H, W) float32 root-mean-square feature amplitude in a window: how much structure there is to align."""
    total = np.zeros(bands[0].shape[:2], np.float32)
    for band in bands:
        total += np.sum(band * band, axis=2)
    mean = cv2.boxFilter(total, cv2.CV_32F, (window_px, window_px), borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(mean / np.float32(3 * len(bands)), 0.0))


def display_gamma(planes: np.ndarray) -> np.ndarray:
    """Linear planes -> float32 values in [0, 1] with a 1/2.2 gamma, white at the 99.5th percentile: the image
    colour distances are measured on (segmentation, edge-adaptive penalties)."""
    white = float(np.percentile(planes, 99.5)) or 1.0
    return np.power(np.clip(planes.astype(np.float32) / np.float32(white), 0.0, 1.0), np.float32(1.0 / 2.2))
