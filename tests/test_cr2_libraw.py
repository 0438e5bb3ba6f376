"""The CR2 writer against references written here: an optimal Huffman code (heapq), the canonical code
procedure of ITU T.81 Annex C, the exact bit count of a predictor-1 lossless JPEG scan, LibRaw (rawpy) for
what it decodes (white balance, levels, crop) and the preview JPEG against the mosaic's own colour sites.
"""

from __future__ import annotations

import heapq
import io
import itertools
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import rawpy
from PIL import Image

from mca.capture.simulated_shots import write_cr2
from mca.devices.sim import cr2
from mca.devices.sim.cr2 import Cr2Metadata, cr2_bytes, encode_lossless_jpeg

BLACK, WHITE = 2048, 15000


def optimal_huffman_cost(freq: dict[int, int]) -> int:
    """Total code length of an optimal (unbounded) Huffman code for `freq` (heapq, textbook)."""
    if len(freq) == 1:
        return next(iter(freq.values()))
    heap = list(freq.values())
    heapq.heapify(heap)
    cost = 0
    while len(heap) > 1:
        a, b = heapq.heappop(heap), heapq.heappop(heap)
        cost += a + b
        heapq.heappush(heap, a + b)
    return cost


@pytest.mark.parametrize(
    "counts",
    [
        {0: 5, 1: 9, 2: 12, 3: 13, 4: 16, 5: 45},
        {0: 1000, 1: 1, 2: 1},
        {s: 1000 - 60 * s for s in range(15)},
        {s: 10 * (s + 1) for s in range(17)},  # the most frequent categories last
        {7: 42},
    ],
)
def test_huffman_lengths_are_optimal_and_the_most_frequent_get_the_shortest(counts: dict[int, int]) -> None:
    freq = np.zeros(17, dtype=np.int64)
    for s, c in counts.items():
        freq[s] = c
    lengths = cr2._huffman_code_lengths(freq)
    assert set(lengths) == set(counts)
    total = sum(counts[s] * lengths[s] for s in counts)
    # never worse than an optimal code that also holds the reserved all-ones point, never better than optimal
    assert total <= optimal_huffman_cost({**counts, 256: 1})
    assert total >= optimal_huffman_cost(counts) if len(counts) > 1 else True
    for a, b in itertools.permutations(counts, 2):
        if counts[a] > counts[b]:
            assert lengths[a] <= lengths[b], (a, b)
    assert sum(2.0**-length for length in lengths.values()) < 1.0  # the all-ones code stays free
    assert max(lengths.values()) <= 16


def test_huffman_lengths_are_limited_to_16_bits_for_a_fibonacci_distribution() -> None:
    fib = [1, 1]
    while len(fib) < 17:
        fib.append(fib[-1] + fib[-2])
    freq = np.array(fib, dtype=np.int64)
    lengths = cr2._huffman_code_lengths(freq)
    assert set(lengths) == set(range(17))  # every symbol keeps a code
    assert max(lengths.values()) == 16
    assert sum(2.0**-length for length in lengths.values()) < 1.0
    assert lengths[16] == min(lengths.values())


def annex_c_codes(lengths: dict[int, int]) -> dict[int, tuple[int, int]]:
    """T.81 Annex C: HUFFSIZE/HUFFCODE from BITS and HUFFVAL (symbols sorted by length, then value)."""
    huffval = sorted(lengths, key=lambda s: (lengths[s], s))
    sizes = [lengths[s] for s in huffval]
    codes = []
    code, size = 0, sizes[0]
    for k, si in enumerate(sizes):
        while si > size:
            code <<= 1
            size += 1
        codes.append(code)
        code += 1
        del k
    return {s: (c, lengths[s]) for s, c in zip(huffval, codes)}


def test_canonical_codes_follow_annex_c() -> None:
    lengths = {0: 2, 1: 3, 2: 3, 3: 3, 4: 3, 5: 3, 6: 4, 7: 5, 8: 6, 9: 7, 10: 8, 11: 9, 12: 10}
    bits, huffval, code_of, len_of = cr2._canonical_codes(lengths)
    assert bits == [0, 1, 5, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0]
    assert huffval == list(range(13))
    for s, (code, length) in annex_c_codes(lengths).items():
        assert int(code_of[s]) == code << s  # the extra bits go below the code
        assert int(len_of[s]) == length + s
    assert annex_c_codes(lengths)[0] == (0b00, 2) and annex_c_codes(lengths)[1] == (0b010, 3)


def predictor_1_categories(rows: np.ndarray, components: int, precision: int) -> np.ndarray:
    """T.81 H.1.2.1, written here: each sample predicted from its left neighbour of the same component, the
    first of a row from the one above, the very first from 2^(P-1); the category is the bit length of |d|."""
    x = rows.astype(np.int64)
    pred = np.empty_like(x)
    pred[:, components:] = x[:, :-components]
    pred[1:, :components] = x[:-1, :components]
    pred[0, :components] = 1 << (precision - 1)
    d = (x - pred + 32768) % 65536 - 32768
    return np.array([int(abs(v)).bit_length() for v in d.ravel()])


@pytest.mark.parametrize(
    ("components", "precision", "shape", "spread"),
    [(1, 14, (40, 64), 50), (2, 12, (31, 90), 3000), (4, 8, (16, 32), 20)],
)
def test_the_scan_has_exactly_the_bits_an_optimal_code_needs(
    components: int, precision: int, shape: tuple[int, int], spread: int
) -> None:
    rng = np.random.default_rng(components)
    base = (1 << (precision - 1)) + np.cumsum(rng.integers(-spread, spread + 1, size=shape), axis=1)
    rows = np.clip(base, 0, (1 << precision) - 1).astype(np.uint16)
    jpeg = encode_lossless_jpeg(rows, components, precision)
    sos = jpeg.index(b"\xff\xda")
    scan = jpeg[sos + 2 + int.from_bytes(jpeg[sos + 2 : sos + 4], "big") : -2]
    assert jpeg[-2:] == b"\xff\xd9"
    unstuffed = scan.replace(b"\xff\x00", b"\xff")
    categories = predictor_1_categories(rows, components, precision)
    counts = {int(s): int(c) for s, c in zip(*np.unique(categories, return_counts=True))}
    extra_bits = int(categories.sum())
    lower = optimal_huffman_cost(counts) + extra_bits if len(counts) > 1 else extra_bits + sum(counts.values())
    upper = optimal_huffman_cost({**counts, 256: 1}) + extra_bits
    assert lower <= 8 * len(unstuffed) < upper + 8
    # the frame header names the shape, precision and components
    sof = jpeg.index(b"\xff\xc3")
    assert jpeg[sof + 4] == precision
    assert int.from_bytes(jpeg[sof + 5 : sof + 7], "big") == shape[0]
    assert int.from_bytes(jpeg[sof + 7 : sof + 9], "big") == shape[1] // components
    assert jpeg[sof + 9] == components


def test_lossless_jpeg_refuses_what_it_cannot_encode() -> None:
    rows = np.zeros((4, 6), np.uint16)
    with pytest.raises(ValueError, match="6 samples per row do not split into 4 components"):
        encode_lossless_jpeg(rows, 4, 12)
    for precision in (1, 16):
        with pytest.raises(ValueError, match=f"precision {precision} bits is outside 2..15"):
            encode_lossless_jpeg(rows, 2, precision)
    encode_lossless_jpeg(rows, 2, 2)
    encode_lossless_jpeg(rows + 32767, 2, 15)
    with pytest.raises(ValueError, match="exceed 12 bits"):
        encode_lossless_jpeg(rows + 4096, 2, 12)
    encode_lossless_jpeg(rows + 4095, 2, 12)


def coloured_mosaic(height: int = 240, width: int = 360) -> tuple[np.ndarray, np.ndarray]:
    """An RGGB mosaic of a scene with a red, a green and a blue third, and the scene's linear RGB (0..1)."""
    scene = np.zeros((height, width, 3))
    scene[:, : width // 3] = (0.8, 0.2, 0.05)
    scene[:, width // 3 : 2 * width // 3] = (0.1, 0.6, 0.15)
    scene[:, 2 * width // 3 :] = (0.05, 0.25, 0.9)
    scene[: height // 2] *= 0.5
    mosaic = np.empty((height, width), np.uint16)
    level = lambda v: np.round(BLACK + v * (WHITE - BLACK)).astype(np.uint16)  # noqa: E731
    mosaic[0::2, 0::2] = level(scene[0::2, 0::2, 0])
    mosaic[0::2, 1::2] = level(scene[0::2, 1::2, 1])
    mosaic[1::2, 0::2] = level(scene[1::2, 0::2, 1])
    mosaic[1::2, 1::2] = level(scene[1::2, 1::2, 2])
    return mosaic, scene


def srgb8(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1, written here."""
    v = np.clip(linear, 0, 1)
    return np.round(255 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055))


def test_the_preview_shows_each_colour_from_its_own_sites(tmp_path: Path) -> None:
    mosaic, scene = coloured_mosaic()
    path = write_cr2(tmp_path / "colour.CR2", mosaic, black_level=BLACK, white_level=WHITE)
    with rawpy.imread(str(path)) as raw:
        thumb = raw.extract_thumb()
    assert thumb.format == rawpy.ThumbFormat.JPEG
    preview = np.asarray(Image.open(io.BytesIO(thumb.data)).convert("RGB")).astype(float)
    step = mosaic.shape[0] // preview.shape[0]
    assert preview.shape[:2] == (mosaic.shape[0] // step, mosaic.shape[1] // step)
    expected = srgb8(scene[::step, ::step])
    inner = np.ones(preview.shape[:2], bool)
    third = preview.shape[1] // 3
    for edge in (third, 2 * third):  # JPEG blurs the colour edges
        inner[:, edge - 4 : edge + 4] = False
    inner[preview.shape[0] // 2 - 4 : preview.shape[0] // 2 + 4] = False
    error = np.abs(preview - expected)[inner]
    assert float(np.median(error)) < 4.0 and float(np.percentile(error, 99)) < 20.0


def test_the_preview_applies_the_as_shot_white_balance(tmp_path: Path) -> None:
    grey = np.full((120, 180), BLACK + (WHITE - BLACK) // 5, np.uint16)
    meta = Cr2Metadata(wb_rggb=(2048, 1024, 1024, 1536))
    data = cr2_bytes(grey, black_level=BLACK, white_level=WHITE, metadata=meta)
    with rawpy.imread(io.BytesIO(data)) as raw:
        assert list(raw.camera_whitebalance)[:3] == [2048.0, 1024.0, 1536.0]  # LibRaw reads ColorData's WB
        thumb = raw.extract_thumb()
    rgb = np.asarray(Image.open(io.BytesIO(thumb.data)).convert("RGB")).astype(float).reshape(-1, 3).mean(axis=0)
    assert rgb == pytest.approx(srgb8(np.array([0.4, 0.2, 0.3])), abs=2.5)


def test_libraw_reads_the_levels_and_the_crop(tmp_path: Path) -> None:
    mosaic = np.random.default_rng(3).integers(BLACK, 12000, size=(100, 150), dtype=np.uint16)
    when = datetime(2024, 5, 1, 10, 15, 2)
    meta = Cr2Metadata(iso=400, exposure_time_s=1 / 250, f_number=2.8, focal_length_mm=50.0, capture_time=when)
    data = cr2_bytes(mosaic, black_level=1024, white_level=12000, metadata=meta)
    width, height, left, top = cr2.raw_frame_geometry(100, 150)
    with rawpy.imread(io.BytesIO(data)) as raw:
        assert np.array_equal(raw.raw_image_visible, mosaic)
        assert (raw.sizes.raw_width, raw.sizes.raw_height) == (width, height) == (150 + left, 100 + top)
        assert (raw.sizes.left_margin, raw.sizes.top_margin) == (left, top)
        assert list(raw.black_level_per_channel) == [1024] * 4
        assert list(raw.camera_white_level_per_channel) == [12000] * 4
        # the masked border left of the crop: black, at the black level
        assert int(np.median(raw.raw_image[:, : left - 2])) == 1024


def test_writing_is_atomic_and_the_bytes_are_cr2_bytes(tmp_path: Path) -> None:
    mosaic = np.random.default_rng(4).integers(0, 1 << 14, size=(48, 64), dtype=np.uint16)
    path = write_cr2(tmp_path / "a.CR2", mosaic, black_level=BLACK, white_level=16383)
    assert path.read_bytes() == cr2_bytes(mosaic, black_level=BLACK, white_level=16383)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.CR2"]
    assert path.read_bytes()[:4] == b"II*\x00" and path.read_bytes()[8:10] == b"CR"
    without = cr2_bytes(mosaic, black_level=BLACK, white_level=16383, preview=False)
    assert len(without) < len(path.read_bytes())
    with rawpy.imread(io.BytesIO(without)) as raw:
        assert np.array_equal(raw.raw_image_visible, mosaic)


def test_the_tiff_structure_read_by_tifffile(tmp_path: Path) -> None:
    """tifffile (an independent TIFF reader) finds every IFD, tag and image where TIFF/Exif put them."""
    import tifffile

    mosaic = np.random.default_rng(5).integers(BLACK, 9000, size=(200, 120), dtype=np.uint16)  # portrait
    when = datetime(2024, 5, 1, 10, 15, 2)
    meta = Cr2Metadata(iso=800, exposure_time_s=1 / 60, f_number=4.0, focal_length_mm=35.0, capture_time=when,
                       lens_model="EF35mm", serial_number="123456", focus_distance_m=1.25)  # fmt: skip
    path = write_cr2(tmp_path / "t.CR2", mosaic, black_level=BLACK, white_level=WHITE, metadata=meta)
    with tifffile.TiffFile(path) as tif:
        pages = tif.pages
        assert len(pages) == 4
        ifd0 = pages[0].tags
        assert ifd0["Make"].value == "Canon" and ifd0["Model"].value == "Canon EOS 70D"
        assert ifd0["DateTime"].value == "2024:05:01 10:15:02"
        assert ifd0["Orientation"].value == 1
        exif = ifd0["ExifTag"].value
        assert exif["ExposureTime"] == (1, 60) and exif["FNumber"] == (4, 1) and exif["FocalLength"] == (35, 1)
        assert exif["ISOSpeedRatings"] == 800
        assert exif["DateTimeOriginal"] == exif["DateTimeDigitized"] == "2024:05:01 10:15:02"
        assert exif["LensModel"] == "EF35mm" and exif["BodySerialNumber"] == "123456"
        assert exif["SubjectDistance"] == (5, 4)
        # IFD0: the preview JPEG, with its own size; IFD1 the thumbnail; IFD2 a small 8-bit RGB image
        at, length = np.ravel(ifd0["StripOffsets"].value)[0], np.ravel(ifd0["StripByteCounts"].value)[0]
        preview = Image.open(io.BytesIO(path.read_bytes()[int(at) : int(at + length)]))
        assert (ifd0["ImageWidth"].value, ifd0["ImageLength"].value) == preview.size == (60, 100)
        ifd1 = pages[1].tags
        thumb_at = int(np.ravel(ifd1["JPEGInterchangeFormat"].value)[0])
        thumb_len = int(np.ravel(ifd1["JPEGInterchangeFormatLength"].value)[0])
        thumb = Image.open(io.BytesIO(path.read_bytes()[thumb_at : thumb_at + thumb_len]))
        assert thumb.size == (60, 100)  # at most 160 wide: the preview itself
        small = pages[2].asarray()
        assert small.shape == (25, 15, 3) and small.dtype == np.uint8
        ifd3 = pages[3].tags
        assert ifd3["Compression"].value == 6
        width = cr2.raw_frame_geometry(200, 120)[0]
        assert tuple(ifd3[50752].value) == (1, (width // 2) & ~1, width - ((width // 2) & ~1))  # cr2_slice


def test_the_default_metadata_is_written_and_read_back(tmp_path: Path) -> None:
    from mca.capture.raw import read_raw

    mosaic = np.random.default_rng(6).integers(BLACK, 9000, size=(64, 96), dtype=np.uint16)
    meta = read_raw(write_cr2(tmp_path / "d.CR2", mosaic, metadata=Cr2Metadata())).metadata
    assert (meta.make, meta.model, meta.lens_model) == ("Canon", "Canon EOS 70D", "EF50mm f/1.8 STM")
    assert (meta.iso, meta.f_number, meta.focal_length_mm) == (100, 8.0, 50.0)
    assert meta.exposure_time_s == pytest.approx(1 / 125)
    assert meta.capture_time == datetime(2024, 1, 1, 12, 0, 0)
    assert meta.focus_distance_m is None


def test_every_size_the_writer_avoids_is_one_libraw_crops_from_its_own_table(monkeypatch: pytest.MonkeyPatch) -> None:
    """LibRaw itself confirms the writer's table: a frame of a listed size has its crop taken from LibRaw's
    Canon table, not from the file's SensorInfo (only the headers are read: the scan is a stub)."""
    import struct

    encode = cr2.encode_lossless_jpeg

    def header_only(rows: np.ndarray, components: int, precision: int) -> bytes:
        jpeg = bytearray(encode(np.zeros((2, 2 * components), np.uint16), components, precision))
        sof = jpeg.index(b"\xff\xc3")
        jpeg[sof + 5 : sof + 9] = struct.pack(">HH", rows.shape[0], rows.shape[1] // components)
        return bytes(jpeg)

    table = sorted(cr2._LIBRAW_CANON_TABLE_SIZES)
    assert len(table) > 30
    monkeypatch.setattr(cr2, "encode_lossless_jpeg", header_only)
    monkeypatch.setattr(cr2, "_LIBRAW_CANON_TABLE_SIZES", frozenset())  # let the writer make those frames
    left, top = cr2.LEFT_MARGIN_PX, cr2.TOP_MARGIN_PX

    def libraw_crop(frame_width: int, frame_height: int) -> tuple[int, int, int, int]:
        data = cr2.cr2_bytes(np.zeros((frame_height - top, frame_width - left), np.uint16), preview=False)
        with rawpy.RawPy() as raw:
            raw.open_buffer(io.BytesIO(data))
            s = raw.sizes
            assert (s.raw_width, s.raw_height) == (frame_width, frame_height)
            return s.width, s.height, s.left_margin, s.top_margin

    reachable = [(w, h) for w, h in table if (w - left) % 2 == 0 and (h - top) % 2 == 0]  # even mosaics only
    assert len(reachable) > 30
    for width, height in reachable:
        ours = (width - left, height - top, left, top)
        assert libraw_crop(width, height) != ours, (width, height)
    # and a size next to one of them follows the file
    assert libraw_crop(5570, 3708) == (5570 - left, 3708 - top, left, top)
    # with its table, the writer never gives LibRaw a frame it would crop on its own: mosaics whose
    # natural frame is a listed size or next to one are decoded with the crop the file states
    monkeypatch.setattr(cr2, "_LIBRAW_CANON_TABLE_SIZES", frozenset(table))
    for width, height in table:
        for dw in (-1, 0, 1):
            if (width + dw - left) % 2 or (height - top) % 2:
                continue  # the writer only takes even mosaics
            mosaic = np.zeros((height - top, width + dw - left), np.uint16)
            data = cr2.cr2_bytes(mosaic, preview=False)
            used_left, used_top = cr2.raw_frame_geometry(*mosaic.shape)[2:]
            with rawpy.RawPy() as raw:
                raw.open_buffer(io.BytesIO(data))
                s = raw.sizes
                assert (s.width, s.height, s.left_margin, s.top_margin) == (
                    mosaic.shape[1],
                    mosaic.shape[0],
                    used_left,
                    used_top,
                ), (width + dw, height)
