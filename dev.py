#!/usr/bin/env python3
"""Set up a fresh machine and run the project: `python3 dev.py demo`, `python3 dev.py test`, `python3 dev.py mutate`.

    python3 dev.py demo [mca demo options]      the main job, outputs in demo-out/
    python3 dev.py test [pytest options]        the whole test suite (what CI runs), one worker per core
    python3 dev.py mutate [MODULE...] [--sample N] [--jobs N] [--resume] [--fail-under PCT]
                                                mutation testing (cosmic-ray): each module's score and its
                                                surviving mutants; MODULE is a path (capture/batch.py,
                                                processing/) or a name (mca.capture.batch); default: the
                                                modules in mutation/config.toml (README, Quick start)

Needs only Python >= 3.11 with pip. Creates `.venv` when missing, installs the
project with its test and lint extras whenever pyproject.toml changed, and on
Debian (as root) installs the system tools the tests use as independent
references: exiftool, gphoto2, shellcheck, tiffinfo (libtiff-tools), pngcheck,
and node, with the Khronos glTF validator from npm into .venv/node.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / "bin"
SYSTEM_TOOLS = {
    "exiftool": "libimage-exiftool-perl",
    "gphoto2": "gphoto2",
    "shellcheck": "shellcheck",
    "tiffinfo": "libtiff-tools",
    "pngcheck": "pngcheck",
    "node": "nodejs",
    "npm": "npm",
}
GLTF_VALIDATOR = "gltf-validator@2.0.0-dev.3.10"  # the Khronos glTF validator, compiled to JavaScript
NODE_PREFIX = VENV / "node"


def _say(message: str) -> None:
    print(f"[dev] {message}", flush=True)


def ensure_venv() -> None:
    python = BIN / "python"
    if not python.exists():
        _say(f"creating {VENV}")
        venv.create(VENV, with_pip=True)
    stamp = VENV / ".installed"
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if stamp.exists() and stamp.read_text() == digest:
        return
    _say("installing the project and its test dependencies into .venv (about a minute)")
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--upgrade", "pip"], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "-q", "-e", f"{ROOT}[test,lint]"], check=True)
    stamp.write_text(digest)


def ensure_system_tools() -> None:
    missing = [pkg for tool, pkg in SYSTEM_TOOLS.items() if shutil.which(tool) is None]
    if not missing:
        return
    if shutil.which("apt-get") is None or os.geteuid() != 0:
        _say(f"not installing {', '.join(missing)} (needs root and apt-get); tests that use them will skip")
        return
    _say(f"installing {', '.join(missing)} with apt-get")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    quiet = {"stdout": subprocess.DEVNULL, "env": env}
    subprocess.run(["apt-get", "update", "-qq"], check=False, **quiet)
    result = subprocess.run(
        ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *missing], check=False, **quiet
    )
    if result.returncode != 0:
        _say(f"apt-get could not install {', '.join(missing)}; tests that use them will skip")


def ensure_gltf_validator() -> None:
    """npm install the Khronos glTF validator into .venv/node (tests/tools.py finds it there)."""
    marker = NODE_PREFIX / "node_modules" / "gltf-validator" / "package.json"
    if marker.exists() and GLTF_VALIDATOR.split("@")[1] in marker.read_text(encoding="utf-8"):
        return
    npm = shutil.which("npm")
    if npm is None:
        _say("npm is missing: the glTF validator test will skip (and fail on CI)")
        return
    _say(f"installing {GLTF_VALIDATOR} with npm into {NODE_PREFIX}")
    NODE_PREFIX.mkdir(parents=True, exist_ok=True)
    result = subprocess.run(
        [npm, "install", "--no-audit", "--no-fund", "--silent", "--prefix", str(NODE_PREFIX), GLTF_VALIDATOR],
        check=False,
        stdout=subprocess.DEVNULL,
    )
    if result.returncode != 0:
        _say("npm could not install the glTF validator; its test will skip (and fail on CI)")


MUTATION_TOOLS = ["cosmic-ray==8.7.0", "coverage==7.17.3"]  # pinned: a new release must not change the scores


def ensure_mutation_tools() -> None:
    probe = subprocess.run([str(BIN / "python"), "-c", "import cosmic_ray, coverage"], capture_output=True)
    if probe.returncode == 0:
        return
    _say(f"installing {' '.join(MUTATION_TOOLS)} into .venv")
    subprocess.run([str(BIN / "python"), "-m", "pip", "install", "-q", *MUTATION_TOOLS], check=True)


def main(argv: list[str]) -> int:
    if len(argv) < 1 or argv[0] not in {"demo", "test", "mutate"}:
        print(__doc__)
        return 2
    os.chdir(ROOT)
    ensure_venv()
    env = dict(os.environ, RERUN_ANALYTICS="0")
    if argv[0] == "demo":
        return subprocess.call([str(BIN / "mca"), "demo", "--out", "demo-out", *argv[1:]], env=env)
    if argv[0] == "mutate":
        ensure_mutation_tools()
        return subprocess.call([str(BIN / "python"), str(ROOT / "mutation" / "mutate.py"), *argv[1:]], env=env)
    ensure_system_tools()
    ensure_gltf_validator()
    args = argv[1:]
    workers = xdist_workers(args)
    if workers > 1:
        # one pytest worker per core (pytest-xdist); an idle OpenMP thread of one worker's compiled kernels
        # would otherwise spin while the other worker holds its partner's core (docs/speed.md)
        args = ["-n", str(workers), "--dist", "worksteal", *args]
        env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return subprocess.call([str(BIN / "python"), "-m", "pytest", *args], env=env)


def xdist_workers(args: list[str]) -> int:
    """pytest-xdist workers for `dev.py test ARGS`: one per core this process may use, at most 4 (each test's
    kernels take two threads), unless ARGS choose (-n, -p no:xdist), only collect (--co) or want the terminal
    (a debugger: --pdb, --trace; no capture: -s), which pytest-xdist's workers cannot give them. 1: add no -n."""
    own = {"-n", "--numprocesses", "--co", "--collect-only", "no:xdist", "--pdb", "--trace", "-s", "--capture=no"}
    if any(a in own or a.startswith(("-n", "--numprocesses=")) for a in args):
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, min(cores, 4))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
