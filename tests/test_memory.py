"""A process with more captures to do keeps the memory it frees (`capture.memory`): the allocator then serves a
large array from pages it already has, and the batch runner switches to it after its first capture only."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from mca.capture import batch
from mca.capture.memory import RETURN_MEMORY_ENV

_GLIBC = sys.platform.startswith("linux") and "glibc" in " ".join(__import__("platform").libc_ver())

# In a process of its own: the setting stays for the life of the process that makes it.
_SCRIPT = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    from mca.capture.memory import keep_freed_memory
    kept = keep_freed_memory()
    first = np.ones(64 << 20, np.uint8)  # 64 MiB, far above the allocator's mmap threshold
    del first
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    second = np.ones(64 << 20, np.uint8)
    print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def _faults_of_a_second_array(env_value: str | None) -> tuple[bool, int]:
    import os

    env = dict(os.environ)
    env.pop(RETURN_MEMORY_ENV, None)
    if env_value is not None:
        env[RETURN_MEMORY_ENV] = env_value
    done = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    kept, faults = done.stdout.split()
    return kept == "True", int(faults)


@pytest.mark.skipif(not _GLIBC, reason="glibc's allocator only")
def test_a_freed_array_is_taken_again_without_new_pages():
    kept, faults = _faults_of_a_second_array(None)
    assert kept
    assert faults < 16  # the 64 MiB come back from the heap: no page is faulted in again
    returned, faults_returned = _faults_of_a_second_array("1")  # MCA_RETURN_MEMORY=1: the allocator as it was
    assert not returned
    assert faults_returned >= 32  # a fresh mapping: every page (or 2 MiB huge page) faulted in again


def test_the_batch_runner_keeps_memory_from_its_second_capture_on(monkeypatch, tmp_path):
    """A single photograph never switches the allocator (with it, its first capture is slower); the inline runner
    switches once a capture is done, before the next one starts."""
    events: list[str] = []

    def process_file(path: Path, *args: object, **kwargs: object) -> str:
        events.append(f"process {path.name}")
        return "outcome"

    monkeypatch.setattr(batch, "process_file", process_file)
    monkeypatch.setattr(batch, "keep_freed_memory", lambda: events.append("keep") or True)
    job = batch._Job(out_root=tmp_path, profile=None, force=False, pipeline=None)  # type: ignore[arg-type]
    runner = batch.InlineRunner(job)
    for name in ("a.CR2", "b.CR2"):
        runner.submit(batch.Task(input_path=tmp_path / name, out_name=name))
    runner.wait(0.0)
    assert events == ["process a.CR2", "keep"]
    runner.wait(0.0)
    assert events == ["process a.CR2", "keep", "process b.CR2", "keep"]
