"""The shot catalog `DIR/catalog.sqlite`: one row per shot with its file, size, sha256, times and status."""

from __future__ import annotations

import datetime
import sqlite3
from dataclasses import dataclass
from pathlib import Path

STATUSES = ("captured", "downloaded", "processed", "failed")
_SCHEMA = """
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
"""


def _now() -> str:
    """Local time to the millisecond, from one clock reading (seconds and milliseconds must agree)."""
    return datetime.datetime.now().isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class ShotRow:
    id: int
    camera_serial: str
    camera_filename: str
    camera_handle: int | None
    file_name: str | None
    size_bytes: int | None
    sha256: str | None
    captured_at: str
    downloaded_at: str | None
    processed_at: str | None
    status: str
    result_path: str | None
    message: str | None


def open_database(path: Path, schema: str) -> sqlite3.Connection:
    """Open (creating) the folder's SQLite catalog in WAL mode with `schema` applied; shared by every table in it."""
    db = sqlite3.connect(str(path))
    db.execute("PRAGMA journal_mode=WAL")
    db.executescript(schema)
    record_software(db)
    db.commit()
    return db


def record_software(db: sqlite3.Connection) -> None:
    """Note in the catalog which software version last wrote to it (table `software`, one row per name)."""
    from mca import __version__

    db.execute("CREATE TABLE IF NOT EXISTS software (name TEXT PRIMARY KEY, version TEXT NOT NULL, seen_at TEXT)")
    db.execute(
        "INSERT INTO software (name, version, seen_at) VALUES ('mca-appliance', ?, ?) "
        "ON CONFLICT(name) DO UPDATE SET version = excluded.version, seen_at = excluded.seen_at",
        (__version__, _now()),
    )


class Catalog:
    """A small SQLite catalog; every change is committed at once so a crash loses nothing already recorded."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.db = open_database(self.path, _SCHEMA)

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_captured(
        self, camera_serial: str, camera_filename: str, camera_handle: int | None, size_bytes: int | None
    ) -> int:
        cur = self.db.execute(
            "INSERT INTO shots (camera_serial, camera_filename, camera_handle, size_bytes, captured_at, status)"
            " VALUES (?, ?, ?, ?, ?, 'captured')",
            (camera_serial, camera_filename, camera_handle, size_bytes, _now()),
        )
        self.db.commit()
        return int(cur.lastrowid)

    def mark_downloaded(self, shot_id: int, file_name: str, size_bytes: int, sha256: str) -> None:
        self.db.execute(
            "UPDATE shots SET file_name=?, size_bytes=?, sha256=?, downloaded_at=?, status='downloaded',"
            " message=NULL WHERE id=?",
            (file_name, size_bytes, sha256, _now(), shot_id),
        )
        self.db.commit()

    def mark_processed(self, shot_id: int, result_path: str) -> None:
        self.db.execute(
            "UPDATE shots SET processed_at=?, status='processed', result_path=?, message=NULL WHERE id=?",
            (_now(), result_path, shot_id),
        )
        self.db.commit()

    def mark_failed(self, shot_id: int, message: str) -> None:
        self.db.execute("UPDATE shots SET status='failed', message=? WHERE id=?", (message, shot_id))
        self.db.commit()

    def note(self, shot_id: int, message: str) -> None:
        self.db.execute("UPDATE shots SET message=? WHERE id=?", (message, shot_id))
        self.db.commit()

    def update_handle(self, shot_id: int, handle: int) -> None:
        self.db.execute("UPDATE shots SET camera_handle=? WHERE id=?", (handle, shot_id))
        self.db.commit()

    def rows(self) -> list[ShotRow]:
        cur = self.db.execute("SELECT * FROM shots ORDER BY id")
        return [ShotRow(*r) for r in cur.fetchall()]

    def get(self, shot_id: int) -> ShotRow:
        row = self.db.execute("SELECT * FROM shots WHERE id=?", (shot_id,)).fetchone()
        if row is None:
            raise KeyError(shot_id)
        return ShotRow(*row)

    def missing(self, camera_serial: str) -> list[ShotRow]:
        """Shots the camera took that never reached the disk."""
        cur = self.db.execute(
            "SELECT * FROM shots WHERE camera_serial=? AND status='captured' ORDER BY id", (camera_serial,)
        )
        return [ShotRow(*r) for r in cur.fetchall()]

    def file_names(self) -> set[str]:
        return {r[0] for r in self.db.execute("SELECT file_name FROM shots WHERE file_name IS NOT NULL")}

    def has_camera_file(self, camera_serial: str, camera_filename: str) -> bool:
        return (
            self.db.execute(
                "SELECT 1 FROM shots WHERE camera_serial=? AND camera_filename=?", (camera_serial, camera_filename)
            ).fetchone()
            is not None
        )
