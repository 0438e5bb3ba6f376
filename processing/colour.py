"""Colour in one place: the sRGB transfer curve (IEC 61966-2-1), white balance and the camera-to-sRGB matrix.

Disparity is measured on the camera's own, unbalanced colour planes; only the images people
look at (all-in-focus, layers, 3D textures and colours, previews) go through `CameraColour`:
the as-shot white-balance gains, then a 3x3 matrix from white-balanced camera RGB to linear
sRGB (D65), then the sRGB curve. The matrix is made the way dcraw and LibRaw make their
`rgb_cam` (from the camera's XYZ-to-camera matrix, `camera_to_srgb_from_xyz`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

# Linear sRGB (D65) to CIE XYZ, IEC 61966-2-1 (the matrix dcraw and LibRaw use).
SRGB_TO_XYZ_D65 = np.array(
    [
        [0.412453, 0.357580, 0.180423],
        [0.212671, 0.715160, 0.072169],
        [0.019334, 0.119193, 0.950227],
    ]
)
IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


# --- the sRGB curve ------------------------------------------------------------------------------------------------


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] to sRGB-encoded values in [0, 1] (IEC 61966-2-1), float32; clipped."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear light: c/12.92 up to 0.04045, else ((c+0.055)/1.055)^2.4; float32."""
    c = np.asarray(encoded, dtype=np.float32)
    return np.where(
        c <= 0.04045, c / np.float32(12.92), np.power((c + np.float32(0.055)) / np.float32(1.055), np.float32(2.4))
    ).astype(np.float32)


@functools.lru_cache(maxsize=1)
def _srgb8_table() -> np.ndarray:
    """8-bit sRGB of linear values k / 65535."""
    return np.round(srgb_encode(np.arange(65536, dtype=np.float64) / 65535.0).astype(np.float64) * 255.0).astype(
        np.uint8
    )


SRGB_CHUNK_VALUES = 1 << 18  # values converted per pass: the temporaries stay in cache, none is full size


def linear_to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] to 8-bit sRGB (through a 16-bit table); clipped, NaN as 0."""
    x = np.asarray(linear, dtype=np.float32)
    flat = x.reshape(-1)
    out = np.empty(flat.shape, np.uint8)
    table = _srgb8_table()
    scaled = np.empty(min(flat.size, SRGB_CHUNK_VALUES), np.float32)
    index = np.empty(scaled.shape, np.uint16)
    for start in range(0, flat.size, SRGB_CHUNK_VALUES):
        part = flat[start : start + SRGB_CHUNK_VALUES]
        s, i = scaled[: part.size], index[: part.size]
        np.fmax(part, np.float32(0.0), out=s)  # fmax/fmin drop NaN: NaN and -inf to 0, +inf to 1
        np.fmin(s, np.float32(1.0), out=s)
        np.multiply(s, np.float32(65535.0), out=s)
        np.add(s, np.float32(0.5), out=s)
        np.copyto(i, s, casting="unsafe")  # truncation: round half up
        np.take(table, i, out=out[start : start + part.size])
    return out.reshape(x.shape)


# --- camera colour -------------------------------------------------------------------------------------------------


def camera_to_srgb_from_xyz(xyz_to_camera: np.ndarray) -> np.ndarray:
    """The 3x3 matrix from white-balanced camera RGB to linear sRGB, given the camera's XYZ-to-camera matrix.

    As dcraw's `cam_xyz_coeff`: camera-from-sRGB = xyz_to_camera @ SRGB_TO_XYZ_D65, each row scaled
    to sum 1 (so that a white-balanced white stays white), then inverted.
    """
    camera_from_srgb = np.asarray(xyz_to_camera, dtype=np.float64).reshape(3, 3) @ SRGB_TO_XYZ_D65
    sums = camera_from_srgb.sum(axis=1, keepdims=True)
    if np.any(np.abs(sums) < 1e-9):
        raise ValueError("the XYZ-to-camera matrix maps white to zero in a channel")
    return np.linalg.inv(camera_from_srgb / sums)


@dataclass(frozen=True)
class CameraColour:
    """How the camera's linear RGB becomes linear sRGB for display: white-balance gains, then a 3x3 matrix.

    `source` says where the numbers came from, e.g. "as shot (Canon EOS 70D)" or what was assumed.
    """

    wb_gains: tuple[float, float, float] = (1.0, 1.0, 1.0)  # multipliers of R, G, B (G = 1)
    camera_to_srgb: tuple[tuple[float, float, float], ...] = IDENTITY  # rows: sRGB R, G, B from camera R, G, B
    source: str = "assumed: the pixels are linear sRGB, already white-balanced"

    @property
    def is_identity(self) -> bool:
        return self.wb_gains == (1.0, 1.0, 1.0) and np.allclose(self.camera_to_srgb, IDENTITY)

    def matrix(self) -> np.ndarray:
        """The whole linear step as one 3x3 matrix: camera_to_srgb @ diag(wb_gains)."""
        return np.asarray(self.camera_to_srgb, dtype=np.float64) @ np.diag(self.wb_gains)

    def to_srgb_linear(self, camera_rgb: np.ndarray) -> np.ndarray:
        """(..., 3) linear camera RGB to linear sRGB, float32 (not clipped: highlights may exceed 1)."""
        rgb = np.asarray(camera_rgb, dtype=np.float32)
        if self.is_identity:
            return rgb
        return np.matmul(rgb, self.matrix().T.astype(np.float32))

    def to_srgb8(self, camera_rgb: np.ndarray) -> np.ndarray:
        """(..., 3) linear camera RGB to 8-bit sRGB for display."""
        return linear_to_srgb8(self.to_srgb_linear(camera_rgb))

    def as_dict(self) -> dict[str, object]:
        """For result.json: the gains, the matrix and where they came from."""
        return {
            "white_balance_gains_rgb": [float(g) for g in self.wb_gains],
            "camera_to_srgb_matrix": [[float(v) for v in row] for row in self.camera_to_srgb],
            "source": self.source,
        }


def camera_colour(
    wb_multipliers: tuple[float, ...] | None, xyz_to_camera: np.ndarray | None, who: str = "the camera"
) -> CameraColour:
    """A `CameraColour` from what a raw file says: as-shot multipliers (R, G, B[, G2]) and XYZ-to-camera matrix.

    Missing or unusable parts are replaced by the identity, and `source` says so.
    """
    gains: tuple[float, float, float] = (1.0, 1.0, 1.0)
    notes = []
    if wb_multipliers is not None and len(wb_multipliers) >= 3 and all(np.isfinite(wb_multipliers[:3])):
        r, g, b = (float(v) for v in wb_multipliers[:3])
        if r > 0 and g > 0 and b > 0:
            gains = (r / g, 1.0, b / g)
            notes.append("as-shot white balance")
    if not notes:
        notes.append("no as-shot white balance (gains 1)")
    matrix: tuple[tuple[float, float, float], ...] = IDENTITY
    if xyz_to_camera is not None:
        m = np.asarray(xyz_to_camera, dtype=np.float64)[:3, :3]
        if m.shape == (3, 3) and np.isfinite(m).all() and np.abs(m).sum() > 0:
            try:
                inverse = camera_to_srgb_from_xyz(m)
                matrix = tuple((float(row[0]), float(row[1]), float(row[2])) for row in inverse)
                notes.append("colour matrix")
            except (ValueError, np.linalg.LinAlgError):
                pass
    if "colour matrix" not in notes:
        notes.append("no colour matrix (camera RGB shown as sRGB)")
    return CameraColour(gains, matrix, f"{who}: " + ", ".join(notes))
