"""Photosite pitch of camera bodies, looked up by the Exif model name, for turning pixels into millimetres."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SensorSpec:
    """A body's sensor: physical size and the active (recorded) image size."""

    model: str
    width_mm: float
    height_mm: float
    width_px: int
    height_px: int

    @property
    def photosite_pitch_mm(self) -> float:
        """Centre-to-centre distance of neighbouring photosites (sensor width / active columns)."""
        return self.width_mm / self.width_px


# Manufacturer specifications (Canon data sheets): sensor size in mm, active image in pixels.
_SPECS = [
    SensorSpec("Canon EOS 70D", 22.5, 15.0, 5472, 3648),
    SensorSpec("Canon EOS 80D", 22.3, 14.9, 6000, 4000),
    SensorSpec("Canon EOS 90D", 22.3, 14.8, 6960, 4640),
    SensorSpec("Canon EOS 60D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 50D", 22.3, 14.9, 4752, 3168),
    SensorSpec("Canon EOS 7D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 7D Mark II", 22.4, 15.0, 5472, 3648),
    SensorSpec("Canon EOS 77D", 22.3, 14.9, 6000, 4000),
    SensorSpec("Canon EOS 100D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 600D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 650D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 700D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 750D", 22.3, 14.9, 6000, 4000),
    SensorSpec("Canon EOS 760D", 22.3, 14.9, 6000, 4000),
    SensorSpec("Canon EOS 800D", 22.3, 14.9, 6000, 4000),
    SensorSpec("Canon EOS 1200D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 1300D", 22.3, 14.9, 5184, 3456),
    SensorSpec("Canon EOS 2000D", 22.3, 14.9, 6000, 4000),
    SensorSpec("Canon EOS 6D", 35.8, 23.9, 5472, 3648),
    SensorSpec("Canon EOS 6D Mark II", 35.9, 24.0, 6240, 4160),
    SensorSpec("Canon EOS 5D Mark II", 36.0, 24.0, 5616, 3744),
    SensorSpec("Canon EOS 5D Mark III", 36.0, 24.0, 5760, 3840),
    SensorSpec("Canon EOS 5D Mark IV", 36.0, 24.0, 6720, 4480),
    SensorSpec("Canon EOS R", 36.0, 24.0, 6720, 4480),
    SensorSpec("Canon EOS RP", 35.9, 24.0, 6240, 4160),
]

# Regional names of the same bodies (Exif Model as written by cameras sold there).
_ALIASES = {
    "Canon EOS Rebel T5i": "Canon EOS 700D",
    "Canon EOS Kiss X7i": "Canon EOS 700D",
    "Canon EOS Rebel T4i": "Canon EOS 650D",
    "Canon EOS Rebel SL1": "Canon EOS 100D",
    "Canon EOS Rebel T3i": "Canon EOS 600D",
    "Canon EOS Rebel T6i": "Canon EOS 750D",
    "Canon EOS Rebel T6s": "Canon EOS 760D",
    "Canon EOS Rebel T7i": "Canon EOS 800D",
    "Canon EOS Rebel T5": "Canon EOS 1200D",
    "Canon EOS Rebel T6": "Canon EOS 1300D",
    "Canon EOS Rebel T7": "Canon EOS 2000D",
}

SENSORS: dict[str, SensorSpec] = {spec.model.lower(): spec for spec in _SPECS}


def _normalise(model: str, make: str | None) -> str:
    name = " ".join(model.split())
    if make and not name.lower().startswith(make.split()[0].lower()):
        name = f"{make.split()[0]} {name}"  # LibRaw-style "EOS 70D" -> "Canon EOS 70D"
    return name


def sensor_for(model: str | None, make: str | None = "Canon") -> SensorSpec | None:
    """The sensor of the body named `model` (Exif Model, e.g. "Canon EOS 70D"), or None if unknown."""
    if not model:
        return None
    name = _normalise(model, make)
    name = _ALIASES.get(name, name)
    return SENSORS.get(name.lower())


def photosite_pitch_mm(model: str | None, make: str | None = "Canon") -> float | None:
    """Photosite pitch of the body named `model`, in mm, or None if the body is not in the table."""
    spec = sensor_for(model, make)
    return spec.photosite_pitch_mm if spec else None


def known_models() -> list[str]:
    """Exif model names in the table."""
    return [spec.model for spec in _SPECS]
