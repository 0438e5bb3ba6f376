"""The shot catalog read back with plain sqlite3, hashlib and datetime (not through the Catalog class): the row
of each step of a shot's life, the queries that drive the next run, the checks against the disk, the migration
of a version-0 catalog written here by hand, and the reserve that lets it record a shot on a full disk.
"""

from __future__ import annotations

import datetime
import hashlib
import os
import sqlite3
import time
from pathlib import Path

import pytest

from mca.capture import catalog as cat
from mca.capture.catalog import Catalog, CatalogError


def raw_rows(path: Path) -> list[dict]:
    with sqlite3.connect(path) as db:
        db.row_factory = sqlite3.Row
        return [dict(r) for r in db.execute("SELECT * FROM shots ORDER BY id")]


def utc(text: str) -> datetime.datetime:
    moment = datetime.datetime.fromisoformat(text)
    assert moment.utcoffset() == datetime.timedelta(0), text
    return moment


def test_a_shots_life_as_rows(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    before = datetime.datetime.now(datetime.UTC) - datetime.timedelta(seconds=1)
    with Catalog(path) as catalog:
        first = catalog.add_captured("SN1", "IMG_0001.CR2", 0x90000001, 25_000_000)
        second = catalog.add_captured("SN1", "IMG_0002.CR2", None, None)
        assert (first, second) == (1, 2)
        shot = tmp_path / "IMG_0001.CR2"
        shot.write_bytes(b"raw bytes")
        catalog.mark_downloaded(first, "IMG_0001.CR2", 9, hashlib.sha256(b"raw bytes").hexdigest())
        (tmp_path / "IMG_0001").mkdir()
        (tmp_path / "IMG_0001" / "result.json").write_text("{}")
        catalog.mark_processed(first, tmp_path / "IMG_0001")
        catalog.mark_failed(second, "the card was pulled")
        catalog.note(first, "looked at")
        catalog.update_handle(second, 77)
        assert catalog.get(first).status == "processed"
        with pytest.raises(KeyError):
            catalog.get(99)
        assert catalog.has_camera_file("SN1", "IMG_0002.CR2") and not catalog.has_camera_file("SN2", "IMG_0002.CR2")
        assert catalog.file_names() == {"IMG_0001.CR2"}
        assert catalog.disagreements() == []
    after = datetime.datetime.now(datetime.UTC) + datetime.timedelta(seconds=1)
    one, two = raw_rows(path)
    assert (one["camera_serial"], one["camera_filename"], one["camera_handle"]) == ("SN1", "IMG_0001.CR2", 0x90000001)
    assert (one["status"], one["file_name"], one["size_bytes"]) == ("processed", "IMG_0001.CR2", 9)
    assert one["sha256"] == hashlib.sha256(b"raw bytes").hexdigest()
    assert one["result_path"] == "IMG_0001"  # relative to the catalog's folder
    assert one["message"] == "looked at"
    times = [utc(one[k]) for k in ("captured_at", "downloaded_at", "processed_at")]
    assert before <= times[0] <= times[1] <= times[2] <= after
    assert all(len(one[k].split(".")[1]) == len("123+00:00") for k in ("captured_at",))  # milliseconds
    assert (two["status"], two["message"], two["camera_handle"], two["file_name"]) == (
        "failed",
        "the card was pulled",
        77,
        None,
    )
    assert two["downloaded_at"] is None and two["processed_at"] is None
    # schema version and the software that wrote it
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT version FROM schema_versions WHERE name='shots'").fetchone() == (1,)
        assert db.execute("SELECT name FROM software").fetchone() == ("mca-appliance",)
        assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_the_queries_that_drive_the_next_run(tmp_path: Path) -> None:
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        captured = catalog.add_captured("SN1", "A.CR2", 1, 10)
        fetched = catalog.add_captured("SN1", "B.CR2", 2, 10)
        failed_download = catalog.add_captured("SN1", "C.CR2", 3, 10)
        failed_processing = catalog.add_captured("SN1", "D.CR2", 4, 10)
        done = catalog.add_captured("SN1", "E.CR2", 5, 10)
        other_camera = catalog.add_captured("SN2", "F.CR2", 6, 10)
        gone = catalog.add_captured("SN1", "G.CR2", 7, 10)
        for shot, name in ((fetched, "B.CR2"), (failed_processing, "D.CR2"), (done, "E.CR2"), (gone, "G.CR2")):
            (tmp_path / name).write_bytes(b"0123456789")
            catalog.mark_downloaded(shot, name, 10, hashlib.sha256(b"0123456789").hexdigest())
        catalog.mark_failed(failed_download, "disk full")
        catalog.mark_failed(failed_processing, "pipeline error")
        catalog.mark_processed(done, tmp_path / "E")
        (tmp_path / "G.CR2").unlink()  # downloaded, then deleted by hand: nothing to process
        assert [r.id for r in catalog.missing("SN1")] == [captured, failed_download]
        assert [r.id for r in catalog.missing("SN2")] == [other_camera]
        assert [r.id for r in catalog.unprocessed()] == [fetched, failed_processing]
        assert [r.id for r in catalog.pending()] == [
            captured,
            fetched,
            failed_download,
            failed_processing,
            other_camera,
            gone,
        ]
        assert [r.id for r in catalog.rows()] == list(range(1, 8))
        # downloading clears an earlier failure's message
        catalog.mark_downloaded(failed_download, "C.CR2", 10, "x")
        assert catalog.get(failed_download).message is None and catalog.get(failed_download).status == "downloaded"


def test_disagreements_with_the_folder(tmp_path: Path) -> None:
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        ok = catalog.add_captured("SN", "A.CR2", 1, 4)
        (tmp_path / "A.CR2").write_bytes(b"abcd")
        catalog.mark_downloaded(ok, "A.CR2", 4, hashlib.sha256(b"abcd").hexdigest())
        assert catalog.disagreements() == []
        (tmp_path / "A.CR2").write_bytes(b"abce")  # same size, other bytes
        problems = catalog.disagreements()
        assert (
            len(problems) == 1
            and "does not match its sha256" in problems[0]
            and "shot 1 (A.CR2, downloaded)" in problems[0]
        )
        assert catalog.disagreements(hash_files=False) == []
        (tmp_path / "A.CR2").write_bytes(b"abcde")
        assert "has 5 bytes, the catalog says 4" in catalog.disagreements()[0]
        (tmp_path / "A.CR2").unlink()
        assert "is missing" in catalog.disagreements()[0]
        (tmp_path / "A.CR2").write_bytes(b"abcd")
        catalog.mark_processed(ok, tmp_path / "A")
        assert "has no result.json" in catalog.disagreements()[0]
        (tmp_path / "A").mkdir()
        (tmp_path / "A" / "result.json").write_text("{}")
        assert catalog.disagreements() == []
        (tmp_path / "stray.cr2").write_bytes(b"x")
        (tmp_path / ".hidden.CR2").write_bytes(b"x")
        (tmp_path / "notes.txt").write_bytes(b"x")
        (tmp_path / "dir.CR2").mkdir()
        assert catalog.disagreements() == [
            f"{tmp_path / 'stray.cr2'}: a photograph in the folder that the catalog does not list"
        ]
        assert catalog.disagreements(image_suffixes=(".png",)) == []
        (tmp_path / "stray.cr2").unlink()
        odd = catalog.add_captured("SN", "B.CR2", 2, 1)
    with sqlite3.connect(tmp_path / "catalog.sqlite") as db:
        db.execute("UPDATE shots SET file_name='B.CR2' WHERE id=?", (odd,))
        db.execute("UPDATE shots SET captured_at='2024-05-01T10:00:00' WHERE id=?", (ok,))
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        problems = catalog.disagreements()
        assert any("time without UTC offset" in p for p in problems)
        assert any("has a file name but is not downloaded" in p for p in problems)
    with sqlite3.connect(tmp_path / "catalog.sqlite") as db:
        db.execute(
            "UPDATE shots SET captured_at='2024-05-01T10:00:00.000+00:00', downloaded_at='2024-05-01T09:00:00.000+00:00' WHERE id=?",
            (ok,),
        )
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        assert any("times out of order" in p for p in catalog.disagreements())


def test_paths_are_stored_relative_to_the_catalog_when_inside_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "shots").mkdir()
    with Catalog(tmp_path / "shots" / "catalog.sqlite") as catalog:
        assert catalog.stored_path(tmp_path / "shots" / "IMG_1") == "IMG_1"
        assert catalog.stored_path(tmp_path / "elsewhere") == str(tmp_path / "elsewhere")
        monkeypatch.chdir(tmp_path / "shots")
        assert catalog.stored_path("IMG_2") == "IMG_2"  # relative to the working folder, as the caller meant
        monkeypatch.chdir(tmp_path)
        assert catalog.stored_path("shots/IMG_3") == "IMG_3"
        assert catalog.resolve("IMG_1") == (tmp_path / "shots").resolve() / "IMG_1"
        assert catalog.resolve(None) is None


def test_local_times_become_utc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TZ", "Asia/Kolkata")  # UTC+05:30, no daylight saving
    time.tzset()
    try:
        assert cat.as_utc("2024-05-01T10:15:02") == "2024-05-01T04:45:02.000+00:00"
        assert cat.as_utc("2024-05-01T10:15:02.5+02:00") == "2024-05-01T08:15:02.500+00:00"
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()


VERSION_0 = """
CREATE TABLE shots (
    id INTEGER PRIMARY KEY AUTOINCREMENT, camera_serial TEXT NOT NULL, camera_filename TEXT NOT NULL,
    camera_handle INTEGER, file_name TEXT, size_bytes INTEGER, sha256 TEXT, captured_at TEXT NOT NULL,
    downloaded_at TEXT, processed_at TEXT,
    status TEXT NOT NULL CHECK (status IN ('captured', 'downloaded', 'processed', 'failed')),
    result_path TEXT, message TEXT
);
"""


def test_a_version_0_catalog_is_migrated_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TZ", "America/Sao_Paulo")  # UTC-03:00 (no daylight saving since 2019)
    time.tzset()
    try:
        folder = tmp_path / "shots"
        (folder / "IMG_0001").mkdir(parents=True)
        path = folder / "catalog.sqlite"
        with sqlite3.connect(path) as db:
            db.executescript(VERSION_0)
            rows = [
                ("SN", "IMG_0001.CR2", "2024-05-01T10:00:00", "2024-05-01T10:00:01", "2024-05-01T10:00:05", "processed", "work/shots/IMG_0001"),
                ("SN", "IMG_0002.CR2", "2024-05-01T11:00:00", None, None, "captured", None),
                ("SN", "IMG_0003.CR2", "2024-05-01T12:00:00", None, None, "failed", "nowhere/IMG_0003"),
                ("SN", "IMG_0004.CR2", "2024-05-01T12:00:00", None, None, "failed", str(folder / "IMG_0001")),
            ]  # fmt: skip
            db.executemany(
                "INSERT INTO shots (camera_serial, camera_filename, captured_at, downloaded_at, processed_at, status,"
                " result_path) VALUES (?, ?, ?, ?, ?, ?, ?)",
                rows,
            )
        Catalog(path).close()
        one, two, three, four = raw_rows(path)
        assert (one["captured_at"], one["downloaded_at"], one["processed_at"]) == (
            "2024-05-01T13:00:00.000+00:00",
            "2024-05-01T13:00:01.000+00:00",
            "2024-05-01T13:00:05.000+00:00",
        )
        assert one["result_path"] == "IMG_0001"  # found under the catalog: made relative to it
        assert two["captured_at"] == "2024-05-01T14:00:00.000+00:00" and two["downloaded_at"] is None
        assert three["result_path"] == "nowhere/IMG_0003"  # not found: kept
        assert four["result_path"] == "IMG_0001"  # absolute inside the folder: relative
        with sqlite3.connect(path) as db:
            assert db.execute("SELECT version FROM schema_versions").fetchall() == [(1,)]
        Catalog(path).close()  # a second open changes nothing
        assert raw_rows(path)[0]["captured_at"] == "2024-05-01T13:00:00.000+00:00"
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()


def test_a_newer_or_damaged_catalog_is_refused_with_what_to_do(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    Catalog(path).close()
    with sqlite3.connect(path) as db:
        db.execute("UPDATE schema_versions SET version=2 WHERE name='shots'")
    with pytest.raises(CatalogError, match="newer mca \\(catalog schema 2, this one knows up to 1\\); upgrade mca"):
        Catalog(path)
    damaged = tmp_path / "damaged" / "catalog.sqlite"
    damaged.parent.mkdir()
    damaged.write_bytes(b"not a database" * 100)
    with pytest.raises(CatalogError, match=r"cannot be opened as the catalog.*move it aside"):
        Catalog(damaged)
    assert isinstance(CatalogError("x"), sqlite3.DatabaseError)


def test_the_reserve_is_made_once_and_given_back_on_a_full_disk(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    catalog = Catalog(path)
    reserve = tmp_path / "catalog.sqlite-reserve"
    assert reserve.stat().st_size == cat.RESERVE_BYTES == 1 << 20
    stamp = reserve.stat().st_mtime_ns
    catalog.close()
    Catalog(path).close()
    assert reserve.stat().st_mtime_ns == stamp  # kept, not made again

    class FullOnce:
        """A connection whose first write fails as SQLite does on a full disk."""

        def __init__(self, db: sqlite3.Connection, failures: int) -> None:
            self.db, self.failures = db, failures

        def execute(self, sql, parameters=()):
            if sql.startswith(("INSERT", "UPDATE")) and self.failures:
                self.failures -= 1
                raise sqlite3.OperationalError("database or disk is full")
            return self.db.execute(sql, parameters)

        def __getattr__(self, name):
            return getattr(self.db, name)

    catalog = Catalog(path)
    catalog.db = FullOnce(catalog.db, 1)  # type: ignore[assignment]
    shot = catalog.add_captured("SN", "A.CR2", 1, 5)  # recorded on the second try, with the reserve given back
    assert not reserve.exists()
    assert catalog.get(shot).camera_filename == "A.CR2"
    catalog.db = FullOnce(catalog.db.db, 2)  # type: ignore[attr-defined]
    with pytest.raises(
        CatalogError, match=r"cannot record the change .*free some space on its disk; shots stay on the camera"
    ):
        catalog.add_captured("SN", "B.CR2", 2, 5)
    catalog.db = catalog.db.db  # type: ignore[attr-defined]
    catalog.close()
    Catalog(path).close()
    assert reserve.stat().st_size == 1 << 20  # the next run sets it aside again
    other = Catalog(path)
    other.db = FullOnce(other.db, 1)  # type: ignore[assignment]
    other.db.execute = lambda sql, parameters=(): (_ for _ in ()).throw(sqlite3.OperationalError("locked"))  # type: ignore[method-assign]
    with pytest.raises(CatalogError, match="cannot record the change \\(locked\\); shots stay"):
        other.mark_failed(1, "x")
    os.remove(reserve)
    other.close()


def test_the_reserve_is_an_ordinary_file_and_a_full_disk_leaves_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno
    import stat

    umask = os.umask(0o022)
    try:
        Catalog(tmp_path / "a.sqlite").close()
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "a.sqlite-reserve").stat().st_mode) == 0o644

    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", no_space)
    monkeypatch.setattr(os, "write", no_space)
    (tmp_path / "full").mkdir()
    with Catalog(tmp_path / "full" / "b.sqlite") as catalog:
        assert catalog.add_captured("SN", "A.CR2", 1, 1) == 1  # the catalog works without its reserve
    assert not (tmp_path / "full" / "b.sqlite-reserve").exists()
