"""The import arrows of docs/architecture.md, checked by parsing every module's imports (nothing is imported).

capture -> processing and capture -> devices are the arrows between the rooms, plus one from the
simulated world (devices/sim, and the camera profiles it renders through) to the optics in processing;
processing is pure (no I/O library); the PTP and GRBL codecs are pure; the real device stacks never
import their simulated twins. A violation names the file, the line and the import.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ROOMS = {"capture": "mca.capture", "processing": "mca.processing", "devices": "mca.devices"}

# Libraries that touch files, devices, the network or the terminal: none of them in processing/.
IO_LIBRARIES = frozenset(
    {"rerun", "rerun_cli", "usb", "libusb_package", "serial", "typer", "rich", "rawpy", "tifffile", "socket", "sqlite3"}
)
# The pure protocol codecs and the sans-I/O transaction engine: bytes in, messages out; no transport library.
CODEC_MODULES = (
    "devices/ptp/codec.py",
    "devices/ptp/codes.py",
    "devices/ptp/datasets.py",
    "devices/ptp/engine.py",
    "devices/ptp/events.py",
    "devices/ptp/framing.py",
    "devices/ptp/liveview.py",
    "devices/ptp/policy.py",
    "devices/ptp/properties.py",
    "devices/ptp/ptpip_packets.py",
    "devices/rail/grbl_protocol.py",
)
CODEC_FORBIDDEN = frozenset({"usb", "libusb_package", "serial", "socket", "select", "threading", "subprocess"})


@dataclass(frozen=True)
class Import:
    path: str  # relative to the repository
    line: int
    module: str  # absolute dotted name

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: imports {self.module}"


@dataclass(frozen=True)
class Module:
    path: str  # relative to the repository, e.g. "capture/commands/process.py"
    source: str

    @property
    def package(self) -> str:
        """`capture/commands/x.py` -> `mca.capture.commands` (where a relative import starts from)."""
        parts = Path(self.path).parts
        return ".".join([ROOMS[parts[0]], *parts[1:-1]])


def room_modules(folder: str) -> list[Module]:
    """Every module below `folder` (a room or a part of one), as it is on disk."""
    files = sorted((ROOT / folder).rglob("*.py"))
    return [Module(str(p.relative_to(ROOT)), p.read_text(encoding="utf-8")) for p in files]


def module_imports(module: Module) -> list[Import]:
    """Every module imported, at any depth (inside functions and `if TYPE_CHECKING:` too), as absolute names."""
    tree = ast.parse(module.source, filename=module.path)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [Import(module.path, node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.package.split(".")
                base = base[: len(base) - (node.level - 1)]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            found.append(Import(module.path, node.lineno, name))
            # `from mca import capture`, `from .. import ptp`: the names may be modules themselves
            found += [Import(module.path, node.lineno, f"{name}.{alias.name}") for alias in node.names]
    return found


def top(module: str) -> str:
    return module.split(".")[0]


def is_under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def violations(modules: list[Module], forbidden_packages: tuple[str, ...], forbidden_top: frozenset[str]) -> list[str]:
    bad: dict[tuple[str, int], Import] = {}
    for module in modules:
        for imp in module_imports(module):
            if any(is_under(imp.module, p) for p in forbidden_packages) or top(imp.module) in forbidden_top:
                bad.setdefault((imp.path, imp.line), imp)  # one line, one report: the module, not its names
    return [str(imp) for _, imp in sorted(bad.items())]


# The arrows, as functions of the modules they look at (the planted-import test hands them one more).


def processing_violations(modules: list[Module]) -> list[str]:
    return violations(modules, ("mca.capture", "mca.devices"), IO_LIBRARIES)


# The simulated world renders its photographs through the paper's optics, and a camera profile is the
# `processing.camera.CameraProfile` it describes: these two may import processing; the real stacks may not.
MAY_IMPORT_PROCESSING = ("devices/sim/", "devices/profiles/")


def devices_violations(modules: list[Module]) -> list[str]:
    bad = violations(modules, ("mca.capture",), frozenset({"rerun", "typer", "rich", "rawpy"}))
    real = [m for m in modules if not m.path.startswith(MAY_IMPORT_PROCESSING)]
    return sorted(set(bad) | set(violations(real, ("mca.processing",), frozenset())))


def codec_violations(modules: list[Module]) -> list[str]:
    return violations(modules, ("mca.capture", "mca.processing"), CODEC_FORBIDDEN)


def twin_violations(modules: list[Module]) -> list[str]:
    """The real stacks (devices/ptp, devices/rail) must not import the simulated twins; `open_rail("sim")` in
    devices/rail/__init__.py starts the twin on request, as pyserial's `serial_for_url("loop://")` does."""
    bad = violations(modules, ("mca.devices.sim",), frozenset())
    return [v for v in bad if not v.startswith("devices/rail/__init__.py")]


# --- the parser itself ----------------------------------------------------------------------------------------------


def test_the_parser_sees_every_kind_of_import() -> None:
    source = (
        "import os, usb.core\n"
        "from mca.capture.raw import read_raw\n"
        "from ..capture import tether\n"
        "from . import colour\n"
        "from mca import devices\n"
        "def f():\n    import rerun as rr\n"
        "if TYPE_CHECKING:\n    from mca.devices.ptp.camera import Camera\n"
    )
    found = {i.module for i in module_imports(Module("processing/pipeline.py", source))}
    assert {
        "os",
        "usb.core",
        "mca.capture.raw",
        "mca.capture.tether",
        "mca.processing.colour",
        "mca.devices",
        "rerun",
        "mca.devices.ptp.camera",
    } <= found


def test_every_room_has_modules() -> None:
    """The checks below would pass vacuously on an empty or misplaced tree."""
    for room in ROOMS:
        assert len(room_modules(room)) >= 5, room
    for path in CODEC_MODULES:
        assert (ROOT / path).is_file(), path


# --- the arrows -----------------------------------------------------------------------------------------------------


def test_processing_imports_neither_capture_nor_devices_nor_io_libraries() -> None:
    bad = processing_violations(room_modules("processing"))
    assert not bad, "processing/ must stay pure (docs/architecture.md):\n" + "\n".join(bad)


def test_devices_imports_neither_capture_nor_processing() -> None:
    bad = devices_violations(room_modules("devices"))
    assert not bad, "devices/ must not import the application, nor the algorithms outside devices/sim:\n" + "\n".join(
        bad
    )


def test_the_simulated_world_has_one_home() -> None:
    """Scenes, textures, the renderers, the CR2 writer, the simulated EOS 70D and the simulated rail all live
    in devices/sim; the rooms hold no other module of that name, and only devices/sim imports the renderer's
    internals from within devices."""
    world = {"render", "scenes", "textures", "render_rgbd", "cr2", "world", "eos70d", "grbl"}
    found = {Path(m.path).parts[2].removesuffix(".py") for m in room_modules("devices/sim")}
    assert world <= found, world - found
    elsewhere = [
        m.path
        for room in ROOMS
        for m in room_modules(room)
        if not m.path.startswith(("devices/sim/", "capture/commands/"))  # `mca simulate` is a command's name
        and Path(m.path).stem in {"simulate", "scenes", "textures", "render_rgbd", "cr2", "sim_grbl", "sim_eos70d"}
    ]
    assert not elsewhere, elsewhere
    assert (ROOT / "devices/profiles/paper-70d.toml").is_file()


def test_codecs_do_no_io() -> None:
    bad = codec_violations([m for m in room_modules("devices") if m.path in CODEC_MODULES])
    assert not bad, "the PTP and GRBL codecs are bytes in, messages out (h11 style):\n" + "\n".join(bad)


def test_real_device_stacks_do_not_import_their_twins() -> None:
    bad = twin_violations(room_modules("devices/ptp") + room_modules("devices/rail"))
    assert not bad, "the real stacks must not depend on the simulated ones:\n" + "\n".join(bad)


def test_every_mca_import_names_a_module_of_a_room() -> None:
    """`mca.<room>.<module>` imports resolve to a file (a moved module leaves no import pointing nowhere)."""
    folder_of = {package: folder for folder, package in ROOMS.items()}
    bad = []
    for room in ROOMS:
        for module in room_modules(room):
            for imp in module_imports(module):
                parts = imp.module.split(".")
                if parts[0] != "mca" or len(parts) < 2 or parts[1] in ("__version__",):
                    continue
                folder = folder_of.get(".".join(parts[:2]))
                if folder is None:
                    continue  # `from mca import __version__`-like names of the package root
                target = ROOT / folder / Path(*parts[2:])
                parent = target.parent
                # the last part may be a name inside a module (`from mca.capture.raw import read_raw`)
                if not any(t.with_suffix(".py").is_file() or (t / "__init__.py").is_file() for t in (target, parent)):
                    bad.append(f"{imp} (no such module)")
    assert not bad, "\n".join(bad)


# --- the checks fail on a planted bad import ------------------------------------------------------------------------

PLANTS = [
    ("processing/_planted.py", "from mca.capture.raw import read_raw", processing_violations, "processing"),
    ("processing/_planted.py", "import rerun as rr", processing_violations, "processing"),
    ("processing/sub/_planted.py", "from ...devices.ptp import camera", processing_violations, "processing"),
    ("devices/_planted.py", "from mca.capture.tether import camera_factory", devices_violations, "devices"),
    ("devices/ptp/_planted.py", "from mca.processing.optics import MCAOptics", devices_violations, "devices"),
    ("devices/rail/_planted.py", "from mca.processing.camera import CameraProfile", devices_violations, "devices"),
    ("devices/sim/_planted.py", "from mca.capture.raw import read_raw", devices_violations, "devices"),
    ("devices/ptp/codec.py", "import usb.core", codec_violations, None),
    (
        "devices/ptp/_planted.py",
        "from mca.devices.sim.eos70d.responder import SimEos70D",
        twin_violations,
        "devices/ptp",
    ),
    (
        "devices/rail/_planted.py",
        "from mca.devices.sim.world import scene_frame_source",
        twin_violations,
        "devices/rail",
    ),
]


@pytest.mark.parametrize(("path", "line", "check", "folder"), PLANTS)
def test_a_planted_bad_import_is_caught(
    path: str, line: str, check: Callable[[list[Module]], list[str]], folder: str | None
) -> None:
    """The tree as it is passes; the same tree with one bad import (inside a function, line 4) fails, naming it."""
    modules = room_modules(folder) if folder else [m for m in room_modules("devices") if m.path in CODEC_MODULES]
    assert check(modules) == []
    planted = Module(path, f'"""planted."""\n\n\ndef f() -> None:\n    {line}\n')
    caught = check([*[m for m in modules if m.path != path], planted])
    assert len(caught) >= 1 and all(c.startswith(f"{path}:5: imports ") for c in caught), caught


# --- commands are thin shells over application functions (issue 17) ------------------------------------------------

# The most statements one function of capture/commands/ may hold (its own: a nested function counts as one and is
# measured on its own; imports, the docstring and every nested statement count). Since the application logic moved
# into capture/ (issue 17) the largest are `demo` (28: the shots' lines), `_shoot` of `mca capture` (26) and
# `process` (24); before the move `capture` held 92, `calibrate` 87, `process` 73 and `evaluate` 54. 30 leaves room
# for an option and fails as soon as a command grows a loop of real work again.
MAX_COMMAND_STATEMENTS = 30

# What a command module may import: typer, the standard library, and the application (mca.capture). The
# algorithms and the devices are reached through application functions, never from a command.
COMMAND_IMPORTS_ALLOWED = frozenset({"typer", "mca"}) | frozenset(sys.stdlib_module_names)

# Helpers that were once defined in a command and now live in the application, with their homes.
MOVED_FROM_COMMANDS = {
    "report_document": "mca.capture.batch",
    "stop_on_sigterm": "mca.capture.batch",
    "resolve_profile": "mca.capture.profile_app",
    "table2_document": "mca.capture.evaluation_app",
    "cached_paper_scene": "mca.capture.evaluation_app",
    "evaluate_rgbd_folder": "mca.capture.evaluation_app",
    "review_rows": "mca.capture.review",
    "format_table": "mca.capture.review",
    "set_config_values": "mca.capture.config",
    "capture_document": "mca.capture.tether_run",
    "process_unfinished": "mca.capture.tether_run",
    "shot_line": "mca.capture.tether_run",
    "simulate_paper": "mca.capture.simulate_app",
    "simulate_rgbd": "mca.capture.simulate_app",
    "simulate_rgbd_tree": "mca.capture.simulate_app",
    "viewer_command": "mca.capture.viewer",
    "has_display": "mca.capture.viewer",
    "describe_profile": "mca.capture.profile_app",
    "run_calibration": "mca.capture.calibration",
}


def own_statements(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """The statements of `function` at any depth of its blocks, a nested function or class counted as one."""
    count = 0
    pending: list[ast.stmt] = list(function.body)
    while pending:
        statement = pending.pop()
        count += 1
        if isinstance(statement, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        for name in ("body", "orelse", "finalbody"):
            pending += [s for s in getattr(statement, name, []) if isinstance(s, ast.stmt)]
        for handler in getattr(statement, "handlers", []):
            pending += handler.body
        for case in getattr(statement, "cases", []):
            pending += case.body
    return count


def command_functions(modules: list[Module]) -> list[tuple[str, str, int]]:
    """(path:line, function name, own statements) of every function in `modules`, nested ones too."""
    found = []
    for module in modules:
        for node in ast.walk(ast.parse(module.source, filename=module.path)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                found.append((f"{module.path}:{node.lineno}", node.name, own_statements(node)))
    return found


def fat_commands(modules: list[Module], limit: int = MAX_COMMAND_STATEMENTS) -> list[str]:
    return [f"{where}: {name} has {n} statements" for where, name, n in command_functions(modules) if n > limit]


def command_import_violations(modules: list[Module]) -> list[str]:
    bad = []
    for module in modules:
        for imp in module_imports(module):
            if top(imp.module) not in COMMAND_IMPORTS_ALLOWED or (
                top(imp.module) == "mca" and not is_under(imp.module, "mca.capture")
            ):
                bad.append(str(imp))
    return sorted(set(bad))


def test_the_statement_count_sees_nested_blocks_and_not_nested_functions() -> None:
    source = (
        "def f(x):\n"
        "    import os\n"
        "    try:\n        if x:\n            a = 1\n        else:\n            a = 2\n"
        "    except ValueError:\n        a = 3\n    finally:\n        pass\n"
        "    def g():\n        return 1\n        return 2\n"
        "    for i in range(3):\n        print(i)\n"
        "    return a\n"
    )
    counts = {name: n for _, name, n in command_functions([Module("capture/commands/x.py", source)])}
    # f: import, try, if, a=1, a=2, a=3, pass, def g, for, print, return = 11; g: 2
    assert counts == {"f": 11, "g": 2}


def test_no_command_function_holds_application_logic() -> None:
    commands = [m for m in room_modules("capture/commands") if not m.path.endswith("__init__.py")]
    assert len(commands) >= 10
    bad = fat_commands(commands)
    assert not bad, (
        f"a command parses options, calls one application function and prints (at most "
        f"{MAX_COMMAND_STATEMENTS} statements); move the work into capture/:\n" + "\n".join(bad)
    )
    fat = Module("capture/commands/_planted.py", "def f():\n" + "    x = 1\n" * (MAX_COMMAND_STATEMENTS + 1))
    assert fat_commands([fat]) == [f"capture/commands/_planted.py:1: f has {MAX_COMMAND_STATEMENTS + 1} statements"]


def test_commands_import_typer_and_only_the_application() -> None:
    commands = [m for m in room_modules("capture/commands") if not m.path.endswith("__init__.py")]
    for module in commands:
        assert any(imp.module == "typer" for imp in module_imports(module)), f"{module.path} does not import typer"
    bad = command_import_violations(commands)
    assert not bad, (
        "commands reach the algorithms and the devices through application functions in capture/:\n" + "\n".join(bad)
    )
    for line in (
        "from mca.processing.evaluate import format_table",
        "from mca.devices.rail import open_rail",
        "import numpy",
    ):
        planted = Module("capture/commands/_planted.py", f"def f() -> None:\n    {line}\n")
        assert command_import_violations([planted]), line


@pytest.mark.parametrize(("name", "home"), sorted(MOVED_FROM_COMMANDS.items()))
def test_moved_helpers_live_in_the_application_not_in_commands(name: str, home: str) -> None:
    import importlib

    assert callable(getattr(importlib.import_module(home), name))
    defined = [
        f"{module.path}:{node.lineno}"
        for module in room_modules("capture/commands")
        for node in ast.walk(ast.parse(module.source))
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name == name
    ]
    assert not defined, f"{name} is defined in a command again: {defined}; its home is {home}"
