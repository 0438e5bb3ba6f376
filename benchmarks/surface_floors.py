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

import sys
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
    from mca.capture.rgbd_evaluation import run_kept
    from mca.processing.surfaces import fit_planes, plane_map

    kept = run_kept(image_path, truth_dir, truth)
    if isinstance(kept, str):
        return kept
    run, result, truth_px = kept.run, kept.result, kept.truth_px
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
    from mca.capture.rgbd_evaluation import print_scores, score_renders

    pairs = score_renders(score_render, argv, __doc__.split("\n")[0])
    scored = print_scores(pairs, STAGES, 9, "   (bad-1, %)")
    if scored:
        for what, reduce in (("mean", np.mean), ("median", np.median)):
            print(f"{what:28s} " + " ".join(f"{reduce([o[s] for o in scored]):9.1f}" for s in STAGES))
    return 0 if scored or not pairs else 1


if __name__ == "__main__":
    sys.exit(main())
