"""SLIC superpixels (Achanta et al. 2012) as scikit-image computes them, on both cores.

The superpixels stage spent 1.5-1.9 s of a 20 MP capture in `skimage.segmentation.slic`, whose k-means loop is
single-threaded and holds the GIL. This module computes the same labels, value for value, for the way the
pipeline calls it (an RGB image, grid seeds, no mask, no smoothing, SLIC not SLIC-zero, connectivity enforced):
`tests/test_slic.py` compares the two label maps pixel for pixel. The preparation stays scikit-image's own
(`rgb2lab`, `regular_grid`); the three loops are ours:

1. Assignment. Every cluster k, in order, offers itself to the pixels of its window (two grid steps either
   side of its centre) at the distance (squared position distance / step^2 + squared Lab distance /
   compactness^2); a pixel takes it when strictly nearer than the best so far. Here the image is cut into
   bands of rows, and each band goes through the clusters whose window reaches it, in the same order: every
   pixel sees the same offers in the same order, so it ends with the same cluster, and the bands run in
   parallel. The arithmetic is single precision when the image is, as scikit-image's (no fast-math: the
   operations and their order are the same, so the values are too).
2. Update. Each cluster's centre becomes the mean position and colour of its pixels, summed in raster order
   (serial, as a different order would round differently).
3. Connectivity. Pieces of a label that are not connected to it become labels of their own; pieces smaller
   than half the mean superpixel size join the last differently labelled neighbour their breadth-first search
   met (serial: it depends on the raster order).
"""

from __future__ import annotations

import numba as nb
import numpy as np

_BAND_ROWS = 16  # rows per band of the parallel assignment


@nb.njit(cache=True, parallel=True)
def _assign(
    image: np.ndarray,
    segments: np.ndarray,
    step_y: int,
    step_x: int,
    spatial_weight: np.float32,
    labels: np.ndarray,
    distance: np.ndarray,
) -> None:
    """One assignment pass over the (3, H, W) Lab `image` (float32, scaled) with the (K, 6) cluster `segments`
    ([z, y, x, L, a, b]): `labels` (H, W) and `distance` (H, W) filled as the serial loop over k would."""
    _, h, w = image.shape
    n = segments.shape[0]
    bands = (h + _BAND_ROWS - 1) // _BAND_ROWS
    for band in nb.prange(bands):
        r0 = band * _BAND_ROWS
        r1 = min(r0 + _BAND_ROWS, h)
        for y in range(r0, r1):
            for x in range(w):
                distance[y, x] = np.float32(np.inf)
        for k in range(n):
            cy = segments[k, 1]
            cx = segments[k, 2]
            if not (cy == cy and cx == cx):
                continue  # an emptied cluster (NaN centre): every comparison with it fails, it takes no pixel
            # window bounds as scikit-image takes them: the float bound truncated towards zero
            y_min = int(max(cy - np.float32(2 * step_y), np.float32(0.0)))
            y_max = int(min(cy + np.float32(2 * step_y + 1), np.float32(h)))
            if y_max <= r0 or y_min >= r1:
                continue
            x_min = int(max(cx - np.float32(2 * step_x), np.float32(0.0)))
            x_max = int(min(cx + np.float32(2 * step_x + 1), np.float32(w)))
            cz = segments[k, 0]
            dz = cz - np.float32(0.0)
            dz = dz * dz
            l0, l1, l2 = segments[k, 3], segments[k, 4], segments[k, 5]
            for y in range(max(y_min, r0), min(y_max, r1)):
                dy = cy - np.float32(y)
                dy = dy * dy
                p0, p1, p2 = image[0, y], image[1, y], image[2, y]
                dist_row, label_row = distance[y], labels[y]
                for x in range(x_min, x_max):  # branch-free, so that the compiler vectorises it
                    dx = cx - np.float32(x)
                    dx = dx * dx
                    d = (dz + dy + dx) * spatial_weight
                    t0 = p0[x] - l0
                    t1 = p1[x] - l1
                    t2 = p2[x] - l2
                    colour = np.float32(0.0) + t0 * t0
                    colour = colour + t1 * t1
                    colour = colour + t2 * t2
                    d = d + colour
                    old = dist_row[x]
                    nearer = old > d
                    label_row[x] = np.int32(k) if nearer else label_row[x]
                    dist_row[x] = d if nearer else old


@nb.njit(cache=True, error_model="numpy")  # an empty cluster's mean is NaN (0 / 0), as in scikit-image
def _update(image: np.ndarray, labels: np.ndarray, segments: np.ndarray) -> None:
    """Each cluster's centre: the mean position and colour of its pixels, summed in raster order."""
    channels, h, w = image.shape
    n = segments.shape[0]
    count = np.zeros(n, np.int64)
    segments[:, :] = 0.0
    for y in range(h):
        for x in range(w):
            k = labels[y, x]
            count[k] += 1
            segments[k, 1] += np.float32(y)
            segments[k, 2] += np.float32(x)
            for c in range(channels):
                segments[k, 3 + c] += image[c, y, x]
    for k in range(n):
        for c in range(segments.shape[1]):
            segments[k, c] = segments[k, c] / np.float32(count[k])


@nb.njit(cache=True)
def _connected(labels: np.ndarray, min_size: int, max_size: int) -> np.ndarray:
    """Connected labels 0..: each 4-connected piece its own label, pieces under `min_size` given the label of
    the last differently labelled neighbour their search met; a search stops at `max_size` pixels."""
    h, w = labels.shape
    out = np.full((h, w), -1, np.int64)
    queue = np.empty((max(max_size, 1), 2), np.int64)
    step_y = np.array((0, 0, 1, -1))
    step_x = np.array((1, -1, 0, 0))
    current = 0
    for y in range(h):
        for x in range(w):
            if out[y, x] >= 0:
                continue
            adjacent = current
            label = labels[y, x]
            out[y, x] = current
            size = 1
            visited = 0
            queue[0, 0] = y
            queue[0, 1] = x
            while visited < size < max_size:
                for i in range(4):
                    yy = queue[visited, 0] + step_y[i]
                    xx = queue[visited, 1] + step_x[i]
                    if 0 <= xx < w and 0 <= yy < h:
                        if labels[yy, xx] == label and out[yy, xx] < 0:
                            out[yy, xx] = current
                            queue[size, 0] = yy
                            queue[size, 1] = xx
                            size += 1
                            if size >= max_size:
                                break
                        elif out[yy, xx] >= 0 and out[yy, xx] != current:
                            adjacent = out[yy, xx]
                visited += 1
            if size < min_size:
                for i in range(size):
                    out[queue[i, 0], queue[i, 1]] = adjacent
            else:
                current += 1
    return out


def slic_labels(image: np.ndarray, n_segments: int, compactness: float, iterations: int) -> np.ndarray:
    """(H, W) int64 labels 0..n-1, every one of them used, of an (H, W, 3) RGB float image in [0, 1]:
    scikit-image's `slic(image, n_segments, compactness, max_num_iter=iterations, start_label=0,
    channel_axis=-1)`."""
    from skimage.color import rgb2lab
    from skimage.util import regular_grid

    rgb = np.asarray(image)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"slic_labels needs an (H, W, 3) RGB image, not {rgb.shape}")
    if rgb.dtype != np.float32:
        # scikit-image's loop runs in the image's float type; ours in single precision only
        raise ValueError(f"slic_labels needs a float32 image, not {rgb.dtype}")
    h, w = rgb.shape[:2]
    rgb = rgb.astype(np.float32, copy=True)
    low, high = rgb.min(), rgb.max()
    if not (np.isfinite(low) and np.isfinite(high)):
        raise ValueError("slic_labels: the image has values that are not finite")
    rgb -= low  # stretched to [0, 1] first, as scikit-image does
    if high != low:
        rgb /= high - low
    lab = np.ascontiguousarray(np.moveaxis(rgb2lab(rgb) * (1.0 / compactness), -1, 0), dtype=np.float32)
    slices = regular_grid((1, h, w), n_segments)
    steps = [int(s.step) if s.step is not None else 1 for s in slices]
    float_steps = [float(s.step) if s.step is not None else 1.0 for s in slices]
    axes = [np.arange(n)[s] for n, s in zip((1, h, w), slices, strict=True)]  # the seeds' rows and columns
    centres = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    segments = np.zeros((centres.shape[0], 6), np.float32)
    segments[:, :3] = centres
    step = np.float32(max(float_steps))  # a C float in scikit-image's signature
    spatial_weight = np.float32(1.0 / float(step * step))
    labels = np.zeros((h, w), np.int32)
    distance = np.empty((h, w), np.float32)
    for i in range(iterations):
        _assign(lab, segments, steps[1], steps[2], spatial_weight, labels, distance)
        if i < iterations - 1:  # the last centres would move nothing
            _update(lab, labels, segments)
    segment_size = h * w / centres.shape[0]
    return _connected(labels, int(0.5 * segment_size), int(3 * segment_size))
