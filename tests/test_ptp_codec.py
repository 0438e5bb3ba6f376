"""The PTP codec: exact byte layouts, round trips (hypothesis), and the bounds every parser keeps.

Written to catch small deliberate bugs: a flipped code, an off-by-one offset, a
container parser accepting trailing bytes or a length shorter than its header.
Layouts are checked against the PTP standard's and the EOS fact sheet's
numbers, and against bytes real cameras sent (tests/test_ptp_replay.py).
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mca.devices.ptp.codec import (
    HEADER_BYTES,
    MAX_DATASET_BYTES,
    ProtocolError,
    Reader,
    is_older_transaction,
    pack_array,
    pack_command,
    pack_data,
    pack_data_header,
    pack_event,
    pack_response,
    pack_string,
    parse_container,
    parse_header,
    parse_params,
)
from mca.devices.ptp.codes import ContainerType, DataType, EosEventCode, EosProp, Event, ObjectFormat, Op, Resp
from mca.devices.ptp.datasets import (
    DeviceInfo,
    DevicePropDesc,
    EosDeviceInfoEx,
    EosFolderEntry,
    ObjectInfo,
    StorageInfo,
    pack_device_info,
    pack_eos_device_info_ex,
    pack_eos_folder_entries,
    pack_object_info,
    pack_prop_desc,
    pack_prop_value,
    pack_storage_info,
    parse_device_info,
    parse_eos_device_info_ex,
    parse_eos_folder_entries,
    parse_object_info,
    parse_prop_desc,
    parse_prop_value,
    parse_storage_ids,
    parse_storage_info,
)
from mca.devices.ptp.events import (
    EosAvailListChanged,
    EosCameraStatus,
    EosObjectAdded,
    EosObjectRemoved,
    EosPropValueChanged,
    EosRequestObjectTransfer,
    EosUndecodedRecord,
    EosUnknownEvent,
    pack_eos_event,
    pack_eos_events,
    pack_focus_info_ex,
    pack_image_format,
    parse_eos_events,
    parse_focus_info_ex,
    parse_image_format,
)
from mca.devices.ptp.liveview import pack_viewfinder_data, parse_viewfinder_data
from mca.devices.ptp.ptpip_packets import (
    pack_data_packet,
    pack_event_packet,
    pack_init_command_ack,
    pack_init_command_request,
    pack_operation_request,
    pack_operation_response,
    pack_start_data,
    parse_event_packet,
    parse_init_command_ack,
    parse_init_command_request,
    parse_operation_request,
    parse_operation_response,
    parse_packet_header,
    parse_start_data,
)
from mca.devices.sim.eos70d.responder import SimEos70D

ROUND_TRIP = settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck), database=None)
u32s = st.integers(0, 0xFFFFFFFF)
u16s = st.integers(0, 0xFFFF)
texts = st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=0xD7FF), max_size=120)
ascii_names = st.text(alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7E), min_size=1, max_size=40)


# -- codes: the numbers of the standard and of the EOS fact sheet --------------------------------------------------


def test_codes_are_the_standard_and_eos_numbers() -> None:
    """Independent reference: PTP (ISO 15740) and the EOS fact sheet (shared/reference/ptp-canon-eos.md)."""
    assert [int(t) for t in ContainerType] == [1, 2, 3, 4]
    assert (Op.GET_DEVICE_INFO, Op.OPEN_SESSION, Op.CLOSE_SESSION, Op.GET_OBJECT_HANDLES) == (
        0x1001,
        0x1002,
        0x1003,
        0x1007,
    )
    assert (Op.GET_OBJECT_INFO, Op.GET_OBJECT, Op.DELETE_OBJECT, Op.INITIATE_CAPTURE, Op.GET_PARTIAL_OBJECT) == (
        0x1008,
        0x1009,
        0x100B,
        0x100E,
        0x101B,
    )
    assert (Op.EOS_GET_PARTIAL_OBJECT, Op.EOS_GET_DEVICE_INFO_EX, Op.EOS_REMOTE_RELEASE) == (0x9107, 0x9108, 0x910F)
    assert (Op.EOS_SET_DEVICE_PROP_VALUE_EX, Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_EVENT_MODE, Op.EOS_GET_EVENT) == (
        0x9110,
        0x9114,
        0x9115,
        0x9116,
    )
    assert (Op.EOS_TRANSFER_COMPLETE, Op.EOS_PC_HDD_CAPACITY, Op.EOS_KEEP_DEVICE_ON) == (0x9117, 0x911A, 0x911D)
    assert (Op.EOS_REMOTE_RELEASE_ON, Op.EOS_REMOTE_RELEASE_OFF, Op.EOS_GET_VIEWFINDER_DATA, Op.EOS_AF_CANCEL) == (
        0x9128,
        0x9129,
        0x9153,
        0x9160,
    )
    assert (Resp.OK, Resp.GENERAL_ERROR, Resp.SESSION_NOT_OPEN, Resp.INVALID_TRANSACTION_ID) == (
        0x2001,
        0x2002,
        0x2003,
        0x2004,
    )
    assert (Resp.INVALID_OBJECT_HANDLE, Resp.DEVICE_BUSY, Resp.SESSION_ALREADY_OPEN, Resp.CANON_OBJECT_NOT_READY) == (
        0x2009,
        0x2019,
        0x201E,
        0xA102,
    )
    assert (Event.OBJECT_ADDED, Event.OBJECT_REMOVED, Event.CAPTURE_COMPLETE) == (0x4002, 0x4003, 0x400D)
    assert (EosEventCode.OBJECT_ADDED_EX, EosEventCode.OBJECT_REMOVED, EosEventCode.REQUEST_OBJECT_TRANSFER) == (
        0xC181,
        0xC182,
        0xC186,
    )
    assert (
        EosEventCode.OBJECT_INFO_CHANGED_EX,
        EosEventCode.PROP_VALUE_CHANGED,
        EosEventCode.AVAIL_LIST_CHANGED,
        EosEventCode.CAMERA_STATUS_CHANGED,
    ) == (0xC187, 0xC189, 0xC18A, 0xC18B)
    assert (ObjectFormat.ASSOCIATION, ObjectFormat.JPEG, ObjectFormat.CANON_CR2) == (0x3001, 0x3801, 0xB103)
    assert (EosProp.APERTURE, EosProp.SHUTTER_SPEED, EosProp.ISO_SPEED, EosProp.FOCUS_MODE) == (
        0xD101,
        0xD102,
        0xD103,
        0xD108,
    )
    assert (EosProp.AVAILABLE_SHOTS, EosProp.CAPTURE_DESTINATION, EosProp.IMAGE_FORMAT) == (0xD11B, 0xD11C, 0xD120)
    assert (EosProp.EVF_OUTPUT_DEVICE, EosProp.EVF_MODE, EosProp.FOCUS_INFO_EX) == (0xD1B0, 0xD1B1, 0xD1D3)
    assert [int(t) for t in DataType][:8] == list(range(1, 9)) and DataType.STR == 0xFFFF


# -- containers ----------------------------------------------------------------------------------------------------


def test_command_container_bytes_match_the_standard_layout() -> None:
    raw = pack_command(0x1002, 0, (1,))
    assert raw == bytes.fromhex("10000000010002100000000001000000")
    c = parse_container(raw)
    assert (c.type, c.code, c.transaction_id, c.params) == (ContainerType.COMMAND, 0x1002, 0, (1,))


def test_container_headers_of_each_kind() -> None:
    assert pack_response(0x2001, 7, ()) == bytes.fromhex("0c000000030001200700000000"[:24])
    assert pack_event(0x4002, 0, (5,)) == struct.pack("<IHHII", 16, 4, 0x4002, 0, 5)
    assert pack_data(0x1009, 3, b"ab") == struct.pack("<IHHI", 14, 2, 0x1009, 3) + b"ab"
    assert pack_data_header(0x9116, 9, 8) == struct.pack("<IHHI", 20, 2, 0x9116, 9)


@ROUND_TRIP
@given(
    st.sampled_from([ContainerType.COMMAND, ContainerType.RESPONSE]),
    u16s,
    u32s,
    st.lists(u32s, max_size=5),
)
def test_parameter_containers_round_trip(kind: int, code: int, tid: int, params: list[int]) -> None:
    raw = (pack_command if kind == ContainerType.COMMAND else pack_response)(code, tid, params)
    assert len(raw) == HEADER_BYTES + 4 * len(params)
    c = parse_container(raw)
    assert (c.type, c.code, c.transaction_id, c.params, c.payload) == (kind, code, tid, tuple(params), b"")


@ROUND_TRIP
@given(u16s, u32s, st.binary(max_size=2000))
def test_data_containers_round_trip(code: int, tid: int, payload: bytes) -> None:
    c = parse_container(pack_data(code, tid, payload))
    assert (c.type, c.code, c.transaction_id, c.payload, c.params) == (ContainerType.DATA, code, tid, payload, ())


@ROUND_TRIP
@given(st.binary(min_size=1, max_size=8))
def test_a_container_with_trailing_bytes_is_refused(extra: bytes) -> None:
    raw = pack_command(0x1001, 1, (2,))
    with pytest.raises(ProtocolError):
        parse_container(raw + extra)
    with pytest.raises(ProtocolError):
        parse_container(raw[:-1])  # and one byte short


@pytest.mark.parametrize("length", [0, 1, 8, 11])
def test_a_length_shorter_than_the_header_is_refused(length: int) -> None:
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", length, 3, 0x2001, 1))


def test_header_bounds() -> None:
    assert parse_header(struct.pack("<IHHI", 12, 3, 0x2001, 1)).payload_bytes == 0  # exactly a header: fine
    assert parse_header(struct.pack("<IHHI", 32, 3, 0x2001, 1)).length == 32  # five parameters: the maximum
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 36, 3, 0x2001, 1))  # six response parameters
    assert parse_header(struct.pack("<IHHI", 24, 4, 0x4002, 1)).length == 24  # three event parameters
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 28, 4, 0x4002, 1))  # four event parameters
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 14, 1, 0x1001, 1))  # parameters not a multiple of 4 bytes
    with pytest.raises(ProtocolError):
        parse_header(struct.pack("<IHHI", 1000, 2, 0x1009, 1), max_container_bytes=100)
    assert parse_header(struct.pack("<IHHI", 100, 2, 0x1009, 1), max_container_bytes=100).length == 100
    for kind in (0, 5, 0xFFFF):
        with pytest.raises(ProtocolError):
            parse_header(struct.pack("<IHHI", 12, kind, 0x2001, 1))
    with pytest.raises(ProtocolError):
        parse_header(b"\x0c\x00\x00\x00\x03\x00\x01\x20\x00\x00\x00")  # 11 bytes
    with pytest.raises(ProtocolError):
        pack_command(0x1001, 1, (1, 2, 3, 4, 5, 6))
    with pytest.raises(ProtocolError):
        pack_event(0x4002, 1, (1, 2, 3, 4))
    with pytest.raises(ProtocolError):
        pack_command(0x1001, 1, (2**32,))


def test_parse_params_bounds() -> None:
    assert parse_params(struct.pack("<5I", 1, 2, 3, 4, 5)) == (1, 2, 3, 4, 5)
    with pytest.raises(ProtocolError):
        parse_params(struct.pack("<6I", *range(6)))
    with pytest.raises(ProtocolError):
        parse_params(b"\x00\x00\x00")
    assert parse_params(struct.pack("<3I", 1, 2, 3), limit=3) == (1, 2, 3)
    with pytest.raises(ProtocolError):
        parse_params(struct.pack("<4I", 1, 2, 3, 4), limit=3)


def test_transaction_ids_are_ordered_with_wrap_around() -> None:
    assert is_older_transaction(5, 6) and is_older_transaction(0xFFFFFFFF, 1)
    assert not is_older_transaction(6, 6) and not is_older_transaction(7, 6) and not is_older_transaction(1, 0xFFFFFFFF)


# -- strings, arrays, the bounded reader ---------------------------------------------------------------------------


def test_string_encoding_counts_utf16_units_with_nul() -> None:
    assert pack_string("") == b"\x00"
    assert pack_string("AB") == b"\x03A\x00B\x00\x00\x00"
    assert Reader(pack_string("Canon EOS 70D")).string() == "Canon EOS 70D"
    assert len(pack_string("x" * 254)) == 1 + 2 * 255
    with pytest.raises(ProtocolError):
        pack_string("x" * 255)


@ROUND_TRIP
@given(texts)
def test_strings_round_trip(text: str) -> None:
    r = Reader(pack_string(text) + b"\xaa")
    assert r.string() == text and r.remaining == 1  # exactly the string's bytes consumed


def test_truncated_string_and_array_are_protocol_errors_not_allocations() -> None:
    with pytest.raises(ProtocolError):
        Reader(b"\x05A\x00B\x00").string()
    with pytest.raises(ProtocolError):
        Reader(struct.pack("<I", 0xFFFFFFFF) + b"\x00" * 8).array("H")
    assert Reader(struct.pack("<I", 4) + b"\x00" * 8).array("H") == (0, 0, 0, 0)  # exactly enough
    with pytest.raises(ProtocolError):
        Reader(struct.pack("<I", 5) + b"\x00" * 8).array("H")  # one item short


@ROUND_TRIP
@given(st.sampled_from(["H", "I", "B", "Q"]), st.data())
def test_arrays_round_trip(fmt: str, data: st.DataObject) -> None:
    bits = struct.calcsize(fmt) * 8
    values = data.draw(st.lists(st.integers(0, 2**bits - 1), max_size=50))
    r = Reader(pack_array(fmt, values))
    assert r.array(fmt) == tuple(values) and r.remaining == 0


def test_reader_reads_exactly_to_the_end_and_no_further() -> None:
    r = Reader(bytes(range(15)))
    assert (r.u8(), r.u16(), r.u32(), r.u64()) == (0, 0x0201, 0x06050403, 0x0E0D0C0B0A090807)
    assert r.remaining == 0
    for read in (r.u8, r.u16, r.u32, r.u64):
        with pytest.raises(ProtocolError):
            read()
    with pytest.raises(ProtocolError):
        Reader(b"abc").take(4)
    assert Reader(b"abcdef", 1, 3).take(2) == b"bc"
    with pytest.raises(ProtocolError):
        Reader(b"abcdef", 1, 3).take(3)  # the end bound holds even with more bytes in the buffer


# -- datasets ------------------------------------------------------------------------------------------------------


@ROUND_TRIP
@given(
    st.builds(
        DeviceInfo,
        standard_version=u16s,
        vendor_extension_id=u32s,
        vendor_extension_version=u16s,
        vendor_extension_desc=texts,
        functional_mode=u16s,
        operations=st.lists(u16s, max_size=200).map(tuple),
        events=st.lists(u16s, max_size=20).map(tuple),
        properties=st.lists(u16s, max_size=20).map(tuple),
        capture_formats=st.lists(u16s, max_size=5).map(tuple),
        image_formats=st.lists(u16s, max_size=15).map(tuple),
        manufacturer=texts,
        model=texts,
        device_version=texts,
        serial_number=texts,
    )
)
def test_device_info_round_trips(info: DeviceInfo) -> None:
    assert parse_device_info(pack_device_info(info)) == info


def test_device_info_field_offsets() -> None:
    raw = pack_device_info(DeviceInfo(100, 6, 200, "", 0, (0x1001, 0x9116), (), (), (), (), "C", "M", "V", "S"))
    assert raw[:15] == struct.pack("<HIHBHI", 100, 6, 200, 0, 0, 2)  # version, ext id, ext version, "", mode, count
    assert struct.unpack_from("<2H", raw, 15) == (0x1001, 0x9116)


def test_the_simulated_70d_device_info_round_trips_and_speaks_like_the_real_body() -> None:
    info = SimEos70D().device_info()
    back = parse_device_info(pack_device_info(info))
    assert back == info
    assert back.vendor_extension_id == 6 and back.vendor_extension_version == 100 and back.model == "Canon EOS 70D"
    assert 0x910F in back.operations and 0x9128 in back.operations and 0x100E not in back.operations


@ROUND_TRIP
@given(
    st.builds(
        StorageInfo,
        storage_type=u16s,
        filesystem_type=u16s,
        access_capability=u16s,
        max_capacity_bytes=st.integers(0, 2**64 - 1),
        free_space_bytes=st.integers(0, 2**64 - 1),
        free_space_images=u32s,
        description=texts,
        volume_label=texts,
    )
)
def test_storage_info_round_trips(info: StorageInfo) -> None:
    assert parse_storage_info(pack_storage_info(info)) == info


def test_storage_info_offsets_and_the_real_r10_no_card_answer() -> None:
    raw = pack_storage_info(StorageInfo(4, 3, 0, 5, 6, 7, "SD1", ""))
    assert struct.unpack_from("<HHHQQI", raw) == (4, 3, 0, 5, 6, 7) and raw[26] == 4  # description at offset 26
    # An EOS R10 without a card answered EOS GetStorageInfo with these 38 bytes (eos-traces, R10 log).
    r10 = bytes.fromhex("040003000000" + "00" * 16 + "ffffffff045300440031000000000000")
    assert len(r10) == 38
    info = parse_storage_info(r10)
    assert (info.storage_type, info.filesystem_type, info.max_capacity_bytes, info.description) == (4, 3, 0, "SD1")
    assert parse_storage_ids(bytes.fromhex("0100000000000200")) == (0x00020000,)


object_infos = st.builds(
    ObjectInfo,
    storage_id=u32s,
    object_format=u16s,
    protection_status=u16s,
    compressed_size_bytes=u32s,
    thumb_format=u16s,
    thumb_compressed_size_bytes=u32s,
    thumb_width_px=u32s,
    thumb_height_px=u32s,
    image_width_px=u32s,
    image_height_px=u32s,
    image_bit_depth=u32s,
    parent_object=u32s,
    association_type=u16s,
    association_desc=u32s,
    sequence_number=u32s,
    filename=texts,
    capture_date=texts,
    modification_date=texts,
    keywords=texts,
)


@ROUND_TRIP
@given(object_infos)
def test_object_info_round_trips(info: ObjectInfo) -> None:
    assert parse_object_info(pack_object_info(info)) == info


def test_object_info_uses_the_documented_offsets() -> None:
    o = ObjectInfo(
        storage_id=0x20001,
        object_format=0xB103,
        protection_status=1,
        compressed_size_bytes=25_000_000,
        thumb_format=0x3808,
        thumb_compressed_size_bytes=11568,
        thumb_width_px=160,
        thumb_height_px=120,
        image_width_px=5472,
        image_height_px=3648,
        image_bit_depth=14,
        parent_object=7,
        association_type=1,
        association_desc=9,
        sequence_number=3,
        filename="IMG_0001.CR2",
        capture_date="20240101T120000",
    )
    raw = pack_object_info(o)
    at = {0: 0x20001, 8: 25_000_000, 14: 11568, 18: 160, 22: 120, 26: 5472, 30: 3648, 34: 14, 38: 7, 44: 9, 48: 3}
    for offset, value in at.items():
        assert struct.unpack_from("<I", raw, offset)[0] == value, offset
    for offset, value in {4: 0xB103, 6: 1, 12: 0x3808, 42: 1}.items():
        assert struct.unpack_from("<H", raw, offset)[0] == value, offset
    assert raw[52:53] == b"\x0d" and raw[53:55] == b"I\x00"  # filename count (12 + NUL) at offset 52
    assert parse_object_info(raw) == o


def test_a_truncated_object_info_is_refused() -> None:
    raw = pack_object_info(ObjectInfo(filename="IMG_0001.CR2", capture_date="20240101T120000"))
    for cut in (0, 10, 51, 53, len(raw) - 3):
        with pytest.raises(ProtocolError):
            parse_object_info(raw[:cut])


prop_descs = st.one_of(
    st.builds(
        lambda c, d, w, a, b: DevicePropDesc(c, d, w, a, b),
        u16s,
        st.sampled_from([DataType.UINT16, DataType.UINT32]),
        st.booleans(),
        u16s,
        u16s,
    ),
    st.builds(
        lambda c, w, a, b, lo, hi, step: DevicePropDesc(c, DataType.UINT32, w, a, b, "range", lo, hi, step),
        u16s,
        st.booleans(),
        u32s,
        u32s,
        u32s,
        u32s,
        u32s,
    ),
    st.builds(
        lambda c, w, a, b, allowed: DevicePropDesc(c, DataType.INT16, w, a, b, "enum", allowed=tuple(allowed)),
        u16s,
        st.booleans(),
        st.integers(-(2**15), 2**15 - 1),
        st.integers(-(2**15), 2**15 - 1),
        st.lists(st.integers(-(2**15), 2**15 - 1), max_size=30),
    ),
    st.builds(
        lambda c, a, b, allowed: DevicePropDesc(c, DataType.STR, True, a, b, "enum", allowed=tuple(allowed)),
        u16s,
        texts,
        texts,
        st.lists(texts, max_size=5),
    ),
)


@ROUND_TRIP
@given(prop_descs)
def test_prop_descs_round_trip(desc: DevicePropDesc) -> None:
    assert parse_prop_desc(pack_prop_desc(desc)) == desc


def test_prop_desc_layout_and_bounds() -> None:
    raw = pack_prop_desc(DevicePropDesc(0x500F, DataType.UINT16, True, 100, 400, "enum", allowed=(100, 200)))
    assert raw == struct.pack("<HHBHHBH2H", 0x500F, 4, 1, 100, 400, 2, 2, 100, 200)
    with pytest.raises(ProtocolError):
        parse_prop_desc(raw[:-1])  # the last enumeration value cut short
    with pytest.raises(ProtocolError):
        parse_prop_desc(struct.pack("<HHBHHBH", 0x500F, 4, 1, 100, 400, 2, 60000))  # count beyond the data
    with pytest.raises(ProtocolError):
        parse_prop_desc(struct.pack("<HHBHHB", 0x500F, 4, 1, 100, 400, 3))  # unknown form flag
    with pytest.raises(ProtocolError):
        parse_prop_desc(struct.pack("<HHB", 0x500F, 0x0099, 1) + b"\x00" * 8)  # unknown datatype
    assert parse_prop_value(pack_prop_value(DataType.INT8, -3), DataType.INT8) == -3


def test_battery_level_enumeration_sent_as_words_is_read_as_the_camera_means_it() -> None:
    """The 60D trace: BatteryLevel declared UINT8, enumeration 100, 75, 50, 25, 0 sent as u16 words."""
    raw = bytes.fromhex("0150020000323202050064004b00320019000000")
    desc = parse_prop_desc(raw)
    assert (desc.code, desc.datatype, desc.current, desc.allowed) == (0x5001, 2, 0x32, (100, 75, 50, 25, 0))


@ROUND_TRIP
@given(st.lists(u32s, max_size=30), st.lists(u32s, max_size=150), st.lists(u32s, max_size=8))
def test_eos_device_info_ex_round_trips(events: list[int], props: list[int], unknown: list[int]) -> None:
    info = EosDeviceInfoEx(tuple(events), tuple(props), tuple(unknown))
    raw = pack_eos_device_info_ex(info)
    assert struct.unpack_from("<I", raw)[0] == len(raw) and parse_eos_device_info_ex(raw) == info


@ROUND_TRIP
@given(
    st.lists(
        st.builds(EosFolderEntry, u32s, u32s, u16s, st.integers(0, 255), u32s, ascii_names.map(lambda s: s[:15]), u32s),
        max_size=10,
    )
)
def test_eos_folder_listing_round_trips(entries: list[EosFolderEntry]) -> None:
    assert parse_eos_folder_entries(pack_eos_folder_entries(entries)) == tuple(entries)


def test_eos_folder_listing_layout_and_bounds() -> None:
    raw = pack_eos_folder_entries([EosFolderEntry(0x91000001, 0x20001, 0xB103, 1, 1234, "IMG_0001.CR2", 99)])
    assert struct.unpack_from("<IIIIH", raw) == (1, 56, 0x91000001, 0x20001, 0xB103)
    assert raw[4 + 4 + 16] == 1 and struct.unpack_from("<I", raw, 8 + 20)[0] == 1234
    assert raw[8 + 32 : 8 + 44] == b"IMG_0001.CR2" and struct.unpack_from("<I", raw, 8 + 48)[0] == 99
    with pytest.raises(ProtocolError):
        parse_eos_folder_entries(struct.pack("<II", 1, 55) + bytes(51))  # an entry shorter than 56
    with pytest.raises(ProtocolError):
        parse_eos_folder_entries(struct.pack("<I", 1000))


# -- EOS event records ---------------------------------------------------------------------------------------------

eos_events = st.one_of(
    st.builds(EosObjectAdded, u32s, u32s, u16s, u32s, u32s, ascii_names, st.booleans()),
    st.builds(EosRequestObjectTransfer, u32s, u16s, u32s, ascii_names),
    st.builds(EosObjectRemoved, u32s),
    st.builds(lambda p, v: EosPropValueChanged(p, v, struct.pack("<I", v)), u16s, u32s),
    st.builds(
        lambda p, raw: EosPropValueChanged(p, int.from_bytes(raw[:4], "little"), raw),
        u16s,
        st.binary(min_size=1, max_size=40),
    ),
    st.builds(
        lambda p, vs: EosAvailListChanged(p, 3, tuple(vs), tuple(struct.pack("<I", v) for v in vs)),
        u16s.filter(lambda p: p not in (0xD120, 0xD121, 0xD122)),
        st.lists(u32s, min_size=1, max_size=20),
    ),
    st.builds(EosCameraStatus, u32s),
    st.builds(
        EosUnknownEvent,
        st.integers(0xC000, 0xCFFF).filter(lambda c: c not in (0xC181, 0xC182, 0xC186, 0xC187, 0xC189, 0xC18A, 0xC18B)),
        st.binary(max_size=30),
    ),
)


@ROUND_TRIP
@given(st.lists(eos_events, max_size=12))
def test_eos_event_lists_round_trip(events: list) -> None:
    back = parse_eos_events(pack_eos_events(events))
    assert back == events


def test_eos_event_records_use_the_documented_offsets() -> None:
    added = EosObjectAdded(0x91000001, 0x20001, 0xB103, 25_000_000, 0x90000002, "IMG_0042.CR2")
    raw = pack_eos_events([added])
    assert struct.unpack_from("<II", raw, 0) == (0x3C, 0xC181)
    assert struct.unpack_from("<I", raw, 0x08)[0] == 0x91000001
    assert struct.unpack_from("<I", raw, 0x0C)[0] == 0x20001
    assert struct.unpack_from("<H", raw, 0x10)[0] == 0xB103
    assert struct.unpack_from("<I", raw, 0x1C)[0] == 25_000_000
    assert struct.unpack_from("<I", raw, 0x20)[0] == 0x90000002
    assert raw[0x28 : 0x28 + 13] == b"IMG_0042.CR2\x00"
    assert raw[-8:] == struct.pack("<II", 8, 0)
    ram = pack_eos_events([EosRequestObjectTransfer(5, 0xB103, 1234, "IMG_0001.CR2")])
    assert struct.unpack_from("<II", ram, 0)[1] == 0xC186
    assert struct.unpack_from("<I", ram, 0x08)[0] == 5 and struct.unpack_from("<I", ram, 0x0C)[0] == 0xB103
    assert struct.unpack_from("<I", ram, 0x14)[0] == 1234 and ram[0x1C : 0x1C + 12] == b"IMG_0001.CR2"
    prop = pack_eos_event(EosPropValueChanged(0xD103, 0x48))
    assert prop == struct.pack("<IIII", 16, 0xC189, 0xD103, 0x48)
    listed = pack_eos_event(EosAvailListChanged(0xD103, 3, (0x48, 0x50)))
    assert listed == struct.pack("<IIIIIII", 28, 0xC18A, 0xD103, 3, 2, 0x48, 0x50)
    assert pack_eos_event(EosCameraStatus(1)) == struct.pack("<III", 12, 0xC18B, 1)
    assert pack_eos_event(EosObjectRemoved(9)) == struct.pack("<III", 12, 0xC182, 9)


def test_the_400d_object_added_record_decodes_to_what_libgphoto2_annotated() -> None:
    """The 400D trace's GetEvent data (eos-traces): libgphoto2's notes name each field."""
    data = bytes.fromhex(
        "3c00000081c1000052639431010001000138000000000000200000008541270000009431"
        "50639431494d475f313538392e4a504700000000f8d2ed490800000000000000"
    )
    [added] = parse_eos_events(data)
    assert added == EosObjectAdded(0x31946352, 0x00010001, 0x3801, 0x274185, 0x31940000, "IMG_1589.JPG")


def test_camera_status_busy_is_only_one() -> None:
    assert EosCameraStatus(1).busy and not EosCameraStatus(0).busy and not EosCameraStatus(2).busy


def test_an_unknown_or_odd_record_never_costs_the_others() -> None:
    """Records of types no parser knows, lists of types 1 and 7, a one-byte string value and a truncated object
    record: each is kept as what it is, and the new file in the same poll is not lost."""
    added = EosObjectAdded(7, 0x20001, 0xB103, 100, 2, "IMG_0007.CR2")
    raw = b"".join(
        [
            struct.pack("<III", 12, 0xC1F6, 0),  # an R10 sends this; nobody decodes it
            struct.pack("<IIIII", 20, 0xC18A, 0xD1C2, 1, 0),  # a list of type 1, no items
            struct.pack("<IIIII", 21, 0xC18A, 0xD14D, 7, 1) + b"\x05",  # type 7 with one odd byte
            struct.pack("<III", 13, 0xC189, 0xD115) + b"\x00",  # Owner "": one value byte (5D Mark III trace)
            struct.pack("<IIII", 16, 0xC181, 1, 2),  # ObjectAddedEx cut short
            pack_eos_event(added),
            struct.pack("<II", 11, 0xC1FF) + b"\x01\x02\x03",
        ]
    ) + struct.pack("<II", 8, 0)
    events = parse_eos_events(raw)
    assert events[0] == EosUnknownEvent(0xC1F6, b"\x00\x00\x00\x00")
    assert events[1] == EosAvailListChanged(0xD1C2, 1, (), ())
    assert events[2].kind == 7 and events[2].values == ()
    assert events[3] == EosPropValueChanged(0xD115, 0, b"\x00") and events[3].text == ""
    assert isinstance(events[4], EosUndecodedRecord) and events[4].code == 0xC181
    assert events[5] == added
    assert events[6] == EosUnknownEvent(0xC1FF, b"\x01\x02\x03")


def test_broken_framing_keeps_every_record_before_it() -> None:
    added = EosObjectAdded(7, 0x20001, 0xB103, 100, 2, "IMG_0007.CR2")
    good = pack_eos_event(added)
    for tail in (
        struct.pack("<II", 0x7FFFFFFF, 0xC181) + b"\x00" * 40,  # claims more than is left
        struct.pack("<II", 4, 0xC189),  # claims less than its own header
        b"\x10\x00\x00",  # a header cut short
    ):
        events = parse_eos_events(good + tail)
        assert events[0] == added and isinstance(events[1], EosUndecodedRecord) and len(events) == 2
    assert parse_eos_events(good) == [added]  # a missing terminator at the very end is fine
    assert parse_eos_events(struct.pack("<II", 8, 0) + good) == []  # nothing after the terminator is read
    with pytest.raises(ProtocolError):
        parse_eos_events(bytes(MAX_DATASET_BYTES + 1))


def test_image_format_value_follows_the_eos_struct() -> None:
    raw = pack_image_format(((6, 0, 4), (1, 0, 3)))
    assert struct.unpack("<9I", raw) == (2, 0x10, 6, 0, 4, 0x10, 1, 0, 3)
    from mca.devices.ptp.codec import Reader as R

    assert parse_image_format(R(raw)) == ((6, 0, 4), (1, 0, 3))
    for bad in (struct.pack("<I", 3), struct.pack("<II", 1, 0x14) + bytes(12), struct.pack("<II", 1, 0x10)):
        with pytest.raises(ProtocolError):
            parse_image_format(R(bad))


def test_focus_info_round_trips_and_reads_the_70d_dump() -> None:
    points = [(i * 10 - 90, -i, 229, 277) for i in range(19)]
    raw = pack_focus_info_ex(points, {3, 18}, (5472, 3648))
    info = parse_focus_info_ex(raw)
    assert info is not None and info.points_total == 19 and info.focused
    assert info.in_focus == (points[3], points[18]) and (info.image_width_px, info.image_height_px) == (5472, 3648)
    none_focused = parse_focus_info_ex(pack_focus_info_ex(points, set(), (5472, 3648)))
    assert none_focused is not None and not none_focused.focused
    assert parse_focus_info_ex(struct.pack("<IHHHHHHHH", 20, 16, 4, 0, 0, 0, 0, 0, 0)) is None  # a placeholder
    # The 70D's FocusInfoEx as libgphoto2's hand decode shows it: 31 points in the struct, 19 in use, 5472x3648.
    head = bytes.fromhex("1a010000160104001f0013006015400e6015400e")
    dump = parse_focus_info_ex(head + bytes(282 - len(head)))
    assert dump is not None and (dump.version, dump.points_total, dump.points_in_use) == (4, 31, 19)
    assert (dump.image_width_px, dump.image_height_px) == (5472, 3648) and not dump.focused
    with pytest.raises(ProtocolError):
        parse_focus_info_ex(head + bytes(20))  # claims 282 bytes


# -- PTP/IP packets and live-view blocks ----------------------------------------------------------------------------


@ROUND_TRIP
@given(u16s, u32s, st.lists(u32s, max_size=5), st.sampled_from([1, 2]))
def test_ptpip_operation_packets_round_trip(code: int, tid: int, params: list[int], phase: int) -> None:
    raw = pack_operation_request(code, tid, tuple(params), phase)
    body_len, kind = parse_packet_header(raw[:8])
    assert kind == 6 and body_len == len(raw) - 8
    got_phase, cmd = parse_operation_request(raw[8:])
    assert (got_phase, cmd.code, cmd.transaction_id, cmd.params) == (phase, code, tid, tuple(params))
    resp = parse_operation_response(pack_operation_response(code, tid, tuple(params))[8:])
    assert (resp.code, resp.transaction_id, resp.params) == (code, tid, tuple(params))


@ROUND_TRIP
@given(u16s, u32s, st.lists(u32s, max_size=3), st.binary(min_size=16, max_size=16), texts, u32s)
def test_ptpip_other_packets_round_trip(
    code: int, tid: int, params: list[int], guid: bytes, name: str, total: int
) -> None:
    ev = parse_event_packet(pack_event_packet(code, tid, tuple(params))[8:])
    assert (ev.code, ev.transaction_id, ev.params) == (code, tid, tuple(params))
    req = parse_init_command_request(pack_init_command_request(guid, name)[8:])
    assert (req.guid, req.name, req.version) == (guid, name, 0x00010000)
    assert parse_init_command_ack(pack_init_command_ack(tid, guid, name)[8:]) == (tid, guid, name)
    assert parse_start_data(pack_start_data(tid, total)[8:]) == (tid, total)
    data = pack_data_packet(tid, b"xyz", end=True)
    assert struct.unpack_from("<III", data) == (15, 12, tid) and data[12:] == b"xyz"


def test_ptpip_bounds() -> None:
    with pytest.raises(ProtocolError):
        parse_packet_header(struct.pack("<II", 7, 6))
    with pytest.raises(ProtocolError):
        parse_packet_header(struct.pack("<II", 8, 15))
    with pytest.raises(ProtocolError):
        parse_packet_header(struct.pack("<II", 8 + 101, 10), max_bytes=100)
    assert parse_packet_header(struct.pack("<II", 8 + 100, 10), max_bytes=100) == (100, 10)
    with pytest.raises(ProtocolError):
        parse_operation_request(b"\x01\x00\x00\x00\x01\x10\x00\x00\x00")
    with pytest.raises(ProtocolError):
        parse_event_packet(struct.pack("<HI4I", 0x4002, 0, 1, 2, 3, 4))  # four event parameters


@ROUND_TRIP
@given(st.binary(max_size=3000), st.lists(st.tuples(st.integers(2, 20), st.binary(max_size=40)), max_size=4))
def test_viewfinder_data_round_trips(jpeg: bytes, others: list[tuple[int, bytes]]) -> None:
    others = [(k if k not in (1, 11) else 2, b) for k, b in others]
    frame = parse_viewfinder_data(pack_viewfinder_data(jpeg, tuple(others)))
    assert frame.jpeg == jpeg and frame.other_blocks == tuple(others)


def test_viewfinder_data_bounds() -> None:
    with pytest.raises(ProtocolError):
        parse_viewfinder_data(struct.pack("<II", 100, 1) + b"x" * 10)
    with pytest.raises(ProtocolError):
        parse_viewfinder_data(struct.pack("<II", 7, 1))
    with pytest.raises(ProtocolError):
        parse_viewfinder_data(b"\x08\x00\x00")


# -- fuzz: hostile bytes raise nothing but ProtocolError ------------------------------------------------------------

PARSERS = [
    parse_container,
    parse_device_info,
    parse_storage_info,
    parse_object_info,
    parse_prop_desc,
    parse_eos_events,
    parse_eos_device_info_ex,
    parse_eos_folder_entries,
    parse_viewfinder_data,
    lambda b: parse_focus_info_ex(b),
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
    pack_eos_device_info_ex(EosDeviceInfoEx((0xC181,), (0xD101,), (0,))),
    pack_viewfinder_data(b"\xff\xd8jpeg", ((4, b"abc"),)),
    pack_focus_info_ex([(1, 2, 3, 4)] * 3, {1}, (5472, 3648)),
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
