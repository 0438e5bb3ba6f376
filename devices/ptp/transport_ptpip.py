"""PTP/IP (PTP over TCP, port 15740): the socket client transport, a thin shell around the transaction engine.

The packets are `devices.ptp.ptpip_packets`; their framing, the phases, the
transaction ids and late replies are the engine's (`devices.ptp.engine` with
`framing.PtpIpFraming`). This shell connects, introduces the host, moves
bytes and answers pings.

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
import time
import uuid
from collections import deque
from pathlib import Path

from mca.devices.ptp.codec import Container, ProtocolError
from mca.devices.ptp.codes import ContainerType
from mca.devices.ptp.engine import NEED_DATA, EventReader, EventReceived, Initiator, PingReceived
from mca.devices.ptp.framing import PtpIpFraming
from mca.devices.ptp.policy import DEFAULT_POLICY, PtpPolicy
from mca.devices.ptp.ptpip_packets import (
    DEFAULT_PORT,
    INIT_COMMAND_ACK,
    INIT_EVENT_ACK,
    INIT_EVENT_REQUEST,
    INIT_FAIL_REASONS,
    MAX_CONTROL_PACKET_BYTES,
    pack_init_command_request,
    pack_packet,
    parse_init_command_ack,
    parse_packet_header,
)
from mca.devices.ptp.transport import (
    DeviceDisconnected,
    Response,
    Transport,
    TransportError,
    TransportTimeout,
    run_to_response,
)

#: Bytes received per recv call: a packet's claimed length is never allocated before its bytes arrive.
RECV_PIECE_BYTES = 64 * 1024
#: Bytes received per recv call on the command connection during a transaction (a download's pieces).
RECV_DATA_PIECE_BYTES = 1024 * 1024
#: Events kept for `read_event`; older ones are dropped beyond this.
MAX_QUEUED_EVENTS = 256


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


class _Conn:
    """Blocking socket helpers: exact reads for the handshake, bounded reads to feed an engine."""

    def __init__(self, sock: socket.socket, name: str, piece_bytes: int = RECV_PIECE_BYTES) -> None:
        self.sock, self.name = sock, name
        self._rx = bytearray(piece_bytes)
        self._rx_view = memoryview(self._rx)

    def _recv_once(self, view: memoryview) -> int:
        """One recv into `view`: at least one byte, or the timeout or disconnect as a transport error."""
        try:
            n = self.sock.recv_into(view)
        except TimeoutError as exc:
            raise TransportTimeout(f"{self.name} did not answer in time") from exc
        except OSError as exc:
            raise DeviceDisconnected(f"{self.name}: connection lost ({exc})") from exc
        if n == 0:
            raise DeviceDisconnected(f"{self.name} closed the connection")
        return n

    def recv_some(self) -> memoryview:
        """What has arrived, at most one piece (valid until the next call; the engine copies what it keeps)."""
        return self._rx_view[: self._recv_once(self._rx_view)]

    def send(self, data: bytes | bytearray | memoryview) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise DeviceDisconnected(
                f"{self.name}: connection lost while sending ({exc}); restart the camera's network link"
            ) from exc

    def recv_into(self, view: memoryview) -> None:
        got = 0
        while got < len(view):
            got += self._recv_once(view[got:])

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


#: On close, how long to wait for the camera to close the command connection too (it ends the session first).
CLOSE_WAIT_S = 1.0


def _close_gracefully(sock: socket.socket, wait_s: float) -> None:
    """Close our side of a connection (FIN) and wait, at most `wait_s`, for the camera to close its side.

    The camera ends the session when it sees the command connection close, and only then closes its end: a
    host that reconnects (or another program that connects) after this returns finds the camera free,
    instead of "busy" while the camera is still releasing the old session."""
    try:
        sock.shutdown(socket.SHUT_WR)
        sock.settimeout(0.05)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            try:
                if not sock.recv(65536):
                    break  # the camera closed its side
            except TimeoutError:
                continue
    except OSError:
        pass
    finally:
        try:
            sock.close()
        except OSError:
            pass


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
        # The transaction state machine and the packets' framing live in the engine; this shell moves bytes.
        self.engine = Initiator(PtpIpFraming(), name=self.name, stale_replies_max=policy.stale_replies_max)
        self._codes = self.engine.sent_codes  # operation code per recent transaction id (late data is handed on)
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
        self.cmd = _Conn(cmd, self.name, RECV_DATA_PIECE_BYTES)
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
        reader = EventReader(PtpIpFraming(), self.name)
        while not self._closed:
            try:
                event = reader.next_event()
            except ProtocolError:
                if reader.framing.broken:
                    break
                continue  # a malformed event, read whole: skipped
            try:
                if event is NEED_DATA:
                    reader.receive_data(self.evt.recv_some())
                elif isinstance(event, PingReceived):
                    self.evt.send(reader.pong())
                elif isinstance(event, EventReceived):
                    with self._event_ready:
                        self._events.append(
                            Container(ContainerType.EVENT, event.code, event.transaction_id, event.params)
                        )
                        self._event_ready.notify_all()
            except TransportTimeout:
                continue
            except (TransportError, OSError):
                break
        with self._event_ready:
            self._event_ready.notify_all()

    def read_event(self, timeout_s: float) -> Container | None:
        with self._event_ready:
            if not self._events:
                self._event_ready.wait(timeout_s)
            return self._events.popleft() if self._events else None

    # -- transactions ----------------------------------------------------------------------------------------
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
        engine = self.engine
        self.cmd.sock.settimeout(self.timeout_s if timeout_s is None else timeout_s)
        for write in engine.send_command(
            code, transaction_id, tuple(params), data_out=data_out, max_data_bytes=max_data_bytes
        ):
            self.cmd.send(write)
        return run_to_response(self, engine, self.cmd.recv_some, sink, self.cmd.send)

    def recover(self, transaction_id: int | None = None) -> None:
        """A timeout between packets leaves the stream in step (a late reply is discarded by its transaction id);
        a packet or data phase cut mid-way does not, and the link is closed (the session reconnects)."""
        if self.engine.in_step:
            self.engine.abandon()
        else:
            self.close()

    @property
    def can_resume(self) -> bool:
        return not self._closed

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        cmd = getattr(self, "cmd", None)
        if cmd is not None:
            _close_gracefully(cmd.sock, min(CLOSE_WAIT_S, self.timeout_s))
        evt = getattr(self, "evt", None)
        if evt is not None:
            try:
                evt.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            try:
                evt.sock.close()
            except OSError:
                pass
        if self._event_thread is not None and self._event_thread is not threading.current_thread():
            self._event_thread.join(2.0)
