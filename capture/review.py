"""The rows of `mca review DIR`: the results and recordings in an output folder (shot, time, regions, distances, status).

Reads `DIR/*/result.json` (written by `mca process`) and the `.rrd` recordings in `DIR` and its
sub-folders; never imports rerun, so it is instant even on a large folder.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

RESULT_NAME = "result.json"


@dataclass
class ReviewRow:
    """One shot (an output folder) or one recording that belongs to no folder."""

    shot: str
    time: str | None = None  # capture time as recorded in result.json, else None
    regions: int | None = None
    nearest_mm: float | None = None  # distance of the nearest region from the lens
    farthest_mm: float | None = None
    nearest_px: float | None = None  # disparity-only results: smallest and largest disparity
    farthest_px: float | None = None
    status: str = "unknown"  # done, failed, unfinished, recording only, unreadable
    recordings: list[str] = field(default_factory=list)  # .rrd paths relative to DIR
    reason: str | None = None


def _finite(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _capture_time(document: dict[str, Any]) -> str | None:
    capture = document.get("capture")
    value = capture.get("capture_time") if isinstance(capture, dict) else None
    if not isinstance(value, str) or not value:
        return None
    try:
        return datetime.fromisoformat(value).strftime("%Y-%m-%d %H:%M:%S")
    except ValueError:
        return value


def row_from_result(folder: Path, document: dict[str, Any]) -> ReviewRow:
    """The row of one output folder from its parsed result.json."""
    listed = document.get("regions")
    regions: list[Any] = listed if isinstance(listed, list) else []
    distances = [d for d in (_finite(r.get("distance_mm")) for r in regions if isinstance(r, dict)) if d is not None]
    disparities = [d for d in (_finite(r.get("disparity_px")) for r in regions if isinstance(r, dict)) if d is not None]
    row = ReviewRow(
        shot=folder.name,
        time=_capture_time(document),
        regions=len(regions),
        status=str(document.get("status") or "done"),
    )
    if distances:
        row.nearest_mm, row.farthest_mm = min(distances), max(distances)
    elif disparities:  # + = farther: the smallest disparity is the nearest object
        row.nearest_px, row.farthest_px = min(disparities), max(disparities)
    return row


def review_rows(directory: Path) -> list[ReviewRow]:
    """Rows for every sub-folder of `directory` holding a result (or a recording), then stray recordings."""
    directory = Path(directory)
    rows: list[ReviewRow] = []
    claimed: set[Path] = set()
    folders = sorted(p for p in directory.iterdir() if p.is_dir() and not p.name.startswith("."))
    stems = {p.name for p in folders}
    for folder in folders:
        recordings = sorted(folder.glob("*.rrd"))
        result = folder / RESULT_NAME
        if result.is_file():
            try:
                document = json.loads(result.read_text(encoding="utf-8"))
                if not isinstance(document, dict):
                    raise ValueError("not a JSON object")
                row = row_from_result(folder, document)
            except (OSError, ValueError) as exc:
                row = ReviewRow(shot=folder.name, status="unreadable", reason=f"{result}: {exc}")
        elif recordings or any(folder.iterdir()):
            row = ReviewRow(shot=folder.name, status="unfinished", reason="no result.json: not processed to the end")
        else:
            continue
        for path in recordings + sorted(directory.glob(f"{folder.name}.rrd")):
            row.recordings.append(str(path.relative_to(directory)))
            claimed.add(path)
        rows.append(row)
    for path in sorted(directory.glob("*.rrd")):
        if path in claimed:
            continue
        stamp = datetime.fromtimestamp(path.stat().st_mtime).strftime("%Y-%m-%d %H:%M:%S")
        rows.append(
            ReviewRow(
                shot=path.stem,
                time=stamp,
                status="recording only",
                recordings=[path.name],
                reason="merged or named recording; time is the file's" if path.stem not in stems else None,
            )
        )
    return rows


def _distance(mm: float | None, px: float | None) -> str:
    if mm is not None:
        return f"{mm:.0f} mm"
    if px is not None:
        return f"{px:+.2f} px"
    return "-"


def format_table(rows: list[ReviewRow]) -> str:
    """The rows as an aligned plain-text table."""
    header = ("shot", "time", "regions", "nearest", "farthest", "status", "recording")
    body = [
        (
            r.shot,
            r.time or "-",
            "-" if r.regions is None else str(r.regions),
            _distance(r.nearest_mm, r.nearest_px),
            _distance(r.farthest_mm, r.farthest_px),
            r.status,
            ", ".join(r.recordings) or "-",
        )
        for r in rows
    ]
    widths = [max(len(line[i]) for line in [header, *body]) for i in range(len(header))]
    right = {2, 3, 4}
    lines = [
        "  ".join(
            cell.rjust(w) if i in right else cell.ljust(w) for i, (cell, w) in enumerate(zip(line, widths))
        ).rstrip()
        for line in [header, *body]
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def review_document(rows: list[ReviewRow]) -> list[dict[str, Any]]:
    """`mca review --json`: the rows as plain data."""
    return [asdict(r) for r in rows]


def review_notes(rows: list[ReviewRow]) -> list[str]:
    """The lines printed under the table: why a shot is unreadable, unfinished or failed, and how to open recordings."""
    notes = [
        f"{row.shot}: {row.reason}"
        for row in rows
        if row.reason and row.status in ("unreadable", "unfinished", "failed")
    ]
    if any(r.recordings for r in rows):
        notes.append("open a recording with: mca view DIR/<recording>.rrd")
    return notes
