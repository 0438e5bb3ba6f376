"""The shot catalog `DIR/catalog.sqlite`: one row per shot with its file, size, sha256, times and status.

Schema version 1 (kept in the `schema_versions` table, row `shots`; the table `releases` holds releases in
flight, see `add_release`):

- times are UTC with their offset, to the millisecond (`2024-05-01T10:15:02.123+00:00`);
- `file_name` and `result_path` are relative to the catalog's folder when they lie inside it
  (absolute otherwise), so the catalog means the same from any working directory and after
  the folder is moved;
- a shot is `captured` (on the card, not on disk), `downloaded` (on disk, verified), `processed`
  (its result folder finished) or `failed` (`message` says why). `pending()` lists what still
  needs work; `unprocessed()` the shots on disk whose processing did not finish.

The catalog always records what the camera took, even on a full disk: it keeps a reserve file of
1 MiB beside it (`catalog.sqlite-reserve`, next to SQLite's -wal and -shm files) and gives that
space back to SQLite when a write fails for lack of space; a later run makes it again.

A catalog without a version (version 0, the first one) is migrated in place when opened: its
local times without offset are read as this machine's local time and converted to UTC, and its
result paths, which were relative to whatever folder the writer ran in, are made relative to the
catalog when the folder is found there. A catalog from a newer mca is refused (`CatalogError`).
"""

from __future__ import annotations

import datetime
import hashlib
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path

STATUSES = ("captured", "downloaded", "processed", "failed")
SCHEMA_VERSION = 1
_SHOTS = """
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
_VERSIONS = """
CREATE TABLE IF NOT EXISTS schema_versions (name TEXT PRIMARY KEY, version INTEGER NOT NULL);
"""
# Releases in flight: written before the shutter is released, removed once the shot's files are in `shots`.
# A row left behind (the run was killed or interrupted in between) names the card as it was before that
# release, so the next connection catalogues the files the release made (`Catalog.pending_releases`).
_RELEASES = """
CREATE TABLE IF NOT EXISTS releases (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    camera_serial TEXT NOT NULL,
    released_at TEXT NOT NULL,
    card_handles TEXT NOT NULL
);
"""
_TIME_COLUMNS = ("captured_at", "downloaded_at", "processed_at")
RESERVE_BYTES = 1 << 20


class CatalogError(sqlite3.DatabaseError):
    """A catalog that cannot be used as it is; names the file and what to do (an `sqlite3.Error`, as callers that
    guard the catalog expect)."""


def _now() -> str:
    """UTC to the millisecond with its offset, from one clock reading (seconds and milliseconds must agree)."""
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")


def as_utc(text: str) -> str:
    """An ISO time as UTC with offset; a time without offset is taken as this machine's local time."""
    moment = datetime.datetime.fromisoformat(text)
    if moment.tzinfo is None:
        moment = moment.astimezone()  # naive: local time of this machine
    return moment.astimezone(datetime.UTC).isoformat(timespec="milliseconds")


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
    try:
        db = sqlite3.connect(str(path), timeout=30.0)
        db.execute("PRAGMA journal_mode=WAL")
        db.executescript(schema)
        db.commit()
    except sqlite3.DatabaseError as exc:
        raise CatalogError(
            f"{path}: cannot be opened as the catalog ({exc}); if the disk is full, free space; if the file is "
            "damaged, move it aside (the shots themselves are the files beside it)"
        ) from None
    try:
        record_software(db)
        db.commit()
    except sqlite3.OperationalError:  # a full disk: the version note waits for the next run, the catalog works
        db.rollback()
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


def schema_version(db: sqlite3.Connection) -> int:
    """The shots table's schema version (0: the first catalog, which had no version)."""
    row = db.execute("SELECT version FROM schema_versions WHERE name='shots'").fetchone()
    return 0 if row is None else int(row[0])


class Catalog:
    """A small SQLite catalog; every change is committed at once so a crash loses nothing already recorded."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.folder = self.path.resolve().parent
        self.reserve = self.folder / f"{self.path.name}-reserve"  # beside SQLite's own -wal and -shm
        self._make_reserve()
        self.db = open_database(self.path, _SHOTS + _VERSIONS + _RELEASES)
        self._migrate()

    # -- a full disk ---------------------------------------------------------------------------------------------

    def _make_reserve(self) -> None:
        """Set aside RESERVE_BYTES on the catalog's disk, if there is room (else the next run tries again)."""
        if self.reserve.exists():
            return
        try:
            fd = os.open(self.reserve, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except OSError:
            return
        try:
            try:
                os.posix_fallocate(fd, 0, RESERVE_BYTES)
            except (AttributeError, OSError):
                os.write(fd, bytes(RESERVE_BYTES))
            os.fsync(fd)
        except OSError:
            os.close(fd)
            self.reserve.unlink(missing_ok=True)
            return
        os.close(fd)

    def _write(self, sql: str, parameters: tuple = ()) -> sqlite3.Cursor:
        """Execute and commit one change; when the disk is full, give the reserve back to SQLite and try once more."""
        for attempt in range(2):
            try:
                cursor = self.db.execute(sql, parameters)
                self.db.commit()
                return cursor
            except sqlite3.OperationalError as exc:
                self.db.rollback()
                if "full" not in str(exc) or attempt or not self.reserve.exists():
                    raise CatalogError(
                        f"{self.path}: cannot record the change ({exc}); "
                        + ("free some space on its disk; " if "full" in str(exc) else "")
                        + "shots stay on the camera's card and are fetched by the next run"
                    ) from None
                self.reserve.unlink(missing_ok=True)
        raise AssertionError("unreachable")

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- versions ------------------------------------------------------------------------------------------------

    def _migrate(self) -> None:
        if schema_version(self.db) == SCHEMA_VERSION:
            return  # the usual case: nothing is written
        with self.db:  # one transaction: a migration is applied entirely or not at all
            self.db.execute("BEGIN IMMEDIATE")
            version = schema_version(self.db)
            if version > SCHEMA_VERSION:
                raise CatalogError(
                    f"{self.path}: written by a newer mca (catalog schema {version}, this one knows up to "
                    f"{SCHEMA_VERSION}); upgrade mca to use it"
                )
            if version == SCHEMA_VERSION:
                return  # another process migrated it meanwhile
            if version == 0:
                self._migrate_0_to_1()
            self.db.execute(
                "INSERT OR REPLACE INTO schema_versions (name, version) VALUES ('shots', ?)", (SCHEMA_VERSION,)
            )

    def _migrate_0_to_1(self) -> None:
        """Local times to UTC with offset; result paths relative to the catalog where the folder is found."""
        rows = self.db.execute(f"SELECT id, {', '.join(_TIME_COLUMNS)}, result_path FROM shots").fetchall()
        for shot_id, *times, result_path in rows:
            converted = [None if t is None else as_utc(t) for t in times]
            self.db.execute(
                f"UPDATE shots SET {', '.join(f'{c}=?' for c in _TIME_COLUMNS)}, result_path=? WHERE id=?",
                (*converted, self._migrated_result_path(result_path), shot_id),
            )

    def _migrated_result_path(self, text: str | None) -> str | None:
        if not text:
            return text
        given = Path(text)
        if given.is_absolute():
            return self.stored_path(given)
        for tail in [Path(*given.parts[i:]) for i in range(len(given.parts))]:  # the writer's working folder is unknown
            if (self.folder / tail).is_dir():
                return tail.as_posix()
        return text  # not found: kept as it was

    # -- paths ---------------------------------------------------------------------------------------------------

    def stored_path(self, path: str | Path) -> str:
        """How a path is kept: relative to the catalog's folder when inside it, else absolute.

        A relative `path` is relative to the current working directory, as the caller meant it.
        """
        absolute = Path(os.path.abspath(path))
        try:
            return absolute.relative_to(self.folder).as_posix()
        except ValueError:
            return str(absolute)

    def resolve(self, stored: str | None) -> Path | None:
        """The absolute path of a stored `file_name` or `result_path`."""
        return None if stored is None else (self.folder / stored)

    # -- changes -------------------------------------------------------------------------------------------------

    def add_captured(
        self, camera_serial: str, camera_filename: str, camera_handle: int | None, size_bytes: int | None
    ) -> int:
        cur = self._write(
            "INSERT INTO shots (camera_serial, camera_filename, camera_handle, size_bytes, captured_at, status)"
            " VALUES (?, ?, ?, ?, ?, 'captured')",
            (camera_serial, camera_filename, camera_handle, size_bytes, _now()),
        )
        assert cur.lastrowid is not None  # an INSERT always has one
        return int(cur.lastrowid)

    def mark_downloaded(self, shot_id: int, file_name: str, size_bytes: int, sha256: str) -> None:
        self._write(
            "UPDATE shots SET file_name=?, size_bytes=?, sha256=?, downloaded_at=?, status='downloaded',"
            " message=NULL WHERE id=?",
            (file_name, size_bytes, sha256, _now(), shot_id),
        )

    def mark_processed(self, shot_id: int, result_path: str | Path) -> None:
        """The shot's result folder is finished; `result_path` is stored relative to the catalog when inside it."""
        self._write(
            "UPDATE shots SET processed_at=?, status='processed', result_path=?, message=NULL WHERE id=?",
            (_now(), self.stored_path(result_path), shot_id),
        )

    def mark_failed(self, shot_id: int, message: str) -> None:
        self._write("UPDATE shots SET status='failed', message=? WHERE id=?", (message, shot_id))

    def note(self, shot_id: int, message: str) -> None:
        self._write("UPDATE shots SET message=? WHERE id=?", (message, shot_id))

    def update_handle(self, shot_id: int, handle: int) -> None:
        self._write("UPDATE shots SET camera_handle=? WHERE id=?", (handle, shot_id))

    def add_release(self, camera_serial: str, card_handles: frozenset[int] | set[int]) -> int:
        """Note a shutter release about to happen and the card's object handles before it (table `releases`)."""
        cur = self._write(
            "INSERT INTO releases (camera_serial, released_at, card_handles) VALUES (?, ?, ?)",
            (camera_serial, _now(), ",".join(str(h) for h in sorted(card_handles))),
        )
        assert cur.lastrowid is not None
        return int(cur.lastrowid)

    def release_done(self, release_id: int) -> None:
        """The release's files are in `shots` (or it made none): forget it."""
        self._write("DELETE FROM releases WHERE id=?", (release_id,))

    def pending_releases(self, camera_serial: str) -> list[tuple[int, frozenset[int]]]:
        """Releases of this camera whose files never reached `shots`: (id, the card's handles before it)."""
        cur = self.db.execute(
            "SELECT id, card_handles FROM releases WHERE camera_serial=? ORDER BY id", (camera_serial,)
        )
        return [(int(i), frozenset(int(h) for h in text.split(",") if h)) for i, text in cur.fetchall()]

    # -- queries -------------------------------------------------------------------------------------------------

    def rows(self) -> list[ShotRow]:
        cur = self.db.execute("SELECT * FROM shots ORDER BY id")
        return [ShotRow(*r) for r in cur.fetchall()]

    def get(self, shot_id: int) -> ShotRow:
        row = self.db.execute("SELECT * FROM shots WHERE id=?", (shot_id,)).fetchone()
        if row is None:
            raise KeyError(shot_id)
        return ShotRow(*row)

    def missing(self, camera_serial: str) -> list[ShotRow]:
        """Shots the camera took that never reached the disk: not downloaded yet, or a download that failed
        (a full disk, a pulled cable); the next connection fetches them."""
        cur = self.db.execute(
            "SELECT * FROM shots WHERE camera_serial=? AND (status='captured' OR (status='failed'"
            " AND downloaded_at IS NULL)) ORDER BY id",
            (camera_serial,),
        )
        return [ShotRow(*r) for r in cur.fetchall()]

    def unprocessed(self) -> list[ShotRow]:
        """Shots on disk whose processing never finished: downloaded, or failed after the download (a run killed
        between download and processing, a full disk); processing them again is safe."""
        cur = self.db.execute(
            "SELECT * FROM shots WHERE file_name IS NOT NULL AND downloaded_at IS NOT NULL"
            " AND status IN ('downloaded', 'failed') ORDER BY id"
        )
        return [ShotRow(*r) for r in cur.fetchall() if self.resolve(r[4]).is_file()]  # type: ignore[union-attr]

    def pending(self) -> list[ShotRow]:
        """Shots still waiting for work: everything not processed (captured, downloaded, or failed with the
        reason in `message`); later runs retry them."""
        cur = self.db.execute("SELECT * FROM shots WHERE status != 'processed' ORDER BY id")
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

    # -- checking against the disk -------------------------------------------------------------------------------

    def disagreements(self, *, hash_files: bool = True, image_suffixes: tuple[str, ...] = (".cr2",)) -> list[str]:
        """Where the catalog and its folder disagree; [] when they agree.

        Every downloaded or processed shot's file exists with its size (and sha256 with `hash_files`);
        a processed shot's result folder holds result.json; times run captured <= downloaded <= processed,
        all with an offset; and every visible file with one of `image_suffixes` in the folder is a shot.
        """
        problems = []
        listed = set()
        for row in self.rows():
            where = f"shot {row.id} ({row.camera_filename}, {row.status})"
            times = [t for t in (row.captured_at, row.downloaded_at, row.processed_at) if t is not None]
            parsed = [datetime.datetime.fromisoformat(t) for t in times]
            if any(p.utcoffset() is None for p in parsed):
                problems.append(f"{where}: a time without UTC offset: {times}")
            elif parsed != sorted(parsed):
                problems.append(f"{where}: times out of order: {times}")
            if row.file_name is not None:
                listed.add(row.file_name)
            if row.status in ("downloaded", "processed"):
                path = self.resolve(row.file_name)
                if path is None or not path.is_file():
                    problems.append(f"{where}: its file {path} is missing")
                elif path.stat().st_size != row.size_bytes:
                    problems.append(
                        f"{where}: {path} has {path.stat().st_size} bytes, the catalog says {row.size_bytes}"
                    )
                elif hash_files and _sha256(path) != row.sha256:
                    problems.append(f"{where}: {path} does not match its sha256")
            if row.status == "processed":
                result = self.resolve(row.result_path)
                if result is None or not (result / "result.json").is_file():
                    problems.append(f"{where}: its result folder {result} has no result.json")
            if row.status == "captured" and row.file_name is not None:
                problems.append(f"{where}: has a file name but is not downloaded")
        for entry in sorted(os.listdir(self.folder)):
            path = self.folder / entry
            if entry.startswith(".") or not path.is_file() or path.suffix.lower() not in image_suffixes:
                continue
            if entry not in listed:
                problems.append(f"{path}: a photograph in the folder that the catalog does not list")
        return problems


def _sha256(path: Path) -> str:
    sha = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            sha.update(block)
    return sha.hexdigest()
