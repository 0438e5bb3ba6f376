"""`mca view FILE.rrd`: open a recording in rerun's native viewer, or serve the web viewer on this machine.

Usage analytics of the viewer stay off: `capture.recording.disable_rerun_analytics` runs before the
viewer starts, and the viewer gets `capture.recording.child_environment`. On a machine without a
display, the command says how to look at the file instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import typer


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


def register(app: typer.Typer) -> None:
    @app.command("view")
    def view(
        recordings: list[Path] = typer.Argument(..., metavar="FILE.rrd...", help="Recordings to open."),
        web: bool = typer.Option(False, "--web", help="Serve the web viewer instead of opening a window."),
        bind: str = typer.Option(
            "127.0.0.1", "--bind", help="Address the web viewer listens on; 0.0.0.0 opens it to the network."
        ),
        web_port: int | None = typer.Option(
            None, "--web-port", help="HTTP port of the web viewer (default 9090, or a free one if that is taken)."
        ),
        grpc_port: int | None = typer.Option(
            None, "--grpc-port", help="Port the web viewer fetches the data from (default 9876, or a free one)."
        ),
    ) -> None:
        """Open recordings in the rerun viewer (native window, or a web viewer on 127.0.0.1 with --web)."""
        import subprocess

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
            typer.echo(f"error: no such recording: {', '.join(missing)}", err=True)
            raise typer.Exit(2)
        if not web and not has_display():
            typer.echo(no_display_advice(recordings[0]), err=True)
            raise typer.Exit(1)
        exe = rerun_executable()
        if exe is None:
            typer.echo(
                "error: the `rerun` command is missing; install it with `pip install rerun-sdk==0.41.*`", err=True
            )
            raise typer.Exit(2)
        disable_rerun_analytics()
        if web:
            try:
                grpc_port = choose_port(bind, grpc_port, DEFAULT_GRPC_PORT, "--grpc-port")
                web_port = choose_port(bind, web_port, DEFAULT_WEB_PORT, "--web-port", {grpc_port})
            except RuntimeError as exc:
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(2) from None
        command = viewer_command(
            exe, recordings, web=web, bind=bind, web_port=web_port or DEFAULT_WEB_PORT, grpc_port=grpc_port or 0
        )
        if web:
            host = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind
            typer.echo(
                f"Serving {', '.join(map(str, recordings))} at http://{host}:{web_port} "
                f"(listening on {bind}); Ctrl-C to stop."
            )
        if os.name == "posix":  # become the viewer: Ctrl-C and signals reach it, no process is left behind
            os.execve(command[0], command, child_environment())
        try:
            code = subprocess.call(command, env=child_environment())
        except KeyboardInterrupt:
            code = 0
        raise typer.Exit(code)
