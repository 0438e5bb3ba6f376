"""`mca profile list|show`: the camera profiles the appliance knows and what they imply."""

from __future__ import annotations

import typer


def _describe(name_or_path: str) -> str:
    from mca.devices.profiles import load_profile
    from mca.processing.optics import MCAOptics

    p = load_profile(name_or_path)
    ap = p.aperture
    first, second = ap.widest_pair
    lines = [
        f"name                 {p.name}",
        f"source               {p.source}",
        f"camera               {p.model}",
        f"pixel pitch          {p.pixel_pitch_mm if p.pixel_pitch_mm is not None else 'unknown'} mm",
        f"image size           {p.width_px or '?'} x {p.height_px or '?'} px",
        f"filters (x, y) mm    red {ap.red_mm}  green {ap.green_mm}  blue {ap.blue_mm}, "
        f"diameter {ap.filter_diameter_mm} mm",
        f"d_a                  {ap.baseline_mm:.3f} mm between the {first} and {second} filter centres",
    ]
    if ap.crosstalk is not None:
        lines.append(f"crosstalk            {ap.crosstalk}")
    if p.lens is None:
        lines.append("lens                 none: depth is reported as disparity in pixels only")
        return "\n".join(lines)
    lines += [
        f"focal length f       {p.lens.focal_length_mm} mm" + (f", f/{p.lens.f_number}" if p.lens.f_number else ""),
        f"sensor distance d_ls {p.lens.sensor_distance_mm:.4f} mm",
        f"focus distance       {p.lens.focus_distance_mm:.2f} mm",
    ]
    if p.pixel_pitch_mm is not None:
        optics = MCAOptics.from_profile(p)
        lines.append(f"magnification M      {optics.magnification:.5f} (eq. 8)")
        lines.append(
            "disparity -> depth   "
            + "  ".join(
                f"{d:+d}px:{optics.from_disparity(d).inter_object_depth_mm:+.1f}mm" for d in (-20, -10, -4, 4, 10, 20)
            )
        )
    return "\n".join(lines)


def register(app: typer.Typer) -> None:
    profile_app = typer.Typer(
        help="Camera profiles: list the built-in ones, show one with its derived optics.", no_args_is_help=True
    )

    @profile_app.command("list")
    def list_profiles() -> None:
        """List the built-in profiles."""
        from mca.devices.profiles import builtin_names, load_profile

        for name in builtin_names():
            p = load_profile(name)
            optics = "disparity only" if p.lens is None else f"focus {p.lens.focus_distance_mm:.1f} mm"
            typer.echo(f"{name:<12} {p.model:<40} d_a {p.aperture.baseline_mm:6.2f}  {optics}")

    @profile_app.command("show")
    def show(profile: str = typer.Argument(..., metavar="NAME|PATH", help="Built-in name or TOML file.")) -> None:
        """Show a profile: its fields and the optics they imply."""
        from mca.processing.camera import ProfileError

        try:
            typer.echo(_describe(profile))
        except ProfileError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None

    app.add_typer(profile_app, name="profile")
