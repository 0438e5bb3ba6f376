"""PTP datasets (DeviceInfo, StorageInfo, ObjectInfo, DevicePropDesc): dataclasses with pure pack/parse functions."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from mca.devices.ptp.codec import (
    MAX_DATASET_BYTES,
    ProtocolError,
    Reader,
    pack_array,
    pack_string,
    u16,
    u32,
    u64,
)
from mca.devices.ptp.codes import DataType

_SCALAR_FORMATS: dict[int, str] = {
    DataType.INT8: "b",
    DataType.UINT8: "B",
    DataType.INT16: "h",
    DataType.UINT16: "H",
    DataType.INT32: "i",
    DataType.UINT32: "I",
    DataType.INT64: "q",
    DataType.UINT64: "Q",
}
_ARRAY_FLAG = 0x4000


def _check_size(buf: bytes | bytearray | memoryview, what: str) -> None:
    if len(buf) > MAX_DATASET_BYTES:
        raise ProtocolError(f"{what} of {len(buf)} bytes exceeds the {MAX_DATASET_BYTES}-byte limit")


@dataclass(frozen=True)
class DeviceInfo:
    standard_version: int = 100
    vendor_extension_id: int = 0
    vendor_extension_version: int = 0
    vendor_extension_desc: str = ""
    functional_mode: int = 0
    operations: tuple[int, ...] = ()
    events: tuple[int, ...] = ()
    properties: tuple[int, ...] = ()
    capture_formats: tuple[int, ...] = ()
    image_formats: tuple[int, ...] = ()
    manufacturer: str = ""
    model: str = ""
    device_version: str = ""
    serial_number: str = ""

    def supports(self, op: int) -> bool:
        return op in self.operations


def pack_device_info(info: DeviceInfo) -> bytes:
    return b"".join(
        [
            u16(info.standard_version),
            u32(info.vendor_extension_id),
            u16(info.vendor_extension_version),
            pack_string(info.vendor_extension_desc),
            u16(info.functional_mode),
            pack_array("H", info.operations),
            pack_array("H", info.events),
            pack_array("H", info.properties),
            pack_array("H", info.capture_formats),
            pack_array("H", info.image_formats),
            pack_string(info.manufacturer),
            pack_string(info.model),
            pack_string(info.device_version),
            pack_string(info.serial_number),
        ]
    )


def parse_device_info(buf: bytes | bytearray | memoryview) -> DeviceInfo:
    _check_size(buf, "DeviceInfo")
    r = Reader(buf)
    return DeviceInfo(
        standard_version=r.u16(),
        vendor_extension_id=r.u32(),
        vendor_extension_version=r.u16(),
        vendor_extension_desc=r.string(),
        functional_mode=r.u16(),
        operations=r.array("H"),
        events=r.array("H"),
        properties=r.array("H"),
        capture_formats=r.array("H"),
        image_formats=r.array("H"),
        manufacturer=r.string(),
        model=r.string(),
        device_version=r.string(),
        serial_number=r.string(),
    )


@dataclass(frozen=True)
class StorageInfo:
    storage_type: int = 4  # removable RAM (a memory card)
    filesystem_type: int = 2  # generic hierarchical
    access_capability: int = 0  # read-write
    max_capacity_bytes: int = 0
    free_space_bytes: int = 0
    free_space_images: int = 0xFFFFFFFF
    description: str = ""
    volume_label: str = ""


def pack_storage_info(info: StorageInfo) -> bytes:
    return b"".join(
        [
            u16(info.storage_type),
            u16(info.filesystem_type),
            u16(info.access_capability),
            u64(info.max_capacity_bytes),
            u64(info.free_space_bytes),
            u32(info.free_space_images),
            pack_string(info.description),
            pack_string(info.volume_label),
        ]
    )


def parse_storage_info(buf: bytes | bytearray | memoryview) -> StorageInfo:
    _check_size(buf, "StorageInfo")
    r = Reader(buf)
    return StorageInfo(r.u16(), r.u16(), r.u16(), r.u64(), r.u64(), r.u32(), r.string(), r.string())


@dataclass(frozen=True)
class ObjectInfo:
    storage_id: int = 0
    object_format: int = 0
    protection_status: int = 0
    compressed_size_bytes: int = 0
    thumb_format: int = 0
    thumb_compressed_size_bytes: int = 0
    thumb_width_px: int = 0
    thumb_height_px: int = 0
    image_width_px: int = 0
    image_height_px: int = 0
    image_bit_depth: int = 0
    parent_object: int = 0
    association_type: int = 0
    association_desc: int = 0
    sequence_number: int = 0
    filename: str = ""
    capture_date: str = ""
    modification_date: str = ""
    keywords: str = ""


def pack_object_info(info: ObjectInfo) -> bytes:
    return b"".join(
        [
            u32(info.storage_id),
            u16(info.object_format),
            u16(info.protection_status),
            u32(info.compressed_size_bytes),
            u16(info.thumb_format),
            u32(info.thumb_compressed_size_bytes),
            u32(info.thumb_width_px),
            u32(info.thumb_height_px),
            u32(info.image_width_px),
            u32(info.image_height_px),
            u32(info.image_bit_depth),
            u32(info.parent_object),
            u16(info.association_type),
            u32(info.association_desc),
            u32(info.sequence_number),
            pack_string(info.filename),
            pack_string(info.capture_date),
            pack_string(info.modification_date),
            pack_string(info.keywords),
        ]
    )


def parse_object_info(buf: bytes | bytearray | memoryview) -> ObjectInfo:
    _check_size(buf, "ObjectInfo")
    r = Reader(buf)
    return ObjectInfo(
        storage_id=r.u32(),
        object_format=r.u16(),
        protection_status=r.u16(),
        compressed_size_bytes=r.u32(),
        thumb_format=r.u16(),
        thumb_compressed_size_bytes=r.u32(),
        thumb_width_px=r.u32(),
        thumb_height_px=r.u32(),
        image_width_px=r.u32(),
        image_height_px=r.u32(),
        image_bit_depth=r.u32(),
        parent_object=r.u32(),
        association_type=r.u16(),
        association_desc=r.u32(),
        sequence_number=r.u32(),
        filename=r.string(),
        capture_date=r.string(),
        modification_date=r.string(),
        keywords=r.string() if r.remaining else "",
    )


PropValue = int | str | tuple[int, ...]


@dataclass(frozen=True)
class DevicePropDesc:
    """A device property: type, current and default value, and its allowed values (range or enumeration)."""

    code: int
    datatype: int
    writable: bool
    factory_default: PropValue
    current: PropValue
    form: str = "none"  # "none", "range" or "enum"
    range_min: int = 0
    range_max: int = 0
    range_step: int = 0
    allowed: tuple[PropValue, ...] = field(default=())


def _pack_value(datatype: int, value: PropValue) -> bytes:
    if datatype == DataType.STR:
        return pack_string(str(value))
    if datatype & _ARRAY_FLAG:
        fmt = _SCALAR_FORMATS.get(datatype & ~_ARRAY_FLAG)
        if fmt is None:
            raise ProtocolError(f"unknown array datatype 0x{datatype:04X}")
        return pack_array(fmt, tuple(value))  # type: ignore[arg-type]
    fmt = _SCALAR_FORMATS.get(datatype)
    if fmt is None:
        raise ProtocolError(f"unknown datatype 0x{datatype:04X}")
    return struct.pack("<" + fmt, value)


def pack_prop_value(datatype: int, value: PropValue) -> bytes:
    """The data phase of SetDevicePropValue / GetDevicePropValue."""
    return _pack_value(datatype, value)


def _read_value(r: Reader, datatype: int) -> PropValue:
    if datatype == DataType.STR:
        return r.string()
    if datatype & _ARRAY_FLAG:
        fmt = _SCALAR_FORMATS.get(datatype & ~_ARRAY_FLAG)
        if fmt is None:
            raise ProtocolError(f"unknown array datatype 0x{datatype:04X}")
        return r.array(fmt)
    fmt = _SCALAR_FORMATS.get(datatype)
    if fmt is None:
        raise ProtocolError(f"unknown datatype 0x{datatype:04X}")
    return r.scalar(fmt)


def parse_prop_value(buf: bytes | bytearray | memoryview, datatype: int) -> PropValue:
    _check_size(buf, "property value")
    return _read_value(Reader(buf), datatype)


def pack_prop_desc(desc: DevicePropDesc) -> bytes:
    parts = [
        u16(desc.code),
        u16(desc.datatype),
        bytes([1 if desc.writable else 0]),
        _pack_value(desc.datatype, desc.factory_default),
        _pack_value(desc.datatype, desc.current),
    ]
    if desc.form == "range":
        parts += [b"\x01"] + [_pack_value(desc.datatype, v) for v in (desc.range_min, desc.range_max, desc.range_step)]
    elif desc.form == "enum":
        if len(desc.allowed) > 0xFFFF:
            raise ProtocolError("enumeration longer than 65535 values")
        parts += [b"\x02", u16(len(desc.allowed))] + [_pack_value(desc.datatype, v) for v in desc.allowed]
    else:
        parts.append(b"\x00")
    return b"".join(parts)


def parse_prop_desc(buf: bytes | bytearray | memoryview) -> DevicePropDesc:
    _check_size(buf, "DevicePropDesc")
    r = Reader(buf)
    code, datatype, getset = r.u16(), r.u16(), r.u8()
    default = _read_value(r, datatype)
    current = _read_value(r, datatype)
    form_flag = r.u8() if r.remaining else 0
    if form_flag == 1:
        lo, hi, step = (_read_value(r, datatype) for _ in range(3))
        if not all(isinstance(v, int) for v in (lo, hi, step)):
            raise ProtocolError(f"range form on non-integer property 0x{code:04X}")
        return DevicePropDesc(code, datatype, bool(getset), default, current, "range", lo, hi, step)  # type: ignore[arg-type]
    if form_flag == 2:
        count = r.u16()
        if count > r.remaining:  # every value takes at least one byte
            raise ProtocolError(f"enumeration of {count} values does not fit the {r.remaining} bytes left")
        if datatype in (DataType.INT8, DataType.UINT8) and r.remaining == 2 * count and count:
            # EOS bodies (60D trace; 70D by libgphoto2's dump) declare BatteryLevel UINT8 but send the
            # enumeration as u16 words: 64 00 4b 00 32 00 19 00 00 00 is 100, 75, 50, 25, 0.
            words = struct.unpack_from(f"<{count}H", r.take(2 * count))
            if all(w <= 0xFF for w in words):
                return DevicePropDesc(code, datatype, bool(getset), default, current, "enum", allowed=words)
            r.pos -= 2 * count
        allowed = tuple(_read_value(r, datatype) for _ in range(count))
        return DevicePropDesc(code, datatype, bool(getset), default, current, "enum", allowed=allowed)
    if form_flag != 0:
        raise ProtocolError(f"unknown property form flag {form_flag} for 0x{code:04X}")
    return DevicePropDesc(code, datatype, bool(getset), default, current)


@dataclass(frozen=True)
class EosDeviceInfoEx:
    """EOS GetDeviceInfoEx (0x9108): the EOS event records and properties the body reports, and a third list.

    Layout: u32 (the dataset size on the bodies seen), then three u32 arrays: event codes, property codes and a
    list libgphoto2 calls "unk" (0, 1, 2, 4, 8 on the 70D and the 5D Mark III).
    """

    events: tuple[int, ...] = ()
    properties: tuple[int, ...] = ()
    unknown: tuple[int, ...] = ()


def pack_eos_device_info_ex(info: EosDeviceInfoEx) -> bytes:
    body = pack_array("I", info.events) + pack_array("I", info.properties) + pack_array("I", info.unknown)
    return u32(4 + len(body)) + body


def parse_eos_device_info_ex(buf: bytes | bytearray | memoryview) -> EosDeviceInfoEx:
    _check_size(buf, "DeviceInfoEx")
    r = Reader(buf)
    r.u32()
    return EosDeviceInfoEx(r.array("I"), r.array("I"), r.array("I"))


def parse_storage_ids(buf: bytes | bytearray | memoryview) -> tuple[int, ...]:
    """GetStorageIDs (0x1004 / EOS 0x9101): a u32 array."""
    _check_size(buf, "StorageIDs")
    return Reader(buf).array("I")


@dataclass(frozen=True)
class EosFolderEntry:
    """One entry of EOS GetObjectInfoEx (0x9109), the fast folder listing libgphoto2 uses on EOS bodies.

    Layout: u32 entry size (>= 56), then u32 handle, u32 storage, u16 format at +8, u8 flags at +16 (bit 0:
    read-only), u32 size at +20, 16-byte NUL-padded ASCII file name at +32, u32 time (seconds) at +48.
    """

    handle: int
    storage_id: int
    object_format: int
    flags: int
    size_bytes: int
    filename: str
    time_s: int


_FE_BODY_BYTES = 52


def pack_eos_folder_entries(entries: list[EosFolderEntry] | tuple[EosFolderEntry, ...]) -> bytes:
    out = [u32(len(entries))]
    for e in entries:
        body = bytearray(_FE_BODY_BYTES)
        struct.pack_into("<IIH", body, 0, e.handle, e.storage_id, e.object_format)
        body[16] = e.flags & 0xFF
        struct.pack_into("<I", body, 20, e.size_bytes)
        name = e.filename.encode("ascii", errors="replace")[:15]
        body[32 : 32 + len(name)] = name
        struct.pack_into("<I", body, 48, e.time_s)
        out.append(u32(4 + len(body)) + bytes(body))
    return b"".join(out)


def parse_eos_folder_entries(buf: bytes | bytearray | memoryview) -> tuple[EosFolderEntry, ...]:
    _check_size(buf, "EOS folder listing")
    r = Reader(buf)
    count = r.u32()
    if count * (4 + _FE_BODY_BYTES) > r.remaining:
        raise ProtocolError(f"folder listing claims {count} entries in {r.remaining} bytes")
    out = []
    for _ in range(count):
        size = r.u32()
        if size < 4 + _FE_BODY_BYTES:
            raise ProtocolError(f"folder entry of {size} bytes is shorter than {4 + _FE_BODY_BYTES}")
        body = r.take(size - 4)
        handle, storage, fmt = struct.unpack_from("<IIH", body, 0)
        (size_bytes,) = struct.unpack_from("<I", body, 20)
        (time_s,) = struct.unpack_from("<I", body, 48)
        name = body[32:48].split(b"\x00", 1)[0].decode("ascii", errors="replace")
        out.append(EosFolderEntry(handle, storage, fmt, body[16], size_bytes, name, time_s))
    return tuple(out)
