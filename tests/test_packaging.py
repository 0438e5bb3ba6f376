"""The package as people install it: licence metadata, tested dependency floors, the lowest-versions constraints."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from importlib.metadata import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_licence_file_matches_the_metadata() -> None:
    project = PYPROJECT["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text(encoding="utf-8").startswith("MIT License\n")
    assert not any(c.startswith("License ::") for c in project["classifiers"])  # SPDX expression instead
    assert metadata("mca-appliance")["License-Expression"] == "MIT"


def test_every_dependency_has_a_floor_and_rerun_one_minor_release() -> None:
    sys.path.insert(0, str(ROOT / ".ci"))
    try:
        from lowest_constraints import constraints, floor_of
    finally:
        sys.path.pop(0)
    project = PYPROJECT["project"]
    for requirement in project["dependencies"] + project["optional-dependencies"]["test"]:
        assert floor_of(requirement)[1] is not None, requirement
    rerun = next(r for r in project["dependencies"] if r.startswith("rerun-sdk"))
    assert rerun == "rerun-sdk>=0.41.0,<0.42"
    pins = constraints(ROOT / "pyproject.toml", ["test"])
    assert "rerun-sdk==0.41.0" in pins and "typer==0.16.0" in pins and "numpy==2.0.0" in pins
    assert all(pin.count("==") == 1 and "[" not in pin for pin in pins)


def test_lowest_constraints_script_runs_standalone() -> None:
    out = subprocess.run(
        [sys.executable, str(ROOT / ".ci" / "lowest_constraints.py"), "test"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "scipy==1.13.0" in out.stdout.split()


def test_readme_installs_with_the_usb_extra_and_says_which_rerun_reads_recordings() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert 'pip install ".[usb]"' in readme
    assert "rerun-sdk==0.41.*" in readme and "opened by the rerun version that wrote it" in readme
    assert (ROOT / "CHANGELOG.md").is_file()
