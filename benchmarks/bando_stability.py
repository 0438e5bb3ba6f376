"""How robust the object checks of `tests/test_bando.py` are on Bando et al.'s four colour-aperture photographs.

The tests run each photograph once, on its exact pixels. Here each runs `--runs` times: the first time as it
is, then with its linear input multiplied by 1 + A n (n white Gaussian noise, one draw per run, A =
`--amplitude`, 1e-4 by default: 40 times below the photographs' 8-bit steps). A change that small should not
change which objects come out whole; the 2.1D sketch's joins and splits can turn it into a region split or a
join. For every photograph this prints how many runs pass the test's check and what failed in the others.

    .venv/bin/python benchmarks/bando_stability.py [--runs 16] [--amplitude 1e-4] [--photos dog.png,sheep.png]

About 1-2 s per run of the 720 x 480 photographs. Prints figures only; nothing here asserts.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from test_bando import (  # noqa: E402  (the tests' own tables and checks, so both judge alike)
    DATA,
    DOG_OBJECTS,
    MAIN_OBJECTS,
    main_object_failures,
    object_failures,
    srgb_to_linear,
)

from mca.devices.profiles import load_profile  # noqa: E402
from mca.processing.pipeline import run_pipeline  # noqa: E402

PHOTOS = ("dog.png", *sorted(MAIN_OBJECTS))


def failures(name: str, labels: np.ndarray) -> list[str]:
    return (
        object_failures(labels, DOG_OBJECTS) if name == "dog.png" else main_object_failures(labels, MAIN_OBJECTS[name])
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=16, help="runs per photograph, the first unperturbed")
    parser.add_argument("--amplitude", type=float, default=1e-4, help="relative amplitude of the input noise")
    parser.add_argument("--photos", default=",".join(PHOTOS), help="comma-separated names in ../shared/data/bando2008")
    args = parser.parse_args()
    import cv2

    aperture = load_profile("bando2008").aperture
    summary = []
    for given in args.photos.split(","):
        name = given if given.endswith(".png") else f"{given}.png"  # "dog" or "dog.png"
        path = DATA / name
        if name not in PHOTOS:
            print(f"{given}: no object check for it in tests/test_bando.py; choose from {', '.join(PHOTOS)}")
            return 2
        if not path.exists():
            print(f"{path}: not found (the photographs are read from ../shared/data/bando2008, never committed)")
            return 2
        image = srgb_to_linear(cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0)
        kinds: Counter[str] = Counter()
        passed = 0
        for run in range(args.runs):
            noisy = image
            if run > 0:
                noise = np.random.default_rng(run).standard_normal(image.shape).astype(np.float32)
                noisy = np.ascontiguousarray(image * (1 + np.float32(args.amplitude) * noise))
            start = time.perf_counter()
            found = failures(name, run_pipeline(noisy, aperture, None).labels)
            passed += not found
            kinds.update({kind.split(" at ")[0] for kind in found})
            state = "ok" if not found else "; ".join(found)
            print(f"{name} run {run + 1}/{args.runs} ({time.perf_counter() - start:.1f} s): {state}", flush=True)
        summary.append((name, passed, kinds))
    print(
        f"\n== object checks passed, {args.runs} runs each (the first unperturbed, then input x (1 + {args.amplitude:g} n)) =="
    )
    for name, passed, kinds in summary:
        what = ", ".join(f"{kind} {count}x" for kind, count in kinds.most_common()) or "-"
        print(f"  {name:11s} {passed:3d} of {args.runs}   failures: {what}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
