"""Opening recordings in rerun's viewer: the native window or the web viewer on this machine, and advice without a display.

Usage analytics of the viewer stay off: `capture.recording.disable_rerun_analytics` runs before the
viewer starts, and the viewer gets `capture.recording.child_environment`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


class ViewerError(RuntimeError):
    """The viewer cannot start; `exit_code` is what `mca view` exits with (2: a usage error, 1: no display)."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


@dataclass(frozen=True)
class ViewerLaunch:
    """The `rerun` command line to run, the environment to run it in, and where a web viewer will be."""

    command: list[str]
    environment: dict[str, str]
    url: str | None = None  # the web viewer's address, None for the native window


def has_display(environ: os._Environ[str] | dict[str, str] = os.environ) -> bool:
    """True when a native window can open (X11 or Wayland on Linux; always on macOS and Windows)."""
    import sys

    if sys.platform in ("darwin", "win32"):
        return True
    return bool(environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY"))


def no_display_advice(path: Path) -> str:
    """What to do where no window can open."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        sdk = version("rerun-sdk")
    except PackageNotFoundError:
        sdk = "matching"
    return (
        f"No display here (neither DISPLAY nor WAYLAND_DISPLAY is set), so the native viewer cannot open.\n"
        f"To look at {path}:\n"
        f"  - copy it to a machine with a display and run:  rerun {path.name}\n"
        f"    (the viewer comes with `pip install rerun-sdk=={sdk}`, the version that wrote it)\n"
        f"  - or serve the web viewer from here:  mca view {path} --web\n"
        f"    then open the printed http://127.0.0.1:... address in a browser on this machine,\n"
        f"    or through an SSH tunnel: ssh -L 9090:127.0.0.1:9090 -L 9876:127.0.0.1:9876 THIS-HOST\n"
        f"    (the ports it prints, if 9090 and 9876 were taken)"
    )


def viewer_command(exe: str, paths: list[Path], *, web: bool, bind: str, web_port: int, grpc_port: int) -> list[str]:
    """The `rerun` command line that shows `paths` natively, or serves them to a browser bound to `bind`."""
    command = [exe, *[str(p) for p in paths]]
    if web:
        command += ["--serve-web", "--bind", bind, "--web-viewer-port", str(web_port), "--port", str(grpc_port)]
    return command


def plan_viewer(
    recordings: list[Path],
    *,
    web: bool = False,
    bind: str = "127.0.0.1",
    web_port: int | None = None,
    grpc_port: int | None = None,
    environ: os._Environ[str] | dict[str, str] = os.environ,
) -> ViewerLaunch:
    """Check the recordings and the display, choose the ports, turn analytics off: what `mca view` then runs.

    Raises `ViewerError` naming a missing recording, the missing `rerun` command or a taken port, and
    with the advice of `no_display_advice` (exit code 1) where no native window can open."""
    from mca.capture.recording import (
        DEFAULT_GRPC_PORT,
        DEFAULT_WEB_PORT,
        child_environment,
        choose_port,
        disable_rerun_analytics,
        rerun_executable,
    )

    missing = [str(p) for p in recordings if not p.is_file()]
    if missing:
        raise ViewerError(f"no such recording: {', '.join(missing)}")
    if not web and not has_display(environ):
        raise ViewerError(no_display_advice(recordings[0]), exit_code=1)
    exe = rerun_executable()
    if exe is None:
        raise ViewerError("the `rerun` command is missing; install it with `pip install rerun-sdk==0.41.*`")
    disable_rerun_analytics()
    url = None
    if web:
        try:
            grpc_port = choose_port(bind, grpc_port, DEFAULT_GRPC_PORT, "--grpc-port")
            web_port = choose_port(bind, web_port, DEFAULT_WEB_PORT, "--web-port", {grpc_port})
        except RuntimeError as exc:
            raise ViewerError(str(exc)) from None
        url = f"http://{'127.0.0.1' if bind in ('0.0.0.0', '::') else bind}:{web_port}"
    command = viewer_command(
        exe, recordings, web=web, bind=bind, web_port=web_port or DEFAULT_WEB_PORT, grpc_port=grpc_port or 0
    )
    return ViewerLaunch(command, dict(child_environment()), url)
