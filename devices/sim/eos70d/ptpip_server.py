"""The simulated EOS 70D served over PTP/IP on 127.0.0.1 (what `mca camera serve-sim --ptpip` runs).

One initiator holds the camera at a time, as on a real body: the command
connection is greeted with InitCommandAck, the event connection with
InitEventAck, then operations run through `SimEos70D.handle`, framed and
checked by the same transaction engine as the host's (`devices.ptp.engine`,
the responder side). A second
initiator gets InitFail (busy) and cannot end the first one's session; only
the session owner's disconnect ends it. Connections are capped
(`max_connections`), a connection that does not complete its handshake in
time is dropped, and every packet is read in bounded pieces: a header
claiming a large body costs nothing until the bytes actually arrive.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
import uuid

from mca.devices.ptp.codec import Container, ProtocolError
from mca.devices.ptp.codes import ContainerType
from mca.devices.ptp.engine import (
    NEED_DATA,
    CommandReceived,
    DataFinished,
    DataReceived,
    EventReader,
    PingReceived,
    Responder,
)
from mca.devices.ptp.framing import PtpIpFraming
from mca.devices.ptp.ptpip_packets import (
    INIT_COMMAND_REQUEST,
    INIT_EVENT_ACK,
    INIT_EVENT_REQUEST,
    INIT_FAIL,
    MAX_CONTROL_PACKET_BYTES,
    pack_event_packet,
    pack_init_command_ack,
    pack_packet,
    parse_init_command_request,
)
from mca.devices.ptp.transport import TransportError, TransportTimeout
from mca.devices.ptp.transport_ptpip import _Conn
from mca.devices.sim.eos70d.faults import DOWNLOAD_OPS, FaultPlan
from mca.devices.sim.eos70d.responder import SimEos70D

DATA_CHUNK_BYTES = 1024 * 1024
MAX_DATA_OUT_BYTES = 16 * 1024 * 1024
#: Connections held open at once (a command and an event connection per initiator, plus refusals in flight).
MAX_CONNECTIONS = 8
#: A connection must complete its init handshake within this time.
HANDSHAKE_TIMEOUT_S = 10.0
#: A packet begun must be complete within this time.
PACKET_TIMEOUT_S = 10.0
#: InitFail reasons (PTP/IP): 1 rejected, 2 busy, 3 unspecified.
FAIL_REJECTED, FAIL_BUSY = 1, 2


class PtpIpServer:
    """A PTP/IP responder for a `SimEos70D`; bind only to loopback addresses."""

    def __init__(
        self,
        camera: SimEos70D | None = None,
        host: str = "127.0.0.1",
        port: int = 15740,
        *,
        faults: FaultPlan | None = None,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        if host not in ("127.0.0.1", "localhost", "::1"):
            raise ValueError(f"the simulated camera binds only to loopback, not {host!r}")
        self.camera = camera or SimEos70D()
        self.faults = faults or FaultPlan()
        self.max_connections = max_connections
        self.guid = uuid.uuid5(uuid.NAMESPACE_OID, self.camera.serial_number).bytes
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.settimeout(0.2)
        self.host, self.port = self._listener.getsockname()[:2]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._sockets: set[socket.socket] = set()
        self._next_conn = 1
        self._event_conns: dict[int, tuple[_Conn | None, threading.Event]] = {}
        self._owner: int | None = None  # the connection id holding the camera
        self._lock = threading.Lock()
        self.sessions_served = 0
        self.refused = 0

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def start(self) -> PtpIpServer:
        t = threading.Thread(target=self._accept_loop, name="sim-ptpip-accept", daemon=True)
        t.start()
        self._threads.append(t)
        return self

    def serve_forever(self) -> None:
        self.start()
        try:
            while not self._stop.is_set():
                time.sleep(0.2)
        finally:
            self.close()

    def close(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        try:
            self._listener.close()
        except OSError:
            pass
        with self._lock:
            for s in list(self._sockets):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))

    def __enter__(self) -> PtpIpServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def open_connections(self) -> int:
        with self._lock:
            return len(self._sockets)

    # -- connections -----------------------------------------------------
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                full = len(self._sockets) >= self.max_connections
                if not full:
                    self._sockets.add(sock)
            if full:  # too many at once: refuse without reading anything
                self.refused += 1
                try:
                    sock.sendall(pack_packet(INIT_FAIL, struct.pack("<I", FAIL_BUSY)))
                except OSError:
                    pass
                sock.close()
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            t = threading.Thread(target=self._serve_socket, args=(sock,), name="sim-ptpip-conn", daemon=True)
            t.start()
            self._threads = [x for x in self._threads if x.is_alive()] + [t]

    def _drop(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.discard(sock)
        try:
            sock.close()
        except OSError:
            pass

    def _serve_socket(self, sock: socket.socket) -> None:
        conn = _Conn(sock, "PTP/IP initiator")
        sock.settimeout(HANDSHAKE_TIMEOUT_S)
        try:
            kind, body = conn.recv_packet(MAX_CONTROL_PACKET_BYTES)
            if kind == INIT_COMMAND_REQUEST:
                parse_init_command_request(body)
                with self._lock:
                    busy = self._owner is not None
                    if not busy:
                        conn_id = self._next_conn
                        self._next_conn += 1
                        self._owner = conn_id
                        ready = threading.Event()
                        self._event_conns[conn_id] = (None, ready)
                if busy:  # another initiator holds the camera
                    self.refused += 1
                    conn.send(pack_packet(INIT_FAIL, struct.pack("<I", FAIL_BUSY)))
                    return
                try:
                    conn.send(
                        pack_init_command_ack(conn_id, self.guid, self.camera.device_info().model.replace("Canon ", ""))
                    )
                    ready.wait(HANDSHAKE_TIMEOUT_S)
                    self._command_loop(conn, conn_id)
                finally:
                    self._end_session(conn_id)
            elif kind == INIT_EVENT_REQUEST:
                (conn_id,) = struct.unpack_from("<I", body) if len(body) >= 4 else (0,)
                with self._lock:
                    entry = self._event_conns.get(conn_id)
                    taken = entry is not None and entry[0] is not None
                if entry is None or taken:
                    conn.send(pack_packet(INIT_FAIL, struct.pack("<I", FAIL_REJECTED)))
                    return
                conn.send(pack_packet(INIT_EVENT_ACK))
                with self._lock:
                    self._event_conns[conn_id] = (conn, entry[1])
                entry[1].set()
                self._event_loop(conn, conn_id)
            else:
                conn.send(pack_packet(INIT_FAIL, struct.pack("<I", FAIL_REJECTED)))
        except (TransportError, ProtocolError, OSError):
            pass
        finally:
            self._drop(sock)

    def _end_session(self, conn_id: int) -> None:
        """The owner left: the camera's session ends, and its event connection with it."""
        with self._lock:
            if self._owner != conn_id:
                return
            self._owner = None
            entry = self._event_conns.pop(conn_id, None)
        self.camera.disconnect()
        if entry and entry[0] is not None:
            try:
                entry[0].sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def _event_loop(self, conn: _Conn, conn_id: int) -> None:
        conn.sock.settimeout(0.1)
        send_lock = threading.Lock()

        def listener(ev) -> None:
            with send_lock:
                conn.send(pack_event_packet(ev.code, ev.transaction_id, ev.params))

        self.camera.std_event_listeners.append(listener)
        reader = EventReader(PtpIpFraming(), "PTP/IP initiator")
        try:
            while not self._stop.is_set():
                with self._lock:
                    if conn_id not in self._event_conns:
                        return
                event = reader.next_event()
                if event is NEED_DATA:
                    try:
                        reader.receive_data(conn.recv_some())
                    except TransportTimeout:
                        continue
                elif isinstance(event, PingReceived):
                    with send_lock:
                        conn.send(reader.pong())
        finally:
            try:
                self.camera.std_event_listeners.remove(listener)
            except ValueError:
                pass

    def _command_loop(self, conn: _Conn, conn_id: int) -> None:
        self.sessions_served += 1
        conn.sock.settimeout(0.5)
        engine = Responder(
            PtpIpFraming(),
            name="PTP/IP initiator",
            expects_data_out=self.camera.expects_data_out,
            max_data_out_bytes=MAX_DATA_OUT_BYTES,
        )
        command: CommandReceived | None = None
        data_out = bytearray()
        waited_s = 0.0
        while not self._stop.is_set():
            event = engine.next_event()
            if event is NEED_DATA:
                try:
                    engine.receive_data(conn.recv_some())
                    waited_s = 0.0
                except TransportTimeout:
                    waited_s += 0.5
                    if not engine.in_step and waited_s >= PACKET_TIMEOUT_S:
                        return  # a packet cut mid-way: the initiator is gone
                    continue
            elif isinstance(event, PingReceived):
                conn.send(engine.pong())
            elif isinstance(event, CommandReceived):
                command, data_out = event, bytearray()
                if not event.data_out and not self._respond_in_time(conn, engine, event, None):
                    return
            elif isinstance(event, DataReceived):
                data_out += event.data
            elif (
                isinstance(event, DataFinished)
                and command is not None
                and not self._respond_in_time(conn, engine, command, bytes(data_out))
            ):
                return

    def _respond_in_time(
        self, conn: _Conn, engine: Responder, command: CommandReceived, data_out: bytes | None
    ) -> bool:
        conn.sock.settimeout(PACKET_TIMEOUT_S)  # a reply's packets may take a while to go out
        try:
            return self._respond(conn, engine, command, data_out)
        finally:
            engine.drop_reply()  # a reply not sent by now never comes
            conn.sock.settimeout(0.5)

    def _respond(self, conn: _Conn, engine: Responder, command: CommandReceived, data_out: bytes | None) -> bool:
        f = self.faults
        cmd = Container(ContainerType.COMMAND, command.code, command.transaction_id, command.params)
        if f.stall_op is not None and cmd.code == f.stall_op:
            f.stall_op = None
            self._stop.wait(30.0)  # the initiator times out and hangs up
            return False
        if f.busy_count:
            self.camera.busy_responses += f.busy_count
            f.busy_count = 0
        self.camera.short_partial_bytes = f.short_read_bytes
        reply = self.camera.handle(cmd, data_out)
        if reply.dropped:
            return True
        delay = reply.delay_s
        if f.late_reply_op is not None and cmd.code == f.late_reply_op:
            f.late_reply_op = None
            delay += f.late_reply_s
        if delay:
            self._stop.wait(delay)
        cut_after = None
        if f.disconnect_after_in_bytes is not None and cmd.code in DOWNLOAD_OPS:
            cut_after, f.disconnect_after_in_bytes = f.disconnect_after_in_bytes, None
        if reply.data is not None:
            data = memoryview(reply.data).cast("B")
            conn.send(engine.send_data_start(len(data)))
            if len(data) == 0:
                conn.send(engine.send_data_piece(b"", last=True))
            for start in range(0, len(data), DATA_CHUNK_BYTES):
                piece = data[start : start + DATA_CHUNK_BYTES]
                if cut_after is not None and start + len(piece) > cut_after:
                    conn.send(engine.send_data_piece(piece[: max(0, cut_after - start)], last=False))
                    return False
                conn.send(engine.send_data_piece(piece, last=start + DATA_CHUNK_BYTES >= len(data)))
        resp = engine.send_response(reply.response.code, reply.response.params)
        if f.corrupt_op is not None and cmd.code == f.corrupt_op:
            f.corrupt_op = None
            resp = b"\x03\x00\x00\x00" + resp[4:]
        conn.send(resp)
        return True


def parse_address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host:
        host, port = text, str(15740)
    return host, int(port)
