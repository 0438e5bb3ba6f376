"""Feature planes for colour alignment: log-compressed colour planes turned into zero-mean band-pass images.

The colour-line cost (`processing.cost`) compares the channels' local structure, not their brightness: each
channel is log-compressed (exposure and shading become offsets) and reduced to three band-pass planes, its
horizontal and vertical derivatives at a fine scale and a difference of Gaussians. Zero local mean lets the
cost use uncentred correlations; the fine blur band-limits the planes for sampling at sub-pixel shifts
(`processing.cost`). `texture_energy` says how much there is to align at each pixel, `signal_weight` how much of
it is signal rather than sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

LOG_GAIN = 32.0  # log1p(LOG_GAIN * v / white): nearly logarithmic above 3 % of white, linear below


def percentile(values: np.ndarray, q: float) -> float:
    """`np.percentile(values, q)` (linear interpolation, finite values), interpolated in float64 whatever the
    dtype: the same bits under every numpy. numpy 2.0 and 2.4 interpolate a float32 array's percentile with
    different roundings (a capture's white 0.35143268 against 0.35143256): the log planes, and from them every
    disparity, then differed between installs. The order statistics themselves are exact."""
    flat = np.ravel(values)
    position = (float(q) / 100.0) * (flat.size - 1)
    below = int(np.floor(position))
    above = min(below + 1, flat.size - 1)
    part = np.partition(flat, (below, above))
    low, high = float(part[below]), float(part[above])
    t = position - below
    step = high - low
    return high - step * (1.0 - t) if t >= 0.5 else low + step * t


def log_compress(planes: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear planes -> float32 log1p(32 v / white), white = the 99.5th percentile."""
    white = percentile(planes, 99.5) or 1.0
    scaled = np.clip(planes, 0.0, None).astype(np.float32) * np.float32(LOG_GAIN / white)
    return np.log1p(scaled)


def gaussian_blur(plane: np.ndarray, sigma_px: float) -> np.ndarray:
    """`cv2.GaussianBlur(plane, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)` of an (H, W) float32 plane, with
    the same bits under OpenCV 4.10 and 5.0: those round a row's last few pixels differently when the width is not
    a multiple of their vector width (the quarter- and half-size planes, 342 and 684 px wide). The plane is
    reflected out to a multiple of 32 px (at least 32 more: more than the kernel's reach), blurred and cut back,
    which is the reflected blur of the plane itself with OpenCV 4.10's bits."""
    width = plane.shape[1]
    pad = (-width) % 32 + 32
    wide = cv2.copyMakeBorder(plane, 0, 0, 0, pad, cv2.BORDER_REFLECT)
    return np.ascontiguousarray(cv2.GaussianBlur(wide, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)[:, :width])


def feature_bands(
    planes: np.ndarray,
    gradient_sigma_px: float = 0.7,
    dog_sigmas_px: tuple[float, float] = (0.6, 1.5),
    log: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Three (H, W, 3) float32 zero-mean feature planes of linear colour planes: d/dx and d/dy of the
    log planes smoothed by `gradient_sigma_px`, and their difference of Gaussians at `dog_sigmas_px`; `log` is
    `log_compress(planes)` when the caller has it (it is then not made again)."""
    return _band_filters(log_compress(planes) if log is None else log, gradient_sigma_px, dog_sigmas_px)


def _band_filters(log: np.ndarray, gradient_sigma_px: float, dog_sigmas_px: tuple[float, float]) -> list[np.ndarray]:
    """The linear part of `feature_bands`, applied to (H, W, C) log planes."""
    gx = np.empty_like(log)
    gy = np.empty_like(log)
    dog = np.empty_like(log)
    for c in range(log.shape[2]):
        plane = np.ascontiguousarray(log[..., c])
        smooth = gaussian_blur(plane, gradient_sigma_px)
        gx[..., c] = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) * np.float32(0.125)
        gy[..., c] = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) * np.float32(0.125)
        fine = gaussian_blur(plane, dog_sigmas_px[0])
        coarse = gaussian_blur(plane, dog_sigmas_px[1])
        dog[..., c] = fine - coarse
    return [gx, gy, dog]


@dataclass(frozen=True)
class FeatureNoise:
    """The sensor noise as the feature planes carry it, beside their signal, for `processing.cost` to take out
    the part of the cost that depends on how sampling averages noise and signal differently.

    `variance` (3, H, W) float32 is each channel's noise variance at each pixel of its log plane; a band's noise
    variance is that times `band_gain[b]`. A band's noise correlates with itself `band_rho[b, axis, lag - 1]` at
    lags 1..3 along x (axis 0) and y (axis 1), its signal (the band less its noise, over the whole image)
    `signal_rho[b, channel, axis, lag - 1]`."""

    variance: np.ndarray
    band_gain: np.ndarray  # (B,) float64
    band_rho: np.ndarray  # (B, 2, 3) float64
    signal_rho: np.ndarray  # (B, 3, 2, 3) float64


def feature_noise(
    planes: np.ndarray,
    bands: list[np.ndarray] | None = None,
    gradient_sigma_px: float = 0.7,
    dog_sigmas_px: tuple[float, float] = (0.6, 1.5),
    log: np.ndarray | None = None,
) -> FeatureNoise:
    """The noise of `feature_bands(planes, ...)` (`FeatureNoise`); `bands`, if given, must be those planes, and
    `log`, if given, `log_compress(planes)`.

    Per channel, the noise of the log plane is measured where it shows least mixed with structure: in the
    diagonal Haar detail (a - b - c + d) / 2 of 2 x 2 blocks, whose variance is the pixel noise variance for
    white noise, averaged over the 16 blocks of 8 x 8 patches. Noise depends on brightness (photon noise; the log
    compresses bright values), so the patches are binned by brightness (24 bins of equal count) and each bin's
    variance is taken from its quietest patches (the 10th percentile, 0.582 of the variance for Gaussian noise:
    at least a tenth of a bin's patches must be free of fine structure, and texture can only raise the
    estimate). A raw sensor's noise variance is alpha x + beta in linear units (photon and read noise), which
    the log turns into (A (e^y - 1) + B) e^(-2y) (`_log_noise`); that curve is fitted to the bins (a lower
    envelope: bins well above it hold texture) and gives every pixel's variance from its brightness. (Reading
    each pixel's variance off the bins directly went wrong where one surface fills most of the image and the
    bins crowd its levels: on paper-e's analysis grid the red tomatoes' red noise came out 18 times too high
    against a noise-free render of the same scene; the fitted curve is within 0.8-1.4 of it everywhere.)

    The bands' noise gains and correlations are their filters' response to white noise (their impulse
    response); their signal's correlations are the bands' own, less the noise's share."""
    log = log_compress(planes) if log is None else log
    h, w = log.shape[:2]
    variance = np.empty((3, h, w), np.float32)
    for c in range(3):
        variance[c] = _brightness_noise(np.ascontiguousarray(log[..., c]))
    gain, rho = _band_noise_response(gradient_sigma_px, dog_sigmas_px)
    if bands is None:
        bands = _band_filters(log, gradient_sigma_px, dog_sigmas_px)
    signal_rho = np.empty((len(bands), 3, 2, 3))
    for b, band in enumerate(bands):
        for c in range(3):
            total, together = _lag_means(np.ascontiguousarray(band[..., c]))
            # summed in float64 and rounded to float32: numpy 2.0 and 2.4 sum a float32 plane in other orders
            # (89678.836 against 89678.859), and a float64 sum's last bit could still differ; its float32 does not
            noise = float(np.float32(np.mean(variance[c], dtype=np.float64))) * gain[b]
            signal = total - noise
            for lag in (1, 2, 3):
                for axis in (0, 1):
                    if signal <= 0.1 * total:  # (nearly) nothing but noise: no signal to keep in step with
                        signal_rho[b, c, axis, lag - 1] = rho[b, axis, lag - 1]
                        continue
                    value = (together[axis, lag - 1] - rho[b, axis, lag - 1] * noise) / signal
                    signal_rho[b, c, axis, lag - 1] = min(max(value, -1.0), 1.0)
    return FeatureNoise(variance, gain, rho, signal_rho)


@nb.njit(cache=True)
def _lag_means(x: np.ndarray) -> tuple[float, np.ndarray]:
    """mean(x^2) of an (H, W) plane, and the mean products x[., j + lag] x[., j] (axis 0: along x) and
    x[i + lag, .] x[i, .] (axis 1: along y) for lags 1..3, in float64, in one pass."""
    h, w = x.shape
    total = 0.0
    sums = np.zeros((2, 3))
    for i in range(h):
        for j in range(w):
            v = np.float64(x[i, j])
            total += v * v
            for lag in range(1, 4):
                if j + lag < w:
                    sums[0, lag - 1] += np.float64(x[i, j + lag]) * v
                if i + lag < h:
                    sums[1, lag - 1] += np.float64(x[i + lag, j]) * v
    means = np.zeros((2, 3))
    for lag in range(1, 4):
        means[0, lag - 1] = sums[0, lag - 1] / max(h * (w - lag), 1)
        means[1, lag - 1] = sums[1, lag - 1] / max((h - lag) * w, 1)
    return total / max(h * w, 1), means


def _brightness_noise(log_plane: np.ndarray, bins: int = 24) -> np.ndarray:
    h, w = log_plane.shape
    even = log_plane[: h // 8 * 8, : w // 8 * 8].astype(np.float64)
    a, b = even[0::2, 0::2], even[0::2, 1::2]
    c, d = even[1::2, 0::2], even[1::2, 1::2]
    # per 8 x 8 patch: the mean square of its 16 diagonal details, and its mean level
    energy = ((a - b - c + d) * 0.5) ** 2
    hq, wq = energy.shape[0] // 4, energy.shape[1] // 4
    if hq * wq < 10 * bins:
        return np.zeros((h, w), np.float32)
    patch_energy = energy.reshape(hq, 4, wq, 4).mean(axis=(1, 3)).ravel()
    level = ((a + b + c + d) * 0.25).reshape(hq, 4, wq, 4).mean(axis=(1, 3)).ravel()
    edges = np.quantile(level, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, bins - 1)
    centres, spreads = [], []
    for k in range(bins):
        inside = which == k
        if np.count_nonzero(inside) >= 10:
            centres.append(float(np.median(level[inside])))
            spreads.append(float(np.quantile(patch_energy[inside], 0.1)) / _CHI2_16_Q10)
    coefficients = _photon_read_curve(np.array(centres), np.array(spreads))
    smooth = gaussian_blur(log_plane, 1.0).astype(np.float64)
    return _log_noise(coefficients, smooth).astype(np.float32)


def _log_noise(coefficients: tuple[float, float], y: np.ndarray) -> np.ndarray:
    """Noise variance of y = log1p(k x) for a linear noise variance alpha x + beta: (A (e^y - 1) + B) e^(-2y)
    with A = alpha k, B = beta k^2 (the derivative of the log is k / (1 + k x) = k e^(-y))."""
    photon, read = coefficients
    return (photon * np.expm1(y) + read) * np.exp(-2.0 * y)


def nnls_2(design: np.ndarray, target: np.ndarray) -> np.ndarray:
    """x >= 0 (2,) minimising |design x - target| for a design (N, 2): what `scipy.optimize.nnls` returns, for
    two unknowns in closed form. The optimum is the unconstrained least-squares solution when that is
    non-negative, else the best of the fits with one unknown held at 0 (or both at 0). Ours because importing
    `scipy.optimize` takes about 0.3 s, on every `mca process`'s critical path (the kernels' warm-up)."""
    a = np.asarray(design, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    candidates = [np.zeros(2)]
    for column in (0, 1):
        norm = float(a[:, column] @ a[:, column])
        if norm > 0:
            single = np.zeros(2)
            single[column] = max(float(a[:, column] @ y) / norm, 0.0)
            candidates.append(single)
    both, _residual, rank, _singular = np.linalg.lstsq(a, y, rcond=None)
    if rank == 2 and np.all(both >= 0):
        return both
    return min(candidates, key=lambda x: float(np.sum((a @ x - y) ** 2)))


def _photon_read_curve(levels: np.ndarray, variances: np.ndarray) -> tuple[float, float]:
    """(A, B) >= 0 of `_log_noise` fitted to the brightness bins' variances in relative terms; texture only
    raises a bin, so bins more than 1.5 times above the curve are dropped and it is fitted again."""
    design = np.stack([np.expm1(levels), np.ones_like(levels)], axis=1) * np.exp(-2.0 * levels)[:, None]
    keep = variances > 0
    coefficients = (0.0, 0.0)
    for _ in range(6):
        if np.count_nonzero(keep) < 2:
            break
        weight = 1.0 / variances[keep]
        solution = nnls_2(design[keep] * weight[:, None], variances[keep] * weight)
        coefficients = (float(solution[0]), float(solution[1]))
        fitted = design @ np.array(coefficients)
        again = (variances > 0) & (variances <= 1.5 * fitted)
        if np.array_equal(again, keep):
            break
        keep = again
    return coefficients


_CHI2_16_Q10 = 0.58201  # the 10th percentile of a chi-square with 16 degrees of freedom, over 16


def _band_noise_response(gradient_sigma_px: float, dog_sigmas_px: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    size = 41
    impulse = np.zeros((size, size, 1), np.float32)
    impulse[size // 2, size // 2, 0] = 1.0
    responses = _band_filters(impulse, gradient_sigma_px, dog_sigmas_px)
    gain = np.empty(len(responses))
    rho = np.empty((len(responses), 2, 3))
    for b, response in enumerate(responses):
        kernel = response[..., 0].astype(np.float64)
        energy = float(np.sum(kernel * kernel))
        gain[b] = energy
        for lag in (1, 2, 3):
            rho[b, 0, lag - 1] = float(np.sum(kernel[:, lag:] * kernel[:, :-lag])) / energy
            rho[b, 1, lag - 1] = float(np.sum(kernel[lag:] * kernel[:-lag])) / energy
    return gain, rho


def window_energy(bands: list[np.ndarray], window_px: int) -> np.ndarray:
    """(H, W) float32 window mean of the squared feature values, summed over bands and channels."""
    total = np.zeros(bands[0].shape[:2], np.float32)
    for band in bands:
        total += np.sum(band * band, axis=2)
    return cv2.boxFilter(total, cv2.CV_32F, (window_px, window_px), borderType=cv2.BORDER_REFLECT)


def texture_energy(bands: list[np.ndarray], window_px: int, energy: np.ndarray | None = None) -> np.ndarray:
    """(H, W) float32 root-mean-square feature amplitude in a window: how much structure there is to align.

    `energy`: the bands' `window_energy` at `window_px` when the caller has it (`cost.CostInput` keeps it)."""
    mean = window_energy(bands, window_px) if energy is None else energy
    return np.sqrt(np.maximum(mean / np.float32(3 * len(bands)), 0.0))


SIGNAL_CHANNELS = ("second", "total")


def signal_weight(
    bands: list[np.ndarray],
    noise: FeatureNoise,
    window_px: int,
    half_snr: float,
    energy: np.ndarray | None = None,
    channels: str = "second",
) -> np.ndarray:
    """(H, W) float32 in [0, 1): how much of each window's structure is signal rather than sensor noise,
    s / (s + `half_snr`), s the window's signal-to-noise ratio E / N - 1: E the feature energy in the window,
    N what `noise` expects of the noise alone there. A window of noise alone (E about N) weighs about 0, one
    whose signal carries `half_snr` times the noise energy 0.5, strong texture about 1.

    `channels` says whose ratio: "second" (the default) that of the channel with the second most signal, each
    channel's energy over its own noise. The colour-alignment cost measures how the channels agree, and a window
    where one channel alone has structure says nothing about the disparity however strong that channel is: a
    dark red sofa with red texture and green and blue noise, a red wall behind red rings. "total": all
    channels' energy over all channels' noise (is there structure in the window at all).

    Unlike `texture_energy`, this does not depend on what the rest of the image holds: on a photograph of
    texture-less surfaces most windows hold noise alone, and their colour-alignment cost says nothing.
    `energy` as for `texture_energy` ("total" only)."""
    if channels not in SIGNAL_CHANNELS:
        raise ValueError(f"signal channels {channels!r}: choose one of {', '.join(SIGNAL_CHANNELS)}")
    gain = np.float32(np.sum(noise.band_gain))
    size = (window_px, window_px)
    if channels == "total":
        if energy is None:
            energy = window_energy(bands, window_px)
        noise_sum = np.asarray(np.sum(noise.variance, axis=0), np.float32) * gain
        noise_energy = cv2.boxFilter(noise_sum, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
        snr = np.maximum(energy / np.maximum(noise_energy, np.float32(1e-30)) - np.float32(1.0), np.float32(0.0))
    else:
        if bands[0].shape[2] != 3:
            raise ValueError(f"signal channels 'second' needs three colour channels, not {bands[0].shape[2]}")
        ratios = []
        for c in range(3):
            squares = np.zeros(bands[0].shape[:2], np.float32)
            for band in bands:
                squares += band[..., c] * band[..., c]
            channel_energy = cv2.boxFilter(squares, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
            channel_noise = cv2.boxFilter(
                np.asarray(noise.variance[c], np.float32) * gain, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT
            )
            ratios.append(channel_energy / np.maximum(channel_noise, np.float32(1e-30)))
        r, g, b = ratios
        # the middle of three: max(min(r, g), min(max(r, g), b))
        second = np.maximum(np.minimum(r, g), np.minimum(np.maximum(r, g), b))
        snr = np.maximum(second - np.float32(1.0), np.float32(0.0))
    return (snr / (snr + np.float32(half_snr))).astype(np.float32)


def display_gamma(planes: np.ndarray) -> np.ndarray:
    """Linear planes -> float32 values in [0, 1] with a 1/2.2 gamma, white at the 99.5th percentile: the image
    colour distances are measured on (segmentation, edge-adaptive penalties)."""
    white = percentile(planes, 99.5) or 1.0
    return np.power(np.clip(planes.astype(np.float32) / np.float32(white), 0.0, 1.0), np.float32(1.0 / 2.2))
