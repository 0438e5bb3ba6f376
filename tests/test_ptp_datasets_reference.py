"""PTP datasets against bytes laid out by hand from the standard (ISO 15740 section 5.5: DeviceInfo, StorageInfo,
ObjectInfo, DevicePropDesc) and from the EOS layouts documented in datasets.py; every bound of the parsers.
The real bodies' datasets are checked in tests/test_ptp_replay.py (the EOS traces).
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mca.devices.ptp import datasets as ds
from mca.devices.ptp.codec import MAX_DATASET_BYTES, ProtocolError


def s(text: str) -> bytes:
    """A PTP string by hand: u8 units incl. NUL, UTF-16LE."""
    return b"\x00" if not text else bytes([len(text) + 1]) + text.encode("utf-16-le") + b"\x00\x00"


def arr16(values: list[int]) -> bytes:
    return struct.pack(f"<I{len(values)}H", len(values), *values)


DEVICE_INFO = (
    struct.pack("<HIH", 100, 6, 200)
    + s("")
    + struct.pack("<H", 0)
    + arr16([0x1001, 0x1002, 0x9116])
    + arr16([0x4002, 0xC101])
    + arr16([0xD402])
    + arr16([0x3801])
    + arr16([0x3801, 0xB103])
    + s("Canon Inc.")
    + s("Canon EOS 70D")
    + s("3-1.1.1")
    + s("SIM70D0000001")
)


def test_device_info_fields_in_the_standard_order() -> None:
    info = ds.parse_device_info(DEVICE_INFO)
    assert info == ds.DeviceInfo(
        100, 6, 200, "", 0, (0x1001, 0x1002, 0x9116), (0x4002, 0xC101), (0xD402,), (0x3801,), (0x3801, 0xB103),
        "Canon Inc.", "Canon EOS 70D", "3-1.1.1", "SIM70D0000001",
    )  # fmt: skip
    assert info.supports(0x9116) and not info.supports(0x1009)
    assert ds.pack_device_info(info) == DEVICE_INFO
    for cut in (1, 5, 20, len(DEVICE_INFO) - 1):
        with pytest.raises(ProtocolError, match=r"truncated|does not fit"):
            ds.parse_device_info(DEVICE_INFO[:cut])


def test_storage_info_fields() -> None:
    raw = struct.pack("<HHHQQI", 4, 2, 0, 32 << 30, 1 << 30, 999) + s("SD") + s("EOS_DIGITAL")
    info = ds.parse_storage_info(raw)
    assert info == ds.StorageInfo(4, 2, 0, 32 << 30, 1 << 30, 999, "SD", "EOS_DIGITAL")
    assert ds.pack_storage_info(info) == raw
    with pytest.raises(ProtocolError):
        ds.parse_storage_info(raw[:25])


OBJECT_INFO = (
    struct.pack("<IHHIHIIIIIIIHII", 0x00020001, 0xB103, 0, 25_000_000, 0x3801, 9000, 160, 120, 5472, 3648, 14,
                0x90000000, 0, 0, 7)
    + s("IMG_0001.CR2") + s("20240501T101502") + s("20240501T101503") + s("mca")
)  # fmt: skip


def test_object_info_fields() -> None:
    info = ds.parse_object_info(OBJECT_INFO)
    assert info == ds.ObjectInfo(
        0x00020001, 0xB103, 0, 25_000_000, 0x3801, 9000, 160, 120, 5472, 3648, 14, 0x90000000, 0, 0, 7,
        "IMG_0001.CR2", "20240501T101502", "20240501T101503", "mca",
    )  # fmt: skip
    assert ds.pack_object_info(info) == OBJECT_INFO
    # keywords may be missing entirely (some bodies stop after the dates)
    without = OBJECT_INFO[: -len(s("mca"))]
    assert ds.parse_object_info(without).keywords == ""
    with pytest.raises(ProtocolError):
        ds.parse_object_info(OBJECT_INFO[:40])


@pytest.mark.parametrize(
    ("datatype", "fmt", "value"),
    [(0x0001, "b", -5), (0x0002, "B", 200), (0x0003, "h", -300), (0x0004, "H", 0xFFFF), (0x0005, "i", -70000),
     (0x0006, "I", 0xFFFFFFFF), (0x0007, "q", -(2**40)), (0x0008, "Q", 2**63)],
)  # fmt: skip
def test_scalar_property_values(datatype: int, fmt: str, value: int) -> None:
    raw = struct.pack("<" + fmt, value)
    assert ds.pack_prop_value(datatype, value) == raw
    assert ds.parse_prop_value(raw, datatype) == value
    array = struct.pack(f"<I2{fmt}", 2, value, value)
    assert ds.pack_prop_value(datatype | 0x4000, (value, value)) == array
    assert ds.parse_prop_value(array, datatype | 0x4000) == (value, value)


def test_string_and_unknown_property_values() -> None:
    assert ds.pack_prop_value(0xFFFF, "Owner") == s("Owner")
    assert ds.parse_prop_value(s("Owner"), 0xFFFF) == "Owner"
    for bad in (0x0009, 0x000A, 0x4009, 0x0000):
        with pytest.raises(ProtocolError, match=r"unknown (array )?datatype"):
            ds.parse_prop_value(b"\x00" * 16, bad)
        with pytest.raises(ProtocolError, match=r"unknown (array )?datatype"):
            ds.pack_prop_value(bad, 1 if not bad & 0x4000 else (1,))
    with pytest.raises(ProtocolError, match="exceeds"):
        ds.parse_prop_value(bytes(MAX_DATASET_BYTES + 1), 0x0002)


def test_prop_desc_forms() -> None:
    # ExposureBias-like: INT16, read-write, default 0, current -3, range -9..9 step 3
    rng = struct.pack("<HHB", 0x5010, 0x0003, 1) + struct.pack("<hh", 0, -3) + b"\x01" + struct.pack("<hhh", -9, 9, 3)
    got = ds.parse_prop_desc(rng)
    assert got == ds.DevicePropDesc(0x5010, 0x0003, True, 0, -3, "range", -9, 9, 3)
    assert ds.pack_prop_desc(got) == rng
    enum = (
        struct.pack("<HHB", 0x5007, 0x0004, 0)
        + struct.pack("<HH", 18, 40)
        + b"\x02"
        + struct.pack("<H3H", 3, 18, 40, 56)
    )
    got = ds.parse_prop_desc(enum)
    assert got == ds.DevicePropDesc(0x5007, 0x0004, False, 18, 40, "enum", allowed=(18, 40, 56))
    assert ds.pack_prop_desc(got) == enum
    plain = struct.pack("<HHB", 0xD402, 0xFFFF, 0) + s("Canon EOS 70D") + s("Canon EOS 70D") + b"\x00"
    got = ds.parse_prop_desc(plain)
    assert got == ds.DevicePropDesc(0xD402, 0xFFFF, False, "Canon EOS 70D", "Canon EOS 70D")
    assert ds.pack_prop_desc(got) == plain
    # the form flag may be missing at the very end
    assert ds.parse_prop_desc(plain[:-1]).form == "none"
    with pytest.raises(ProtocolError, match="unknown property form flag 3 for 0xD402"):
        ds.parse_prop_desc(plain[:-1] + b"\x03")
    with pytest.raises(ProtocolError, match="range form on non-integer property 0xD402"):
        ds.parse_prop_desc(plain[:-1] + b"\x01" + s("a") + s("b") + s("c"))
    with pytest.raises(ProtocolError, match="enumeration of 5 values does not fit the 4 bytes left"):
        ds.parse_prop_desc(enum[:-8] + struct.pack("<H", 5) + b"\x00" * 4)
    with pytest.raises(ProtocolError, match="65535"):
        ds.pack_prop_desc(ds.DevicePropDesc(0x5007, 0x0002, False, 0, 0, "enum", allowed=(0,) * 0x10000))
    with pytest.raises(ProtocolError, match="exceeds"):
        ds.parse_prop_desc(bytes(MAX_DATASET_BYTES + 1))


def test_battery_level_sent_as_words_is_read_as_the_eos_bodies_mean_it() -> None:
    head = struct.pack("<HHB", 0x5001, 0x0002, 0) + bytes([100, 75]) + b"\x02" + struct.pack("<H", 5)
    words = bytes.fromhex("64 00 4b 00 32 00 19 00 00 00")  # the 60D trace: 100, 75, 50, 25, 0
    assert ds.parse_prop_desc(head + words).allowed == (100, 75, 50, 25, 0)
    # proper bytes stay bytes
    assert ds.parse_prop_desc(head + bytes([100, 75, 50, 25, 0])).allowed == (100, 75, 50, 25, 0)
    # words above 0xFF are not the EOS quirk: the bytes are read as the declared u8 values
    odd = (
        struct.pack("<HHB", 0x5001, 0x0002, 0)
        + bytes([1, 2])
        + b"\x02"
        + struct.pack("<H", 2)
        + bytes.fromhex("0001 0002")
    )
    assert ds.parse_prop_desc(odd).allowed == (0, 1)
    empty = struct.pack("<HHB", 0x5001, 0x0002, 0) + bytes([1, 2]) + b"\x02" + struct.pack("<H", 0)
    assert ds.parse_prop_desc(empty).allowed == ()
    signed = (
        struct.pack("<HHB", 0x5001, 0x0001, 0)
        + bytes([1, 2])
        + b"\x02"
        + struct.pack("<H", 2)
        + bytes.fromhex("0500 0600")
    )
    assert ds.parse_prop_desc(signed).allowed == (5, 6)
    wide = (
        struct.pack("<HHB", 0x5001, 0x0004, 0)
        + struct.pack("<HH", 1, 2)
        + b"\x02"
        + struct.pack("<H", 2)
        + bytes.fromhex("0500 0600")
    )
    assert ds.parse_prop_desc(wide).allowed == (5, 6)


def test_eos_device_info_ex_and_storage_ids() -> None:
    body = (
        struct.pack("<I2I", 2, 0xC181, 0xC189) + struct.pack("<I1I", 1, 0xD101) + struct.pack("<I5I", 5, 0, 1, 2, 4, 8)
    )
    raw = struct.pack("<I", 4 + len(body)) + body
    info = ds.parse_eos_device_info_ex(raw)
    assert info == ds.EosDeviceInfoEx((0xC181, 0xC189), (0xD101,), (0, 1, 2, 4, 8))
    assert ds.pack_eos_device_info_ex(info) == raw
    with pytest.raises(ProtocolError):
        ds.parse_eos_device_info_ex(raw[:-1])
    assert ds.parse_storage_ids(struct.pack("<I2I", 2, 0x00010001, 0x00020001)) == (0x00010001, 0x00020001)
    with pytest.raises(ProtocolError):
        ds.parse_storage_ids(struct.pack("<I1I", 2, 1))
    for parse in (ds.parse_eos_device_info_ex, ds.parse_storage_ids, ds.parse_device_info, ds.parse_object_info,
                  ds.parse_storage_info, ds.parse_eos_folder_entries):  # fmt: skip
        with pytest.raises(ProtocolError, match="exceeds the 16777216-byte limit"):
            parse(bytes(MAX_DATASET_BYTES + 1))


def folder_entry(handle: int, name: bytes, size: int, flags: int = 0, extra: bytes = b"") -> bytes:
    body = bytearray(52)
    struct.pack_into("<IIH", body, 0, handle, 0x00020001, 0xB103)
    body[16] = flags
    struct.pack_into("<I", body, 20, size)
    body[32 : 32 + len(name)] = name
    struct.pack_into("<I", body, 48, 1_714_558_502)
    return struct.pack("<I", 56 + len(extra)) + bytes(body) + extra


def test_eos_folder_listing() -> None:
    raw = (
        struct.pack("<I", 2)
        + folder_entry(1, b"IMG_0001.CR2", 25_000_000)
        + folder_entry(2, b"100CANON", 0, 1, b"xxxx")
    )
    got = ds.parse_eos_folder_entries(raw)
    assert got == (
        ds.EosFolderEntry(1, 0x00020001, 0xB103, 0, 25_000_000, "IMG_0001.CR2", 1_714_558_502),
        ds.EosFolderEntry(2, 0x00020001, 0xB103, 1, 0, "100CANON", 1_714_558_502),
    )
    assert ds.pack_eos_folder_entries(got[:1]) == struct.pack("<I", 1) + folder_entry(1, b"IMG_0001.CR2", 25_000_000)
    # a full 16-byte name field has no NUL: all of it; longer names are cut to 15 when written
    (full,) = ds.parse_eos_folder_entries(struct.pack("<I", 1) + folder_entry(3, b"ABCDEFGHIJKLMNOP", 1))
    assert full.filename == "ABCDEFGHIJKLMNOP"
    long = ds.EosFolderEntry(4, 1, 2, 0x1FF, 5, "X" * 40, 6)
    (back,) = ds.parse_eos_folder_entries(ds.pack_eos_folder_entries([long]))
    assert back.filename == "X" * 15 and back.flags == 0xFF
    with pytest.raises(ProtocolError, match="claims 3 entries in 112 bytes"):
        ds.parse_eos_folder_entries(struct.pack("<I", 3) + raw[4:116])
    with pytest.raises(ProtocolError, match="folder entry of 55 bytes is shorter than 56"):
        ds.parse_eos_folder_entries(struct.pack("<II", 1, 55) + bytes(60))
    assert ds.parse_eos_folder_entries(struct.pack("<I", 0)) == ()
    exact = struct.pack("<I", 1) + folder_entry(9, b"A", 1)
    assert len(ds.parse_eos_folder_entries(exact)) == 1


names = st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=0x7FF), max_size=30)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.builds(
        ds.ObjectInfo,
        storage_id=st.integers(0, 0xFFFFFFFF),
        object_format=st.integers(0, 0xFFFF),
        compressed_size_bytes=st.integers(0, 0xFFFFFFFF),
        image_width_px=st.integers(0, 0xFFFFFFFF),
        parent_object=st.integers(0, 0xFFFFFFFF),
        association_type=st.integers(0, 0xFFFF),
        filename=names,
        capture_date=names,
        keywords=names,
    )
)
def test_object_info_round_trips(info: ds.ObjectInfo) -> None:
    assert ds.parse_object_info(ds.pack_object_info(info)) == info


def test_default_datasets_mean_what_the_standard_says() -> None:
    # DeviceInfo(): PTP 1.00 (100), no vendor extension, no lists, empty strings
    assert (
        ds.pack_device_info(ds.DeviceInfo())
        == struct.pack("<HIH", 100, 0, 0)
        + b"\x00"
        + struct.pack("<H", 0)
        + struct.pack("<5I", 0, 0, 0, 0, 0)
        + b"\x00" * 4
    )
    # StorageInfo(): removable RAM (4), generic hierarchical (2), read-write (0), free images unused (0xFFFFFFFF)
    assert ds.pack_storage_info(ds.StorageInfo()) == struct.pack("<HHHQQI", 4, 2, 0, 0, 0, 0xFFFFFFFF) + b"\x00\x00"
    # ObjectInfo(): every number 0, every string empty
    assert ds.pack_object_info(ds.ObjectInfo()) == bytes(52) + b"\x00" * 4
    desc = ds.DevicePropDesc(0x5001, 0x0002, False, 1, 2)
    assert (desc.form, desc.range_min, desc.range_max, desc.range_step, desc.allowed) == ("none", 0, 0, 0, ())


def test_datasets_are_values_that_cannot_change() -> None:
    from dataclasses import FrozenInstanceError

    for value in (ds.DeviceInfo(), ds.StorageInfo(), ds.ObjectInfo(), ds.EosDeviceInfoEx(),
                  ds.EosFolderEntry(1, 2, 3, 0, 5, "A", 6), ds.DevicePropDesc(1, 2, False, 0, 0)):  # fmt: skip
        field = next(iter(value.__dataclass_fields__))
        with pytest.raises(FrozenInstanceError):
            setattr(value, field, 1)
        hash(value)


def test_the_dataset_limit_is_inclusive() -> None:
    assert ds.parse_storage_ids(bytes(MAX_DATASET_BYTES)) == ()
