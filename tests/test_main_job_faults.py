"""The main job under faults: kills, a full disk, pulled cables and concurrent runs lose and mix nothing (issue 13).

Runs tests/main_job_faults.py (see there what each round does and checks) in a process of its
own. When this machine lets us make a mount namespace (`unshare -r -m`, or `unshare -m` as
root: CI as root or not), the output folder lies on a small tmpfs that is really filled up;
otherwise a shim makes the runs' writes under the output folder fail with ENOSPC. The number of
rounds is `MCA_FAULT_ROUNDS` (8 in the suite). The counts are printed for the closing note.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROUNDS = int(os.environ.get("MCA_FAULT_ROUNDS", "8"))
DRIVER = Path(__file__).with_name("main_job_faults.py")


def _namespace_prefix() -> list[str]:
    """The command prefix that gives the driver a mount namespace of its own, or [] when none can be made."""
    unshare = shutil.which("unshare")
    if unshare is None or not sys.platform.startswith("linux"):
        return []
    for prefix in ([unshare, "-r", "-m"], [unshare, "-m"]):
        probe = subprocess.run([*prefix, "true"], capture_output=True, check=False)
        if probe.returncode == 0:
            return prefix
    return []


@pytest.fixture(scope="module")
def summary(tmp_path_factory) -> dict:
    """One run of the driver, shared by the assertions below."""
    tmp_path = tmp_path_factory.mktemp("main-job-faults")
    prefix = _namespace_prefix()
    env = dict(os.environ, RERUN_ANALYTICS="0", MCA_SIM_SIZE="0.1")
    if prefix:
        env["MCA_FAULTS_IN_NAMESPACE"] = "1"
    done = subprocess.run(
        [
            *prefix,
            sys.executable,
            str(DRIVER),
            *("--work", str(tmp_path), "--rounds", str(ROUNDS), "--seed", "13"),
            *("--tmpfs-mb", str(64 + 16 * ROUNDS)),  # a shot with its outputs and recording: about 5 MB
        ],
        capture_output=True,
        text=True,
        timeout=60 * max(10, ROUNDS),
        env=env,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    print(
        f"\nmain job under faults ({summary['disk']}): {summary['faults_injected']} faults injected "
        f"{summary['faults']}, {summary['files_checked']} files checked, {summary['exposures']} exposures: "
        f"{summary['processed']} processed, {summary['pending']} pending, {len(summary['problems'])} problems"
    )
    for entry in summary["rounds"]:
        print(f"  {entry}")
    for finding in summary["findings"]:
        print(f"  finding: {finding}")
    print(f"  exposures on the card the catalog does not list: {summary['unlisted_exposures']}")
    return summary


@pytest.mark.slow
def test_the_main_job_under_kills_full_disks_disconnects_and_concurrent_runs(summary):
    """Nothing outside --out touched, no partial output visible, the catalog agrees with the disk, every
    catalogued shot processed or pending after each round and processed after the clean runs."""
    assert summary["problems"] == [], "\n".join(summary["problems"])
    assert summary["faults_injected"] >= ROUNDS // 2
    listed = summary["exposures"] - len(summary["unlisted_exposures"])
    assert listed > 0 and summary["processed"] == listed and summary["pending"] == 0


@pytest.mark.slow
def test_every_exposure_on_the_card_is_in_the_catalog(summary):
    """A kill or Ctrl-C between the shutter release and the catalog row no longer hides the exposure: the release
    is noted (table `releases`) before the shutter goes, and the next run catalogues and fetches what it made."""
    assert summary["unlisted_exposures"] == []
