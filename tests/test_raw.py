"""read_raw: planes against independent numpy references, metadata round trips, every input format, and every bad input."""

from __future__ import annotations

import math
import os
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

import mca.capture.raw as raw_module
from mca.capture.raw import RawFrame, RawReadError, UnknownBodyError, read_raw, require_known_body
from mca.capture.simulated_shots import write_cr2
from mca.devices.sim.cr2 import EOS_70D_ACTIVE_HEIGHT_PX, EOS_70D_ACTIVE_WIDTH_PX, Cr2Metadata

BLACK = 2048
WHITE = 15000
PITCH_70D_MM = 22.5 / 5472  # sensor width / active columns


def _mosaic(height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 1 << 14, size=(height, width), dtype=np.uint16)


def _reference_planes(mosaic: np.ndarray, black: float, white: float) -> np.ndarray:
    """R, mean of the two greens, B of an RGGB mosaic, computed directly in float64."""
    m = mosaic.astype(np.float64)
    span = white - black
    r = (m[0::2, 0::2] - black) / span
    g = ((m[0::2, 1::2] - black) + (m[1::2, 0::2] - black)) / (2 * span)
    b = (m[1::2, 1::2] - black) / span
    return np.clip(np.stack([r, g, b], axis=-1), 0.0, 1.0)


def _srgb_decode(code: float) -> float:
    """IEC 61966-2-1, written out independently of capture.raw."""
    return code / 12.92 if code <= 0.04045 else ((code + 0.055) / 1.055) ** 2.4


@pytest.fixture()
def small_cr2(tmp_path: Path) -> tuple[Path, np.ndarray, Cr2Metadata]:
    mosaic = _mosaic(64, 96, seed=11)
    meta = Cr2Metadata(
        iso=400,
        exposure_time_s=1 / 60,
        f_number=5.6,
        focal_length_mm=35.0,
        capture_time=datetime(2023, 5, 6, 7, 8, 9),
        lens_model="EF-S18-55mm f/3.5-5.6 IS STM",
        focus_distance_m=1.25,
    )
    return (
        write_cr2(tmp_path / "IMG_0001.CR2", mosaic, black_level=BLACK, white_level=WHITE, metadata=meta),
        mosaic,
        meta,
    )


# ----------------------------------------------------------------------------- CR2


def test_cr2_planes_equal_an_independent_computation_from_the_mosaic(small_cr2) -> None:
    path, mosaic, _ = small_cr2
    frame = read_raw(path)
    assert frame.source_format == "cr2"
    assert frame.half_resolution
    assert frame.planes.dtype == np.float32 and frame.planes.shape == (32, 48, 3)
    np.testing.assert_allclose(frame.planes, _reference_planes(mosaic, BLACK, WHITE), atol=1e-6)
    assert frame.pixel_pitch_mm == pytest.approx(2 * PITCH_70D_MM)
    assert frame.path == path


def test_cr2_metadata_round_trips(small_cr2) -> None:
    path, _, _meta = small_cr2
    m = read_raw(path).metadata
    assert (m.make, m.model) == ("Canon", "Canon EOS 70D")
    assert m.iso == 400
    assert m.exposure_time_s == pytest.approx(1 / 60)
    assert m.f_number == pytest.approx(5.6)
    assert m.focal_length_mm == pytest.approx(35.0)
    assert m.capture_time == datetime(2023, 5, 6, 7, 8, 9)
    assert m.lens_model == "EF-S18-55mm f/3.5-5.6 IS STM"
    assert m.focus_distance_m == pytest.approx(1.25)
    assert m.photosite_pitch_mm == pytest.approx(PITCH_70D_MM)
    assert m.black_level == (BLACK,) * 4
    assert m.white_level == WHITE
    assert m.cfa_pattern == "RGGB"


def test_focus_distance_falls_back_to_canon_file_info(tmp_path: Path) -> None:
    # A real 70D writes no Exif SubjectDistance; the maker-note FileInfo has it in cm.
    path = write_cr2(tmp_path / "f.CR2", _mosaic(32, 32), metadata=Cr2Metadata(focus_distance_m=3.0))
    data = bytearray(path.read_bytes())
    at = data.find((0x9206).to_bytes(2, "little") + (5).to_bytes(2, "little"))
    data[at : at + 2] = (0x9999).to_bytes(2, "little")  # hide SubjectDistance under an unknown tag
    path.write_bytes(bytes(data))
    assert read_raw(path).metadata.focus_distance_m == pytest.approx(3.0)


def test_demosaiced_rgb_of_a_flat_grey_mosaic_is_flat(tmp_path: Path) -> None:
    level = 6000
    path = write_cr2(tmp_path / "grey.CR2", np.full((64, 96), level, np.uint16), black_level=BLACK, white_level=WHITE)
    frame = read_raw(path)
    rgb = frame.demosaiced_rgb()
    assert rgb.shape == (64, 96, 3) and rgb.dtype == np.float32
    expected = (level - BLACK) / (WHITE - BLACK)
    np.testing.assert_allclose(rgb[4:-4, 4:-4], expected, atol=2e-4)
    np.testing.assert_allclose(frame.planes, expected, atol=1e-6)


@pytest.mark.slow
def test_full_size_cr2_planes(tmp_path: Path) -> None:
    mosaic = _mosaic(EOS_70D_ACTIVE_HEIGHT_PX, EOS_70D_ACTIVE_WIDTH_PX, seed=7)
    path = write_cr2(tmp_path / "IMG_0002.CR2", mosaic, black_level=BLACK, white_level=WHITE, preview=False)
    frame = read_raw(path)
    assert frame.planes.shape == (1824, 2736, 3)
    assert float(np.max(np.abs(frame.planes - _reference_planes(mosaic, BLACK, WHITE)))) < 1e-6


def test_require_known_body(small_cr2, tmp_path: Path) -> None:
    frame = read_raw(small_cr2[0])
    assert require_known_body(frame).model == "Canon EOS 70D"
    with pytest.raises(UnknownBodyError, match="Canon EOS 70D"):
        require_known_body(frame, known=["Canon EOS 80D"])


def test_raw_from_a_camera_without_a_profile(tmp_path: Path) -> None:
    meta = Cr2Metadata(model="Canon EOS 9000Q")
    path = write_cr2(tmp_path / "other.CR2", _mosaic(32, 48), metadata=meta)
    frame = read_raw(path)  # readable: the caller decides
    assert frame.metadata.model == "Canon EOS 9000Q"
    assert frame.metadata.photosite_pitch_mm is None and frame.pixel_pitch_mm is None
    with pytest.raises(RawReadError) as err:
        require_known_body(frame)
    assert "Canon EOS 9000Q" in str(err.value) and "other.CR2" in str(err.value)
    assert "capture/sensors.py" in err.value.advice


# ----------------------------------------------------------------------------- DNG


def test_dng_bayer_planes(tmp_path: Path) -> None:
    mosaic = np.random.default_rng(4).integers(0, 4096, size=(64, 96), dtype=np.uint16)
    path = tmp_path / "x.dng"
    tifffile.imwrite(
        path,
        mosaic,
        photometric=32803,  # CFA
        extratags=[
            (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
            (50708, "s", 0, "Canon EOS 70D", True),  # UniqueCameraModel
            (271, "s", 0, "Canon", True),
            (272, "s", 0, "Canon EOS 70D", True),
            (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
            (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern RGGB
            (50714, "H", 1, (256,), True),  # BlackLevel
            (50717, "H", 1, (4095,), True),  # WhiteLevel
            (50721, "2i", 9, (10000, 1, 0, 1, 0, 1, 0, 1, 10000, 1, 0, 1, 0, 1, 0, 1, 10000, 1), True),
            (50778, "H", 1, (21,), True),
        ],
    )
    frame = read_raw(path)
    assert frame.source_format == "dng"
    np.testing.assert_allclose(frame.planes, _reference_planes(mosaic, 256, 4095), atol=1e-6)
    assert frame.pixel_pitch_mm == pytest.approx(2 * PITCH_70D_MM)


# ----------------------------------------------------------------------------- RGB images

_CODES = np.arange(256, dtype=np.uint8)


def _code_image() -> np.ndarray:
    """(16, 16, 3) uint8 RGB holding every 8-bit code once per channel, channels shuffled apart."""
    r = _CODES.reshape(16, 16)
    return np.stack([r, r[::-1], r.T], axis=-1)


@pytest.mark.parametrize("suffix, fmt", [(".png", "png"), (".ppm", "ppm")])
def test_8bit_lossless_images_are_linearised_with_the_srgb_formula(tmp_path: Path, suffix: str, fmt: str) -> None:
    rgb = _code_image()
    path = tmp_path / f"img{suffix}"
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    frame = read_raw(path)
    expected = np.vectorize(lambda c: _srgb_decode(c / 255.0))(rgb.astype(np.float64))
    assert frame.source_format == fmt and not frame.half_resolution
    assert frame.planes.shape == (16, 16, 3)
    np.testing.assert_allclose(frame.planes, expected, atol=1e-6)
    assert frame.pixel_pitch_mm is None
    np.testing.assert_array_equal(frame.demosaiced_rgb(), frame.planes)


def test_jpeg_is_linearised_with_the_srgb_formula(tmp_path: Path) -> None:
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 120, 40  # flat: JPEG reproduces it to within 1 code
    path = tmp_path / "img.jpg"
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 100])
    frame = read_raw(path)
    for c, code in enumerate((200, 120, 40)):
        lo, hi = _srgb_decode((code - 1) / 255) - 1e-6, _srgb_decode((code + 1) / 255) + 1e-6
        assert lo <= float(frame.planes[..., c].min()) and float(frame.planes[..., c].max()) <= hi
    assert frame.source_format == "jpeg"


def test_16bit_tiff_is_taken_as_linear(tmp_path: Path) -> None:
    rgb = np.random.default_rng(5).integers(0, 65536, size=(20, 30, 3), dtype=np.uint16)
    path = tmp_path / "lin.tif"
    tifffile.imwrite(path, rgb, photometric="rgb")
    frame = read_raw(path)
    assert frame.source_format == "tiff"
    np.testing.assert_allclose(frame.planes, rgb / 65535.0, atol=1e-7)


def test_8bit_tiff_and_grey_png_are_srgb(tmp_path: Path) -> None:
    rgb = _code_image()
    tifffile.imwrite(tmp_path / "s.tif", rgb, photometric="rgb")
    expected = np.vectorize(lambda c: _srgb_decode(c / 255.0))(rgb.astype(np.float64))
    np.testing.assert_allclose(read_raw(tmp_path / "s.tif").planes, expected, atol=1e-6)
    grey = _CODES.reshape(16, 16)
    assert cv2.imwrite(str(tmp_path / "g.png"), grey)
    planes = read_raw(tmp_path / "g.png").planes
    for c in range(3):
        np.testing.assert_allclose(planes[..., c], expected[..., 0], atol=1e-6)


def test_16bit_png_is_srgb(tmp_path: Path) -> None:
    codes = np.array([[0, 1000, 30000, 65535]], dtype=np.uint16)
    assert cv2.imwrite(str(tmp_path / "d.png"), np.repeat(codes[..., None], 3, axis=-1))
    planes = read_raw(tmp_path / "d.png").planes
    expected = [_srgb_decode(c / 65535) for c in codes[0]]
    np.testing.assert_allclose(planes[0, :, 0], expected, atol=1e-6)


# ----------------------------------------------------------------------------- bad input


def _assert_names_file(err: RawReadError, path: Path, *words: str) -> None:
    text = str(err)
    assert str(path) in text
    assert err.advice, "the error must say what to do"
    for w in words:
        assert w in text.lower()
    assert err.__cause__ is None and (err.__context__ is None or err.__suppress_context__), "no chained traceback"


def test_truncated_cr2(small_cr2, tmp_path: Path) -> None:
    data = small_cr2[0].read_bytes()
    for cut in (len(data) // 2, len(data) - 10, 200, 12):
        path = tmp_path / f"cut{cut}.CR2"
        path.write_bytes(data[:cut])
        with pytest.raises(RawReadError) as err:
            read_raw(path)
        _assert_names_file(err.value, path)
        assert any(w in str(err.value) for w in ("truncated", "damaged", "cut off")), str(err.value)


def test_jpeg_renamed_to_cr2(tmp_path: Path) -> None:
    path = tmp_path / "IMG_0003.CR2"
    _ok, jpg = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    path.write_bytes(jpg.tobytes())
    with pytest.raises(RawReadError) as err:
        read_raw(path)
    _assert_names_file(err.value, path, "jpeg", "not a camera raw")


@pytest.mark.parametrize(
    "content", [b"", b"\x00" * 100, b"hello, not a raw file at all"], ids=["empty", "zeros", "text"]
)
def test_empty_or_garbage_cr2(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.CR2"
    path.write_bytes(content)
    with pytest.raises(RawReadError) as err:
        read_raw(path)
    _assert_names_file(err.value, path)
    if not content:
        assert "empty" in str(err.value)


def test_garbage_with_unknown_extension(tmp_path: Path) -> None:
    path = tmp_path / "notes.bin"
    path.write_bytes(b"\x01\x02\x03 not an image")
    with pytest.raises(RawReadError) as err:
        read_raw(path)
    _assert_names_file(err.value, path, "not a format")


def test_directory_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RawReadError) as err:
        read_raw(tmp_path)
    _assert_names_file(err.value, tmp_path, "folder")
    missing = tmp_path / "nope.CR2"
    with pytest.raises(RawReadError) as err:
        read_raw(missing)
    _assert_names_file(err.value, missing, "no such file")


def test_unreadable_file(small_cr2, monkeypatch: pytest.MonkeyPatch) -> None:
    path = small_cr2[0]
    if os.geteuid() == 0:
        # root reads any file whatever its mode, so deny the open itself.
        def deny(p: Path):
            raise PermissionError(13, "Permission denied", str(p))

        monkeypatch.setattr(raw_module, "_open_binary", deny)
    else:
        path.chmod(0)
    try:
        with pytest.raises(RawReadError) as err:
            read_raw(path)
    finally:
        path.chmod(0o644)
    _assert_names_file(err.value, path, "permission")


def test_corrupt_raw_data_is_reported_not_raised_from_libraw(small_cr2, tmp_path: Path) -> None:
    data = bytearray(small_cr2[0].read_bytes())
    sof = data.find(b"\xff\xc3")
    data[sof - 200 : sof + 12] = b"\x00" * 212  # wipe the Huffman table and frame header
    path = tmp_path / "corrupt.CR2"
    path.write_bytes(bytes(data))
    try:
        frame = read_raw(path)
    except RawReadError as err:
        _assert_names_file(err, path)
    else:  # LibRaw may still decode something; it must at least be a well-formed frame
        assert isinstance(frame, RawFrame) and np.all(np.isfinite(frame.planes))


def test_srgb_formula_constants() -> None:
    from mca.capture.raw import srgb_to_linear

    codes = np.array([0.0, 0.04045, 0.5, 1.0])
    np.testing.assert_allclose(srgb_to_linear(codes), [_srgb_decode(c) for c in codes], rtol=1e-6)
    assert math.isclose(float(srgb_to_linear(np.array([0.04045]))[0]), 0.04045 / 12.92, rel_tol=1e-6)
