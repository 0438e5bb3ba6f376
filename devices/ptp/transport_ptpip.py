"""PTP/IP (PTP over TCP, port 15740): pure packet pack/parse functions and a socket client transport.

Packets are u32 length, u32 type, body. The command/data connection carries
OperationRequest, StartData/Data/EndData and OperationResponse; the event
connection carries Event packets. The simulated camera's server reuses the
same functions from the other side.
"""

from __future__ import annotations

import select
import socket
import struct
import uuid
from dataclasses import dataclass

from mca.devices.ptp.codec import Container, ProtocolError, Reader, parse_params
from mca.devices.ptp.codes import ContainerType
from mca.devices.ptp.transport import DeviceDisconnected, Response, Transport, TransportError, TransportTimeout

DEFAULT_PORT = 15740
PROTOCOL_VERSION = 0x00010000
INIT_COMMAND_REQUEST, INIT_COMMAND_ACK, INIT_EVENT_REQUEST, INIT_EVENT_ACK, INIT_FAIL = 1, 2, 3, 4, 5
OPERATION_REQUEST, OPERATION_RESPONSE, EVENT, START_DATA, DATA, CANCEL, END_DATA, PING, PONG = range(6, 15)
DATAPHASE_NONE_OR_IN, DATAPHASE_OUT = 1, 2
#: Largest control packet accepted; data packets are bounded by the transaction's own limit.
MAX_CONTROL_PACKET_BYTES = 64 * 1024
MAX_DATA_PACKET_BYTES = 64 * 1024 * 1024
_HDR = struct.Struct("<II")


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


def pack_data_packet(transaction_id: int, payload: bytes | memoryview, end: bool) -> bytes:
    return _HDR.pack(12 + len(payload), END_DATA if end else DATA) + struct.pack("<I", transaction_id) + bytes(payload)


class _Conn:
    """Blocking socket helpers with exact reads."""

    def __init__(self, sock: socket.socket, name: str) -> None:
        self.sock, self.name = sock, name

    def send(self, data: bytes | memoryview) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise DeviceDisconnected(
                f"{self.name}: connection lost while sending ({exc}); restart the camera's network link"
            ) from exc

    def recv_into(self, view: memoryview) -> None:
        got = 0
        while got < len(view):
            try:
                n = self.sock.recv_into(view[got:])
            except TimeoutError as exc:
                raise TransportTimeout(f"{self.name} did not answer in time") from exc
            except OSError as exc:
                raise DeviceDisconnected(f"{self.name}: connection lost ({exc})") from exc
            if n == 0:
                raise DeviceDisconnected(f"{self.name} closed the connection")
            got += n

    def recv_exact(self, n: int) -> bytes:
        buf = bytearray(n)
        self.recv_into(memoryview(buf))
        return bytes(buf)

    def recv_packet(self, max_bytes: int = MAX_CONTROL_PACKET_BYTES) -> tuple[int, bytes]:
        body_len, kind = parse_packet_header(self.recv_exact(8), max_bytes)
        return kind, self.recv_exact(body_len)


class PtpIpTransport(Transport):
    """The initiator (host) side of PTP/IP."""

    def __init__(
        self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, timeout_s: float = 5.0, name: str = "mca"
    ) -> None:
        self.name = f"ptpip:{host}:{port}"
        self.timeout_s = timeout_s
        self._closed = False
        try:
            cmd = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise TransportError(
                f"cannot reach {self.name}: {exc}; is the camera (or `mca camera serve-sim`) running?"
            ) from exc
        cmd.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.cmd = _Conn(cmd, self.name)
        self.cmd.send(pack_init_command_request(uuid.uuid4().bytes, name))
        kind, body = self.cmd.recv_packet()
        if kind != INIT_COMMAND_ACK:
            cmd.close()
            raise TransportError(
                f"{self.name} refused the connection (packet type {kind}); accept the host on the camera"
            )
        self.connection_id, self.camera_guid, self.camera_name = parse_init_command_ack(body)
        evt = socket.create_connection((host, port), timeout=timeout_s)
        self.evt = _Conn(evt, self.name)
        self.evt.send(pack_packet(INIT_EVENT_REQUEST, struct.pack("<I", self.connection_id)))
        kind, _ = self.evt.recv_packet()
        if kind != INIT_EVENT_ACK:
            self.close()
            raise TransportError(f"{self.name} refused the event connection (packet type {kind})")

    def transaction(
        self,
        code,
        transaction_id,
        params=(),
        *,
        data_out=None,
        sink=None,
        max_data_bytes=64 * 1024 * 1024,
        timeout_s=None,
    ) -> Response:
        if self._closed:
            raise TransportError(f"{self.name} is closed")
        self.cmd.sock.settimeout(self.timeout_s if timeout_s is None else timeout_s)
        self.cmd.send(
            pack_operation_request(
                code, transaction_id, tuple(params), DATAPHASE_OUT if data_out is not None else DATAPHASE_NONE_OR_IN
            )
        )
        if data_out is not None:
            self.cmd.send(pack_start_data(transaction_id, len(data_out)))
            self.cmd.send(pack_data_packet(transaction_id, data_out, end=True))
        total: int | None = None
        got = 0
        data: bytearray | None = None
        while True:
            body_len, kind = parse_packet_header(
                self.cmd.recv_exact(8), max(max_data_bytes + 4, MAX_CONTROL_PACKET_BYTES)
            )
            if kind in (DATA, END_DATA):
                if total is None:
                    raise ProtocolError(f"{self.name} sent data without StartData")
                if body_len < 4:
                    raise ProtocolError(f"{self.name} sent a data packet without its transaction id")
                (_tid,) = struct.unpack("<I", self.cmd.recv_exact(4))
                n = body_len - 4
                if got + n > total:
                    raise ProtocolError(f"{self.name} sent {got + n} data bytes after announcing {total}")
                if sink is None:
                    self.cmd.recv_into(memoryview(data)[got : got + n])  # type: ignore[arg-type]
                else:
                    piece = bytearray(n)
                    self.cmd.recv_into(memoryview(piece))
                    sink(memoryview(piece))
                got += n
                continue
            body = self.cmd.recv_exact(body_len)
            if kind == START_DATA:
                _, total = parse_start_data(body)
                if total > max_data_bytes:
                    raise ProtocolError(
                        f"{self.name} announced {total} data bytes, more than the {max_data_bytes} expected"
                    )
                if sink is None:
                    data = bytearray(total)
                continue
            if kind == OPERATION_RESPONSE:
                resp = parse_operation_response(body)
                if resp.transaction_id != transaction_id:
                    raise ProtocolError(
                        f"{self.name} answered transaction {resp.transaction_id}, expected {transaction_id}"
                    )
                if total is not None and got != total:
                    raise ProtocolError(f"{self.name} sent {got} of the {total} data bytes it announced")
                return Response(resp.code, resp.params, bytes(data) if data is not None else None, got)
            if kind == PING:
                self.cmd.send(pack_packet(PONG))
                continue
            raise ProtocolError(f"{self.name} sent PTP/IP packet type {kind} during a transaction")

    def read_event(self, timeout_s: float) -> Container | None:
        ready, _, _ = select.select([self.evt.sock], [], [], timeout_s)
        if not ready:
            return None
        self.evt.sock.settimeout(self.timeout_s)
        kind, body = self.evt.recv_packet()
        if kind == PING:
            self.evt.send(pack_packet(PONG))
            return None
        if kind != EVENT:
            raise ProtocolError(f"{self.name} sent packet type {kind} on the event connection")
        return parse_event_packet(body)

    def recover(self) -> None:
        """PTP/IP has no stall to clear: a broken stream cannot be resynchronised, so the link is closed."""
        self.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for conn in (getattr(self, "cmd", None), getattr(self, "evt", None)):
            if conn is not None:
                try:
                    conn.sock.close()
                except OSError:
                    pass
