"""The optics of accurate depth: MCA disparity, inter-image depth, inter-object depth and distance (paper eqs. 2, 6, 8-14).

Sign convention, everywhere: positive means farther than the focus plane. A
farther object focuses in front of the sensor (its image plane lies a positive
inter-image depth Δd toward the lens) and shows each colour channel displaced
toward its filter's side in the displayed image; a nearer one the opposite way.

Symbols of the paper: δ disparity on the sensor (mm), d_a distance between the
centres of the two filters compared, d_ls lens-to-sensor distance, f focal
length, M = (d_ls - f)/f the magnification, Δd inter-image (image-side)
depth, ΔD inter-object (object-side) depth from the focus plane.

All functions accept floats or numpy arrays (elementwise); those marked `register_jitable` are also called
from compiled kernels (`processing.depth.depth_map_mm`), the same formulas per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numba.extending import register_jitable

from mca.processing.camera import CameraProfile

Value = TypeVar("Value", float, np.ndarray)


@register_jitable
def magnification(sensor_distance_mm: float, focal_length_mm: float) -> float:
    """M = (d_ls - f) / f, the lateral magnification at the focus plane (eq. 8)."""
    return (sensor_distance_mm - focal_length_mm) / focal_length_mm


@register_jitable
def inter_image_depth_mm(disparity_mm: Value, sensor_distance_mm: float, filter_centre_distance_mm: float) -> Value:
    """Δd = δ d_ls / (d_a + δ): image-side depth of a plane from its disparity (eq. 2)."""
    return disparity_mm * sensor_distance_mm / (filter_centre_distance_mm + disparity_mm)


def disparity_mm_from_inter_image_depth(
    inter_image_depth: Value, sensor_distance_mm: float, filter_centre_distance_mm: float
) -> Value:
    """δ = d_a Δd / (d_ls - Δd): disparity on the sensor of an image plane Δd in front of it (eq. 11)."""
    return filter_centre_distance_mm * inter_image_depth / (sensor_distance_mm - inter_image_depth)


def inter_object_depth_from_disparity_mm(
    disparity_mm: Value, sensor_distance_mm: float, focal_length_mm: float, filter_centre_distance_mm: float
) -> Value:
    """ΔD = d_ls δ / (M (M d_a - δ)): object-side depth straight from disparity (eq. 10)."""
    m = magnification(sensor_distance_mm, focal_length_mm)
    return sensor_distance_mm * disparity_mm / (m * (m * filter_centre_distance_mm - disparity_mm))


@register_jitable
def inter_object_depth_far_mm(inter_image_depth: Value, sensor_distance_mm: float, focal_length_mm: float) -> Value:
    """ΔD = Δd / (M² (1 - (M+1)/M · Δd/d_ls)) for an object beyond the focus plane, Δd >= 0 (eq. 13)."""
    m = magnification(sensor_distance_mm, focal_length_mm)
    return inter_image_depth / (m * m * (1.0 - (m + 1.0) / m * inter_image_depth / sensor_distance_mm))


@register_jitable
def inter_object_depth_near_mm(
    inter_image_depth_magnitude: Value, sensor_distance_mm: float, focal_length_mm: float
) -> Value:
    """|ΔD| = |Δd| / (M² (1 + (M+1)/M · |Δd|/d_ls)) for an object before the focus plane (eq. 14), magnitudes."""
    m = magnification(sensor_distance_mm, focal_length_mm)
    return inter_image_depth_magnitude / (
        m * m * (1.0 + (m + 1.0) / m * inter_image_depth_magnitude / sensor_distance_mm)
    )


def inter_object_depth_mm(inter_image_depth: Value, sensor_distance_mm: float, focal_length_mm: float) -> Value:
    """Signed ΔD from signed Δd: eq. 13 on the far side, eq. 14 (negated) on the near side."""
    depth = np.asarray(inter_image_depth, dtype=float)
    far = inter_object_depth_far_mm(np.maximum(depth, 0.0), sensor_distance_mm, focal_length_mm)
    near = -inter_object_depth_near_mm(np.maximum(-depth, 0.0), sensor_distance_mm, focal_length_mm)
    result = np.where(depth >= 0, far, near)
    return result if isinstance(inter_image_depth, np.ndarray) else float(result)  # type: ignore[return-value,unused-ignore]


def inter_image_depth_from_inter_object_depth_mm(
    inter_object_depth: Value, sensor_distance_mm: float, focal_length_mm: float
) -> Value:
    """Inverse of eqs. 13/14: Δd = M² ΔD / (1 + M (M+1) ΔD / d_ls), signed."""
    m = magnification(sensor_distance_mm, focal_length_mm)
    return m * m * inter_object_depth / (1.0 + m * (m + 1.0) * inter_object_depth / sensor_distance_mm)


# --- the exact thin-lens model, written from the Gaussian lens equation alone (eq. 6) -------------------------


def image_distance_mm(object_distance_mm: Value, focal_length_mm: float) -> Value:
    """v = f u / (u - f): where a point at distance u from the lens comes to focus (Gaussian lens equation)."""
    return focal_length_mm * object_distance_mm / (object_distance_mm - focal_length_mm)


def thin_lens_disparity_mm(
    object_distance_mm: Value, sensor_distance_mm: float, focal_length_mm: float, filter_centre_distance_mm: float
) -> Value:
    """Exact disparity on the sensor between two sub-aperture images of a point at `object_distance_mm`.

    Rays through two aperture points d_a apart converge at v and cross the sensor at d_ls
    d_a |d_ls - v| / v apart (similar triangles); positive when v < d_ls (object beyond focus).
    """
    v = image_distance_mm(object_distance_mm, focal_length_mm)
    return filter_centre_distance_mm * (sensor_distance_mm - v) / v


def thin_lens_distance_mm(
    disparity_mm: Value, sensor_distance_mm: float, focal_length_mm: float, filter_centre_distance_mm: float
) -> Value:
    """Exact object distance from the lens for a disparity on the sensor (inverse of `thin_lens_disparity_mm`)."""
    v = filter_centre_distance_mm * sensor_distance_mm / (filter_centre_distance_mm + disparity_mm)
    return focal_length_mm * v / (v - focal_length_mm)


@dataclass(frozen=True)
class DepthEstimate:
    """One point on the chain disparity -> inter-image depth -> inter-object depth -> distance."""

    disparity_px: float
    inter_image_depth_mm: float
    inter_object_depth_mm: float
    distance_mm: float


@dataclass(frozen=True)
class MCAOptics:
    """A profile's optics bound together: converts between the four depth quantities of the paper.

    Disparities are between the images of the widest filter pair, in pixels of pitch `pixel_pitch_mm`.
    """

    focal_length_mm: float
    sensor_distance_mm: float
    filter_centre_distance_mm: float
    pixel_pitch_mm: float

    @classmethod
    def from_profile(cls, profile: CameraProfile, pixel_pitch_mm: float | None = None) -> MCAOptics:
        if profile.lens is None:
            raise ValueError(
                f"profile '{profile.name}' has no [lens] section: only disparities in pixels are available"
            )
        pitch = pixel_pitch_mm if pixel_pitch_mm is not None else profile.pixel_pitch_mm
        if pitch is None:
            raise ValueError(f"profile '{profile.name}' has no camera.pixel_pitch_mm: cannot convert pixels to mm")
        return cls(profile.lens.focal_length_mm, profile.lens.sensor_distance_mm, profile.aperture.baseline_mm, pitch)

    @property
    def magnification(self) -> float:
        return magnification(self.sensor_distance_mm, self.focal_length_mm)

    @property
    def focus_distance_mm(self) -> float:
        f, d = self.focal_length_mm, self.sensor_distance_mm
        return f * d / (d - f)

    def inter_image_depth_mm(self, disparity_px: Value) -> Value:
        return inter_image_depth_mm(
            disparity_px * self.pixel_pitch_mm, self.sensor_distance_mm, self.filter_centre_distance_mm
        )

    def disparity_px(self, inter_image_depth: Value) -> Value:
        return (
            disparity_mm_from_inter_image_depth(
                inter_image_depth, self.sensor_distance_mm, self.filter_centre_distance_mm
            )
            / self.pixel_pitch_mm
        )

    def inter_object_depth_mm(self, inter_image_depth: Value) -> Value:
        return inter_object_depth_mm(inter_image_depth, self.sensor_distance_mm, self.focal_length_mm)

    def inter_image_depth_from_inter_object_mm(self, inter_object_depth: Value) -> Value:
        return inter_image_depth_from_inter_object_depth_mm(
            inter_object_depth, self.sensor_distance_mm, self.focal_length_mm
        )

    def distance_mm(self, disparity_px: Value) -> Value:
        """Distance from the lens for a disparity, via eqs. 2 and 13/14."""
        return self.focus_distance_mm + self.inter_object_depth_mm(self.inter_image_depth_mm(disparity_px))

    def disparity_px_at_distance(self, distance_mm: Value) -> Value:
        """Disparity of an object at `distance_mm`, by the exact thin-lens model."""
        return (
            thin_lens_disparity_mm(
                distance_mm, self.sensor_distance_mm, self.focal_length_mm, self.filter_centre_distance_mm
            )
            / self.pixel_pitch_mm
        )

    def from_disparity(self, disparity_px: float) -> DepthEstimate:
        image_depth = float(self.inter_image_depth_mm(disparity_px))
        object_depth = float(self.inter_object_depth_mm(image_depth))
        return DepthEstimate(float(disparity_px), image_depth, object_depth, self.focus_distance_mm + object_depth)

    def from_inter_image_depth(self, inter_image_depth: float) -> DepthEstimate:
        return self.from_disparity(float(self.disparity_px(inter_image_depth)))

    def from_distance(self, distance_mm: float) -> DepthEstimate:
        return self.from_disparity(float(self.disparity_px_at_distance(distance_mm)))
