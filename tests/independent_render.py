"""An MCA renderer written apart from `mca`'s own simulator, for tests that check the pipeline on renders made
by other code (the appliance is judged on scenes rendered by code it never saw).

It imports nothing of `mca`: the profile is read with `tomllib`, and the optics are derived here from the thin
lens, not taken from `processing.optics`. What it shares with the project is only the profile's meaning and the
sign convention (red-blue disparity + = farther than focus). Its method differs from `mca simulate`'s on
purpose: spatial disc kernels made of pixel-integrated Gaussians, hard depth slices composited with "over",
hidden background continued with the nearest farther colour, its own sensor noise.

Geometry, seen from behind the camera (x right, y up), the lens at the origin, the sensor at s behind it: a
point at distance Z focuses at v = 1 / (1/f - 1/Z), and a ray through aperture point a meets the sensor at the
chief ray's point + a (1 - s/v). The image on the sensor is upside down, so in the picture (row 0 at the top,
column 0 at the left of the scene) a filter centred at (px, py) mm moves its image by
(px, -py) (s/v - 1) / pitch pixels, and each channel sees a disc of diameter d_filter |s/v - 1| / pitch
centred there. The red-blue disparity is d_rb (s/v - 1) / pitch (the paper's eq. 11 for the image plane)."""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage
from scipy.special import erf

CHANNELS = ("red", "green", "blue")
BLACK_DN, WHITE_DN, FULL_WELL_E_ISO100, READ_NOISE_E = 2048, 15000, 26000.0, 3.0
ANTI_ALIAS_SIGMA_PX = 0.35  # the lens' and sensor's own blur in focus


@dataclass(frozen=True)
class Optics:
    """The thin lens focused at `focus_mm`, with the profile's filters, pixels of `pitch_mm`."""

    focal_mm: float
    focus_mm: float
    pitch_mm: float
    filters_mm: dict[str, tuple[float, float]]
    filter_diameter_mm: float

    @classmethod
    def from_profile(cls, path: Path, focus_mm: float, pitch_mm: float) -> Optics:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        aperture = data["aperture"]
        return cls(
            float(data["lens"]["focal_length_mm"]),
            focus_mm,
            pitch_mm,
            {c: (float(aperture[c][0]), float(aperture[c][1])) for c in CHANNELS},
            float(aperture["filter_diameter_mm"]),
        )

    @property
    def sensor_mm(self) -> float:
        return 1.0 / (1.0 / self.focal_mm - 1.0 / self.focus_mm)

    def defocus(self, distance_mm: np.ndarray | float) -> np.ndarray | float:
        """s / v - 1: + behind the focus plane, - before it."""
        return self.sensor_mm * (1.0 / self.focal_mm - 1.0 / np.asarray(distance_mm, np.float64)) - 1.0

    def red_blue_px(self, distance_mm: np.ndarray | float) -> np.ndarray | float:
        baseline = self.filters_mm["red"][0] - self.filters_mm["blue"][0]
        return baseline * self.defocus(distance_mm) / self.pitch_mm

    def shift_px(self, channel: str, red_blue_px: float) -> tuple[float, float]:
        """(columns, rows) a channel's image moves at a red-blue disparity."""
        baseline = self.filters_mm["red"][0] - self.filters_mm["blue"][0]
        px, py = self.filters_mm[channel]
        return px * red_blue_px / baseline, -py * red_blue_px / baseline

    def disc_radius_px(self, red_blue_px: float) -> float:
        baseline = self.filters_mm["red"][0] - self.filters_mm["blue"][0]
        return 0.5 * self.filter_diameter_mm * abs(red_blue_px) / baseline


def srgb_to_linear(image_u8: np.ndarray) -> np.ndarray:
    c = image_u8.astype(np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _pixel_gaussians(centres: np.ndarray, sigma: float, half: int) -> np.ndarray:
    """(n, 2 half + 1): a Gaussian of `sigma` at each centre, integrated over the pixels -half..half."""
    i = np.arange(-half, half + 1, dtype=np.float64)
    scale = sigma * math.sqrt(2.0)
    return 0.5 * (erf((i[None] + 0.5 - centres[:, None]) / scale) - erf((i[None] - 0.5 - centres[:, None]) / scale))


def disc_kernel(centre_px: tuple[float, float], radius_px: float, sigma_px: float) -> np.ndarray:
    """A uniform disc of `radius_px` centred at (columns, rows) `centre_px`, seen through pixel-integrated
    Gaussians of `sigma_px`; the kernel's middle element is offset 0, its sum 1."""
    cx, cy = centre_px
    half = int(math.ceil(max(abs(cx), abs(cy)) + radius_px + 4.0 * sigma_px + 1.0))
    if radius_px < 0.02:
        points = np.array([[cx, cy]])
    else:
        step = radius_px / 12.0
        t = np.arange(-12, 13) * step
        xx, yy = np.meshgrid(t, t)
        inside = xx**2 + yy**2 <= radius_px**2
        points = np.stack([xx[inside] + cx, yy[inside] + cy], axis=1)
    kernel = _pixel_gaussians(points[:, 1], sigma_px, half).T @ _pixel_gaussians(points[:, 0], sigma_px, half)
    return (kernel / kernel.sum()).astype(np.float32)


def render(
    linear: np.ndarray,
    red_blue_px: np.ndarray,
    optics: Optics,
    step_px: float = 0.05,
    supersample: int = 1,
    sigma_px: float = ANTI_ALIAS_SIGMA_PX,
    same_surface_px: float = 1.0,
) -> np.ndarray:
    """(H, W, 3) linear scene radiance and its (H, W) red-blue disparity (finite everywhere) -> what each
    channel's pixels receive through its filter, (H, W, 3) float32.

    The scene is cut into slices `step_px` of disparity apart, composited far to near with "over", each slice's
    premultiplied colour and coverage convolved with each channel's shifted disc. A slice reaches on under the
    nearer pixels as far as the channels' shifts and discs can show them: there its colour is that of the
    nearest pixel at least `same_surface_px` farther (the background an occluder hides). `sigma_px`: the lens' and sensor's
    own blur in focus (a Gaussian).

    Each scene pixel is a point, and a point's image on a grid of pixels is pulled toward the pixel centres when
    the kernel is narrow (its centroid 0.127 px off the grid where it should be 0.150, at sigma 0.35 px): at small
    disparities the image moves less than its truth says. `supersample` n renders on a grid n times finer (the
    scene enlarged with cubic interpolation, each pixel 1/n as wide) and averages n x n blocks, which takes most
    of that error out at n^2 times the work (docs/evaluation.md, thirteenth stop)."""
    if supersample > 1:
        h, w = red_blue_px.shape
        size = (w * supersample, h * supersample)
        fine = render(
            np.clip(cv2.resize(linear.astype(np.float32), size, interpolation=cv2.INTER_CUBIC), 0.0, None),
            cv2.resize(red_blue_px.astype(np.float32), size, interpolation=cv2.INTER_NEAREST) * supersample,
            replace(optics, pitch_mm=optics.pitch_mm / supersample),
            step_px * supersample,
            sigma_px=sigma_px * supersample,
            same_surface_px=same_surface_px * supersample,
        )
        return cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)
    h, w = red_blue_px.shape
    low, high = float(red_blue_px.min()), float(red_blue_px.max())
    largest = max(abs(low), abs(high))
    blur = optics.disc_radius_px(largest)
    reach_all = 0.5 * (high - low) + blur + 3.0
    pad = int(math.ceil(reach_all + 0.5 * largest + blur + 4.0 * sigma_px + 4.0))
    scene = cv2.copyMakeBorder(linear.astype(np.float32), pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
    depth = cv2.copyMakeBorder(red_blue_px.astype(np.float32), pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
    level = np.rint((depth - low) / step_px).astype(np.int32)
    out = np.zeros(scene.shape, np.float32)
    for k in np.unique(level)[::-1]:  # farthest first
        d = low + k * step_px
        ys, xs = np.nonzero(level == k)
        kernels = [
            disc_kernel(optics.shift_px(c, d), optics.disc_radius_px(d), sigma_px)[::-1, ::-1].copy() for c in CHANNELS
        ]
        reach = 0.5 * (d - low) + blur + 3.0
        margin = int(math.ceil(reach)) + max(k_.shape[0] for k_ in kernels) // 2 + 1
        y0, y1 = max(ys.min() - margin, 0), min(ys.max() + margin + 1, depth.shape[0])
        x0, x1 = max(xs.min() - margin, 0), min(xs.max() + margin + 1, depth.shape[1])
        own = level[y0:y1, x0:x1] == k
        local = depth[y0:y1, x0:x1]
        distance = cv2.distanceTransform((~own).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        under = (distance <= reach) & (local < d - step_px / 2)
        colour = scene[y0:y1, x0:x1]
        if under.any():
            behind = depth >= d - same_surface_px
            if not behind.all():
                _, (iy, ix) = ndimage.distance_transform_edt(~behind[y0:y1, x0:x1], return_indices=True)
                colour = colour[iy, ix]
        alpha = (own | under).astype(np.float32)
        for ci, kernel in enumerate(kernels):  # filter2D correlates: the kernels are flipped for a convolution
            cover = cv2.filter2D(alpha, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)
            light = cv2.filter2D(
                np.ascontiguousarray(colour[..., ci] * alpha), cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT
            )
            out[y0:y1, x0:x1, ci] = light + (1.0 - cover) * out[y0:y1, x0:x1, ci]
    return out[pad : pad + h, pad : pad + w]


def expose(
    image: np.ndarray,
    iso: float,
    white_fraction: float,
    seed: int,
    *,
    black_dn: int = BLACK_DN,
    white_dn: int = WHITE_DN,
    bits: int = 14,
    full_well_e_iso100: float = FULL_WELL_E_ISO100,
    read_noise_e: float = READ_NOISE_E,
    adc_noise_dn: float = 0.0,
    noise: bool = True,
) -> np.ndarray:
    """Linear light -> a 16-bit linear TIFF's samples ((DN - black) / (white - black) of 65535) of a sensor of
    `bits` bits: linear 1 reaches `white_fraction` of white - black, the full well is `full_well_e_iso100` x
    100 / `iso` electrons; Poisson photon noise, Gaussian read noise (electrons) and converter noise (DN), none
    without `noise`. Samples below the black level are 0."""
    full_well_e = full_well_e_iso100 * 100.0 / iso
    mean_e = np.clip(image, 0.0, None) * white_fraction * full_well_e
    if noise:
        rng = np.random.default_rng(seed)
        electrons = rng.poisson(mean_e).astype(np.float64) + rng.normal(0.0, read_noise_e, mean_e.shape)
        dn = black_dn + electrons * (white_dn - black_dn) / full_well_e
        if adc_noise_dn > 0:
            dn = dn + rng.normal(0.0, adc_noise_dn, mean_e.shape)
    else:
        dn = black_dn + mean_e * (white_dn - black_dn) / full_well_e
    dn = np.clip(np.rint(dn), black_dn, min(white_dn, 2**bits - 1))
    return np.rint((dn - black_dn) / (white_dn - black_dn) * 65535.0).astype(np.uint16)


def fill_farthest(inverse_mm: np.ndarray) -> np.ndarray:
    """Unknown (NaN) pixels of an inverse-distance map, mostly hidden background, take the smallest inverse distance
    (the farthest point) among their known 5x5 neighbours, growing inwards until every pixel has one."""
    filled = np.where(np.isfinite(inverse_mm), inverse_mm, np.inf)
    while np.isinf(filled).any():
        grown = -cv2.dilate(-filled, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)
        filled = np.where(np.isinf(filled) & np.isfinite(grown), grown, filled)
    return filled


def profile_text(
    original: str, name: str, pitch_mm: float, size: tuple[int, int], sensor_mm: float | None = None
) -> str:
    """A profile TOML's text with another name, pixel pitch and sensor size (width, height) in px, and the lens'
    sensor distance when `sensor_mm` is given (a render's profile: `mca process` then needs no assumed pitch)."""
    values = {
        "name": f'"{name}"',
        "pixel_pitch_mm": repr(pitch_mm),
        "width_px": str(size[0]),
        "height_px": str(size[1]),
    }
    if sensor_mm is not None:
        values["sensor_distance_mm"] = repr(sensor_mm)
    lines = []
    for line in original.splitlines():
        key = line.split("=")[0].strip() if "=" in line and not line.lstrip().startswith("#") else ""
        lines.append(f"{key} = {values[key]}" if key in values else line)
    return "\n".join(lines) + "\n"
