"""`mca optics`: convert between disparity, inter-image depth, inter-object depth and distance for a profile."""

from __future__ import annotations

import json

import typer


def register(app: typer.Typer) -> None:
    @app.command("optics")
    def optics(
        profile: str = typer.Option("paper-70d", "--profile", "-p", help="Built-in profile name or TOML file."),
        disparity_px: float | None = typer.Option(
            None, "--disparity-px", help="Disparity between the widest filter pair, pixels."
        ),
        inter_image_depth_mm: float | None = typer.Option(
            None, "--inter-image-depth-mm", help="Image-side depth Δd from the sensor, mm."
        ),
        distance_mm: float | None = typer.Option(None, "--distance-mm", help="Object distance from the lens, mm."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    ) -> None:
        """From one of disparity, inter-image depth or distance, print all four (eqs. 2, 11, 13/14 and the thin lens).

        Signs: positive means farther than the focus plane.
        """
        from mca.capture.profile_app import convert_optics

        try:
            values = convert_optics(
                profile, disparity_px=disparity_px, inter_image_depth_mm=inter_image_depth_mm, distance_mm=distance_mm
            )
        except ValueError as exc:  # a ProfileError is a ValueError too
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        if as_json:
            typer.echo(json.dumps(values))
            return
        for key, value in values.items():
            typer.echo(f"{key:<22} {value:+.4f}")
