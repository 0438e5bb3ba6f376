"""dev.py, the README's two commands: how `python3 dev.py test` spreads the suite over the machine's cores."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def dev():
    spec = importlib.util.spec_from_file_location("dev_script", ROOT / "dev.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("cores, expected", [(1, 1), (2, 2), (3, 3), (16, 4)])
def test_one_worker_per_core_at_most_four(dev, monkeypatch, cores, expected):
    monkeypatch.setattr(dev.os, "sched_getaffinity", lambda pid: set(range(cores)))
    assert dev.xdist_workers([]) == expected
    assert dev.xdist_workers(["-q", "-k", "batch", "tests/test_batch.py"]) == expected


@pytest.mark.parametrize(
    "args",
    [["-n", "0"], ["-n4"], ["--numprocesses=3"], ["-p", "no:xdist"], ["--co", "-q"], ["--pdb"], ["--trace"], ["-s"]],
)
def test_no_workers_added_when_the_caller_chooses_or_needs_the_terminal(dev, monkeypatch, args):
    """1: dev.py adds no -n (the caller's own -n stands; a debugger or -s gets one process)."""
    monkeypatch.setattr(dev.os, "sched_getaffinity", lambda pid: {0, 1})
    assert dev.xdist_workers(args) == 1
