"""`mca config show|paths|set`: the effective appliance configuration, the files it was read from, and setting it."""

from __future__ import annotations

import json

import typer


def register(app: typer.Typer) -> None:
    config_app = typer.Typer(
        help="The appliance config file: show the effective values and where they came from.", no_args_is_help=True
    )

    @config_app.command("show")
    def show(as_json: bool = typer.Option(False, "--json", help="Print one JSON object: values and sources.")) -> None:
        """Print the effective config as TOML, each value commented with the file it came from (or "default")."""
        from mca.capture.config import ConfigError, config_document, config_lines, load_config

        try:
            config = load_config()
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        if as_json:
            typer.echo(json.dumps(config_document(config), indent=2))
            return
        for line in config_lines(config):
            typer.echo(line)

    @config_app.command("paths")
    def paths() -> None:
        """List the files searched, lowest precedence first, and whether each exists."""
        import os

        from mca.capture.config import ENV_VAR, config_paths

        if os.environ.get(ENV_VAR):
            typer.echo(f"${ENV_VAR} is set: only this file is read")
        for path in config_paths():
            typer.echo(f"{'found  ' if path.exists() else 'missing'}  {path}")

    @config_app.command("set")
    def set_values(
        assignments: list[str] = typer.Argument(
            ..., metavar="KEY=VALUE...", help="One or more, e.g. camera=sim rail=sim."
        ),
        system: bool = typer.Option(False, "--system", help="Write the system file (/etc/mca/config.toml)."),
    ) -> None:
        """Set one or more keys in the config file ($MCA_CONFIG, else the user file); all of them or none."""
        from mca.capture.config import ConfigError, set_config_values, settable_config_path, toml_value

        path = settable_config_path(system)
        try:
            written = set_config_values(path, assignments)
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        except OSError as exc:
            typer.echo(f"error: cannot write {path}: {exc.strerror or exc}", err=True)
            raise typer.Exit(1) from None
        for key, value in written.items():
            typer.echo(f"{key} = {toml_value(value)}  # {path}")

    app.add_typer(config_app, name="config")
