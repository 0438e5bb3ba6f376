"""Fault-injection driver for the main job (tethered capture -> download -> process -> record), run by
tests/test_main_job_faults.py in its own process (and mount namespace, when one can be made).

The camera is the simulated EOS 70D served over PTP/IP by `mca camera serve-sim` in a process of
its own, so that its card outlives the runs that are killed, as a real camera's does. The runs
reach it through a TCP proxy that can pull the cable (drop every connection). Each round runs
the real `mca capture --process --record` in a subprocess and injects one fault:

- `sigkill` / `sigint`: the signal at a random moment of the run;
- `disconnect`: the proxy drops the connections once or twice while the run goes on;
- `disk-full`: the output folder's file system is filled to within a random few hundred kB
  (a size-limited tmpfs when a mount namespace can be made, else a shim in the run's Python
  that fails writes under the output folder with ENOSPC after a byte budget);
- `concurrent`: two `mca process OUT --out OUT` batches run against the same folder while the
  capture processes into it, one of them killed at a random moment.

After every round it checks: nothing outside the output folder changed; no partial output is
visible (every visible result folder is complete and made from the photograph beside it; no
visible temporary or partial file); the catalog agrees with the disk (`Catalog.disagreements`);
and every shot in the catalog is processed or pending. At the end, runs without faults must leave
every catalogued shot processed and nothing of ours half-done. Exposures on the camera's card
that the catalog does not list at the end are reported apart (`unlisted_exposures`). It prints
one JSON line with the counts.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

FAULTS = ("sigkill", "sigint", "disconnect", "disk-full", "concurrent")
OUR_LEFTOVERS = re.compile(r"^\..+\.mca-(staging|replaced)-")


# --- the cable ------------------------------------------------------------------------------------------------------


class Proxy:
    """A TCP forwarder on 127.0.0.1 that can drop every connection at once (a pulled cable)."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.lock = threading.Lock()
        self.sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            try:
                server = socket.create_connection(self.upstream, timeout=5)
                server.settimeout(None)
            except OSError:
                client.close()
                continue
            with self.lock:
                self.sockets += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        try:
            while True:
                data = source.recv(1 << 16)
                if not data:
                    break
                sink.sendall(data)
        except OSError:
            pass
        for sock in (source, sink):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def drop_all(self) -> int:
        with self.lock:
            dropped, self.sockets = self.sockets, []
        for sock in dropped:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()
        return len(dropped) // 2


# --- a full disk ----------------------------------------------------------------------------------------------------


def mount_tmpfs(folder: Path, size_mb: int) -> bool:
    """Mount a size-limited tmpfs on `folder` (needs a mount namespace of our own: see the test)."""
    if os.environ.get("MCA_FAULTS_IN_NAMESPACE") != "1":
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(folder)], check=False)
    return done.returncode == 0


SHIM = """
import builtins, errno, io, os, sys
limit, root = int(sys.argv[1]), os.path.realpath(sys.argv[2])
written = [0]
real_open = builtins.open


class Counted:
    def __init__(self, handle):
        self._handle = handle

    def write(self, data):
        written[0] += len(data)
        if written[0] > limit:
            raise OSError(errno.ENOSPC, "No space left on device (simulated)")
        return self._handle.write(data)

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._handle.close()

    def __iter__(self):
        return iter(self._handle)


def counted_open(file, mode="r", *args, **kwargs):
    handle = real_open(file, mode, *args, **kwargs)
    if any(c in mode for c in "wax+") and isinstance(file, (str, os.PathLike)):
        if os.path.realpath(file).startswith(root + os.sep):
            return Counted(handle)
    return handle


builtins.open = counted_open
io.open = counted_open
sys.argv = ["mca", *sys.argv[3:]]
from mca.capture.cli import app
app(prog_name="mca")
"""


# --- checks ---------------------------------------------------------------------------------------------------------


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def snapshot(folder: Path) -> dict[str, tuple[int, str]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, sha256(p)) for p in sorted(folder.rglob("*")) if p.is_file()}


class Checker:
    def __init__(self, out: Path, outside: list[Path], cwd: Path, camera_address: tuple[str, int]) -> None:
        self.out = out
        self.outside = {folder: snapshot(folder) for folder in outside}
        self.cwd = cwd
        self.camera_address = camera_address
        self.files_checked = 0
        self.unlisted: list[str] = []  # exposures on the card that the catalog does not know

    def card_files(self) -> list[str]:
        from mca.devices.cameras import open_camera
        from mca.devices.ptp.codes import ObjectFormat

        host, port = self.camera_address
        for attempt in range(20):
            try:
                camera = open_camera(f"ptpip:{host}:{port}", timeout_s=5.0)()
                break
            except Exception:
                time.sleep(0.25 * (attempt + 1))
        else:
            raise RuntimeError("cannot reach the simulated camera to list its card")
        try:
            return sorted(info.filename for _, info in camera.files() if info.object_format != ObjectFormat.ASSOCIATION)
        finally:
            camera.close()

    def check(self, final: bool = False, with_catalog: bool = True) -> tuple[list[str], dict[str, int]]:
        from mca.capture.catalog import Catalog

        problems: list[str] = []
        for folder, before in self.outside.items():
            after = snapshot(folder)
            self.files_checked += len(after)
            if after != before:
                problems.append(f"outside --out: {folder} changed")
        if any(self.cwd.iterdir()):
            problems.append(f"the working folder got files: {sorted(p.name for p in self.cwd.iterdir())}")
        if not self.out.exists():
            return problems, {}
        for entry in sorted(self.out.iterdir()):
            name = entry.name
            if name.startswith("."):
                if final and OUR_LEFTOVERS.match(name):
                    problems.append(f"a leftover of a killed run after the clean runs: {name}")
                continue
            if entry.is_dir():
                problems += self._check_result(entry)
            elif name.endswith((".part", ".tmp")):
                problems.append(f"a partial file is visible: {name}")
        if not with_catalog:  # on a full disk SQLite cannot even open the catalog to read it
            return problems, {}
        with Catalog(self.out / "catalog.sqlite") as catalog:
            problems += catalog.disagreements(hash_files=True)
            rows = catalog.rows()
            pending = {r.id for r in catalog.pending()} | {r.id for r in catalog.unprocessed()}
        self.files_checked += sum(1 for r in rows if r.file_name)
        statuses = Counter(r.status for r in rows)
        for row in rows:
            if row.status != "processed" and row.id not in pending:
                problems.append(f"shot {row.id} ({row.camera_filename}) is {row.status}, neither processed nor pending")
            if row.status == "processed":
                result = json.loads((self.out / row.result_path / "result.json").read_text())
                if result.get("source", {}).get("sha256") != row.sha256:
                    problems.append(f"shot {row.id}: its result was made from another photograph")
        listed = {r.camera_filename for r in rows}
        card = self.card_files()
        self.unlisted = [name for name in card if name not in listed]
        if final:
            not_done = [f"{r.id}:{r.status}:{r.message}" for r in rows if r.status != "processed"]
            if not_done:
                problems.append(f"after the clean runs, shots still not processed: {not_done}")
        counts = {
            "exposures": len(card),
            "processed": statuses["processed"],
            "pending": len(pending),
        }
        return problems, counts

    def _check_result(self, folder: Path) -> list[str]:
        problems = []
        result = folder / "result.json"
        if not result.is_file():
            return [f"a result folder without result.json is visible: {folder.name}"]
        document = json.loads(result.read_text())
        for name in document.get("outputs", []):
            self.files_checked += 1
            if not (folder / name).is_file() or (folder / name).stat().st_size == 0:
                problems.append(f"{folder.name}/{name} listed in result.json is missing or empty")
        for path in folder.rglob("*"):
            if path.name.startswith("."):
                problems.append(f"a hidden (temporary) file inside a result folder: {path.relative_to(self.out)}")
        photo = Path(document.get("source", {}).get("path", ""))
        if photo.parent == self.out and photo.is_file():
            self.files_checked += 1
            if sha256(photo) != document["source"]["sha256"]:
                problems.append(f"{folder.name}: result.json names content that {photo.name} does not hold")
        return problems


# --- the rounds -----------------------------------------------------------------------------------------------------


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--shots", type=int, default=2)
    parser.add_argument("--seed", type=int, default=13)
    parser.add_argument("--tmpfs-mb", type=int, default=96)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    work = args.work
    disk = work / "disk"
    disk.mkdir(parents=True, exist_ok=True)
    tmpfs = mount_tmpfs(disk, args.tmpfs_mb)
    out, cwd, outside_same_fs, outside_other = disk / "out", disk / "cwd", disk / "outside", work / "outside"
    for folder in (cwd, outside_same_fs, outside_other):
        folder.mkdir(parents=True, exist_ok=True)
    for folder in (outside_same_fs, outside_other):  # what a careless writer could hit: a sibling of --out
        (folder / "layers").mkdir(exist_ok=True)
        (folder / "layers" / "00.png").write_bytes(b"user's own")
        (folder / "result.json").write_text("{}")
        (folder / "IMG_0001.CR2").write_bytes(os.urandom(1000))
    env = dict(os.environ, RERUN_ANALYTICS="0", MCA_SIM_SIZE=os.environ.get("MCA_SIM_SIZE", "0.1"))
    mca = [sys.executable, "-m", "mca"]
    camera = subprocess.Popen(
        [*mca, "camera", "serve-sim", "--ptpip", "127.0.0.1:0"], stderr=subprocess.PIPE, text=True, env=env, cwd=cwd
    )
    line = camera.stderr.readline()
    match = re.search(r"ptpip:127\.0\.0\.1:(\d+)", line)
    if not match:
        print(json.dumps({"problems": [f"the simulated camera did not start: {line}"]}))
        return 1
    camera_address = ("127.0.0.1", int(match.group(1)))
    proxy = Proxy(camera_address)
    checker = Checker(out, [outside_same_fs, outside_other], cwd, camera_address)
    faults: Counter[str] = Counter()
    problems: list[str] = []
    findings: list[str] = []  # not failures of the data invariants, reported
    rounds_log = []

    def capture_command(label: str, count: int = args.shots) -> list[str]:
        return [
            "capture",
            "--camera",
            f"ptpip:127.0.0.1:{proxy.port}",
            "--count",
            str(count),
            "--out",
            str(out),
            "--process",
            "--profile",
            "paper-70d",
            "--record",
            str(out / f"session-{label}.rrd"),
        ]

    def start(command: list[str], budget: int | None = None) -> subprocess.Popen:
        argv = [*mca, *command] if budget is None else [sys.executable, "-c", SHIM, str(budget), str(out), *command]
        return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)

    def finish(proc: subprocess.Popen, fault: str = "", timeout_s: float = 180.0) -> str:
        try:
            _, err = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
            problems.append(f"a run hung for {timeout_s:.0f} s and was killed: {err[-500:]}")
        if "Traceback (most recent call last)" in err:
            last = err[err.rindex("Traceback") :].strip().splitlines()
            where = [line.strip() for line in last if line.strip().startswith("File ")][-1:]
            text = f"{' '.join(where)} {last[-1]}"
            if fault == "disk-full":  # a full disk ends `mca capture` with a traceback: issue 13 item 8 (tethering)
                findings.append(f"traceback on a full disk: {text}")
            else:
                problems.append(f"a run ended with a traceback: {text}")
        return err

    try:
        for round_number in range(args.rounds):
            fault = FAULTS[round_number % len(FAULTS)] if round_number < len(FAULTS) else rng.choice(FAULTS)
            ballast = disk / "ballast"
            note = ""
            if fault == "disk-full" and tmpfs:
                free = shutil.disk_usage(disk).free
                keep = rng.randint(50_000, 1_500_000)
                with open(ballast, "wb") as handle:
                    handle.truncate(0)
                    block = b"\0" * (1 << 20)
                    remaining = max(0, free - keep)
                    while remaining > 0:
                        try:
                            remaining -= handle.write(block[: min(len(block), remaining)])
                        except OSError:
                            break
                note = f"{shutil.disk_usage(disk).free} bytes left"
                proc = start(capture_command(f"{round_number:02d}"))
            elif fault == "disk-full":
                budget = rng.randint(50_000, 1_500_000)
                note = f"writes fail after {budget} bytes"
                proc = start(capture_command(f"{round_number:02d}"), budget=budget)
            else:
                proc = start(capture_command(f"{round_number:02d}"))
            started = time.monotonic()
            if fault in ("sigkill", "sigint"):
                time.sleep(rng.uniform(0.8, 5.0))
                if proc.poll() is None:
                    proc.send_signal(signal.SIGKILL if fault == "sigkill" else signal.SIGINT)
                    faults[fault] += 1
                    note = f"after {time.monotonic() - started:.1f} s"
                else:
                    note = "the run had finished"
            elif fault == "disconnect":
                for _ in range(rng.randint(1, 2)):
                    time.sleep(rng.uniform(0.5, 4.0))
                    if proc.poll() is None and proxy.drop_all():
                        faults[fault] += 1
            elif fault == "disk-full":
                faults[fault] += 1
            elif fault == "concurrent":
                batches = [
                    start(["process", str(out), "--out", str(out), "--profile", "paper-70d", "--workers", "1", "-q"])
                    for _ in range(2)
                ]
                faults[fault] += 1
                time.sleep(rng.uniform(0.5, 5.0))
                victim = batches[rng.randrange(2)]
                if victim.poll() is None:
                    victim.send_signal(signal.SIGKILL)
                    faults["sigkill"] += 1
                for batch in batches:
                    finish(batch)
            finish(proc, fault)
            round_problems, counts = checker.check(with_catalog=not ballast.exists())
            if ballast.exists():
                ballast.unlink()
                more, counts = checker.check()
                round_problems += more
            problems += [f"round {round_number} ({fault}): {p}" for p in round_problems]
            rounds_log.append({"round": round_number, "fault": fault, "note": note, **counts})
        clean_runs = 0
        for _ in range(3):  # runs without faults: they must finish everything the faults left pending
            clean_runs += 1
            finish(start(capture_command(f"clean-{clean_runs}", count=1)))
            round_problems, counts = checker.check(final=False)
            if counts.get("pending") == 0:
                break
        final_problems, counts = checker.check(final=True)
        problems += [f"after {clean_runs} clean run(s): {p}" for p in final_problems]
    finally:
        proxy.listener.close()
        camera.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            camera.wait(10)
        if camera.poll() is None:
            camera.kill()
    print(
        json.dumps(
            {
                "disk": "tmpfs" if tmpfs else "enospc-shim",
                "faults": dict(faults),
                "faults_injected": sum(faults.values()),
                "files_checked": checker.files_checked,
                "exposures": counts.get("exposures", 0),
                "processed": counts.get("processed", 0),
                "pending": counts.get("pending", 0),
                "rounds": rounds_log,
                "problems": problems,
                "findings": sorted(set(findings)),
                "unlisted_exposures": checker.unlisted,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
