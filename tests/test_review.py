"""`mca review DIR`: the table of results and recordings in an output folder, from result.json files and .rrd names."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from mca.capture.cli import app
from mca.capture.review import format_table, review_rows


def _result(
    folder: Path, regions: list[dict], capture_time: str | None = "2024-05-06T07:08:09", status: str = "done"
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    document = {
        "input": f"{folder.name}.CR2",
        "profile": "paper-70d",
        "regions": regions,
        "status": status,
        "capture": {"capture_time": capture_time, "model": "Canon EOS 70D"},
    }
    (folder / "result.json").write_text(json.dumps(document), encoding="utf-8")


def _out_folder(tmp_path: Path) -> Path:
    out = tmp_path / "out"
    _result(
        out / "paper-c",
        [
            {"id": 1, "distance_mm": 912.4, "disparity_px": -6.1},
            {"id": 2, "distance_mm": 1187.9, "disparity_px": 9.0},
            {"id": 3, "distance_mm": None, "disparity_px": 0.4},
        ],
    )
    (out / "paper-c" / "recording.rrd").write_bytes(b"rrd")
    _result(
        out / "flat",
        [{"id": 1, "distance_mm": None, "disparity_px": -2.5}, {"id": 2, "distance_mm": None, "disparity_px": 3.25}],
        capture_time=None,
    )
    (out / "broken").mkdir()
    (out / "broken" / "depth.tiff").write_bytes(b"half")
    (out / "bad").mkdir()
    (out / "bad" / "result.json").write_text("{not json", encoding="utf-8")
    (out / "empty").mkdir()
    (out / "c.rrd").write_bytes(b"rrd")
    (out / "flat.rrd").write_bytes(b"rrd")
    return out


def test_rows_read_results_and_recordings(tmp_path: Path) -> None:
    rows = {r.shot: r for r in review_rows(_out_folder(tmp_path))}
    assert set(rows) == {"paper-c", "flat", "broken", "bad", "c"}  # an empty folder is no shot
    c = rows["paper-c"]
    assert (c.regions, c.nearest_mm, c.farthest_mm, c.status) == (3, 912.4, 1187.9, "done")
    assert c.time == "2024-05-06 07:08:09" and c.recordings == ["paper-c/recording.rrd"]
    flat = rows["flat"]  # disparity-only: nearest is the smallest disparity
    assert (flat.nearest_mm, flat.nearest_px, flat.farthest_px) == (None, -2.5, 3.25)
    assert flat.time is None and flat.recordings == ["flat.rrd"]
    assert rows["broken"].status == "unfinished"
    assert rows["bad"].status == "unreadable" and "result.json" in rows["bad"].reason
    assert rows["c"].status == "recording only" and rows["c"].recordings == ["c.rrd"]


def test_table_has_a_line_per_shot(tmp_path: Path) -> None:
    table = format_table(review_rows(_out_folder(tmp_path)))
    lines = table.splitlines()
    assert lines[0].split() == ["shot", "time", "regions", "nearest", "farthest", "status", "recording"]
    assert len(lines) == 2 + 5
    paper = next(line for line in lines if line.startswith("paper-c"))
    assert "912 mm" in paper and "1188 mm" in paper and "done" in paper
    assert "-2.50 px" in next(line for line in lines if line.startswith("flat"))


def test_cli_prints_the_table_and_json(tmp_path: Path) -> None:
    out = _out_folder(tmp_path)
    result = CliRunner().invoke(app, ["review", str(out)])
    assert result.exit_code == 0, result.output
    assert "paper-c" in result.output and "mca view" in result.output
    assert "broken: no result.json" in result.output
    listed = json.loads(CliRunner().invoke(app, ["review", str(out), "--json"]).output)
    assert {row["shot"] for row in listed} == {"paper-c", "flat", "broken", "bad", "c"}
    missing = CliRunner().invoke(app, ["review", str(tmp_path / "nope")])
    assert missing.exit_code == 2


def test_view_without_display_says_how_to_look(tmp_path: Path, monkeypatch) -> None:
    from mca.capture.viewer import has_display, viewer_command

    recording = tmp_path / "c.rrd"
    recording.write_bytes(b"rrd")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert not has_display()
    result = CliRunner().invoke(app, ["view", str(recording)])
    assert result.exit_code == 1
    assert "rerun c.rrd" in result.output and "--web" in result.output and "127.0.0.1" in result.output
    assert has_display({"WAYLAND_DISPLAY": "wayland-0"})
    command = viewer_command("rerun", [recording], web=True, bind="127.0.0.1", web_port=9090, grpc_port=9876)
    assert command[command.index("--bind") + 1] == "127.0.0.1" and "--serve-web" in command
    assert viewer_command("rerun", [recording], web=False, bind="127.0.0.1", web_port=1, grpc_port=2) == [
        "rerun",
        str(recording),
    ]
    assert CliRunner().invoke(app, ["view", str(tmp_path / "none.rrd")]).exit_code == 2
