"""Surface textures for simulated scenes: photographs scikit-image ships, tiled and tinted into object colours.

The photographs come from `skimage.data` (bundled with scikit-image, a declared
dependency; nothing is downloaded and no user file is read). A texture is
defined in frame units (1 = the frame height) so that a scene looks the same,
up to resampling, at every render size.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

# Photographs in skimage.data that are part of the scikit-image wheel (no pooch download needed).
PHOTOGRAPHS = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "brick",
    "grass",
    "gravel",
    "camera",
    "moon",
    "coins",
    "text",
    "page",
    "clock",
    "hubble_deep_field",
    "immunohistochemistry",
    "retina",
    "cell",
)


@dataclass(frozen=True)
class Texture:
    """A photograph tiled (mirrored) over a surface, its luminance modulating the surface colour.

    `tile_height` is the height of one copy of the photograph in frame units (1 = frame height);
    `contrast` is the standard deviation of the relative modulation; `offset` shifts the tiling
    (frame units) so that two objects with the same photograph do not look identical.
    """

    photograph: str = "gravel"
    tile_height: float = 0.2
    contrast: float = 0.3
    offset: tuple[float, float] = (0.0, 0.0)


@functools.cache
def photograph_luminance(name: str) -> np.ndarray:
    """The named skimage.data photograph as float32 luminance, zero mean and unit standard deviation."""
    if name not in PHOTOGRAPHS:
        raise ValueError(f"unknown texture photograph '{name}'; choose one of {', '.join(PHOTOGRAPHS)}")
    import skimage.data

    image = np.asarray(getattr(skimage.data, name)())
    if image.ndim == 3:
        image = image[..., :3].astype(np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    image = image.astype(np.float32)
    std = float(image.std())
    result = (image - float(image.mean())) / (std if std > 0 else 1.0)
    result.setflags(write=False)
    return result


def texture_patch(
    texture: Texture, origin_px: tuple[float, float], shape: tuple[int, int], frame_height_px: float
) -> np.ndarray:
    """Relative modulation (around 1.0, float32, `shape`) of `texture` over a raster patch.

    `origin_px` is the (x, y) pixel position of the patch's top-left pixel in a raster whose
    frame height is `frame_height_px` pixels; the tiling is anchored to the frame, not the patch.
    """
    source = photograph_luminance(texture.photograph)
    tile_h = max(2, int(round(texture.tile_height * frame_height_px)))
    tile_w = max(2, int(round(tile_h * source.shape[1] / source.shape[0])))
    shrinking = tile_h < source.shape[0]
    tile = cv2.resize(source, (tile_w, tile_h), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC)
    # Mirror-tile a period of 2 tiles, then take the patch at its frame position modulo the period.
    period = np.block([[tile, tile[:, ::-1]], [tile[::-1, :], tile[::-1, ::-1]]])
    x0 = int(round(origin_px[0] + texture.offset[0] * frame_height_px)) % period.shape[1]
    y0 = int(round(origin_px[1] + texture.offset[1] * frame_height_px)) % period.shape[0]
    reps_y = -(-(y0 + shape[0]) // period.shape[0])
    reps_x = -(-(x0 + shape[1]) // period.shape[1])
    tiled = np.tile(period, (reps_y, reps_x))[y0 : y0 + shape[0], x0 : x0 + shape[1]]
    return np.clip(1.0 + texture.contrast * tiled, 0.05, 3.0).astype(np.float32)
