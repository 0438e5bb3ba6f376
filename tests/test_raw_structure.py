"""read_raw's parsing against independent readers: TIFF directories as tifffile reads them, DNG variants as LibRaw
decodes them, header fields and limits from hand-built bytes (TIFF 6.0, ITU T.81, DNG 1.4), and expected values
computed here from first principles.
"""

from __future__ import annotations

import io
import math
import mmap
import struct
from pathlib import Path

import numpy as np
import pytest
import tifffile

from mca.capture import raw
from mca.capture.raw import NotAPhotographError, RawReadError, read_raw
from mca.capture.simulated_shots import write_cr2
from mca.devices.sim.cr2 import Cr2Metadata

# --------------------------------------------------------------------------- the TIFF directory parser vs tifffile

# (tag, TIFF type, count, value): every TIFF 6.0 field type, single and multi-valued, small (inline) and large
EXTRA_TAGS = [
    (65000, 1, 1, (7,)),  # BYTE
    (65001, 1, 6, (1, 2, 3, 4, 5, 6)),
    (65002, 2, 0, "probe text"),  # ASCII
    (65003, 3, 1, (513,)),  # SHORT
    (65004, 3, 3, (1, 60000, 3)),
    (65005, 4, 1, (70000,)),  # LONG
    (65006, 4, 2, (4000000000, 5)),
    (65007, 5, 1, (28, 10)),  # RATIONAL
    (65008, 5, 3, (1, 2, 3, 4, 50, 8)),
    (65009, 6, 2, (-5, 7)),  # SBYTE
    (65010, 7, 5, b"\x00\x01\xfe\xff\x10"),  # UNDEFINED
    (65011, 8, 2, (-300, 300)),  # SSHORT
    (65012, 9, 2, (-70000, 70000)),  # SLONG
    (65013, 10, 2, (-1, 4, 9, -8)),  # SRATIONAL
    (65014, 11, 1, (0.25,)),  # FLOAT
    (65015, 11, 3, (1.5, -2.0, 1e-3)),
    (65016, 12, 1, (math.pi,)),  # DOUBLE
    (65017, 12, 2, (2.5, -1e10)),
]


def _expected(typ: int, value: object) -> object:
    """The value a reader gives, from the TIFF 6.0 definitions: rationals as numerator / denominator."""
    if typ in (5, 10):
        v = list(value)  # type: ignore[call-overload]
        return tuple(v[k] / v[k + 1] for k in range(0, len(v), 2))
    return value


@pytest.mark.parametrize("byteorder", ["<", ">"])
def test_every_field_type_is_read_as_tifffile_reads_it(tmp_path: Path, byteorder: str) -> None:
    path = tmp_path / "tags.tif"
    tifffile.imwrite(
        path,
        np.zeros((4, 4, 3), np.uint8),
        photometric="rgb",
        byteorder=byteorder,
        extratags=[(tag, typ, count, value, True) for tag, typ, count, value in EXTRA_TAGS],
    )
    with tifffile.TiffFile(path) as tf:
        theirs = {tag.code: tag.value for tag in tf.pages[0].tags}
    with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
        ours = raw._Tiff(m).ifds[0].tags
    for tag, typ, _count, value in EXTRA_TAGS:
        expected = _expected(typ, value)
        got = ours[tag]
        if typ == 2:
            assert got == theirs[tag] == expected
        elif typ == 7:
            assert got == bytes(theirs[tag]) == expected
        else:
            their = theirs[tag]
            their = tuple(their) if isinstance(their, (tuple, bytes)) else (their,)  # BYTE arrives as bytes
            if typ in (5, 10):  # tifffile keeps rationals as (numerator, denominator) pairs
                their = tuple(a / b for a, b in zip(their[0::2], their[1::2], strict=True))
            np.testing.assert_allclose(got, their, rtol=1e-6, err_msg=f"tag {tag}")
            np.testing.assert_allclose(got, expected, rtol=1e-6, err_msg=f"tag {tag}")
    assert ours[256] == (4,) and ours[257] == (4,)  # ImageWidth, ImageLength


def test_a_value_over_64_kib_is_located_not_copied(tmp_path: Path) -> None:
    """A hostile file cannot make the reader copy megabytes per tag: such values are only located (offset, count)."""
    blob = bytes(range(256)) * 300  # 76,800 bytes
    path = tmp_path / "big.tif"
    tifffile.imwrite(
        path, np.zeros((4, 4, 3), np.uint8), photometric="rgb", extratags=[(65020, 7, len(blob), blob, True)]
    )
    data = path.read_bytes()
    with tifffile.TiffFile(path) as tf:
        offset = tf.pages[0].tags[65020].valueoffset
    assert data[offset : offset + len(blob)] == blob
    ifd = raw._Tiff(data).ifds[0]
    assert 65020 not in ifd.tags
    assert ifd.raw[65020] == (7, len(blob), offset)


def _tiff_with_ifd_at_the_end(order: str = "<") -> bytes:
    """A TIFF 6.0 structure by hand: header, Make and Model strings, then IFD0 as the last bytes of the file."""
    make, model = b"Hand Made\0", b"Probe 7\0"
    values_at = 8
    ifd_at = values_at + len(make) + len(model)
    ifd_at += ifd_at % 2  # IFDs start on a word boundary
    head = (b"II*\0" if order == "<" else b"MM\0*") + struct.pack(order + "I", ifd_at)
    body = (make + model).ljust(ifd_at - 8, b"\0")
    entries = [
        struct.pack(order + "HHII", 0x010F, 2, len(make), values_at),
        struct.pack(order + "HHII", 0x0110, 2, len(model), values_at + len(make)),
        struct.pack(order + "HHI", 0x0112, 3, 1) + struct.pack(order + "H", 1) + b"\0\0",  # Orientation
    ]
    return head + body + struct.pack(order + "H", len(entries)) + b"".join(entries) + struct.pack(order + "I", 0)


@pytest.mark.parametrize("order", ["<", ">"])
def test_an_ifd_ending_exactly_at_the_end_of_the_file_is_read(order: str) -> None:
    data = _tiff_with_ifd_at_the_end(order)
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        theirs = {tag.code: tag.value for tag in tf.pages[0].tags}
    assert theirs[0x010F] == "Hand Made"
    meta = raw._metadata(raw._Tiff(data))
    assert (meta["make"], meta["model"]) == (theirs[0x010F], theirs[0x0110]) == ("Hand Made", "Probe 7")
    with pytest.raises(ValueError, match="cut off"):  # one byte fewer: the next-IFD offset is cut off
        raw._Tiff(data[:-1])


def _chunk(kind: bytes, body: bytes) -> bytes:
    import zlib

    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def _png_with_exif(exif: bytes) -> bytes:
    """A 16 x 16 RGB PNG (written by OpenCV) with a tEXt and an eXIf chunk (PNG 1.5) before its image data."""
    import cv2

    ok, png = cv2.imencode(".png", np.random.default_rng(3).integers(0, 255, (16, 16, 3), dtype=np.uint8))
    assert ok
    data = png.tobytes()
    at = data.find(b"IDAT") - 4
    text = _chunk(b"tEXt", b"Software\0" + b"a PNG writer that puts its name first " * 3)
    return data[:at] + text + _chunk(b"eXIf", exif) + data[at:]


def test_png_exif_whose_directory_fills_the_chunk(tmp_path: Path) -> None:
    path = tmp_path / "e.png"
    path.write_bytes(_png_with_exif(_tiff_with_ifd_at_the_end(">")))
    meta = read_raw(path).metadata
    assert (meta.make, meta.model) == ("Hand Made", "Probe 7")


# --------------------------------------------------------------------------- Canon maker notes


def _cr2_with_file_info(path: Path, words: dict[int, int]) -> Path:
    """A CR2 without Exif SubjectDistance (as a real 70D writes it) whose Canon FileInfo has `words` set."""
    path = write_cr2(
        path, np.full((32, 32), 3000, np.uint16), metadata=Cr2Metadata(focus_distance_m=1.0), preview=False
    )
    data = bytearray(path.read_bytes())
    at = data.find(struct.pack("<HH", 0x9206, 5))  # hide SubjectDistance under an unknown tag
    data[at : at + 2] = struct.pack("<H", 0x9999)
    entry = data.find(struct.pack("<HHI", 0x0093, 3, 26))  # FileInfo: 26 SHORTs, offset from the file's start
    (offset,) = struct.unpack("<I", data[entry + 8 : entry + 12])
    for word, value in words.items():
        struct.pack_into("<H", data, offset + 2 * word, value)
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize(
    ("words", "metres"),
    [
        ({20: 350, 21: 250}, 3.0),  # FocusDistanceUpper 3.5 m, Lower 2.5 m: the middle of the range
        ({20: 350, 21: 0}, 3.5),  # no lower bound: the upper one
        ({20: 65535, 21: 1200}, math.inf),  # focused at infinity
        ({19: 1, 20: 0, 21: 0}, None),  # LiveViewShooting on, no focus distance
    ],
)
def test_focus_distance_from_the_canon_file_info(tmp_path: Path, words: dict[int, int], metres: float | None) -> None:
    path = _cr2_with_file_info(tmp_path / "f.CR2", {19: 0, 20: 0, 21: 0, **words})
    got = read_raw(path).metadata.focus_distance_m
    assert got == (pytest.approx(metres) if metres is not None and math.isfinite(metres) else metres)


def test_the_file_info_words_are_those_exiftool_reads(tmp_path: Path) -> None:
    """ExifTool, the independent reader, sees the focus range at the words read above."""
    import json
    import subprocess

    from tools import require

    exiftool = require("exiftool", "Debian: apt-get install libimage-exiftool-perl")
    path = _cr2_with_file_info(tmp_path / "f.CR2", {19: 0, 20: 350, 21: 250})
    out = subprocess.run(
        [exiftool, "-j", "-n", "-FocusDistanceUpper", "-FocusDistanceLower", str(path)],
        capture_output=True,
        text=True,
        check=True,
    )
    tags = json.loads(out.stdout)[0]
    assert (tags["FocusDistanceUpper"], tags["FocusDistanceLower"]) == (3.5, 2.5)
    assert read_raw(path).metadata.focus_distance_m == pytest.approx((3.5 + 2.5) / 2)
    written = write_cr2(
        tmp_path / "w.CR2", np.full((32, 32), 3000, np.uint16), metadata=Cr2Metadata(focus_distance_m=2.25)
    )
    out = subprocess.run([exiftool, "-j", "-n", "-FocusDistanceUpper", str(written)], capture_output=True, text=True)
    assert json.loads(out.stdout)[0]["FocusDistanceUpper"] == 2.25  # what the CR2 writer puts there too


# --------------------------------------------------------------------------- header sizes and the pixel limit


@pytest.mark.parametrize("marker", [0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF])
def test_every_t81_frame_header_gives_the_size(marker: int) -> None:
    """ITU T.81 Table B.1: SOF0-3, 5-7, 9-11, 13-15 are frame headers: P, Y (lines), X (samples per line)."""
    sof = bytes([0xFF, marker]) + struct.pack(">HBHHB", 17, 8, 300, 200, 3) + b"\x01\x11\x00" * 3
    assert raw.image_size_px(b"\xff\xd8" + sof, "jpeg") == (200, 300)


@pytest.mark.parametrize("marker", [0xC4, 0xC8, 0xCC])  # DHT, JPG (reserved), DAC: not frame headers
def test_segments_that_are_not_frame_headers_give_no_size(marker: int) -> None:
    segment = bytes([0xFF, marker]) + struct.pack(">HBHHB", 17, 8, 300, 200, 3) + b"\x01\x11\x00" * 3
    assert raw.image_size_px(b"\xff\xd8" + segment + b"\xff\xd9" + b"\0" * 8, "jpeg") is None


def _png(height: int, width: int, shade: tuple[int, int, int] = (40, 90, 160)) -> bytes:
    import cv2

    image = np.empty((height, width, 3), np.uint8)
    image[...] = shade[::-1]
    image[0, 0] = (255, 255, 255)  # not one value everywhere
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()


def test_the_pixel_limit_comes_from_the_environment_and_is_inclusive(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(raw.MAX_MEGAPIXELS_ENV, raising=False)
    assert raw.current_policy().max_pixels == 100_000_000  # the README's default: 100 MP
    monkeypatch.setenv(raw.MAX_MEGAPIXELS_ENV, "0.001")  # 1000 pixels
    assert raw.current_policy().max_pixels == 1000
    (tmp_path / "at.png").write_bytes(_png(25, 40))  # exactly 1000 pixels
    assert read_raw(tmp_path / "at.png").planes.shape == (25, 40, 3)
    (tmp_path / "over.png").write_bytes(_png(25, 41))
    with pytest.raises(raw.ImageTooLargeError, match=r"declares 41 x 25 pixels"):
        read_raw(tmp_path / "over.png")
    for bad in ("0", "-3", "nan", "inf", "many"):
        monkeypatch.setenv(raw.MAX_MEGAPIXELS_ENV, bad)
        with pytest.raises(ValueError, match=raw.MAX_MEGAPIXELS_ENV):
            raw.current_policy()


def test_a_cr2_whose_directory_declares_too_many_pixels_is_refused_before_decoding(tmp_path: Path) -> None:
    mosaic = np.random.default_rng(2).integers(2048, 15000, size=(32, 48), dtype=np.uint16)
    path = write_cr2(tmp_path / "lie.CR2", mosaic, black_level=2048, white_level=15000)
    assert read_raw(path).planes.shape == (16, 24, 3)
    data = bytearray(path.read_bytes())
    for tag in (0x0100, 0x0101):  # IFD0's ImageWidth and ImageLength (LONG, count 1): 60000 each
        entry = struct.pack("<HHI", tag, 4, 1)
        at = data.find(entry)
        assert at > 0
        data[at + 8 : at + 12] = struct.pack("<I", 60000)
    path.write_bytes(bytes(data))
    with pytest.raises(raw.ImageTooLargeError, match=r"declares 60000 x 60000 pixels \(3600 MP\)"):
        read_raw(path)


# --------------------------------------------------------------------------- photograph mode


def test_photograph_mode_refuses_grey_but_takes_two_equal_channels(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    base = rng.uniform(0.1, 0.9, (20, 20)).astype(np.float32)
    other = rng.uniform(0.1, 0.9, (20, 20)).astype(np.float32)
    # two channels equal and the third different is colour (a scene lit in one filter colour): taken
    for planes in (
        np.stack([base, base, other], -1),
        np.stack([base, other, base], -1),
        np.stack([other, base, base], -1),
    ):
        raw.check_photograph_planes(Path("x.tiff"), planes)
    with pytest.raises(NotAPhotographError, match="three identical colour channels"):
        raw.check_photograph_planes(Path("x.tiff"), np.stack([base] * 3, -1))
    with pytest.raises(NotAPhotographError, match="one value in every pixel"):
        raw.check_photograph_planes(Path("x.tiff"), np.full((20, 20, 3), 0.5, np.float32))
    # the same through read_raw: a 16-bit TIFF whose red equals its green
    codes = np.round(np.stack([base, base, other], -1) * 65535).astype(np.uint16)
    tifffile.imwrite(tmp_path / "rg.tiff", codes, photometric="rgb")
    with raw.read_policy(photograph=True):
        np.testing.assert_allclose(read_raw(tmp_path / "rg.tiff").planes, codes / 65535.0, atol=1e-7)


def test_grey_and_alpha_tiff_is_read_as_three_equal_planes(tmp_path: Path) -> None:
    grey = np.arange(12 * 20, dtype=np.uint16).reshape(12, 20) * 200
    alpha = np.full_like(grey, 65535)
    tifffile.imwrite(tmp_path / "ga.tiff", np.stack([grey, alpha], -1), photometric="minisblack", extrasamples=[2])
    planes = read_raw(tmp_path / "ga.tiff").planes
    assert planes.shape == (12, 20, 3)
    for c in range(3):
        np.testing.assert_allclose(planes[..., c], grey / 65535.0, atol=1e-7)
    with raw.read_policy(photograph=True), pytest.raises(NotAPhotographError, match="two channels"):
        read_raw(tmp_path / "ga.tiff")


# --------------------------------------------------------------------------- DNG variants, decoded by LibRaw

_IDENTITY_MATRIX = (10000, 1, 0, 1, 0, 1, 0, 1, 10000, 1, 0, 1, 0, 1, 0, 1, 10000, 1)


def _dng_tags(model: str) -> list[tuple]:
    return [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion (DNGBackwardVersion is optional, DNG 1.4 p. 20)
        (50708, "s", 0, model, True),  # UniqueCameraModel
        (50721, "2i", 9, _IDENTITY_MATRIX, True),  # ColorMatrix1
    ]


def test_a_linear_dng_gives_full_resolution_planes(tmp_path: Path) -> None:
    """A LinearRaw DNG (three samples per pixel): no mosaic, so planes are each pixel's (value - black) / range."""
    rgb = np.random.default_rng(1).integers(300, 4000, size=(32, 48, 3), dtype=np.uint16)
    path = tmp_path / "linear.dng"
    tifffile.imwrite(
        path,
        rgb,
        photometric=34892,  # LinearRaw
        extratags=[*_dng_tags("Probe Linear"), (50714, "H", 1, (256,), True), (50717, "H", 1, (4095,), True)],
    )
    frame = read_raw(path)
    assert frame.source_format == "dng" and not frame.half_resolution and frame.metadata.cfa_pattern is None
    expected = np.clip((rgb - 256.0) / (4095 - 256), 0.0, 1.0)
    np.testing.assert_allclose(frame.planes, expected, atol=1e-6)
    np.testing.assert_array_equal(frame.demosaiced_rgb(), frame.planes)


def _mosaic_dng(path: Path, blacks: tuple[int, int, int, int], white: int, fraction: float) -> np.ndarray:
    """An RGGB DNG with a black level per CFA site (BlackLevelRepeatDim 2 x 2), each site at `fraction` of its range."""
    grid = np.array(blacks).reshape(2, 2)  # R G / G B sites
    mosaic = np.zeros((48, 64), np.uint16)
    for dy in range(2):
        for dx in range(2):
            mosaic[dy::2, dx::2] = round(grid[dy, dx] + fraction * (white - grid[dy, dx]))
    tifffile.imwrite(
        path,
        mosaic,
        photometric=32803,  # CFA
        extratags=[
            *_dng_tags("Probe Black"),
            (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
            (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern RGGB
            (50713, "H", 2, (2, 2), True),  # BlackLevelRepeatDim
            (50714, "H", 4, blacks, True),  # BlackLevel, row by row
            (50717, "H", 1, (white,), True),
        ],
    )
    return mosaic


def test_a_black_level_per_cfa_site_is_subtracted_per_colour(tmp_path: Path) -> None:
    path = tmp_path / "black.dng"
    _mosaic_dng(path, (100, 300, 300, 500), 4000, 0.5)  # R 100, both greens 300, B 500
    frame = read_raw(path)
    assert frame.half_resolution and frame.metadata.cfa_pattern == "RGGB"
    assert sorted(frame.metadata.black_level or ()) == [100.0, 300.0, 300.0, 500.0]
    np.testing.assert_allclose(frame.planes, 0.5, atol=2e-4)  # every colour at half its own range
    rgb = frame.demosaiced_rgb()
    assert rgb.shape == (48, 64, 3)
    np.testing.assert_allclose(rgb[4:-4, 4:-4], 0.5, atol=2e-3)


def test_a_dng_is_recognised_by_its_version_tag_whatever_its_name(tmp_path: Path) -> None:
    """DNG 1.4: DNGVersion alone marks a DNG. Named .tif or .CR2 it is still decoded as a raw, not an RGB TIFF."""
    mosaic = _mosaic_dng(tmp_path / "a.dng", (256, 256, 256, 256), 4095, 0.25)
    expected = read_raw(tmp_path / "a.dng").planes
    np.testing.assert_allclose(expected, (mosaic[0, 0] - 256) / (4095 - 256), atol=1e-6)
    for name in ("a.tif", "a.CR2"):
        (tmp_path / name).write_bytes((tmp_path / "a.dng").read_bytes())
        frame = read_raw(tmp_path / name)
        assert frame.source_format == "dng" and frame.half_resolution
        np.testing.assert_array_equal(frame.planes, expected)
    plain = tmp_path / "plain.tif"  # the same structure without DNGVersion: an RGB TIFF
    tifffile.imwrite(plain, np.full((8, 8, 3), 1000, np.uint16), photometric="rgb")
    assert read_raw(plain).source_format == "tiff"


def test_a_raw_truncated_inside_its_image_data_is_reported_as_truncated(tmp_path: Path) -> None:
    mosaic = np.random.default_rng(6).integers(2048, 15000, size=(64, 96), dtype=np.uint16)
    path = write_cr2(tmp_path / "t.CR2", mosaic, black_level=2048, white_level=15000)
    data = path.read_bytes()
    cut = tmp_path / "cut.CR2"
    cut.write_bytes(data[: len(data) - 64])
    with pytest.raises(RawReadError, match=r"is truncated: its image data runs to byte \d+ but the file has only"):
        read_raw(cut)
    dng = tmp_path / "cut.dng"
    _mosaic_dng(tmp_path / "whole.dng", (256, 256, 256, 256), 4095, 0.5)
    dng.write_bytes((tmp_path / "whole.dng").read_bytes()[:-100])
    with pytest.raises(RawReadError, match="is truncated"):
        read_raw(dng)
