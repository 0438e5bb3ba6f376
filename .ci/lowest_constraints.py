#!/usr/bin/env python3
"""Write a pip constraints file pinning every dependency of pyproject.toml to its declared floor.

pip has no lowest-version resolution, so `.ci/lowest` installs the project with these pins
(`pip install -c FILE -e '.[test]'`) and runs the suite: a floor that does not work fails CI.
Usage: lowest_constraints.py [EXTRA ...] > constraints.txt (the runtime dependencies always, plus the extras named).
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

REQUIREMENT = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[[^\]]*\])?\s*(.*?)\s*(;.*)?$")


def floor_of(requirement: str) -> tuple[str, str | None]:
    """(distribution name, lowest version allowed by its `>=` or `==` clause, or None)."""
    match = REQUIREMENT.match(requirement)
    if match is None:
        raise ValueError(f"cannot read the requirement {requirement!r}")
    name, _extras, spec, _marker = match.groups()
    floor = None
    for clause in filter(None, (part.strip() for part in spec.split(","))):
        operator, version = re.match(r"(>=|==|~=|<=|<|>|!=)\s*(\S+)", clause).groups()  # type: ignore[union-attr]
        if operator in (">=", "==", "~="):
            floor = version
    return name.lower().replace("_", "-"), floor


def constraints(pyproject: Path, extras: list[str]) -> list[str]:
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    requirements = list(project.get("dependencies", []))
    optional = project.get("optional-dependencies", {})
    for extra in extras:
        if extra not in optional:
            raise SystemExit(f"{pyproject}: no optional dependency group '{extra}' (have {', '.join(optional)})")
        requirements += optional[extra]
    pins: dict[str, str] = {}
    for requirement in requirements:
        name, floor = floor_of(requirement)
        if floor is None:
            raise SystemExit(f"{pyproject}: '{requirement}' declares no floor; give it one (>=X) that the suite passes")
        if pins.get(name, floor) != floor:
            raise SystemExit(f"{pyproject}: {name} has two floors, {pins[name]} and {floor}")
        pins[name] = floor
    return [f"{name}=={version}" for name, version in sorted(pins.items())]


if __name__ == "__main__":
    root = Path(__file__).resolve().parent.parent
    print("\n".join(constraints(root / "pyproject.toml", sys.argv[1:])))
