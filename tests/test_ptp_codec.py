"""The PTP codec: containers, datasets and EOS event lists round-trip, and hostile bytes raise only ProtocolError."""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mca.devices.ptp.codec import (
    ProtocolError,
    Reader,
    pack_command,
    pack_data,
    pack_string,
    parse_container,
    parse_header,
)
from mca.devices.ptp.codes import ContainerType, EosProp
from mca.devices.ptp.datasets import (
    DevicePropDesc,
    ObjectInfo,
    StorageInfo,
    pack_device_info,
    pack_object_info,
    pack_prop_desc,
    pack_storage_info,
    parse_device_info,
    parse_object_info,
    parse_prop_desc,
    parse_storage_info,
)
from mca.devices.ptp.events import (
    EosAvailListChanged,
    EosCameraStatus,
    EosObjectAdded,
    EosPropValueChanged,
    EosRequestObjectTransfer,
    pack_eos_events,
    pack_image_format,
    parse_eos_events,
)
from mca.devices.ptp.transport_ptpip import (
    parse_init_command_request,
    parse_operation_request,
    parse_operation_response,
    parse_packet_header,
    parse_start_data,
)
from mca.devices.sim_eos70d.responder import SimEos70D


def test_command_container_bytes_match_the_standard_layout() -> None:
    raw = pack_command(0x1002, 0, (1,))
    assert raw == bytes.fromhex("10000000010002100000000001000000")
    c = parse_container(raw)
    assert (c.type, c.code, c.transaction_id, c.params) == (ContainerType.COMMAND, 0x1002, 0, (1,))


def test_header_rejects_impossible_lengths() -> None:
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 11, 3, 0x2001, 1))
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 12 + 6 * 4, 3, 0x2001, 1))  # six response parameters
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 1000, 2, 0x1009, 1), max_container_bytes=100)


def test_string_encoding_counts_utf16_units_with_nul() -> None:
    assert pack_string("") == b"\x00"
    assert pack_string("AB") == b"\x03A\x00B\x00\x00\x00"
    assert Reader(pack_string("Canon EOS 70D")).string() == "Canon EOS 70D"


def test_array_count_larger_than_data_is_a_protocol_error_not_an_allocation() -> None:
    with pytest.raises(ProtocolError):
        Reader(struct.pack("<I", 0xFFFFFFFF) + b"\x00" * 8).array("H")


def test_device_info_of_the_simulated_70d_round_trips_and_lacks_initiate_capture() -> None:
    info = SimEos70D().device_info()
    back = parse_device_info(pack_device_info(info))
    assert back == info
    assert back.vendor_extension_id == 0xB and back.model == "Canon EOS 70D"
    assert 0x910F in back.operations and 0x9128 in back.operations and 0x100E not in back.operations


def test_storage_and_object_info_round_trip_with_documented_offsets() -> None:
    s = StorageInfo(max_capacity_bytes=16 << 30, free_space_bytes=1 << 30, description="SD", volume_label="EOS")
    assert parse_storage_info(pack_storage_info(s)) == s
    o = ObjectInfo(
        storage_id=0x20001,
        object_format=0xB103,
        compressed_size_bytes=25_000_000,
        parent_object=7,
        filename="IMG_0001.CR2",
        capture_date="20240101T120000",
    )
    raw = pack_object_info(o)
    assert struct.unpack_from("<H", raw, 4)[0] == 0xB103 and struct.unpack_from("<I", raw, 8)[0] == 25_000_000
    assert struct.unpack_from("<I", raw, 38)[0] == 7 and raw[52:53] == b"\x0d"  # filename count at offset 52
    assert parse_object_info(raw) == o


def test_prop_desc_enum_and_range_round_trip() -> None:
    e = DevicePropDesc(0x500F, 4, True, 100, 400, "enum", allowed=(100, 200, 400, 800))
    r = DevicePropDesc(0x5001, 2, False, 100, 80, "range", 0, 100, 1)
    assert parse_prop_desc(pack_prop_desc(e)) == e
    assert parse_prop_desc(pack_prop_desc(r)) == r


def test_eos_event_records_use_the_documented_offsets() -> None:
    added = EosObjectAdded(0x91000001, 0x20001, 0xB103, 25_000_000, 0x90000002, "IMG_0042.CR2")
    raw = pack_eos_events([added])
    assert struct.unpack_from("<II", raw, 0)[1] == 0xC181
    assert struct.unpack_from("<I", raw, 0x08)[0] == 0x91000001
    assert struct.unpack_from("<H", raw, 0x10)[0] == 0xB103
    assert struct.unpack_from("<I", raw, 0x1C)[0] == 25_000_000
    assert struct.unpack_from("<I", raw, 0x20)[0] == 0x90000002
    assert raw[0x28 : 0x28 + 12] == b"IMG_0042.CR2"
    assert raw[-8:] == struct.pack("<II", 8, 0)
    ram = EosRequestObjectTransfer(5, 0xB103, 1234, "IMG_0001.CR2")
    raw2 = pack_eos_events([ram])
    assert struct.unpack_from("<I", raw2, 0x14)[0] == 1234 and raw2[0x1C : 0x1C + 12] == b"IMG_0001.CR2"


def test_eos_event_list_round_trips() -> None:
    events = [
        EosObjectAdded(1, 2, 0xB103, 3, 4, "A.CR2"),
        EosRequestObjectTransfer(9, 0xB103, 10, "B.CR2"),
        EosPropValueChanged(EosProp.ISO_SPEED, 0x48),
        EosAvailListChanged(EosProp.ISO_SPEED, 3, (0x48, 0x50)),
        EosCameraStatus(True),
    ]
    back = parse_eos_events(pack_eos_events(events))
    assert back[0] == events[0] and back[1] == events[1] and back[4] == events[4]
    assert back[2].prop == EosProp.ISO_SPEED and back[2].value == 0x48
    assert back[3].values == (0x48, 0x50)
    assert parse_eos_events(struct.pack("<II", 8, 0)) == []  # an empty poll


def test_image_format_value_follows_the_eos_struct() -> None:
    raw = pack_image_format(((6, 0, 4), (1, 0, 3)))
    assert struct.unpack("<9I", raw) == (2, 0x10, 6, 0, 4, 0x10, 1, 0, 3)


def test_eos_record_claiming_more_than_the_data_is_rejected() -> None:
    with pytest.raises(ProtocolError):
        parse_eos_events(struct.pack("<II", 0x7FFFFFFF, 0xC181) + b"\x00" * 40)


def test_data_container_round_trip() -> None:
    c = parse_container(pack_data(0x1009, 7, b"\x01\x02\x03"))
    assert c.payload == b"\x01\x02\x03" and c.type == ContainerType.DATA


PARSERS = [
    parse_container,
    parse_device_info,
    parse_storage_info,
    parse_object_info,
    parse_prop_desc,
    parse_eos_events,
    lambda b: parse_packet_header(b),
    parse_init_command_request,
    parse_operation_request,
    parse_operation_response,
    parse_start_data,
]


_SEEDS = [
    pack_device_info(SimEos70D().device_info()),
    pack_object_info(ObjectInfo(filename="IMG_0001.CR2")),
    pack_eos_events(SimEos70D().all_props_events()[:6]),
    pack_prop_desc(DevicePropDesc(0x500F, 4, True, 100, 400, "enum", allowed=(100, 200))),
    pack_command(0x1002, 0, (1,)),
]


@settings(max_examples=10_000, deadline=None, suppress_health_check=list(HealthCheck), database=None)
@given(
    st.integers(0, len(_SEEDS) - 1),
    st.integers(0, 4096),
    st.integers(0, 255),
    st.integers(0, 4096),
    st.binary(max_size=12),
)
def test_fuzzed_bytes_raise_nothing_but_protocol_error(seed: int, pos: int, value: int, cut: int, tail: bytes) -> None:
    """Each case flips one byte of a valid dataset, truncates it and appends junk, then feeds every parser."""
    data = bytearray(_SEEDS[seed])
    if data:
        data[pos % len(data)] = value
    data = bytes(data[: cut % (len(data) + 1)]) + tail
    for parse in PARSERS:
        try:
            parse(data)
        except ProtocolError:
            pass
