"""`mca process --cluster`: the same per-file task on a Dask scheduler and worker on 127.0.0.1 gives a local run's outputs."""

from __future__ import annotations

import pytest
from test_batch import assert_same_outputs
from test_process import make_cr2, make_png, make_tiff
from typer.testing import CliRunner

from mca.capture.batch import run_batch
from mca.capture.cli import app
from mca.devices.profiles import load_profile

distributed = pytest.importorskip("distributed", reason="dask[distributed] is the 'cluster' extra")


@pytest.fixture(scope="module")
def cluster_address():
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None
    ) as cluster:
        yield cluster.scheduler_address


def test_cluster_run_equals_local_run(tmp_path, cluster_address):
    folder = tmp_path / "in"
    folder.mkdir()
    make_png(folder / "p.png", 40, 56)
    make_tiff(folder / "t.tiff", 36, 48)
    make_cr2(folder / "c.CR2", 64, 80)
    (folder / "bad.png").write_bytes(b"not a png")
    profile = load_profile("paper-70d")
    local = run_batch([folder], tmp_path / "local", profile, workers=1)
    assert cluster_address.startswith("tcp://127.0.0.1:")
    remote = run_batch([folder], tmp_path / "cluster", profile, cluster=cluster_address)
    statuses = {o.input_path.name: o.status for o in remote.outcomes}
    assert statuses == {"p.png": "done", "t.tiff": "done", "c.CR2": "done", "bad.png": "failed"}
    assert statuses == {o.input_path.name: o.status for o in local.outcomes}
    assert "bad.png" in remote.failed[0].reason
    assert_same_outputs(tmp_path / "local", tmp_path / "cluster")


def test_cli_cluster_resumes(tmp_path, cluster_address):
    folder = tmp_path / "in"
    folder.mkdir()
    make_png(folder / "a.png", 32, 40)
    args = ["process", str(folder), "--out", str(tmp_path / "out"), "--cluster", cluster_address]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    assert "1 done" in first.output
    second = CliRunner().invoke(app, args)
    assert second.exit_code == 0 and "1 skipped" in second.output
