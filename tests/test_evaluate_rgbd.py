"""Per-pixel evaluation on rendered real scenes: the figures on hand-made arrays, the peers' conventions, and
`mca evaluate --rgbd` run for real on a tiny rendered Middlebury tree."""

from __future__ import annotations

import json
import os
import re
import stat
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from mca.devices.profiles import load_profile
from mca.processing.evaluate import (
    PixelMetrics,
    RgbdRow,
    depth_edge_band,
    depth_edges,
    disparity_slope,
    pixel_metrics,
    summarise_rgbd,
)

PROFILE = load_profile("paper-70d")
MIDDLEBURY = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "middlebury"


# --- the figures ------------------------------------------------------------------------------------------------


def test_depth_edge_band_is_the_5px_neighbourhood_of_true_jumps() -> None:
    truth = np.zeros((20, 40), np.float32)
    truth[:, 20:] = 3.0  # one vertical edge between columns 19 and 20
    truth[0, 0] = np.nan  # unknown pixels are never in the band and make no edge
    band = depth_edge_band(truth)
    columns = np.nonzero(band[10])[0]
    assert columns.min() == 19 - 5 and columns.max() == 20 + 5
    assert not band[0, 0]
    edges = depth_edges(truth)
    assert set(np.nonzero(edges[10])[0]) == {19, 20}  # both sides of the jump
    assert np.array_equal(depth_edge_band(truth, edges=edges), band)  # edges handed in: the same band
    smooth = np.tile(np.linspace(0.0, 8.0, 40, dtype=np.float32), (20, 1))  # 0.2 px per px: a slope, no edge
    assert not depth_edge_band(smooth).any()


def test_pixel_metrics_on_hand_made_arrays() -> None:
    h, w = 10, 40
    true_d = np.zeros((h, w), np.float32)
    true_d[:, 20:] = 4.0
    true_d[0, :] = np.nan  # 40 unknown pixels: not counted
    focus = 1000.0
    true_z = np.where(np.isfinite(true_d), np.where(true_d > 0, 1100.0, 1010.0), np.nan)
    est_d = true_d.copy()
    est_d[5, 0:10] += 0.7  # 10 pixels off by 0.7: bad-0.5, not bad-1
    est_d[6, 30:34] -= 2.0  # 4 pixels off by 2: bad both
    est_d[7, 35:38] = np.nan  # 3 pixels without value: bad both, not covered
    est_z = true_z.copy()
    est_z[np.isfinite(true_d) & (true_d > 0)] = 1090.0  # right half 10 mm near: rel error 10/100
    est_z[7, 35:38] = np.nan
    m = pixel_metrics(est_d, est_z, true_d, true_z, focus)
    valid = 9 * 40
    assert m.valid_px == valid
    assert m.bad_1 == pytest.approx(7 / valid)
    assert m.bad_05 == pytest.approx(17 / valid)
    assert m.coverage == pytest.approx((valid - 3) / valid)
    # the edge band: columns 14..25 of the 9 known rows
    assert m.edge_px == 9 * 12
    assert m.edge_bad_1 == pytest.approx(0 / m.edge_px) and m.edge_bad_05 == pytest.approx(0 / m.edge_px)
    # depth: left half exact (10 mm off focus: excluded from the relative error, < 25 mm), right half 10 mm off
    # 180 left-half pixels at 0 mm, 177 right-half at 10 mm and 3 without value (infinite): the middle pair is 0, 10
    assert m.median_abs_depth_mm == pytest.approx(5.0)
    assert m.median_rel_inter_object == pytest.approx(0.1)
    # a disparity-only method has no depth figures
    assert np.isnan(pixel_metrics(est_d, None, true_d, true_z, focus).median_abs_depth_mm)


def test_interior_misses_are_counted_apart_from_the_edges() -> None:
    # one depth edge between columns 29 and 30 of a 10 x 100 truth: both are edge pixels, and columns 0..8 and
    # 51..99 are more than 20 px from the nearer of them
    true_d = np.zeros((10, 100), np.float32)
    true_d[:, 30:] = 3.0
    true_z = np.where(true_d > 0, 1100.0, 1000.0)
    est_d = true_d.copy()
    est_d[:, 5] += 2.0  # 10 interior misses on the near side
    est_d[:, 80:82] -= 1.5  # 20 interior misses on the far side
    est_d[:, 31] += 2.0  # 10 misses beside the edge: not interior
    m = pixel_metrics(est_d, None, true_d, true_z, 1000.0)
    assert m.far_px == 10 * (9 + 49)
    assert m.far_bad_1 == pytest.approx(30 / m.far_px)
    assert m.bad_1 == pytest.approx(40 / 1000)
    # no depth edge at all: every pixel is interior
    flat = pixel_metrics(np.zeros((5, 5), np.float32), None, np.zeros((5, 5), np.float32), np.ones((5, 5)), 0.0)
    assert flat.far_px == 25 and flat.far_bad_1 == 0.0


def test_the_disparity_slope_measures_compression_and_ignores_gross_errors() -> None:
    true_d = np.tile(np.linspace(-6.0, 8.0, 200, dtype=np.float32), (20, 1))
    true_z = np.full(true_d.shape, 1200.0)
    compressed = 0.9 * true_d + 0.3
    assert disparity_slope(compressed, true_d, np.ones(true_d.shape, bool)) == pytest.approx(0.9, abs=1e-6)
    m = pixel_metrics(compressed, None, true_d, true_z, 1000.0)
    assert m.disparity_slope == pytest.approx(0.9, abs=1e-6)
    # gross errors (beyond SLOPE_WITHIN_PX) and missing values do not bend it
    spoiled = compressed.copy()
    spoiled[:, ::7] = 40.0
    spoiled[::3, 1::7] = np.nan
    assert pixel_metrics(spoiled, None, true_d, true_z, 1000.0).disparity_slope == pytest.approx(0.9, abs=1e-6)
    # a truth of one level has no slope to measure
    level = np.full((20, 20), 2.0, np.float32)
    assert np.isnan(pixel_metrics(level + 0.1, None, level, np.full(level.shape, 1100.0), 1000.0).disparity_slope)


def test_the_worst_slope_is_the_one_farthest_from_one() -> None:
    def metrics(slope: float) -> PixelMetrics:
        return PixelMetrics(0.1, 0.2, 0.3, 0.4, 5.0, 0.1, 1.0, 100, 10, disparity_slope=slope)

    rows = [RgbdRow(f"s{i}", "g", {"ours": metrics(v)}) for i, v in enumerate([0.95, 1.08, 0.9, 1.02])]
    summary = summarise_rgbd(rows, ["ours"])["ours"]["disparity_slope"]
    assert summary["worst"] == pytest.approx(0.9) and summary["median"] == pytest.approx(0.985)


def test_missing_values_count_as_bad_and_as_infinite_errors() -> None:
    true_d = np.ones((4, 4), np.float32)
    true_z = np.full((4, 4), 1200.0, np.float32)
    nothing = np.full((4, 4), np.nan, np.float32)
    m = pixel_metrics(nothing, nothing, true_d, true_z, 1000.0)
    assert (m.bad_1, m.bad_05, m.coverage) == (1.0, 1.0, 0.0)
    assert m.median_abs_depth_mm == np.inf and m.median_rel_inter_object == np.inf


def test_summary_takes_median_and_worst_per_figure() -> None:
    def metrics(bad: float, cover: float) -> PixelMetrics:
        return PixelMetrics(bad, bad, bad, bad, 10 * bad, bad, cover, 100, 10)

    rows = [
        RgbdRow(f"s{i}", "g", {"ours": metrics(b, c)}) for i, (b, c) in enumerate([(0.1, 0.9), (0.3, 1.0), (0.2, 0.5)])
    ]
    rows.append(RgbdRow("s3", "g", {}, status={"ours": "failed: x"}))
    summary = summarise_rgbd(rows, ["ours"])["ours"]
    assert summary["bad_1"] == {"median": pytest.approx(0.2), "worst": pytest.approx(0.3), "count": 3}
    assert summary["coverage"]["worst"] == pytest.approx(0.5)  # the lowest coverage is the worst


# --- the peers' conventions ---------------------------------------------------------------------------------------


def _plane(distance_mm: float, width: int = 200, height: int = 150):
    from mca.devices.sim.render_rgbd import render_filter_images, rgbd_optics

    optics = rgbd_optics(PROFILE, width, height, 1000.0, 22.5)
    rng = np.random.default_rng(4)
    grey = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), 1.5)
    texture = grey[..., None] * np.array([0.9, 0.7, 0.5], np.float32)  # colours on a line, as the peers assume
    images = render_filter_images(texture, np.full((height, width), distance_mm), optics)
    return images, optics.disparity_px(distance_mm)


def test_the_wta_peer_finds_a_fronto_parallel_plane() -> None:
    from mca.processing.peers import colour_line_wta_subpixel

    for distance in (1250.0, 860.0):
        images, disparity = _plane(distance)
        found = colour_line_wta_subpixel(images, PROFILE.aperture, (-6.0, 6.0), window_px=15, steps=81)
        step = 12.0 / 80
        assert np.median(found[20:-20, 20:-20]) == pytest.approx(disparity, abs=step)


def test_bando_runner_encodes_its_input_and_decodes_its_labels(tmp_path) -> None:
    """A stand-in program (not Bando's) that checks the PPM and answers label d = 3 everywhere, written as the
    real one writes depth_global.pgm (FORMAT.md): g = floor(label * 255 / (N - 1)), label = d - DMIN."""
    from mca.capture.peer_bando import decode_labels, label_range, labels_per_disparity, run_bando

    fake = tmp_path / "fake_bando"
    fake.write_text(
        f"#!{sys.executable}\n"
        "import sys\n"
        "data = open(sys.argv[1], 'rb').read()\n"
        "head = data.split(b'\\n', 3)\n"
        "assert head[0] == b'P6' and head[2] == b'255' and sys.argv[2] == '7', head[:3]\n"
        "w, h = map(int, head[1].split())\n"
        "assert len(head[3]) == 3 * w * h\n"
        "lo, hi = int(sys.argv[3]), int(sys.argv[4])\n"
        "g = ((3 - lo) * 255) // (hi - lo)\n"
        "open('depth_global.pgm', 'wb').write(b'P5\\n%d %d\\n255\\n' % (w, h) + bytes([g]) * (w * h))\n"
        f"import os; open({str(tmp_path / 'cwd.txt')!r}, 'w').write(os.getcwd())\n"
    )
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    assert labels_per_disparity(PROFILE.aperture) == pytest.approx(0.5)  # red-blue disparity = 2 d (paper-70d)
    assert label_range((-11.3, 15.2), 0.5) == (-6, 8)
    planes = np.random.default_rng(0).random((30, 40, 3)).astype(np.float32)
    answer = run_bando(fake, planes, PROFILE.aperture, (-11.3, 15.2))
    assert answer.labels == (-6, 8)
    assert not Path((tmp_path / "cwd.txt").read_text()).exists()  # its working folder is gone
    np.testing.assert_array_equal(answer.disparity_px, np.full((30, 40), 6.0))  # d = 3 -> 6 px red-blue
    # every grey value the program can write decodes to its own label, for every range size up to 255 labels
    for n in (2, 15, 16, 60, 255):
        labels = np.arange(n + 1)
        grey = (labels * 255) // n
        np.testing.assert_array_equal(decode_labels(grey.astype(np.uint8), -3, n - 3), labels - 3)


def test_bando_geometry_is_refused_for_other_apertures() -> None:
    import dataclasses

    from mca.capture.peer_bando import BandoGeometryError, labels_per_disparity

    rotated = dataclasses.replace(PROFILE.aperture, green_mm=(0.0, -6.0))
    with pytest.raises(BandoGeometryError, match="red right, green up, blue left"):
        labels_per_disparity(rotated)


BANDO = os.environ.get("MCA_BANDO_BIN")


@pytest.mark.skipif(not BANDO, reason="Bando 2008's program is not built (set MCA_BANDO_BIN to run this check)")
def test_bandos_program_finds_a_fronto_parallel_plane_with_our_geometry() -> None:
    from mca.capture.peer_bando import run_bando

    images, disparity = _plane(1520.0, 640, 200)
    assert 5.5 < disparity < 6.8  # the program's label 3: red 3 px right, blue 3 px left, green 3 px up
    answer = run_bando(Path(BANDO), images, PROFILE.aperture, (-10.0, 12.0))
    assert np.median(answer.disparity_px[30:-30, 30:-30]) == pytest.approx(round(disparity / 2) * 2, abs=0.01)


# --- mca evaluate --rgbd, for real --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_tree(tmp_path_factory) -> Path:
    """A cropped Middlebury scene as its own tree, rendered downscaled by 3/4 (240 x 176)."""
    if not MIDDLEBURY.is_dir():
        pytest.skip(f"the Middlebury scenes are not at {MIDDLEBURY}")
    from typer.testing import CliRunner

    from mca.capture.cli import app

    root = tmp_path_factory.mktemp("rgbd")
    source = root / "src" / "Cones"
    source.mkdir(parents=True)
    image = cv2.imread(str(MIDDLEBURY / "Cones" / "im.png"))
    disparity = cv2.imread(str(MIDDLEBURY / "Cones" / "disp.png"), cv2.IMREAD_UNCHANGED)
    box = (slice(80, 315), slice(110, 430))  # 320 x 235: cones in front of the lattice
    cv2.imwrite(str(source / "im.png"), image[box])
    cv2.imwrite(str(source / "disp.png"), disparity[box])
    (source / "SOURCE.txt").write_text("Disparity scale factor: 4\n")
    renders = root / "renders"
    result = CliRunner().invoke(
        app,
        ["simulate", "--from-rgbd-tree", str(root / "src"), "--scale", "0.75", "--seeds", "7", "--out", str(renders)],
    )
    assert result.exit_code == 0, result.output
    assert "Cones-s7: rendered" in result.output and "240x176 tiff" in result.output
    return renders


def _table_rows(output: str) -> dict[tuple[str, str], list[str]]:
    rows = {}
    for line in output.splitlines():
        parts = line.split()
        if len(parts) >= 9 and parts[0] == "Cones-s7":
            rows[(parts[0], parts[1])] = parts[2:9]
    return rows


def test_mca_evaluate_rgbd_prints_figures_consistent_with_its_json(tiny_tree: Path) -> None:
    from typer.testing import CliRunner

    from mca.capture.cli import app

    runner = CliRunner()
    missing = str(tiny_tree / "no-such-program")
    table = runner.invoke(app, ["evaluate", "--rgbd", str(tiny_tree), "--bando", missing])
    assert table.exit_code == 0, table.output
    rows = _table_rows(table.output)
    assert set(rows) == {("Cones-s7", "ours"), ("Cones-s7", "ours-raw"), ("Cones-s7", "wta")}
    assert re.search(r"Cones-s7\s+bando\s+not built", table.output)
    assert (tiny_tree / ".peers").is_dir()  # the WTA answer is cached for the next run

    report = runner.invoke(app, ["evaluate", "--rgbd", str(tiny_tree), "--bando", missing, "--json"])
    assert report.exit_code == 0, report.output
    document = json.loads(report.stdout)
    (render,) = document["renders"]
    assert render["name"] == "Cones-s7" and render["status"]["bando"] == "not built"
    for method in ("ours", "ours-raw", "wta"):
        assert method in render["metrics"], render["status"]
        figures = render["metrics"][method]
        printed = rows[("Cones-s7", method)]
        for cell, key in zip(printed, PixelMetrics.FIELDS):
            value = figures[key]
            if cell.endswith("%"):
                assert float(cell[:-1]) == pytest.approx(100 * value, abs=0.051), (method, key)
            elif cell == "inf":
                assert value is None or value == float("inf")
            else:
                assert float(cell) == pytest.approx(value, abs=0.051), (method, key)
        assert 0.0 <= figures["bad_1"] <= figures["bad_05"] <= 1.0
        assert 0.0 <= figures["coverage"] <= 1.0
        # one render: the median and the worst are its own figures
        assert document["all"][method]["bad_1"]["median"] == pytest.approx(figures["bad_1"])
    # the WTA answer came from the cache the second time: the same figures
    assert rows[("Cones-s7", "wta")][0] == f"{100 * render['metrics']['wta']['bad_1']:.1f}%"


def test_mca_evaluate_rgbd_names_an_empty_folder(tmp_path) -> None:
    from typer.testing import CliRunner

    from mca.capture.cli import app

    result = CliRunner().invoke(app, ["evaluate", "--rgbd", str(tmp_path)])
    assert result.exit_code == 2
    assert "no rendered scene" in result.output and str(tmp_path) in result.output


# --- the peers' cache -------------------------------------------------------------------------------------------

_LOADED_BY_WTA = """
import sys
import numpy as np
from mca.devices.profiles import load_profile
from mca.processing.peers import colour_line_wta_subpixel
planes = np.random.default_rng(0).random((40, 60, 3)).astype(np.float32)
colour_line_wta_subpixel(planes, load_profile("paper-70d").aperture, (-2.0, 2.0), window_px=5, steps=9)
for name, module in sys.modules.items():
    path = getattr(module, "__file__", None) or ""
    if name.startswith("mca.") and path.endswith(".py") and not path.endswith("__init__.py"):
        print(name)
"""


def test_the_wta_cache_key_covers_every_module_the_peer_runs(tmp_path: Path) -> None:
    """`peer_code_digest` reads the modules a peer reaches from their source; a fresh process that runs the WTA
    peer loads no module of ours outside that set, so no code it runs can change without changing the key."""
    import subprocess

    from mca.capture.rgbd_evaluation import _mca_imports

    done = subprocess.run([sys.executable, "-c", _LOADED_BY_WTA], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    loaded = {line for line in done.stdout.splitlines() if line.startswith("mca.processing.")}
    covered = _mca_imports("mca.processing.peers")
    assert {"mca.processing.peers", "mca.processing.disparity", "mca.processing.sampling"} <= covered
    assert loaded <= covered, sorted(loaded - covered)


def test_a_peer_runs_again_when_its_code_or_its_input_changes(tmp_path: Path) -> None:
    """The cached answer is reused only for the same planes, range, parameters and code."""
    from types import SimpleNamespace

    from mca.capture.rgbd_evaluation import RenderEntry, _cached_peer, _Context, peer_code_digest

    image = tmp_path / "Scene-s1.tiff"
    image.write_bytes(b"not read here")
    entry = RenderEntry("Scene-s1", ".", image, tmp_path / "truth", {})
    loaded = SimpleNamespace(pixel_scale=1.0, input_size_px=(6, 4))
    optics = SimpleNamespace(distance_mm=lambda d: 1000.0 + d)
    planes = np.zeros((4, 6, 3), np.float32)
    runs = []

    def compute() -> tuple[np.ndarray, float]:
        runs.append(1)
        return np.full((4, 6), float(len(runs)), np.float32), 0.5

    def answer(code: str, context: _Context) -> float:
        return float(_cached_peer(entry, "wta", context, {"window": 15}, code, compute).disparity_px[0, 0])

    context = _Context(loaded, optics, (-2.0, 3.0), aligned=planes)
    assert answer("code-a", context) == 1.0
    assert answer("code-a", context) == 1.0 and len(runs) == 1  # from the cache
    assert answer("code-b", context) == 2.0  # the peer's code changed
    changed = _Context(loaded, optics, (-2.0, 3.0), aligned=planes + np.float32(0.001))
    assert answer("code-b", changed) == 3.0  # the capture reads differently
    assert answer("code-b", _Context(loaded, optics, (-2.0, 4.0), aligned=planes)) == 4.0  # another range
    assert len(list((tmp_path / ".peers").glob("Scene-s1.wta.*.npz"))) == 1  # the stale answers are gone

    program = tmp_path / "program"
    program.write_bytes(b"one build")
    first = peer_code_digest("mca.capture.peer_bando", program)
    program.write_bytes(b"rebuilt, longer")  # in the same process, as a rebuild during an evaluation
    assert peer_code_digest("mca.capture.peer_bando", program) != first
    assert peer_code_digest("mca.capture.peer_bando") != peer_code_digest("mca.processing.peers")
