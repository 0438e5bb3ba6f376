"""Render the README's figures: the pipeline's disparity and regions for the four Bando et al. photographs.

    .venv/bin/python docs/make_figures.py [--data ../shared/data/bando2008]

The photographs themselves stay out of the repository (their licence is non-commercial); the
figures show only what the appliance computed from them: the per-region disparity in false
colour (widest filter pair, pixels; blue = near, red = far) with the region boundaries in white.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parents[1] / "shared" / "data" / "bando2008"
RANGE_PX = (-4.0, 16.0)


def render(disparity_px: np.ndarray, labels: np.ndarray, title: str) -> np.ndarray:
    lo, hi = RANGE_PX
    scaled = np.clip((np.nan_to_num(disparity_px, nan=lo) - lo) / (hi - lo), 0, 1)
    image = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    edges = cv2.morphologyEx(labels.astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    image[edges] = 255
    cv2.rectangle(image, (0, 0), (image.shape[1], 26), (0, 0, 0), -1)
    cv2.putText(image, title, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def colour_bar(width: int) -> np.ndarray:
    ramp = np.tile(np.linspace(0, 255, width).astype(np.uint8), (18, 1))
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)
    lo, hi = RANGE_PX
    strip = np.zeros((40, width, 3), np.uint8)
    strip[:18] = bar
    for value in range(int(lo), int(hi) + 1, 4):
        x = int((value - lo) / (hi - lo) * (width - 1))
        cv2.putText(
            strip,
            f"{value:+d} px",
            (min(max(0, x - 14), width - 44), 34),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return strip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=HERE / "figures")
    args = parser.parse_args()

    import tifffile

    from mca.capture.pipeline_app import process_file
    from mca.capture.profiles import load_profile

    profile = load_profile("bando2008")
    args.out.mkdir(parents=True, exist_ok=True)
    tiles = []
    with tempfile.TemporaryDirectory() as work:
        for name in ("dog", "bonsai", "chair", "sheep"):
            outcome = process_file(args.data / f"{name}.png", work, profile)
            if outcome.status != "done":
                raise SystemExit(f"{name}: {outcome.reason}")
            folder = Path(outcome.output_dir)
            disparity = tifffile.imread(folder / "disparity.tiff")
            labels = cv2.imread(str(folder / "regions.png"), cv2.IMREAD_UNCHANGED)
            result = json.loads((folder / "result.json").read_text())
            title = f"{name}: {len(result['regions'])} regions, {sum(result['timings_s'].get(k, 0) for k in ('pipeline',)):.1f} s"
            tile = render(disparity, labels, title)
            tiles.append(
                cv2.resize(tile, (480, int(480 * tile.shape[0] / tile.shape[1])), interpolation=cv2.INTER_AREA)
            )
            print(title)
    height = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    grid = np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])
    grid = np.vstack([grid, colour_bar(grid.shape[1])])
    path = args.out / "bando2008.png"
    cv2.imwrite(str(path), grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
