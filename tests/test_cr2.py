"""CR2 writer: LibRaw (through rawpy) and exiftool, as independent readers, must see exactly what was written."""

from __future__ import annotations

import json
import subprocess
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import rawpy
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tools import require

from mca.capture.simulated_shots import write_cr2
from mca.devices.sim.cr2 import (
    EOS_70D_ACTIVE_HEIGHT_PX,
    EOS_70D_ACTIVE_WIDTH_PX,
    Cr2Metadata,
    _huffman_code_lengths,
    cr2_bytes,
    encode_lossless_jpeg,
    raw_frame_geometry,
)

BLACK = 2048
WHITE = 15000


def _random_mosaic(height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 1 << 14, size=(height, width), dtype=np.uint16)


def _libraw_view(path: Path) -> tuple[np.ndarray, object, list[int], list[int], bytes, np.ndarray]:
    with rawpy.imread(str(path)) as raw:
        return (
            raw.raw_image_visible.copy(),
            raw.sizes,
            list(raw.black_level_per_channel),
            list(raw.camera_white_level_per_channel),
            raw.color_desc,
            raw.raw_pattern.copy(),
        )


@pytest.mark.parametrize("height, width", [(22, 22), (64, 96), (96, 64), (130, 202), (200, 780)])
def test_small_random_mosaic_round_trips_bit_exactly_through_libraw(tmp_path: Path, height: int, width: int) -> None:
    mosaic = _random_mosaic(height, width, seed=height * width)
    path = write_cr2(tmp_path / "small.CR2", mosaic, black_level=BLACK, white_level=WHITE)
    visible, sizes, black, white, desc, pattern = _libraw_view(path)
    assert np.array_equal(visible, mosaic)
    assert (sizes.width, sizes.height) == (width, height)
    assert black == [BLACK] * 4
    assert white == [WHITE] * 4
    # RGGB: LibRaw colour indices R=0, G=1, B=2, G2=3 over the visible area.
    assert desc == b"RGBG"
    assert pattern.tolist() == [[0, 1], [3, 2]]


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    half_height=st.integers(11, 40),
    half_width=st.integers(11, 60),
    bits=st.integers(1, 14),
    seed=st.integers(0, 2**32 - 1),
)
def test_any_even_size_and_bit_depth_round_trips(
    tmp_path: Path, half_height: int, half_width: int, bits: int, seed: int
) -> None:
    height, width = 2 * half_height, 2 * half_width
    if width + 84 > 4 * (height + 50):
        return  # refused as too elongated (tested separately)
    mosaic = np.random.default_rng(seed).integers(0, 1 << bits, size=(height, width), dtype=np.uint16)
    path = write_cr2(tmp_path / "h.CR2", mosaic, preview=False)
    visible, sizes, *_ = _libraw_view(path)
    assert (sizes.width, sizes.height) == (width, height)
    assert np.array_equal(visible, mosaic)


@pytest.mark.slow
def test_full_size_70d_mosaic_round_trips_with_the_70d_active_area(tmp_path: Path) -> None:
    mosaic = _random_mosaic(EOS_70D_ACTIVE_HEIGHT_PX, EOS_70D_ACTIVE_WIDTH_PX, seed=70)
    path = write_cr2(tmp_path / "IMG_0001.CR2", mosaic, black_level=BLACK, white_level=WHITE)
    with rawpy.imread(str(path)) as raw:
        assert (raw.sizes.width, raw.sizes.height) == (5472, 3648)
        assert (raw.sizes.left_margin, raw.sizes.top_margin) == (84, 50)
        assert np.array_equal(raw.raw_image_visible, mosaic)
        # The optical-black margins hold the black level.
        assert np.all(raw.raw_image[:, :84] == BLACK)
        assert np.all(raw.raw_image[:50, :] == BLACK)
        assert list(raw.black_level_per_channel) == [BLACK] * 4


def test_frame_never_takes_a_size_from_libraws_canon_table() -> None:
    # 5484x3658 plus the 84/50 margins would be 5568x3708, the real 70D frame, which LibRaw
    # crops from its own table (to 5496x3670); the writer widens the left margin instead.
    assert raw_frame_geometry(3658, 5484) == (5570, 3708, 86, 50)
    assert raw_frame_geometry(3648, 5472) == (5556, 3698, 84, 50)


@pytest.mark.parametrize(
    "mosaic",
    [
        np.zeros((32, 48), dtype=np.uint16),
        np.full((32, 48), (1 << 14) - 1, dtype=np.uint16),
        np.tile(np.array([[0, (1 << 14) - 1], [(1 << 14) - 1, 0]], dtype=np.uint16), (16, 24)),
        np.full((32, 48), 0xFF, dtype=np.uint16),  # many 0xFF bytes in the scan: byte stuffing
    ],
    ids=["zeros", "saturated", "max-differences", "ff-bytes"],
)
def test_extreme_mosaics_round_trip(tmp_path: Path, mosaic: np.ndarray) -> None:
    path = write_cr2(tmp_path / "x.CR2", mosaic, black_level=BLACK, white_level=(1 << 14) - 1, preview=False)
    visible, *_ = _libraw_view(path)
    assert np.array_equal(visible, mosaic)


def test_written_file_is_exactly_cr2_bytes_and_leaves_no_temporary(tmp_path: Path) -> None:
    mosaic = _random_mosaic(40, 60, seed=3)
    meta = Cr2Metadata(capture_time=datetime(2024, 2, 3, 4, 5, 6))
    path = write_cr2(tmp_path / "a.CR2", mosaic, metadata=meta)
    assert path.read_bytes() == cr2_bytes(mosaic, metadata=meta)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.CR2"]
    # Overwriting replaces the file in one step; a failed write leaves the old one untouched.
    write_cr2(path, mosaic + 1, metadata=meta)
    with pytest.raises(ValueError):
        write_cr2(path, np.zeros((41, 60), dtype=np.uint16))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.CR2"]
    assert np.array_equal(_libraw_view(path)[0], mosaic + 1)


@pytest.mark.parametrize(
    "mosaic, kwargs, message",
    [
        (np.zeros((31, 48), np.uint16), {}, "even"),
        (np.zeros((20, 48), np.uint16), {}, "at least 22"),
        (np.full((32, 48), 1 << 14, np.uint16), {}, "0..16383"),
        (np.zeros((32, 48), np.uint16), {"black_level": 9000, "white_level": 8000}, "black_level"),
        (np.zeros((32, 48), np.uint16), {"black_level": 0}, "black_level"),
        (np.zeros((32, 48, 3), np.uint16), {}, "2-D"),
        (np.zeros((24, 400), np.uint16), {}, "elongated"),
    ],
)
def test_invalid_mosaics_are_refused(mosaic: np.ndarray, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        cr2_bytes(mosaic, **kwargs)


def test_huffman_lengths_are_limited_to_16_bits_and_leave_the_all_ones_code_free() -> None:
    freq = np.zeros(17, dtype=np.int64)
    fib = [1, 1]
    while len(fib) < 17:
        fib.append(fib[-1] + fib[-2])  # Fibonacci counts make an unlimited Huffman tree 17 deep
    freq[:] = fib
    lengths = _huffman_code_lengths(freq)
    assert set(lengths) == set(range(17))
    assert max(lengths.values()) <= 16
    kraft = sum(2.0**-n for n in lengths.values())
    assert kraft < 1.0  # strictly: one code point (all ones) stays unused


def test_lossless_jpeg_headers_follow_t81() -> None:
    rows = _random_mosaic(30, 40, seed=5)
    jpeg = encode_lossless_jpeg(rows, components=2, precision=14)
    assert jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9"
    sof = jpeg.index(b"\xff\xc3")
    precision, height, width, comps = (
        jpeg[sof + 4],
        int.from_bytes(jpeg[sof + 5 : sof + 7], "big"),
        int.from_bytes(jpeg[sof + 7 : sof + 9], "big"),
        jpeg[sof + 9],
    )
    assert (precision, height, width, comps) == (14, 30, 20, 2)
    sos = jpeg.index(b"\xff\xda")
    assert jpeg[sos + 4] == 2 and jpeg[sos + 9] == 1  # two components, predictor 1


@pytest.fixture()
def exiftool() -> str:
    # the independent metadata reference: fails on CI, skips elsewhere, when missing
    return require("exiftool", "Debian: apt-get install libimage-exiftool-perl")


def test_exiftool_reports_a_canon_eos_70d_cr2_with_the_written_exposure(tmp_path: Path, exiftool: str) -> None:
    meta = Cr2Metadata(
        iso=800,
        exposure_time_s=1 / 250,
        f_number=5.6,
        focal_length_mm=35.0,
        capture_time=datetime(2023, 11, 12, 13, 14, 15),
        lens_model="EF-S18-55mm f/3.5-5.6 IS STM",
        focus_distance_m=2.5,
    )
    path = write_cr2(tmp_path / "IMG_0002.CR2", _random_mosaic(64, 96), metadata=meta)
    out = subprocess.run([exiftool, "-j", "-n", "-a", str(path)], capture_output=True, text=True, check=True)
    tags = json.loads(out.stdout)[0]
    assert tags["FileType"] == "CR2"
    assert tags["Make"] == "Canon"
    assert tags["Model"] == "Canon EOS 70D"
    assert tags["ISO"] == 800
    assert tags["ExposureTime"] == pytest.approx(1 / 250)
    assert tags["FNumber"] == pytest.approx(5.6)
    assert tags["FocalLength"] == pytest.approx(35.0)
    assert tags["DateTimeOriginal"] == "2023:11:12 13:14:15"
    assert tags["LensModel"] == "EF-S18-55mm f/3.5-5.6 IS STM"
    assert tags["FocusDistanceUpper"] == pytest.approx(2.5)
    assert tags["PerChannelBlackLevel"] == "2048 2048 2048 2048"
    assert tags["SpecularWhiteLevel"] == 15000
    assert "Warning" not in tags and "Error" not in tags
