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
        from mca.devices.profiles import load_profile
        from mca.processing.camera import ProfileError
        from mca.processing.optics import MCAOptics

        given = [v is not None for v in (disparity_px, inter_image_depth_mm, distance_mm)]
        if sum(given) != 1:
            typer.echo("error: give exactly one of --disparity-px, --inter-image-depth-mm, --distance-mm", err=True)
            raise typer.Exit(2)
        try:
            optics_model = MCAOptics.from_profile(load_profile(profile))
        except (ProfileError, ValueError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        if disparity_px is not None:
            estimate = optics_model.from_disparity(disparity_px)
        elif inter_image_depth_mm is not None:
            if inter_image_depth_mm >= optics_model.sensor_distance_mm:
                typer.echo(
                    "error: --inter-image-depth-mm must be smaller than the sensor distance "
                    f"{optics_model.sensor_distance_mm:.3f} mm",
                    err=True,
                )
                raise typer.Exit(2)
            estimate = optics_model.from_inter_image_depth(inter_image_depth_mm)
        else:
            assert distance_mm is not None
            if distance_mm <= optics_model.focal_length_mm:
                typer.echo(
                    f"error: --distance-mm must exceed the focal length {optics_model.focal_length_mm} mm", err=True
                )
                raise typer.Exit(2)
            estimate = optics_model.from_distance(distance_mm)
        values = {
            "disparity_px": round(estimate.disparity_px, 6),
            "inter_image_depth_mm": round(estimate.inter_image_depth_mm, 6),
            "inter_object_depth_mm": round(estimate.inter_object_depth_mm, 4),
            "distance_mm": round(estimate.distance_mm, 4),
        }
        if as_json:
            typer.echo(json.dumps(values))
            return
        for key, value in values.items():
            typer.echo(f"{key:<22} {value:+.4f}")
