"""Human names for camera properties (ISO, shutter speed, capture target, image format) and their value tables."""

from __future__ import annotations

from dataclasses import dataclass

from mca.devices.ptp.codes import CAPTURE_DESTINATION_CARD, CAPTURE_DESTINATION_RAM, EosProp, StdProp


def _apex_table(base_code: int, base_stop: int, stops: list[str]) -> dict[int, str]:
    """EOS exposure codes move 8 units per stop with third stops at +3 and +5."""
    out: dict[int, str] = {}
    for i, names in enumerate(stops):
        for offset, name in zip((0, 3, 5), names.split("|")):
            if name:
                out[base_code + 8 * (i + base_stop) + offset] = name
    return out


# ISO: 0x48 is ISO 100, +8 per stop (libgphoto2's canon_isospeed table agrees).
EOS_ISO = {
    0x00: "Auto",
    **_apex_table(
        0x48,
        0,
        [
            "100|125|160",
            "200|250|320",
            "400|500|640",
            "800|1000|1250",
            "1600|2000|2500",
            "3200|4000|5000",
            "6400|8000|10000",
            "12800||",
        ],
    ),
}
# Shutter speed: 0x10 is 30 s, 0x38 is 1 s, +8 per stop down to 0xA0 = 1/8000.
EOS_SHUTTER = {
    0x0C: "bulb",
    **_apex_table(
        0x10,
        0,
        [
            "30|25|20",
            "15|13|10",
            "8|6|5",
            "4|3.2|2.5",
            "2|1.6|1.3",
            "1|0.8|0.6",
            "0.5|0.4|0.3",
            "1/4|1/5|1/6",
            "1/8|1/10|1/13",
            "1/15|1/20|1/25",
            "1/30|1/40|1/50",
            "1/60|1/80|1/100",
            "1/125|1/160|1/200",
            "1/250|1/320|1/400",
            "1/500|1/640|1/800",
            "1/1000|1/1250|1/1600",
            "1/2000|1/2500|1/3200",
            "1/4000|1/5000|1/6400",
            "1/8000||",
        ],
    ),
}
# Aperture: 0x20 is f/2.8, +8 per stop.
EOS_APERTURE = _apex_table(
    0x20, 0, ["2.8|3.2|3.5", "4|4.5|5", "5.6|6.3|7.1", "8|9|10", "11|13|14", "16|18|20", "22|25|29", "32||"]
)
EOS_CAPTURE_TARGET = {CAPTURE_DESTINATION_CARD: "Memory card", CAPTURE_DESTINATION_RAM: "Internal RAM"}
CAPTURE_TARGET_ALIASES = {"card": "Memory card", "ram": "Internal RAM", "sdram": "Internal RAM"}
# Image format entries are (type, size, compression): type 6 RAW / 1 JPEG, size 0 Large, compression 3 fine / 2 normal / 4 lossless.
EOS_IMAGE_FORMATS: dict[tuple[tuple[int, int, int], ...], str] = {
    ((6, 0, 4),): "RAW",
    ((1, 0, 3),): "Large Fine JPEG",
    ((1, 0, 2),): "Large Normal JPEG",
    ((1, 1, 3),): "Medium Fine JPEG",
    ((1, 2, 3),): "Small Fine JPEG",
    ((6, 0, 4), (1, 0, 3)): "RAW + Large Fine JPEG",
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


def spec_for(name: str) -> PropertySpec:
    key = name.strip().lower().replace(" ", "").replace("-", "")
    key = ALIASES.get(key, key)
    if key not in PROPERTIES:
        raise KeyError(f"unknown property {name!r}; known: {', '.join(PROPERTIES)}")
    return PROPERTIES[key]
