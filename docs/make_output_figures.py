"""Render the README's pictures of the main outputs, from one simulated shot processed by `mca process`.

    .venv/bin/python docs/make_output_figures.py [--scene paper-c] [--size 0.25] [--out docs/figures]

Writes `outputs.png` (the photograph as the camera took it, the all-in-focus image, the regions, the
depth map beside the simulator's ground truth, on one colour scale) and `scene_glb.png` (scene.glb
drawn from a viewpoint to the left of and above the camera, every textured quad projected with the
file's own vertices and textures, so the layers' distances show) with OpenCV alone, and `rerun.png`:
the rerun viewer's own screenshot of the shot's recording (`rerun --screenshot-to`), headless under
Xvfb with Mesa's software Vulkan (Debian: xvfb, mesa-vulkan-drivers); skipped when those are missing.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent


def _turbo(depth_mm: np.ndarray, lo: float, hi: float) -> np.ndarray:
    scaled = np.clip((np.nan_to_num(depth_mm, nan=hi) - lo) / (hi - lo), 0, 1)
    image = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    image[~np.isfinite(depth_mm)] = 0
    return image


def _titled(image_bgr: np.ndarray, title: str, width: int) -> np.ndarray:
    scale = width / image_bgr.shape[1]
    image = cv2.resize(image_bgr, (width, int(round(image_bgr.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    cv2.rectangle(image, (0, 0), (image.shape[1], 24), (0, 0, 0), -1)
    cv2.putText(image, title, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def _depth_scale_bar(width: int, lo: float, hi: float) -> np.ndarray:
    bar = cv2.applyColorMap(np.tile(np.linspace(0, 255, width).astype(np.uint8), (16, 1)), cv2.COLORMAP_TURBO)
    strip = np.zeros((36, width, 3), np.uint8)
    strip[:16] = bar
    for value in np.linspace(lo, hi, 5):
        x = int((value - lo) / (hi - lo) * (width - 1))
        cv2.putText(
            strip, f"{value:.0f} mm", (min(max(0, x - 20), width - 60), 31), 0, 0.4, (255, 255, 255), 1, cv2.LINE_AA
        )
    return strip


def _region_image(labels: np.ndarray, document: dict) -> np.ndarray:
    colours = np.zeros((int(labels.max()) + 1, 3), np.uint8)
    for region in document["regions"]:
        hue = (region["id"] * 0.618033988749895) % 1.0
        colours[region["id"]] = cv2.cvtColor(np.uint8([[[int(hue * 180), 190, 240]]]), cv2.COLOR_HSV2BGR)[0, 0]
    image = colours[labels]
    edges = cv2.morphologyEx(labels.astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    image[edges] = 255
    for region in document["regions"]:
        ys, xs = np.nonzero(labels == region["id"])
        if len(xs) and region["distance_mm"] is not None:
            text = f"#{region['id']} {region['distance_mm']:.0f} mm"
            at = (int(np.median(xs)) - 40, int(np.median(ys)))
            cv2.putText(image, text, at, 0, 0.9, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(image, text, at, 0, 0.9, (255, 255, 255), 2, cv2.LINE_AA)
    return image


def render_glb(path: Path, size: tuple[int, int] = (900, 600), yaw_deg: float = 28.0, pitch_deg: float = 12.0):
    """scene.glb seen from a camera orbiting the scene's centre: quads textured, composited far to near."""
    from mca.capture import outputs

    gltf, binary = outputs.read_glb(path)
    quads = []
    for mesh in gltf["meshes"]:
        primitive = mesh["primitives"][0]
        corners = outputs.glb_accessor(gltf, binary, primitive["attributes"]["POSITION"]).astype(np.float64)
        texture_index = gltf["materials"][primitive["material"]]["pbrMetallicRoughness"]["baseColorTexture"]["index"]
        png = outputs.glb_image(gltf, binary, gltf["textures"][texture_index]["source"])
        quads.append((corners, cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)))
    every = np.vstack([c for c, _ in quads])
    centre = (every.min(axis=0) + every.max(axis=0)) / 2
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    rotation = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]]) @ np.array(
        [[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)], [0, math.sin(pitch), math.cos(pitch)]]
    )
    eye = centre + rotation @ np.array([0.0, 0.0, -centre[2]])  # as far from the centre as the camera was
    width, height = size
    focal = 1.1 * width

    def project(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = (points - eye) @ rotation  # the viewer's frame: x right, y up, looking down -z
        return np.stack(
            [width / 2 + focal * local[:, 0] / -local[:, 2], height / 2 - focal * local[:, 1] / -local[:, 2]], 1
        ), -local[:, 2]

    canvas = np.full((height, width, 3), 40.0)
    for corners, texture in sorted(quads, key=lambda q: -project(q[0])[1].mean()):
        image_points, _ = project(corners)
        h, w = texture.shape[:2]
        source = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
        warp = cv2.getPerspectiveTransform(source, image_points.astype(np.float32))
        warped = cv2.warpPerspective(texture, warp, (width, height), flags=cv2.INTER_LINEAR)
        alpha = warped[..., 3:4].astype(np.float64) / 255.0
        canvas = canvas * (1 - alpha) + warped[..., :3].astype(np.float64) * alpha
        cv2.polylines(canvas, [np.round(image_points).astype(np.int32)], True, (200, 200, 200), 1, cv2.LINE_AA)
    image = canvas.astype(np.uint8)
    cv2.putText(
        image,
        f"scene.glb, viewed {yaw_deg:.0f} deg to the left, {pitch_deg:.0f} deg above",
        (10, 22),
        0,
        0.6,
        (255, 255, 255),
        1,
        cv2.LINE_AA,
    )
    return image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="paper-c")
    parser.add_argument("--size", type=float, default=0.25)
    parser.add_argument("--out", type=Path, default=HERE / "figures")
    args = parser.parse_args()

    from typer.testing import CliRunner

    from mca.capture.cli import app
    from mca.capture.raw import read_raw
    from mca.devices.profiles import load_profile
    from mca.devices.sim.world import capture_cr2_bytes, render_scene

    profile = load_profile("paper-70d")
    capture = render_scene(args.scene, profile, size=args.size)
    with tempfile.TemporaryDirectory() as tmp:
        cr2 = Path(tmp) / f"{args.scene}.CR2"
        cr2.write_bytes(capture_cr2_bytes(capture, profile))
        recording = Path(tmp) / "shot.rrd"
        result = CliRunner().invoke(app, ["process", str(cr2), "--out", tmp, "-q", "--record", str(recording)])
        if result.exit_code != 0:
            raise SystemExit(result.output)
        folder = Path(tmp) / args.scene
        document = json.loads((folder / "result.json").read_text())
        import tifffile

        depth = tifffile.imread(folder / "depth.tiff")
        labels = cv2.imread(str(folder / "regions.png"), cv2.IMREAD_UNCHANGED)
        aif = cv2.imread(str(folder / "all_in_focus.png"))
        frame = read_raw(cr2)
        photo = cv2.cvtColor(frame.colour.to_srgb8(frame.planes), cv2.COLOR_RGB2BGR)
        truth = capture.depth_mm
        finite = truth[np.isfinite(truth)]
        lo, hi = float(np.percentile(finite, 1)) - 20, float(np.percentile(finite, 99)) + 20
        column = 420
        top = np.hstack(
            [
                _titled(photo, "the photograph (colour fringes: the MCA)", column),
                _titled(aif, "all_in_focus.png (fringes removed)", column),
                _titled(_region_image(labels, document), "regions.png: region, distance", column),
            ]
        )
        bottom = np.hstack(
            [
                _titled(_turbo(depth, lo, hi), "depth.tiff (mm)", column),
                _titled(_turbo(truth, lo, hi), "simulator's ground truth (mm)", column),
                np.vstack(
                    [
                        _titled(_turbo(np.abs(depth - truth) * 10 + lo, lo, hi), "|error| x 10", column),
                    ]
                ),
            ]
        )
        figure = np.vstack([top, bottom, np.hstack([_depth_scale_bar(column, lo, hi)] * 3)])
        args.out.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.out / "outputs.png"), figure)
        cv2.imwrite(str(args.out / "scene_glb.png"), render_glb(folder / "scene.glb"))
        print(f"wrote {args.out / 'outputs.png'} and {args.out / 'scene_glb.png'}")
        screenshot(recording, args.out / "rerun.png")


def screenshot(recording: Path, out: Path, width: int = 1600) -> None:
    """The rerun viewer's screenshot of `recording`, taken headless (Xvfb, software Vulkan), scaled to `width`."""
    import os
    import shutil
    import subprocess

    from mca.capture.recording import child_environment, rerun_executable

    exe, xvfb = rerun_executable(), shutil.which("xvfb-run")
    if exe is None or xvfb is None:
        print("no rerun screenshot: needs xvfb-run (apt-get install xvfb mesa-vulkan-drivers) and rerun-sdk")
        return
    raw = out.with_suffix(".full.png")
    command = [xvfb, "-a", "-s", "-screen 0 1800x1100x24", exe, "--renderer", "vulkan"]
    command += ["--window-size", "1800x1100", "--screenshot-to", str(raw), str(recording)]
    subprocess.run(command, env=child_environment(), capture_output=True, timeout=600, check=False)
    if not raw.is_file():
        print("no rerun screenshot: the viewer could not render here (see `rerun --renderer vulkan`)")
        return
    image = cv2.imread(str(raw))
    os.unlink(raw)
    image = cv2.resize(image, (width, round(image.shape[0] * width / image.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(out), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
