"""What the accurate-depth pipeline returns, and the recorder interface its stages report to."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from mca.processing.chromatic import NO_LATERAL_COLOUR, LateralColour


class Recorder(Protocol):
    """Receives what each stage computed; the application turns it into a rerun recording.

    `stage` names the stage ("planes", "disparity", "sketch", "depth", "mpi", "all_in_focus", ...);
    `items` are arrays and numbers named with units (e.g. disparity_px=..., confidence=...).
    Processing never imports rerun: it only calls these two methods.
    """

    def record(self, stage: str, **items: Any) -> None: ...

    def timing(self, stage: str, seconds: float) -> None: ...


class NullRecorder:
    """A recorder that keeps nothing."""

    def record(self, stage: str, **items: Any) -> None:
        return None

    def timing(self, stage: str, seconds: float) -> None:
        return None


@dataclass
class Region:
    """One region of the 2.1D sketch: an object of the scene, with its depth."""

    id: int  # label value in `DepthResult.labels` (1..L)
    pixels: int  # area in processing pixels
    order: int  # front-to-back rank, 0 = nearest
    occludes: list[int]  # ids of regions this one occludes
    disparity_px: float  # in input-image pixels, widest filter pair, + = farther
    inter_image_depth_mm: float | None = None  # eq. 2
    inter_object_depth_mm: float | None = None  # eq. 13/14, from the focus plane
    distance_mm: float | None = None  # from the lens
    slant: tuple[float, float, float] | None = None  # disparity plane a*x + b*y + c (input px coordinates)
    in_focus: bool = False
    confidence: float = 0.0


class MultiPlaneImage:
    """One RGBA plane of the 3D images: the perception image at Δd, the accurate image at ΔD.

    `rgba` is (H, W, 4) float32 in [0, 1], premultiplied. The pipeline builds it lazily from the shared
    display image and label map (`source`), so that L planes do not hold L full-size RGBA copies.
    """

    def __init__(
        self,
        region_id: int,
        rgba: np.ndarray | None,
        inter_image_depth_mm: float | None,
        inter_object_depth_mm: float | None,
        disparity_px: float,
        *,
        source: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        if rgba is None and source is None:
            raise ValueError("a MultiPlaneImage needs its rgba array or a (display image, labels) source")
        self.region_id = region_id
        self._rgba = rgba
        self._source = source
        self.inter_image_depth_mm = inter_image_depth_mm
        self.inter_object_depth_mm = inter_object_depth_mm
        self.disparity_px = disparity_px

    @property
    def rgba(self) -> np.ndarray:
        if self._rgba is not None:
            return self._rgba
        display, labels = self._source  # type: ignore[misc]
        alpha = (labels == self.region_id).astype(np.float32)
        rgba = np.empty(labels.shape + (4,), np.float32)
        np.multiply(display, alpha[..., None], out=rgba[..., :3])
        rgba[..., 3] = alpha
        return rgba

    @property
    def lazy_source(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(display image, labels) when `rgba` is built on demand as display x mask with alpha = mask
        (mask = labels == region_id), so that a caller can convert just the part it needs; else None."""
        return self._source if self._rgba is None else None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self._rgba.shape[:2]) if self._rgba is not None else tuple(self._source[1].shape)  # type: ignore

    def __repr__(self) -> str:
        return (
            f"MultiPlaneImage(region_id={self.region_id}, shape={self.shape}, "
            f"inter_object_depth_mm={self.inter_object_depth_mm}, disparity_px={self.disparity_px})"
        )


@dataclass
class DepthResult:
    """Everything the pipeline computed for one capture, at processing resolution.

    `pixel_scale` is the number of input-image pixels per processing pixel (2 for Bayer
    planes taken at half resolution, 1 for RGB images): disparities are always reported
    in input-image pixels.
    """

    labels: np.ndarray  # (H, W) uint16, 0 = none
    disparity_px: np.ndarray  # (H, W) float32, region model, input px
    raw_disparity_px: np.ndarray  # (H, W) float32, per-pixel estimate, input px
    confidence: np.ndarray  # (H, W) float32 in [0, 1]
    depth_mm: np.ndarray | None  # (H, W) float32 distance from the lens, NaN unknown
    all_in_focus: np.ndarray  # (H, W, 3) float32 linear RGB, fringes removed
    regions: list[Region]
    focus_region: int | None
    layers: list[MultiPlaneImage]
    pixel_scale: float = 1.0
    timings_s: dict[str, float] = field(default_factory=dict)
    lateral_colour: LateralColour = NO_LATERAL_COLOUR  # what `processing.chromatic` measured and took out
