"""PTP/IP (PTP over TCP, port 15740): pure packet pack/parse functions and a socket client transport.

Packets are u32 length, u32 type, body. The command/data connection carries
OperationRequest, StartData/Data/EndData and OperationResponse; the event
connection carries Event packets. The simulated camera's server reuses the
same functions from the other side.

The host introduces itself with the same GUID on every connection (a camera
asks its user to approve each new host; libgphoto2 stores its GUID too): by
default one derived from the machine id and the user, or any 16 bytes the
caller keeps. A background thread reads the event connection all the time
(a camera whose event channel is never read stalls), answering pings and
queueing events for `read_event`. Packets are received in bounded pieces, so
a header's claim allocates nothing until the bytes arrive.
"""

from __future__ import annotations

import getpass
import socket
import struct
import threading
import uuid
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from mca.devices.ptp.codec import Container, ProtocolError, Reader, is_older_transaction, parse_params
from mca.devices.ptp.codes import ContainerType
from mca.devices.ptp.policy import DEFAULT_POLICY, PtpPolicy
from mca.devices.ptp.transport import DeviceDisconnected, Response, Transport, TransportError, TransportTimeout

DEFAULT_PORT = 15740
PROTOCOL_VERSION = 0x00010000
INIT_COMMAND_REQUEST, INIT_COMMAND_ACK, INIT_EVENT_REQUEST, INIT_EVENT_ACK, INIT_FAIL = 1, 2, 3, 4, 5
OPERATION_REQUEST, OPERATION_RESPONSE, EVENT, START_DATA, DATA, CANCEL, END_DATA, PING, PONG = range(6, 15)
DATAPHASE_NONE_OR_IN, DATAPHASE_OUT = 1, 2
#: Largest control packet accepted; data packets are bounded by the transaction's own limit.
MAX_CONTROL_PACKET_BYTES = 64 * 1024
MAX_DATA_PACKET_BYTES = 64 * 1024 * 1024
#: Bytes received per recv call: a packet's claimed length is never allocated before its bytes arrive.
RECV_PIECE_BYTES = 64 * 1024
#: Events kept for `read_event`; older ones are dropped beyond this.
MAX_QUEUED_EVENTS = 256
_HDR = struct.Struct("<II")
INIT_FAIL_REASONS = {1: "rejected", 2: "busy (another computer holds the camera)", 3: "unspecified"}


def host_guid(machine_id_path: Path = Path("/etc/machine-id")) -> bytes:
    """A GUID that stays the same for this machine and user, so the camera recognises the host it approved."""
    try:
        machine = machine_id_path.read_text().strip()
    except OSError:
        machine = socket.gethostname()
    try:
        user = getpass.getuser()
    except Exception:
        user = "user"
    return uuid.uuid5(uuid.NAMESPACE_OID, f"mca-ptpip-host:{machine}:{user}").bytes


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
        """Exactly `n` bytes, received in pieces of at most RECV_PIECE_BYTES (nothing allocated up front)."""
        buf = bytearray()
        while len(buf) < n:
            piece = bytearray(min(RECV_PIECE_BYTES, n - len(buf)))
            self.recv_into(memoryview(piece))
            buf += piece
        return bytes(buf)

    def recv_packet(self, max_bytes: int = MAX_CONTROL_PACKET_BYTES) -> tuple[int, bytes]:
        body_len, kind = parse_packet_header(self.recv_exact(8), max_bytes)
        return kind, self.recv_exact(body_len)


class PtpIpTransport(Transport):
    """The initiator (host) side of PTP/IP."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        timeout_s: float | None = None,
        name: str = "mca",
        guid: bytes | None = None,
        policy: PtpPolicy = DEFAULT_POLICY,
    ) -> None:
        super().__init__()
        self.name = f"ptpip:{host}:{port}"
        self.policy = policy
        self.timeout_s = policy.transaction_timeout_s if timeout_s is None else timeout_s
        self.guid = guid if guid is not None else host_guid()
        self._closed = False
        self._desynced = False  # a packet was cut mid-way: the stream cannot be read on
        self._codes: dict[int, int] = {}
        self._events: deque[Container] = deque(maxlen=MAX_QUEUED_EVENTS)
        self._event_ready = threading.Condition()
        self._event_thread: threading.Thread | None = None
        connect_timeout = min(self.timeout_s, 10.0)
        try:
            cmd = socket.create_connection((host, port), timeout=connect_timeout)
        except OSError as exc:
            raise TransportError(
                f"cannot reach {self.name}: {exc}; is the camera (or `mca camera serve-sim`) running?"
            ) from exc
        cmd.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.cmd = _Conn(cmd, self.name)
        self.cmd.send(pack_init_command_request(self.guid, name))
        kind, body = self.cmd.recv_packet()
        if kind != INIT_COMMAND_ACK:
            cmd.close()
            reason = INIT_FAIL_REASONS.get(struct.unpack_from("<I", body)[0], "") if len(body) >= 4 else ""
            raise TransportError(
                f"{self.name} refused the connection (packet type {kind}{', ' + reason if reason else ''}); "
                "accept this computer on the camera's screen, or close the other program using it"
            )
        self.connection_id, self.camera_guid, self.camera_name = parse_init_command_ack(body)
        try:
            evt = socket.create_connection((host, port), timeout=connect_timeout)
        except OSError as exc:
            self.close()
            raise TransportError(f"{self.name}: the event connection failed: {exc}") from exc
        self.evt = _Conn(evt, self.name)
        self.evt.send(pack_packet(INIT_EVENT_REQUEST, struct.pack("<I", self.connection_id)))
        kind, _ = self.evt.recv_packet()
        if kind != INIT_EVENT_ACK:
            self.close()
            raise TransportError(f"{self.name} refused the event connection (packet type {kind})")
        # set here, not in the thread: a transport closed at once must not leave the thread a closed socket
        evt.settimeout(0.5)
        self._event_thread = threading.Thread(target=self._read_events, name="ptpip-events", daemon=True)
        self._event_thread.start()

    # -- the event connection, read all the time ----------------------------------------------------------------
    def _read_events(self) -> None:
        while not self._closed:
            try:
                kind, body = self.evt.recv_packet()
            except TransportTimeout:
                continue
            except (TransportError, ProtocolError, OSError):
                break
            try:
                if kind == PING:
                    self.evt.send(pack_packet(PONG))
                elif kind == EVENT:
                    event = parse_event_packet(body)
                    with self._event_ready:
                        self._events.append(event)
                        self._event_ready.notify_all()
            except (TransportError, ProtocolError):
                continue
        with self._event_ready:
            self._event_ready.notify_all()

    def read_event(self, timeout_s: float) -> Container | None:
        with self._event_ready:
            if not self._events:
                self._event_ready.wait(timeout_s)
            return self._events.popleft() if self._events else None

    # -- transactions ----------------------------------------------------------------------------------------
    def _recv_header(self, max_bytes: int) -> tuple[int, int]:
        raw = self.cmd.recv_exact(8)
        return parse_packet_header(raw, max_bytes)

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
            raise DeviceDisconnected(f"{self.name} is closed; reconnect")
        self._codes[transaction_id] = code  # a late reply's data is handed on with its operation code
        while len(self._codes) > 64:
            del self._codes[next(iter(self._codes))]
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
        stale = 0
        stale_tid: int | None = None
        stale_data = bytearray()
        while True:
            try:
                body_len, kind = self._recv_header(max(max_data_bytes + 4, MAX_CONTROL_PACKET_BYTES))
            except TransportTimeout:
                if got or stale_tid is not None:
                    self._desynced = True
                raise
            self._desynced = True  # until the packet is complete
            if kind in (DATA, END_DATA):
                if body_len < 4:
                    raise ProtocolError(f"{self.name} sent a data packet without its transaction id")
                (tid,) = struct.unpack("<I", self.cmd.recv_exact(4))
                n = body_len - 4
                if stale_tid is not None and tid == stale_tid:
                    piece = self.cmd.recv_exact(n)
                    if len(stale_data) + n <= 4 * 1024 * 1024:
                        stale_data += piece
                    self._desynced = False
                    continue
                if total is None:
                    raise ProtocolError(f"{self.name} sent data without StartData")
                if got + n > total:
                    raise ProtocolError(f"{self.name} sent {got + n} data bytes after announcing {total}")
                if sink is None:
                    self.cmd.recv_into(memoryview(data)[got : got + n])  # type: ignore[arg-type]
                else:
                    remaining = n
                    while remaining:
                        piece = self.cmd.recv_exact(min(RECV_PIECE_BYTES * 16, remaining))
                        sink(memoryview(piece))
                        remaining -= len(piece)
                got += n
                self._desynced = False
                continue
            body = self.cmd.recv_exact(body_len)
            self._desynced = False
            if kind == START_DATA:
                tid, announced = parse_start_data(body)
                if tid != transaction_id:  # the data phase of a reply we gave up on
                    stale_tid, stale_data = tid, bytearray()
                    continue
                total = announced
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
                    if (
                        is_older_transaction(resp.transaction_id, transaction_id)
                        and stale < self.policy.stale_replies_max
                    ):
                        stale += 1
                        self.counters.stale_replies_discarded += 1
                        if stale_tid == resp.transaction_id and self.on_stale_data is not None and stale_data:
                            stale_code = self._codes.get(resp.transaction_id, 0)
                            self.on_stale_data(stale_code, resp.transaction_id, bytes(stale_data))
                        stale_tid, stale_data = None, bytearray()
                        continue
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

    def recover(self, transaction_id: int | None = None) -> None:
        """A timeout between packets leaves the stream in step (a late reply is discarded by its transaction id);
        a packet cut mid-way does not, and the link is closed (the session reconnects)."""
        if self._desynced:
            self.close()

    @property
    def can_resume(self) -> bool:
        return not self._closed

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for conn in (getattr(self, "cmd", None), getattr(self, "evt", None)):
            if conn is not None:
                try:
                    conn.sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                try:
                    conn.sock.close()
                except OSError:
                    pass
        if self._event_thread is not None and self._event_thread is not threading.current_thread():
            self._event_thread.join(2.0)
