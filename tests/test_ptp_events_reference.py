"""EOS GetEvent records against real bytes (the 400D's ObjectAddedEx, the 70D's FocusInfoEx decode in
../shared/reference/eos-traces) and against records written out by hand from the documented layout:
u32 size, u32 code, body; the list ends with a record of size 8 and code 0.
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path

import pytest

from mca.devices.ptp import events as ev
from mca.devices.ptp.codec import MAX_DATASET_BYTES, ProtocolError, Reader

TRACES = Path(__file__).resolve().parents[2] / "shared" / "reference" / "eos-traces"
if not TRACES.is_dir():
    TRACES = Path("/work/shared/reference/eos-traces")
needs_traces = pytest.mark.skipif(
    not TRACES.is_dir() and not os.environ.get("CI"),
    reason="the EOS traces (../shared/reference/eos-traces) are absent",
)


def hexdump_bytes(path: Path) -> bytes:
    """The bytes of a `gphoto2 --debug` hexdump ("0000  50 00 ...-0b 07 ...  ascii")."""
    out = bytearray()
    for line in path.read_text(errors="replace").splitlines():
        match = re.match(r"^([0-9a-f]{4})  ((?:[0-9a-f]{2}[ -]){1,16})", line)
        if match:
            out += bytes.fromhex(match[2].replace("-", " "))
    return bytes(out)


def record(code: int, body: bytes) -> bytes:
    return struct.pack("<II", 8 + len(body), code) + body


END = struct.pack("<II", 8, 0)


@needs_traces
def test_the_400d_object_added_record_decodes_to_what_libgphoto2_printed() -> None:
    data = hexdump_bytes(TRACES / "eos400d_libgphoto2-400d-objectaddedex-fragment.log")
    assert len(data) == 0x50 and data[:4] == b"\x50\x00\x00\x00"
    payload = data[12:]  # after the PTP data container header
    events = ev.parse_eos_events(payload)
    assert events == [
        ev.EosObjectAdded(
            handle=0x31946352,  # "objectid"
            storage_id=0x00010001,  # "storageid"
            object_format=0x3801,  # "ofc": EXIF/JPEG
            size_bytes=0x00274185,  # "compressedsize"
            parent=0x31940000,  # "parentid"
            filename="IMG_1589.JPG",
        )
    ]
    # the same record sent as ObjectInfoChangedEx (0xC187) is a change, not a new file
    changed = bytearray(payload)
    changed[4:6] = b"\x87\xc1"
    assert ev.parse_eos_events(bytes(changed))[0].changed is True
    assert ev.parse_eos_events(payload)[0].changed is False
    # what we write for those values puts each field where the 400D put it
    ours = ev.pack_eos_event(events[0])
    for start, end in ((0, 18), (28, 36), (40, 53)):
        assert ours[start:end] == payload[start:end], (start, end)
    assert len(ours) == 0x3C == struct.unpack_from("<I", payload)[0]
    assert payload[ev.OBJECT_ADDED_NAME_OFFSET :].startswith(b"IMG_1589.JPG\x00")
    assert ours[ev.OBJECT_ADDED_NAME_OFFSET :].startswith(b"IMG_1589.JPG\x00")


@needs_traces
def test_the_70d_focus_info_dump_decodes() -> None:
    text = (TRACES / "eos70d_libgphoto2-70d-focusinfoex-NOTRACE.txt").read_text()
    raw = bytearray()
    for offset, hex_bytes in re.findall(r"^(\d+): ((?:[0-9a-f]{2} ?)+)", text, flags=re.M):
        assert int(offset) == len(raw)
        raw += bytes.fromhex(hex_bytes.split("\t")[0])
    raw = bytes(raw)
    assert len(raw) == 282 == struct.unpack_from("<I", raw)[0]
    info = ev.parse_focus_info_ex(raw)
    assert info is not None
    assert (info.version, info.points_total, info.points_in_use) == (4, 31, 19)
    assert (info.image_width_px, info.image_height_px) == (5472, 3648)
    assert info.in_focus == () and not info.focused  # the focus mask (bytes 268..271) is empty
    # with points 0 and 9 marked in focus: their boxes, from the tables at 20 (heights), 82 (widths), 144 (x), 206 (y)
    marked = bytearray(raw)
    marked[268] = 0b0000_0001
    marked[269] = 0b0000_0010
    focused = ev.parse_focus_info_ex(bytes(marked))
    assert focused is not None and focused.focused

    def table(at: int, i: int) -> int:
        return struct.unpack_from("<h", raw, at + 2 * i)[0]

    assert focused.in_focus == tuple((table(144, i), table(206, i), table(82, i), table(20, i)) for i in (0, 9))
    assert focused.in_focus[0] == (-1395, 0, 277, 229)


def test_focus_info_bounds() -> None:
    points = [(10 * i, -5 * i, 40, 30) for i in range(9)]
    raw = ev.pack_focus_info_ex(points, {0, 8}, (5472, 3648))
    assert struct.unpack_from("<IH", raw) == (len(raw), len(raw) - 4)
    info = ev.parse_focus_info_ex(raw)
    assert info is not None and info.in_focus == ((0, 0, 40, 30), (80, -40, 40, 30))
    with pytest.raises(ProtocolError, match="claims"):
        ev.parse_focus_info_ex(struct.pack("<I", len(raw) + 1) + raw[4:])
    with pytest.raises(ProtocolError, match="claims 19 bytes"):
        ev.parse_focus_info_ex(struct.pack("<I", 19) + raw[4:])
    assert ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 20, 16, 4, 0, 0, 0, 0, 0, 0)) is None
    assert ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 20, 16, 4, 3, 0, 0, 0, 0, 0)) is None
    with pytest.raises(ProtocolError, match="uses 4 of 3 points"):
        ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 60, 56, 4, 3, 4, 0, 0, 0, 0) + bytes(40))
    # 3 points need 20 + 24 + 1 = 45 bytes
    ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 45, 41, 4, 3, 3, 0, 0, 0, 0) + bytes(25))
    with pytest.raises(ProtocolError, match="does not fit 44 bytes"):
        ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 44, 40, 4, 3, 3, 0, 0, 0, 0) + bytes(24))
    # one point: 20 + 8 + one mask byte
    ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 29, 25, 4, 1, 1, 0, 0, 0, 0) + bytes(9))
    with pytest.raises(ProtocolError, match="with 1 points does not fit 28 bytes"):
        ev.parse_focus_info_ex(struct.pack("<IHHHHHHHH", 28, 24, 4, 1, 1, 0, 0, 0, 0) + bytes(8))
    # eight points: one mask byte; point 7 is its top bit, point 8 the first bit of the next byte
    eight = [(i, -i, 10 + i, 20 + i) for i in range(8)]
    assert len(ev.pack_focus_info_ex(eight, {7}, (100, 80))) == 20 + 8 * 8 + 1
    assert ev.pack_focus_info_ex(eight, {7}, (100, 80))[-1] == 0x80
    nine = [*eight, (8, -8, 18, 28)]
    packed = ev.pack_focus_info_ex(nine, {7, 8}, (100, 80))
    assert packed[-2:] == b"\x80\x01"
    focused = ev.parse_focus_info_ex(packed)
    assert focused is not None and focused.in_focus == ((7, -7, 17, 27), (8, -8, 18, 28))


def test_request_object_transfer_record() -> None:
    # handle, format, (u32), size, (u32), then the name at 0x1C from the record start
    body = struct.pack("<IIIII", 0x90000001, 0x0000B103, 0, 25_000_000, 0) + b"IMG_0042.CR2\x00\x00\x00\x00"
    (got,) = ev.parse_eos_events(record(0xC186, body) + END)
    assert got == ev.EosRequestObjectTransfer(0x90000001, 0xB103, 25_000_000, "IMG_0042.CR2")
    assert record(0xC186, body)[ev.REQUEST_TRANSFER_NAME_OFFSET :].startswith(b"IMG_0042.CR2\x00")
    upper = struct.pack("<IIIII", 1, 0x1234B103, 0, 5, 0) + b"A\x00"
    assert ev.parse_eos_events(record(0xC186, upper))[0].object_format == 0xB103  # the low 16 bits
    assert ev.pack_eos_event(got) == record(0xC186, body)


def test_simple_records() -> None:
    data = b"".join(
        [
            record(0xC182, struct.pack("<I", 77)),
            record(0xC189, struct.pack("<I", 0xD101) + struct.pack("<I", 0x30)),
            record(0xC189, struct.pack("<I", 0xD402) + b"Canon EOS 70D\x00\x00\x00"),
            record(0xC189, struct.pack("<I", 0xD1B0) + b"\x02"),  # a one-byte value
            record(0xC18B, struct.pack("<I", 1)),
            record(0xC18B, struct.pack("<I", 0)),
            record(0xC18B, struct.pack("<I", 2)),
            record(0xC1F6, b"\x01\x02\x03"),
            END,
            record(0xC182, struct.pack("<I", 99)),  # after the terminator: not read
        ]
    )
    got = ev.parse_eos_events(data)
    assert got[0] == ev.EosObjectRemoved(77)
    assert (got[1].prop, got[1].value) == (0xD101, 0x30)
    assert (
        got[2].prop == 0xD402 and got[2].text == "Canon EOS 70D" and got[2].value == int.from_bytes(b"Cano", "little")
    )
    assert (got[3].prop, got[3].value, got[3].raw) == (0xD1B0, 2, b"\x02")
    assert [g.busy for g in got[4:7]] == [True, False, False]
    assert got[7] == ev.EosUnknownEvent(0xC1F6, b"\x01\x02\x03")
    assert len(got) == 8
    assert ev.EosPropValueChanged(0xD402, int.from_bytes(b"AB\x00\x00", "little")).text == "AB"
    # packing writes the same records back
    assert ev.pack_eos_events(got) == data[: data.index(END) + 8]


def test_avail_lists() -> None:
    enum = record(0xC18A, struct.pack("<III", 0xD101, 3, 3) + struct.pack("<3I", 0x10, 0x20, 0x30))
    (got,) = ev.parse_eos_events(enum)
    assert (got.prop, got.kind, got.values) == (0xD101, 3, (0x10, 0x20, 0x30))
    # the 70D's 0xD17D list: 33 items of 12 bytes (396 bytes)
    items = b"".join(struct.pack("<III", i, 0xAA, 0xBB) for i in range(33))
    (wide,) = ev.parse_eos_events(record(0xC18A, struct.pack("<III", 0xD17D, 3, 33) + items))
    assert wide.values == tuple(range(33)) and all(len(r) == 12 for r in wide.raw_values)
    # 5 u32 items plus 2 stray bytes: u32-spaced
    (odd,) = ev.parse_eos_events(
        record(0xC18A, struct.pack("<III", 0xD102, 3, 5) + struct.pack("<5I", *range(5)) + b"xy")
    )
    assert odd.values == (0, 1, 2, 3, 4)
    # a list of another type, or empty: no values, the bytes kept
    (other,) = ev.parse_eos_events(record(0xC18A, struct.pack("<III", 0xD103, 1, 2) + b"abcd"))
    assert (other.kind, other.values, other.raw_values) == (1, (), (b"abcd",))
    (empty,) = ev.parse_eos_events(record(0xC18A, struct.pack("<III", 0xD103, 3, 0)))
    assert (empty.values, empty.raw_values) == ((), ())
    # more items claimed than bytes: that record is undecoded, the next one still read
    bad = record(0xC18A, struct.pack("<III", 0xD101, 3, 9) + struct.pack("<2I", 1, 2))
    got_bad = ev.parse_eos_events(bad + record(0xC182, struct.pack("<I", 5)) + END)
    assert isinstance(got_bad[0], ev.EosUndecodedRecord) and "claims 9 values in 8 bytes" in got_bad[0].reason
    assert got_bad[1] == ev.EosObjectRemoved(5)
    bad7 = record(0xC18A, struct.pack("<III", 0xD101, 3, 3) + struct.pack("<2I", 1, 2))
    assert isinstance(ev.parse_eos_events(bad7)[0], ev.EosUndecodedRecord)
    # image formats (0xD120): items are ImageFormat structs, values their index
    raw_jpeg = struct.pack("<IIIII", 1, 0x10, 1, 0, 3)
    raw_both = struct.pack("<IIIIIIIII", 2, 0x10, 6, 0, 4, 0x10, 1, 0, 3)
    (formats,) = ev.parse_eos_events(record(0xC18A, struct.pack("<III", 0xD120, 3, 2) + raw_jpeg + raw_both))
    assert formats.values == (0, 1) and formats.raw_values == (raw_jpeg, raw_both)
    too_many = record(0xC18A, struct.pack("<III", 0xD120, 3, 3) + raw_jpeg + raw_jpeg)
    assert "claims 3 image formats in 40 bytes" in ev.parse_eos_events(too_many)[0].reason
    assert ev.pack_eos_event(formats) == record(0xC18A, struct.pack("<III", 0xD120, 3, 2) + raw_jpeg + raw_both)
    assert ev.pack_eos_event(got) == enum


def test_image_format_struct() -> None:
    raw = ev.pack_image_format(((6, 0, 4), (1, 0, 3)))
    assert raw == struct.pack("<9I", 2, 0x10, 6, 0, 4, 0x10, 1, 0, 3)
    assert ev.image_format_of(raw) == ((6, 0, 4), (1, 0, 3))
    assert ev.parse_image_format(Reader(struct.pack("<5I", 1, 0x10, 1, 2, 3))) == ((1, 2, 3),)
    for bad in (struct.pack("<I", 0), struct.pack("<I", 3), struct.pack("<5I", 1, 0x0C, 1, 2, 3), b"\x01"):
        assert ev.image_format_of(bad) is None
    with pytest.raises(ProtocolError, match="lists 3 files"):
        ev.parse_image_format(Reader(struct.pack("<I", 3)))
    with pytest.raises(ProtocolError, match="entry size is 12"):
        ev.parse_image_format(Reader(struct.pack("<5I", 1, 0x0C, 1, 2, 3)))
    for entries in ((), ((1, 0, 3),) * 3):
        with pytest.raises(ProtocolError):
            ev.pack_image_format(entries)


def test_broken_framing_keeps_what_came_before() -> None:
    first = record(0xC182, struct.pack("<I", 1))
    (kept, broken) = ev.parse_eos_events(first + b"\x01\x02\x03")
    assert kept == ev.EosObjectRemoved(1)
    assert isinstance(broken, ev.EosUndecodedRecord) and "header truncated at offset 12" in broken.reason
    assert broken.body == b"\x01\x02\x03"
    (kept, short) = ev.parse_eos_events(first + struct.pack("<II", 7, 0xC182) + b"zz")
    assert "claims 7 bytes, less than 8" in short.reason and short.code == 0xC182 and short.body == b"zz"
    (kept, long) = ev.parse_eos_events(first + struct.pack("<II", 20, 0xC182) + b"zz")
    assert "claims 20 bytes, 10 left" in long.reason and long.body == b"zz"
    # exactly fitting is fine; a record whose body is too short for its code is undecoded, the next read
    got = ev.parse_eos_events(record(0xC182, b"\x01\x00") + record(0xC18B, struct.pack("<I", 1)))
    assert isinstance(got[0], ev.EosUndecodedRecord) and got[0].code == 0xC182 and got[0].body == b"\x01\x00"
    assert got[1] == ev.EosCameraStatus(1)
    assert ev.parse_eos_events(b"") == []
    assert ev.parse_eos_events(END) == []
    # an object record cut inside its fixed fields
    cut = record(0xC181, struct.pack("<IIH", 1, 2, 3))
    assert isinstance(ev.parse_eos_events(cut)[0], ev.EosUndecodedRecord)


def test_size_limits() -> None:
    with pytest.raises(ProtocolError, match="exceeds"):
        ev.parse_eos_events(bytes(MAX_DATASET_BYTES + 1))
    one = record(0xC182, struct.pack("<I", 1))
    assert len(ev.parse_eos_events(one * ev.MAX_EVENT_RECORDS)) == ev.MAX_EVENT_RECORDS
    with pytest.raises(ProtocolError, match="more than 65536 records"):
        ev.parse_eos_events(one * (ev.MAX_EVENT_RECORDS + 1))


def test_object_added_names_are_cut_to_the_field_and_round_trip() -> None:
    added = ev.EosObjectAdded(5, 0x00020001, 0xB103, 123456, 0x90000000, "IMG_0001.CR2")
    raw = ev.pack_eos_events([added, ev.EosObjectAdded(6, 1, 2, 3, 4, "X", changed=True)])
    assert struct.unpack_from("<I", raw, 4)[0] == 0xC181
    got = ev.parse_eos_events(raw)
    assert got[0] == added and got[1].changed and got[1].filename == "X"
    assert struct.unpack_from("<I", raw, struct.unpack_from("<I", raw)[0] + 4)[0] == 0xC187
    long_name = "N" * 400
    (cut,) = ev.parse_eos_events(ev.pack_eos_event(ev.EosObjectAdded(1, 1, 1, 1, 1, long_name)))
    assert cut.filename == "N" * 255
    with pytest.raises(TypeError):
        ev.pack_eos_event("not an event")  # type: ignore[arg-type]
    undecoded = ev.EosUndecodedRecord(0xC1AA, b"\x01\x02", "why")
    assert ev.pack_eos_event(undecoded) == record(0xC1AA, b"\x01\x02")


def test_image_format_types_and_frozen_records() -> None:
    from dataclasses import FrozenInstanceError

    # ImageFormat file types as libgphoto2's EOS decoder names them: 1 JPEG, 6 CR2
    assert (ev.IMAGE_TYPE_JPEG, ev.IMAGE_TYPE_RAW) == (1, 6)
    for value in (
        ev.EosObjectAdded(1, 2, 3, 4, 5, "A"),
        ev.EosRequestObjectTransfer(1, 2, 3, "A"),
        ev.EosObjectRemoved(1),
        ev.EosPropValueChanged(1, 2),
        ev.EosAvailListChanged(1, 3, ()),
        ev.EosCameraStatus(1),
        ev.EosUnknownEvent(1, b""),
        ev.EosUndecodedRecord(1, b""),
    ):
        field = next(iter(value.__dataclass_fields__))
        with pytest.raises(FrozenInstanceError):
            setattr(value, field, 9)
