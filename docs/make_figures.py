"""Render the README's figure: our regions and dense disparity beside Bando et al.'s own output, per photograph.

    .venv/bin/python docs/make_figures.py [--data ../shared/data/bando2008] [--bando PATH]

The photographs themselves stay out of the repository (their licence is non-commercial); the
figures show only what was computed from them: per row, our regions (each painted with its
disparity), our dense disparity and Bando 2008's graph-cut disparity (when its program is built), in false
colour (widest filter pair, pixels; blue = near, red = far) with the region boundaries in white.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parents[1] / "shared" / "data" / "bando2008"
RANGE_PX = (-4.0, 20.0)


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


def region_image(result) -> np.ndarray:
    """Each region painted with its own disparity: the 2.1D sketch as a picture."""
    level = np.zeros(int(result.labels.max()) + 1, np.float32)
    for region in result.regions:
        level[region.id] = region.disparity_px
    return level[result.labels]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=HERE / "figures")
    parser.add_argument("--bando", type=Path, default=None, help="Bando 2008's built program (else MCA_BANDO_BIN)")
    args = parser.parse_args()

    from mca.capture.peer_bando import find_bando, run_bando
    from mca.devices.profiles import load_profile
    from mca.processing.colour import srgb_decode
    from mca.processing.pipeline import run_pipeline

    profile = load_profile("bando2008")
    binary = find_bando(args.bando)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in ("dog", "bonsai", "chair", "sheep"):
        image = cv2.imread(str(args.data / f"{name}.png"), cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"{args.data / name}.png: not found or not an image (pass --data)")
        planes = srgb_decode(image[..., ::-1].astype(np.float32) / 255.0)
        result = run_pipeline(planes, profile.aperture, None)
        seconds = result.timings_s["total"]
        tiles = [
            render(region_image(result), result.labels, f"{name}: ours, {len(result.regions)} regions"),
            render(result.disparity_px, result.labels * 0, "ours: dense disparity"),
        ]
        if binary is not None:
            run = run_bando(binary, planes, profile.aperture, (-10.0, 20.0))
            tiles.append(render(run.disparity_px, np.zeros_like(result.labels), "Bando 2008 (graph cuts)"))
        row = np.hstack(
            [cv2.resize(t, (360, int(360 * t.shape[0] / t.shape[1])), interpolation=cv2.INTER_AREA) for t in tiles]
        )
        rows.append(row)
        print(
            f"{name}: {len(result.regions)} regions, {seconds:.1f} s"
            + ("" if binary else " (Bando's program not found)")
        )
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    grid = np.vstack([*rows, colour_bar(width)])
    path = args.out / "bando2008.png"
    cv2.imwrite(str(path), grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
