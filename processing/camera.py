"""Camera profiles: the validated optical parameters of an MCA camera (sensor, lens, filter aperture)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

CHANNELS = ("red", "green", "blue")

# Plausible ranges: a value outside them is a typo or a hostile file, and would only fail later with a
# ZeroDivisionError or an overflow in every photograph processed with the profile.
MAX_LENS_MM = 10_000.0  # focal length, lens-sensor distance (d_ls): 10 m
MAX_FOCUS_DISTANCE_MM = 1_000_000.0  # 1 km: beyond it the focus is infinity for any lens here
MAX_APERTURE_MM = 1_000.0  # aperture and filter diameters, filter centres
MIN_BASELINE_MM = 0.01  # d_a of the widest filter pair: below it there is no disparity to measure
F_NUMBER_RANGE = (0.5, 1_000.0)
MIN_PIXEL_PITCH_MM = 0.0001
MAX_IMAGE_SIDE_PX = 1_000_000
MAX_CROSSTALK = 1_000.0


class ProfileError(ValueError):
    """A profile that cannot be used; names the profile source and the offending field."""

    def __init__(self, field: str, reason: str, source: str | None = None) -> None:
        self.field = field
        self.reason = reason
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}field '{field}': {reason}")


@dataclass(frozen=True)
class Lens:
    """A thin lens focused so that the sensor sits `sensor_distance_mm` (the paper's d_ls) behind it."""

    focal_length_mm: float
    sensor_distance_mm: float
    f_number: float | None = None

    @property
    def focus_distance_mm(self) -> float:
        """Object distance in focus on the sensor, from the Gaussian lens equation (eq. 6 with zero depth)."""
        f, d = self.focal_length_mm, self.sensor_distance_mm
        return f * d / (d - f)


@dataclass(frozen=True)
class FilterAperture:
    """Three colour filters in the aperture; centres in mm seen from behind the camera, x right, y up."""

    filter_diameter_mm: float
    red_mm: tuple[float, float]
    green_mm: tuple[float, float]
    blue_mm: tuple[float, float]
    diameter_mm: float | None = None
    crosstalk: tuple[tuple[float, float, float], ...] | None = None
    # the lens's lateral colour (`processing.chromatic`): None (none taken out), "measure" (measured in each
    # capture), or ((kx, ky) of red, (kx, ky) of blue) against green, in parts per thousand (calibrated)
    lateral_colour: str | tuple[tuple[float, float], tuple[float, float]] | None = None

    def centre_mm(self, channel: str) -> tuple[float, float]:
        return {"red": self.red_mm, "green": self.green_mm, "blue": self.blue_mm}[channel]

    def filter_centre_distance_mm(self, first: str, second: str) -> float:
        """The paper's d_a: distance between the centres of the two filters whose images are compared."""
        (ax, ay), (bx, by) = self.centre_mm(first), self.centre_mm(second)
        return math.hypot(ax - bx, ay - by)

    @property
    def widest_pair(self) -> tuple[str, str]:
        """The two filters farthest apart: their images give the largest, most precise disparity."""
        pairs = [("red", "blue"), ("red", "green"), ("green", "blue")]
        return max(pairs, key=lambda pair: self.filter_centre_distance_mm(*pair))

    @property
    def baseline_mm(self) -> float:
        """d_a of the widest pair, the pair in which disparities are reported."""
        return self.filter_centre_distance_mm(*self.widest_pair)

    def shift_per_disparity(self, channel: str) -> tuple[float, float]:
        """Displacement (dx, dy) in image pixels of `channel` per pixel of disparity of the widest pair.

        Image axes: x right, y down. A farther object (positive disparity) moves each
        channel toward its filter's side; the lens centre is the fixed point.
        """
        x_mm, y_mm = self.centre_mm(channel)
        scale = 1.0 / self.baseline_mm
        return (x_mm * scale, -y_mm * scale)


@dataclass(frozen=True)
class CameraProfile:
    """Everything processing needs to know about one MCA camera; `lens` is None for disparity-only profiles."""

    name: str
    model: str
    aperture: FilterAperture
    pixel_pitch_mm: float | None = None
    width_px: int | None = None
    height_px: int | None = None
    lens: Lens | None = None
    source: str | None = None

    @property
    def has_optics(self) -> bool:
        """True when distances in mm can be computed (lens, pixel pitch and aperture known)."""
        return self.lens is not None and self.pixel_pitch_mm is not None


def _section(data: Mapping[str, Any], name: str, source: str, required: bool = True) -> Mapping[str, Any] | None:
    value = data.get(name)
    if value is None:
        if required:
            raise ProfileError(name, "missing section; add it (see README, 'Camera profiles')", source)
        return None
    if not isinstance(value, Mapping):
        raise ProfileError(name, f"must be a table, got {type(value).__name__}", source)
    return value


def _number(
    table: Mapping[str, Any],
    key: str,
    field: str,
    source: str,
    *,
    required: bool = True,
    positive: bool = True,
    maximum: float | None = None,
) -> float | None:
    if key not in table:
        if required:
            raise ProfileError(field, "missing; it is required", source)
        return None
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProfileError(field, f"must be a finite number, got {value!r}", source)
    if positive and value <= 0:
        raise ProfileError(field, f"must be positive, got {value!r}", source)
    if maximum is not None and abs(value) > maximum:
        raise ProfileError(field, f"{value!r} is beyond the plausible {maximum:g} (check the unit: mm)", source)
    return float(value)


def _point(table: Mapping[str, Any], key: str, field: str, source: str) -> tuple[float, float]:
    if key not in table:
        raise ProfileError(field, "missing; give the filter centre as [x_mm, y_mm]", source)
    value = table[key]
    if (
        not isinstance(value, (list, tuple))
        or len(value) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    ):
        raise ProfileError(field, f"must be [x_mm, y_mm] (two numbers), got {value!r}", source)
    if max(abs(value[0]), abs(value[1])) > MAX_APERTURE_MM:
        raise ProfileError(
            field, f"{list(value)!r} lies beyond the plausible {MAX_APERTURE_MM:g} mm from the axis", source
        )
    return (float(value[0]), float(value[1]))


def _crosstalk(table: Mapping[str, Any], source: str) -> tuple[tuple[float, float, float], ...] | None:
    if "crosstalk" not in table:
        return None
    value = table["crosstalk"]
    field = "aperture.crosstalk"
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ProfileError(field, "must be a 3x3 matrix [[..],[..],[..]] (sensor channel <- filter)", source)
    rows: list[tuple[float, float, float]] = []
    for row in value:
        if (
            not isinstance(row, (list, tuple))
            or len(row) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in row)
            or any(abs(v) > MAX_CROSSTALK for v in row)
        ):
            raise ProfileError(
                field, f"each row must hold three numbers of at most {MAX_CROSSTALK:g}, got {row!r}", source
            )
        rows.append((float(row[0]), float(row[1]), float(row[2])))
    a = rows
    det = (
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
        - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    )
    if abs(det) < 1e-6:
        raise ProfileError(field, "is singular: the channels could not be separated", source)
    return (rows[0], rows[1], rows[2])


MAX_LATERAL_COLOUR_PPT = 20.0  # 2 % magnification between colours: far beyond any photographic lens


def _lateral_colour(
    table: Mapping[str, Any], source: str
) -> str | tuple[tuple[float, float], tuple[float, float]] | None:
    if "lateral_colour" not in table:
        return None
    value = table["lateral_colour"]
    field = "aperture.lateral_colour"
    if value == "measure":
        return "measure"
    if (
        not isinstance(value, (list, tuple))
        or len(value) != 2
        or not all(
            isinstance(row, (list, tuple))
            and len(row) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in row)
            for row in value
        )
    ):
        raise ProfileError(
            field,
            '"measure" (in each capture) or [[kx, ky] of red, [kx, ky] of blue] against green, in parts per '
            f"thousand (result.json's lateral_colour of a capture of a flat, textured target), got {value!r}",
            source,
        )
    if any(abs(v) > MAX_LATERAL_COLOUR_PPT for row in value for v in row):
        raise ProfileError(field, f"{value!r}: beyond {MAX_LATERAL_COLOUR_PPT:g} parts per thousand", source)
    return ((float(value[0][0]), float(value[0][1])), (float(value[1][0]), float(value[1][1])))


def profile_from_mapping(data: Mapping[str, Any], source: str = "<profile>") -> CameraProfile:
    """Validate a parsed profile (e.g. from TOML) and build a `CameraProfile`; errors name `source` and the field."""
    if not isinstance(data, Mapping):
        raise ProfileError("<top level>", "a profile must be a table of sections", source)
    name = data.get("name")
    if not isinstance(name, str) or not name.strip():
        raise ProfileError("name", "missing or empty; give the profile a name", source)

    camera = _section(data, "camera", source)
    assert camera is not None
    model = camera.get("model")
    if not isinstance(model, str) or not model.strip():
        raise ProfileError("camera.model", "missing or empty", source)
    pitch = _number(camera, "pixel_pitch_mm", "camera.pixel_pitch_mm", source, required=False)
    if pitch is not None and not MIN_PIXEL_PITCH_MM <= pitch <= 0.1:
        raise ProfileError(
            "camera.pixel_pitch_mm", f"{pitch} mm is not a photosite pitch (give mm, e.g. 0.004109)", source
        )
    size = []
    for key in ("width_px", "height_px"):
        value = camera.get(key)
        if value is not None and (
            isinstance(value, bool) or not isinstance(value, int) or not 0 < value <= MAX_IMAGE_SIDE_PX
        ):
            raise ProfileError(
                f"camera.{key}", f"must be a positive integer of at most {MAX_IMAGE_SIDE_PX}, got {value!r}", source
            )
        size.append(value)

    lens_table = _section(data, "lens", source, required=False)
    lens = None
    if lens_table is not None:
        focal = _number(lens_table, "focal_length_mm", "lens.focal_length_mm", source, maximum=MAX_LENS_MM)
        assert focal is not None
        f_number = _number(lens_table, "f_number", "lens.f_number", source, required=False)
        if f_number is not None and not F_NUMBER_RANGE[0] <= f_number <= F_NUMBER_RANGE[1]:
            raise ProfileError(
                "lens.f_number",
                f"{f_number!r} is not an f-number ({F_NUMBER_RANGE[0]:g} to {F_NUMBER_RANGE[1]:g})",
                source,
            )
        has_focus = "focus_distance_mm" in lens_table
        has_sensor = "sensor_distance_mm" in lens_table
        if has_focus == has_sensor:
            raise ProfileError(
                "lens.focus_distance_mm", "give exactly one of focus_distance_mm and sensor_distance_mm", source
            )
        if has_focus:
            focus = _number(
                lens_table, "focus_distance_mm", "lens.focus_distance_mm", source, maximum=MAX_FOCUS_DISTANCE_MM
            )
            assert focus is not None
            if focus <= focal:
                raise ProfileError(
                    "lens.focus_distance_mm",
                    f"{focus} mm is not beyond the focal length {focal} mm: nothing would be in focus",
                    source,
                )
            sensor = focal * focus / (focus - focal)
        else:
            given = _number(lens_table, "sensor_distance_mm", "lens.sensor_distance_mm", source, maximum=MAX_LENS_MM)
            assert given is not None
            sensor = given
            if sensor <= focal:
                raise ProfileError(
                    "lens.sensor_distance_mm",
                    f"{sensor} mm must exceed the focal length {focal} mm for a real image",
                    source,
                )
        lens = Lens(focal_length_mm=focal, sensor_distance_mm=sensor, f_number=f_number)

    ap = _section(data, "aperture", source)
    assert ap is not None
    filter_diameter = _number(ap, "filter_diameter_mm", "aperture.filter_diameter_mm", source, maximum=MAX_APERTURE_MM)
    assert filter_diameter is not None
    centres = {c: _point(ap, c, f"aperture.{c}", source) for c in CHANNELS}
    baseline = max(
        math.hypot(centres[a][0] - centres[b][0], centres[a][1] - centres[b][1])
        for a, b in (("red", "green"), ("red", "blue"), ("green", "blue"))
    )
    if baseline < MIN_BASELINE_MM:
        raise ProfileError(
            "aperture.red",
            f"the filter centres lie at most {baseline:g} mm apart (red {list(centres['red'])}, green "
            f"{list(centres['green'])}, blue {list(centres['blue'])}): with no baseline d_a there is no disparity; "
            f"give centres at least {MIN_BASELINE_MM} mm apart",
            source,
        )
    diameter = _number(ap, "diameter_mm", "aperture.diameter_mm", source, required=False, maximum=MAX_APERTURE_MM)
    if diameter is None and lens is not None and lens.f_number is not None:
        diameter = lens.focal_length_mm / lens.f_number
    if diameter is not None:
        for channel, (x, y) in centres.items():
            reach = math.hypot(x, y) + filter_diameter / 2
            if reach > diameter / 2 + 1e-9:
                raise ProfileError(
                    f"aperture.{channel}",
                    f"filter reaches {reach:.2f} mm from the axis, outside the aperture of radius "
                    f"{diameter / 2:.2f} mm",
                    source,
                )
    for first, second in (("red", "green"), ("red", "blue"), ("green", "blue")):
        (ax, ay), (bx, by) = centres[first], centres[second]
        if math.hypot(ax - bx, ay - by) < filter_diameter - 1e-9:
            raise ProfileError(f"aperture.{second}", f"filter overlaps the {first} filter", source)
    aperture = FilterAperture(
        filter_diameter_mm=filter_diameter,
        red_mm=centres["red"],
        green_mm=centres["green"],
        blue_mm=centres["blue"],
        diameter_mm=diameter,
        crosstalk=_crosstalk(ap, source),
        lateral_colour=_lateral_colour(ap, source),
    )
    return CameraProfile(
        name=name.strip(),
        model=model.strip(),
        aperture=aperture,
        pixel_pitch_mm=pitch,
        width_px=size[0],
        height_px=size[1],
        lens=lens,
        source=source,
    )
