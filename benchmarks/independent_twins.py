"""Twins of a render folder made by another renderer: does the pipeline do as well on renders it did not make?

    python benchmarks/independent_twins.py RENDERS OUT      # e.g. the dev set's held-out folder
    mca evaluate --rgbd OUT --no-peers                      # beside: mca evaluate --rgbd RENDERS --no-peers

For each render of RENDERS (written by `mca simulate --from-rgbd`), the same scene is rendered again by
`tests/independent_render.py`, which shares no code with `mca simulate` (its own disc kernels, depth slices and
compositing, hidden-background fill, resampling and noise), and written to OUT with its truth in the layout
`mca evaluate --rgbd` reads. What the twin takes from the render: the Middlebury photograph (resized here), the
true distance of every pixel (`truth/<name>.distance.tiff`; its unknown pixels filled here with the farthest
neighbour), the size, pixel pitch and focus, and the sensor's settings (ISO, full well, read noise, exposure,
crosstalk, vignetting, with docs/simulator.md's meanings). Its disparities come from its own optics. The twins
carry no camera tags: each one's profile gives the render's pixel pitch and size.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from independent_render import Optics, expose, fill_farthest, profile_text, render, srgb_to_linear  # noqa: E402

ADC_NOISE_DN = 1.0  # the converter's own noise, beside the sensor's read noise


def _photograph(truth: dict, renders: Path) -> Path:
    """The Middlebury photograph a render was made of."""
    for base in (REPO / "..", renders, Path.cwd()):
        image = (base / truth["source"]["image"]).resolve()
        if image.is_file():
            return image
    raise SystemExit(f"{truth['scene']}: its source {truth['source']['image']} is not found next to the repository")


def _sensor(light: np.ndarray, truth: dict, pitch_mm: float, sensor_mm: float, seed: int) -> np.ndarray:
    """The render's sensor (docs/simulator.md's meanings): vignetting, crosstalk (out_c = sum_f M[c][f] in_f),
    exposure (the share of white - black a white surface reaches on the axis), Poisson photons, Gaussian read
    noise, 14-bit levels; written as (DN - black) / (white - black) of 65535."""
    realism = truth.get("realism") or truth["draw"]
    sensor = realism["sensor"]
    height, width, _ = light.shape
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    radius2_px = (cols - (width - 1) / 2.0) ** 2 + (rows - (height - 1) / 2.0) ** 2
    x = light.astype(np.float64)
    if realism.get("vignetting") == "cos4":
        x *= ((1.0 / (1.0 + radius2_px * pitch_mm**2 / sensor_mm**2)) ** 2)[..., None]
    elif realism.get("vignetting") == "poly":
        k2, k4 = realism["vignetting_k"]
        r2 = radius2_px / (((width - 1) / 2.0) ** 2 + ((height - 1) / 2.0) ** 2)
        x *= (1.0 + k2 * r2 + k4 * r2**2)[..., None]
    if realism.get("crosstalk") is not None:
        x = np.einsum("hwf,cf->hwc", x, np.asarray(realism["crosstalk"], np.float64))
    return expose(
        x,
        float(sensor["iso"]),
        float(sensor["exposure"]),
        seed,
        black_dn=int(sensor["black_level"]),
        white_dn=int(sensor["white_level"]),
        bits=int(sensor["bits"]),
        full_well_e_iso100=float(sensor["full_well_e"]),
        read_noise_e=float(sensor["read_noise_e"]),
        adc_noise_dn=ADC_NOISE_DN,
        noise=bool(sensor.get("noise", True)),
    )


def twin(truth_path: Path, renders: Path, out: Path, step_px: float, supersample: int = 2) -> str:
    truth = json.loads(truth_path.read_text(encoding="utf-8"))
    image_path = _photograph(truth, renders)
    optics_info = truth["optics"]
    size = (int(optics_info["width_px"]), int(optics_info["height_px"]))
    pitch_mm = float(optics_info["pixel_pitch_mm"])
    photo = srgb_to_linear(cv2.imread(str(image_path), cv2.IMREAD_COLOR)[..., ::-1])
    shrink = size[0] < 0.9 * photo.shape[1]
    linear = cv2.resize(photo, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC).clip(0.0, 1.0)
    distance_mm = tifffile.imread(truth_path.parent / truth["files"]["distance_mm"]).astype(np.float64)
    if distance_mm.shape != size[::-1]:
        raise SystemExit(f"{truth['scene']}: its distance map is {distance_mm.shape}, not {size[::-1]}")
    known = np.isfinite(distance_mm)
    inverse = fill_farthest(1.0 / distance_mm)
    profile_path = truth_path.parent / truth["files"]["profile"]
    optics = Optics.from_profile(profile_path, float(truth["focus_distance_mm"]), pitch_mm)
    if abs(optics.sensor_mm - float(optics_info["sensor_distance_mm"])) > 1e-6:
        raise SystemExit(f"{truth['scene']}: its focus and sensor distance disagree with the thin lens")
    red_blue = optics.red_blue_px(1.0 / inverse)
    started = time.perf_counter()
    light = render(linear, red_blue.astype(np.float32), optics, step_px, supersample)
    seconds = time.perf_counter() - started
    name = f"{truth['scene']}-twin"
    (out / "truth").mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(out / f"{name}.tiff", _sensor(light, truth, pitch_mm, optics.sensor_mm, int(truth["seed"]) + 1))
    tifffile.imwrite(out / "truth" / f"{name}.disparity.tiff", np.where(known, red_blue, np.nan).astype(np.float32))
    tifffile.imwrite(out / "truth" / f"{name}.distance.tiff", np.where(known, 1.0 / inverse, np.nan).astype(np.float32))
    text = profile_text(profile_path.read_text(encoding="utf-8"), f"{name}-profile", pitch_mm, size)
    (out / "truth" / f"{name}.profile.toml").write_text(text, encoding="utf-8")
    twin_truth = dict(truth, scene=name, image=f"{name}.tiff", format="tiff", profile=f"{name}-profile")
    twin_truth["renderer"] = {
        "by": "tests/independent_render.py",
        "twin_of": truth["scene"],
        "step_px": step_px,
        "supersample": supersample,
    }
    twin_truth["valid_fraction"] = float(known.mean())
    twin_truth["files"] = {
        "distance_mm": f"{name}.distance.tiff",
        "disparity_px": f"{name}.disparity.tiff",
        "profile": f"{name}.profile.toml",
    }
    (out / "truth" / f"{name}.json").write_text(json.dumps(twin_truth, indent=2), encoding="utf-8")
    return (
        f"{name}: {size[0]}x{size[1]}, {red_blue[known].min():+.2f}..{red_blue[known].max():+.2f} px, {seconds:.0f} s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("renders", type=Path, help="a folder written by mca simulate --from-rgbd (with truth/)")
    parser.add_argument("out", type=Path, help="where the twins and their truth/ go")
    parser.add_argument("--step-px", type=float, default=0.05, help="disparity between depth slices")
    parser.add_argument(
        "--supersample", type=int, default=2, help="render on a grid this many times finer (1: 4x faster, less exact)"
    )
    args = parser.parse_args()
    truths = sorted(args.renders.rglob("truth/*.json"))
    truths = [t for t in truths if json.loads(t.read_text(encoding="utf-8")).get("kind") == "rgbd"]
    if not truths:
        raise SystemExit(f"{args.renders}: no RGB-D render (truth/*.json) to twin")
    for index, path in enumerate(truths, 1):
        print(
            f"[{index}/{len(truths)}] {twin(path, args.renders, args.out, args.step_px, args.supersample)}", flush=True
        )


if __name__ == "__main__":
    main()
