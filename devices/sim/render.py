"""Physically based MCA image formation: a scene of textured layers in, the camera's Bayer mosaic and ground truth out.

The model (thin lens, sections IV-V of the paper): a point at distance u focuses at
v = f u / (u - f) (eq. 6). Its sub-aperture image through a filter centred at p (mm,
x right and y up seen from behind) meets the sensor p (d_ls - v) / v mm away from the
chief ray, which is (+p_x, -p_y) (d_ls - v) / v / pitch pixels in the displayed image
(x right, y down), and is spread over the filter's disk scaled by |d_ls - v| / v, a
disk of diameter filter_diameter |d_ls - v| / v / pitch pixels. Between the red and
blue filters (d_a apart) that is the disparity δ = d_a (d_ls - v) / v (eq. 11 with
Δd = d_ls - v); `MCAOptics.disparity_px_at_distance` and
`FilterAperture.shift_per_disparity` give exactly these numbers and are used here.

Occlusion is rendered by back-to-front layered compositing: each layer is shifted
and blurred per filter, colour and coverage alike, then composited over what lies
behind it. A slanted layer is cut into thin depth slices with tent weights, so its
disparity varies continuously. Each filter's image is sampled at the Bayer sites of
its own sensor colour (RGGB: red at (0, 0), green at (1, 0) and (0, 1), blue at
(1, 1) of each 2x2 block, (x, y) in full-resolution pixels), optionally mixed by a
crosstalk matrix, then photon and read noise and 14-bit quantisation are applied.

Coordinates: scenes are drawn in frame units, x right and y down, 1 = the frame
height, so that a scene does not depend on the render size. Pure: arrays and
parameters in, arrays out.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.fft

from mca.devices.sim.textures import Texture, texture_patch
from mca.processing.camera import CHANNELS, CameraProfile, FilterAperture
from mca.processing.optics import MCAOptics

# The Bayer sites of an RGGB mosaic: (name, x offset, y offset, sensor channel index) in each 2x2 block.
BAYER_SITES: tuple[tuple[str, int, int, int], ...] = (("R", 0, 0, 0), ("G1", 1, 0, 1), ("G2", 0, 1, 1), ("B", 1, 1, 2))
# Each filter's image is rendered on the grid of the first site of its own sensor colour.
_OWN_SITE = {0: "R", 1: "G1", 2: "B"}
# Centre wavelengths of the three filters, for diffraction.
WAVELENGTH_MM = {"red": 610e-6, "green": 530e-6, "blue": 460e-6}
_SLICE_STEP_PX = 0.25  # largest disparity step (full-resolution px) between the slices of a slanted layer


# --- scene description -------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Shape:
    """An object's silhouette: the union of polygons, each an (N, 2) array of (x, y) in frame units."""

    polygons: tuple[np.ndarray, ...]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in frame units."""
        points = np.concatenate(self.polygons)
        return (
            float(points[:, 0].min()),
            float(points[:, 1].min()),
            float(points[:, 0].max()),
            float(points[:, 1].max()),
        )


@dataclass(frozen=True)
class Slant:
    """A flat surface slanted along an image axis: `from_mm` at the low end of its extent (left for axis "x",
    top for "y"), `to_mm` at the high end; distances from the lens.

    A physically planar surface seen through a lens has its *inverse* distance affine in image
    coordinates (Z = Z0 + k X with x = f X / Z gives 1/Z = (1 - k x / f) / Z0), hence its MCA disparity
    too (delta = d_a (d_ls (1/f - 1/u) - 1), affine in 1/u): the distance is interpolated in 1/u.
    """

    from_mm: float
    to_mm: float
    axis: str = "x"

    def __post_init__(self) -> None:
        if self.axis not in ("x", "y"):
            raise ValueError(f"slant axis must be 'x' or 'y', got {self.axis!r}")

    def distance_at_fraction_mm(self, t: np.ndarray | float) -> np.ndarray | float:
        """Distance at fraction t in [0, 1] of the extent (0 = low end): 1/u linear in t (a true plane)."""
        inverse = 1.0 / self.from_mm + (1.0 / self.to_mm - 1.0 / self.from_mm) * np.asarray(t, dtype=np.float64)
        return 1.0 / inverse

    @property
    def middle_mm(self) -> float:
        """Distance at the middle of the extent (the harmonic mean of the two ends)."""
        return float(self.distance_at_fraction_mm(0.5))


@dataclass(frozen=True, eq=False)
class Layer:
    """One textured surface of a scene: an object (id >= 1) or the background (id 0, `shape` None = whole frame).

    `reflectance` is the linear radiance of the surface in the red, green and blue filter
    bands (1.0 = a white surface); `distance_mm` is from the lens, for a slanted layer the
    distance at the middle of its extent (`Slant.middle_mm` for a true plane); it decides the compositing order.
    """

    id: int
    name: str
    colour: str
    reflectance: tuple[float, float, float]
    distance_mm: float
    texture: Texture
    shape: Shape | None = None
    slant: Slant | None = None
    paper_label: str | None = None

    def distance_at_mm(self, position: np.ndarray | float) -> np.ndarray | float:
        """Distance from the lens at frame coordinate `position` along the slant axis (constant if not slanted)."""
        if self.slant is None:
            return self.distance_mm if np.isscalar(position) else np.full_like(position, self.distance_mm)
        low, high = self._extent()
        t = np.clip((np.asarray(position, dtype=np.float64) - low) / max(high - low, 1e-12), 0.0, 1.0)
        value = self.slant.distance_at_fraction_mm(t)
        return float(value) if np.isscalar(position) else value

    def _extent(self) -> tuple[float, float]:
        assert self.shape is not None and self.slant is not None
        x0, y0, x1, y1 = self.shape.bounds
        return (x0, x1) if self.slant.axis == "x" else (y0, y1)

    @property
    def distance_range_mm(self) -> tuple[float, float]:
        if self.slant is None:
            return (self.distance_mm, self.distance_mm)
        return (min(self.slant.from_mm, self.slant.to_mm), max(self.slant.from_mm, self.slant.to_mm))


@dataclass(frozen=True, eq=False)
class Scene:
    """Objects in front of an optional background; ids of objects are the label values (1..N)."""

    name: str
    description: str
    objects: tuple[Layer, ...]
    background: Layer | None = None

    def __post_init__(self) -> None:
        ids = [o.id for o in self.objects]
        if len(set(ids)) != len(ids) or any(i <= 0 or i > 65535 for i in ids):
            raise ValueError(f"scene '{self.name}': object ids must be distinct and in 1..65535, got {ids}")
        if any(o.shape is None for o in self.objects):
            raise ValueError(
                f"scene '{self.name}': every object needs a shape (only the background may fill the frame)"
            )


# --- optics and sensor ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimulationOptics:
    """The optics a rendering uses: may deviate from a profile (a perturbed lens) and may be scaled down.

    `width_px`/`height_px` are the mosaic size; `pixel_pitch_mm` the photosite pitch at that size
    (scaled up when the image is scaled down, so that disparities in pixels scale with the image).
    """

    focal_length_mm: float
    sensor_distance_mm: float
    pixel_pitch_mm: float
    aperture: FilterAperture
    width_px: int
    height_px: int
    anti_alias_sigma_px: float = 0.6

    @classmethod
    def from_profile(cls, profile: CameraProfile, scale: float = 1.0) -> SimulationOptics:
        """The profile's nominal optics at `scale` times its image size (mosaic dimensions rounded to even)."""
        if profile.lens is None or profile.pixel_pitch_mm is None or not profile.width_px or not profile.height_px:
            raise ValueError(f"profile '{profile.name}' lacks the lens, pixel pitch or image size a simulation needs")
        if not 0 < scale <= 1.0:
            raise ValueError(f"scale must be in (0, 1], got {scale}")
        width = max(2, 2 * int(round(profile.width_px * scale / 2)))
        height = max(2, 2 * int(round(profile.height_px * scale / 2)))
        pitch = profile.pixel_pitch_mm * profile.height_px / height
        return cls(
            profile.lens.focal_length_mm, profile.lens.sensor_distance_mm, pitch, profile.aperture, width, height
        )

    def perturbed(
        self, *, focal_length_factor: float = 1.0, sensor_distance_factor: float = 1.0, baseline_factor: float = 1.0
    ) -> SimulationOptics:
        """A lens that deviates from this one: focal length, d_ls and filter positions scaled by the factors."""
        ap = self.aperture
        scaled = dataclasses.replace(
            ap,
            red_mm=(ap.red_mm[0] * baseline_factor, ap.red_mm[1] * baseline_factor),
            green_mm=(ap.green_mm[0] * baseline_factor, ap.green_mm[1] * baseline_factor),
            blue_mm=(ap.blue_mm[0] * baseline_factor, ap.blue_mm[1] * baseline_factor),
        )
        return dataclasses.replace(
            self,
            focal_length_mm=self.focal_length_mm * focal_length_factor,
            sensor_distance_mm=self.sensor_distance_mm * sensor_distance_factor,
            aperture=scaled,
        )

    @property
    def mca(self) -> MCAOptics:
        return MCAOptics(self.focal_length_mm, self.sensor_distance_mm, self.aperture.baseline_mm, self.pixel_pitch_mm)

    @property
    def focus_distance_mm(self) -> float:
        return self.mca.focus_distance_mm

    @property
    def crosstalk(self) -> np.ndarray | None:
        """Sensor channel <- filter mixing matrix of the aperture, or None for none."""
        return None if self.aperture.crosstalk is None else np.asarray(self.aperture.crosstalk, dtype=np.float32)

    def truth(self) -> dict[str, Any]:
        """The optics as a rendering's truth file records them (`optics` in `<scene>.truth.json`)."""
        return {
            "focal_length_mm": self.focal_length_mm,
            "sensor_distance_mm": self.sensor_distance_mm,
            "pixel_pitch_mm": self.pixel_pitch_mm,
            "filter_centre_distance_mm": self.aperture.baseline_mm,
            "widest_pair": list(self.aperture.widest_pair),
            "filter_diameter_mm": self.aperture.filter_diameter_mm,
            "width_px": self.width_px,
            "height_px": self.height_px,
        }

    def disparity_px(self, distance_mm: float) -> float:
        """Widest-pair disparity at `distance_mm`, exact thin lens, in pixels of this mosaic."""
        return float(self.mca.disparity_px_at_distance(distance_mm))

    def channel_shift_px(self, channel: str, distance_mm: float) -> tuple[float, float]:
        """(dx, dy) of `channel`'s sub-aperture image relative to the chief ray: (+p_x, -p_y)(d_ls - v)/v/pitch."""
        sx, sy = self.aperture.shift_per_disparity(channel)
        d = self.disparity_px(distance_mm)
        return (sx * d, sy * d)

    def sharpness_sigma_px(self, channel: str) -> float:
        """Gaussian sigma (full-resolution px) of the in-focus blur of `channel`: diffraction through the filter's
        sub-aperture (Airy core ~ 0.42 λ N with N = d_ls / filter diameter) combined with the sensor's
        anti-aliasing filter."""
        n_number = self.sensor_distance_mm / self.aperture.filter_diameter_mm
        diffraction_mm = 0.42 * WAVELENGTH_MM[channel] * n_number
        return math.hypot(diffraction_mm / self.pixel_pitch_mm, self.anti_alias_sigma_px)

    def blur_diameter_px(self, distance_mm: float) -> float:
        """Diameter of a filter's defocus disk: filter_diameter |d_ls - v| / v / pitch = (D_f / d_a) |δ|."""
        return self.aperture.filter_diameter_mm / self.aperture.baseline_mm * abs(self.disparity_px(distance_mm))


@dataclass(frozen=True)
class SensorModel:
    """Photon and read noise and quantisation of a 14-bit CMOS sensor (defaults close to a Canon EOS 70D).

    At ISO 100 the `full_well_e` electrons reach the white level; at ISO N, 100/N of them.
    `exposure` is the fraction of saturation a white surface (reflectance 1) reaches.
    """

    black_level: int = 2048
    white_level: int = 15000
    bits: int = 14
    full_well_e: float = 26000.0
    iso: float = 100.0
    read_noise_e: float = 12.0
    exposure: float = 0.6
    noise: bool = True

    @property
    def saturation_e(self) -> float:
        return self.full_well_e * 100.0 / self.iso

    @property
    def electrons_per_dn(self) -> float:
        return self.saturation_e / (self.white_level - self.black_level)


@dataclass
class Rendering:
    """A simulated capture: the raw mosaic and what is true about it.

    `mosaic` (H, W) uint16 RGGB with black level; `planes_linear` (H/2, W/2, 3) float32, the
    noise-free signal of the red, green (mean of both sites) and blue sites as a fraction of
    white - black; `depth_mm` (H, W) float32, distance of the front-most surface along each
    pixel's chief ray; `labels` (H, W) uint16 object ids, 0 = background; `truth` the JSON-ready
    description (see `docs/simulator.md`).
    """

    mosaic: np.ndarray
    planes_linear: np.ndarray
    depth_mm: np.ndarray
    labels: np.ndarray
    truth: dict[str, Any] = field(default_factory=dict)


# --- rasterising ----------------------------------------------------------------------------------------------


def rasterize(
    shape: Shape, frame_height_px: float, origin_px: tuple[int, int], size: tuple[int, int], offset_px: float = -0.5
) -> np.ndarray:
    """Anti-aliased coverage (float32 in [0, 1], `size` = (h, w)) of `shape` on a pixel raster.

    A point (x, y) in frame units lies at pixel x * frame_height_px + offset_px (pixel centres are
    integers); `origin_px` is the (x, y) pixel of the raster's top-left element.
    """
    mask = np.zeros(size, np.uint8)
    shift_bits = 4
    scale = float(1 << shift_bits)
    polys = []
    for poly in shape.polygons:
        px = poly * frame_height_px + offset_px - np.array(origin_px, dtype=np.float64)
        polys.append(np.round(px * scale).astype(np.int32).reshape(-1, 1, 2))
    cv2.fillPoly(mask, polys, 255, lineType=cv2.LINE_AA, shift=shift_bits)
    return mask.astype(np.float32) * (1.0 / 255.0)


def _pixel_bounds(
    shape: Shape, frame_height_px: float, offset_px: float, margin_px: float, limit: tuple[int, int]
) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = shape.bounds
    left = max(0, int(math.floor(x0 * frame_height_px + offset_px - margin_px)))
    top = max(0, int(math.floor(y0 * frame_height_px + offset_px - margin_px)))
    right = min(limit[1], int(math.ceil(x1 * frame_height_px + offset_px + margin_px)) + 1)
    bottom = min(limit[0], int(math.ceil(y1 * frame_height_px + offset_px + margin_px)) + 1)
    return left, top, max(left, right), max(top, bottom)


@functools.lru_cache(maxsize=256)
def disk_kernel(diameter_px: float) -> np.ndarray | None:
    """Normalised pillbox of `diameter_px` with anti-aliased rim (16x16 supersampling); None below 0.2 px."""
    radius = diameter_px / 2.0
    if diameter_px < 0.2:
        return None
    half = int(math.ceil(radius + 0.5))
    sub = 16
    coords = (np.arange((2 * half + 1) * sub) + 0.5) / sub - (half + 0.5)
    yy, xx = np.meshgrid(coords, coords, indexing="ij")
    inside = (xx * xx + yy * yy <= radius * radius).astype(np.float32)
    kernel = inside.reshape(2 * half + 1, sub, 2 * half + 1, sub).sum(axis=(1, 3))
    kernel /= kernel.sum()
    return kernel.astype(np.float32)


class _Spectra:
    """Shift-and-blur in the Fourier domain: exact sub-pixel translation (a linear phase) times the disk's OTF.

    The input is mirror-padded to a fast FFT size; content moved past the padding wraps around, so
    callers keep a margin wider than the largest shift plus blur radius.
    """

    _MARGIN = 16  # mirrored border around the input, so that the periodic wrap sees no step

    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        m = 2 * self._MARGIN
        self.fft_shape = (
            scipy.fft.next_fast_len(shape[0] + m, real=True),
            scipy.fft.next_fast_len(shape[1] + m, real=True),
        )
        self.freq_y = np.fft.fftfreq(self.fft_shape[0]).astype(np.float32)
        self.freq_x = np.fft.rfftfreq(self.fft_shape[1]).astype(np.float32)

    def forward(self, image: np.ndarray) -> np.ndarray:
        m = self._MARGIN
        padded = cv2.copyMakeBorder(
            image.astype(np.float32, copy=False),
            m,
            self.fft_shape[0] - self.shape[0] - m,
            m,
            self.fft_shape[1] - self.shape[1] - m,
            cv2.BORDER_REFLECT_101,
        )
        return scipy.fft.rfft2(padded, workers=-1)

    def disk_otf(self, blur_diameter_px: float) -> np.ndarray | None:
        kernel = disk_kernel(round(blur_diameter_px, 3))
        if kernel is None:
            return None
        half = kernel.shape[0] // 2
        embedded = np.zeros(self.fft_shape, np.float32)
        embedded[: kernel.shape[0], : kernel.shape[1]] = kernel
        embedded = np.roll(embedded, (-half, -half), axis=(0, 1))  # centre the kernel on pixel (0, 0)
        return scipy.fft.rfft2(embedded, workers=-1).real.astype(np.float32)

    def gaussian_otf(self, sigma_px: float) -> np.ndarray:
        """Transfer function of a Gaussian blur of `sigma_px` (the diffraction and anti-aliasing blur)."""
        gy = np.exp(-2.0 * (np.pi * sigma_px * self.freq_y) ** 2).astype(np.float32)
        gx = np.exp(-2.0 * (np.pi * sigma_px * self.freq_x) ** 2).astype(np.float32)
        return gy[:, None] * gx[None, :]

    def inverse(self, spectrum: np.ndarray, shift_px: tuple[float, float], otf: np.ndarray | None) -> np.ndarray:
        """dst(x) = (src * disk)(x - shift), cropped to the input shape."""
        ramp_y = np.exp(-2j * np.pi * self.freq_y * shift_px[1]).astype(np.complex64)
        ramp_x = np.exp(-2j * np.pi * self.freq_x * shift_px[0]).astype(np.complex64)
        product = spectrum * ramp_y[:, None] * ramp_x[None, :]
        if otf is not None:
            product *= otf
        out = scipy.fft.irfft2(product, s=self.fft_shape, workers=-1)
        m = self._MARGIN
        return out[m : m + self.shape[0], m : m + self.shape[1]]


def shift_image(image: np.ndarray, shift_px: tuple[float, float], blur_diameter_px: float = 0.0) -> np.ndarray:
    """Translate a 2-D image by `shift_px` = (dx, dy), dst(x) = src(x - shift), exactly at sub-pixel level,
    and blur it with a disk of `blur_diameter_px`; the image is treated as periodic (keep a margin)."""
    spectra = _Spectra(image.shape[:2])
    return spectra.inverse(spectra.forward(image), shift_px, spectra.disk_otf(blur_diameter_px)).astype(np.float32)


# --- rendering -------------------------------------------------------------------------------------------------


def _site_offsets_px(cosited: bool) -> dict[str, tuple[float, float]]:
    """Each Bayer site's position relative to the centre of its 2x2 block, full-resolution pixels."""
    return {name: ((0.0, 0.0) if cosited else (dx - 0.5, dy - 0.5)) for name, dx, dy, _ in BAYER_SITES}


def _slices(layer: Layer, optics: SimulationOptics) -> list[tuple[float, float | None]]:
    """(distance_mm, position along the slant axis in frame units) of each depth slice; one unslanted slice."""
    if layer.slant is None:
        return [(layer.distance_mm, None)]
    low, high = layer._extent()
    span_px = abs(optics.disparity_px(layer.slant.to_mm) - optics.disparity_px(layer.slant.from_mm))
    count = max(2, int(math.ceil(span_px / _SLICE_STEP_PX)) + 1)
    return [(float(layer.distance_at_mm(p)), float(p)) for p in np.linspace(low, high, count)]


def _render_filter_images(scene: Scene, optics: SimulationOptics, cosited: bool) -> list[np.ndarray]:
    """The composite image through each filter (red, green, blue), each sampled on its own colour's Bayer grid."""
    plane_h, plane_w = optics.height_px // 2, optics.width_px // 2
    frame_h = float(plane_h)  # plane pixels per frame unit
    sites = _site_offsets_px(cosited)
    layers = ([scene.background] if scene.background is not None else []) + sorted(
        scene.objects, key=lambda o: -o.distance_mm
    )
    all_distances = [d for layer in layers for d in layer.distance_range_mm]
    sharpness_px = 3.0 * max(optics.sharpness_sigma_px(c) for c in CHANNELS) / 2.0
    reach = (
        max(
            max(
                abs(optics.disparity_px(d)) * 0.5 * math.hypot(*optics.aperture.shift_per_disparity(c))
                for c in CHANNELS
            )
            + optics.blur_diameter_px(d) / 4.0
            for d in all_distances
        )
        + sharpness_px
    )
    pad = int(math.ceil(reach)) + 4
    padded = (plane_h + 2 * pad, plane_w + 2 * pad)
    offset_px = pad - 0.5  # frame x -> padded plane pixel: x * frame_h + offset_px
    composite = [np.zeros(padded, np.float32) for _ in CHANNELS]

    for layer in layers:
        # Coverage and texture over the layer's region of interest (the whole padded frame for a background).
        if layer.shape is None:
            left, top, right, bottom = 0, 0, padded[1], padded[0]
            alpha = np.ones((bottom - top, right - left), np.float32)
        else:
            left, top, right, bottom = _pixel_bounds(layer.shape, frame_h, offset_px, reach + 3, padded)
            alpha = rasterize(layer.shape, frame_h, (left, top), (bottom - top, right - left), offset_px)
        if alpha.size == 0:
            continue
        modulation = texture_patch(layer.texture, (left - offset_px, top - offset_px), alpha.shape, frame_h)
        accumulated = [np.zeros(alpha.shape + (2,), np.float32) for _ in CHANNELS]
        slices = _slices(layer, optics)
        step = 1.0
        if len(slices) > 1:
            positions = np.array([p for _, p in slices])
            step = float(positions[1] - positions[0]) * frame_h  # slice spacing, plane px
        for distance, position in slices:
            weight = alpha
            x0, y0, x1, y1 = 0, 0, alpha.shape[1], alpha.shape[0]
            if position is not None:
                assert layer.slant is not None
                centre = position * frame_h + offset_px
                along = np.arange(left, right) if layer.slant.axis == "x" else np.arange(top, bottom)
                tent = np.clip(1.0 - np.abs(along - centre) / step, 0.0, 1.0).astype(np.float32)
                nonzero = np.nonzero(tent)[0]
                if nonzero.size == 0:
                    continue
                lo = max(0, int(nonzero[0] - reach - 3))
                hi = min(tent.size, int(nonzero[-1] + reach + 4))
                if layer.slant.axis == "x":
                    x0, x1 = lo, hi
                    weight = alpha * tent[None, :]
                else:
                    y0, y1 = lo, hi
                    weight = alpha * tent[:, None]
            w = weight[y0:y1, x0:x1]
            if not w.any():
                continue
            spectra = _Spectra(w.shape)
            opaque = layer.shape is None  # a background covers everything: coverage stays 1
            coverage_spectrum = None if opaque else spectra.forward(w)
            texture_spectrum = spectra.forward(w * modulation[y0:y1, x0:x1])
            disk = spectra.disk_otf(optics.blur_diameter_px(distance) / 2.0)
            for index, channel in enumerate(CHANNELS):
                shift = optics.channel_shift_px(channel, distance)
                site = sites[_OWN_SITE[index]]
                move = ((shift[0] - site[0]) / 2.0, (shift[1] - site[1]) / 2.0)
                otf = spectra.gaussian_otf(optics.sharpness_sigma_px(channel) / 2.0)
                if disk is not None:
                    otf = otf * disk
                target = accumulated[index][y0:y1, x0:x1]
                target[..., 0] += layer.reflectance[index] * spectra.inverse(texture_spectrum, move, otf)
                if coverage_spectrum is None:
                    target[..., 1] += 1.0
                else:
                    target[..., 1] += spectra.inverse(coverage_spectrum, move, otf)
        for index in range(len(CHANNELS)):
            region = composite[index][top:bottom, left:right]
            premultiplied, coverage = accumulated[index][..., 0], accumulated[index][..., 1]
            region *= 1.0 - np.clip(coverage, 0.0, 1.0)
            region += premultiplied
    return [np.maximum(c[pad : pad + plane_h, pad : pad + plane_w], 0.0) for c in composite]


def _sensor_sites(
    filter_images: Sequence[np.ndarray], crosstalk: np.ndarray | None, cosited: bool
) -> dict[str, np.ndarray]:
    """The signal at each Bayer site: filter images moved to the site's grid and mixed by the crosstalk matrix."""
    sites = _site_offsets_px(cosited)
    values = {}
    for name, _, _, channel in BAYER_SITES:
        total = None
        for index, image in enumerate(filter_images):
            if crosstalk is None:
                gain = 1.0 if index == channel else 0.0
            else:
                gain = float(crosstalk[channel, index])
            if gain == 0.0:
                continue
            own = sites[_OWN_SITE[index]]
            target = sites[name]
            if own != target:
                # Move the whole image to the other site's grid; the border is mirrored, not wrapped.
                margin = 4
                padded = cv2.copyMakeBorder(image, margin, margin, margin, margin, cv2.BORDER_REFLECT_101)
                moved = shift_image(padded, (-(target[0] - own[0]) / 2.0, -(target[1] - own[1]) / 2.0))
                image = moved[margin:-margin, margin:-margin]
            total = gain * image if total is None else total + gain * image
        values[name] = total if total is not None else np.zeros_like(filter_images[0])
    return values


def _expose(signal: np.ndarray, sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Fraction-of-saturation signal -> 14-bit digital numbers with photon (Poisson) and read noise.

    Photon noise is drawn as Poisson where fewer than 50 electrons are expected and as its normal
    limit (variance = mean) elsewhere, combined with the Gaussian read noise in one draw.
    """
    span = sensor.white_level - sensor.black_level
    if not sensor.noise:
        dn = sensor.black_level + signal.astype(np.float32) * np.float32(span)
    else:
        electrons = np.maximum(signal, 0.0).astype(np.float32) * np.float32(sensor.saturation_e)
        sigma = np.sqrt(electrons + np.float32(sensor.read_noise_e**2))
        noisy = electrons + sigma * rng.standard_normal(electrons.shape, dtype=np.float32)
        low = electrons < 50.0
        if low.any():
            few = electrons[low].astype(np.float64)
            noisy[low] = rng.poisson(few) + sensor.read_noise_e * rng.standard_normal(few.shape)
        dn = np.float32(sensor.black_level) + noisy * np.float32(1.0 / sensor.electrons_per_dn)
    top = min(sensor.white_level, (1 << sensor.bits) - 1)
    np.rint(dn, out=dn)
    np.clip(dn, 0, top, out=dn)
    return dn.astype(np.uint16)


def render(
    scene: Scene,
    optics: SimulationOptics,
    sensor: SensorModel = SensorModel(),
    *,
    seed: int | None = 0,
    cosited: bool = False,
) -> Rendering:
    """Simulate one MCA photograph of `scene` through `optics` on `sensor`.

    `cosited=True` samples every colour at the centre of its 2x2 block instead of at its Bayer
    site (an idealised sensor, for tests of the algorithms without the Bayer offsets).
    """
    if optics.width_px % 2 or optics.height_px % 2:
        raise ValueError(f"the mosaic size must be even, got {optics.width_px}x{optics.height_px}")
    filter_images = _render_filter_images(scene, optics, cosited)
    values = _sensor_sites(filter_images, optics.crosstalk, cosited)
    scale = sensor.exposure
    planes = np.dstack([values["R"], 0.5 * (values["G1"] + values["G2"]), values["B"]]).astype(np.float32) * scale
    rng = np.random.default_rng(seed)
    mosaic = np.empty((optics.height_px, optics.width_px), np.uint16)
    for name, dx, dy, _ in BAYER_SITES:
        mosaic[dy::2, dx::2] = _expose(values[name] * scale, sensor, rng)
    depth_mm, labels, masks = truth_rasters(scene, optics)
    truth = scene_truth(scene, optics, labels, masks)
    truth["sensor"] = {
        "black_level": sensor.black_level,
        "white_level": sensor.white_level,
        "iso": sensor.iso,
        "exposure": sensor.exposure,
        "noise": sensor.noise,
        "cfa": "RGGB",
        "cosited": cosited,
    }
    truth["seed"] = seed
    return Rendering(
        mosaic=mosaic, planes_linear=np.clip(planes, 0.0, 1.0), depth_mm=depth_mm, labels=labels, truth=truth
    )


# --- ground truth ---------------------------------------------------------------------------------------------


def truth_rasters(
    scene: Scene, optics: SimulationOptics
) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[tuple[int, int, int, int], np.ndarray]]]:
    """Per full-resolution pixel: distance of the front-most surface (mm, float32) and its object id (uint16).

    Also returns each object's binary mask in its bounding box: {id: ((left, top, right, bottom), mask)}.
    Pixels are decided at their centre (coverage >= 1/2), on the undisplaced (chief-ray) image.
    """
    h, w = optics.height_px, optics.width_px
    frame_h = float(h)
    background = scene.background.distance_mm if scene.background is not None else np.inf
    depth = np.full((h, w), background, np.float32)
    labels = np.zeros((h, w), np.uint16)
    masks = {}
    for layer in scene.objects:
        assert layer.shape is not None
        left, top, right, bottom = _pixel_bounds(layer.shape, frame_h, -0.5, 2, (h, w))
        if right <= left or bottom <= top:
            masks[layer.id] = ((left, top, right, bottom), np.zeros((0, 0), bool))
            continue
        mask = rasterize(layer.shape, frame_h, (left, top), (bottom - top, right - left)) >= 0.5
        surface: np.ndarray
        if layer.slant is None:
            surface = np.asarray(layer.distance_mm, np.float32)
        else:
            along = np.arange(left, right) if layer.slant.axis == "x" else np.arange(top, bottom)
            ramp = np.asarray(layer.distance_at_mm((along + 0.5) / frame_h), np.float32)
            surface = ramp[None, :] if layer.slant.axis == "x" else ramp[:, None]
        surface = np.broadcast_to(surface, mask.shape)
        region_depth = depth[top:bottom, left:right]
        nearer = mask & (surface < region_depth)
        region_depth[nearer] = surface[nearer]
        labels[top:bottom, left:right][nearer] = layer.id
        masks[layer.id] = ((left, top, right, bottom), mask)
    return depth, labels, masks


def scene_truth(
    scene: Scene,
    optics: SimulationOptics,
    labels: np.ndarray,
    masks: dict[int, tuple[tuple[int, int, int, int], np.ndarray]],
) -> dict[str, Any]:
    """The JSON-ready ground truth of a rendering: objects with distances, disparities, occlusions and order."""
    focus = optics.focus_distance_mm
    occluders: dict[int, set[int]] = {o.id: set() for o in scene.objects}
    visible: dict[int, int] = {}
    for layer in scene.objects:
        (left, top, right, bottom), mask = masks[layer.id]
        if mask.size == 0:
            visible[layer.id] = 0
            continue
        seen = labels[top:bottom, left:right][mask]
        visible[layer.id] = int(np.count_nonzero(seen == layer.id))
        for other in np.unique(seen):
            if other != layer.id and other != 0:
                occluders[int(other)].add(layer.id)
    distinct = sorted({round(o.distance_mm, 6) for o in scene.objects})
    objects = []
    for layer in sorted(scene.objects, key=lambda o: o.id):
        slant = None
        if layer.slant is not None:
            low, high = layer._extent()
            slant = {
                "from_mm": layer.slant.from_mm,
                "to_mm": layer.slant.to_mm,
                "axis": layer.slant.axis,
                "from_inter_object_depth_mm": layer.slant.from_mm - focus,
                "to_inter_object_depth_mm": layer.slant.to_mm - focus,
                "from_disparity_px": optics.disparity_px(layer.slant.from_mm),
                "to_disparity_px": optics.disparity_px(layer.slant.to_mm),
                # where from_mm and to_mm hold: the ends of the extent along the axis, mosaic pixel
                # coordinates; in between 1/distance and the disparity are affine (a plane)
                "extent_px": [low * optics.height_px - 0.5, high * optics.height_px - 0.5],
                "model": "plane",
            }
        estimate = optics.mca.from_distance(layer.distance_mm)
        objects.append(
            {
                "id": layer.id,
                "name": layer.name,
                "paper_label": layer.paper_label,
                "colour": layer.colour,
                "distance_mm": layer.distance_mm,
                "inter_object_depth_mm": layer.distance_mm - focus,
                "inter_image_depth_mm": estimate.inter_image_depth_mm,
                "disparity_px": optics.disparity_px(layer.distance_mm),
                "blur_diameter_px": optics.blur_diameter_px(layer.distance_mm),
                "slant": slant,
                "occludes": sorted(occluders[layer.id]),
                "order": distinct.index(round(layer.distance_mm, 6)),
                "visible_px": visible[layer.id],
            }
        )
    background = None
    if scene.background is not None:
        b = scene.background
        background = {
            "id": 0,
            "name": b.name,
            "colour": b.colour,
            "distance_mm": b.distance_mm,
            "inter_object_depth_mm": b.distance_mm - focus,
            "disparity_px": optics.disparity_px(b.distance_mm),
        }
    return {
        "scene": scene.name,
        "description": scene.description,
        "focus_distance_mm": focus,
        "optics": optics.truth(),
        "objects": objects,
        "background": background,
    }
