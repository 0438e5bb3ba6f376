"""Rerun's command-line binary and its usage analytics, kept off before rerun is ever imported."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

# --- rerun's usage analytics: off, before rerun is ever imported ----------------------------------------------------
#
# rerun 0.41 (crates/utils/re_analytics, native pipeline) sends usage events unless the user's
# analytics config (~/.config/rerun/analytics.json, written by `rerun analytics disable`) says
# `analytics_enabled: false`, or the environment has `CI` set; `FORCE_RERUN_ANALYTICS` overrides
# both. The SDK's OpenTelemetry tracing is active only with `TELEMETRY_ENABLED=true`.

_ANALYTICS_ENV_DONE = False
_ANALYTICS_CONFIG_DONE = False


def quiet_rerun_environment(environ: os._Environ[str] | dict[str, str] = os.environ) -> None:
    """Set the environment so that rerun (SDK and viewer) reports nothing: call before `import rerun`.

    Removes `FORCE_RERUN_ANALYTICS` (which would override the opt-out) and sets
    `TELEMETRY_ENABLED=false` (the SDK's OpenTelemetry export).
    """
    environ.pop("FORCE_RERUN_ANALYTICS", None)
    environ["TELEMETRY_ENABLED"] = "false"


def rerun_analytics_config_path(environ: Mapping[str, str] = os.environ) -> Path:
    """Where rerun keeps its analytics opt-out on Linux (directories::ProjectDirs: $XDG_CONFIG_HOME/rerun)."""
    base = environ.get("XDG_CONFIG_HOME") or str(Path(environ.get("HOME", str(Path.home()))) / ".config")
    if sys.platform == "darwin":
        base = str(Path.home() / "Library" / "Application Support")
    return Path(base) / "rerun" / "analytics.json"


def rerun_analytics_disabled(environ: Mapping[str, str] = os.environ) -> bool:
    """True when rerun's own config says analytics are off."""
    try:
        config = json.loads(rerun_analytics_config_path(environ).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(config, dict) and config.get("analytics_enabled") is False


def child_environment() -> dict[str, str]:
    """The environment for a `rerun` child process (viewer, server, `rerun rrd`): analytics off.

    `CI=1` is added only when the config-file opt-out could not be confirmed (e.g. a read-only
    home): it is the one environment variable rerun itself reads to stay quiet.
    """
    env = dict(os.environ)
    quiet_rerun_environment(env)
    if not rerun_analytics_disabled(env):
        env["CI"] = "1"
    return env


def disable_rerun_analytics() -> None:
    """Make sure no rerun usage data leaves the bench; cheap after the first call.

    Sets the environment (`quiet_rerun_environment`) and, once per machine, records the opt-out
    in rerun's own config with `rerun analytics disable` (what rerun documents for opting out).
    """
    global _ANALYTICS_ENV_DONE, _ANALYTICS_CONFIG_DONE
    if not _ANALYTICS_ENV_DONE:
        quiet_rerun_environment()
        _ANALYTICS_ENV_DONE = True
    if _ANALYTICS_CONFIG_DONE:
        return
    _ANALYTICS_CONFIG_DONE = True
    if rerun_analytics_disabled():
        return
    exe = rerun_executable()
    if exe is None:
        return
    env = dict(os.environ)
    env["CI"] = "1"  # the opt-out command itself must not report
    try:
        subprocess.run(
            [exe, "analytics", "disable"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        pass


quiet_rerun_environment()
_ANALYTICS_ENV_DONE = True


def rerun_executable() -> str | None:
    """Path of the `rerun` command-line binary matching the SDK (the one the rerun-sdk wheel ships), or None.

    The binary itself rather than the Python wrapper script in the venv's bin/, so that signals
    (Ctrl-C, terminate) reach the viewer directly.
    """
    try:
        import rerun_cli  # the wheel's package holding the binary

        bundled = Path(rerun_cli.__file__).parent / "rerun"
        if bundled.is_file() and os.access(bundled, os.X_OK):
            return str(bundled)
    except ImportError:
        pass
    beside = Path(sys.executable).parent / "rerun"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    return shutil.which("rerun")
