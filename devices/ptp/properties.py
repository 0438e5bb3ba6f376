"""Human names for camera properties (ISO, shutter speed, aperture, capture target, image format) and their value tables.

EOS exposure codes move 8 units per stop; third stops sit at +3 and +5, half
stops at +4 (a body lists one or the other, set by a custom function). Names
repeat where a third and a half stop share a nominal value (f/3.5 is 0x24 and
0x25); `code_for` then prefers the code the camera offers.
"""

from __future__ import annotations

from dataclasses import dataclass

from mca.devices.ptp.codes import CAPTURE_DESTINATION_CARD, CAPTURE_DESTINATION_RAM, EosProp, StdProp


def _stop_table(base_code: int, stops: list[str]) -> dict[int, str]:
    """`stops[i]` is "whole|third|half|third": the names at base + 8i, +3, +4 and +5 (empty = no such value)."""
    out: dict[int, str] = {}
    for i, names in enumerate(stops):
        for offset, name in zip((0, 3, 4, 5), names.split("|")):
            if name:
                out[base_code + 8 * i + offset] = name
    return out


# ISO: 0x48 is ISO 100, +8 per stop; the 70D's "H" expansion is ISO 25600 (0x88). Thirds only.
EOS_ISO: dict[int, str] = {
    0x00: "Auto",
    **_stop_table(
        0x48,
        [
            "100|125||160",
            "200|250||320",
            "400|500||640",
            "800|1000||1250",
            "1600|2000||2500",
            "3200|4000||5000",
            "6400|8000||10000",
            "12800|16000||20000",
            "25600|32000||40000",
            "51200|||",
        ],
    ),
}
# Shutter speed: 0x10 is 30 s, 0x38 is 1 s, +8 per stop down to 0xA0 = 1/8000 s.
EOS_SHUTTER: dict[int, str] = {
    0x0C: "bulb",
    **_stop_table(
        0x10,
        [
            "30|25|20|20",
            "15|13|10|10",
            "8|6|6|5",
            "4|3.2|3|2.5",
            "2|1.6|1.5|1.3",
            "1|0.8|0.7|0.6",
            "0.5|0.4|0.3|0.3",
            "1/4|1/5|1/6|1/6",
            "1/8|1/10|1/10|1/13",
            "1/15|1/20|1/20|1/25",
            "1/30|1/40|1/45|1/50",
            "1/60|1/80|1/90|1/100",
            "1/125|1/160|1/180|1/200",
            "1/250|1/320|1/350|1/400",
            "1/500|1/640|1/750|1/800",
            "1/1000|1/1250|1/1500|1/1600",
            "1/2000|1/2500|1/3000|1/3200",
            "1/4000|1/5000|1/6000|1/6400",
            "1/8000|||",
        ],
    ),
}
# Aperture: 0x08 is f/1.0, 0x20 is f/2.8, +8 per stop (an f/1.8 lens opens at 0x14 or 0x15).
EOS_APERTURE: dict[int, str] = _stop_table(
    0x08,
    [
        "1|1.1|1.2|1.2",
        "1.4|1.6|1.8|1.8",
        "2|2.2|2.5|2.5",
        "2.8|3.2|3.5|3.5",
        "4|4.5|4.5|5",
        "5.6|6.3|6.7|7.1",
        "8|9|9.5|10",
        "11|13|13|14",
        "16|18|19|20",
        "22|25|27|29",
        "32|36|38|40",
        "45|51|54|57",
        "64|72|76|81",
        "91|||",
    ],
)
EOS_CAPTURE_TARGET: dict[int, str] = {CAPTURE_DESTINATION_CARD: "Memory card", CAPTURE_DESTINATION_RAM: "Internal RAM"}
CAPTURE_TARGET_ALIASES = {"card": "Memory card", "ram": "Internal RAM", "sdram": "Internal RAM"}

# Image format entries are (type, size, compression): type 6 RAW / 1 JPEG; size 0 L, 1 M, 2 S, 0xE S1, 0xF S2, 0x10 S3;
# compression 2 normal, 3 fine, 4 lossless (RAW).
_SIZE_NAMES = {
    0: "Large",
    1: "Medium",
    2: "Small",
    5: "Medium1",
    6: "Medium2",
    0xE: "Small1",
    0xF: "Small2",
    0x10: "Small3",
}
_RAW_SIZE_NAMES = {0: "RAW", 1: "mRAW", 2: "sRAW"}
_QUALITY_NAMES = {2: "Normal", 3: "Fine"}
ImageFormat = tuple[tuple[int, int, int], ...]


def image_format_name(entries: ImageFormat) -> str:
    """ "RAW + Large Fine JPEG" style name of an EOS image format (one or two files per shot)."""
    parts = []
    for kind, size, compression in entries:
        if kind == 6:
            parts.append(_RAW_SIZE_NAMES.get(size, f"RAW size {size}"))
        elif kind == 1 and size in _SIZE_NAMES and compression in _QUALITY_NAMES:
            parts.append(f"{_SIZE_NAMES[size]} {_QUALITY_NAMES[compression]} JPEG")
        else:
            parts.append(f"type{kind}/size{size}/q{compression}")
    return " + ".join(parts)


#: Image formats settable by name on any EOS body (a body's own list adds its other formats).
EOS_IMAGE_FORMAT_NAMES: dict[ImageFormat, str] = {
    f: image_format_name(f)
    for f in (((6, 0, 4),), ((1, 0, 3),), ((1, 0, 2),), ((1, 1, 3),), ((1, 2, 3),), ((6, 0, 4), (1, 0, 3)))
}


@dataclass(frozen=True)
class PropertySpec:
    """One human-named property: its EOS code and, for generic PTP cameras, its standard code."""

    name: str
    eos_code: int | None
    std_code: int | None
    table: dict[int, str] | None = None
    description: str = ""


PROPERTIES: dict[str, PropertySpec] = {
    "iso": PropertySpec("iso", EosProp.ISO_SPEED, StdProp.EXPOSURE_INDEX, EOS_ISO, "ISO speed"),
    "shutterspeed": PropertySpec(
        "shutterspeed", EosProp.SHUTTER_SPEED, StdProp.EXPOSURE_TIME, EOS_SHUTTER, "exposure time in seconds"
    ),
    "aperture": PropertySpec("aperture", EosProp.APERTURE, StdProp.F_NUMBER, EOS_APERTURE, "f-number"),
    "capturetarget": PropertySpec(
        "capturetarget",
        EosProp.CAPTURE_DESTINATION,
        None,
        EOS_CAPTURE_TARGET,
        "where shots go: the memory card or the camera's RAM (downloaded at once)",
    ),
    "imageformat": PropertySpec(
        "imageformat", EosProp.IMAGE_FORMAT, StdProp.COMPRESSION_SETTING, None, "file type and size"
    ),
}
ALIASES = {
    "shutter": "shutterspeed",
    "shutter_speed": "shutterspeed",
    "capture_target": "capturetarget",
    "image_format": "imageformat",
    "format": "imageformat",
    "target": "capturetarget",
}


class UnknownPropertyName(LookupError):
    """A property name this stack does not know; the message lists the known ones."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "unknown property"


def spec_for(name: str) -> PropertySpec:
    key = name.strip().lower().replace(" ", "").replace("-", "")
    key = ALIASES.get(key, key)
    if key not in PROPERTIES:
        raise UnknownPropertyName(f"unknown property {name!r}; known: {', '.join(PROPERTIES)}")
    return PROPERTIES[key]


def code_for(table: dict[int, str], name: str, offered: tuple[int, ...] = ()) -> int | None:
    """The code whose name is `name` (case-insensitive), preferring one the camera offers; None if no such name."""
    wanted = name.strip().lower()
    candidates = [code for code, label in table.items() if label.lower() == wanted]
    for code in candidates:
        if code in offered:
            return code
    return candidates[0] if candidates else None
