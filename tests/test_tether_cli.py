"""`mca capture` and `mca camera` against the simulated camera: files, catalog rows and property commands."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from typer.testing import CliRunner

from mca.capture.cli import app


def test_capture_three_shots_leaves_three_cr2_files_and_a_catalog(tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    files = sorted(p.name for p in out.glob("*.CR2"))
    assert files == ["IMG_0001.CR2", "IMG_0002.CR2", "IMG_0003.CR2"]
    rows = (
        sqlite3.connect(out / "catalog.sqlite")
        .execute("SELECT file_name, status, size_bytes, sha256 FROM shots ORDER BY id")
        .fetchall()
    )
    assert [(r[0], r[1]) for r in rows] == [(f, "downloaded") for f in files]
    assert all(r[2] == (out / r[0]).stat().st_size and len(r[3]) == 64 for r in rows)


def test_camera_config_get_and_set_on_the_simulated_body() -> None:
    runner = CliRunner()
    got = runner.invoke(app, ["camera", "config", "get", "iso", "--camera", "sim"])
    assert got.exit_code == 0 and "iso = 100" in got.output and "6400" in got.output
    bad = runner.invoke(app, ["camera", "config", "set", "iso", "123", "--camera", "sim"])
    assert bad.exit_code == 2
    info = runner.invoke(app, ["camera", "info", "--camera", "sim"])
    assert "Canon EOS 70D" in info.output and "SIM70D0000001" in info.output
