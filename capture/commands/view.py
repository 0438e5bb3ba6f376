"""`mca view FILE.rrd`: open a recording in rerun's native viewer, or serve the web viewer on this machine.

The checks, the ports and the command line come from `capture.viewer.plan_viewer`; on a machine
without a display, the command says how to look at the file instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import typer


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

        from mca.capture.viewer import ViewerError, plan_viewer

        try:
            launch = plan_viewer(recordings, web=web, bind=bind, web_port=web_port, grpc_port=grpc_port)
        except ViewerError as exc:
            typer.echo(f"error: {exc}" if exc.exit_code == 2 else str(exc), err=True)
            raise typer.Exit(exc.exit_code) from None
        if launch.url is not None:
            typer.echo(
                f"Serving {', '.join(map(str, recordings))} at {launch.url} (listening on {bind}); Ctrl-C to stop."
            )
        if os.name == "posix":  # become the viewer: Ctrl-C and signals reach it, no process is left behind
            os.execve(launch.command[0], launch.command, launch.environment)
        try:
            code = subprocess.call(launch.command, env=launch.environment)
        except KeyboardInterrupt:
            code = 0
        raise typer.Exit(code)
