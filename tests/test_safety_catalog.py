"""The shot catalog keeps its promises across runs, folders and versions (issue 13, item 5).

Before the fix the catalog stored result paths relative to the caller's working directory, local
times without offset and no schema version, and a shot downloaded by a run killed before
processing was never processed.
"""

from __future__ import annotations

import datetime
import os
import sqlite3

import pytest
from typer.testing import CliRunner

from mca.capture.catalog import Catalog
from mca.capture.cli import app
from mca.capture.tether import TetherSession
from mca.devices.cameras import make_sim_rig, open_camera
from mca.devices.sim.world import scene_frame_source

FIRST_CATALOG_SCHEMA = """
CREATE TABLE IF NOT EXISTS shots (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    camera_serial TEXT NOT NULL,
    camera_filename TEXT NOT NULL,
    camera_handle INTEGER,
    file_name TEXT,
    size_bytes INTEGER,
    sha256 TEXT,
    captured_at TEXT NOT NULL,
    downloaded_at TEXT,
    processed_at TEXT,
    status TEXT NOT NULL CHECK (status IN ('captured', 'downloaded', 'processed', 'failed')),
    result_path TEXT,
    message TEXT
);
"""  # the catalog as the first mca wrote it (no version)


@pytest.fixture
def tiny_frames(monkeypatch):
    monkeypatch.setenv("MCA_SIM_SIZE", "0.1")  # 547 x 365 simulated frames: a shot processes in about a second


def test_result_paths_are_relative_to_the_catalog_not_the_working_folder(tmp_path, monkeypatch, tiny_frames):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "1", "--out", "shots", "--process"])
    assert result.exit_code == 0, result.output
    with Catalog(tmp_path / "shots" / "catalog.sqlite") as catalog:
        (row,) = catalog.rows()
        assert row.status == "processed" and row.result_path == "IMG_0001"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    with Catalog(tmp_path / "shots" / "catalog.sqlite") as catalog:
        folder = catalog.resolve(catalog.rows()[0].result_path)
        assert folder == tmp_path / "shots" / "IMG_0001" and (folder / "result.json").is_file()
        assert catalog.disagreements() == []
    outside = tmp_path / "results" / "x"
    with Catalog(tmp_path / "shots" / "catalog.sqlite") as catalog:
        catalog.mark_processed(1, outside)
        assert catalog.get(1).result_path == str(outside)  # outside the catalog's folder: absolute


def test_times_are_utc_with_an_offset(tmp_path):
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        shot = catalog.add_captured("SERIAL", "IMG_0001.CR2", 1, 10)
        catalog.mark_downloaded(shot, "IMG_0001.CR2", 10, "0" * 64)
        row = catalog.get(shot)
    for text in (row.captured_at, row.downloaded_at):
        moment = datetime.datetime.fromisoformat(text)
        assert moment.utcoffset() == datetime.timedelta(0), text
        assert abs(moment - datetime.datetime.now(datetime.UTC)) < datetime.timedelta(minutes=5)


def test_the_first_catalog_is_migrated_to_a_versioned_one(tmp_path, monkeypatch):
    monkeypatch.setenv("TZ", "Europe/Berlin")  # a known offset for the local times of the first catalog
    import time

    time.tzset()
    try:
        shots = tmp_path / "demo-out" / "shots"
        (shots / "IMG_0001").mkdir(parents=True)
        (shots / "IMG_0001" / "result.json").write_text("{}")
        db = sqlite3.connect(shots / "catalog.sqlite")
        db.executescript(FIRST_CATALOG_SCHEMA)
        db.execute(
            "INSERT INTO shots (camera_serial, camera_filename, camera_handle, file_name, size_bytes, sha256,"
            " captured_at, downloaded_at, processed_at, status, result_path) VALUES"
            " ('S', 'IMG_0001.CR2', 1, 'IMG_0001.CR2', 3, 'x', '2024-07-01T12:00:00.000', '2024-07-01T12:00:01.500',"
            " '2024-07-01T12:00:05.000', 'processed', 'demo-out/shots/IMG_0001')"
        )
        db.commit()
        db.close()
        with Catalog(shots / "catalog.sqlite") as catalog:
            row = catalog.get(1)
            version = catalog.db.execute("SELECT version FROM schema_versions WHERE name='shots'").fetchone()
        assert version == (1,)
        assert row.captured_at == "2024-07-01T10:00:00.000+00:00"  # 12:00 CEST is 10:00 UTC
        assert row.downloaded_at == "2024-07-01T10:00:01.500+00:00"
        assert row.result_path == "IMG_0001"
        # opened again: nothing changes
        with Catalog(shots / "catalog.sqlite") as catalog:
            assert catalog.get(1) == row
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()


def test_a_catalog_of_a_newer_mca_is_refused(tmp_path):
    from mca.capture.catalog import CatalogError

    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        catalog.db.execute("UPDATE schema_versions SET version=99 WHERE name='shots'")
        catalog.db.commit()
    with pytest.raises(CatalogError, match="newer mca"):
        Catalog(tmp_path / "catalog.sqlite")


def test_a_shot_downloaded_but_not_processed_is_processed_by_the_next_run(tmp_path, monkeypatch, tiny_frames):
    """A run killed between download and processing leaves the shot 'downloaded'; the next --process run does it."""
    out = tmp_path / "shots"
    rig = make_sim_rig(scene_frame_source())
    session = TetherSession(open_camera("sim", rig=rig), out)  # downloads only, as if killed before processing
    session.connect()
    (first,) = session.capture(1)
    session.close()
    assert first.status == "downloaded"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--count", "1", "--out", str(out), "--process"])
    assert result.exit_code == 0, result.output
    with Catalog(out / "catalog.sqlite") as catalog:
        rows = catalog.rows()
        assert [r.status for r in rows] == ["processed", "processed"], [(r.status, r.message) for r in rows]
        assert catalog.pending() == [] and catalog.unprocessed() == []
        assert catalog.disagreements() == []
    assert "left unprocessed by an earlier run" in result.output


def test_disagreements_name_what_differs(tmp_path):
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        shot = catalog.add_captured("S", "IMG_0001.CR2", 1, 3)
        (tmp_path / "IMG_0001.CR2").write_bytes(b"abc")
        import hashlib

        catalog.mark_downloaded(shot, "IMG_0001.CR2", 3, hashlib.sha256(b"abc").hexdigest())
        assert catalog.disagreements() == []
        (tmp_path / "IMG_0001.CR2").write_bytes(b"abd")
        assert "does not match its sha256" in catalog.disagreements()[0]
        (tmp_path / "IMG_0002.CR2").write_bytes(b"x")
        assert any("does not list" in p for p in catalog.disagreements())
        catalog.mark_processed(shot, tmp_path / "IMG_0001")
        assert any("no result.json" in p for p in catalog.disagreements())
        os.remove(tmp_path / "IMG_0001.CR2")
        assert any("is missing" in p for p in catalog.disagreements())


def test_a_full_disk_cannot_stop_the_catalog_recording_a_shot(tmp_path, monkeypatch):
    """SQLite reports a full disk: the catalog gives back its reserve and the insert goes through."""
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        assert catalog.reserve.stat().st_size == 1 << 20
        real = catalog.db
        calls = {"n": 0}

        class FullOnce:
            def execute(self, *args):
                calls["n"] += 1
                if calls["n"] == 1:
                    raise sqlite3.OperationalError("database or disk is full")
                return real.execute(*args)

            def __getattr__(self, name):
                return getattr(real, name)

        catalog.db = FullOnce()
        shot = catalog.add_captured("S", "IMG_0001.CR2", 1, 10)
        catalog.db = real
        assert catalog.get(shot).status == "captured" and not catalog.reserve.exists()
    with Catalog(tmp_path / "catalog.sqlite") as catalog:  # the next run finds room: the reserve is back
        assert catalog.reserve.stat().st_size == 1 << 20


def test_a_failed_download_is_fetched_again(tmp_path):
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        shot = catalog.add_captured("S", "IMG_0001.CR2", 1, 10)
        catalog.mark_failed(shot, "No space left on device")
        assert [r.id for r in catalog.missing("S")] == [shot]  # a full disk: not given up
        assert [r.id for r in catalog.pending()] == [shot]
