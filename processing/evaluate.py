"""Evaluation against simulated ground truth: the paper's Table 2 (inter-object depth errors), region count and order.

Pure: a rendering's truth (labels, the JSON-ready truth dict), the pipeline's result and
peer disparity maps in, numbers and a text table out. Objects are matched to regions by
majority overlap; peers, which have no segmentation, are given the true object masks
(an advantage to them). For the in-focus object (true depth 0) the relative error is
replaced by the absolute error in mm, as the paper's relative error is undefined there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from mca.processing.optics import MCAOptics
from mca.processing.result import DepthResult


@dataclass
class ObjectRow:
    """One line of Table 2: a labelled object (or one end of a slanted one)."""

    label: str
    name: str
    true_mm: float  # true inter-object depth ΔD
    estimates_mm: dict[str, float]  # method -> estimated ΔD

    def abs_error_mm(self, method: str) -> float:
        return abs(self.estimates_mm[method] - self.true_mm)

    def rel_error(self, method: str) -> float | None:
        """Relative error; None for the in-focus object (truth 0), judged by its absolute error instead."""
        return None if abs(self.true_mm) < 1e-9 else self.abs_error_mm(method) / abs(self.true_mm)


@dataclass
class SceneEvaluation:
    scene: str
    rows: list[ObjectRow]
    true_region_count: int
    region_count: int
    order_correct: bool
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


def _end_points(mask: np.ndarray, axis: str, fraction: float = 0.04) -> list[tuple[np.ndarray, float, float]]:
    """The low and high ends of a mask along `axis`: (pixels mask of the end band, x, y of its centre)."""
    ys, xs = np.nonzero(mask)
    along = xs if axis == "x" else ys
    low, high = along.min(), along.max()
    span = max(high - low, 1)
    ends = []
    for lo, hi in ((low, low + fraction * span), (high - fraction * span, high)):
        sel = (along >= lo) & (along <= hi)
        band = np.zeros_like(mask)
        band[ys[sel], xs[sel]] = True
        ends.append((band, float(xs[sel].mean()), float(ys[sel].mean())))
    return ends


def _depth_from_disparity(disparity_input_px: float, optics: MCAOptics) -> float:
    return float(optics.inter_object_depth_mm(optics.inter_image_depth_mm(float(disparity_input_px))))


def evaluate_scene(
    truth: dict,
    truth_labels: np.ndarray,
    result: DepthResult,
    optics: MCAOptics,
    peers: dict[str, np.ndarray] | None = None,
    seconds: float = 0.0,
) -> SceneEvaluation:
    """Table 2 rows for one scene. `truth_labels` may be at full resolution: it is resized to the result's grid.

    `peers` maps a method name to a disparity map (input px, the result's grid, NaN = invalid).
    """
    peers = peers or {}
    height, width = result.labels.shape
    labels = cv2.resize(truth_labels.astype(np.uint16), (width, height), interpolation=cv2.INTER_NEAREST)
    kernel = np.ones((5, 5), np.uint8)
    by_id = {r.id: r for r in result.regions}
    rows: list[ObjectRow] = []
    matched: dict[int, int] = {}
    for obj in truth["objects"]:
        mask = labels == obj["id"]
        if mask.sum() == 0:
            continue
        ids, counts = np.unique(result.labels[mask], return_counts=True)
        region = by_id.get(int(ids[np.argmax(counts)]))
        if region is not None:
            matched[obj["id"]] = region.id
        core = cv2.erode(mask.astype(np.uint8), kernel).astype(bool)
        core = core if core.sum() > 50 else mask
        slant = obj.get("slant")
        label = obj.get("paper_label") or str(obj["id"])
        if slant is None:
            estimates = {}
            estimates["ours"] = (
                region.inter_object_depth_mm
                if region is not None and region.inter_object_depth_mm is not None
                else float("nan")
            )
            for name, disparity in peers.items():
                estimates[name] = _depth_from_disparity(float(np.nanmedian(disparity[core])), optics)
            rows.append(ObjectRow(label, obj["name"], float(obj["inter_object_depth_mm"]), estimates))
            continue
        labels_ab = label.split("-") if "-" in label else [label + "0", label + "1"]
        scale_in = truth_labels.shape[1] / width  # input (truth-raster) px per result px
        extent = slant.get("extent_px")
        for end, ((band, x, y), end_label, key) in enumerate(
            zip(_end_points(mask, slant["axis"]), labels_ab, ("from_inter_object_depth_mm", "to_inter_object_depth_mm"))
        ):
            estimates = {}
            if region is not None:
                a, b, c = region.slant if region.slant is not None else (0.0, 0.0, region.disparity_px)
                s = result.pixel_scale
                xi, yi = (x + 0.5) * s - 0.5, (y + 0.5) * s - 0.5
                if extent is not None:
                    # the true distance holds at the end of the extent: evaluate the plane exactly there
                    at = float(extent[end]) * s / scale_in + 0.5 * (s / scale_in - 1.0)
                    xi, yi = (at, yi) if slant["axis"] == "x" else (xi, at)
                estimates["ours"] = _depth_from_disparity(a * xi + b * yi + c, optics)
            else:
                estimates["ours"] = float("nan")
            for name, disparity in peers.items():
                estimates[name] = _depth_from_disparity(float(np.nanmedian(disparity[band])), optics)
            rows.append(
                ObjectRow(
                    end_label, f"{obj['name']} ({'near' if 'from' in key else 'far'} end)", float(slant[key]), estimates
                )
            )
    true_count = len(truth["objects"]) + (1 if truth.get("background") else 0)
    # order: every object found in a region of its own (a missing or shared object fails), every pair with
    # distinct true ranks ranked the same way, and every true occlusion (truth `occludes`) found as one
    notes = []
    order_ok = len(matched) == len(truth["objects"]) and len(set(matched.values())) == len(matched)
    if len(matched) < len(truth["objects"]):
        notes.append(f"{len(truth['objects']) - len(matched)} object(s) not found")
    ranks = {o["id"]: o["order"] for o in truth["objects"]}
    for i in matched:
        for j in matched:
            if ranks[i] < ranks[j] and by_id[matched[i]].order >= by_id[matched[j]].order:
                order_ok = False
    for obj in truth["objects"]:
        for hidden in obj.get("occludes", []):
            if obj["id"] in matched and hidden in matched and matched[hidden] not in by_id[matched[obj["id"]]].occludes:
                order_ok = False
                notes.append(f"occlusion {obj['id']} over {hidden} not found")
    if len(set(matched.values())) < len(matched):
        notes.append("two objects fell into one region")
    return SceneEvaluation(truth["scene"], rows, true_count, len(result.regions), order_ok, seconds, notes)


@dataclass
class Summary:
    median_rel: dict[str, float]
    worst_rel: dict[str, float]
    focus_abs_mm: dict[str, float]  # worst absolute error of in-focus objects


def summarise(evaluations: list[SceneEvaluation], methods: list[str]) -> Summary:
    median, worst, focus = {}, {}, {}
    for m in methods:
        known = [r.rel_error(m) for e in evaluations for r in e.rows]
        rel = [float(v) if np.isfinite(v) else np.inf for v in known if v is not None]
        foc = [
            float(v)
            for e in evaluations
            for r in e.rows
            if r.rel_error(m) is None
            for v in [r.abs_error_mm(m)]
            if v is not None
        ]
        median[m] = float(np.median(rel)) if rel else float("nan")
        worst[m] = float(np.max(rel)) if rel else float("nan")
        focus[m] = float(np.max(foc)) if foc else float("nan")
    return Summary(median, worst, focus)


def format_table(evaluations: list[SceneEvaluation], methods: list[str]) -> str:
    """Table 2 of the paper for the simulated scenes, one column group per method."""
    head = f"{'scene':<8} {'obj':<4} {'true ΔD':>8}"
    for m in methods:
        head += f" | {m + ' ΔD':>10} {'abs':>6} {'rel':>7}"
    lines = [head, "-" * len(head)]
    for e in evaluations:
        for r in e.rows:
            line = f"{e.scene:<8} {r.label:<4} {r.true_mm:>8.1f}"
            for m in methods:
                rel = r.rel_error(m)
                rel_text = "  focus" if rel is None else f"{100 * rel:6.1f}%"
                line += f" | {r.estimates_mm[m]:>10.1f} {r.abs_error_mm(m):>6.1f} {rel_text:>7}"
            lines.append(line)
        lines.append(
            f"{e.scene:<8} regions {e.region_count} (true {e.true_region_count}), order "
            f"{'right' if e.order_correct else 'WRONG'}, {e.seconds:.2f} s"
            + (f"; {'; '.join(e.notes)}" if e.notes else "")
        )
    s = summarise(evaluations, methods)
    lines.append("-" * len(head))
    for m in methods:
        lines.append(
            f"{m:<12} median rel {100 * s.median_rel[m]:5.1f}%  worst rel {100 * s.worst_rel[m]:6.1f}%  "
            f"in-focus worst abs {s.focus_abs_mm[m]:5.1f} mm"
        )
    regions_ok = sum(e.region_count == e.true_region_count for e in evaluations)
    order_ok = sum(e.order_correct for e in evaluations)
    lines.append(f"region count right in {regions_ok}/{len(evaluations)}, order right in {order_ok}/{len(evaluations)}")
    return "\n".join(lines)


def bayer_planes(mosaic: np.ndarray, black_level: float, white_level: float) -> np.ndarray:
    """Half-resolution linear planes (R, mean of the two G, B) of an RGGB mosaic, 0..1 of white - black.

    The channels keep their Bayer sample positions: pass `RGGB_HALF_RES_OFFSETS_PX` to the pipeline.
    """
    m = (mosaic.astype(np.float32) - np.float32(black_level)) / np.float32(white_level - black_level)
    return np.dstack([m[0::2, 0::2], 0.5 * (m[0::2, 1::2] + m[1::2, 0::2]), m[1::2, 1::2]]).astype(np.float32)


# --- per-pixel figures on rendered real scenes (mca evaluate --rgbd) -------------------------------------------------

EDGE_JUMP_PX = 0.5  # a true depth edge: 8-neighbours whose red-blue disparities differ by more than this
EDGE_BAND_PX = 5  # pixels within this distance of a true depth edge are "near edges"
MIN_OFF_FOCUS_MM = 25.0  # relative inter-object error only where the truth is this far off the focus plane
FAR_FROM_EDGE_PX = 20  # pixels farther than this from every true depth edge are "interior" (far-1)
SLOPE_WITHIN_PX = 3.0  # the disparity slope is fitted to the estimates at most this far off (not to gross errors)
MIN_SLOPE_SPREAD_PX = 0.5  # ... and only where the true disparities spread at least this much (standard deviation)
MIN_SLOPE_PX = 100  # ... over at least this many pixels


@dataclass
class PixelMetrics:
    """Per-pixel accuracy of one disparity/depth map against the truth of a rendering.

    Shares are of truth-valid pixels; a missing estimate (NaN) counts as bad and as an infinite
    error in the medians (so a median is infinite when over half the pixels have no value).
    """

    bad_1: float  # share with |disparity error| > 1 px
    bad_05: float  # share with |disparity error| > 0.5 px
    edge_bad_1: float  # the same within EDGE_BAND_PX of true depth edges (NaN when there are none)
    edge_bad_05: float
    median_abs_depth_mm: float  # median |Z_est - Z_true|
    median_rel_inter_object: float  # median |Z_est - Z_true| / |Z_true - F| where |Z_true - F| >= 25 mm
    coverage: float  # share with a value
    valid_px: int
    edge_px: int
    # where the misses are: bad-1 of the interior (farther than FAR_FROM_EDGE_PX from every true depth edge; NaN
    # when there is none), and the least-squares slope of the estimated against the true disparity over the
    # estimates within SLOPE_WITHIN_PX of the truth (1: none; below 1 the estimate is compressed towards one level,
    # which every relative depth error inherits; NaN when the truth spreads less than MIN_SLOPE_SPREAD_PX)
    far_bad_1: float = float("nan")
    disparity_slope: float = float("nan")
    far_px: int = 0

    FIELDS = (
        "bad_1",
        "bad_05",
        "edge_bad_1",
        "edge_bad_05",
        "far_bad_1",
        "median_abs_depth_mm",
        "median_rel_inter_object",
        "disparity_slope",
        "coverage",
    )

    def as_dict(self) -> dict[str, float | int]:
        return {name: getattr(self, name) for name in self.FIELDS + ("valid_px", "edge_px", "far_px")}


def depth_edges(true_disparity_px: np.ndarray, jump_px: float = EDGE_JUMP_PX) -> np.ndarray:
    """The true depth edges: pixels with an 8-neighbour, both known, whose disparities differ by more than
    `jump_px`."""
    d = np.asarray(true_disparity_px, np.float32)
    edges = np.zeros(d.shape, bool)
    h, w = d.shape
    padded = np.pad(d, 1, constant_values=np.nan)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                neighbour = padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                edges |= np.abs(d - neighbour) > jump_px  # NaN compares False: unknown pixels make no edge
    return edges


def depth_edge_band(
    true_disparity_px: np.ndarray,
    jump_px: float = EDGE_JUMP_PX,
    band_px: int = EDGE_BAND_PX,
    edges: np.ndarray | None = None,
) -> np.ndarray:
    """Truth-valid pixels within `band_px` (Euclidean) of a true depth edge (`depth_edges`; pass them as
    `edges` when they are at hand, for several bands of one truth)."""
    if edges is None:
        edges = depth_edges(true_disparity_px, jump_px)
    valid = np.isfinite(np.asarray(true_disparity_px, np.float32))
    if not edges.any():
        return np.zeros(valid.shape, bool)
    size = 2 * band_px + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    near = cv2.dilate(edges.astype(np.uint8), disk).astype(bool)
    return near & valid


def disparity_slope(estimate_disparity_px: np.ndarray, true_disparity_px: np.ndarray, mask: np.ndarray) -> float:
    """Least-squares slope of the estimated against the true disparity over `mask`'s pixels whose estimate is
    within `SLOPE_WITHIN_PX` of the truth: 1 when the estimate follows the truth's range, below 1 when it is
    compressed towards one level. NaN with fewer than `MIN_SLOPE_PX` such pixels or a truth that spreads less
    than `MIN_SLOPE_SPREAD_PX` over them."""
    est = np.asarray(estimate_disparity_px, np.float64)
    true = np.asarray(true_disparity_px, np.float64)
    with np.errstate(invalid="ignore"):
        near = mask & (np.abs(est - true) <= SLOPE_WITHIN_PX)  # NaN compares False
    if int(near.sum()) < MIN_SLOPE_PX:
        return float("nan")
    t, e = true[near], est[near]
    t = t - t.mean()
    spread = float(np.mean(t * t))
    if spread < MIN_SLOPE_SPREAD_PX**2:
        return float("nan")
    return float(np.mean(t * (e - e.mean())) / spread)


def pixel_metrics(
    estimate_disparity_px: np.ndarray,
    estimate_distance_mm: np.ndarray | None,
    true_disparity_px: np.ndarray,
    true_distance_mm: np.ndarray,
    focus_distance_mm: float,
    edge_band: np.ndarray | None = None,
    far: np.ndarray | None = None,
) -> PixelMetrics:
    """The figures of `PixelMetrics` for one estimate (maps at the truth's size, NaN = no value).

    Without `estimate_distance_mm` the depth figures are NaN (a disparity-only method). `edge_band` and `far`:
    `depth_edge_band(true)` and the pixels outside `depth_edge_band(true, band_px=FAR_FROM_EDGE_PX)` when the
    caller scores several estimates against one truth (made here otherwise).
    """
    true_d = np.asarray(true_disparity_px, np.float32)
    est_d = np.asarray(estimate_disparity_px, np.float32)
    if est_d.shape != true_d.shape:
        raise ValueError(f"estimate {est_d.shape} and truth {true_d.shape} differ in size")
    valid = np.isfinite(true_d) & np.isfinite(np.asarray(true_distance_mm, np.float32))
    n = int(valid.sum())
    if n == 0:
        raise ValueError("the truth has no valid pixel")
    edges = depth_edges(true_d) if edge_band is None or far is None else None  # once, for either band
    band = depth_edge_band(true_d, edges=edges) if edge_band is None else (edge_band & valid)
    interior = (~depth_edge_band(true_d, band_px=FAR_FROM_EDGE_PX, edges=edges) if far is None else far) & valid
    error = np.abs(est_d - true_d)
    error = np.where(np.isfinite(error), error, np.inf)

    def share_bad(mask: np.ndarray, limit: float) -> float:
        count = int(mask.sum())
        return float(np.count_nonzero(error[mask] > limit)) / count if count else float("nan")

    abs_depth = rel = float("nan")
    if estimate_distance_mm is not None:
        z_true = np.asarray(true_distance_mm, np.float64)
        z_est = np.asarray(estimate_distance_mm, np.float64)
        dz = np.abs(z_est - z_true)
        dz = np.where(np.isfinite(dz), dz, np.inf)
        abs_depth = float(np.median(dz[valid]))
        off = valid & (np.abs(z_true - focus_distance_mm) >= MIN_OFF_FOCUS_MM)
        if off.any():
            rel = float(np.median(dz[off] / np.abs(z_true[off] - focus_distance_mm)))
    return PixelMetrics(
        bad_1=share_bad(valid, 1.0),
        bad_05=share_bad(valid, 0.5),
        edge_bad_1=share_bad(band, 1.0),
        edge_bad_05=share_bad(band, 0.5),
        median_abs_depth_mm=abs_depth,
        median_rel_inter_object=rel,
        coverage=float(np.count_nonzero(np.isfinite(est_d[valid]))) / n,
        valid_px=n,
        edge_px=int(band.sum()),
        far_bad_1=share_bad(interior, 1.0),
        disparity_slope=disparity_slope(est_d, true_d, valid),
        far_px=int(interior.sum()),
    )


@dataclass
class RgbdRow:
    """One render's figures for every method; `status[method]` says why a method has none ("not built", ...)."""

    name: str
    group: str
    metrics: dict[str, PixelMetrics]
    status: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    summary: str = ""


# figures where lower is better; coverage is the one where higher is better, and the slope's best is 1
_HIGHER_IS_BETTER = {"coverage"}
_BEST_AT = {"disparity_slope": 1.0}


def summarise_rgbd(rows: list[RgbdRow], methods: list[str]) -> dict[str, dict[str, dict[str, float]]]:
    """{method: {figure: {"median": .., "worst": .., "count": n}}} over the rows that have the method."""
    summary: dict[str, dict[str, dict[str, float]]] = {}
    for method in methods:
        have = [r.metrics[method] for r in rows if method in r.metrics]
        figures: dict[str, dict[str, float]] = {}
        for name in PixelMetrics.FIELDS:
            values = np.array([getattr(m, name) for m in have], np.float64)
            values = values[~np.isnan(values)]
            if values.size == 0:
                figures[name] = {"median": float("nan"), "worst": float("nan"), "count": 0}
                continue
            if name in _BEST_AT:
                worst = values[np.argmax(np.abs(values - _BEST_AT[name]))]
            else:
                worst = values.min() if name in _HIGHER_IS_BETTER else values.max()
            figures[name] = {"median": float(np.median(values)), "worst": float(worst), "count": int(values.size)}
        summary[method] = figures
    return summary


_COLUMNS = (
    ("bad_1", "bad-1", "pct"),
    ("bad_05", "bad-.5", "pct"),
    ("edge_bad_1", "edge-1", "pct"),
    ("edge_bad_05", "edge-.5", "pct"),
    ("far_bad_1", "far-1", "pct"),
    ("median_abs_depth_mm", "|dZ| mm", "mm"),
    ("median_rel_inter_object", "rel dD", "pct"),
    ("disparity_slope", "slope", "ratio"),
    ("coverage", "cover", "pct"),
)


def _cell(value: float, kind: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if math.isinf(value):
        return "inf"
    if kind == "ratio":
        return f"{value:.2f}"
    return f"{100 * value:.1f}%" if kind == "pct" else f"{value:.1f}"


def format_rgbd_table(rows: list[RgbdRow], methods: list[str]) -> str:
    """One line per render and method, then per group and overall the median and worst of each figure."""
    head = f"{'render':<22} {'method':<9}" + "".join(f" {title:>8}" for _, title, _ in _COLUMNS) + f" {'s':>6}"
    lines = [head, "-" * len(head)]
    for row in rows:
        name = row.name if row.group in ("", ".") else f"{row.group}/{row.name}"
        for method in methods:
            label = f"{name:<22} {method:<9}"
            if method not in row.metrics:
                lines.append(f"{label} {row.status.get(method, 'no result')}")
                continue
            m = row.metrics[method]
            seconds = row.seconds.get(method)
            lines.append(
                label
                + "".join(f" {_cell(getattr(m, key), kind):>8}" for key, _, kind in _COLUMNS)
                + (f" {seconds:6.1f}" if seconds is not None else "")
            )
    groups = sorted({r.group for r in rows})
    for group in groups + (["all"] if len(groups) > 1 else []):
        members = [r for r in rows if group in ("all", r.group)]
        summary = summarise_rgbd(members, methods)
        lines.append("-" * len(head))
        for which in ("median", "worst"):
            for method in methods:
                figures = summary[method]
                count = figures["bad_1"]["count"]
                label = f"{(group if group not in ('', '.') else 'all') + ' ' + which:<22} {method:<9}"
                if not count:
                    lines.append(f"{label} no result")
                    continue
                lines.append(
                    label
                    + "".join(f" {_cell(figures[key][which], kind):>8}" for key, _, kind in _COLUMNS)
                    + f"  ({count} render{'s' if count != 1 else ''})"
                )
    return "\n".join(lines)
