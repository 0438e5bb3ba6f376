"""MCA captures of real photographs with known depth: an sRGB image and its disparity map in, the capture and truth out.

An RGB-D scene (e.g. a Middlebury stereo view with its ground-truth disparity) is rendered
through the MCA optics with the same image formation as `devices.sim.render` (thin lens,
eqs. 6 and 11; see that module's docstring): a point at distance Z is imaged by filter c
shifted by `SimulationOptics.channel_shift_px(c, Z)` and spread over the filter's disk of
`SimulationOptics.blur_diameter_px(Z)`, with the in-focus sharpness blur on top, shift and
blur applied exactly in the Fourier domain (`simulate._Spectra`).

Depth: the stereo disparity d (affine in 1/Z) is mapped affinely onto inverse distance,
1/Z = 1/far + (d - d_min) / (d_max - d_min) (1/near - 1/far), so planes stay planes. Pixels of
unknown disparity are filled from the farther neighbouring surface along their row (they are
mostly background occluded in the other stereo view) and rendered, but marked unknown in
the truth.

Occlusion: the scene is cut into thin slices of red-blue disparity (at most 0.25 px apart,
tent weights, so disparity varies continuously). Slices are processed front to back; each
slice's colour and coverage are shifted and blurred per filter, and its colour is added
where the coverage of the slices in front of it leaves light through: transmittance
1 - min(1, sum of the coverage of every slice at least `occlusion_gap_px` nearer). Within
that gap slices add (one continuous surface does not hide itself, which "over" between
tent slices would do), across it the nearer surface hides the farther one. Where a nearer
surface's channels move off the farther one (disocclusion) the hidden background is
needed: behind the near side of every depth edge a second layer carries the farther
surface, mirrored across the edge (colour) and linearly extrapolated (disparity), for
the width the largest channel shift plus blur can uncover. Each slice is processed tile by
tile over the tiles where it has support, so the work follows the image area, not the
number of slices times the frame.

Sensor: linear filter images -> optional vignetting (cos^4 of the chief-ray angle, or a
radial polynomial) -> optional crosstalk (sensor channel <- filter) -> exposure -> photon
and read noise and 14-bit quantisation (`simulate.SensorModel`, `simulate._expose`), either
at every pixel for all three channels (an RGB capture, read back as a 16-bit linear TIFF)
or at the sites of an RGGB mosaic (`simulate.BAYER_SITES`). The filter images are rendered
at full sensor resolution, so each Bayer site samples its own position exactly.

Pure: arrays and parameters in, arrays and numbers out.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.fft
import scipy.ndimage

from mca.devices.sim.render import BAYER_SITES, SensorModel, SimulationOptics, _expose, _Spectra
from mca.processing.camera import CHANNELS, CameraProfile
from mca.processing.colour import srgb_decode

SLICE_STEP_PX = 0.25  # largest red-blue disparity step between slices (px of the render)
OCCLUSION_GAP_PX = 1.0  # a slice hides another only when it is at least this much nearer (red-blue px)


# --- depth from stereo disparity --------------------------------------------------------------------------------


def fill_from_farther_neighbour(disparity: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unknown stereo disparities filled from the farther (smaller-disparity) of the nearest valid pixels to
    their left and right on the same row; rows with no valid pixel take the farthest valid value."""
    d = np.asarray(disparity, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if valid.all():
        return d.copy()
    if not valid.any():
        raise ValueError("the disparity map has no valid pixel")
    h, w = d.shape
    columns = np.broadcast_to(np.arange(w), (h, w))
    left_index = np.maximum.accumulate(np.where(valid, columns, -1), axis=1)
    right_index = np.minimum.accumulate(np.where(valid, columns, w)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(h)[:, None]
    left = np.where(left_index >= 0, d[rows, np.clip(left_index, 0, w - 1)], np.inf)
    right = np.where(right_index < w, d[rows, np.clip(right_index, 0, w - 1)], np.inf)
    fill = np.minimum(left, right)
    fill[~np.isfinite(fill)] = float(d[valid].min())
    return np.where(valid, d, fill)


@dataclass(frozen=True)
class DepthRange:
    """The distances (mm from the lens) the nearest and farthest valid stereo disparity are mapped to."""

    near_mm: float
    far_mm: float

    def __post_init__(self) -> None:
        if not (0 < self.near_mm < self.far_mm):
            raise ValueError(f"need 0 < near < far, got near {self.near_mm} mm, far {self.far_mm} mm")

    def distance_mm(self, disparity: np.ndarray, d_min: float, d_max: float) -> np.ndarray:
        """1/Z = 1/far + (d - d_min)/(d_max - d_min) (1/near - 1/far): stereo disparity is affine in 1/Z."""
        t = (np.asarray(disparity, np.float64) - d_min) / max(d_max - d_min, 1e-12)
        inverse = 1.0 / self.far_mm + t * (1.0 / self.near_mm - 1.0 / self.far_mm)
        return 1.0 / inverse


# --- the renderer -----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderParams:
    """Numerical knobs of the slice renderer (defaults keep it within 0.25 px of disparity everywhere)."""

    slice_step_px: float = SLICE_STEP_PX
    occlusion_gap_px: float = OCCLUSION_GAP_PX
    tile_px: int | None = None  # None: from the reach of shift + blur (4x it, 96..384)


def _reach_px(optics: SimulationOptics, disparity_px: np.ndarray) -> float:
    """How far (px) a pixel's light can land from it: the largest channel shift plus blur and sharpness radius."""
    extreme = float(np.max(np.abs(disparity_px)))
    shift = max(math.hypot(*optics.aperture.shift_per_disparity(c)) for c in CHANNELS) * extreme
    blur = optics.aperture.filter_diameter_mm / optics.aperture.baseline_mm * extreme / 2.0
    sharp = 3.0 * max(optics.sharpness_sigma_px(c) for c in CHANNELS)
    return shift + blur + sharp + 2.0


def hidden_layer(
    radiance: np.ndarray, disparity_px: np.ndarray, optics: SimulationOptics, gap_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The farther surface continued behind the near side of every depth edge, where a channel shift can uncover it.

    A depth edge is a pair of 8-neighbours whose red-blue disparities differ by more than `gap_px`.
    Each pixel on the near side within reach of such an edge gets the colour of the far surface
    mirrored across its nearest far-side edge pixel, and that surface's disparity linearly
    extrapolated (never nearer than the edge pixel). Returns (mask, radiance (H, W, 3), disparity)
    of the hidden layer; outside the mask the values are meaningless.
    """
    d = disparity_px.astype(np.float32)
    nearest_neighbour = cv2.erode(d, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    far_edge = (d - nearest_neighbour) > gap_px  # this pixel has a neighbour nearer by more than the gap
    h, w = d.shape
    empty = np.zeros((h, w), bool)
    if not far_edge.any():
        return empty, np.zeros_like(radiance), d.copy()
    reach = int(math.ceil(_reach_px(optics, d)))
    distance, (iy, ix) = scipy.ndimage.distance_transform_edt(~far_edge, return_indices=True)
    edge_d = d[iy, ix]
    mask = (distance <= reach) & (d < edge_d - gap_px)
    if not mask.any():
        return empty, np.zeros_like(radiance), d.copy()
    ys, xs = np.nonzero(mask)
    ey, ex = iy[ys, xs], ix[ys, xs]
    my, mx = np.clip(2 * ey - ys, 0, h - 1), np.clip(2 * ex - xs, 0, w - 1)  # mirrored across the edge pixel
    same_surface = np.abs(d[my, mx] - d[ey, ex]) <= gap_px
    sy, sx = np.where(same_surface, my, ey), np.where(same_surface, mx, ex)
    colour = np.zeros_like(radiance)
    colour[ys, xs] = radiance[sy, sx]
    extrapolated = np.maximum(2.0 * d[ey, ex] - d[sy, sx], d[ey, ex])
    hidden_d = d.copy()
    hidden_d[ys, xs] = extrapolated
    return mask, colour, hidden_d


def render_filter_images(
    radiance: np.ndarray, distance_mm: np.ndarray, optics: SimulationOptics, params: RenderParams = RenderParams()
) -> np.ndarray:
    """The image through each filter (H, W, 3: red, green, blue) of a scene given per pixel by its linear
    radiance in the three bands and its distance from the lens (finite everywhere), at the render's full
    resolution, each channel at every pixel (the sensor samples it afterwards).

    `radiance` and `distance_mm` are the chief-ray (pinhole) view: pixel (x, y) of the render sees the
    surface point of `radiance[y, x]`. Occlusion, disocclusion and the per-filter shift and defocus disk
    follow the module docstring.
    """
    radiance = np.asarray(radiance, np.float32)
    h, w = distance_mm.shape
    if radiance.shape != (h, w, 3):
        raise ValueError(f"radiance must be (H, W, 3) matching the distance map {h}x{w}, got {radiance.shape}")
    if (h, w) != (optics.height_px, optics.width_px):
        raise ValueError(f"the optics are for {optics.width_px}x{optics.height_px}, the scene is {w}x{h}")
    if not np.all(np.isfinite(distance_mm)) or np.any(distance_mm <= optics.focal_length_mm):
        raise ValueError("every distance must be finite and beyond the focal length")
    disparity = np.asarray(optics.mca.disparity_px_at_distance(distance_mm.astype(np.float64)), np.float32)
    hidden_mask, hidden_colour, hidden_d = hidden_layer(radiance, disparity, optics, params.occlusion_gap_px)

    reach = int(math.ceil(_reach_px(optics, np.concatenate([disparity.ravel(), hidden_d[hidden_mask]]))))
    margin = reach + 2
    tile = params.tile_px or int(min(384, max(96, 4 * margin)))
    pad = margin  # frame content beyond the border, mirrored, so that shifts bring plausible light in
    rows = int(math.ceil((h + 2 * pad) / tile))
    cols = int(math.ceil((w + 2 * pad) / tile))
    canvas_h, canvas_w = rows * tile, cols * tile

    def canvas(array: np.ndarray) -> np.ndarray:
        return cv2.copyMakeBorder(array, pad, canvas_h - h - pad, pad, canvas_w - w - pad, cv2.BORDER_REFLECT_101)

    colour_c = canvas(radiance)
    disparity_c = canvas(disparity)
    hidden_colour_c = canvas(hidden_colour)
    hidden_d_c = canvas(hidden_d)
    hidden_c = canvas(hidden_mask.astype(np.uint8)).astype(bool)
    hidden_d_c = np.where(hidden_c, hidden_d_c, np.nan).astype(np.float32)

    low = float(min(disparity.min(), np.nanmin(hidden_d_c) if hidden_c.any() else np.inf))
    high = float(max(disparity.max(), np.nanmax(hidden_d_c) if hidden_c.any() else -np.inf))
    count = max(2, int(math.ceil((high - low) / params.slice_step_px)) + 1)
    step = max((high - low) / (count - 1), 1e-6)
    levels = low + step * np.arange(count)
    gap_slices = max(1, int(math.ceil(params.occlusion_gap_px / step - 1e-9)))

    # each tile's range of slices (visible and hidden surfaces)
    active: list[list[tuple[int, int]]] = [[] for _ in range(count)]
    for ty in range(rows):
        for tx in range(cols):
            block = (slice(ty * tile, (ty + 1) * tile), slice(tx * tile, (tx + 1) * tile))
            lo, hi = float(disparity_c[block].min()), float(disparity_c[block].max())
            if hidden_c[block].any():
                lo = min(lo, float(np.nanmin(hidden_d_c[block])))
                hi = max(hi, float(np.nanmax(hidden_d_c[block])))
            first = max(0, int(math.floor((lo - low) / step)))
            last = min(count - 1, int(math.ceil((hi - low) / step)))
            for k in range(first, last + 1):
                active[k].append((ty, tx))

    size = tile + 2 * margin
    spectra = _Spectra((size, size))
    m0 = _Spectra._MARGIN
    gaussians = [spectra.gaussian_otf(optics.sharpness_sigma_px(c)) for c in CHANNELS]
    image = np.zeros((canvas_h + 2 * margin, canvas_w + 2 * margin, 3), np.float32)
    occluded = np.zeros_like(image)  # summed coverage of the slices at least the gap nearer
    pending: deque[tuple[int, list[tuple[int, int, np.ndarray]]]] = deque()
    source = np.zeros((4,) + spectra.fft_shape, np.float32)

    for k in range(count):  # front to back: increasing disparity = farther
        while pending and pending[0][0] <= k - gap_slices:
            for y0, x0, coverage in pending.popleft()[1]:
                occluded[y0 : y0 + size, x0 : x0 + size] += coverage
        if not active[k]:
            continue
        level = float(levels[k])
        distance = float(optics.mca.distance_mm(level)) if abs(level) > 1e-9 else optics.focus_distance_mm
        disk = spectra.disk_otf(optics.blur_diameter_px(distance))
        transfer = []
        for index, channel in enumerate(CHANNELS):
            sx, sy = optics.channel_shift_px(channel, distance)
            ramp_y = np.exp(-2j * np.pi * spectra.freq_y * sy).astype(np.complex64)
            ramp_x = np.exp(-2j * np.pi * spectra.freq_x * sx).astype(np.complex64)
            otf = gaussians[index] if disk is None else gaussians[index] * disk
            transfer.append(otf * ramp_y[:, None] * ramp_x[None, :])
        covered: list[tuple[int, int, np.ndarray]] = []
        for ty, tx in active[k]:
            block = (slice(ty * tile, (ty + 1) * tile), slice(tx * tile, (tx + 1) * tile))
            weight = np.maximum(1.0 - np.abs(disparity_c[block] - level) / step, 0.0)
            extra = np.nan_to_num(np.maximum(1.0 - np.abs(hidden_d_c[block] - level) / step, 0.0))
            if not weight.any() and not extra.any():
                continue
            y0, x0 = ty * tile, tx * tile  # the tile plus its margin, in the output canvas
            window = occluded[y0 : y0 + size, x0 : x0 + size]
            if window.min() >= 1.0:
                continue  # wholly hidden by nearer surfaces: neither seen nor hiding anything new
            source[:] = 0.0
            core = (slice(m0 + margin, m0 + margin + tile), slice(m0 + margin, m0 + margin + tile))
            premultiplied = colour_c[block] * weight[..., None] + hidden_colour_c[block] * extra[..., None]
            for index in range(3):
                source[index][core] = premultiplied[..., index]
            source[3][core] = weight + extra
            spectrum = scipy.fft.rfft2(source, axes=(-2, -1), workers=1)
            products = np.empty((6,) + spectrum.shape[1:], np.complex64)
            for index in range(3):
                products[index] = spectrum[index] * transfer[index]
                products[3 + index] = spectrum[3] * transfer[index]
            out = scipy.fft.irfft2(products, s=spectra.fft_shape, axes=(-2, -1), workers=1)
            out = out[:, m0 : m0 + size, m0 : m0 + size]
            light = np.moveaxis(out[:3], 0, -1)
            coverage = np.moveaxis(out[3:], 0, -1).astype(np.float32)
            image[y0 : y0 + size, x0 : x0 + size] += light * (1.0 - np.minimum(window, 1.0))
            covered.append((y0, x0, coverage))
        pending.append((k, covered))
    top = margin + pad
    return np.maximum(image[top : top + h, margin + pad : margin + pad + w], 0.0)


# --- the sensor -------------------------------------------------------------------------------------------------


# "poly" vignetting when no coefficients are drawn or given (`mca simulate --from-rgbd --vignetting poly`): the
# middle of POLY_K2_RANGE and POLY_K4_RANGE (below). Until the twenty-second stop it was (0, 0), which rendered no
# vignetting at all while the truth said "poly"
POLY_K_TYPICAL = (-0.275, -0.025)


@dataclass(frozen=True)
class Realism:
    """What the sensor and lens add to the ideal filter images.

    `vignetting`: "none", "cos4" (cos^4 of the chief-ray angle, atan(r / d_ls)) or "poly"
    (1 + k2 rn^2 + k4 rn^4, rn = radius / half-diagonal, coefficients `vignetting_k`; by default
    `POLY_K_TYPICAL`, the middle of the ranges the folder mode draws from: the corners at 0.70 of the centre).
    `crosstalk`: 3x3 sensor channel <- filter, or None.
    """

    sensor: SensorModel = field(default_factory=SensorModel)
    crosstalk: tuple[tuple[float, float, float], ...] | None = None
    vignetting: str = "none"
    vignetting_k: tuple[float, float] = POLY_K_TYPICAL

    def __post_init__(self) -> None:
        if self.vignetting not in ("none", "cos4", "poly"):
            raise ValueError(f"vignetting must be none, cos4 or poly, got {self.vignetting!r}")

    def as_dict(self) -> dict[str, Any]:
        return {
            "sensor": asdict(self.sensor),
            "crosstalk": None if self.crosstalk is None else [list(r) for r in self.crosstalk],
            "vignetting": self.vignetting,
            "vignetting_k": list(self.vignetting_k) if self.vignetting == "poly" else None,
        }


def vignetting_gain(realism: Realism, optics: SimulationOptics) -> np.ndarray | None:
    """Relative illumination (H, W) float32 at each pixel, or None for none."""
    if realism.vignetting == "none":
        return None
    h, w = optics.height_px, optics.width_px
    y = (np.arange(h, dtype=np.float32) - (h - 1) / 2.0)[:, None]
    x = (np.arange(w, dtype=np.float32) - (w - 1) / 2.0)[None, :]
    radius_px = np.sqrt(x * x + y * y)
    if realism.vignetting == "cos4":
        tangent = radius_px * np.float32(optics.pixel_pitch_mm / optics.sensor_distance_mm)
        return (1.0 / (1.0 + tangent * tangent)) ** 2  # cos^4(atan t) = 1 / (1 + t^2)^2
    rn2 = (radius_px / np.float32(math.hypot(w / 2.0, h / 2.0))) ** 2
    k2, k4 = realism.vignetting_k
    return np.maximum(1.0 + np.float32(k2) * rn2 + np.float32(k4) * rn2 * rn2, 0.0).astype(np.float32)


def sensor_signal(filter_images: np.ndarray, realism: Realism, optics: SimulationOptics) -> np.ndarray:
    """The noise-free signal of each sensor colour (H, W, 3) as a fraction of saturation: vignetting,
    crosstalk and exposure applied to the filter images."""
    signal = filter_images.astype(np.float32, copy=True)
    gain = vignetting_gain(realism, optics)
    if gain is not None:
        signal *= gain[..., None]
    if realism.crosstalk is not None:
        mix = np.asarray(realism.crosstalk, np.float32)
        signal = np.einsum("hwj,ij->hwi", signal, mix, optimize=True).astype(np.float32)
    signal *= np.float32(realism.sensor.exposure)
    return signal


def expose_rgb(signal: np.ndarray, sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Digital numbers (H, W, 3) uint16 with black level: every pixel records all three colours."""
    return np.dstack([_expose(signal[..., c], sensor, rng) for c in range(3)])


def expose_mosaic(signal: np.ndarray, sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """An RGGB mosaic (H, W) uint16 with black level: each site records its own colour at its own position."""
    h, w = signal.shape[:2]
    if h % 2 or w % 2:
        raise ValueError(f"a Bayer mosaic needs an even size, got {w}x{h}")
    mosaic = np.empty((h, w), np.uint16)
    for _, dx, dy, channel in BAYER_SITES:
        mosaic[dy::2, dx::2] = _expose(np.ascontiguousarray(signal[dy::2, dx::2, channel]), sensor, rng)
    return mosaic


def dn_to_linear16(dn: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """Digital numbers -> 16-bit linear values, (dn - black) / (white - black) * 65535 (a linear TIFF's encoding)."""
    span = np.float32(sensor.white_level - sensor.black_level)
    linear = np.clip((dn.astype(np.float32) - np.float32(sensor.black_level)) / span, 0.0, 1.0)
    return np.rint(linear * 65535.0).astype(np.uint16)


# --- one scene, end to end ----------------------------------------------------------------------------------------


@dataclass
class RgbdRendering:
    """A rendered capture of an RGB-D scene and what is true about it.

    `image_dn` is (H, W, 3) uint16 digital numbers (format "rgb") or the (H, W) RGGB mosaic (format
    "mosaic"), black level included; `distance_mm` and `disparity_px` (red-blue, px of the render,
    + = farther than focus) are float32 per pixel of the chief-ray view, NaN where the source
    disparity was unknown; `truth` the JSON-ready description.
    """

    image_dn: np.ndarray
    filter_images: np.ndarray
    distance_mm: np.ndarray
    disparity_px: np.ndarray
    valid: np.ndarray
    truth: dict[str, Any] = field(default_factory=dict)


def render_rgbd(
    image_srgb: np.ndarray,
    stereo_disparity: np.ndarray,
    valid: np.ndarray,
    optics: SimulationOptics,
    depth_range: DepthRange,
    realism: Realism = Realism(),
    *,
    output: str = "rgb",
    seed: int | None = 0,
    params: RenderParams = RenderParams(),
) -> RgbdRendering:
    """Render one MCA capture of an RGB-D scene.

    `image_srgb` (H, W, 3) sRGB in [0, 1] (R, G, B); `stereo_disparity` (H, W) in any unit affine in
    inverse depth (larger = nearer), `valid` where it is known. `optics` must be of the same size.
    `output` "rgb" exposes all three colours at every pixel, "mosaic" an RGGB mosaic.
    """
    if output not in ("rgb", "mosaic"):
        raise ValueError(f"output must be 'rgb' or 'mosaic', got {output!r}")
    valid = np.asarray(valid, bool)
    if valid.sum() < 2:
        raise ValueError("the disparity map has fewer than two valid pixels")
    known = np.asarray(stereo_disparity, np.float64)[valid]
    d_min, d_max = float(known.min()), float(known.max())
    if d_max <= d_min:
        raise ValueError("the valid disparities are all equal: no depth to map")
    filled = fill_from_farther_neighbour(stereo_disparity, valid)
    distance = depth_range.distance_mm(filled, d_min, d_max)
    radiance = srgb_decode(np.clip(image_srgb, 0.0, 1.0))
    filter_images = render_filter_images(radiance, distance, optics, params)
    signal = sensor_signal(filter_images, realism, optics)
    rng = np.random.default_rng(seed)
    dn = expose_rgb(signal, realism.sensor, rng) if output == "rgb" else expose_mosaic(signal, realism.sensor, rng)
    disparity = np.asarray(optics.mca.disparity_px_at_distance(distance), np.float32)
    truth_distance = np.where(valid, distance, np.nan).astype(np.float32)
    truth_disparity = np.where(valid, disparity, np.nan).astype(np.float32)
    truth = rgbd_truth(optics, depth_range, realism, truth_disparity, output, seed)
    return RgbdRendering(dn, filter_images, truth_distance, truth_disparity, valid, truth)


def rgbd_truth(
    optics: SimulationOptics,
    depth_range: DepthRange,
    realism: Realism,
    disparity_px: np.ndarray,
    output: str,
    seed: int | None,
) -> dict[str, Any]:
    """The JSON-ready description of an RGB-D rendering (optics, focus, depth range, realism, disparity range)."""
    finite = disparity_px[np.isfinite(disparity_px)]
    focus = optics.focus_distance_mm
    return {
        "focus_distance_mm": focus,
        "near_mm": depth_range.near_mm,
        "far_mm": depth_range.far_mm,
        "near_inter_object_depth_mm": depth_range.near_mm - focus,
        "far_inter_object_depth_mm": depth_range.far_mm - focus,
        "near_disparity_px": optics.disparity_px(depth_range.near_mm),
        "far_disparity_px": optics.disparity_px(depth_range.far_mm),
        "disparity_range_px": [float(finite.min()), float(finite.max())] if finite.size else None,
        "valid_fraction": float(finite.size / disparity_px.size),
        "optics": optics.truth(),
        "realism": realism.as_dict(),
        "output": output,
        "cfa": "RGGB" if output == "mosaic" else None,
        "seed": seed,
    }


# --- randomised realism -------------------------------------------------------------------------------------------

# The ranges the folder mode draws from (documented in docs/simulator.md).
FOCUS_RANGE_MM = (800.0, 1400.0)  # focus distance
FRONT_FOCUS_SHARE = 0.35  # share of scenes focused in front of everything (all surfaces behind the focus plane)
FRONT_NEAR_OFFSET_MM = (0.0, 40.0)  # nearest surface this far behind the focus plane, when focused in front
INSIDE_NEAR_OFFSET_MM = (-170.0, -40.0)  # otherwise the nearest surface this far before it
FAR_OFFSET_MM = (150.0, 550.0)  # the farthest surface this far behind the focus plane
ISO_CHOICES = (100.0, 200.0, 400.0, 800.0, 1600.0, 3200.0)
EXPOSURE_RANGE = (0.35, 0.8)  # fraction of saturation a white surface reaches
CROSSTALK_SHARE = 0.5  # share of scenes with crosstalk
CROSSTALK_RANGE = (0.02, 0.12)  # total leak into each sensor colour from the other two filters
VIGNETTING_CHOICES = ("none", "cos4", "poly")
POLY_K2_RANGE = (-0.45, -0.1)
POLY_K4_RANGE = (-0.15, 0.1)


@dataclass(frozen=True)
class SceneDraw:
    """One random draw of the folder mode: where the lens focuses, the depth range and the sensor's realism."""

    focus_distance_mm: float
    depth_range: DepthRange
    focus_placement: str  # "front" (in front of every surface) or "inside" (between near and far)
    realism: Realism

    def as_dict(self) -> dict[str, Any]:
        return {
            "focus_distance_mm": self.focus_distance_mm,
            "near_mm": self.depth_range.near_mm,
            "far_mm": self.depth_range.far_mm,
            "focus_placement": self.focus_placement,
            **self.realism.as_dict(),
        }


def draw_scene_settings(rng: np.random.Generator, base: SensorModel = SensorModel()) -> SceneDraw:
    """Random focus distance, depth range, noise level (ISO, exposure), crosstalk and vignetting."""
    focus = float(rng.uniform(*FOCUS_RANGE_MM))
    front = bool(rng.random() < FRONT_FOCUS_SHARE)
    near_offset = float(rng.uniform(*(FRONT_NEAR_OFFSET_MM if front else INSIDE_NEAR_OFFSET_MM)))
    far_offset = float(rng.uniform(*FAR_OFFSET_MM))
    depth_range = DepthRange(focus + near_offset, focus + far_offset)
    iso = float(rng.choice(ISO_CHOICES))
    exposure = float(rng.uniform(*EXPOSURE_RANGE))
    sensor = SensorModel(
        black_level=base.black_level,
        white_level=base.white_level,
        bits=base.bits,
        full_well_e=base.full_well_e,
        iso=iso,
        read_noise_e=base.read_noise_e,
        exposure=exposure,
        noise=True,
    )
    crosstalk = None
    if rng.random() < CROSSTALK_SHARE:
        strength = float(rng.uniform(*CROSSTALK_RANGE))
        rows: list[tuple[float, float, float]] = []
        for i in range(3):
            split = rng.uniform(0.2, 0.8)
            leak = [strength * split, strength * (1.0 - split)]
            row = [0.0, 0.0, 0.0]
            row[i] = 1.0 - strength
            others = [j for j in range(3) if j != i]
            row[others[0]], row[others[1]] = leak
            rows.append((round(row[0], 6), round(row[1], 6), round(row[2], 6)))
        crosstalk = tuple(rows)
    vignetting = str(rng.choice(VIGNETTING_CHOICES))
    k = (float(rng.uniform(*POLY_K2_RANGE)), float(rng.uniform(*POLY_K4_RANGE))) if vignetting == "poly" else (0.0, 0.0)
    realism = Realism(sensor=sensor, crosstalk=crosstalk, vignetting=vignetting, vignetting_k=k)
    return SceneDraw(focus, depth_range, "front" if front else "inside", realism)


def rgbd_optics(
    profile: CameraProfile, width_px: int, height_px: int, focus_distance_mm: float, sensor_width_mm: float
) -> SimulationOptics:
    """The profile's lens and aperture focused at `focus_distance_mm` (d_ls = f F / (F - f), eq. 6), on a sensor
    `sensor_width_mm` wide imaged by `width_px` x `height_px` pixels (the render is the whole sensor width)."""
    if profile.lens is None:
        raise ValueError(f"profile '{profile.name}' has no lens: an MCA capture cannot be rendered with it")
    f = profile.lens.focal_length_mm
    if focus_distance_mm <= f:
        raise ValueError(f"focus distance {focus_distance_mm} mm is not beyond the focal length {f} mm")
    return SimulationOptics(
        focal_length_mm=f,
        sensor_distance_mm=f * focus_distance_mm / (focus_distance_mm - f),
        pixel_pitch_mm=sensor_width_mm / width_px,
        aperture=profile.aperture,
        width_px=width_px,
        height_px=height_px,
    )
