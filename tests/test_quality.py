"""`--quality full|preview` (issue 16): the pipeline gets `PipelineParams.for_quality`, result.json says which, and
a preview result never stands for a full one (nor the other way round); batch workers get their share of threads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_process import fake_pipeline, make_png
from typer.testing import CliRunner

from mca.capture.batch import run_batch, worker_threads
from mca.capture.cli import app
from mca.capture.pipeline_app import RESULT_NAME, process_file, settings_key
from mca.capture.threads import threads_per_worker
from mca.devices.profiles import load_profile
from mca.processing.pipeline import PipelineParams

SIM_SCALE = 0.1  # of the 70D's 5472 x 3648: 547 x 365 photosites, about a second through the pipeline


@pytest.fixture(scope="module")
def profile():
    return load_profile("paper-70d")


@pytest.fixture(scope="module")
def small_cr2(tmp_path_factory) -> Path:
    """A small simulated CR2 (the paper's scene g) that the real pipeline processes in about a second."""
    from mca.devices.sim.world import capture_cr2_bytes, render_scene

    profile = load_profile("paper-70d")
    path = tmp_path_factory.mktemp("quality") / "knife.CR2"
    path.write_bytes(capture_cr2_bytes(render_scene("paper-g", profile, size=SIM_SCALE), profile))
    return path


def _document(out: Path, name: str) -> dict:
    return json.loads((out / name / RESULT_NAME).read_text())


def test_the_pipeline_receives_the_parameters_of_the_quality(tmp_path, profile):
    seen: list[PipelineParams] = []

    def spy(planes, aperture, optics, *, params: PipelineParams, **options):
        seen.append(params)
        return fake_pipeline(planes, aperture, optics, **options)

    source = make_png(tmp_path / "a.png")
    for quality in ("preview", "full"):
        outcome = process_file(source, tmp_path / quality, profile, pipeline=spy, quality=quality)
        assert outcome.status == "done", outcome.reason
    assert seen == [PipelineParams.for_quality("preview"), PipelineParams()]
    assert seen[0] != seen[1]  # otherwise this test could not tell the settings apart
    preview = _document(tmp_path / "preview", "a")["settings"]
    assert preview["quality"] == "preview"
    assert (
        preview["pipeline_params"]["analysis_max_side_px"] == PipelineParams.for_quality("preview").analysis_max_side_px
    )
    assert preview["pipeline_params"]["boundaries"] is None  # preview leaves out the boundary snap
    full = _document(tmp_path / "full", "a")["settings"]
    assert full["quality"] == "full"
    assert full["pipeline_params"]["analysis_max_side_px"] == PipelineParams().analysis_max_side_px


def test_the_settings_key_includes_the_quality_and_full_keeps_the_earlier_key(profile):
    assert settings_key(profile, "preview") != settings_key(profile, "full")
    assert settings_key(profile) == settings_key(profile, "full")  # results made before --quality stay finished
    with pytest.raises(ValueError, match="preview"):
        settings_key(profile, "draft")


def test_cli_a_preview_result_does_not_stop_a_full_run_and_each_quality_skips_its_own(small_cr2, tmp_path):
    out = tmp_path / "out"
    runner = CliRunner()

    def run(*extra: str) -> dict:
        result = runner.invoke(app, ["process", str(small_cr2), "--out", str(out), "--json", *extra])
        assert result.exit_code == 0, result.output
        (entry,) = json.loads(result.output)["files"]
        return entry

    first = run("--quality", "preview")
    assert first["status"] == "done"
    assert _document(out, "knife")["settings"]["quality"] == "preview"
    assert run("--quality", "preview")["status"] == "skipped"  # same photograph, same settings

    full = run()  # the default is full: it must not take the preview result for its own
    assert full["status"] == "done", full
    document = _document(out, "knife")
    assert document["settings"]["quality"] == "full" and document["status"] == "done"
    assert document["settings_sha256"] != settings_key(load_profile("paper-70d"), "preview")
    assert run("--quality", "full")["status"] == "skipped"
    again = run("--quality", "preview")  # and a later preview run does not take the full result for a preview
    assert again["status"] == "done" and _document(out, "knife")["settings"]["quality"] == "preview"


def test_cli_a_result_without_settings_counts_as_full(small_cr2, tmp_path, profile):
    out = tmp_path / "out"
    assert process_file(small_cr2, out, profile, pipeline=fake_pipeline).status == "done"
    path = out / "knife" / RESULT_NAME
    document = json.loads(path.read_text())
    del document["settings"]  # as an mca before --quality wrote it
    path.write_text(json.dumps(document))
    assert process_file(small_cr2, out, profile, pipeline=fake_pipeline).status == "skipped"
    assert process_file(small_cr2, out, profile, pipeline=fake_pipeline, quality="preview").status == "done"


def test_cli_an_unknown_quality_is_a_usage_error(tmp_path):
    source = make_png(tmp_path / "a.png")
    result = CliRunner().invoke(app, ["process", str(source), "--out", str(tmp_path / "o"), "--quality", "fast"])
    assert result.exit_code == 2
    assert "--quality" in result.output and "full, preview" in result.output
    assert not (tmp_path / "o" / "a").exists()
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--out", str(tmp_path / "c"), "--quality", "x"])
    assert result.exit_code == 2 and "--quality" in result.output


def test_capture_process_with_preview_quality(tmp_path, monkeypatch):
    monkeypatch.setenv("MCA_SIM_SIZE", str(SIM_SCALE))
    out = tmp_path / "shots"
    result = CliRunner().invoke(
        app, ["capture", "--camera", "sim", "--count", "1", "--out", str(out), "--process", "--quality", "preview"]
    )
    assert result.exit_code == 0, result.output
    document = _document(out, "IMG_0001")
    assert document["status"] == "done" and document["settings"]["quality"] == "preview"


def test_the_api_takes_the_quality(small_cr2):
    import mca

    preview = mca.depth_from_file(small_cr2, "paper-70d", quality="preview")
    full = mca.depth_from_file(small_cr2, "paper-70d")
    assert preview.labels.shape == full.labels.shape  # the same processing grid, the analysis grid differs
    with pytest.raises(ValueError, match="quality"):
        mca.depth_from_file(small_cr2, "paper-70d", quality="best")


# --- threads of batch workers ---------------------------------------------------------------------------------------


def test_threads_per_worker_shares_the_cores():
    assert threads_per_worker(1, cores=2) == 2
    assert threads_per_worker(2, cores=2) == 1
    assert threads_per_worker(3, cores=2) == 1
    assert threads_per_worker(2, cores=8) == 4


def test_worker_threads_follows_the_environment(monkeypatch):
    monkeypatch.setenv("MCA_WORKER_THREADS", "0")
    assert worker_threads(2) is None  # no limit
    monkeypatch.setenv("MCA_WORKER_THREADS", "3")
    assert worker_threads(2) == 3
    monkeypatch.setenv("MCA_WORKER_THREADS", "many")
    with pytest.raises(Exception, match="MCA_WORKER_THREADS"):
        worker_threads(2)
    monkeypatch.delenv("MCA_WORKER_THREADS")
    assert worker_threads(2) == threads_per_worker(2)


LIMIT_SCRIPT = """
import json, sys
import numba  # loaded before the limit, as in a worker that ran a file already
from mca.capture.threads import limit_threads
from mca.processing import disparity
limit_threads(1)
import cv2
calls = []
disparity.parallel_map(lambda i: calls.append(i), range(4))
# numba re-reads NUMBA_NUM_THREADS before every compile and refuses a new value once its pool runs
compiled = numba.njit(lambda x: x + 1)(1)
print(json.dumps({"numba": numba.get_num_threads(), "opencv": cv2.getNumThreads(), "helpers": disparity._WORKERS,
                  "calls": sorted(calls), "compiled": compiled}))
"""


def test_limit_threads_limits_numba_opencv_and_the_helper_threads():
    done = subprocess.run([sys.executable, "-c", LIMIT_SCRIPT], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    seen = json.loads(done.stdout)
    assert seen == {"numba": 1, "opencv": 1, "helpers": 1, "calls": [0, 1, 2, 3], "compiled": 2}


def thread_reporting_pipeline(planes, aperture, optics, **options):
    """A pool worker's view of its thread limits, written beside the outputs (MCA_TEST_THREADS_DIR)."""
    import cv2
    import numba

    folder = Path(os.environ["MCA_TEST_THREADS_DIR"])
    seen = {
        "opencv": cv2.getNumThreads(),
        "numba_env": os.environ.get("NUMBA_NUM_THREADS"),
        "numba_pool": numba.config.NUMBA_NUM_THREADS,  # sized when numba loaded: after the limit, not before
    }
    (folder / f"{os.getpid()}.json").write_text(json.dumps(seen))
    return fake_pipeline(planes, aperture, optics, **options)


def test_pool_workers_run_with_their_share_of_threads(tmp_path, profile, monkeypatch):
    report_dir = tmp_path / "threads"
    report_dir.mkdir()
    monkeypatch.setenv("MCA_TEST_THREADS_DIR", str(report_dir))
    monkeypatch.setenv("MCA_WORKER_THREADS", "1")  # as on 2 cores with 2 workers, whatever this machine has
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("a", "b", "c"):
        make_png(inputs / f"{name}.png")
    report = run_batch([inputs], tmp_path / "out", profile, workers=2, pipeline=thread_reporting_pipeline)
    assert [o.status for o in report.outcomes] == ["done"] * 3, [o.reason for o in report.outcomes]
    seen = [json.loads(p.read_text()) for p in report_dir.iterdir()]
    assert seen and all(s == {"opencv": 1, "numba_env": "1", "numba_pool": 1} for s in seen), seen


def test_files_processed_in_this_process_keep_every_thread(tmp_path, profile, monkeypatch):
    import cv2

    before = cv2.getNumThreads()
    report = run_batch([make_png(tmp_path / "a.png")], tmp_path / "out", profile, pipeline=fake_pipeline)
    assert report.outcomes[0].status == "done"
    assert cv2.getNumThreads() == before  # --workers 1: nothing is limited


def test_mca_process_does_not_import_the_slow_scipy_modules(small_cr2, tmp_path):
    """`scipy.optimize` (0.3 s) and `scipy.ndimage` (0.2 s) are slow to import, and a one-file `mca process` would
    pay for them on its critical path: the noise fit is ours (`features.nnls_2`), and so are the region boxes of
    the outputs (`labels.label_boxes`). A whole run, the real pipeline, every output written, in a fresh process."""
    script = (
        "import sys\n"
        "from mca.capture.cli import main\n"
        f"sys.argv = ['mca', 'process', {str(small_cr2)!r}, '--out', {str(tmp_path / 'out')!r}]\n"
        "try:\n"
        "    main()\n"
        "except SystemExit as stop:\n"
        "    assert not stop.code, stop.code\n"
        "print(sorted(m for m in sys.modules if m.startswith(('scipy.optimize', 'scipy.ndimage'))))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "out" / small_cr2.stem / RESULT_NAME).is_file()
    assert done.stdout.strip().splitlines()[-1] == "[]", done.stdout[-2000:]
