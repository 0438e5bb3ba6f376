"""PTP/IP packets (PTP over TCP, CIPA DC-005): their numbers and pure pack/parse functions, no sockets.

A packet is a u32 length (the whole packet), a u32 type, then the body. The
command/data connection carries OperationRequest, StartData/Data/EndData and
OperationResponse; the event connection carries Event packets; either may carry
Ping/Pong. `devices.ptp.framing.PtpIpFraming` streams these through the
transaction engine; the host transport and the simulated camera's server use
the same functions from the two sides.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from mca.devices.ptp.codec import Container, ProtocolError, Reader, parse_params
from mca.devices.ptp.codes import ContainerType

DEFAULT_PORT = 15740
PROTOCOL_VERSION = 0x00010000
INIT_COMMAND_REQUEST, INIT_COMMAND_ACK, INIT_EVENT_REQUEST, INIT_EVENT_ACK, INIT_FAIL = 1, 2, 3, 4, 5
OPERATION_REQUEST, OPERATION_RESPONSE, EVENT, START_DATA, DATA, CANCEL, END_DATA, PING, PONG = range(6, 15)
DATAPHASE_NONE_OR_IN, DATAPHASE_OUT = 1, 2
#: Largest control packet accepted; data packets are bounded by the transaction's own limit.
MAX_CONTROL_PACKET_BYTES = 64 * 1024
MAX_DATA_PACKET_BYTES = 64 * 1024 * 1024
_HDR = struct.Struct("<II")
INIT_FAIL_REASONS = {1: "rejected", 2: "busy (another computer holds the camera)", 3: "unspecified"}


def pack_packet(kind: int, body: bytes = b"") -> bytes:
    return _HDR.pack(8 + len(body), kind) + body


def parse_packet_header(buf: bytes | memoryview, max_bytes: int = MAX_DATA_PACKET_BYTES) -> tuple[int, int]:
    """(body length, type) from the 8-byte header, checked against bounds."""
    if len(buf) < 8:
        raise ProtocolError(f"PTP/IP header needs 8 bytes, got {len(buf)}")
    length, kind = _HDR.unpack_from(buf)
    if length < 8:
        raise ProtocolError(f"PTP/IP packet length {length} is shorter than its header")
    if not 1 <= kind <= 14:
        raise ProtocolError(f"unknown PTP/IP packet type {kind}")
    if length - 8 > max_bytes:
        raise ProtocolError(f"PTP/IP packet of {length} bytes exceeds the {max_bytes}-byte limit")
    return length - 8, kind


def _utf16z(text: str) -> bytes:
    return text.encode("utf-16-le") + b"\x00\x00"


def _read_utf16z(r: Reader) -> str:
    units = []
    while True:
        unit = r.u16()
        if unit == 0:
            break
        units.append(unit)
    return struct.pack(f"<{len(units)}H", *units).decode("utf-16-le", errors="replace")


@dataclass(frozen=True)
class InitCommandRequest:
    guid: bytes
    name: str
    version: int


def pack_init_command_request(guid: bytes, name: str, version: int = PROTOCOL_VERSION) -> bytes:
    if len(guid) != 16:
        raise ValueError("a PTP/IP GUID has 16 bytes")
    return pack_packet(INIT_COMMAND_REQUEST, guid + _utf16z(name) + struct.pack("<I", version))


def parse_init_command_request(body: bytes) -> InitCommandRequest:
    r = Reader(body)
    guid = r.take(16)
    name = _read_utf16z(r)
    version = r.u32() if r.remaining >= 4 else 0
    return InitCommandRequest(guid, name, version)


def pack_init_command_ack(connection_id: int, guid: bytes, name: str, version: int = PROTOCOL_VERSION) -> bytes:
    return pack_packet(
        INIT_COMMAND_ACK, struct.pack("<I", connection_id) + guid + _utf16z(name) + struct.pack("<I", version)
    )


def parse_init_command_ack(body: bytes) -> tuple[int, bytes, str]:
    r = Reader(body)
    return r.u32(), r.take(16), _read_utf16z(r)


def pack_operation_request(code: int, transaction_id: int, params: tuple[int, ...] = (), dataphase: int = 1) -> bytes:
    if len(params) > 5:
        raise ProtocolError("at most 5 parameters")
    return pack_packet(
        OPERATION_REQUEST,
        struct.pack("<IHI", dataphase, code, transaction_id) + struct.pack(f"<{len(params)}I", *params),
    )


def parse_operation_request(body: bytes) -> tuple[int, Container]:
    """(dataphase, command container)."""
    if len(body) < 10:
        raise ProtocolError(f"OperationRequest of {len(body)} bytes is shorter than 10")
    dataphase, code, tid = struct.unpack_from("<IHI", body)
    return dataphase, Container(ContainerType.COMMAND, code, tid, parse_params(body[10:]))


def pack_operation_response(code: int, transaction_id: int, params: tuple[int, ...] = ()) -> bytes:
    return pack_packet(
        OPERATION_RESPONSE, struct.pack("<HI", code, transaction_id) + struct.pack(f"<{len(params)}I", *params)
    )


def parse_operation_response(body: bytes) -> Container:
    if len(body) < 6:
        raise ProtocolError(f"OperationResponse of {len(body)} bytes is shorter than 6")
    code, tid = struct.unpack_from("<HI", body)
    return Container(ContainerType.RESPONSE, code, tid, parse_params(body[6:]))


def pack_event_packet(code: int, transaction_id: int, params: tuple[int, ...] = ()) -> bytes:
    return pack_packet(EVENT, struct.pack("<HI", code, transaction_id) + struct.pack(f"<{len(params)}I", *params))


def parse_event_packet(body: bytes) -> Container:
    if len(body) < 6:
        raise ProtocolError(f"Event packet of {len(body)} bytes is shorter than 6")
    code, tid = struct.unpack_from("<HI", body)
    return Container(ContainerType.EVENT, code, tid, parse_params(body[6:], 3))


def pack_start_data(transaction_id: int, total_bytes: int) -> bytes:
    return pack_packet(START_DATA, struct.pack("<IQ", transaction_id, total_bytes))


def parse_start_data(body: bytes) -> tuple[int, int]:
    if len(body) < 8:
        raise ProtocolError(f"StartData of {len(body)} bytes is shorter than 8")
    if len(body) >= 12:
        return struct.unpack_from("<IQ", body)
    return struct.unpack_from("<II", body)


def pack_data_packet(transaction_id: int, payload: bytes | bytearray | memoryview, end: bool) -> bytes:
    return _HDR.pack(12 + len(payload), END_DATA if end else DATA) + struct.pack("<I", transaction_id) + bytes(payload)
