"""`mca profile list|show`: the camera profiles the appliance knows and what they imply."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    profile_app = typer.Typer(
        help="Camera profiles: list the built-in ones, show one with its derived optics.", no_args_is_help=True
    )

    @profile_app.command("list")
    def list_profiles() -> None:
        """List the built-in profiles."""
        from mca.capture.profile_app import profile_list_lines

        for line in profile_list_lines():
            typer.echo(line)

    @profile_app.command("show")
    def show(profile: str = typer.Argument(..., metavar="NAME|PATH", help="Built-in name or TOML file.")) -> None:
        """Show a profile: its fields and the optics they imply."""
        from mca.capture.profile_app import ProfileError, describe_profile

        try:
            typer.echo(describe_profile(profile))
        except ProfileError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None

    app.add_typer(profile_app, name="profile")
