"""Which stage loses the pixels? bad-1 of each stage's disparity on renders with known depth, beside the floors.

    python benchmarks/surface_floors.py RENDERS [--names Art-s2,Venus-s1] [--workers 2]

For each TIFF render under RENDERS (`mca simulate --from-rgbd[-tree]`, e.g. `--dev-set`'s `native/tuning/`) the
default pipeline runs in-process as `mca process` runs it (`capture.api.run_depth`, the render's own profile
from its truth/), its run kept (`pipeline.finished_run`) so that the stages' intermediate maps can be scored.
Printed per render, each the share of pixels more than 1 px of red-blue disparity off the truth (a missing value
counts as bad):

- `dense`: the dense search's per-pixel disparity (`processing.dense`), what the surfaces are fitted to;
- `own-fit`: every superpixel's own robust plane through the dense map (`surfaces.fit_planes`);
- `chosen`: the planes the surfaces' ICM chose, each superpixel among its own and its neighbours' within two
  rings (`surfaces.build_surfaces`);
- `final`: the depth map the pipeline writes, turned back into disparity (regions, refinement, boundaries);
- `best-cand`: a floor of the selection: every superpixel given, among the same candidate planes, the one
  with the fewest bad pixels against the truth (the truth picks; the candidates are the pipeline's);
- `sp-plane`: a floor of the segmentation: every superpixel given the plane fitted to the truth itself.

`chosen` far above `best-cand` means the right plane was among the candidates and the selection (its data
term, the dense map) took another; `best-cand` near `sp-plane` means the candidate set is not what limits.
Renders larger than the pipeline's analysis grid (1400 px) are skipped: the surfaces' grid would not be the
truth's. Prints figures only; docs/evaluation.md (thirty-first stop) gives them for the development set.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

STAGES = ("dense", "own-fit", "chosen", "final", "best-cand", "sp-plane")


def bad_1(estimate_px: np.ndarray, truth_px: np.ndarray) -> float:
    """Share (%) of the truth's known pixels whose estimate is more than 1 px off or missing."""
    known = np.isfinite(truth_px)
    error = np.abs(estimate_px[known] - truth_px[known])
    return 100.0 * float(np.mean(~(error <= 1.0)))


def best_candidates(surfaces: Any, truth_an: np.ndarray, to_input: float, rings: int, samples: int) -> np.ndarray:
    """(n, 3) per superpixel the candidate plane (its own fit or a neighbour's within `rings`) with the fewest
    pixels more than 1 input px off `truth_an` (the truth on the analysis grid, in its px)."""
    from mca.processing.surfaces import _graph

    labels = surfaces.labels
    graph = _graph(labels, surfaces.count, rings, samples)
    width = labels.shape[1]
    flat_truth = truth_an.ravel()
    known = np.isfinite(flat_truth)
    best = surfaces.planes.copy()
    for s in range(surfaces.count):
        pixels = graph.pix_index[graph.pix_ptr[s] : graph.pix_ptr[s + 1]]
        pixels = pixels[known[pixels]]
        if pixels.size == 0:
            continue
        planes = surfaces.fitted[graph.cand_list[graph.cand_ptr[s] : graph.cand_ptr[s + 1]]]
        ys, xs = np.divmod(pixels, width)
        predicted = planes[:, :1] * xs + planes[:, 1:2] * ys + planes[:, 2:]
        misses = np.count_nonzero(np.abs(predicted - flat_truth[pixels]) * to_input > 1.0, axis=1)
        best[s] = planes[int(np.argmin(misses))]
    return best


def score_render(image_path: str, truth_dir: str, truth: dict[str, Any]) -> dict[str, float] | str:
    """The stages' bad-1 (%) for one render, or a sentence saying why it was skipped."""
    from mca.capture import api
    from mca.capture.pipeline_app import read_input
    from mca.capture.rgbd_evaluation import _read_float_tiff
    from mca.devices.profiles import load_profile_file
    from mca.processing import pipeline as pl
    from mca.processing.surfaces import fit_planes, plane_map

    truth_root = Path(truth_dir)
    truth_px = _read_float_tiff(truth_root / truth["files"]["disparity_px"])
    profile = load_profile_file(truth_root / truth["files"]["profile"])
    loaded = read_input(Path(image_path))
    if max(loaded.planes.shape[:2]) > pl.PipelineParams().analysis_max_side_px or loaded.pixel_scale != 1:
        return "larger than the analysis grid (or a Bayer input): its surfaces are not on the truth's grid"
    kept: dict[str, Any] = {}

    def pipeline(planes: np.ndarray, aperture: Any, optics: Any, **kwargs: Any) -> Any:
        kept["run"] = pl.finished_run(planes, aperture, optics, **kwargs)
        return kept["run"].result()

    result = api.run_depth(loaded, profile, pipeline=pipeline)
    run = kept["run"]
    if run.factor != 1 or run.surfaces.labels.shape != truth_px.shape:
        return f"analysed on a grid {run.factor}x smaller than the truth's"
    to_input = float(run.to_input)
    surfaces = run.surfaces
    params = run.params.surfaces
    truth_an = truth_px / np.float32(to_input)
    weights = np.isfinite(truth_an).astype(np.float32)
    own_truth = fit_planes(surfaces.labels, surfaces.count, np.nan_to_num(truth_an), weights, params.slope_ridge)
    best = best_candidates(surfaces, truth_an, to_input, params.rings, params.boundary_samples)
    maps = {
        "dense": run.dense.disparity_px,
        "own-fit": plane_map(surfaces.labels, surfaces.fitted),
        "chosen": plane_map(surfaces.labels, surfaces.planes),
        "best-cand": plane_map(surfaces.labels, best),
        "sp-plane": plane_map(surfaces.labels, own_truth),
    }
    figures = {name: bad_1(m * np.float32(to_input), truth_px) for name, m in maps.items()}
    figures["final"] = bad_1(np.asarray(result.disparity_px, np.float32), truth_px)
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("renders", type=Path)
    parser.add_argument("--names", default="", help="comma-separated parts of render names to keep")
    parser.add_argument("--workers", type=int, default=2, help="renders scored at once (processes)")
    args = parser.parse_args(argv)
    from mca.capture.rgbd_evaluation import find_renders

    entries = find_renders(args.renders)
    wanted = [n for n in args.names.split(",") if n]
    entries = [e for e in entries if not wanted or any(n in e.name for n in wanted)]
    jobs = [(str(e.image_path), str(e.truth_dir), e.truth) for e in entries]
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        outcomes = list(pool.map(score_render, *zip(*jobs))) if jobs else []
    print(f"{'render':28s} " + " ".join(f"{s:>9s}" for s in STAGES) + "   (bad-1, %)")
    scored = []
    for entry, outcome in zip(entries, outcomes):
        label = f"{entry.group}/{entry.name}"[-28:]
        if isinstance(outcome, str):
            print(f"{label:28s} skipped: {outcome}")
            continue
        scored.append(outcome)
        print(f"{label:28s} " + " ".join(f"{outcome[s]:9.1f}" for s in STAGES), flush=True)
    if scored:
        for what, reduce in (("mean", np.mean), ("median", np.median)):
            print(f"{what:28s} " + " ".join(f"{reduce([o[s] for o in scored]):9.1f}" for s in STAGES))
    return 0 if scored or not jobs else 1


if __name__ == "__main__":
    sys.exit(main())
