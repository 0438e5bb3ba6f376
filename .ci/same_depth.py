#!/usr/bin/env python3
"""CI: the newest dependencies (.venv) and the lowest declared ones (.venv-lowest) give one photograph the same
depth, to the bit. Runs `mca process` in each venv on real colour-aperture photographs (../shared/data/bando2008)
and compares what the two wrote: the disparity and depth maps, the region map, the all-in-focus image and the
layers cut from it, and every region's numbers in result.json. Exits 1 naming what differs. (The all-in-focus
image is resampled by our own cubic since the twenty-seventh stop: OpenCV 4.10 and 5.0 round its coordinates
differently.)

Usage: .ci/same_depth.py [PHOTO...]   (run from the repository; both venvs must exist)
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VENVS = {"newest": ROOT / ".venv", "lowest": ROOT / ".venv-lowest"}
PHOTOS = ("dog.png", "sheep.png")


def _data_dir() -> Path:
    for base in (ROOT.parent / "shared", Path("/work/shared")):
        if (base / "data" / "bando2008").is_dir():
            return base / "data" / "bando2008"
    sys.exit("[same-depth] ../shared/data/bando2008 is missing")


def _process(venv: Path, photo: Path, out: Path) -> Path:
    command = [str(venv / "bin" / "mca"), "process", str(photo), "--profile", "bando2008", "--out", str(out), "-q"]
    env = dict(os.environ, RERUN_ANALYTICS="0")
    if venv == VENVS["lowest"]:
        env.setdefault("NUMBA_CACHE_DIR", str(venv / "numba-cache"))  # where .ci/lowest's suite compiled them
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        sys.exit(f"[same-depth] {' '.join(command)} failed ({done.returncode}):\n{done.stdout}{done.stderr}")
    return out / photo.stem


def _arrays(folder: Path) -> dict[str, object]:
    import cv2
    import numpy as np
    import tifffile

    found: dict[str, object] = {}
    for name in ("disparity.tiff", "depth.tiff"):
        if (folder / name).exists():
            found[name] = np.nan_to_num(tifffile.imread(folder / name), nan=-1e30)
    for image in ("regions.png", "all_in_focus.png", *sorted(f"layers/{p.name}" for p in folder.glob("layers/*.png"))):
        found[image] = cv2.imread(str(folder / image), cv2.IMREAD_UNCHANGED)
    regions = json.loads((folder / "result.json").read_text(encoding="utf-8"))["regions"]
    found["result.json regions"] = regions  # every region's numbers (timings and versions are elsewhere)
    return found


def main(argv: list[str]) -> int:
    import numpy as np

    for name, venv in VENVS.items():
        if not (venv / "bin" / "mca").exists():
            sys.exit(f"[same-depth] {venv} has no mca: run .ci/lowest and python3 dev.py test first ({name})")
    photos = [Path(p) for p in argv] or [_data_dir() / name for name in PHOTOS]
    differ = []
    with tempfile.TemporaryDirectory(prefix="same-depth-") as tmp:
        for photo in photos:
            made = {name: _arrays(_process(venv, photo, Path(tmp) / name)) for name, venv in VENVS.items()}
            for key, newest in made["newest"].items():
                lowest = made["lowest"].get(key)
                same = newest == lowest if isinstance(newest, list) else np.array_equal(newest, lowest)
                if not same:
                    differ.append(f"{photo.name}: {key}")
            print(f"[same-depth] {photo.name}: {', '.join(made['newest'])} compared", flush=True)
    if differ:
        print("[same-depth] the two installs differ: " + "; ".join(differ), file=sys.stderr)
        return 1
    print("[same-depth] the newest and the lowest versions give the same depth, to the bit")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
