"""The Canon EOS GetEvent record list (0x9116 data phase): dataclasses with pure pack/parse functions.

Record layout (all little-endian): u32 size, u32 code, body; the list ends
with a record of size 8 and code 0. Offsets below are from the record start.
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
    """0xC189: a property's value; `value` is the first u32, `raw` the whole value body (ImageFormat is a struct)."""

    prop: int
    value: int
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class EosAvailListChanged:
    """0xC18A: the values a property may take (u32 items)."""

    prop: int
    datatype: int
    values: tuple[int, ...]
    raw_values: tuple[bytes, ...] = field(default=(), repr=False)


@dataclass(frozen=True)
class EosCameraStatus:
    """0xC18B: 1 while the camera is busy (writing, focusing), 0 when ready."""

    busy: bool


@dataclass(frozen=True)
class EosUnknownEvent:
    code: int
    body: bytes = field(repr=False)


EosEvent = (
    EosObjectAdded
    | EosRequestObjectTransfer
    | EosObjectRemoved
    | EosPropValueChanged
    | EosAvailListChanged
    | EosCameraStatus
    | EosUnknownEvent
)


# ImageFormat (0xD120) values are a struct: u32 count (1 or 2), then per file u32 0x10, type, size, compression.
IMAGE_TYPE_JPEG = 1
IMAGE_TYPE_RAW = 6
ImageFormatEntry = tuple[int, int, int]  # (type, size, compression)


def pack_image_format(entries: tuple[ImageFormatEntry, ...]) -> bytes:
    if len(entries) not in (1, 2):
        raise ProtocolError("an EOS image format names one or two files")
    out = [u32(len(entries))]
    for kind, size, compression in entries:
        out += [u32(0x10), u32(kind), u32(size), u32(compression)]
    return b"".join(out)


def parse_image_format(r: Reader) -> tuple[ImageFormatEntry, ...]:
    count = r.u32()
    if count not in (1, 2):
        raise ProtocolError(f"EOS image format lists {count} files, expected 1 or 2")
    entries = []
    for _ in range(count):
        if r.u32() != 0x10:
            raise ProtocolError("EOS image format entry size is not 16")
        entries.append((r.u32(), r.u32(), r.u32()))
    return tuple(entries)


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
            + u32(0)
            + _name_field(event.filename)
        )
        code = EosEventCode.OBJECT_INFO_CHANGED_EX if event.changed else EosEventCode.OBJECT_ADDED_EX
        return _record(code, _pad4(body))
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
        return _record(EosEventCode.AVAIL_LIST_CHANGED, u32(event.prop) + u32(event.datatype) + u32(count) + items)
    if isinstance(event, EosCameraStatus):
        return _record(EosEventCode.CAMERA_STATUS_CHANGED, u32(1 if event.busy else 0))
    if isinstance(event, EosUnknownEvent):
        return _record(event.code, event.body)
    raise TypeError(f"not an EOS event: {event!r}")


def pack_eos_events(events: list[EosEvent] | tuple[EosEvent, ...]) -> bytes:
    """The GetEvent data phase: the records then the terminator (size 8, code 0)."""
    return b"".join(pack_eos_event(e) for e in events) + u32(8) + u32(0)


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
        if prop == EosProp.IMAGE_FORMAT:
            parse_image_format(Reader(raw))  # validates the struct
        if len(raw) < 4:
            raise ProtocolError(f"PropValueChanged for 0x{prop:04X} carries {len(raw)} value bytes, needs 4")
        return EosPropValueChanged(prop, struct.unpack_from("<I", raw)[0], raw)
    if code == EosEventCode.AVAIL_LIST_CHANGED:
        prop, datatype, count = r.u32(), r.u32(), r.u32()
        if prop == EosProp.IMAGE_FORMAT:
            raws = []
            if count > r.remaining // 20:
                raise ProtocolError(f"AvailListChanged claims {count} image formats in {r.remaining} bytes")
            for _ in range(count):
                start = r.pos
                parse_image_format(r)
                raws.append(r._buf[start : r.pos])
            return EosAvailListChanged(prop, datatype, tuple(range(len(raws))), tuple(raws))
        if count * 4 > r.remaining:
            raise ProtocolError(f"AvailListChanged claims {count} values in {r.remaining} bytes")
        values = struct.unpack_from(f"<{count}I", r._buf, r.pos)
        r.pos += 4 * count
        return EosAvailListChanged(prop, datatype, values)
    if code == EosEventCode.CAMERA_STATUS_CHANGED:
        return EosCameraStatus(bool(r.u32()))
    return EosUnknownEvent(code, r.take(r.remaining))


def parse_eos_events(buf: bytes | bytearray | memoryview) -> list[EosEvent]:
    """Parse a GetEvent data phase. A missing terminator is tolerated at the very end of the data."""
    if len(buf) > MAX_DATASET_BYTES:
        raise ProtocolError(f"EOS event list of {len(buf)} bytes exceeds the {MAX_DATASET_BYTES}-byte limit")
    data = bytes(buf)
    events: list[EosEvent] = []
    pos = 0
    while pos < len(data):
        if len(data) - pos < 8:
            raise ProtocolError(f"EOS event record header truncated at offset {pos}")
        size, code = struct.unpack_from("<II", data, pos)
        if size < 8:
            raise ProtocolError(f"EOS event record at offset {pos} claims {size} bytes, less than its header")
        if pos + size > len(data):
            raise ProtocolError(f"EOS event record at offset {pos} claims {size} bytes, only {len(data) - pos} left")
        if size == 8 and code == 0:
            return events
        if len(events) >= MAX_EVENT_RECORDS:
            raise ProtocolError(f"EOS event list holds more than {MAX_EVENT_RECORDS} records")
        events.append(_parse_record(code, Reader(data, pos + 8, pos + size)))
        pos += size
    return events
