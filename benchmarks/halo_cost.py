"""Whose are the halos? Beside occluding edges, is the far side occluded, or does the cost itself prefer the near side?

    python benchmarks/halo_cost.py RENDERS [--names Moebius-s2,Art-s2] [--workers 2]

For each TIFF render under RENDERS (`mca simulate --from-rgbd[-tree]`, e.g. `--dev-set`'s `native/tuning/`) the
default pipeline runs in-process as `mca process` runs it (`capture.api.run_depth`, the render's own profile from
its truth/, the run kept by `pipeline.finished_run`). On the analysis grid it then takes:

- *halo* pixels: the dense disparity more than `HALO_ERROR_PX` nearer than the truth, with a truth more than
  `EDGE_JUMP_PX` nearer within `EDGE_REACH_PX` (the band beside an occluding edge that the near side spreads into);
- *right* pixels: the same edges' neighbourhood where the dense map is within `RIGHT_PX` of the truth.

Printed per render: the halo's share of the pixels; how many channels of each halo pixel are occluded at its true
disparity (the truth's own map forward-warped into each channel's view, the nearest surface winning: a channel's
sample there falls on a surface more than `OCCLUDED_PX` nearer, in px of the analysis grid; the other thresholds
are in input px); and, for halo and right pixels, how often the
colour-line cost (`cost.cost_at`, the pipeline's window, sampler and noise model) is lower at the true map than at
the dense map, at full size, at half size and for their sum. Halo pixels that are unoccluded and whose cost prefers
the dense map are the cost's own fattening, which no occlusion model mends (docs/evaluation.md, thirty-second stop).
Renders larger than the analysis grid are skipped. Prints figures only.
"""

from __future__ import annotations

import sys
from typing import Any

import cv2
import numpy as np

HALO_ERROR_PX = 2.0
EDGE_JUMP_PX = 5.0
EDGE_REACH_PX = 25
RIGHT_PX = 0.5
OCCLUDED_PX = 1.5


def near_edge(truth_px: np.ndarray, jump_px: float = EDGE_JUMP_PX, reach_px: int = EDGE_REACH_PX) -> np.ndarray:
    """Pixels with a truth more than `jump_px` nearer (smaller disparity) within `reach_px` (a square)."""
    filled = np.where(np.isfinite(truth_px), truth_px, np.float32(np.inf)).astype(np.float32)
    nearest = cv2.erode(filled, np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8))
    with np.errstate(invalid="ignore"):
        return np.isfinite(truth_px) & (truth_px - nearest > jump_px)


def halo_mask(dense_px: np.ndarray, truth_px: np.ndarray, edge: np.ndarray | None = None) -> np.ndarray:
    """Pixels beside a near edge whose dense disparity is more than `HALO_ERROR_PX` nearer than the truth."""
    edge = near_edge(truth_px) if edge is None else edge
    with np.errstate(invalid="ignore"):
        return edge & (dense_px - truth_px < -HALO_ERROR_PX)


def visible_disparity(disparity_px: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """(3, H, W): in each channel's view, the disparity of the nearest surface of `disparity_px` seen there (each
    pixel forward-warped by its channel shift to the four pixels around where it lands; +inf where none lands)."""
    h, w = disparity_px.shape
    out = np.full((3, h * w), np.inf, np.float32)
    ys, xs = np.mgrid[0:h, 0:w]
    d = disparity_px.ravel().astype(np.float32)
    known = np.isfinite(d)
    for c in range(3):
        tx = xs.ravel() + d * np.float32(shifts[c, 0])
        ty = ys.ravel() + d * np.float32(shifts[c, 1])
        x0, y0 = np.floor(tx), np.floor(ty)
        for dy in (0, 1):
            for dx in (0, 1):
                qx, qy = x0 + dx, y0 + dy
                inside = known & (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
                index = qy[inside].astype(np.int64) * w + qx[inside].astype(np.int64)
                np.minimum.at(out[c], index, d[inside])
    return out.reshape(3, h, w)


def occluded_channels(truth_px: np.ndarray, shifts: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """For each of `pixels` (a mask), how many channels' samples at its true disparity fall on a surface more than
    `OCCLUDED_PX` nearer, in the truth's own forward-warped views."""
    h, w = truth_px.shape
    seen = visible_disparity(truth_px, shifts)
    ys, xs = np.nonzero(pixels)
    d = truth_px[ys, xs]
    count = np.zeros(len(ys), np.int64)
    for c in range(3):
        qx = np.clip(xs + np.floor(d * shifts[c, 0] + 0.5).astype(np.int64), 0, w - 1)
        qy = np.clip(ys + np.floor(d * shifts[c, 1] + 0.5).astype(np.int64), 0, h - 1)
        count += seen[c, qy, qx] < d - OCCLUDED_PX
    return count


def score_render(image_path: str, truth_dir: str, truth: dict[str, Any]) -> dict[str, float] | str:
    """The halo's figures (%) for one render, or a sentence saying why it was skipped."""
    from mca.capture.rgbd_evaluation import run_kept
    from mca.processing.cost import channel_shifts, cost_at, cost_input

    kept = run_kept(image_path, truth_dir, truth)
    if isinstance(kept, str):
        return kept
    run, truth_px = kept.run, kept.truth_px
    # the masks in input px, where the thresholds are; the cost maps on the analysis grid, in its px
    dense_px = run.dense.disparity_px * np.float32(run.to_input)
    edge = near_edge(truth_px)
    halo = halo_mask(dense_px, truth_px, edge)
    with np.errstate(invalid="ignore"):
        right = edge & (np.abs(dense_px - truth_px) <= RIGHT_PX)
    truth_an = truth_px / np.float32(run.to_input)
    occluded = occluded_channels(truth_an, channel_shifts(run.aperture), halo)
    params = run.params.dense
    maps = np.stack([np.nan_to_num(truth_an), run.dense.disparity_px]).astype(np.float32)
    inputs = cost_input(run.small, params.noise_model)  # the run lets its own go after the refinement
    full = cost_at(inputs.stacked, run.aperture, maps, params.window_px, params.noise_floor, noise=inputs.noise)
    small = cv2.pyrDown(run.small)
    small_inputs = cost_input(small, params.noise_model)
    size = (small.shape[1], small.shape[0])
    small_maps = np.stack([cv2.resize(m, size, interpolation=cv2.INTER_NEAREST) / 2 for m in maps])
    half = cost_at(
        small_inputs.stacked, run.aperture, small_maps, params.window_px, params.noise_floor, noise=small_inputs.noise
    )
    shape = (truth_an.shape[1], truth_an.shape[0])
    half = np.stack([cv2.resize(v, shape, interpolation=cv2.INTER_LINEAR) for v in half])
    figures = {"halo": 100.0 * float(halo.mean())}
    count = max(len(occluded), 1)
    for n, name in ((0, "occ-0"), (1, "occ-1")):
        figures[name] = 100.0 * float(np.count_nonzero(occluded == n)) / count
    figures["occ-2+"] = 100.0 * float(np.count_nonzero(occluded >= 2)) / count
    for label, mask in (("halo", halo), ("right", right)):
        for cost_name, volume in (("full", full), ("half", half), ("sum", full + half)):
            cheaper = volume[0][mask] < volume[1][mask]
            figures[f"{label}:{cost_name}"] = 100.0 * float(cheaper.mean()) if cheaper.size else float("nan")
    return figures


COLUMNS = (
    "halo",
    "occ-0",
    "occ-1",
    "occ-2+",
    "halo:full",
    "halo:half",
    "halo:sum",
    "right:full",
    "right:half",
    "right:sum",
)


def main(argv: list[str] | None = None) -> int:
    from mca.capture.rgbd_evaluation import print_scores, score_renders

    pairs = score_renders(score_render, argv, __doc__.split("\n")[0])
    print("halo: share of the pixels; occ-n: halo pixels with n channels occluded at the truth; x:cost: pixels of x")
    print("whose cost is lower at the true map than at the dense map (all in %)")
    scored = print_scores(pairs, COLUMNS, 10)
    if scored:
        print(f"{'median':28s} " + " ".join(f"{np.nanmedian([o[c] for o in scored]):10.1f}" for c in COLUMNS))
    return 0 if scored or not pairs else 1


if __name__ == "__main__":
    sys.exit(main())
