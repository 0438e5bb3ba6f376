"""`mca capture --hook-script FILE`: run the user's program around a capture run, as gphoto2 does.

The program is run with the environment variable `ACTION` set to `init` (once, before the camera is
opened), `start` (before the shots are taken or awaited), `download` (after each file is stored, with
`ARGUMENT` = the file's path) and `stop` (at the end, also after Ctrl-C), as gphoto2's `--hook-script`
does. mca adds `MCA_SHOT_ID` (the catalog row), `MCA_CATALOG` and `MCA_OUT_DIR` for `download`.

A hook never loses a file: it runs after the file is on disk, fsynced and catalogued. A hook that fails
(non-zero exit, cannot be started, runs longer than `timeout_s`) is reported (`HookFailure`), the run goes
on and ends with exit status 1; a hook that moves or deletes the file is reported the same way, and the
catalog still says where the file was stored. As in gphoto2, a failing `init` stops the run before anything
is taken.
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

HOOK_TIMEOUT_S = 600.0  # a hook that hangs must not hold the camera forever


@dataclass(frozen=True)
class HookFailure:
    """One failed run of the hook: which action, which file, what went wrong."""

    action: str
    argument: str
    message: str

    def __str__(self) -> str:
        what = f"ACTION={self.action}" + (f" ARGUMENT={self.argument}" if self.argument else "")
        return f"hook script {what}: {self.message}"


class HookScript:
    """The user's hook program; `run(action, argument)` returns a `HookFailure` or None."""

    def __init__(self, path: str | Path, *, timeout_s: float = HOOK_TIMEOUT_S) -> None:
        self.path = Path(path).expanduser()
        self.timeout_s = timeout_s
        if not self.path.is_file():
            raise ValueError(f"--hook-script {self.path}: no such file; give the path of an executable program")
        if not os.access(self.path, os.X_OK):
            raise ValueError(f"--hook-script {self.path}: not executable; `chmod +x {self.path}`")
        self.failures: list[HookFailure] = []

    def run(self, action: str, argument: str = "", extra_env: dict[str, str] | None = None) -> HookFailure | None:
        env = dict(os.environ, ACTION=action, ARGUMENT=argument, **(extra_env or {}))
        try:
            done = subprocess.run(
                [str(self.path.resolve())],
                env=env,
                stdin=subprocess.DEVNULL,
                capture_output=True,
                text=True,
                errors="replace",
                timeout=self.timeout_s,
                check=False,
            )
        except subprocess.TimeoutExpired:
            failure = HookFailure(action, argument, f"{self.path} ran longer than {self.timeout_s:.0f} s; stopped")
        except OSError as exc:
            failure = HookFailure(action, argument, f"{self.path} cannot be run: {exc.strerror or exc}")
        else:
            if done.returncode == 0:
                return None
            said = (done.stderr or done.stdout).strip().splitlines()
            tail = f": {said[-1]}" if said else ""
            failure = HookFailure(action, argument, f"{self.path} exited with status {done.returncode}{tail}")
        self.failures.append(failure)
        return failure
