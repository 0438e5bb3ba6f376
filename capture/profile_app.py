"""The application side of `mca profile` and `mca optics` (and `--profile none` of `mca process`): a profile
described with the optics it implies, and one of disparity, inter-image depth or distance converted into all four."""

from __future__ import annotations

from pathlib import Path

from mca.devices.profiles import DEFAULT_PROFILE, ProfileError, builtin_names, load_profile
from mca.processing.camera import CameraProfile

__all__ = ["ProfileError", "convert_optics", "describe_profile", "profile_list_lines", "resolve_profile"]


def resolve_profile(name: str | None) -> CameraProfile:
    """The profile for `--profile`: a built-in name or TOML path (None: the default); `none` is the default
    filter geometry without lens data (results in disparity pixels only)."""
    import dataclasses

    if name is not None and name.lower() == "none":
        base = load_profile(DEFAULT_PROFILE)
        return dataclasses.replace(base, name="none", lens=None, source=f"{base.source} (filter geometry only)")
    return load_profile(name or DEFAULT_PROFILE)


def profile_list_lines() -> list[str]:
    """`mca profile list`: one line per built-in profile: name, camera, d_a and the focus (or disparity only)."""
    lines = []
    for name in builtin_names():
        p = load_profile(name)
        optics = "disparity only" if p.lens is None else f"focus {p.lens.focus_distance_mm:.1f} mm"
        lines.append(f"{name:<12} {p.model:<40} d_a {p.aperture.baseline_mm:6.2f}  {optics}")
    return lines


def describe_profile(name_or_path: str) -> str:
    """`mca profile show`: a profile's fields and the optics they imply (eq. 8 magnification, disparity -> depth)."""
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
    if isinstance(ap.lateral_colour, str):
        lines.append("lateral colour       measured in each capture")
    elif ap.lateral_colour is not None:
        (rx, ry), (bx, by) = ap.lateral_colour
        lines.append(f"lateral colour       red {rx:+g}, {ry:+g}  blue {bx:+g}, {by:+g} (x, y; parts per thousand)")
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


def convert_optics(
    profile: str | Path | CameraProfile,
    *,
    disparity_px: float | None = None,
    inter_image_depth_mm: float | None = None,
    distance_mm: float | None = None,
) -> dict[str, float]:
    """`mca optics`: from exactly one of disparity (widest filter pair, px), inter-image depth Δd (mm) or object
    distance (mm), all four quantities (eqs. 2, 11, 13/14 and the thin lens); + = farther than the focus plane.

    Raises `ProfileError` for a bad profile and `ValueError` naming the option for a value out of range."""
    from mca.processing.optics import MCAOptics

    given = [v is not None for v in (disparity_px, inter_image_depth_mm, distance_mm)]
    if sum(given) != 1:
        raise ValueError("give exactly one of --disparity-px, --inter-image-depth-mm, --distance-mm")
    model = MCAOptics.from_profile(profile if isinstance(profile, CameraProfile) else load_profile(profile))
    if disparity_px is not None:
        estimate = model.from_disparity(disparity_px)
    elif inter_image_depth_mm is not None:
        if inter_image_depth_mm >= model.sensor_distance_mm:
            raise ValueError(
                f"--inter-image-depth-mm must be smaller than the sensor distance {model.sensor_distance_mm:.3f} mm"
            )
        estimate = model.from_inter_image_depth(inter_image_depth_mm)
    else:
        assert distance_mm is not None
        if distance_mm <= model.focal_length_mm:
            raise ValueError(f"--distance-mm must exceed the focal length {model.focal_length_mm} mm")
        estimate = model.from_distance(distance_mm)
    return {
        "disparity_px": round(estimate.disparity_px, 6),
        "inter_image_depth_mm": round(estimate.inter_image_depth_mm, 6),
        "inter_object_depth_mm": round(estimate.inter_object_depth_mm, 4),
        "distance_mm": round(estimate.distance_mm, 4),
    }
