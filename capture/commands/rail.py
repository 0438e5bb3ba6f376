"""`mca rail home|move MM|status`: drive the bench rail (a GRBL stage on a serial port, or `--rail sim`)."""

from __future__ import annotations

from typing import Any, NoReturn

import typer

_RAIL_OPTION = typer.Option(
    None,
    "--rail",
    envvar="MCA_RAIL",
    help="Serial port of the GRBL controller (e.g. /dev/ttyUSB0), or 'sim' for the simulated controller "
    "(default: the config file's rail, else sim).",
)


def _open(rail_spec: str | None) -> Any:  # a devices.rail.Rail; imported lazily to keep `mca --help` fast
    from mca.capture.config import ConfigError
    from mca.capture.rail_app import open_configured_rail

    try:
        return open_configured_rail(rail_spec)
    except ConfigError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(code=2) from None


def _fail(error: Exception) -> NoReturn:
    typer.echo(f"error: {error}", err=True)
    raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    rail_app = typer.Typer(help="Home, move and query the bench rail (GRBL over serial).", no_args_is_help=True)

    @rail_app.command("home")
    def home(rail: str | None = _RAIL_OPTION) -> None:
        """Run the homing cycle ($H); the rail then stands at its home switch, unlocked."""
        from mca.capture.rail_app import RailError, describe_status

        try:
            with _open(rail) as stage:
                typer.echo(describe_status(stage.home()))
        except RailError as error:
            _fail(error)

    @rail_app.command("move")
    def move(
        position_mm: float = typer.Argument(..., help="Target in mm from the home switch (0 .. travel)."),
        rail: str | None = _RAIL_OPTION,
        feed: float = typer.Option(600.0, "--feed", help="Feed rate in mm/min (capped by the controller's $110)."),
        home_first: bool = typer.Option(False, "--home", help="Home first (a controller fresh from reset is locked)."),
    ) -> None:
        """Move to an absolute position, wait until idle, and print the position read back."""
        from mca.capture.rail_app import RailError, describe_status

        try:
            with _open(rail) as stage:
                if home_first:
                    stage.home()
                try:
                    typer.echo(describe_status(stage.move_to(position_mm, feed_mm_per_min=feed)))
                except KeyboardInterrupt:
                    stage.halt()
                    raise
        except RailError as error:
            _fail(error)

    @rail_app.command("status")
    def status(rail: str | None = _RAIL_OPTION) -> None:
        """Print the controller state, the position and the travel."""
        from mca.capture.rail_app import RailError, describe_status

        try:
            with _open(rail) as stage:
                typer.echo(describe_status(stage.status()))
                typer.echo(f"travel 0 .. {stage.travel_mm:.3f} mm; controller {stage.banner or 'GRBL'}")
        except RailError as error:
            _fail(error)

    app.add_typer(rail_app, name="rail")
