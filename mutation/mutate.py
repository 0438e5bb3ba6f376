"""Mutation testing of one or more modules with cosmic-ray: prints each module's score and its surviving mutants.

Run it as `python3 dev.py mutate [MODULE...]` (MODULE: a path such as capture/batch.py or processing/,
or a dotted name such as mca.capture.batch). What it does for each module:

1. copies the package into build/mutation/<module>/src laid out as the import package `mca`
   (pyproject's package-dir: capture/ -> mca/capture, ...), so the mutants are written into that copy,
   never into the working tree, and a killed run leaves nothing behind;
2. runs the module's tests (mutation/config.toml) once unmutated under coverage: they must pass, and
   the run's length sets the per-mutant timeout;
3. makes cosmic-ray's mutants (the operators listed in config.toml), skips the equivalent ones listed
   in mutation/equivalent.toml, and counts a mutant on a line no test executes as survived without
   running it;
4. applies each mutant in turn (cosmic-ray's `mutate_and_test`) and runs the tests with `pytest -x`
   and PYTHONPATH pointing at the copy; results go to build/mutation/<module>/session.sqlite, which
   cosmic-ray's own tools read (`cr-report`, `cr-html`).

Score = killed / (mutants - equivalent). Exit status 1 when a module is below --fail-under.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HERE = ROOT / "mutation"
BUILD = ROOT / "build" / "mutation"
CONFIG = HERE / "config.toml"
EQUIVALENT = HERE / "equivalent.toml"
NOT_COVERED = "not covered: no test executes this line"


@dataclass
class ModuleReport:
    """What one module's run found."""

    module: str
    total: int = 0
    killed: int = 0
    equivalent: int = 0
    not_covered: int = 0
    not_sampled: int = 0
    survivors: list[dict[str, object]] = field(default_factory=list)
    duration_s: float = 0.0
    tests: list[str] = field(default_factory=list)
    error: str | None = None

    @property
    def counted(self) -> int:
        return self.total - self.equivalent - self.not_sampled

    @property
    def score(self) -> float:
        return 100.0 * self.killed / self.counted if self.counted else 100.0


def _say(message: str) -> None:
    print(f"[mutate] {message}", flush=True)


def package_dirs() -> dict[str, str]:
    """Import package -> folder, from pyproject's [tool.setuptools] package-dir."""
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return dict(setuptools["package-dir"])


def module_path(name: str) -> Path:
    """A repository-relative .py path (or folder) for `name`: a path, or a dotted name under `mca`."""
    candidate = (ROOT / name).resolve()
    if candidate.exists():
        return candidate.relative_to(ROOT)
    if re.fullmatch(r"[A-Za-z_][\w.]*", name):
        dirs = package_dirs()
        parts = name.split(".")
        for length in range(len(parts), 0, -1):
            package = ".".join(parts[:length])
            if package in dirs:
                rest = parts[length:]
                base = ROOT / dirs[package] / Path(*rest) if rest else ROOT / dirs[package]
                for path in (base.with_suffix(".py"), base):
                    if path.exists():
                        return path.relative_to(ROOT)
    raise SystemExit(
        f"mutate: no module {name!r} (give a path such as capture/batch.py or a name such as mca.capture.batch)"
    )


def expand(names: list[str]) -> list[Path]:
    """Module files for the names given (a folder gives its .py files, __init__ excluded)."""
    paths: list[Path] = []
    for name in names:
        path = module_path(name)
        if (ROOT / path).is_dir():
            paths.extend(sorted(p.relative_to(ROOT) for p in (ROOT / path).glob("*.py") if p.name != "__init__.py"))
        else:
            paths.append(path)
    return paths


def import_name(path: Path) -> str:
    """mca.capture.batch for capture/batch.py."""
    for package, folder in sorted(package_dirs().items(), key=lambda item: -len(item[1])):
        try:
            rest = path.with_suffix("").relative_to(folder)
        except ValueError:
            continue
        return ".".join([package, *rest.parts])
    raise SystemExit(f"mutate: {path} is not inside the package (pyproject.toml package-dir)")


def tests_for(path: Path, config: dict) -> list[str]:
    """The module's test files: config.toml's list (those that exist), else the test files that import it."""
    listed = config.get("modules", {}).get(str(path), {}).get("tests")
    if listed:
        present = [t for t in listed if (ROOT / t).exists()]
        for missing in sorted(set(listed) - set(present)):
            _say(f"{path}: {missing} does not exist (yet); left out")
        return present
    dotted = import_name(path)
    package, _, leaf = dotted.rpartition(".")
    pattern = re.compile(rf"\b{re.escape(dotted)}\b|from {re.escape(package)} import [^\n]*\b{re.escape(leaf)}\b")
    return sorted(
        str(t.relative_to(ROOT)) for t in (ROOT / "tests").glob("test_*.py") if pattern.search(t.read_text("utf-8"))
    )


def make_copy(work: Path) -> Path:
    """build/mutation/<module>/src/mca/...: the package as `import mca` sees it, from the working tree."""
    src = work / "src"
    if src.exists():
        shutil.rmtree(src)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc")
    for package, folder in package_dirs().items():
        target = src / Path(*package.split("."))
        shutil.copytree(ROOT / folder, target, ignore=ignore, dirs_exist_ok=True)
    return src


def test_command(tests: list[str]) -> str:
    # -P: the working tree's mca/ (the current directory) must not shadow the copy on PYTHONPATH;
    # -x: the first failing test is enough; the plugin makes hypothesis deterministic
    return " ".join(
        [
            sys.executable,
            "-P",
            "-m",
            "pytest",
            "-x",
            "-q",
            "-p",
            "no:cacheprovider",
            "-p",
            "mutation_plugin",
            "--no-header",
            "-W",
            "ignore",
            *tests,
        ]
    )


def test_env(src: Path, work: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(src), str(HERE), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["RERUN_ANALYTICS"] = "0"
    env["MCA_MUTATION"] = "1"
    env["NUMBA_CACHE_DIR"] = str(work / "numba-cache")
    env.pop("CI", None)  # a mutant must not fail for a missing reference tool rather than for the bug
    return env


def baseline(tests: list[str], src: Path, target: Path, work: Path, env: dict[str, str]) -> tuple[float, set[int]]:
    """Run the tests once unmutated under coverage: (seconds, executed lines of the copied module)."""
    data = work / ".coverage"
    for old in work.glob(".coverage*"):
        old.unlink()
    # the tests start workers and `mca` subprocesses: their lines count too
    rc = work / "coveragerc"
    rc.write_text(
        f"[run]\ndata_file = {data}\ninclude = {target}\nparallel = true\n"
        "patch = subprocess, _exit, fork\nconcurrency = thread, multiprocessing\n"
    )
    command = [sys.executable, "-P", "-m", "coverage", "run", f"--rcfile={rc}", *test_command(tests).split()[2:]]
    start = time.monotonic()
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    elapsed = time.monotonic() - start
    if result.returncode != 0:
        tail = "\n".join((result.stdout + result.stderr).strip().splitlines()[-25:])
        raise RuntimeError(f"the tests fail on the unmutated code, so no mutant can be judged:\n{tail}")
    import coverage

    cov = coverage.Coverage(data_file=str(data), config_file=str(rc))
    cov.combine(data_paths=[str(work)], keep=False)
    cov.load()
    executed = set(cov.get_data().lines(str(target)) or ())
    return elapsed, executed


def uncovered_lines(target: Path, executed: set[int]) -> set[int]:
    """Lines whose statement no test executed (multi-line statements count by their first line)."""
    from coverage.parser import PythonParser

    parser = PythonParser(filename=str(target))
    parser.parse_source()
    source_lines = target.read_text("utf-8").count("\n") + 1
    missing: set[int] = set()
    for line in range(1, source_lines + 1):
        first = parser.first_line(line)
        if first in parser.statements and first not in executed and line not in executed:
            missing.add(line)
    return missing


def compiled_lines(source: str) -> set[int]:
    """Lines of functions compiled by numba (@nb.njit, @numba.jit, @guvectorize, ...): coverage cannot trace
    compiled code, so these lines are never "not covered"; their mutants are run like any other."""
    import ast

    lines: set[int] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and any(
            re.search(r"\b(n?jit|[gu]*vectorize|stencil|cfunc)\b", ast.unparse(d)) for d in node.decorator_list
        ):
            first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            lines.update(range(first, (node.end_lineno or node.lineno) + 1))
    return lines


def load_equivalents(path: Path) -> list[dict[str, str]]:
    entries = tomllib.loads(EQUIVALENT.read_text("utf-8")).get("mutant", []) if EQUIVALENT.exists() else []
    return [e for e in entries if e.get("module") == str(path)]


def load_rules() -> dict[str, str]:
    """Rules of equivalent.toml ([[rule]] name, reason) that apply to every module: name -> reason."""
    rules = tomllib.loads(EQUIVALENT.read_text("utf-8")).get("rule", []) if EQUIVALENT.exists() else []
    return {r["name"]: r["reason"] for r in rules}


def annotation_spans(source: str) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(start, end) positions of every annotation, when the module postpones their evaluation (PEP 563)."""
    import ast

    tree = ast.parse(source)
    postponed = any(
        isinstance(node, ast.ImportFrom)
        and node.module == "__future__"
        and any(a.name == "annotations" for a in node.names)
        for node in tree.body
    )
    if not postponed:
        return []
    found = []
    for node in ast.walk(tree):
        annotations = []
        if isinstance(node, ast.arg | ast.AnnAssign) and node.annotation is not None:
            annotations.append(node.annotation)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.returns is not None:
            annotations.append(node.returns)
        for a in annotations:
            found.append(((a.lineno, a.col_offset), (a.end_lineno or a.lineno, a.end_col_offset or 0)))
    return found


class Equivalence:
    """Decides whether one mutant of a module is equivalent: listed in equivalent.toml, or caught by a rule."""

    def __init__(self, path: Path, source: str) -> None:
        self.entries = load_equivalents(path)
        self.rules = load_rules()
        self.lines = source.split("\n")
        self.spans = annotation_spans(source) if "annotation" in self.rules else []

    def reason(self, start_pos: tuple[int, int], operator: str, after: str | None) -> str | None:
        """Why the mutant at `start_pos` (line, column) is equivalent, or None; `after` is its mutated line."""
        row = start_pos[0]
        if any(a <= tuple(start_pos) < b for a, b in self.spans):
            return self.rules["annotation"]
        text = self.lines[row - 1].strip()
        for entry in self.entries:
            if entry.get("line", "").strip() != text or entry.get("operator") not in (None, operator):
                continue
            if entry.get("mutant") is None or (after is not None and entry["mutant"].strip() == after):
                return str(entry["reason"])
        return None

    def may_apply(self, start_pos: tuple[int, int], operator: str) -> bool:
        """Whether `reason` could find something (so the mutant's diff is worth computing)."""
        return self.reason(start_pos, operator, None) is not None or any(
            e.get("line", "").strip() == self.lines[start_pos[0] - 1].strip() for e in self.entries
        )


def diff_lines(diff: str) -> tuple[str, str]:
    """(original line, mutated line) of a one-line cosmic-ray diff, stripped."""
    before = [line[1:].strip() for line in diff.splitlines() if line.startswith("-") and not line.startswith("---")]
    after = [line[1:].strip() for line in diff.splitlines() if line.startswith("+") and not line.startswith("+++")]
    return " / ".join(before), " / ".join(after)


def mutant_diff(target: Path, source: str, operator_name: str, occurrence: int) -> str:
    import difflib

    import cosmic_ray.plugins
    from cosmic_ray.mutating import mutate_code

    mutated = mutate_code(source, cosmic_ray.plugins.get_operator(operator_name)(), occurrence)
    if mutated is None:
        return ""
    return "\n".join(
        difflib.unified_diff(source.split("\n"), mutated.split("\n"), lineterm="", n=0, fromfile="a", tofile="b")
    )


def run_module(
    path: Path, config: dict, sample: int | None, resume: bool, tests_override: list[str] | None
) -> ModuleReport:
    """Mutate one module and test every mutant; the report of what survived."""
    from cosmic_ray.commands.init import init
    from cosmic_ray.mutating import mutate_and_test
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome, WorkResult

    report = ModuleReport(module=str(path))
    started = time.monotonic()
    tests = tests_override or tests_for(path, config)
    report.tests = tests
    if not tests:
        report.error = "no test file imports this module (name some in mutation/config.toml)"
        return report
    slug = str(path).replace("/", "_").removesuffix(".py")
    work = BUILD / slug
    work.mkdir(parents=True, exist_ok=True)
    session = work / "session.sqlite"
    stamp_file = work / "stamp"
    source = (ROOT / path).read_text("utf-8")
    stamp = hashlib.sha256(
        "\0".join([source, *tests, *[(ROOT / t).read_text("utf-8") for t in tests], CONFIG.read_text("utf-8")]).encode()
    ).hexdigest()
    fresh = not (resume and session.exists() and stamp_file.exists() and stamp_file.read_text() == stamp)
    finished = False
    if not fresh:
        with use_db(str(session), WorkDB.Mode.open) as db:
            finished = not any(True for _ in db.pending_work_items)
    src = make_copy(work)
    target = src / Path(*import_name(path).split(".")).with_suffix(".py")
    env = test_env(src, work)
    _say(f"{path}: {len(tests)} test files: {' '.join(tests)}")
    timeout_s = 0.0
    if not finished:  # a finished run that is resumed is only reported again
        try:
            baseline_s, executed = baseline(tests, src, target, work, env)
        except RuntimeError as error:
            report.error = str(error)
            return report
        timeout_s = max(float(config.get("min_timeout_s", 30)), float(config.get("timeout_factor", 3.0)) * baseline_s)
        _say(
            f"{path}: the unmutated tests pass in {baseline_s:.1f} s (under coverage); "
            f"timeout per mutant {timeout_s:.0f} s"
        )

    if fresh:
        session.unlink(missing_ok=True)
        keep = set(config["operators"])
        with use_db(str(session), WorkDB.Mode.create) as db:
            init([target], db, {})
            missing = uncovered_lines(target, executed) - compiled_lines(source)
            equivalence = Equivalence(path, source)
            items = sorted(
                db.work_items,
                key=lambda w: (w.mutations[0].start_pos, w.mutations[0].operator_name, w.mutations[0].occurrence),
            )
            items = [w for w in items if w.mutations[0].operator_name in keep]
            db.clear()
            db.add_work_items(items)
            chosen = set(range(len(items)))
            if sample is not None and sample < len(items):
                step = len(items) / sample  # a fixed, evenly spread sample: the same mutants every run
                chosen = {int(i * step) for i in range(sample)}
            for index, item in enumerate(items):
                mutation = item.mutations[0]
                if index not in chosen:
                    db.set_result(item.job_id, WorkResult(worker_outcome=WorkerOutcome.SKIPPED, output="not sampled"))
                    continue
                row = mutation.start_pos[0]
                try:
                    diff = mutant_diff(target, source, mutation.operator_name, mutation.occurrence)
                except Exception as error:  # cosmic-ray 8.7's ExceptionReplacer fails on dotted names (a.b.Error)
                    db.set_result(
                        item.job_id,
                        WorkResult(
                            worker_outcome=WorkerOutcome.NO_TEST, output=f"cosmic-ray cannot make it: {error!r}"
                        ),
                    )
                    continue
                candidate = equivalence.may_apply(tuple(mutation.start_pos), mutation.operator_name)
                if candidate or row in missing:
                    _, after = diff_lines(diff)
                    reason = equivalence.reason(tuple(mutation.start_pos), mutation.operator_name, after)
                    if reason is not None:
                        db.set_result(
                            item.job_id,
                            WorkResult(worker_outcome=WorkerOutcome.SKIPPED, output=f"equivalent: {reason}", diff=diff),
                        )
                    else:
                        if row in missing:
                            db.set_result(
                                item.job_id,
                                WorkResult(
                                    worker_outcome=WorkerOutcome.NORMAL,
                                    test_outcome=TestOutcome.SURVIVED,
                                    output=NOT_COVERED,
                                    diff=diff,
                                ),
                            )
        stamp_file.write_text(stamp)

    with use_db(str(session), WorkDB.Mode.open) as db:
        pending = sorted(db.pending_work_items, key=lambda w: w.mutations[0].start_pos)
        command = test_command(tests)
        _say(f"{path}: {db.num_work_items} mutants, {len(pending)} to run")
        saved_env = dict(os.environ)
        os.environ.clear()
        os.environ.update(env)
        os.chdir(ROOT)
        try:
            for count, item in enumerate(pending, 1):
                result = mutate_and_test(item.mutations, command, timeout_s)
                db.set_result(item.job_id, result)
                if count % 25 == 0 or count == len(pending):
                    _say(f"{path}: {count}/{len(pending)} run ({time.monotonic() - started:.0f} s)")
        finally:
            os.environ.clear()
            os.environ.update(saved_env)
        # equivalence is decided again here, so that entries added to equivalent.toml after a run count
        # without running it again (`--resume` on a finished run only reports)
        equivalence = Equivalence(path, source)
        for item, result in db.completed_work_items:
            mutation = item.mutations[0]
            output = result.output or ""
            if output == "not sampled":
                report.not_sampled += 1
                report.total += 1
                continue
            if result.worker_outcome == WorkerOutcome.NO_TEST:
                continue  # cosmic-ray found nothing to change at that position
            report.total += 1
            _, after = diff_lines(result.diff or "")
            if output.startswith("equivalent:") or equivalence.reason(
                tuple(mutation.start_pos), mutation.operator_name, after
            ):
                report.equivalent += 1
            elif result.test_outcome == TestOutcome.SURVIVED:
                before, after = diff_lines(result.diff or "")
                report.not_covered += output == NOT_COVERED
                report.survivors.append(
                    {
                        "line": mutation.start_pos[0],
                        "operator": mutation.operator_name,
                        "occurrence": mutation.occurrence,
                        "before": before,
                        "after": after,
                        "why": "no test executes this line" if output == NOT_COVERED else "tests pass",
                    }
                )
            else:
                report.killed += 1
    report.survivors.sort(key=lambda s: (s["line"], s["operator"]))
    report.duration_s = time.monotonic() - started
    return report


def print_report(reports: list[ModuleReport]) -> None:
    for report in reports:
        if report.error:
            continue
        print(f"\n== surviving mutants of {report.module} ({len(report.survivors)})")
        for s in report.survivors:
            print(f"{report.module}:{s['line']}: {s['operator'].removeprefix('core/')} ({s['why']})")
            print(f"    - {s['before']}\n    + {s['after']}")
    print("\n| module | killed / counted | score | equivalent (excluded) | survived, not covered | time |")
    print("|---|---|---|---|---|---|")
    for report in reports:
        if report.error:
            print(f"| {report.module} | error: {report.error.splitlines()[0]} | | | | |")
            continue
        sampled = f" (sample of {report.counted})" if report.not_sampled else ""
        print(
            f"| {report.module} | {report.killed} / {report.counted}{sampled} | {report.score:.1f} % | "
            f"{report.equivalent} | {len(report.survivors)}, {report.not_covered} | {report.duration_s / 60:.1f} min |"
        )
    for report in reports:
        if report.error:
            print(f"\n{report.module}: {report.error}", file=sys.stderr)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python3 dev.py mutate", description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", help="paths or dotted names; default: every module in config.toml")
    parser.add_argument("--tests", nargs="+", help="test files to use instead of config.toml's")
    parser.add_argument(
        "--sample", type=int, help="test only N evenly spread mutants per module (the same N every run)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="modules mutated at once (each in its own copy)")
    parser.add_argument(
        "--resume", action="store_true", help="go on with an interrupted run whose inputs are unchanged"
    )
    parser.add_argument("--fail-under", type=float, help="exit 1 when a module scores below this percentage")
    parser.add_argument("--json", type=Path, help="also write the reports to this file")
    args = parser.parse_args(argv)
    config = tomllib.loads(CONFIG.read_text("utf-8"))
    paths = expand(args.modules) if args.modules else [Path(p) for p in config.get("modules", {})]
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        # each module works in its own copy; cosmic-ray's worker is in-process, so jobs > 1 runs it in subprocesses
        if args.jobs > 1 and len(paths) > 1:
            futures = [pool.submit(_run_in_subprocess, p, args) for p in paths]
            reports = [f.result() for f in futures]
        else:
            reports = [run_module(p, config, args.sample, args.resume, args.tests) for p in paths]
    print_report(reports)
    if args.json:
        args.json.write_text(json.dumps([r.__dict__ | {"score": r.score} for r in reports], indent=1))
    if any(r.error for r in reports):
        return 2
    if args.fail_under is not None and any(r.score < args.fail_under for r in reports):
        return 1
    return 0


def _run_in_subprocess(path: Path, args: argparse.Namespace) -> ModuleReport:
    out = BUILD / f"{uuid.uuid4().hex}.json"
    BUILD.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, __file__, str(path), "--json", str(out)]
    command += ["--sample", str(args.sample)] if args.sample else []
    command += ["--resume"] if args.resume else []
    command += ["--tests", *args.tests] if args.tests else []
    log = BUILD / (str(path).replace("/", "_") + ".log")
    with log.open("w") as handle:
        subprocess.run(command, stdout=handle, stderr=subprocess.STDOUT)
    _say(f"{path}: done (log {log.relative_to(ROOT)})")
    data = json.loads(out.read_text())[0]
    out.unlink()
    data.pop("score", None)
    return ModuleReport(**data)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
