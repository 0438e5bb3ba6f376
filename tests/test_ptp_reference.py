"""The PTP codec against bytes written out by hand from the PTP standard (ISO 15740, the USB Still Image class).

A container is: u32 length (header included), u16 type (1 command, 2 data, 3 response, 4 event), u16 code,
u32 transaction id, then up to five u32 parameters (three for an event) or the data payload, all little
endian. A PTP string is a u8 count of UTF-16 units including the terminating NUL, then UTF-16LE; an array
is a u32 count then the items. The expected bytes below are literals, not made with the codec.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mca.devices.ptp import codec
from mca.devices.ptp.codec import ProtocolError, Reader


def test_command_container_bytes_are_the_standard_layout() -> None:
    # OpenSession (0x1002), transaction 0, session id 1
    assert codec.pack_command(0x1002, 0, [1]) == bytes.fromhex("10000000 0100 0210 00000000 01000000")
    # GetObject (0x1009), transaction 7, handle 0x12345678
    assert codec.pack_command(0x1009, 7, (0x12345678,)) == bytes.fromhex("10000000 0100 0910 07000000 78563412")
    assert codec.pack_command(0x1001, 1) == bytes.fromhex("0c000000 0100 0110 01000000")
    five = codec.pack_command(0x9116, 0xFFFFFFFF, [1, 2, 3, 4, 0xFFFFFFFF])
    assert five == bytes.fromhex("20000000 0100 1691 ffffffff 01000000 02000000 03000000 04000000 ffffffff")


def test_response_event_and_data_container_bytes() -> None:
    assert codec.pack_response(0x2001, 3, [9]) == bytes.fromhex("10000000 0300 0120 03000000 09000000")
    assert codec.pack_event(0x4002, 5, [1, 2, 3]) == bytes.fromhex(
        "18000000 0400 0240 05000000 010000000200000003000000"
    )
    assert codec.pack_data(0x1001, 2, b"\xaa\xbb\xcc") == bytes.fromhex("0f000000 0200 0110 02000000 aabbcc")
    assert codec.pack_data_header(0x1009, 4, 0x1000) == bytes.fromhex("0c100000 0200 0910 04000000")
    assert codec.pack_data_header(0x1009, 4, 0xFFFFFFFF - 12) == bytes.fromhex("ffffffff 0200 0910 04000000")
    with pytest.raises(ProtocolError, match="does not fit"):
        codec.pack_data_header(0x1009, 4, 0xFFFFFFFF - 11)


def test_parameter_limits_when_packing() -> None:
    with pytest.raises(ProtocolError, match="6 parameters, at most 5"):
        codec.pack_command(0x1001, 1, [0] * 6)
    with pytest.raises(ProtocolError, match="4 parameters, at most 3"):
        codec.pack_event(0x4002, 1, [0] * 4)
    codec.pack_response(0x2001, 1, [0] * 5)  # five are fine for a response
    with pytest.raises(ProtocolError, match="does not fit in u32"):
        codec.pack_command(0x1001, 1, [0x1_0000_0000])
    with pytest.raises(ProtocolError, match="does not fit in u32"):
        codec.pack_command(0x1001, 1, [-1])
    codec.pack_command(0x1001, 1, [0, 0xFFFFFFFF])


def test_parse_container_reads_the_standard_layout() -> None:
    got = codec.parse_container(bytes.fromhex("14000000 0300 0120 0a000000 05000000 06000000"))
    assert (got.type, got.code, got.transaction_id, got.params, got.payload) == (3, 0x2001, 10, (5, 6), b"")
    data = codec.parse_container(bytes.fromhex("10000000 0200 0410 02000000 01020304"))
    assert (data.type, data.code, data.transaction_id, data.params, data.payload) == (
        2,
        0x1004,
        2,
        (),
        b"\x01\x02\x03\x04",
    )
    event = codec.parse_container(bytearray.fromhex("10000000 0400 0240 00000000 07000000"))
    assert event.params == (7,) and event.type == 4
    header = codec.parse_header(memoryview(bytes.fromhex("10000000 0200 0910 03000000")))
    assert (header.length, header.type, header.code, header.transaction_id, header.payload_bytes) == (
        16,
        2,
        0x1009,
        3,
        4,
    )


@pytest.mark.parametrize(
    ("hex_bytes", "message"),
    [
        ("0c000000 0100 0110", "header needs 12 bytes, got 8"),
        ("0c000000 0500 0110 01000000", "unknown container type 5"),
        ("0c000000 0000 0110 01000000", "unknown container type 0"),
        ("0b000000 0300 0120 01000000", "shorter than its header"),
        ("00000000 0200 0120 01000000", "shorter than its header"),
        ("0e000000 0300 0120 01000000 0000", "not a header plus at most 5"),  # not whole u32s
        ("24000000 0100 0110 01000000" + "00000000" * 6, "not a header plus at most 5"),  # six parameters
        ("1c000000 0400 0240 01000000" + "00000000" * 4, "event container .* at most 3"),  # four for an event
        ("14000000 0300 0120 01000000 01000000", "claims 20 bytes but 16"),  # shorter than it claims
        ("10000000 0300 0120 01000000 01000000 ff", "claims 16 bytes but 17"),  # trailing bytes
    ],
)
def test_malformed_containers_are_refused_with_the_reason(hex_bytes: str, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        codec.parse_container(bytes.fromhex(hex_bytes))


def test_header_limits_are_inclusive() -> None:
    exactly = bytes.fromhex("20000000 0200 0910 01000000")
    assert codec.parse_header(exactly, max_container_bytes=32).length == 32
    with pytest.raises(ProtocolError, match="claims 33 bytes, more than the 32 allowed"):
        codec.parse_header(bytes.fromhex("21000000 0200 0910 01000000"), max_container_bytes=32)
    # exactly five / three parameters pass, data containers have no parameter rule
    assert codec.parse_header(bytes.fromhex("20000000 0100 0110 01000000")).length == 32
    assert codec.parse_header(bytes.fromhex("18000000 0400 0240 01000000")).length == 24
    assert codec.parse_header(bytes.fromhex("13000000 0200 0110 01000000")).payload_bytes == 7
    assert codec.parse_header(bytes.fromhex("0c000000 0300 0120 01000000")).payload_bytes == 0


@given(
    kind=st.sampled_from([1, 3, 4]),
    code=st.integers(0, 0xFFFF),
    tid=st.integers(0, 0xFFFFFFFF),
    params=st.lists(st.integers(0, 0xFFFFFFFF), max_size=5),
)
def test_params_containers_round_trip_and_match_struct(kind: int, code: int, tid: int, params: list[int]) -> None:
    if kind == 4:
        params = params[:3]
    raw = codec.pack_params_container(kind, code, tid, params)
    assert raw == struct.pack(f"<IHHI{len(params)}I", 12 + 4 * len(params), kind, code, tid, *params)
    back = codec.parse_container(raw)
    assert (back.type, back.code, back.transaction_id, back.params) == (kind, code, tid, tuple(params))


@given(payload=st.binary(max_size=300), code=st.integers(0, 0xFFFF), tid=st.integers(0, 0xFFFFFFFF))
def test_data_containers_round_trip(payload: bytes, code: int, tid: int) -> None:
    raw = codec.pack_data(code, tid, payload)
    assert raw[:12] == struct.pack("<IHHI", 12 + len(payload), 2, code, tid)
    back = codec.parse_container(raw)
    assert back.payload == payload and back.params == () and back.code == code and back.transaction_id == tid


def test_older_transactions_with_wraparound() -> None:
    assert codec.is_older_transaction(4, 5)
    assert not codec.is_older_transaction(5, 5)
    assert not codec.is_older_transaction(6, 5)
    assert codec.is_older_transaction(0xFFFFFFFF, 0)  # wrapped: the id before 0
    assert not codec.is_older_transaction(0, 0xFFFFFFFF)
    assert codec.is_older_transaction(5 - 2**31 + 1 + 2**32, 5)  # just under half the ring back
    assert not codec.is_older_transaction((5 - 2**31) % 2**32, 5)  # exactly half: not older


def test_parse_params() -> None:
    assert codec.parse_params(bytes.fromhex("01000000 02000000")) == (1, 2)
    assert codec.parse_params(b"") == ()
    assert codec.parse_params(b"\x00" * 20) == (0,) * 5
    with pytest.raises(ProtocolError, match="24 bytes"):
        codec.parse_params(b"\x00" * 24)
    with pytest.raises(ProtocolError, match="6 bytes"):
        codec.parse_params(b"\x00" * 6)
    assert codec.parse_params(b"\x00" * 12, limit=3) == (0, 0, 0)
    with pytest.raises(ProtocolError):
        codec.parse_params(b"\x00" * 16, limit=3)


def test_reader_reads_little_endian_scalars_and_checks_every_byte() -> None:
    r = Reader(bytes.fromhex("01 0302 07060504 0f0e0d0c0b0a0908 ff"))
    assert r.remaining == 16
    assert r.u8() == 1
    assert r.u16() == 0x0203
    assert r.u32() == 0x04050607
    assert r.u64() == 0x08090A0B0C0D0E0F
    assert r.remaining == 1 and r.pos == 15
    with pytest.raises(ProtocolError, match="u16 needs 2 bytes at offset 15, 1 left"):
        r.u16()
    assert r.u8() == 0xFF
    for read in (r.u8, r.u16, r.u32, r.u64):
        with pytest.raises(ProtocolError, match="truncated dataset"):
            read()
    assert r.remaining == 0


def test_reader_window_scalar_and_take() -> None:
    data = bytearray(range(10))
    r = Reader(data, start=2, end=6)
    assert r.remaining == 4 and r.pos == 2
    assert r.scalar("h") == 0x0302
    assert r.scalar("B") == 4
    assert r.take(1) == b"\x05"
    with pytest.raises(ProtocolError):
        r.take(1)  # the window ends at 6 although the buffer goes on
    with pytest.raises(ProtocolError):
        r.scalar("B")
    assert Reader(data, end=100).end == 10
    assert Reader(memoryview(b"abc")).take(3) == b"abc"
    with pytest.raises(ProtocolError):
        Reader(b"abc").take(-1)
    assert Reader(b"abc").take(0) == b""


def test_strings_the_standard_way() -> None:
    # "EOS" = 3 units + NUL = 4
    assert codec.pack_string("EOS") == bytes.fromhex("04 4500 4f00 5300 0000")
    assert codec.pack_string("") == b"\x00"
    assert codec.pack_string("µ") == bytes.fromhex("02 b500 0000")
    assert Reader(bytes.fromhex("04 4500 4f00 5300 0000")).string() == "EOS"
    r = Reader(bytes.fromhex("00 02 4100 0000 ff"))
    assert r.string() == "" and r.pos == 1
    assert r.string() == "A" and r.pos == 6
    # a string without its NUL is kept whole; text after an early NUL is dropped
    assert Reader(bytes.fromhex("02 4100 4200")).string() == "AB"
    assert Reader(bytes.fromhex("03 4100 0000 4200")).string() == "A"
    with pytest.raises(ProtocolError):
        Reader(bytes.fromhex("05 4100 0000")).string()
    longest = "x" * 254
    assert codec.pack_string(longest)[0] == 255
    assert Reader(codec.pack_string(longest)).string() == longest
    with pytest.raises(ProtocolError, match="256 UTF-16 units"):
        codec.pack_string("x" * 255)


@given(st.text(max_size=120).filter(lambda t: "\x00" not in t))
def test_any_string_round_trips(text: str) -> None:
    raw = codec.pack_string(text)
    if len(text.encode("utf-16-le")) // 2 + 1 <= 255:
        assert Reader(raw).string() == text


def test_arrays_the_standard_way() -> None:
    assert codec.pack_array("H", [0x1001, 0x1002]) == bytes.fromhex("02000000 0110 0210")
    assert codec.pack_array("I", []) == bytes.fromhex("00000000")
    r = Reader(bytes.fromhex("03000000 0100 0200 0300 ff"))
    assert r.array("H") == (1, 2, 3) and r.pos == 10
    assert Reader(bytes.fromhex("01000000 78563412")).array("I") == (0x12345678,)
    # the count is checked against what remains before anything is allocated
    with pytest.raises(ProtocolError, match="array of 4 items of 2 bytes does not fit the 6 bytes left"):
        Reader(bytes.fromhex("04000000 0100 0200 0300")).array("H")
    with pytest.raises(ProtocolError):
        Reader(bytes.fromhex("ffffffff 00")).array("Q")
    exact = Reader(bytes.fromhex("02000000 01000000 02000000"))
    assert exact.array("I") == (1, 2) and exact.remaining == 0


def test_ascii_cstrings_stop_at_nul_record_end_or_limit() -> None:
    r = Reader(b"IMG_0001.CR2\x00rest")
    assert r.cstring_ascii() == "IMG_0001.CR2" and r.pos == 13
    assert Reader(b"ABCDEF").cstring_ascii() == "ABCDEF"
    unterminated = Reader(b"ABCDEF", end=4)
    assert unterminated.cstring_ascii() == "ABCD" and unterminated.pos == 4
    limited = Reader(b"ABCDEF\x00")
    assert limited.cstring_ascii(max_bytes=3) == "ABC" and limited.pos == 3
    short = Reader(b"AB\x00CDEF")
    assert short.cstring_ascii(max_bytes=5) == "AB" and short.pos == 3
    assert Reader(b"\x00x").cstring_ascii() == ""


def test_scalar_helpers() -> None:
    assert codec.u16(0x1234) == b"\x34\x12"
    assert codec.u32(0x12345678) == b"\x78\x56\x34\x12"
    assert codec.u64(1) == b"\x01" + b"\x00" * 7


def test_the_dataset_limit_is_16_mib() -> None:
    """What a peer may make the host hold in memory for one dataset (DeviceInfo, an event list, ...)."""
    from mca.devices.ptp.datasets import parse_storage_ids

    assert codec.MAX_DATASET_BYTES == 16 * 1024 * 1024
    assert parse_storage_ids(bytes(16 * 1024 * 1024)) == ()
    with pytest.raises(ProtocolError, match="16777217 bytes exceeds the 16777216-byte limit"):
        parse_storage_ids(bytes(16 * 1024 * 1024 + 1))
