"""Runs Bando et al. 2008's released colour-filtered-aperture depth program as a peer, when it is built.

The program (../shared/peers/bando2008/: build.sh, FORMAT.md) is built outside the repository
and found through `--bando PATH` or the environment variable MCA_BANDO_BIN; it is never copied
here. We hand it an 8-bit sRGB binary PPM of the capture's linear planes and read back its final
labels (depth_global.pgm).

Its shift convention (FORMAT.md): for label d the aligned image takes red at (x + d, y), green at
(x, y - d), blue at (x - d, y). Ours: a point of widest-pair disparity δ is imaged by filter c at
chief-ray position + `FilterAperture.shift_per_disparity(c)` δ. The two agree when red's shift
per disparity is (+k, 0), green's (0, -k) and blue's (-k, 0): then d = k δ (k = 1/2 for paper-70d
and bando2008: red-blue disparity = 2 d). Other geometries are refused (`BandoGeometryError`).
"""

from __future__ import annotations

import math
import os
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.colour import srgb_encode

ENV_VARIABLE = "MCA_BANDO_BIN"
HALF_WINDOW = 7  # the program's SIZE argument: a 15x15 window, as in the paper's run.sh
TIMEOUT_S = 1800.0  # the 20 MP dev render took 831 s on two busy cores


class BandoGeometryError(ValueError):
    """The profile's filters are not laid out as the program assumes (red right, green up, blue left, equal)."""


@dataclass(frozen=True)
class BandoRun:
    """The program's answer: disparity per pixel in widest-pair px of the planes handed in, and how it went."""

    disparity_px: np.ndarray  # (H, W) float32
    labels: tuple[int, int]  # DMIN, DMAX handed to it
    seconds: float


def find_bando(explicit: str | Path | None = None) -> Path | None:
    """The program at `explicit` when given, else at $MCA_BANDO_BIN, when that is an executable file; else None."""
    candidate = explicit if explicit else os.environ.get(ENV_VARIABLE)
    if candidate:
        path = Path(candidate).expanduser()
        if path.is_file() and os.access(path, os.X_OK):
            return path
    return None


def labels_per_disparity(aperture: FilterAperture, tolerance: float = 1e-6) -> float:
    """k such that the program's label d = k x our widest-pair disparity; raises BandoGeometryError otherwise."""
    rx, ry = aperture.shift_per_disparity("red")
    gx, gy = aperture.shift_per_disparity("green")
    bx, by = aperture.shift_per_disparity("blue")
    k = rx
    ok = (
        k > 0
        and abs(ry) < tolerance
        and abs(bx + k) < tolerance
        and abs(by) < tolerance
        and abs(gx) < tolerance
        and abs(gy + k) < tolerance
    )
    if not ok:
        raise BandoGeometryError(
            "Bando's program assumes red right, green up, blue left at equal distances from the centre; "
            f"this aperture shifts red {rx:+.3f},{ry:+.3f} green {gx:+.3f},{gy:+.3f} blue {bx:+.3f},{by:+.3f} px/px"
        )
    return float(k)


def label_range(range_px: tuple[float, float], k: float) -> tuple[int, int]:
    """Integer DMIN, DMAX covering our disparity search range `range_px` (px of the planes handed in)."""
    low, high = sorted((range_px[0] * k, range_px[1] * k))
    return int(math.floor(low)), int(math.ceil(high))


def srgb8(planes: np.ndarray) -> np.ndarray:
    """Linear planes -> 8-bit sRGB, one gain for the whole image (99.5th percentile to white), as a camera would."""
    linear = np.clip(np.asarray(planes, np.float32), 0.0, None)
    white = float(np.percentile(linear, 99.5)) or 1.0
    encoded = srgb_encode(linear / white)  # clipped to [0, 1]; the curve of processing/colour.py
    return np.clip(np.rint(encoded * 255.0), 0, 255).astype(np.uint8)


def write_ppm(path: Path, rgb8: np.ndarray) -> None:
    height, width = rgb8.shape[:2]
    with open(path, "wb") as handle:
        handle.write(f"P6\n{width} {height}\n255\n".encode("ascii"))
        handle.write(np.ascontiguousarray(rgb8, np.uint8).tobytes())


def read_pgm(path: Path) -> np.ndarray:
    """A binary P5 file with maxval 255 (the program's depth_global.pgm)."""
    data = path.read_bytes()
    fields: list[bytes] = []
    position = 0
    while len(fields) < 4:
        while position < len(data) and data[position : position + 1].isspace():
            position += 1
        if data[position : position + 1] == b"#":
            position = data.index(b"\n", position) + 1
            continue
        end = position
        while end < len(data) and not data[end : end + 1].isspace():
            end += 1
        fields.append(data[position:end])
        position = end
    if fields[0] != b"P5" or int(fields[3]) != 255:
        raise ValueError(f"{path}: not an 8-bit binary PGM (P5, maxval 255)")
    width, height = int(fields[1]), int(fields[2])
    pixels = np.frombuffer(data, np.uint8, count=width * height, offset=position + 1)
    return pixels.reshape(height, width)


def decode_labels(grey: np.ndarray, disp_min: int, disp_max: int) -> np.ndarray:
    """depth_global.pgm grey values -> label d (FORMAT.md: g = floor(label 255 / (N - 1)), label = d - DMIN)."""
    steps = disp_max - disp_min
    if steps < 1 or steps > 255:
        raise ValueError(f"the label range {disp_min}..{disp_max} cannot be decoded exactly")
    label = (grey.astype(np.int64) * steps + 254) // 255
    return (label + disp_min).astype(np.float32)


def run_bando(
    binary: Path,
    planes: np.ndarray,
    aperture: FilterAperture,
    range_px: tuple[float, float],
    *,
    timeout_s: float = TIMEOUT_S,
) -> BandoRun:
    """Run the program on `planes` (linear RGB, aligned to common sample positions) searching `range_px`
    (widest-pair px of the planes); returns its final disparity in the same px. Raises RuntimeError with the
    program's own words when it fails or times out."""
    import time

    k = labels_per_disparity(aperture)
    disp_min, disp_max = label_range(range_px, k)
    with tempfile.TemporaryDirectory(prefix="mca-bando-", ignore_cleanup_errors=True) as name:
        work = Path(name)
        write_ppm(work / "in.ppm", srgb8(planes))
        started = time.perf_counter()
        try:
            done = subprocess.run(
                [str(binary), "in.ppm", str(HALF_WINDOW), str(disp_min), str(disp_max)],
                cwd=work,
                capture_output=True,
                timeout=timeout_s,
                stdin=subprocess.DEVNULL,
            )
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"{binary} did not finish within {timeout_s:.0f} s") from None
        seconds = time.perf_counter() - started
        output = work / "depth_global.pgm"
        if done.returncode != 0 or not output.is_file():
            tail = (done.stderr or done.stdout).decode("utf-8", "replace").strip().splitlines()[-3:]
            raise RuntimeError(f"{binary} failed (exit {done.returncode}): {' | '.join(tail) or 'no output'}")
        grey = read_pgm(output)
        if grey.shape != planes.shape[:2]:
            raise RuntimeError(
                f"{binary} wrote a {grey.shape[1]}x{grey.shape[0]} map for a {planes.shape[1]}x{planes.shape[0]} image"
            )
        return BandoRun(decode_labels(grey, disp_min, disp_max) / np.float32(k), (disp_min, disp_max), seconds)
