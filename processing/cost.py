"""The colour-alignment cost of an MCA capture: how badly the three filter images disagree at a disparity.

Measure: the colour-line measure of Bando et al. 2008, L = det(C) / (C_rr C_gg C_bb) over a window, C the
3x3 covariance of the (shifted) colour channels. Through the regularised pairwise correlations rho_ab it is
L = 1 - rho_rg^2 - rho_rb^2 - rho_gb^2 + 2 rho_rg rho_rb rho_gb: 0 when the window's colours lie on a line
(the channels are aligned), towards 1 for unrelated channels, invariant to the gain, offset and sign of each
channel, so objects of any colour align. It is evaluated on zero-mean band-pass feature planes
(`processing.features`), several of which are pooled into one covariance per window.

Geometry: for a candidate disparity d of the widest filter pair, channel c is sampled at x + d s_c, where
s_c = `FilterAperture.shift_per_disparity(c)` (px of channel displacement per px of disparity).

Sampling and noise: interpolating averages neighbouring pixels' noise. Bilinear sampling halfway between pixels
halves the variance of white noise, so with sensor noise in every channel the channels correlate best where they
all fall between pixels, and the minimum is pulled towards those disparities (odd red-blue disparities for the
paper's aperture; up to 0.4 px on the rendered real scenes). The signal, smoother than the noise, loses less. With
a noise model (`features.FeatureNoise`: each channel's noise variance per pixel, measured from the capture
itself, and how the feature bands filter it) each channel's window variance gets back what its samples lost
beyond what their signal lost (`_noise_deficit`): the noise keeps the share of the signal it had before sampling,
at every disparity, and the pull is gone. The pipeline does this by default (`DenseParams.noise_model`,
`RefineParams.noise_model`). On the rendered real scenes (tuning part) it lowered bad-0.5 from 27.1 to 24.1 %
and the relative depth error from 9.0 to 8.0 %, and left the simulator's paper scenes (CR2) as they were (median
object error 1.34 -> 1.37 %, in-focus object 1.5 -> 1.6 mm).

The cubic B-spline (4 x 4 taps, `sampling="bspline"`) is the other way to an even noise gain (0.46-0.50 at every
offset); it is an option, not the default: it smooths the signal by an amount that depends on the offset too, and
on the paper scenes it did worse (median object error 2.5 % with the noise model, 3.5 % without; the in-focus
object 2.3 mm off), while on the full-colour renders it did a little better (tuning bad-0.5 21.6 %).

What the noise model does not take out: a window of interpolated noise is smoother, so it holds fewer
independent samples, and the chance correlation between channels of noise alone is larger there. On flat grey with
white noise the bilinear cost, with or without the model, still swings by about 0.01 with a 2 px period in the
red-blue disparity; on a weakly textured, noisy surface that is as much as the signal's own curve (Venus-s2, ISO
1600, the vignetted top left: the summed cost peaked at the truth, 4.5-5.2 px, and was lowest 1 px either side;
the dense map came out 0.85 px short over the whole surface, and exact on the same render without noise).

The band-limited sampler (`sampling="phase"`) moves each channel by a Kaiser-windowed sinc of 16 taps
(`shift_band_limited`), whose gain is flat within 0.1 % up to 0.8 of the Nyquist frequency at every fractional shift:
the bands' noise keeps 97-100 % of its variance and its correlations at every shift, the signal is not smoothed,
and no noise model is needed. For a search over evenly spaced candidates the bands are shifted once per set of
fractional channel shifts (4 for 0.5 px steps with the paper's aperture) and the kernel moves them by whole
pixels only; per-pixel maps (`cost_at`) read bands shifted 1/8 px apart, blended linearly (apertures whose
channels move along one image axis each; others fall back to bilinear), made strip by strip for the rows each strip
reads. On 24 tuning renders, as the dense
search's sampler, the final bad-1 mean went 8.41 -> 7.90 %, the worst 19.6 -> 17.9 %, bad-0.5 23.4 -> 21.8 %,
the relative error 7.6 -> 7.1 %. For the dense search it is an option, not the default: with it the books of the
Bando photograph dog.png come out as two regions (`tests/test_bando.py`), the 2.1D sketch's joins again turning a
small change of the dense map into a region split (docs/evaluation.md, seventeenth stop). The refinement, which
comes after the sketch, uses it by default (`RefineParams.sampling`; docs/evaluation.md, twenty-second stop).

Both kernels are compiled with numba (pure numpy would spend seconds per megapixel here): the box sums are
running sums over a ring buffer of rows, so one candidate costs one pass over the image.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numba as nb
import numpy as np

from mca.processing.camera import CHANNELS, FilterAperture
from mca.processing.features import (
    FeatureNoise,
    feature_bands,
    feature_noise,
    log_compress,
    signal_weight,
    texture_energy,
    window_energy,
)
from mca.processing.jit import FASTMATH


def channel_shifts(aperture: FilterAperture) -> np.ndarray:
    """(3, 2) float64: (dx, dy) image displacement of red, green, blue per pixel of widest-pair disparity."""
    return np.array([aperture.shift_per_disparity(c) for c in CHANNELS], dtype=np.float64)


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _bspline_weights(t: float) -> tuple[float, float, float, float]:
    """Cubic B-spline weights of the taps at floor - 1 .. floor + 2 for a sample at fraction t in [0, 1)."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return s * s * s / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _bspline(img: np.ndarray, y: float, x: float) -> float:
    """img sampled at (y, x) through the cubic B-spline (4 x 4 taps, indices clamped to the image)."""
    h, w = img.shape
    y0 = int(np.floor(y))
    x0 = int(np.floor(x))
    wy0, wy1, wy2, wy3 = _bspline_weights(y - y0)
    wx0, wx1, wx2, wx3 = _bspline_weights(x - x0)
    xa = min(max(x0 - 1, 0), w - 1)
    xb = min(max(x0, 0), w - 1)
    xc = min(max(x0 + 1, 0), w - 1)
    xd = min(max(x0 + 2, 0), w - 1)
    total = 0.0
    for j in range(4):
        row = img[min(max(y0 - 1 + j, 0), h - 1)]
        wy = wy0 if j == 0 else (wy1 if j == 1 else (wy2 if j == 2 else wy3))
        total += wy * (wx0 * row[xa] + wx1 * row[xb] + wx2 * row[xc] + wx3 * row[xd])
    return total


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _sample_row(src: np.ndarray, y: int, sx: float, sy: float, out: np.ndarray, tmp: np.ndarray) -> None:
    """out[x] = src sampled through the cubic B-spline at (x + sx, y + sy), tap indices clamped to the image;
    separable: the four rows are combined into `tmp` first."""
    h, w = src.shape
    fy = y + sy
    y0 = int(np.floor(fy))
    wy0, wy1, wy2, wy3 = _bspline_weights(fy - y0)
    r0 = src[min(max(y0 - 1, 0), h - 1)]
    r1 = src[min(max(y0, 0), h - 1)]
    r2 = src[min(max(y0 + 1, 0), h - 1)]
    r3 = src[min(max(y0 + 2, 0), h - 1)]
    for x in range(w):
        tmp[x] = wy0 * r0[x] + wy1 * r1[x] + wy2 * r2[x] + wy3 * r3[x]
    ix = int(np.floor(sx))
    wx0, wx1, wx2, wx3 = _bspline_weights(sx - ix)
    lo = min(max(1 - ix, 0), w)  # first x whose taps x + ix - 1 .. x + ix + 2 are all inside
    hi = max(min(w - 3 - ix, w - 1), lo - 1)  # last such x
    for x in range(w):
        if x < lo or x > hi:
            out[x] = (
                wx0 * tmp[min(max(x + ix - 1, 0), w - 1)]
                + wx1 * tmp[min(max(x + ix, 0), w - 1)]
                + wx2 * tmp[min(max(x + ix + 1, 0), w - 1)]
                + wx3 * tmp[min(max(x + ix + 2, 0), w - 1)]
            )
    for x in range(lo, hi + 1):
        out[x] = wx0 * tmp[x + ix - 1] + wx1 * tmp[x + ix] + wx2 * tmp[x + ix + 1] + wx3 * tmp[x + ix + 2]


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _sample_row_bilinear(src: np.ndarray, y: int, sx: float, sy: float, out: np.ndarray) -> None:
    """out[x] = src bilinearly sampled at (x + sx, y + sy), coordinates clamped to the image."""
    h, w = src.shape
    fy = min(max(y + sy, 0.0), h - 1.0)
    y0 = int(fy)
    ty = fy - y0
    y1 = min(y0 + 1, h - 1)
    ix = int(np.floor(sx))
    tx = sx - ix
    a = (1.0 - tx) * (1.0 - ty)
    b = tx * (1.0 - ty)
    c = (1.0 - tx) * ty
    d = tx * ty
    lo = min(max(-ix, 0), w)  # first x whose taps x + ix, x + ix + 1 are both inside
    hi = max(min(w - 1 - ix - 1, w - 1), lo - 1)  # last such x
    for x in range(w):
        if x < lo or x > hi:
            xa = min(max(x + ix, 0), w - 1)
            xb = min(max(x + ix + 1, 0), w - 1)
            out[x] = a * src[y0, xa] + b * src[y0, xb] + c * src[y1, xa] + d * src[y1, xb]
    n = hi + 1 - lo
    if n <= 0:
        return
    # The inside on slices indexed from 0, so that the compiler sees no negative index and vectorises the loop.
    inside = out[lo : hi + 1]
    top = src[y0, lo + ix : lo + ix + n + 1]
    bottom = src[y1, lo + ix : lo + ix + n + 1]
    if ty == 0.0:
        for i in range(n):
            inside[i] = (1.0 - tx) * top[i] + tx * top[i + 1]
    else:
        for i in range(n):
            inside[i] = a * top[i] + b * top[i + 1] + c * bottom[i] + d * bottom[i + 1]


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _sample_row_shifted(
    src: np.ndarray, y: int, sx: float, sy: float, out: np.ndarray, tmp: np.ndarray, bspline: bool
) -> None:
    """out[x] = src sampled at (x + sx, y + sy) through the cubic B-spline (`tmp`: its scratch row) or
    bilinearly."""
    if bspline:
        _sample_row(src, y, sx, sy, out, tmp)
    else:
        _sample_row_bilinear(src, y, sx, sy, out)


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _row_taps(
    h: int, w: int, y: int, disparity_row: np.ndarray, sx: float, sy: float, at: np.ndarray, frac: np.ndarray
):
    """The bilinear taps of row y shifted by d(x) (sx, sy), the position clamped to the image: at[0..3, x] = y0,
    x0, y1, x1 and frac[0..1, x] = fx, fy. Made once per channel and row, used for every band."""
    for x in range(w):
        dd = disparity_row[x]
        px = min(max(x + dd * sx, 0.0), w - 1.0)
        py = min(max(y + dd * sy, 0.0), h - 1.0)
        x0 = int(px)
        y0 = int(py)
        at[0, x] = y0
        at[1, x] = x0
        at[2, x] = min(y0 + 1, h - 1)
        at[3, x] = min(x0 + 1, w - 1)
        frac[0, x] = px - x0
        frac[1, x] = py - y0


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _gather_row(src: np.ndarray, at: np.ndarray, frac: np.ndarray, out: np.ndarray) -> None:
    """out[x] = src sampled bilinearly at the taps of `_row_taps`."""
    for x in range(out.shape[0]):
        y0, x0, y1, x1 = at[0, x], at[1, x], at[2, x], at[3, x]
        fx, fy = frac[0, x], frac[1, x]
        top = src[y0, x0] * (1.0 - fx) + src[y0, x1] * fx
        bottom = src[y1, x0] * (1.0 - fx) + src[y1, x1] * fx
        out[x] = top * (1.0 - fy) + bottom * fy


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _sample_row_map_bspline(src: np.ndarray, y: int, disparity_row: np.ndarray, sx: float, sy: float, out: np.ndarray):
    """out[x] = src sampled at (x + d(x) sx, y + d(x) sy) through the cubic B-spline, clamped (bilinear
    per-pixel sampling goes through `_row_taps` and `_gather_row`)."""
    _h, w = src.shape
    for x in range(w):
        dd = disparity_row[x]
        out[x] = _bspline(src, y + dd * sy, x + dd * sx)


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _axis_gain(t: float, rho: np.ndarray, bspline: bool) -> float:
    """Noise variance gain of sampling at fraction t along one axis, for noise correlating rho[lag - 1] at lags
    1..3: the sum over tap pairs of w_i w_j rho(|i - j|)."""
    if bspline:
        w0, w1, w2, w3 = _bspline_weights(t)
        return (
            w0 * w0
            + w1 * w1
            + w2 * w2
            + w3 * w3
            + 2.0 * rho[0] * (w0 * w1 + w1 * w2 + w2 * w3)
            + 2.0 * rho[1] * (w0 * w2 + w1 * w3)
            + 2.0 * rho[2] * (w0 * w3)
        )
    return (1.0 - t) * (1.0 - t) + t * t + 2.0 * rho[0] * t * (1.0 - t)


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _noise_deficit(sx, sy, gain, rho, signal_rho, bspline):
    """How much noise variance (per unit of pixel noise variance, summed over the bands) a sample at offset
    (sx, sy) lacks for its noise to keep the ratio to its signal it had before sampling: interpolation averages
    noise down more than the smoother signal. `signal_rho` is this channel's (B, 2, 3)."""
    tx = sx - np.floor(sx)
    ty = sy - np.floor(sy)
    total = 0.0
    for b in range(gain.shape[0]):
        kept = _axis_gain(tx, signal_rho[b, 0], bspline) * _axis_gain(ty, signal_rho[b, 1], bspline)
        total += gain[b] * (kept - _axis_gain(tx, rho[b, 0], bspline) * _axis_gain(ty, rho[b, 1], bspline))
    return total


_DEFICIT_STEPS = 64  # per-pixel shifts: the deficit is looked up at 1/64 px of fractional offset


@nb.njit(cache=True, fastmath=FASTMATH)
def _deficit_table(gain, rho, signal_rho, bspline):
    """(3, S + 1, S + 1): `_noise_deficit` of each channel at fractional offsets (i / S, j / S)."""
    steps = _DEFICIT_STEPS
    table = np.empty((3, steps + 1, steps + 1))
    for c in range(3):
        for i in range(steps + 1):
            for j in range(steps + 1):
                table[c, i, j] = _noise_deficit(i / steps, j / steps, gain, rho, signal_rho[:, c], bspline)
    return table


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _add_noise_deficit(ring_row, variance, y, sx, sy, d_row, per_pixel, deficit, table):
    """ring_row[x] += the noise variance that channel `variance` (H, W) lacks in its sample for pixel (x, y),
    shifted by (sx, sy) (times d_row[x] when per_pixel): the sampled pixel's variance times its deficit,
    `deficit` for a uniform shift, looked up in `table` (S + 1, S + 1) per pixel."""
    h, w = variance.shape
    if not per_pixel:
        yi = min(max(int(np.floor(y + sy + 0.5)), 0), h - 1)
        shift = int(np.floor(sx + 0.5))
        for x in range(w):
            ring_row[x] += deficit * variance[yi, min(max(x + shift, 0), w - 1)]
    else:
        steps = _DEFICIT_STEPS
        for x in range(w):
            dx = d_row[x] * sx
            dy = d_row[x] * sy
            fx = np.floor(dx)
            fy = np.floor(dy)
            yi = min(max(int(y + fy + (dy - fy >= 0.5)), 0), h - 1)
            xi = min(max(int(x + fx + (dx - fx >= 0.5)), 0), w - 1)
            ring_row[x] += table[int((dx - fx) * steps + 0.5), int((dy - fy) * steps + 0.5)] * variance[yi, xi]


@nb.njit(cache=True, fastmath=FASTMATH, inline="always")
def _products(samples: np.ndarray, products: np.ndarray) -> None:
    """products (6, W) = rr, gg, bb, rg, rb, gb of the sampled row `samples` (B, 3, W), summed over the bands in
    float32: the first band's assigned, each next one's added, one loop each (the compiler vectorises both)."""
    for b in range(samples.shape[0]):
        rr, gg, bb = samples[b, 0], samples[b, 1], samples[b, 2]
        p0, p1, p2, p3, p4, p5 = products[0], products[1], products[2], products[3], products[4], products[5]
        if b == 0:
            for x in range(rr.shape[0]):
                p0[x] = rr[x] * rr[x]
                p1[x] = gg[x] * gg[x]
                p2[x] = bb[x] * bb[x]
                p3[x] = rr[x] * gg[x]
                p4[x] = rr[x] * bb[x]
                p5[x] = gg[x] * bb[x]
        else:
            for x in range(rr.shape[0]):
                p0[x] += rr[x] * rr[x]
                p1[x] += gg[x] * gg[x]
                p2[x] += bb[x] * bb[x]
                p3[x] += rr[x] * gg[x]
                p4[x] += rr[x] * bb[x]
                p5[x] += gg[x] * bb[x]


@nb.njit(cache=True, fastmath=FASTMATH, error_model="numpy")  # numpy's: no zero-division check stops vectorising
def _cost_map(bands, shifts, d, disparity, radius, eps, out, bspline, variance, gain, rho, signal_rho):
    """Colour-line cost of every pixel (window (2 radius + 1)^2, clamped at the borders) with the channels
    sampled at x + d s_c, d the scalar `d` or, when `disparity` has rows, the per-pixel map; into `out` (h, w).

    One pass over the rows: each row's six products (rr, gg, bb, rg, rb, gb, pooled over the bands) go into a
    ring buffer of the window's rows; column sums are updated as rows enter and leave, and a running sum
    ring along each row gives the window sums.

    With a noise model (`variance` (3, H, W) per-pixel noise variance of each channel, `gain` (B,) and `rho`
    (B, 2, 3) of the bands, `features.FeatureNoise`; `variance` empty for none), each channel's variance in
    the window gets back the noise its samples lost by interpolation (`_noise_deficit`), so that the cost's
    noise term is the same at every disparity."""
    nbands, _, h, w = bands.shape
    win = 2 * radius + 1
    ring = np.zeros((win, 6, w), np.float32)
    col = np.zeros((6, w), np.float32)
    box = np.empty((6, w), np.float32)
    samples = np.empty((nbands, 3, w), np.float32)
    tmp = np.empty(w, np.float32)
    taps = np.empty((3, 4, w), np.int64)  # per-pixel bilinear sampling: each channel's taps, shared by the bands
    fractions = np.empty((3, 2, w))
    per_pixel = disparity.shape[0] > 0
    noisy = variance.shape[0] > 0
    uniform = np.zeros(3)
    table = np.zeros((3, 1, 1))
    if noisy:
        if per_pixel:
            table = _deficit_table(gain, rho, signal_rho, bspline)
        else:
            for c in range(3):
                uniform[c] = _noise_deficit(d * shifts[c, 0], d * shifts[c, 1], gain, rho, signal_rho[:, c], bspline)
    for y in range(h + radius):
        slot = y % win
        if y >= win:
            for c in range(6):
                for x in range(w):
                    col[c, x] -= ring[slot, c, x]
        if y < h:
            if per_pixel and not bspline:
                for c in range(3):
                    _row_taps(h, w, y, disparity[y], shifts[c, 0], shifts[c, 1], taps[c], fractions[c])
            for b in range(nbands):
                for c in range(3):
                    if per_pixel and not bspline:
                        _gather_row(bands[b, c], taps[c], fractions[c], samples[b, c])
                    elif per_pixel:
                        _sample_row_map_bspline(bands[b, c], y, disparity[y], shifts[c, 0], shifts[c, 1], samples[b, c])
                    else:
                        _sample_row_shifted(
                            bands[b, c], y, d * shifts[c, 0], d * shifts[c, 1], samples[b, c], tmp, bspline
                        )
            products = ring[slot]
            _products(samples, products)
            if noisy:
                for c in range(3):
                    row = disparity[y] if per_pixel else tmp  # tmp: a row of the right type, unused
                    _add_noise_deficit(
                        ring[slot, c],
                        variance[c],
                        y,
                        shifts[c, 0] if per_pixel else d * shifts[c, 0],
                        shifts[c, 1] if per_pixel else d * shifts[c, 1],
                        row,
                        per_pixel,
                        uniform[c],
                        table[c],
                    )
            for c in range(6):
                for x in range(w):
                    col[c, x] += ring[slot, c, x]
        else:
            for c in range(6):
                for x in range(w):
                    ring[slot, c, x] = 0.0
        yc = y - radius
        if yc < 0:
            continue
        rows = min(yc + radius, h - 1) - max(yc - radius, 0) + 1
        # the six running sums side by side: six independent chains of additions, not one after another
        a0 = a1 = a2 = a3 = a4 = a5 = np.float32(0.0)
        for x in range(min(radius, w)):
            a0 += col[0, x]
            a1 += col[1, x]
            a2 += col[2, x]
            a3 += col[3, x]
            a4 += col[4, x]
            a5 += col[5, x]
        for x in range(w):
            if x + radius < w:
                xr = x + radius
                a0 += col[0, xr]
                a1 += col[1, xr]
                a2 += col[2, xr]
                a3 += col[3, xr]
                a4 += col[4, xr]
                a5 += col[5, xr]
            if x - radius - 1 >= 0:
                xl = x - radius - 1
                a0 -= col[0, xl]
                a1 -= col[1, xl]
                a2 -= col[2, xl]
                a3 -= col[3, xl]
                a4 -= col[4, xl]
                a5 -= col[5, xl]
            box[0, x] = a0
            box[1, x] = a1
            box[2, x] = a2
            box[3, x] = a3
            box[4, x] = a4
            box[5, x] = a5
        for x in range(w):
            cols = min(x + radius, w - 1) - max(x - radius, 0) + 1
            e = eps * rows * cols * nbands
            irr = 1.0 / np.sqrt(box[0, x] + e)
            igg = 1.0 / np.sqrt(box[1, x] + e)
            ibb = 1.0 / np.sqrt(box[2, x] + e)
            rg = box[3, x] * irr * igg
            rb = box[4, x] * irr * ibb
            gb = box[5, x] * igg * ibb
            value = 1.0 - rg * rg - rb * rb - gb * gb + 2.0 * rg * rb * gb
            out[yc, x] = min(max(value, 0.0), 1.0)


@nb.njit(cache=True, parallel=True)
def _maps(
    bands: np.ndarray,
    shifts: np.ndarray,
    candidates: np.ndarray,
    disparities: np.ndarray,
    radius: int,
    eps: float,
    bspline: bool,
    variance: np.ndarray,
    gain: np.ndarray,
    rho: np.ndarray,
    signal_rho: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[k] = the cost map at the scalar candidates[k], or at the per-pixel disparities[k] when `candidates`
    is empty; one map per thread at a time."""
    w = bands.shape[3]
    per_pixel = candidates.shape[0] == 0
    none = np.zeros((0, w), np.float32)
    for k in nb.prange(out.shape[0]):
        if per_pixel:
            _cost_map(bands, shifts, 0.0, disparities[k], radius, eps, out[k], bspline, variance, gain, rho, signal_rho)
        else:
            _cost_map(bands, shifts, candidates[k], none, radius, eps, out[k], bspline, variance, gain, rho, signal_rho)


def stack_bands(bands: list[np.ndarray]) -> np.ndarray:
    """Feature planes [(H, W, 3), ...] -> the (B, 3, H, W) float32 layout the kernels take."""
    return np.ascontiguousarray(np.stack([np.moveaxis(b, -1, 0) for b in bands]), dtype=np.float32)


@dataclass(frozen=True)
class CostInput:
    """What the cost reads of one set of planes: their feature bands, stacked for the kernels, with their noise
    model. Made once per capture (`cost_input`) and shared by every stage that reads the colour-alignment cost
    of those planes (the dense search, the refinement, the texture evidence)."""

    bands: list[np.ndarray]  # [(H, W, 3) float32, ...] as `features.feature_bands` makes them (views of `stacked`)
    stacked: np.ndarray  # (B, 3, H, W) float32, `stack_bands(bands)`
    noise: FeatureNoise | None  # `features.feature_noise(planes, bands)`, None when no stage asks for it
    # what the stages derive from the bands and ask for more than once, made on first use
    _made: dict[tuple, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)

    def window_energy(self, window_px: int) -> np.ndarray:
        """`features.window_energy` of the bands (shared by every caller: do not write to it)."""
        return self._once(("energy", window_px), lambda: window_energy(self.bands, window_px))

    def texture_energy(self, window_px: int) -> np.ndarray:
        """`features.texture_energy` of the bands (shared: do not write to it)."""
        return self._once(
            ("texture", window_px), lambda: texture_energy(self.bands, window_px, self.window_energy(window_px))
        )

    def signal_weight(self, window_px: int, half_snr: float, channels: str = "second") -> np.ndarray:
        """`features.signal_weight` of the bands with their noise model (shared: do not write to it). The dense
        search and the refinement ask for the same window's."""
        if self.noise is None:
            raise ValueError("these cost inputs carry no noise model: make them with cost_input(..., noise_model=True)")
        noise = self.noise
        return self._once(
            ("signal", window_px, half_snr, channels),
            lambda: signal_weight(
                self.bands,
                noise,
                window_px,
                half_snr,
                self.window_energy(window_px) if channels == "total" else None,
                channels,
            ),
        )

    def _once(self, key: tuple, make: Callable[[], np.ndarray]) -> np.ndarray:
        if key not in self._made:
            self._made[key] = make()
        return self._made[key]


def cost_input(planes: np.ndarray, noise_model: bool = True) -> CostInput:
    """The `CostInput` of (H, W, 3) linear planes; the noise model is measured only when `noise_model`. Its
    `bands` are views of its stack (one copy of the bands, not two: 47 MB less at 20 MP, held through the dense
    search's peak)."""
    log = log_compress(planes)
    stacked = stack_bands(feature_bands(planes, log=log))
    bands = [np.moveaxis(stacked[b], 0, -1) for b in range(stacked.shape[0])]
    return CostInput(bands, stacked, feature_noise(planes, bands, log=log) if noise_model else None)


SAMPLINGS = ("bspline", "bilinear", "phase")
_PHASE_GROUPS_MAX = 16  # "phase" sampling: at most this many distinct sets of fractional channel shifts


_SHIFT_HALF_TAPS = 8  # the band-limited shift: a Kaiser-windowed sinc of 2 x 8 taps
_SHIFT_BETA = 5.0  # its window: gain flat within 0.1 % up to 0.8 of the Nyquist frequency at every fraction


def shift_taps(fraction: float) -> np.ndarray:
    """The 2 x `_SHIFT_HALF_TAPS` taps (at offsets -7..8) that sample a line at x + `fraction`, 0 <= fraction < 1:
    a Kaiser-windowed sinc, its sum 1. Read-only: the same array is handed to every caller of one fraction (the
    per-pixel sampler asks for the same eight fractions strip after strip; making them took 0.2 s of a 20 MP
    capture's refinement)."""
    return _shift_taps(float(fraction))


@functools.lru_cache(maxsize=64)
def _shift_taps(fraction: float) -> np.ndarray:
    half = _SHIFT_HALF_TAPS
    x = np.arange(-half + 1, half + 1) - fraction
    window = np.i0(_SHIFT_BETA * np.sqrt(np.clip(1.0 - (x / half) ** 2, 0.0, 1.0))) / np.i0(_SHIFT_BETA)
    taps = np.sinc(x) * window
    taps = (taps / taps.sum()).astype(np.float32)
    taps.flags.writeable = False
    return taps


def _filter_along(planes: np.ndarray, taps: np.ndarray, axis: int, out: np.ndarray) -> None:
    """Each (H, W) plane of `planes` (N, H, W) float32 convolved with the shift `taps` along `axis` (0: x, 1: y),
    mirrored at the borders, into `out`.

    `cv2.filter2D` with the taps as a row or a column, not `cv2.sepFilter2D` with a one-tap other axis, which
    runs a second, one-tap pass: `filter2D` takes less than half the time along y and a quarter less along x,
    with the bits 4.x's separable filter gave. Along y, OpenCV 5.0's separable filter sums in another order than
    4.x's; on the refinement's strips of 1368- and 2736-px-wide images `filter2D` gives the same bits under 4.10
    and 5.0 (measured; other shapes, narrow ones especially, can differ; docs/evaluation.md, twenty-fourth stop)."""
    kernel = taps.reshape(1, -1) if axis == 0 else taps.reshape(-1, 1)
    anchor = (_SHIFT_HALF_TAPS - 1, 0) if axis == 0 else (0, _SHIFT_HALF_TAPS - 1)
    for i in range(planes.shape[0]):
        cv2.filter2D(planes[i], -1, kernel, dst=out[i], anchor=anchor, borderType=cv2.BORDER_REFLECT)


def shift_band_limited(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """`image` (..., H, W) sampled at (x + dx, y + dy): the fractional part by a band-limited (windowed sinc)
    filter along each axis, mirrored at the borders; the whole pixels moved with the border repeated. Unlike
    bilinear sampling, it keeps the power spectrum of the image up to 0.8 of the Nyquist frequency: the noise of
    a band-pass plane keeps its variance and its correlation at every fractional shift."""
    out = np.ascontiguousarray(image, np.float32)
    lead = out.shape[:-2]
    flat = out.reshape((-1,) + out.shape[-2:])
    for axis, shift in ((-1, dx), (-2, dy)):
        whole = int(np.floor(shift))
        frac = shift - whole
        if frac > 1e-9:
            moved = np.empty_like(flat)
            _filter_along(flat, shift_taps(frac), 0 if axis == -1 else 1, moved)
            flat = moved
        if whole:
            n = flat.shape[axis]
            flat = np.take(flat, np.clip(np.arange(n) + whole, 0, n - 1), axis=axis)
    return np.ascontiguousarray(flat.reshape(lead + flat.shape[-2:]), np.float32)


def _phase_groups(shifts: np.ndarray, candidates: np.ndarray) -> list[tuple[np.ndarray, float, np.ndarray, float]]:
    """Candidates grouped so that within a group every channel's shifts differ by whole pixels: a list of
    (indices, base, multiples, spacing) with candidates[indices] = base + spacing * multiples, the base within
    one spacing above zero (its channels' whole-pixel shifts are then 0 or -1: near the borders the clamping
    differs from the other samplers' by a pixel or two). Candidates that do not fall into a few such groups
    (uneven, or a step whose shifts repeat only after many steps) are a group each."""
    alone = [(np.array([k]), float(d), np.zeros(1), 1.0) for k, d in enumerate(candidates)]
    if len(candidates) < 2:
        return alone
    step = float(candidates[1] - candidates[0])
    if step <= 0 or not np.allclose(np.diff(candidates), step, atol=1e-9):
        return alone
    for period in range(1, _PHASE_GROUPS_MAX + 1):
        moved = period * step * shifts
        if np.allclose(moved, np.round(moved), atol=1e-6):
            break
    else:
        return alone
    groups = []
    for first in range(min(period, len(candidates))):
        indices = np.arange(first, len(candidates), period)
        lead = float(candidates[first])
        on_grid = abs(lead / step - round(lead / step)) < 1e-6
        # on the grid k * step, the base is the group's member in [0, period * step), whatever slice of the
        # candidates came in: chunks of one search share their shifted bands
        base = step * (round(lead / step) % period) if on_grid else lead
        multiples = np.round((candidates[indices] - base) / (period * step))
        groups.append((indices, base, multiples, period * step))
    return groups


def _noise_arrays(
    noise: FeatureNoise | None, bands: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if noise is None:
        return np.zeros((0, 1, 1), np.float32), np.zeros(1), np.zeros((1, 2, 3)), np.zeros((1, 3, 2, 3))
    if noise.variance.shape != (3,) + bands.shape[2:] or noise.band_gain.shape[0] != bands.shape[0]:
        raise ValueError(
            f"the noise model ({noise.variance.shape}, {noise.band_gain.shape[0]} bands) is not of these bands "
            f"({bands.shape})"
        )
    return (
        np.ascontiguousarray(noise.variance, np.float32),
        np.asarray(noise.band_gain, np.float64),
        np.ascontiguousarray(noise.band_rho, np.float64),
        np.ascontiguousarray(noise.signal_rho, np.float64),
    )


def _check_sampling(sampling: str) -> bool:
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, not {sampling!r}")
    return sampling == "bspline"  # "phase" where its own path does not apply (channels moving off the axes): bilinear


def cost_volume(
    bands: np.ndarray,
    aperture: FilterAperture,
    candidates_px: np.ndarray,
    window_px: int,
    noise_floor: float,
    sampling: str = "bilinear",
    noise: FeatureNoise | None = None,
    out: np.ndarray | None = None,
    shifted: dict | None = None,
) -> np.ndarray:
    """(D, H, W) float32 colour-line cost of every pixel at every candidate disparity (px of these planes).

    `bands` (B, 3, H, W) from `stack_bands`; `noise_floor` is the band-pass amplitude treated as flat (it
    regularises the correlations of windows with nothing to align); `sampling` "bspline", "bilinear" or "phase"
    (see the module docstring for which to use when); `noise` (`features.feature_noise` of the planes the bands
    are of) takes out the noise bias of sampling (module docstring); the "phase" sampler keeps the noise's
    variance at every shift, has no such bias and ignores it. `out`: a (D, H, W) float32 array to fill (a buffer
    used again), else a new one is made. `shifted`: "phase" sampling only, a dict the caller keeps across the
    chunks of one search over the same bands, which then shifts them once (`_phase_volume`)."""
    candidates = np.asarray(candidates_px, np.float64)
    shape = (len(candidates),) + bands.shape[2:]
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32:
        raise ValueError(f"out must be float32 {shape}, not {out.dtype} {out.shape}")
    if len(candidates) and sampling == "phase":
        shifts = channel_shifts(aperture)
        _phase_volume(bands, shifts, _phase_groups(shifts, candidates), window_px, noise_floor, out, shifted)
        return out
    if len(candidates):
        _maps(
            bands,
            channel_shifts(aperture),
            candidates,
            np.zeros((1, 1, 1), np.float32),
            int(window_px) // 2,
            float(noise_floor) ** 2,
            _check_sampling(sampling),
            *_noise_arrays(noise, bands),
            out,
        )
    return out


def _phase_volume(bands, shifts, groups, window_px, noise_floor, out, shifted=None):
    """`cost_volume` with every channel shifted band-limited (`shift_band_limited`) to each group's base disparity;
    the kernel then only moves whole pixels, where sampling changes neither signal nor noise. `shifted`: a dict
    that keeps the shifted bands by base for the next call on the same bands (a search made in chunks)."""
    empty = _noise_arrays(None, bands)
    for indices, base, multiples, spacing in groups:
        whole = np.round(spacing * shifts)  # each channel's whole-pixel move per multiple
        key = round(base, 9)
        moved = shifted.get(key) if shifted is not None else None
        if moved is None:
            moved = np.empty_like(bands)
            for c in range(3):
                moved[:, c] = shift_band_limited(bands[:, c], base * shifts[c, 0], base * shifts[c, 1])
            if shifted is not None:
                shifted[key] = moved
        _maps(
            moved,
            whole,
            multiples,
            np.zeros((1, 1, 1), np.float32),
            int(window_px) // 2,
            float(noise_floor) ** 2,
            False,
            *empty,
            _view_rows(out, indices),
        )


_PHASES = 8  # per-pixel "phase" sampling: band-limited shifts 1/8 px apart, linear between the two nearest


def _axis_aligned(shifts: np.ndarray) -> bool:
    return bool(np.all(np.count_nonzero(np.abs(shifts) > 1e-12, axis=1) <= 1))


@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _gather_phased(phases, axis, shift, disparity, out, first_row, height, stack_row):
    """out[b, r, x] = the channel's bands at image pixel (x, y = first_row + r) + disparity[r, x] * shift along
    `axis` (0: x, 1: y), from `phases` (P + 1, B, rows, W): its bands shifted by k / P px (`shift_band_limited`),
    k = 0..P, whose row 0 is image row `stack_row`; the whole pixels clamped to the image (`height` rows)."""
    steps = phases.shape[0] - 1
    nbands, rows, w = out.shape
    for r in nb.prange(rows):
        row = np.int64(r)  # a prange index may be unsigned: kept signed so that the clamps stay integers
        y = first_row + row
        for x in range(w):
            pos = disparity[row, x] * shift
            whole = np.floor(pos)
            q = (pos - whole) * steps
            i = min(int(q), steps - 1)
            t = q - i
            yy = int(y)
            xx = int(x)
            if axis == 0:
                xx = min(max(xx + int(whole), 0), w - 1)
            else:
                yy = min(max(yy + int(whole), 0), height - 1)
            yy -= stack_row
            for b in range(nbands):
                out[b, row, x] = (1.0 - t) * phases[i, b, yy, xx] + t * phases[i + 1, b, yy, xx]


def _shift_into(planes: np.ndarray, amount: float, axis: int, out: np.ndarray) -> None:
    """`shift_band_limited(planes, ...)` by `amount` (0 <= amount <= 1) along `axis` (0: x, 1: y), written into
    `out` (same shape) without the temporaries: the same bits, and at 20 MP no 15 MB copy to allocate and touch
    per phase."""
    if amount <= 1e-9:
        out[...] = planes
    elif amount >= 1.0 - 1e-9:  # a whole pixel, the border repeated
        if axis == 0:
            out[..., :-1] = planes[..., 1:]
            out[..., -1] = planes[..., -1]
        else:
            out[..., :-1, :] = planes[..., 1:, :]
            out[..., -1, :] = planes[..., -1, :]
    else:
        _filter_along(np.ascontiguousarray(planes, np.float32), shift_taps(amount), axis, out)


# The per-pixel "phase" sampler works in strips of this many rows: each strip's shifted bands (`_PHASES` + 1 copies of
# every band of every channel) are made in the same buffers, read, and replaced by the next strip's. Made whole for
# the image, they were about 400 MB at 20 MP: the refinement's peak and the process's, made twice as costly again by
# the first write to so much fresh memory (docs/evaluation.md, twenty-third stop).
_PHASE_STRIP_ROWS = 96


def _phase_rows(h: int, axis: int, rows: tuple[int, int]) -> tuple[int, int]:
    """The image rows [lo, hi) that `_phase_strip` shifts for the rows `rows`: along y `_SHIFT_HALF_TAPS` + 1 rows
    more on either side (within the image), which the shifts of the rows in `rows` read."""
    if axis == 0:
        return rows
    return max(0, rows[0] - _SHIFT_HALF_TAPS - 1), min(h, rows[1] + _SHIFT_HALF_TAPS + 1)


def _phase_strip(bands: np.ndarray, c: int, axis: int, span: tuple[int, int], out: np.ndarray) -> np.ndarray:
    """Channel c's bands shifted by k / `_PHASES` px along `axis`, k = 0..`_PHASES`, on the image rows
    span = [lo, hi) (`_phase_rows` of the rows a strip samples), written into the front of `out` and returned as a
    view: (P + 1, B, hi - lo, W), whose row 0 is image row lo. The bits of the whole image's shifts
    (`_shift_into`) on the sampled rows: along y the rows beyond them are there for the shifts to read (reflected
    only at the image's own borders), and are themselves wrong at the span's ends; nothing reads them there."""
    lo, hi = span
    source = np.ascontiguousarray(bands[:, c, lo:hi])
    stack = out[:, :, : hi - lo]
    for k in range(_PHASES + 1):
        _shift_into(source, k / _PHASES, axis, stack[k])
    return stack


def _sample_rows(maps: np.ndarray, amount: float, rows: tuple[int, int], h: int) -> tuple[int, int]:
    """The image rows [first, last) that a channel moving `amount` px along y per px of disparity samples for the
    map rows `rows` (whole pixels clamped to the image, as `_gather_phased` clamps them)."""
    first, last = rows
    whole = np.floor(maps[:, first:last] * np.float32(amount))  # finite: `cost_at` costs the rest at 0
    low, high = int(whole.min()), int(whole.max())
    return min(max(first + low, 0), h - 1), min(max(last - 1 + high, 0), h - 1) + 1


def _phase_maps(bands, shifts, maps, window_px, noise_floor, out):
    """`cost_at` with the channels moved by band-limited shifts (`shift_band_limited`, 1/`_PHASES` px apart) rather
    than bilinear sampling; for apertures whose channels each move along one image axis. Strip by strip
    (`_PHASE_STRIP_ROWS`); a strip's windows read `window_px` // 2 rows on either side of it, sampled with it."""
    nbands, _, h, w = bands.shape
    radius = int(window_px) // 2
    count = maps.shape[0]
    batch = max(1, min(nb.get_num_threads(), count))
    noise = _noise_arrays(None, bands)
    eps = float(noise_floor) ** 2
    moving: list[tuple[int, float] | None] = []  # per channel: the axis it moves along, its shift per px of disparity
    for c in range(3):
        axis = 0 if abs(shifts[c, 0]) > 0 else 1
        amount = float(shifts[c, axis])
        moving.append(None if amount == 0.0 else (axis, amount))
    buffers: list[np.ndarray | None] = [None, None, None]  # each channel's shifted bands, used again strip by strip
    window_rows = min(h, _PHASE_STRIP_ROWS + 2 * radius)
    sampled = np.empty((batch, nbands, 3, window_rows, w), np.float32)
    costs = np.empty((batch, window_rows, w), np.float32)
    for top in range(0, h, _PHASE_STRIP_ROWS):
        bottom = min(h, top + _PHASE_STRIP_ROWS)
        first, last = max(0, top - radius), min(h, bottom + radius)  # the rows the strip's windows read
        stacks: list[tuple[np.ndarray, int, float, int] | None] = [None, None, None]
        for c in range(3):  # one channel after another: OpenCV's filters take both cores already
            motion = moving[c]
            if motion is None:
                continue
            axis, amount = motion
            rows = _sample_rows(maps, amount, (first, last), h) if axis == 1 else (first, last)
            lo, hi = _phase_rows(h, axis, rows)
            buffer = buffers[c]
            if buffer is None or buffer.shape[2] < hi - lo:
                buffer = buffers[c] = np.empty((_PHASES + 1, nbands, hi - lo + 32, w), np.float32)
            stacks[c] = (_phase_strip(bands, c, axis, (lo, hi), buffer), axis, amount, lo)
        for start in range(0, count, batch):
            stop = min(start + batch, count)
            for k in range(start, stop):
                for c in range(3):
                    strip = sampled[k - start, :, c, : last - first]
                    stack = stacks[c]
                    if stack is None:
                        strip[...] = bands[:, c, first:last]
                    else:
                        moved, along, by, stack_row = stack
                        _gather_phased(moved, along, by, maps[k, first:last], strip, first, h, stack_row)
            _presampled_maps(sampled, stop - start, last - first, radius, eps, *noise, costs)
            out[start:stop, top:bottom] = costs[: stop - start, top - first : bottom - first]


@nb.njit(cache=True, parallel=True)
def _presampled_maps(sampled, count, rows, radius, eps, variance, gain, rho, signal_rho, out) -> None:
    """out[k, :rows] = the cost map of the bands sampled[k, :, :, :rows] ((B, 3, rows, W)) as they stand (already
    moved; the noise arrays `_noise_arrays(None, ...)`'s: no noise model), k < `count`; one map per thread. The
    buffers come whole, whatever part of them a strip fills, so that the kernel is compiled for one layout."""
    zeros = np.zeros((3, 2))
    none = np.zeros((0, sampled.shape[4]), np.float32)
    for k in nb.prange(count):
        _cost_map(
            sampled[k, :, :, :rows],
            zeros,
            0.0,
            none,
            radius,
            eps,
            out[k, :rows],
            False,
            variance,
            gain,
            rho,
            signal_rho,
        )


def _view_rows(out, indices):
    """The rows `indices` (evenly spaced) of `out` as a view, for the kernel to write into."""
    return out[indices[0] : indices[-1] + 1 : (indices[1] - indices[0]) if len(indices) > 1 else 1]


def cost_at(
    bands: np.ndarray,
    aperture: FilterAperture,
    disparity_maps_px: np.ndarray,
    window_px: int,
    noise_floor: float,
    sampling: str = "bilinear",
    noise: FeatureNoise | None = None,
) -> np.ndarray:
    """Colour-line cost of every pixel at per-pixel disparities: (K, H, W) maps in, (K, H, W) costs out.

    `sampling` and `noise` as for `cost_volume` (see the module docstring); "phase" works strip by strip
    (`_phase_maps`). A disparity that is not finite is costed at 0: the kernels assume finite values (`jit.FASTMATH`),
    and a NaN would have become an index anywhere in memory."""
    bspline = _check_sampling(sampling)
    maps = np.ascontiguousarray(disparity_maps_px, dtype=np.float32)
    if maps.ndim == 2:
        maps = maps[None]
    finite = np.isfinite(maps)
    if not finite.all():
        maps = np.where(finite, maps, np.float32(0.0))
    out = np.empty(maps.shape, np.float32)
    shifts = channel_shifts(aperture)
    if sampling == "phase" and _axis_aligned(shifts):
        _phase_maps(bands, shifts, maps, window_px, noise_floor, out)
        return out
    _maps(
        bands,
        shifts,
        np.zeros(0),
        maps,
        int(window_px) // 2,
        float(noise_floor) ** 2,
        bspline,
        *_noise_arrays(noise, bands),
        out,
    )
    return out
