"""The displacement between two images, to a few thousandths of a pixel, for the tests that check where an MCA
renderer puts each channel (`tests/test_render_rgbd.py` checks it against known shifts)."""

from __future__ import annotations

import cv2
import numpy as np


def phase_shift_px(moved: np.ndarray, reference: np.ndarray, border: int = 40) -> tuple[float, float]:
    """(dx, dy) such that moved(x) = reference(x - d), by phase correlation: the integer part from the peak of
    the phase correlation, the rest from the slope of the cross-power spectrum's phase, -2 pi (f_x dx + f_y dy),
    fitted over the low frequencies (weighted by magnitude) of the Hann-windowed interiors."""
    # windowed, or a shift of several pixels against the image's edges can win the peak; phaseCorrelate windows
    # float64 inputs in place, hence the copies astype makes
    window = cv2.createHanningWindow(reference.shape[::-1], cv2.CV_64F)
    (cx, cy), _ = cv2.phaseCorrelate(reference.astype(np.float64), moved.astype(np.float64), window)
    ix, iy = int(round(cx)), int(round(cy))
    h, w = reference.shape
    a = reference[border : h - border, border : w - border].astype(np.float64)
    b = moved[border + iy : h - border + iy, border + ix : w - border + ix].astype(np.float64)
    window = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    cross = np.fft.fft2((b - b.mean()) * window) * np.conj(np.fft.fft2((a - a.mean()) * window))
    fy = np.broadcast_to(np.fft.fftfreq(a.shape[0])[:, None], a.shape)
    fx = np.broadcast_to(np.fft.fftfreq(a.shape[1])[None, :], a.shape)
    radius = np.hypot(fx, fy)
    low = (radius > 0) & (radius < 0.15)
    weight = np.sqrt(np.abs(cross[low]))
    design = np.stack([fx[low], fy[low]], axis=1) * (-2.0 * np.pi) * weight[:, None]
    (dx, dy), *_ = np.linalg.lstsq(design, np.angle(cross[low]) * weight, rcond=None)
    return ix + float(dx), iy + float(dy)
