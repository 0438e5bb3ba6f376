"""A weakly textured twin of the Middlebury tree: the same scenes and true disparities, their photographs with the
fine texture taken out, for the stress set of docs/evaluation.md ("Weakly textured surfaces").

Each photograph goes twice through OpenCV's mean-shift filter (spatial radius 1/60 of its width, colour radius
28 of 255, one pyramid level), then a Gaussian of 1 px: walls, boxes and paper become flat areas of one colour
with soft shading, object outlines and strong markings stay. That is the kind of content the issue's independent
set holds (plastic, lampshades, flower pots, painted walls) and the nine photographs mostly do not.
`disp.png` and `SOURCE.txt` are copied unchanged, so the truth is the original's.

    .venv/bin/python benchmarks/flat_tree.py OUT [--from ../shared/data/middlebury]
    .venv/bin/mca simulate --from-rgbd-tree OUT --seeds 5,6 --scenes Art,Cones,Dolls,Laundry,Moebius,Venus -o FLAT
    .venv/bin/mca simulate --from-rgbd-tree OUT --seeds 5 --scenes Books,Reindeer,Teddy -o FLAT
    .venv/bin/mca evaluate --rgbd FLAT

Prints each scene's texture before and after (mean absolute Laplacian of the grey image, 8-bit units).
"""

from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def flatten(image: np.ndarray) -> np.ndarray:
    """An 8-bit BGR photograph with its fine texture taken out (see the module docstring)."""
    radius = max(4, image.shape[1] // 60)
    flat = cv2.pyrMeanShiftFiltering(image, radius, 28, maxLevel=1)
    flat = cv2.pyrMeanShiftFiltering(flat, radius, 28, maxLevel=1)
    return cv2.GaussianBlur(flat, (0, 0), 1.0)


def texture(image: np.ndarray) -> float:
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)
    return float(np.abs(cv2.Laplacian(grey, cv2.CV_32F)).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--from", dest="source", type=Path, default=REPO.parent / "shared" / "data" / "middlebury")
    args = parser.parse_args()
    scenes = sorted(p for p in args.source.iterdir() if (p / "im.png").is_file() and (p / "disp.png").is_file())
    if not scenes:
        raise SystemExit(f"{args.source}: no <Scene>/im.png with disp.png; give the Middlebury tree with --from")
    for scene in scenes:
        image = cv2.imread(str(scene / "im.png"), cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"{scene / 'im.png'}: OpenCV cannot read it as an image")
        target = args.out / scene.name
        target.mkdir(parents=True, exist_ok=True)
        flat = flatten(image)
        partial = target / "im.png.partial.png"
        cv2.imwrite(str(partial), flat)
        os.replace(partial, target / "im.png")
        for name in ("disp.png", "SOURCE.txt"):
            if (scene / name).is_file():
                shutil.copyfile(scene / name, target / name)
        print(f"{scene.name:10s} texture {texture(image):6.2f} -> {texture(flat):5.2f}", flush=True)


if __name__ == "__main__":
    main()
