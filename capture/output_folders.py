"""Output folders of `mca process`: safe unique names, one lock per folder, staging, replace-then-delete, recovery.

Inside an output root OUT every name we create besides the result folders is hidden:

    OUT/NAME/                         a finished result folder; its result.json names the input (path, sha256)
    OUT/.mca.lock                     the root lock, held for moments: while a name is chosen or a folder swapped
    OUT/.NAME.mca-lock                held while a run works on NAME; says which input it works for
    OUT/.NAME.mca-staging-PID-HEX/    where that run writes NAME's new outputs
    OUT/.NAME.mca-replaced-HEX/       NAME's previous outputs, from the swap until they are deleted

A folder name comes from the input's stem, made safe (never `.`, `..`, hidden, a path or a
symbolic link, always inside OUT); when that name belongs to a different input, the next
free one (`NAME-2`, `NAME-3`, ...) is used, so different photographs never share a folder.
The owner of a folder is matched by the input's resolved path first, then by its content
(sha256): a changed photograph at the same path replaces its old result, a copy of an
already processed one finds it.

New outputs are written into a staging folder and swapped in only when complete
(`FolderClaim.commit`): the old folder is renamed aside, the new one renamed into place, the
old one deleted. A run killed at any moment leaves either the old result or the new one
visible, never a mixture; the next run that claims the name finishes or undoes the swap
(`recover_name`). A folder that exists but is not an mca result (a user's folder, a
symbolic link) is never written into or deleted: its name is skipped.

Locks are `flock` locks: the kernel drops them when a process dies, so a killed run never
leaves a folder locked. They need a local file system or NFSv4.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import shutil
import time
import unicodedata
import uuid
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

RESULT_NAME = "result.json"  # written last into a folder: its presence makes a folder a result
ROOT_LOCK_NAME = ".mca.lock"
LOCK_SUFFIX = ".mca-lock"
STAGING_MARK = ".mca-staging-"
REPLACED_MARK = ".mca-replaced-"
MAX_NAME_CHARS = 100
MAX_CANDIDATES = 10_000
WAIT_POLL_S = 0.2

# What the writers put into a result folder (capture/pipeline_app.py, docs/outputs.md); a folder holding only
# these names (and no result.json) is what an earlier mca left when it was killed half-way.
OUTPUT_NAMES = frozenset(
    {
        "depth.tiff",
        "disparity.tiff",
        "regions.png",
        "all_in_focus.png",
        "scene.ply",
        "scene.glb",
        "recording.rrd",
        RESULT_NAME,
        "layers",
    }
)
_SIGNATURE_OUTPUTS = OUTPUT_NAMES - {"layers", "recording.rrd"}
_OUR_TEMP = re.compile(r"^\..+\.\d+\.[0-9a-f]+\.tmp$")  # outputs.temporary_name
_LAYER = re.compile(r"^\d{2,}\.png$")
_HIDDEN_OF_NAME = re.compile(r"^\.(?P<name>.+?)(?:\.mca-lock|\.mca-staging-\d+-[0-9a-f]+|\.mca-replaced-[0-9a-f]+)$")


class OutputFolderError(RuntimeError):
    """An output root or folder that cannot be used; the message names it and says what to do."""


# --- names ----------------------------------------------------------------------------------------------------------

_UNSAFE = re.compile(r"[\x00-\x1f\x7f/\\:*?\"<>|]")


def safe_folder_name(text: str, fallback: str = "photo") -> str:
    """A folder name made from `text` that is a plain, visible name: no separators or control characters,
    not `.`/`..`, not hidden, at most 100 characters. Leading dots are dropped ("...CR2" -> "CR2")."""
    cleaned = unicodedata.normalize("NFC", text)
    cleaned = "".join(ch if ch.isprintable() else "_" for ch in cleaned)
    cleaned = _UNSAFE.sub("_", cleaned).strip(" ").lstrip(".").rstrip(". ")
    cleaned = cleaned[:MAX_NAME_CHARS].rstrip(". ")
    return cleaned or fallback


def output_name_for(input_path: str | os.PathLike[str]) -> str:
    """The preferred folder name of an input: its stem made safe; a stem that is only dots gives the whole name."""
    path = Path(input_path)
    name = safe_folder_name(path.stem, fallback="")
    if not name:
        name = safe_folder_name(path.name.replace(".", "_").strip("_"), fallback="photo")
    return name


def _candidates(preferred: str) -> Iterator[str]:
    yield preferred
    for index in range(2, MAX_CANDIDATES):
        yield f"{preferred}-{index}"


# --- the input's identity -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SourceId:
    """What identifies an input: its resolved path and its content."""

    path: str  # resolved, absolute
    sha256: str
    size_bytes: int
    mtime_ns: int

    def matches_path(self, owner: dict[str, Any]) -> bool:
        return bool(owner.get("path")) and owner.get("path") == self.path

    def matches_content(self, owner: dict[str, Any]) -> bool:
        return bool(owner.get("sha256")) and owner.get("sha256") == self.sha256


def source_identity(path: str | os.PathLike[str]) -> SourceId:
    """Resolved path, sha256, size and modification time of an input file (read once, in 1 MiB blocks).

    Never blocks on a FIFO: raises `capture.raw.NotARegularFileError` for anything but a regular file,
    `OSError` when it cannot be opened.
    """
    from mca.capture.raw import regular_file_descriptor

    fd = regular_file_descriptor(path)
    with os.fdopen(fd, "rb", closefd=True) as handle:
        info = os.fstat(handle.fileno())
        sha = hashlib.sha256()
        for block in iter(lambda: handle.read(1 << 20), b""):
            sha.update(block)
    return SourceId(os.path.realpath(path), sha.hexdigest(), info.st_size, info.st_mtime_ns)


# --- locks ----------------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def root_lock(root: Path) -> Iterator[None]:
    """Hold the output root's lock (`OUT/.mca.lock`): name choices and swaps happen one at a time."""
    fd = os.open(root / ROOT_LOCK_NAME, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing drops the lock


class NameLock:
    """`OUT/.NAME.mca-lock`, held while a run works on NAME; its content names the input (JSON)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self.fd = fd

    @classmethod
    def try_acquire(cls, root: Path, name: str) -> NameLock | None:
        """The lock, or None when another run holds it (never waits). Call with the root lock held."""
        path = root / f".{name}{LOCK_SUFFIX}"
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        except BaseException:
            os.close(fd)
            raise
        return cls(path, fd)

    def write_owner(self, owner: dict[str, Any]) -> None:
        data = json.dumps(owner).encode("utf-8")
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, data, 0)

    def release(self) -> None:
        """Delete the lock file, then drop the lock. Call with the root lock held (no one can open it meanwhile)."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        os.close(self.fd)


def lock_owner(root: Path, name: str) -> dict[str, Any]:
    """What the lock file of NAME says about the input being worked on ({} when unreadable)."""
    try:
        data = json.loads((root / f".{name}{LOCK_SUFFIX}").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


# --- what a folder is -----------------------------------------------------------------------------------------------


def read_result(folder: Path) -> dict[str, Any] | None:
    """The folder's result.json as a dict, None when absent or unreadable."""
    try:
        data = json.loads((folder / RESULT_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def result_owner(document: dict[str, Any]) -> dict[str, Any]:
    """{path, sha256} of the input a result.json was made from (an earlier mca wrote only `input`)."""
    source = document.get("source")
    if isinstance(source, dict):
        return {"path": source.get("path"), "sha256": source.get("sha256")}
    given = document.get("input")
    return {"path": os.path.realpath(given) if isinstance(given, str) and given else None, "sha256": None}


def _is_legacy_partial(folder: Path, names: list[str]) -> bool:
    """A folder an earlier mca left half-written: only output names, at least one output or temporary file of ours."""
    ours = False
    for name in names:
        entry = folder / name
        if _OUR_TEMP.match(name):
            ours = True
            continue
        if name not in OUTPUT_NAMES or entry.is_symlink():
            return False
        if name == "layers":
            if not entry.is_dir():
                return False
            for layer in os.listdir(entry):
                if not (_LAYER.match(layer) or _OUR_TEMP.match(layer)) or (entry / layer).is_symlink():
                    return False
        elif entry.is_file():
            ours = ours or name in _SIGNATURE_OUTPUTS
        else:
            return False
    return ours


def folder_kind(folder: Path) -> str:
    """ "absent", "result" (a finished mca folder), "empty", "partial" (an earlier mca's unfinished folder)
    or "foreign" (anything else: a file, a symbolic link, a folder of somebody else's files)."""
    if folder.is_symlink():
        return "foreign"
    if not folder.exists():
        return "absent"
    if not folder.is_dir():
        return "foreign"
    try:
        names = os.listdir(folder)
    except OSError:
        return "foreign"
    if not names:
        return "empty"
    if RESULT_NAME in names:
        document = read_result(folder)
        return "result" if document is not None and "outputs" in document else "foreign"
    return "partial" if _is_legacy_partial(folder, names) else "foreign"


# --- recovery -------------------------------------------------------------------------------------------------------


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _remove_tree(path: Path) -> None:
    if path.is_symlink() or not path.is_dir():
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        return
    shutil.rmtree(path, ignore_errors=True)


def _hidden_of(root: Path, name: str, mark: str) -> list[Path]:
    prefix = f".{name}{mark}"
    try:
        entries = [root / entry for entry in os.listdir(root) if entry.startswith(prefix)]
    except OSError:
        return []
    return sorted(entries, key=lambda p: (p.stat().st_mtime_ns if p.exists() else 0, p.name))


def _swap_in(root: Path, name: str, staging: Path) -> Path | None:
    """Rename the current folder NAME aside (if any) and `staging` into its place; the aside folder, to delete."""
    final = root / name
    aside = None
    if final.exists() or final.is_symlink():
        aside = root / f".{name}{REPLACED_MARK}{uuid.uuid4().hex[:12]}"
        os.rename(final, aside)
    os.rename(staging, final)
    _fsync_dir(root)
    return aside


def recover_name(root: Path, name: str) -> None:
    """Finish or undo what a killed run left for NAME; call with the root lock and NAME's lock held.

    A complete staging folder (it has result.json) is swapped in, as its run was about to do;
    otherwise a folder renamed aside is put back if NAME is missing. The rest is deleted.
    """
    staging = _hidden_of(root, name, STAGING_MARK)
    replaced = _hidden_of(root, name, REPLACED_MARK)
    if not staging and not replaced:
        return
    final = root / name
    kind = folder_kind(final)
    complete = [s for s in staging if not s.is_symlink() and (s / RESULT_NAME).is_file()]
    if complete and kind in ("absent", "empty", "partial", "result"):
        aside = _swap_in(root, name, complete[-1])
        if aside is not None:
            replaced.append(aside)
    elif kind == "absent" and replaced and not replaced[-1].is_symlink():
        os.rename(replaced[-1], final)
        _fsync_dir(root)
    for leftover in staging + replaced:
        if leftover.exists() or leftover.is_symlink():
            _remove_tree(leftover)


def recover_root(root: Path) -> int:
    """Clean up after killed runs in the whole output root (root lock held); returns the names recovered."""
    try:
        entries = os.listdir(root)
    except OSError:
        return 0
    names = {m.group("name") for m in map(_HIDDEN_OF_NAME.match, entries) if m}
    recovered = 0
    for name in sorted(names):
        lock = NameLock.try_acquire(root, name)
        if lock is None:
            continue  # a live run works on it
        try:
            recover_name(root, name)
            recovered += 1
        finally:
            lock.release()
    return recovered


# --- claiming a folder ----------------------------------------------------------------------------------------------


def prepare_root(out_root: str | os.PathLike[str]) -> Path:
    """Create the output root if needed and return it resolved; an `OutputFolderError` says why it cannot be."""
    root = Path(out_root)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputFolderError(f"the output folder {root} is a file; give a folder for the outputs") from None
    except NotADirectoryError:
        raise OutputFolderError(
            f"cannot create the output folder {root}: a part of its path is a file, not a folder"
        ) from None
    except OSError as exc:
        raise OutputFolderError(f"cannot create the output folder {root}: {exc.strerror or exc}") from None
    if not root.is_dir():
        raise OutputFolderError(f"the output folder {root} is not a folder")
    if not os.access(root, os.W_OK | os.X_OK):
        raise OutputFolderError(f"the output folder {root} is not writable by this user; fix its permissions")
    return root.resolve()


@dataclass
class FolderClaim:
    """NAME inside the output root, locked for this run until released."""

    root: Path
    name: str
    lock: NameLock

    @property
    def final(self) -> Path:
        return self.root / self.name

    def existing_result(self) -> dict[str, Any] | None:
        """The finished result.json now in the folder, if any."""
        return read_result(self.final) if folder_kind(self.final) == "result" else None

    def staging_path(self) -> Path:
        """A fresh name for a hidden folder beside NAME to write the new outputs into (this process's id and a
        random part: whatever comes to be there is this run's). The caller makes it inside the `try` whose
        `finally` discards it: a Ctrl-C that lands just after the mkdir must not leave it behind."""
        return self.root / f".{self.name}{STAGING_MARK}{os.getpid()}-{uuid.uuid4().hex[:8]}"

    def commit(self, staging: Path) -> Path:
        """Make `staging` the folder NAME (files fsynced first); the previous folder is deleted afterwards."""
        for folder, _, files in os.walk(staging):
            for file_name in files:
                with contextlib.suppress(OSError):
                    fd = os.open(os.path.join(folder, file_name), os.O_RDONLY)
                    try:
                        os.fsync(fd)
                    finally:
                        os.close(fd)
            _fsync_dir(Path(folder))
        with root_lock(self.root):
            kind = folder_kind(self.final)
            if kind == "foreign":
                raise OutputFolderError(
                    f"{self.final} appeared while this photograph was processed and is not an mca output folder; "
                    "move it away and rerun"
                )
            aside = _swap_in(self.root, self.name, staging)
        if aside is not None:
            _remove_tree(aside)
        return self.final

    def discard(self, staging: Path) -> None:
        if staging.exists() or staging.is_symlink():
            _remove_tree(staging)

    def release(self) -> None:
        with root_lock(self.root):
            self.lock.release()


def _choose(root: Path, preferred: str, source: SourceId) -> tuple[str, NameLock | None]:
    """Under the root lock: (NAME, its lock) for this input, or (NAME, None) when another run holds the folder
    of this very input (wait and try again).

    The candidates are NAME, NAME-2, ... up to the first name with neither folder nor lock. The
    folder whose result names this input's path wins; else one holding the same content; else the
    first free (absent, empty, or an earlier mca's unfinished) name. Foreign folders are passed over.
    """
    held: dict[str, NameLock] = {}
    by_content: str | None = None
    free: str | None = None
    busy_same: str | None = None
    chosen: str | None = None
    try:
        for name in _candidates(preferred):
            final = root / name
            lock_path = root / f".{name}{LOCK_SUFFIX}"
            last = not (final.exists() or final.is_symlink() or lock_path.exists())
            if last and free is not None:
                break
            lock = NameLock.try_acquire(root, name)
            if lock is None:  # another run works on NAME right now
                owner = lock_owner(root, name)
                if busy_same is None and (source.matches_path(owner) or source.matches_content(owner)):
                    busy_same = name
                continue
            held[name] = lock
            if last:
                free = name
                break
            recover_name(root, name)
            kind = folder_kind(final)
            if kind == "result":
                owner = result_owner(read_result(final) or {})
                if source.matches_path(owner):
                    chosen = name
                    break
                if by_content is None and source.matches_content(owner):
                    by_content = name
                    continue
            elif kind in ("absent", "empty", "partial") and free is None:
                free = name
                continue
            held.pop(name).release()
        if chosen is None and busy_same is not None:
            return busy_same, None
        chosen = chosen or by_content or free
        if chosen is None:
            raise OutputFolderError(
                f"no free folder name for {preferred!r} in {root} after {MAX_CANDIDATES} tries; clean up the folder"
            )
        return chosen, held.pop(chosen)
    finally:
        for lock in held.values():
            lock.release()


@contextlib.contextmanager
def claim_folder(
    out_root: Path,
    preferred: str,
    source: SourceId,
    *,
    on_wait: Callable[[str], None] | None = None,
    poll_s: float = WAIT_POLL_S,
) -> Iterator[FolderClaim]:
    """Lock the output folder of `source` for this run: its own folder if it has one, else a new free name.

    While another run works on the same input, waits for it (calling `on_wait(name)` once), so
    that this run then finds its result. Stale leftovers of killed runs are cleaned up first.
    """
    root = Path(out_root)
    preferred = safe_folder_name(preferred)
    announced = False
    while True:
        with root_lock(root):
            recover_root(root)
            name, lock = _choose(root, preferred, source)
            if lock is not None:
                lock.write_owner({**asdict(source), "pid": os.getpid()})
        if lock is not None:
            break
        if on_wait is not None and not announced:
            announced = True
            with contextlib.suppress(Exception):
                on_wait(name)
        time.sleep(poll_s)
    claim = FolderClaim(root, name, lock)
    try:
        yield claim
    finally:
        claim.release()


__all__ = [
    "RESULT_NAME",
    "FolderClaim",
    "OutputFolderError",
    "SourceId",
    "claim_folder",
    "folder_kind",
    "output_name_for",
    "prepare_root",
    "read_result",
    "recover_root",
    "result_owner",
    "safe_folder_name",
    "source_identity",
]
