"""Encodes a Bayer mosaic as a Canon EOS 70D CR2 (TIFF + lossless JPEG) that LibRaw decodes bit-exactly.

The simulated camera serves these files, and tests use them to feed the real
raw reader. Only numpy (and opencv for the optional preview JPEG) are used.

Layout of a file written here (little-endian TIFF, CR2 header)::

    header   II*\\0, IFD0 offset, "CR", 2, 0, offset of the raw IFD
    IFD0     Make, Model, DateTime, Orientation, Exif pointer
             (+ a small JPEG preview when ``preview=True``)
      Exif   ExposureTime, FNumber, ISO, DateTimeOriginal, FocalLength,
             SubjectDistance, LensModel, MakerNote
      Canon maker notes: ImageType, ModelID, FileInfo (focus distance),
             LensModel, SensorInfo (0x00e0), ColorData7 (0x4001: per-channel
             black level, white levels, as-shot white balance)
    IFD1     thumbnail JPEG (preview only)
    IFD2     small uncompressed RGB image (preview only)
    IFD3     Compression 6, StripOffsets, StripByteCounts, 0xc640 cr2_slice
             -> ITU T.81 lossless JPEG (SOF3, predictor 1, 2 components)

How LibRaw (0.22, read from its source: ``identify()``, ``parseCanonMakernotes``,
``lossless_jpeg_load_raw``) crops the frame, and why the frame is sized so:

* A Canon raw frame whose size is in LibRaw's own table is cropped with the
  table's margins. The real EOS 70D frame, 5568x3708, is in that table with
  left 72 / top 38 and so comes out as 5496x3670, not 5472x3648.
* For any other frame size, LibRaw uses the maker-note SensorInfo when the
  ColorData record gave it a black level: ``left = SensorLeftBorder`` (rounded
  up to even), ``width = SensorRightBorder - left`` (right border exclusive),
  likewise for top/height; the black level then comes from ColorData.

So the mosaic is placed at (left 84, top 50) -- the 70D's real active-area
origin -- inside a frame with optical-black margins on the left and top filled
with the black level; the frame is never a size from LibRaw's table. For
every even mosaic size from 22x22 up (5472x3648 included),
``rawpy.imread(p).raw_image_visible`` is exactly the mosaic and ``sizes``
gives its width and height.
"""

from __future__ import annotations

import io
import itertools
import os
import struct
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime
from fractions import Fraction

import numpy as np

EOS_70D_ACTIVE_WIDTH_PX = 5472
EOS_70D_ACTIVE_HEIGHT_PX = 3648
EOS_70D_MODEL_ID = 0x80000325  # Canon ModelID maker-note value of the EOS 70D
LEFT_MARGIN_PX = 84  # 70D SensorLeftBorder: optical-black columns before the active area
TOP_MARGIN_PX = 50  # 70D SensorTopBorder: optical-black rows above the active area
MIN_SIDE_PX = 22  # LibRaw rejects images narrower or lower than this

# Raw frame sizes (width, height) that LibRaw crops from its own Canon table
# (identify.cpp, table `canon`); a frame of one of these sizes would ignore
# SensorInfo, so the writer never produces one.
_LIBRAW_CANON_TABLE_SIZES = frozenset(
    {
        (1944, 1416),
        (2144, 1560),
        (2224, 1456),
        (2376, 1728),
        (2672, 1968),
        (3152, 2068),
        (3160, 2344),
        (3344, 2484),
        (3516, 2328),
        (3596, 2360),
        (3744, 2784),
        (3944, 2622),
        (3948, 2622),
        (3984, 2622),
        (4032, 2656),
        (4104, 3048),
        (4116, 2178),
        (4152, 2772),
        (4160, 3124),
        (4176, 3062),
        (4192, 3062),
        (4312, 2876),
        (4352, 2850),
        (4352, 2874),
        (4476, 2954),
        (4480, 3348),
        (4480, 3366),
        (4496, 3366),
        (4768, 3516),
        (4832, 3204),
        (4832, 3228),
        (5108, 3349),
        (5120, 3318),
        (5280, 3528),
        (5344, 3516),
        (5344, 3584),
        (5344, 3950),
        (5360, 3516),
        (5568, 3708),
        (5632, 3710),
        (5712, 3774),
        (5792, 3804),
        (5920, 3950),
        (6096, 4051),
        (6096, 4056),
        (6288, 4056),
        (6384, 4224),
        (6880, 4544),
        (6888, 4546),
        (7128, 4732),
        (8896, 5920),
    }
)


@dataclass(frozen=True)
class Cr2Metadata:
    """What the camera records about one exposure; written to Exif and Canon maker notes."""

    make: str = "Canon"
    model: str = "Canon EOS 70D"
    iso: int = 100
    exposure_time_s: float = 1 / 125
    f_number: float = 8.0
    focal_length_mm: float = 50.0
    capture_time: datetime = field(default_factory=lambda: datetime(2024, 1, 1, 12, 0, 0))
    lens_model: str | None = "EF50mm f/1.8 STM"
    focus_distance_m: float | None = None
    # As-shot white balance levels R, G, G, B (1024 = a gain of 1). The simulated camera renders a white
    # surface as equal R, G and B (its pixels are neutral), so as shot means no gain at all.
    wb_rggb: tuple[int, int, int, int] = (1024, 1024, 1024, 1024)
    serial_number: str | None = None


# --------------------------------------------------------------------------
# Lossless JPEG (ITU T.81 process 14, predictor 1)
# --------------------------------------------------------------------------

_SSSS_LUT = np.zeros(1 << 16, dtype=np.uint8)  # difference category: bit length of |d|
for _k in range(16):
    _SSSS_LUT[1 << _k : 1 << (_k + 1)] = _k + 1
_MASK_OF = ((1 << np.arange(17, dtype=np.int64)) - 1).astype(np.int16)  # low-bit mask per category (s <= 15)


def _huffman_code_lengths(freq: np.ndarray) -> dict[int, int]:
    """Code length per symbol, at most 16 bits, no all-ones code (T.81 Annex K.2, K.3)."""
    symbols = [int(s) for s in np.flatnonzero(freq)]
    counts = {s: int(freq[s]) for s in symbols}
    reserved = 256  # the reserved code point that keeps any code from being all ones
    counts[reserved] = 1
    # Plain Huffman on at most 18 symbols.
    groups: list[tuple[int, list[int]]] = [(c, [s]) for s, c in counts.items()]
    size = dict.fromkeys(counts, 0)
    while len(groups) > 1:
        groups.sort(key=lambda g: g[0])
        (c1, s1), (c2, s2) = groups[0], groups[1]
        for s in s1 + s2:
            size[s] += 1
        groups = [(c1 + c2, s1 + s2)] + groups[2:]
    bits = np.zeros(40, dtype=np.int64)
    for s in size:
        bits[size[s]] += 1
    # Annex K.3 (Adjust_BITS): move codes longer than 16 bits up the tree.
    i = 39
    while i > 16:
        while bits[i] > 0:
            j = i - 2
            while bits[j] == 0:
                j -= 1
            bits[i] -= 2
            bits[i - 1] += 1
            bits[j + 1] += 2
            bits[j] -= 1
        i -= 1
    while bits[i] == 0:
        i -= 1
    bits[i] -= 1  # drop the reserved code point
    # Hand out lengths: most frequent symbols get the shortest codes.
    ordered = sorted(symbols, key=lambda s: (-counts[s], s))
    lengths: dict[int, int] = {}
    k = 0
    for length in range(1, 17):
        for _ in range(int(bits[length])):
            lengths[ordered[k]] = length
            k += 1
    return lengths


def _canonical_codes(lengths: dict[int, int]) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """BITS and HUFFVAL for the DHT segment, and per-category lookup arrays for the coder.

    The lookups give, per category s, the Huffman code shifted left by s (the
    extra bits go below it) as uint32, and the total code-word length in bits.
    """
    order = sorted(lengths, key=lambda s: (lengths[s], s))
    bits = [0] * 16
    for s in order:
        bits[lengths[s] - 1] += 1
    code_of = np.zeros(17, dtype=np.uint32)
    len_of = np.zeros(17, dtype=np.uint8)
    code = 0
    prev_len = lengths[order[0]]
    for s in order:
        code <<= lengths[s] - prev_len
        prev_len = lengths[s]
        code_of[s] = code << s
        len_of[s] = lengths[s] + s
        code += 1
    return bits, order, code_of, len_of


def _block_categories(
    rows: np.ndarray, above: np.ndarray | None, components: int, precision: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predictor-1 differences of a block of JPEG rows, their categories and the category histogram.

    `above` is the row before the block (None for the first block): the first
    sample of each component in a row is predicted from the row above, in the
    first row from 2^(precision-1) (T.81 H.1.2.1). Differences are formed in
    uint16 arithmetic and read as int16, exact since |d| < 2^15.
    """
    d = np.empty(rows.shape, dtype=np.uint16)
    np.subtract(rows[:, components:], rows[:, :-components], out=d[:, components:])
    np.subtract(rows[1:, :components], rows[:-1, :components], out=d[1:, :components])
    first_pred = np.full(components, 1 << (precision - 1), np.uint16) if above is None else above[:components]
    np.subtract(rows[0, :components], first_pred, out=d[0, :components])
    d = d.view(np.int16)
    ssss = _SSSS_LUT[np.abs(d).view(np.uint16)]
    return d, ssss, np.bincount(ssss.reshape(-1), minlength=17)


def _pack_block(
    d: np.ndarray, s: np.ndarray, start_bit: int, code_of: np.ndarray, len_of: np.ndarray
) -> tuple[int, np.ndarray]:
    """Pack the code words of one block that starts at bit `start_bit` of the scan.

    Returns the index of the first 32-bit word touched and the words (uint32,
    big-endian bit order once serialised). Bit fields never overlap, so a
    float64 bincount of the word parts sums them exactly.
    """
    d = d.reshape(-1)
    s = s.reshape(-1)
    extra = (d + (_MASK_OF[s] & (d >> 15))).view(np.uint16)  # T.81 F.1.2.1: negative d -> d + 2^s - 1
    value = (code_of[s] | extra).astype(np.uint64)
    length = len_of[s]
    end = np.cumsum(length, dtype=np.int32)  # a block holds < 2^31 bits
    end += start_bit & 31
    pos = end - length
    word = pos >> 5
    shifted = value << (np.int32(64) - (pos & 31) - length).astype(np.uint64)
    n_words = int((int(end[-1]) + 31) >> 5)
    words = np.bincount(word, weights=(shifted >> np.uint64(32)).astype(np.float64), minlength=n_words)
    word += 1
    lo = (shifted & np.uint64(0xFFFFFFFF)).astype(np.float64)
    words += np.bincount(word, weights=lo, minlength=n_words + 1)[:n_words]
    return start_bit >> 5, words.astype(np.uint32)


def _entropy_coded_scan(rows: np.ndarray, components: int, precision: int) -> tuple[list[int], list[int], bytes]:
    """DHT BITS, HUFFVAL and the byte-stuffed scan for `rows`, in blocks of rows on threads.

    Phase 1 finds each block's differences and category histogram; the
    Huffman table comes from their sum (T.81 Annex K). Phase 2 packs each
    block at its bit offset, known from its histogram, so blocks are independent.
    """
    per_row = rows.shape[1]
    step = max(1, (1 << 20) // per_row)
    starts = list(range(0, rows.shape[0], step))
    workers = max(1, min(4, os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        blocks = list(
            pool.map(
                lambda a: _block_categories(rows[a : a + step], rows[a - 1] if a else None, components, precision),
                starts,
            )
        )
        freq = np.sum([h for _, _, h in blocks], axis=0)
        bits, huffval, code_of, len_of = _canonical_codes(_huffman_code_lengths(freq))
        block_bits = [int(h @ len_of.astype(np.int64)) for _, _, h in blocks]
        start_bits = np.concatenate(([0], np.cumsum(block_bits)[:-1])).tolist()
        total_bits = sum(block_bits)
        out = np.zeros((total_bits + 31) // 32 + 1, dtype=np.uint32)
        jobs = [(d, s, b) for (d, s, _), b in zip(blocks, start_bits)]
        for first, words in pool.map(lambda job: _pack_block(job[0], job[1], job[2], code_of, len_of), jobs):
            out[first : first + words.size] |= words
    data = out.astype(">u4").view(np.uint8)[: (total_bits + 7) // 8].copy()
    if total_bits & 7:
        data[-1] |= np.uint8((1 << (8 - (total_bits & 7))) - 1)  # pad the last byte with 1 bits
    ff = np.flatnonzero(data == 0xFF)
    if ff.size:
        data = np.insert(data, ff + 1, np.uint8(0))  # byte stuffing, T.81 F.1.2.3
    return bits, huffval, data.tobytes()


def encode_lossless_jpeg(rows: np.ndarray, components: int, precision: int) -> bytes:
    """Encode a (jpeg_rows, samples_per_row) uint16 array as a lossless JPEG (SOF3, predictor 1).

    ``samples_per_row`` holds ``components`` interleaved components; the frame
    header says width ``samples_per_row / components`` and height ``jpeg_rows``.
    """
    n_rows, per_row = rows.shape
    if per_row % components:
        raise ValueError(f"{per_row} samples per row do not split into {components} components")
    if not 2 <= precision <= 15:
        raise ValueError(f"precision {precision} bits is outside 2..15")
    rows = np.ascontiguousarray(rows, dtype=np.uint16)
    if int(rows.max(initial=0)) >> precision:
        raise ValueError(f"sample values exceed {precision} bits")
    bits, huffval, scan = _entropy_coded_scan(rows, components, precision)

    def segment(marker: int, payload: bytes) -> bytes:
        return struct.pack(">HH", marker, len(payload) + 2) + payload

    dht = segment(0xFFC4, bytes([0x00]) + bytes(bits) + bytes(huffval))
    sof = segment(
        0xFFC3,
        struct.pack(">BHHB", precision, n_rows, per_row // components, components)
        + b"".join(bytes([c + 1, 0x11, 0]) for c in range(components)),
    )
    sos = segment(
        0xFFDA,
        bytes([components])
        + b"".join(bytes([c + 1, 0x00]) for c in range(components))
        + bytes([1, 0, 0]),  # predictor 1, Se = 0, point transform 0
    )
    return b"\xff\xd8" + dht + sof + sos + scan + b"\xff\xd9"


# --------------------------------------------------------------------------
# TIFF structure
# --------------------------------------------------------------------------

_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _UNDEFINED = 1, 2, 3, 4, 5, 7
_TYPE_SIZE = {_BYTE: 1, _ASCII: 1, _SHORT: 2, _LONG: 4, _RATIONAL: 8, _UNDEFINED: 1}


@dataclass
class _Entry:
    tag: int
    type: int
    count: int
    data: bytes  # little-endian value bytes; patched later for pointers when `pointer_to` is set
    pointer_to: str | None = None


def _ascii(tag: int, text: str) -> _Entry:
    raw = text.encode("ascii", "replace") + b"\0"
    return _Entry(tag, _ASCII, len(raw), raw)


def _shorts(tag: int, values: list[int]) -> _Entry:
    return _Entry(tag, _SHORT, len(values), struct.pack(f"<{len(values)}H", *values))


def _longs(tag: int, values: list[int]) -> _Entry:
    return _Entry(tag, _LONG, len(values), struct.pack(f"<{len(values)}I", *values))


def _rational(tag: int, value: float) -> _Entry:
    f = Fraction(value).limit_denominator(100000)
    return _Entry(tag, _RATIONAL, 1, struct.pack("<II", f.numerator, f.denominator))


def _undefined(tag: int, data: bytes) -> _Entry:
    return _Entry(tag, _UNDEFINED, len(data), data)


def _pointer(tag: int, target: str, type_: int = _LONG, count: int = 1) -> _Entry:
    return _Entry(tag, type_, count, b"\0\0\0\0", pointer_to=target)


def _ifd_size(entries: list[_Entry]) -> int:
    size = 2 + 12 * len(entries) + 4
    for e in entries:
        if len(e.data) > 4 and e.pointer_to is None:
            size += len(e.data) + (len(e.data) & 1)
    return size


def _ifd_bytes(entries: list[_Entry], offset: int, next_ifd: int, addresses: dict[str, int]) -> bytes:
    """Serialise one IFD at file offset `offset`; long values follow the entry table."""
    entries = sorted(entries, key=lambda e: e.tag)
    table = [struct.pack("<H", len(entries))]
    heap: list[bytes] = []
    heap_at = offset + 2 + 12 * len(entries) + 4
    for e in entries:
        if e.pointer_to is not None:
            value = struct.pack("<I", addresses[e.pointer_to])
        elif len(e.data) <= 4:
            value = e.data.ljust(4, b"\0")
        else:
            value = struct.pack("<I", heap_at)
            padded = e.data + b"\0" * (len(e.data) & 1)
            heap.append(padded)
            heap_at += len(padded)
        table.append(struct.pack("<HHI", e.tag, e.type, e.count) + value)
    table.append(struct.pack("<I", next_ifd))
    return b"".join(table) + b"".join(heap)


@dataclass(frozen=True)
class _Frame:
    """Where the mosaic sits in the raw frame that the JPEG stores."""

    width_px: int
    height_px: int
    left_px: int
    top_px: int


def raw_frame_geometry(mosaic_height_px: int, mosaic_width_px: int) -> tuple[int, int, int, int]:
    """(frame_width_px, frame_height_px, left_px, top_px) of the raw frame a mosaic is written into."""
    f = _frame_for(mosaic_height_px, mosaic_width_px)
    return f.width_px, f.height_px, f.left_px, f.top_px


def _frame_for(h: int, w: int) -> _Frame:
    left, top = LEFT_MARGIN_PX, TOP_MARGIN_PX
    while (w + left, h + top) in _LIBRAW_CANON_TABLE_SIZES:
        left += 2
    return _Frame(w + left, h + top, left, top)


def _slices(frame_width_px: int) -> tuple[int, int, int]:
    """cr2_slice (0xc640): one slice of half the frame width, then the rest, as 70D files do."""
    first = (frame_width_px // 2) & ~1
    return 1, first, frame_width_px - first


def _jpeg_rows(frame: np.ndarray, slices: tuple[int, int, int]) -> np.ndarray:
    """Reorder the frame into the JPEG sample stream: slice by slice, each row-major."""
    count, width, last = slices
    edges = [i * width for i in range(count + 1)] + [count * width + last]
    stream = np.concatenate([frame[:, a:b].reshape(-1) for a, b in itertools.pairwise(edges)])
    return stream.reshape(frame.shape)


def _preview_images(
    mosaic: np.ndarray, black_level: int, white_level: int, wb_rggb: tuple[int, int, int, int] = (1024,) * 4
) -> tuple[bytes, bytes, np.ndarray]:
    """A preview JPEG (IFD0), thumbnail JPEG (IFD1) and small RGB image (IFD2), all sRGB 8-bit.

    Camera RGB with the as-shot white balance `wb_rggb` applied, as the camera's own previews are
    (no colour matrix: the encoder knows none).
    """
    import cv2

    from mca.processing.colour import linear_to_srgb8

    red, green, _, blue = (float(v) for v in wb_rggb)
    gains = np.array([red / green, 1.0, blue / green], dtype=np.float32)

    def rgb_at(step: int) -> np.ndarray:
        r = mosaic[0::step, 0::step].astype(np.float32)
        g = mosaic[0::step, 1::step].astype(np.float32)
        b = mosaic[1::step, 1::step].astype(np.float32)
        h = min(r.shape[0], g.shape[0], b.shape[0])
        w = min(r.shape[1], g.shape[1], b.shape[1])
        lin = np.stack([r[:h, :w], g[:h, :w], b[:h, :w]], axis=-1)
        lin = np.clip((lin - black_level) / max(white_level - black_level, 1), 0.0, 1.0)
        return linear_to_srgb8(lin * gains)

    step = max(2, 2 * (mosaic.shape[1] // 1440))
    preview = rgb_at(step)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(preview, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    thumb_w = min(160, preview.shape[1])
    thumb = cv2.resize(
        preview, (thumb_w, max(1, round(thumb_w * preview.shape[0] / preview.shape[1]))), interpolation=cv2.INTER_AREA
    )
    ok2, tjpg = cv2.imencode(".jpg", cv2.cvtColor(thumb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    small = cv2.resize(
        preview, (max(1, preview.shape[1] // 4), max(1, preview.shape[0] // 4)), interpolation=cv2.INTER_AREA
    )
    if not (ok and ok2):
        raise RuntimeError("opencv could not encode the preview JPEG")
    return jpg.tobytes(), tjpg.tobytes(), small


def _maker_notes(
    meta: Cr2Metadata, frame: _Frame, mosaic_shape: tuple[int, int], black_level: int, white_level: int
) -> list[_Entry]:
    h, w = mosaic_shape
    entries = [_ascii(0x0006, meta.model)]
    if meta.model == "Canon EOS 70D":
        entries.append(_longs(0x0010, [EOS_70D_MODEL_ID]))
    file_info = [0] * 26
    file_info[0] = 2 * len(file_info)
    if meta.focus_distance_m is not None:
        cm = 65535 if meta.focus_distance_m > 655.34 else max(1, round(meta.focus_distance_m * 100))
        file_info[20] = file_info[21] = cm  # FocusDistanceUpper / Lower, cm (ExifTool's Canon::FileInfo 20, 21)
    entries.append(_shorts(0x0093, file_info))
    if meta.lens_model:
        entries.append(_ascii(0x0095, meta.lens_model))
    # SensorInfo: LibRaw reads width = right - left, so the right/bottom borders are exclusive here.
    sensor_info = [
        34,
        frame.width_px,
        frame.height_px,
        0,
        0,
        frame.left_px,
        frame.top_px,
        frame.left_px + w,
        frame.top_px + h,
        2,
        frame.top_px,
        frame.left_px - 2,
        frame.top_px + h - 1,
        0,
        0,
        0,
        0,
    ]
    entries.append(_shorts(0x00E0, sensor_info))
    # ColorData7, version 10 (the 70D's record, 1313 int16): WB as shot, black and white levels.
    color = [0] * 1313
    color[0] = 10
    color[0x3F:0x43] = list(meta.wb_rggb)
    color[0x43] = 5200
    color[0x1F8:0x1FC] = [black_level] * 4
    color[0x1FC] = white_level
    color[0x1FD] = white_level
    entries.append(_shorts(0x4001, color))
    return entries


def cr2_bytes(
    mosaic: np.ndarray,
    *,
    black_level: int = 2048,
    white_level: int = 15000,
    metadata: Cr2Metadata | None = None,
    bits_per_sample: int = 14,
    preview: bool = True,
) -> bytes:
    """The bytes of a CR2 holding `mosaic` (H, W) uint16, RGGB, H and W even and >= 22.

    `black_level` (at least 1) fills the optical-black margins and is recorded
    as the per-channel black level; `white_level` is recorded as the
    saturation level. Mosaic values may lie anywhere in 0..2^bits-1.
    """
    meta = metadata or Cr2Metadata()
    mosaic = np.asarray(mosaic)
    if mosaic.ndim != 2 or mosaic.dtype.kind not in "ui":
        raise ValueError(f"mosaic must be a 2-D unsigned integer array, got {mosaic.dtype} {mosaic.shape}")
    h, w = mosaic.shape
    if h % 2 or w % 2 or h < MIN_SIDE_PX or w < MIN_SIDE_PX:
        raise ValueError(f"mosaic {w}x{h}: width and height must be even and at least {MIN_SIDE_PX}")
    limit = (1 << bits_per_sample) - 1
    if not 1 <= black_level < white_level <= limit:
        # LibRaw applies SensorInfo (and so the exact crop) only when ColorData gives a black level above 0.
        raise ValueError(f"need 1 <= black_level ({black_level}) < white_level ({white_level}) <= {limit}")
    if mosaic.size and (int(mosaic.min()) < 0 or int(mosaic.max()) > limit):
        raise ValueError(f"mosaic values must lie in 0..{limit} for {bits_per_sample}-bit samples")
    frame_geo = _frame_for(h, w)
    if (frame_geo.width_px > 4 * frame_geo.height_px) or (frame_geo.height_px > 4 * frame_geo.width_px):
        raise ValueError(f"mosaic {w}x{h} is too elongated for LibRaw's CR2 reader (aspect ratio above 4)")
    frame = np.full((frame_geo.height_px, frame_geo.width_px), black_level, dtype=np.uint16)
    frame[frame_geo.top_px :, frame_geo.left_px :] = mosaic
    slices = _slices(frame_geo.width_px)
    jpeg = encode_lossless_jpeg(_jpeg_rows(frame, slices), components=2, precision=bits_per_sample)

    stamp = meta.capture_time.strftime("%Y:%m:%d %H:%M:%S")
    ifd0 = [
        _ascii(0x010F, meta.make),
        _ascii(0x0110, meta.model),
        _shorts(0x0112, [1]),
        _ascii(0x0132, stamp),
        _pointer(0x8769, "exif"),
    ]
    exif = [
        _rational(0x829A, meta.exposure_time_s),
        _rational(0x829D, meta.f_number),
        _shorts(0x8827, [int(meta.iso)]),
        _undefined(0x9000, b"0230"),
        _ascii(0x9003, stamp),
        _ascii(0x9004, stamp),
        _rational(0x920A, meta.focal_length_mm),
        _pointer(0x927C, "makernote", _UNDEFINED, 0),
    ]
    if meta.focus_distance_m is not None:
        exif.append(_rational(0x9206, meta.focus_distance_m))
    if meta.lens_model:
        exif.append(_ascii(0xA434, meta.lens_model))
    if meta.serial_number:
        exif.append(_ascii(0xA431, meta.serial_number))
    notes = _maker_notes(meta, frame_geo, (h, w), black_level, white_level)
    raw_ifd = [
        _shorts(0x0103, [6]),
        _pointer(0x0111, "raw_data"),
        _longs(0x0117, [len(jpeg)]),
        _shorts(0xC640, list(slices)),
    ]

    blobs: dict[str, bytes] = {}
    chain = ["ifd0"]
    ifds: dict[str, list[_Entry]] = {"ifd0": ifd0}
    if preview:
        big, thumb, small = _preview_images(mosaic, black_level, white_level, meta.wb_rggb)
        ifd0 += [
            _longs(0x0100, [0]),
            _longs(0x0101, [0]),  # patched below with the preview size
            _shorts(0x0103, [6]),
            _pointer(0x0111, "preview"),
            _longs(0x0117, [len(big)]),
        ]
        ifds["ifd1"] = [
            _shorts(0x0103, [6]),
            _pointer(0x0201, "thumb"),
            _longs(0x0202, [len(thumb)]),
        ]
        sh, sw = small.shape[:2]
        ifds["ifd2"] = [
            _longs(0x0100, [sw]),
            _longs(0x0101, [sh]),
            _shorts(0x0102, [8, 8, 8]),
            _shorts(0x0103, [1]),
            _shorts(0x0106, [2]),
            _pointer(0x0111, "small"),
            _shorts(0x0115, [3]),
            _longs(0x0116, [sh]),
            _longs(0x0117, [small.nbytes]),
        ]
        import cv2  # only for the size of the preview JPEG

        decoded = cv2.imdecode(np.frombuffer(big, np.uint8), cv2.IMREAD_UNCHANGED)
        if decoded is None:
            raise ValueError("the preview JPEG just encoded could not be decoded")
        ifd0[-5] = _longs(0x0100, [decoded.shape[1]])
        ifd0[-4] = _longs(0x0101, [decoded.shape[0]])
        blobs.update(preview=big, thumb=thumb, small=small.tobytes())
        chain += ["ifd1", "ifd2"]
    chain.append("ifd3")
    ifds["ifd3"] = raw_ifd

    # Lay out: header, IFD chain with its sub-IFDs, maker notes, image data.
    addresses: dict[str, int] = {}
    at = 16
    for name in chain:
        addresses[name] = at
        at += _ifd_size(ifds[name])
        if name == "ifd0":
            addresses["exif"] = at
            at += _ifd_size(exif)
            addresses["makernote"] = at
            at += _ifd_size(notes)
    makernote_size = _ifd_size(notes)
    for e in exif:
        if e.pointer_to == "makernote":
            e.count = makernote_size
    for name in [n for n in ("preview", "thumb", "small") if n in blobs]:
        at += at & 1
        addresses[name] = at
        at += len(blobs[name])
    at += at & 1
    addresses["raw_data"] = at

    out = io.BytesIO()
    out.write(b"II*\0" + struct.pack("<I", 16) + b"CR\x02\x00" + struct.pack("<I", addresses["ifd3"]))
    for i, name in enumerate(chain):
        next_ifd = addresses[chain[i + 1]] if i + 1 < len(chain) else 0
        _write_at(out, addresses[name], _ifd_bytes(ifds[name], addresses[name], next_ifd, addresses))
        if name == "ifd0":
            _write_at(out, addresses["exif"], _ifd_bytes(exif, addresses["exif"], 0, addresses))
            _write_at(out, addresses["makernote"], _ifd_bytes(notes, addresses["makernote"], 0, addresses))
    for name, blob in blobs.items():
        _write_at(out, addresses[name], blob)
    _write_at(out, addresses["raw_data"], jpeg)
    return out.getvalue()


def _write_at(out: io.BytesIO, offset: int, data: bytes) -> None:
    if out.tell() < offset:
        out.write(b"\0" * (offset - out.tell()))
    assert out.tell() == offset, "CR2 layout overlap"
    out.write(data)
