"""The photograph reader against files written by independent writers: Pillow writes JPEG, PNG and PPM with
Exif tags set here (Exif 2.3 tag numbers), tifffile writes TIFF; the expected metadata and sizes are the
values the test wrote, converted with the Exif definitions (FocalPlaneXResolution is pixels per unit,
unit 2 = inch, 3 = cm, 4 = mm).
"""

from __future__ import annotations

import math
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, TiffImagePlugin

from mca.capture import raw
from mca.capture.raw import RawReadError, read_raw


def picture(height: int = 30, width: int = 44) -> Image.Image:
    rng = np.random.default_rng(1)
    return Image.fromarray(rng.integers(20, 235, size=(height, width, 3), dtype=np.uint8))


def exif(make: str = "ACME", model: str = "Probe 1", unit: int = 3, resolution: float = 2500.0) -> Image.Exif:
    ex = Image.Exif()
    ex[0x010F] = make
    ex[0x0110] = model
    ex[0x0132] = "2023:01:02 03:04:05"
    ifd = ex.get_ifd(0x8769)
    ifd[0x9003] = "2024:05:01 10:15:02"  # DateTimeOriginal wins over DateTime
    ifd[0x829D] = TiffImagePlugin.IFDRational(Fraction(28, 10))  # FNumber
    ifd[0x829A] = TiffImagePlugin.IFDRational(Fraction(1, 250))  # ExposureTime
    ifd[0x8827] = 400  # ISO
    ifd[0x920A] = TiffImagePlugin.IFDRational(Fraction(50, 1))  # FocalLength
    ifd[0x9206] = TiffImagePlugin.IFDRational(Fraction(3, 2))  # SubjectDistance, m
    ifd[0xA434] = "Macro 50"  # LensModel
    ifd[0xA20E] = TiffImagePlugin.IFDRational(Fraction(resolution).limit_denominator(1000))  # FocalPlaneXResolution
    ifd[0xA210] = unit  # FocalPlaneResolutionUnit
    return ex


@pytest.mark.parametrize(("unit", "mm_per_unit"), [(2, 25.4), (3, 10.0), (4, 1.0)])
def test_jpeg_exif_metadata(tmp_path: Path, unit: int, mm_per_unit: float) -> None:
    path = tmp_path / "a.jpg"
    picture().save(path, exif=exif(unit=unit), quality=95)
    frame = read_raw(path)
    meta = frame.metadata
    assert frame.source_format == "jpeg" and frame.planes.shape == (30, 44, 3)
    assert (meta.make, meta.model, meta.lens_model) == ("ACME", "Probe 1", "Macro 50")
    assert meta.capture_time == datetime(2024, 5, 1, 10, 15, 2)
    assert meta.f_number == pytest.approx(2.8)
    assert meta.exposure_time_s == pytest.approx(1 / 250)
    assert meta.iso == 400
    assert meta.focal_length_mm == pytest.approx(50.0)
    assert meta.focus_distance_m == pytest.approx(1.5)
    assert meta.photosite_pitch_mm == pytest.approx(mm_per_unit / 2500.0)
    assert frame.pixel_pitch_mm == pytest.approx(mm_per_unit / 2500.0)


def test_a_known_body_takes_its_pitch_from_the_data_sheet(tmp_path: Path) -> None:
    path = tmp_path / "b.jpg"
    picture().save(path, exif=exif(make="Canon", model="Canon EOS 70D", unit=4, resolution=100.0))
    assert read_raw(path).metadata.photosite_pitch_mm == pytest.approx(22.5 / 5472)


def test_png_exif_and_missing_metadata(tmp_path: Path) -> None:
    path = tmp_path / "c.png"
    picture().save(path, exif=exif())
    meta = read_raw(path).metadata
    assert (meta.make, meta.model, meta.iso) == ("ACME", "Probe 1", 400)
    plain = tmp_path / "d.png"
    picture().save(plain)
    bare = read_raw(plain)
    assert bare.metadata.make is None and bare.metadata.capture_time is None and bare.pixel_pitch_mm is None
    # DateTime (IFD0) when there is no DateTimeOriginal; a malformed time is no time
    ex = Image.Exif()
    ex[0x0132] = "2023:01:02 03:04:05"
    picture().save(tmp_path / "e.jpg", exif=ex)
    assert read_raw(tmp_path / "e.jpg").metadata.capture_time == datetime(2023, 1, 2, 3, 4, 5)
    ex[0x0132] = "yesterday"
    picture().save(tmp_path / "f.jpg", exif=ex)
    assert read_raw(tmp_path / "f.jpg").metadata.capture_time is None


@pytest.mark.parametrize(
    ("fmt", "suffix", "options"),
    [("JPEG", ".jpg", {}), ("JPEG", ".jpg", {"progressive": True}), ("PNG", ".png", {}), ("PPM", ".ppm", {})],
)
def test_declared_sizes_are_read_from_the_headers(tmp_path: Path, fmt: str, suffix: str, options: dict) -> None:
    path = tmp_path / f"s{suffix}"
    picture(37, 53).save(path, format=fmt, **options)
    data = path.read_bytes()
    kind = {".jpg": "jpeg", ".png": "png", ".ppm": "ppm"}[suffix]
    assert raw.image_size_px(data, kind) == (53, 37)
    assert read_raw(path).planes.shape == (37, 53, 3)


def test_header_sizes_of_odd_files() -> None:
    assert raw.image_size_px(b"P6\n# a comment 99 99\n640 480\n255\n", "ppm") == (640, 480)
    assert raw.image_size_px(b"P6 640\n480 255\n", "ppm") == (640, 480)
    assert raw.image_size_px(b"P6\nwide 480\n255\n", "ppm") is None
    assert raw.image_size_px(b"P6\n640\n", "ppm") is None
    assert raw.image_size_px(b"\x89PNG\r\n\x1a\n" + b"\x00" * 8, "png") is None
    # a JPEG with padding 0xFF bytes and an RST marker before its frame header
    sof = b"\xff\xc0\x00\x11\x08" + (300).to_bytes(2, "big") + (200).to_bytes(2, "big") + b"\x03" + b"\x00" * 9
    assert raw.image_size_px(b"\xff\xd8\xff\xff\xd0" + sof, "jpeg") == (200, 300)
    app = b"\xff\xe0\x00\x04ab"
    assert raw.image_size_px(b"\xff\xd8" + app + sof, "jpeg") == (200, 300)
    assert raw.image_size_px(b"\xff\xd8\xff\xda\x00\x04ab" + sof, "jpeg") is None  # scan before any frame
    assert raw.image_size_px(b"\xff\xd8\xff\xe0\x00\x01" + sof, "jpeg") is None  # a length below 2
    assert raw.image_size_px(b"\xff\xd8" + sof[:8], "jpeg") is None
    assert raw.image_size_px(b"anything", "tiff") is None


def test_magic_bytes_decide_the_kind() -> None:
    assert raw._magic_kind(b"\xff\xd8\xff\xe0") == "jpeg"
    assert raw._magic_kind(b"\x89PNG\r\n\x1a\n") == "png"
    assert raw._magic_kind(b"P6\n") == "ppm" and raw._magic_kind(b"P5 ") == "ppm"
    assert raw._magic_kind(b"P6x") is None and raw._magic_kind(b"P6") is None
    assert raw._magic_kind(b"II*\x00\x10\x00\x00\x00CR\x02\x00") == "cr2"
    assert raw._magic_kind(b"MM\x00*\x00\x00\x00\x08\x00\x00") == "tiff-structure"
    assert raw._magic_kind(b"\x00\x00\x00\x18ftypcrx \x00") == "cr3"
    assert raw._magic_kind(b"GIF89a") is None


def test_a_jpeg_named_as_a_raw_is_refused_with_advice(tmp_path: Path) -> None:
    path = tmp_path / "x.CR2"
    picture().save(path, format="JPEG")
    with pytest.raises(RawReadError, match=r"rename this one to \.jpg"):
        read_raw(path)
    png = tmp_path / "y.CR2"
    picture().save(png, format="PNG")
    with pytest.raises(RawReadError, match=r"rename this one to \.png"):
        read_raw(png)


def test_tiff_samples_of_each_kind_are_linearised_as_their_kind_says(tmp_path: Path) -> None:
    import tifffile

    values16 = np.array([[[0, 32768, 65535]]], np.uint16).repeat(4, 0).repeat(4, 1)
    tifffile.imwrite(tmp_path / "a.tiff", values16, photometric="rgb")
    got = read_raw(tmp_path / "a.tiff").planes
    np.testing.assert_allclose(got[0, 0], [0.0, 32768 / 65535, 1.0], atol=1e-6)  # 16-bit: linear
    values8 = np.array([[[0, 128, 255]]], np.uint8).repeat(4, 0).repeat(4, 1)
    tifffile.imwrite(tmp_path / "b.tiff", values8, photometric="rgb")
    srgb = 128 / 255
    expected = ((srgb + 0.055) / 1.055) ** 2.4  # IEC 61966-2-1
    np.testing.assert_allclose(read_raw(tmp_path / "b.tiff").planes[0, 0], [0.0, expected, 1.0], atol=1e-5)
    floats = np.array([[[-0.5, 0.25, 2.0]]], np.float32).repeat(4, 0).repeat(4, 1)
    tifffile.imwrite(tmp_path / "c.tiff", floats, photometric="rgb")
    np.testing.assert_allclose(read_raw(tmp_path / "c.tiff").planes[0, 0], [0.0, 0.25, 1.0])
    planar = np.stack([np.full((4, 4), v, np.uint16) for v in (100, 200, 300)])
    tifffile.imwrite(tmp_path / "d.tiff", planar, photometric="rgb", planarconfig="separate")
    np.testing.assert_allclose(read_raw(tmp_path / "d.tiff").planes[0, 0], np.array([100, 200, 300]) / 65535, rtol=1e-6)
    assert not math.isnan(float(read_raw(tmp_path / "c.tiff").planes.sum()))


def test_planes_from_memory_must_be_three_colour_planes() -> None:
    from mca.capture.raw import RawFrame

    frame = RawFrame.from_planes(np.zeros((4, 6, 3)), pixel_pitch_mm=0.008, name="x")
    assert frame.planes.dtype == np.float32 and frame.pixel_pitch_mm == 0.008 and frame.source_format == "array"
    for shape in ((4, 6), (4, 6, 4), (4, 6, 1)):
        with pytest.raises(ValueError, match=r"planes must be \(H, W, 3\)"):
            RawFrame.from_planes(np.zeros(shape))


def test_a_file_too_large_for_the_pixel_limit_says_its_size(tmp_path: Path) -> None:
    path = tmp_path / "huge.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100 << 20))  # 100 MiB
    with raw.read_policy(max_megapixels=1.0), pytest.raises(raw.ImageTooLargeError, match="is 100 MiB, more than"):
        read_raw(path)


def test_photograph_mode_refuses_float_samples_that_are_not_finite(tmp_path: Path) -> None:
    import tifffile

    nan = np.full((4, 4, 3), np.nan, np.float32)
    tifffile.imwrite(tmp_path / "nan.tiff", nan, photometric="rgb")
    with raw.read_policy(photograph=True), pytest.raises(raw.NotAPhotographError, match="no finite sample"):
        read_raw(tmp_path / "nan.tiff")
    ok = np.random.default_rng(2).uniform(0.25, 0.75, (32, 32, 3)).astype(np.float32)
    tifffile.imwrite(tmp_path / "ok.tiff", ok, photometric="rgb")
    with raw.read_policy(photograph=True):
        np.testing.assert_allclose(read_raw(tmp_path / "ok.tiff").planes, ok, atol=1e-6)
