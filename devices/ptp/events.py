"""The Canon EOS GetEvent record list (0x9116 data phase): dataclasses with pure pack/parse functions.

Record layout (all little-endian): u32 size, u32 code, body; the list ends
with a record of size 8 and code 0. Offsets below are from the record start.

Real bodies send records nobody has a decoder for (0xC1F6 on an R10, OLC
blocks, property lists of types 1 and 7, string values shorter than a u32).
Such a record never costs the others: an unknown code becomes
`EosUnknownEvent`, a known code whose body does not decode becomes
`EosUndecodedRecord` with the reason, and a list whose framing breaks keeps
every record before the break (as libgphoto2 does). Only a list larger than
`MAX_DATASET_BYTES` or with more than `MAX_EVENT_RECORDS` records is refused.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from mca.devices.ptp.codec import MAX_DATASET_BYTES, ProtocolError, Reader, u32
from mca.devices.ptp.codes import EosEventCode, EosProp

#: A poll never yields more records than this (a camera that claims more is misbehaving).
MAX_EVENT_RECORDS = 65536
#: File names in EOS records are fixed-size ASCII fields on the camera; longer ones are cut.
MAX_EVENT_FILENAME_BYTES = 256
#: Offsets inside records, from the record start (ptp-canon-eos fact sheet; the 400D trace's 0xC181 agrees).
OBJECT_ADDED_NAME_OFFSET = 0x28
REQUEST_TRANSFER_NAME_OFFSET = 0x1C
#: The property-list type whose items are u32-spaced values (libgphoto2 decodes only this one).
AVAIL_LIST_ENUM = 3
IMAGE_FORMAT_PROPS = (EosProp.IMAGE_FORMAT, EosProp.IMAGE_FORMAT_CF, EosProp.IMAGE_FORMAT_SD)


@dataclass(frozen=True)
class EosObjectAdded:
    """0xC181 ObjectAddedEx (or 0xC187 ObjectInfoChangedEx when `changed`): a file or folder appeared on a card."""

    handle: int
    storage_id: int
    object_format: int
    size_bytes: int
    parent: int
    filename: str
    changed: bool = False


@dataclass(frozen=True)
class EosRequestObjectTransfer:
    """0xC186: a shot waits in camera RAM for the host to download it."""

    handle: int
    object_format: int
    size_bytes: int
    filename: str


@dataclass(frozen=True)
class EosObjectRemoved:
    handle: int


@dataclass(frozen=True)
class EosPropValueChanged:
    """0xC189: a property's value.

    `raw` is the whole value body (ImageFormat is a struct, strings are NUL-terminated ASCII, some values are a
    single byte); `value` is its first bytes read as a little-endian unsigned integer (at most 4 of them).
    """

    prop: int
    value: int
    raw: bytes = field(default=b"", repr=False)

    @property
    def text(self) -> str:
        """The value read as a NUL-terminated ASCII string (Owner, Artist, SerialNumber, LensName)."""
        raw = self.raw or u32(self.value)
        return raw.split(b"\x00", 1)[0].decode("ascii", errors="replace")


@dataclass(frozen=True)
class EosAvailListChanged:
    """0xC18A: the values a property may take.

    `kind` is the list type the camera sent (3 = enumeration of u32-spaced items, the only one libgphoto2
    decodes; 1 and 7 occur with no items). `values` holds the enumeration's items as integers (for image
    formats: their index), `raw_values` each item's bytes.
    """

    prop: int
    kind: int
    values: tuple[int, ...]
    raw_values: tuple[bytes, ...] = field(default=(), repr=False)


@dataclass(frozen=True)
class EosCameraStatus:
    """0xC18B: the camera's status word; 1 means busy (writing, focusing), anything else is not busy."""

    status: int

    @property
    def busy(self) -> bool:
        return self.status == 1


@dataclass(frozen=True)
class EosUnknownEvent:
    """A record code this parser has no decoder for; skipped by the host, shown by `mca camera doctor`."""

    code: int
    body: bytes = field(repr=False)


@dataclass(frozen=True)
class EosUndecodedRecord:
    """A record that could not be decoded (body too short, list framing broken); the others are kept."""

    code: int
    body: bytes = field(repr=False)
    reason: str = ""


EosEvent = (
    EosObjectAdded
    | EosRequestObjectTransfer
    | EosObjectRemoved
    | EosPropValueChanged
    | EosAvailListChanged
    | EosCameraStatus
    | EosUnknownEvent
    | EosUndecodedRecord
)


# ImageFormat (0xD120) values are a struct: u32 count (1 or 2), then per file u32 0x10, type, size, compression.
IMAGE_TYPE_JPEG = 1
IMAGE_TYPE_RAW = 6
IMAGE_FORMAT_ENTRY_BYTES = 0x10
ImageFormatEntry = tuple[int, int, int]  # (type, size, compression)


def pack_image_format(entries: tuple[ImageFormatEntry, ...]) -> bytes:
    if len(entries) not in (1, 2):
        raise ProtocolError("an EOS image format names one or two files")
    out = [u32(len(entries))]
    for kind, size, compression in entries:
        out += [u32(IMAGE_FORMAT_ENTRY_BYTES), u32(kind), u32(size), u32(compression)]
    return b"".join(out)


def parse_image_format(r: Reader) -> tuple[ImageFormatEntry, ...]:
    count = r.u32()
    if count not in (1, 2):
        raise ProtocolError(f"EOS image format lists {count} files, expected 1 or 2")
    entries = []
    for _ in range(count):
        entry_bytes = r.u32()
        if entry_bytes != IMAGE_FORMAT_ENTRY_BYTES:
            raise ProtocolError(f"EOS image format entry size is {entry_bytes}, not {IMAGE_FORMAT_ENTRY_BYTES}")
        entries.append((r.u32(), r.u32(), r.u32()))
    return tuple(entries)


def image_format_of(raw: bytes) -> tuple[ImageFormatEntry, ...] | None:
    """The entries of an ImageFormat value, or None when it does not decode."""
    try:
        return parse_image_format(Reader(raw))
    except ProtocolError:
        return None


def _name_field(name: str) -> bytes:
    raw = name.encode("ascii", errors="replace")[: MAX_EVENT_FILENAME_BYTES - 1]
    return raw + b"\x00"


def _pad4(b: bytes) -> bytes:
    return b + b"\x00" * (-len(b) % 4)


def _record(code: int, body: bytes) -> bytes:
    return u32(8 + len(body)) + u32(code) + body


def pack_eos_event(event: EosEvent) -> bytes:
    """One record, size included."""
    if isinstance(event, EosObjectAdded):
        body = (
            struct.pack(
                "<IIHHIIII",
                event.handle,
                event.storage_id,
                event.object_format,
                0,
                0,
                0,
                event.size_bytes,
                event.parent,
            )
            + u32(event.handle)  # the 400D trace repeats the object id here
            + _name_field(event.filename)
        )
        code = EosEventCode.OBJECT_INFO_CHANGED_EX if event.changed else EosEventCode.OBJECT_ADDED_EX
        return _record(code, _pad4(body) + u32(0))  # a u32 follows the name (the 400D record is 0x3C bytes)
    if isinstance(event, EosRequestObjectTransfer):
        body = struct.pack("<IIIII", event.handle, event.object_format, 0, event.size_bytes, 0) + _name_field(
            event.filename
        )
        return _record(EosEventCode.REQUEST_OBJECT_TRANSFER, _pad4(body))
    if isinstance(event, EosObjectRemoved):
        return _record(EosEventCode.OBJECT_REMOVED, u32(event.handle))
    if isinstance(event, EosPropValueChanged):
        return _record(EosEventCode.PROP_VALUE_CHANGED, u32(event.prop) + (event.raw or u32(event.value)))
    if isinstance(event, EosAvailListChanged):
        items = b"".join(event.raw_values) if event.raw_values else b"".join(u32(v) for v in event.values)
        count = len(event.raw_values) if event.raw_values else len(event.values)
        return _record(EosEventCode.AVAIL_LIST_CHANGED, u32(event.prop) + u32(event.kind) + u32(count) + items)
    if isinstance(event, EosCameraStatus):
        return _record(EosEventCode.CAMERA_STATUS_CHANGED, u32(event.status))
    if isinstance(event, (EosUnknownEvent, EosUndecodedRecord)):
        return _record(event.code, event.body)
    raise TypeError(f"not an EOS event: {event!r}")


def pack_eos_events(events: list[EosEvent] | tuple[EosEvent, ...]) -> bytes:
    """The GetEvent data phase: the records then the terminator (size 8, code 0)."""
    return b"".join(pack_eos_event(e) for e in events) + u32(8) + u32(0)


def _int_le(raw: bytes) -> int:
    return int.from_bytes(raw[:4], "little")


def _parse_avail_list(r: Reader) -> EosAvailListChanged:
    prop, kind, count = r.u32(), r.u32(), r.u32()
    rest = r.take(r.remaining)
    if prop in IMAGE_FORMAT_PROPS and count:
        items = Reader(rest)
        if count > len(rest) // (4 + IMAGE_FORMAT_ENTRY_BYTES):
            raise ProtocolError(f"AvailListChanged claims {count} image formats in {len(rest)} bytes")
        formats = []
        for _ in range(count):
            start = items.pos
            parse_image_format(items)
            formats.append(rest[start : items.pos])
        return EosAvailListChanged(prop, kind, tuple(range(len(formats))), tuple(formats))
    if kind != AVAIL_LIST_ENUM or count == 0:
        return EosAvailListChanged(prop, kind, (), (rest,) if rest else ())
    if count > len(rest):
        raise ProtocolError(f"AvailListChanged claims {count} values in {len(rest)} bytes")
    # Items are u32-spaced on every body seen; the 70D's 0xD17D list has 12-byte items (396 bytes for 33).
    item_bytes = len(rest) // count if len(rest) % count == 0 else 4
    if count * item_bytes > len(rest):
        raise ProtocolError(f"AvailListChanged claims {count} values in {len(rest)} bytes")
    raws = tuple(rest[i * item_bytes : (i + 1) * item_bytes] for i in range(count))
    return EosAvailListChanged(prop, kind, tuple(_int_le(x) for x in raws), raws)


def _parse_record(code: int, r: Reader) -> EosEvent:
    if code in (EosEventCode.OBJECT_ADDED_EX, EosEventCode.OBJECT_INFO_CHANGED_EX):
        handle, storage, fmt = r.u32(), r.u32(), r.u16()
        r.take(10)
        size, parent = r.u32(), r.u32()
        r.take(4)
        name = r.cstring_ascii(MAX_EVENT_FILENAME_BYTES)
        return EosObjectAdded(
            handle, storage, fmt, size, parent, name, changed=code == EosEventCode.OBJECT_INFO_CHANGED_EX
        )
    if code == EosEventCode.REQUEST_OBJECT_TRANSFER:
        handle, fmt = r.u32(), r.u32()
        r.take(4)
        size = r.u32()
        r.take(4)
        return EosRequestObjectTransfer(handle, fmt & 0xFFFF, size, r.cstring_ascii(MAX_EVENT_FILENAME_BYTES))
    if code == EosEventCode.OBJECT_REMOVED:
        return EosObjectRemoved(r.u32())
    if code == EosEventCode.PROP_VALUE_CHANGED:
        prop = r.u32()
        raw = r.take(r.remaining)
        return EosPropValueChanged(prop, _int_le(raw), raw)
    if code == EosEventCode.AVAIL_LIST_CHANGED:
        return _parse_avail_list(r)
    if code == EosEventCode.CAMERA_STATUS_CHANGED:
        return EosCameraStatus(r.u32())
    return EosUnknownEvent(code, r.take(r.remaining))


def parse_eos_events(buf: bytes | bytearray | memoryview) -> list[EosEvent]:
    """Parse a GetEvent data phase; see the module docstring for what is kept when records are odd."""
    if len(buf) > MAX_DATASET_BYTES:
        raise ProtocolError(f"EOS event list of {len(buf)} bytes exceeds the {MAX_DATASET_BYTES}-byte limit")
    data = bytes(buf)
    events: list[EosEvent] = []
    pos = 0
    while pos < len(data):
        if len(data) - pos < 8:
            events.append(EosUndecodedRecord(0, data[pos:], f"record header truncated at offset {pos}"))
            break
        size, code = struct.unpack_from("<II", data, pos)
        if size < 8:
            events.append(
                EosUndecodedRecord(code, data[pos + 8 :], f"record at offset {pos} claims {size} bytes, less than 8")
            )
            break
        if size > len(data) - pos:
            events.append(
                EosUndecodedRecord(
                    code, data[pos + 8 :], f"record at offset {pos} claims {size} bytes, {len(data) - pos} left"
                )
            )
            break
        if size == 8 and code == 0:
            break
        if len(events) >= MAX_EVENT_RECORDS:
            raise ProtocolError(f"EOS event list holds more than {MAX_EVENT_RECORDS} records")
        try:
            events.append(_parse_record(code, Reader(data, pos + 8, pos + size)))
        except ProtocolError as exc:
            events.append(EosUndecodedRecord(code, data[pos + 8 : pos + size], str(exc)))
        pos += size
    return events


# -- FocusInfoEx (0xD1D3) ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FocusInfo:
    """The autofocus points of a FocusInfoEx value and which of them are in focus.

    Layout (the 70D's hand decode and libgphoto2 agree): u32 size, u16 half size, u16 version, u16 points in
    the struct (n), u16 points in use, u16 width and height of the image twice, then tables of n u16 each:
    heights, widths, x and y centres (signed, from the image centre), then a bit mask of the points in focus.
    """

    version: int
    points_total: int
    points_in_use: int
    image_width_px: int
    image_height_px: int
    in_focus: tuple[tuple[int, int, int, int], ...]  # (x, y, width, height) of each point in focus

    @property
    def focused(self) -> bool:
        return bool(self.in_focus)


FOCUS_INFO_HEADER_BYTES = 20


def parse_focus_info_ex(raw: bytes) -> FocusInfo | None:
    """The FocusInfoEx value, or None when it is a zero-filled placeholder. Malformed values raise ProtocolError."""
    r = Reader(raw)
    size = r.u32()
    if size > len(raw) or size < FOCUS_INFO_HEADER_BYTES:
        raise ProtocolError(f"FocusInfoEx claims {size} bytes in a value of {len(raw)}")
    r.u16()  # half size
    version, total, in_use = r.u16(), r.u16(), r.u16()
    width, height = r.u16(), r.u16()
    if not total or not in_use:
        return None
    if in_use > total:
        raise ProtocolError(f"FocusInfoEx uses {in_use} of {total} points")
    if FOCUS_INFO_HEADER_BYTES + 8 * total + (total + 7) // 8 > size:
        raise ProtocolError(f"FocusInfoEx with {total} points does not fit {size} bytes")
    base = FOCUS_INFO_HEADER_BYTES
    mask_at = base + 8 * total
    points = []
    for i in range(in_use):
        if not raw[mask_at + i // 8] & (1 << (i % 8)):
            continue
        h, w, x, y = (struct.unpack_from("<h", raw, base + 2 * total * k + 2 * i)[0] for k in range(4))
        points.append((x, y, w, h))
    return FocusInfo(version, total, in_use, width, height, tuple(points))


def pack_focus_info_ex(
    points: list[tuple[int, int, int, int]], in_focus: set[int], image_size_px: tuple[int, int], version: int = 4
) -> bytes:
    """A FocusInfoEx value: `points` are (x, y, width, height); `in_focus` the indices of the focused ones."""
    n = len(points)
    tables = b"".join(struct.pack(f"<{n}h", *(p[k] for p in points)) for k in (3, 2, 0, 1))
    mask = bytearray((n + 7) // 8)
    for i in in_focus:
        mask[i // 8] |= 1 << (i % 8)
    body = struct.pack("<7H", version, n, n, *image_size_px, *image_size_px) + tables + bytes(mask)
    size = 6 + len(body)
    return struct.pack("<IH", size, size - 4) + body
