"""The independent validators the tests run (tiffinfo, pngcheck, exiftool, the Khronos glTF validator, rerun).

`dev.py test` installs them; on CI (`CI` set) a missing one fails the test instead of skipping it, so a
validator that silently went missing cannot turn a check into a skip.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent
GLTF_VALIDATOR_DIR = ROOT / ".venv" / "node"  # dev.py: npm install --prefix .venv/node gltf-validator


def benchmark_module(name: str) -> ModuleType:
    """`benchmarks/<name>.py` loaded as a module (the benchmarks are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def require(tool: str, install: str) -> str:
    """The path of command-line tool `tool`; fails on CI, skips elsewhere, when it is missing."""
    path = shutil.which(tool)
    if path is None:
        message = f"{tool} is not installed ({install}); `python3 dev.py test` installs it"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


def gltf_validator() -> tuple[str, Path]:
    """(node, the gltf-validator package folder)."""
    node = require("node", "apt-get install nodejs")
    package = Path(os.environ.get("MCA_GLTF_VALIDATOR", GLTF_VALIDATOR_DIR / "node_modules" / "gltf-validator"))
    if not (package / "index.js").is_file():
        message = f"the Khronos glTF validator is not at {package} (npm install --prefix .venv/node gltf-validator)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return node, package
