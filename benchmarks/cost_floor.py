"""How close to the truth is the colour-line cost's own minimum? The floor under every optimiser of that cost.

    python benchmarks/cost_floor.py RENDERS [--names Art-s1,Cones-s1] [--cell 32]
    python benchmarks/cost_floor.py --photograph ../shared/data/middlebury/Art/im.png [--grey]

For each TIFF render of RENDERS (`mca simulate --from-rgbd`, or the twins of `benchmarks/independent_twins.py`)
the raw colour-line cost the refinement measures (`processing.cost.cost_at`: 9x9 windows, the capture's own
noise model, bilinear sampling) is evaluated at the TRUE disparity plus offsets of -0.6 .. +0.6 px in 0.15 px
steps, summed over each `--cell` square with the refinement's weights (texture times the signal weight of the
channel with the second most signal), and the parabola through the lowest sum gives the cell's minimum. Cells
with unknown truth, a depth edge inside (true disparity spread over 0.3 px) or no interior minimum are left out.

Printed per render: the cells' minimum offset from the truth (median, median and 75th percentile of its size,
share beyond 0.3 px). A pipeline that found each cell's cost minimum exactly would still be off by this much; a
relative depth error of that offset over the scene's typical |disparity| follows from it (docs/evaluation.md,
fifteenth stop). Renders larger than the pipeline's analysis grid (1400 px) are skipped: the pipeline would
measure them reduced.

`--photograph IMAGE`: no render folder; the photograph (8-bit sRGB, resized to 1368 px wide) is rendered as one
fronto-parallel plane at +2 and +5 px by `tests/independent_render.py` (no code shared with `mca simulate`),
without sensor noise, with `devices/profiles/paper-70d.toml`'s filters, and measured the same way (the cost without a
noise model). `--grey` first makes the photograph grey (every channel its mean), so that its channels are one
line: what is left then is the cost's sampling alone.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def cell_minima(
    planes: np.ndarray, aperture, truth_px: np.ndarray, cell_px: int, noise_model: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """(minima, kept): per cell (row-major over the image) the cost minimum's offset from the truth and whether
    the cell counts (see the module docstring)."""
    from mca.processing.cost import cost_at, cost_input
    from mca.processing.refine import RefineParams, _parabola_minima

    refine = RefineParams()
    inputs = cost_input(np.ascontiguousarray(planes, np.float32), noise_model)
    known = np.isfinite(truth_px)
    filled = np.where(known, truth_px, np.nanmedian(truth_px)).astype(np.float32)
    offsets = np.arange(-0.6, 0.6001, 0.15)
    maps = np.stack([filled + np.float32(o) for o in offsets])
    costs = cost_at(inputs.stacked, aperture, maps, refine.window_px, refine.noise_floor, noise=inputs.noise)
    weight = inputs.texture_energy(refine.window_px)
    if inputs.noise is not None:
        weight = weight * inputs.signal_weight(refine.window_px, refine.half_weight_snr, refine.signal_channels)
    h, w = truth_px.shape
    cells_x = (w + cell_px - 1) // cell_px
    cell = ((np.arange(h)[:, None] // cell_px) * cells_x + np.arange(w)[None, :] // cell_px).ravel()
    n = int(cell.max()) + 1
    votes = np.where(known, weight, 0.0).astype(np.float64).ravel()
    sums = np.stack([np.bincount(cell, c.ravel() * votes, n) for c in costs], axis=1)
    minima, curvature = _parabola_minima(sums, offsets)
    count = np.bincount(cell, known.ravel(), n)
    values = np.where(known, truth_px, 0.0).ravel().astype(np.float64)
    mean = np.bincount(cell, values, n) / np.maximum(count, 1)
    spread = np.sqrt(np.maximum(np.bincount(cell, values**2, n) / np.maximum(count, 1) - mean**2, 0.0))
    kept = (count > 0.9 * cell_px * cell_px) & (curvature > 0) & (spread < 0.3)
    return minima, kept


def photograph_floor(image: str, grey: bool, cell_px: int) -> None:
    """The floor on a noise-free plane of one photograph (see the module docstring)."""
    from pathlib import Path

    import cv2

    repo = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(repo / "tests"))
    from independent_render import Optics, render, srgb_to_linear

    from mca.capture.simulated_shots import sensor_width_mm
    from mca.devices.profiles import load_profile_file

    profile_path = repo / "devices" / "profiles" / "paper-70d.toml"
    profile = load_profile_file(profile_path)
    width = 1368  # the development set's renders: the whole sensor width in this many pixels
    # the pitch as `mca process` takes it for those renders; the focus distance only places the plane, whose
    # disparity is given below
    optics = Optics.from_profile(profile_path, 1200.0, sensor_width_mm(profile) / width)
    picture = cv2.imread(image, cv2.IMREAD_COLOR)
    if picture is None:
        raise SystemExit(f"{image}: not an image OpenCV can read")
    linear = srgb_to_linear(picture[..., ::-1])
    linear = cv2.resize(linear, (width, round(width * linear.shape[0] / linear.shape[1])), interpolation=cv2.INTER_AREA)
    if grey:
        linear = np.repeat(linear.mean(axis=2, keepdims=True), 3, axis=2)
    for disparity_px in (2.0, 5.0):
        light = render(
            np.ascontiguousarray(linear, np.float32),
            np.full(linear.shape[:2], disparity_px, np.float32),
            optics,
            0.05,
            2,
        )
        planes = light[40:-40, 40:-40]  # away from the frame's replicated border
        truth = np.full(planes.shape[:2], disparity_px, np.float32)
        minima, kept = cell_minima(planes, profile.aperture, truth, cell_px, noise_model=False)
        size = np.abs(minima[kept])
        print(
            f"{Path(image).parent.name or image} {'grey' if grey else 'colour'} plane at {disparity_px:+.0f} px: "
            f"{kept.sum()} cells, median {np.median(minima[kept]):+.3f}, median |.| {np.median(size):.3f}, "
            f"p75 |.| {np.percentile(size, 75):.3f}, > 0.3 px {np.mean(size > 0.3):.0%}",
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("renders", nargs="?", help="a folder of renders with truth/ beside them")
    parser.add_argument("--photograph", help="instead: a photograph rendered as a noise-free plane")
    parser.add_argument("--grey", action="store_true", help="with --photograph: made grey first")
    parser.add_argument("--names", default="", help="only these renders (comma-separated)")
    parser.add_argument("--cell", type=int, default=32, help="side of the cells, px")
    args = parser.parse_args(argv)
    if args.photograph:
        photograph_floor(args.photograph, args.grey, args.cell)
        return 0
    if not args.renders:
        parser.error("give a render folder or --photograph")

    from mca.capture.api import read_input
    from mca.capture.rgbd_evaluation import _read_float_tiff, find_renders
    from mca.devices.profiles import load_profile_file

    wanted = {n for n in args.names.split(",") if n}
    print(f"{'render':<18} {'cells':>5} {'median':>7} {'med |.|':>7} {'p75 |.|':>7} {'> 0.3':>6}   (px)")
    for entry in find_renders(args.renders):
        if wanted and entry.name not in wanted:
            continue
        if entry.image_path.suffix.lower() not in (".tif", ".tiff"):
            print(f"{entry.name:<18} skipped: not a TIFF render (a raw's planes need the Bayer alignment)")
            continue
        truth = _read_float_tiff(entry.truth_file("disparity_px"))
        if max(truth.shape) > 1400:
            print(f"{entry.name:<18} skipped: {truth.shape[1]} px wide, over the analysis grid")
            continue
        profile = load_profile_file(entry.truth_file("profile"))
        planes = read_input(entry.image_path).planes
        minima, kept = cell_minima(planes, profile.aperture, truth, args.cell)
        m = minima[kept]
        if m.size == 0:
            print(f"{entry.name:<18} no cell counts")
            continue
        size = np.abs(m)
        print(
            f"{entry.name:<18} {m.size:>5} {np.median(m):>+7.3f} {np.median(size):>7.3f} "
            f"{np.percentile(size, 75):>7.3f} {np.mean(size > 0.3):>6.0%}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
