"""`mca config show|paths|set`: the effective appliance configuration, the files it was read from, and setting it."""

from __future__ import annotations

import json
from pathlib import Path

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

    @config_app.command("set")
    def set_values(
        assignments: list[str] = typer.Argument(
            ..., metavar="KEY=VALUE...", help="One or more, e.g. camera=sim rail=sim."
        ),
        system: bool = typer.Option(False, "--system", help="Write the system file (/etc/mca/config.toml)."),
    ) -> None:
        """Set one or more keys in the config file ($MCA_CONFIG, else the user file); all of them or none."""
        import os

        from mca.capture.config import ENV_VAR, SYSTEM_CONFIG, ConfigError, user_config_path

        path = (
            SYSTEM_CONFIG
            if system
            else Path(os.environ[ENV_VAR]).expanduser()
            if os.environ.get(ENV_VAR)
            else user_config_path()
        )
        try:
            written = set_config_values(path, assignments)
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        except OSError as exc:
            typer.echo(f"error: cannot write {path}: {exc.strerror or exc}", err=True)
            raise typer.Exit(1) from None
        for key, value in written.items():
            typer.echo(f"{key} = {_toml_value(value)}  # {path}")

    app.add_typer(config_app, name="config")


def set_config_values(path: Path, assignments: list[str]) -> dict[str, object]:
    """Validate every KEY=VALUE, then write them all into the TOML file at `path` (atomically); returns them.

    Values are checked as the loader checks them; a relative path (output_dir, a profile file) is made
    absolute from the current folder, since the loader would read it relative to the file's folder.
    """
    from mca.capture.config import ConfigError, read_config_file, validate_value
    from mca.capture.outputs import write_bytes_atomic

    changes: dict[str, object] = {}
    for assignment in assignments:
        key, sep, text = assignment.partition("=")
        key, text = key.strip(), text.strip()
        if not sep or not key:
            raise ConfigError(path, f"'{assignment}' is not KEY=VALUE (e.g. camera=sim)")
        value: object = text
        if key == "workers":
            try:
                value = int(text)
            except ValueError:
                raise ConfigError(path, f"must be a whole number, got {text!r}", key) from None
        elif key == "output_dir" or (key == "profile" and ("/" in text or text.lower().endswith(".toml"))):
            value = str(Path(text).expanduser().resolve())
        validate_value(path, key, value)  # raises naming the file and the key
        changes[key] = value
    data = dict(read_config_file(path)) if path.exists() else {}
    data.update(changes)
    text = "# mca appliance configuration (mca config set; see deploy/config.example.toml)\n"
    text += "".join(f"{key} = {_toml_value(value)}\n" for key, value in data.items())
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, text.encode("utf-8"))
    return changes
