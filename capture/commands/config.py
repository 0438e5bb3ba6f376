"""`mca config show|paths`: the effective appliance configuration and the files it was read from."""

from __future__ import annotations

import json

import typer


def _toml_value(value: object) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    return json.dumps(str(value))  # a JSON string is a valid TOML basic string


def register(app: typer.Typer) -> None:
    config_app = typer.Typer(
        help="The appliance config file: show the effective values and where they came from.", no_args_is_help=True
    )

    @config_app.command("show")
    def show(as_json: bool = typer.Option(False, "--json", help="Print one JSON object: values and sources.")) -> None:
        """Print the effective config as TOML, each value commented with the file it came from (or "default")."""
        from mca.capture.config import KEYS, ConfigError, load_config

        try:
            config = load_config()
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        if as_json:
            typer.echo(
                json.dumps(
                    {
                        "values": {
                            key: (getattr(config, key) if key == "workers" else str(getattr(config, key)))
                            for key in KEYS
                        },
                        "sources": {key: config.source_of(key) for key in KEYS},
                    },
                    indent=2,
                )
            )
            return
        rendered = [(f"{key} = {_toml_value(getattr(config, key))}", config.source_of(key)) for key in KEYS]
        width = max(len(text) for text, _ in rendered)
        for text, source in rendered:
            typer.echo(f"{text:<{width}}  # {source}")

    @config_app.command("paths")
    def paths() -> None:
        """List the files searched, lowest precedence first, and whether each exists."""
        import os

        from mca.capture.config import ENV_VAR, config_paths

        if os.environ.get(ENV_VAR):
            typer.echo(f"${ENV_VAR} is set: only this file is read")
        for path in config_paths():
            typer.echo(f"{'found  ' if path.exists() else 'missing'}  {path}")

    app.add_typer(config_app, name="config")
