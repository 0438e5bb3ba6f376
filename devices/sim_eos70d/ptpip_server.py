"""The simulated EOS 70D served over PTP/IP on 127.0.0.1 (what `mca camera serve-sim --ptpip` runs).

One initiator at a time: the command connection is greeted with
InitCommandAck, the event connection with InitEventAck, then operations
run through `SimEos70D.handle`. Closing the connection ends the session.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
import uuid

from mca.devices.ptp.codec import ProtocolError
from mca.devices.ptp.transport import TransportError
from mca.devices.ptp.transport_ptpip import (
    DATA,
    END_DATA,
    INIT_COMMAND_REQUEST,
    INIT_EVENT_ACK,
    INIT_EVENT_REQUEST,
    MAX_DATA_PACKET_BYTES,
    OPERATION_REQUEST,
    PING,
    PONG,
    START_DATA,
    _Conn,
    pack_data_packet,
    pack_event_packet,
    pack_init_command_ack,
    pack_operation_response,
    pack_packet,
    pack_start_data,
    parse_init_command_request,
    parse_operation_request,
    parse_packet_header,
    parse_start_data,
)
from mca.devices.sim_eos70d.faults import DOWNLOAD_OPS, FaultPlan
from mca.devices.sim_eos70d.responder import SimEos70D

DATA_CHUNK_BYTES = 1024 * 1024
MAX_DATA_OUT_BYTES = 16 * 1024 * 1024


class PtpIpServer:
    """A PTP/IP responder for a `SimEos70D`; bind only to loopback addresses."""

    def __init__(
        self,
        camera: SimEos70D | None = None,
        host: str = "127.0.0.1",
        port: int = 15740,
        *,
        faults: FaultPlan | None = None,
    ) -> None:
        if host not in ("127.0.0.1", "localhost", "::1"):
            raise ValueError(f"the simulated camera binds only to loopback, not {host!r}")
        self.camera = camera or SimEos70D()
        self.faults = faults or FaultPlan()
        self.guid = uuid.uuid5(uuid.NAMESPACE_OID, self.camera.serial_number).bytes
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.settimeout(0.2)
        self.host, self.port = self._listener.getsockname()[:2]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._sockets: set[socket.socket] = set()
        self._next_conn = 1
        self._event_conns: dict[int, tuple[_Conn, threading.Event]] = {}
        self._lock = threading.Lock()
        self.sessions_served = 0

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

    # -- connections -----------------------------------------------------
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._sockets.add(sock)
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
        sock.settimeout(10.0)
        try:
            kind, body = conn.recv_packet()
            if kind == INIT_COMMAND_REQUEST:
                parse_init_command_request(body)
                with self._lock:
                    conn_id = self._next_conn
                    self._next_conn += 1
                    ready = threading.Event()
                    self._event_conns[conn_id] = (None, ready)  # type: ignore[assignment]
                conn.send(
                    pack_init_command_ack(conn_id, self.guid, self.camera.device_info().model.replace("Canon ", ""))
                )
                ready.wait(10.0)
                self._command_loop(conn, conn_id)
            elif kind == INIT_EVENT_REQUEST:
                (conn_id,) = struct.unpack_from("<I", body) if len(body) >= 4 else (0,)
                with self._lock:
                    entry = self._event_conns.get(conn_id)
                if entry is None:
                    conn.send(pack_packet(5, struct.pack("<I", 1)))  # InitFail
                    return
                conn.send(pack_packet(INIT_EVENT_ACK))
                with self._lock:
                    self._event_conns[conn_id] = (conn, entry[1])
                entry[1].set()
                self._event_loop(conn, conn_id)
            else:
                conn.send(pack_packet(5, struct.pack("<I", 1)))
        except (TransportError, ProtocolError, OSError):
            pass
        finally:
            self._drop(sock)

    def _event_loop(self, conn: _Conn, conn_id: int) -> None:
        conn.sock.settimeout(0.1)
        listener = lambda ev: conn.send(pack_event_packet(ev.code, ev.transaction_id, ev.params))  # noqa: E731
        self.camera.std_event_listeners.append(listener)
        try:
            while not self._stop.is_set():
                try:
                    kind, _ = conn.recv_packet()
                except TransportError as exc:
                    if "did not answer" in str(exc):
                        continue
                    return
                if kind == PING:
                    conn.send(pack_packet(PONG))
        finally:
            try:
                self.camera.std_event_listeners.remove(listener)
            except ValueError:
                pass

    def _command_loop(self, conn: _Conn, conn_id: int) -> None:
        self.sessions_served += 1
        conn.sock.settimeout(0.5)
        try:
            while not self._stop.is_set():
                try:
                    header = conn.recv_exact(8)
                except TransportError as exc:
                    if "did not answer" in str(exc):
                        continue
                    return
                conn.sock.settimeout(10.0)
                body_len, kind = parse_packet_header(header)
                body = conn.recv_exact(body_len)
                if kind == PING:
                    conn.send(pack_packet(PONG))
                    continue
                if kind != OPERATION_REQUEST:
                    raise ProtocolError(f"expected OperationRequest, got packet type {kind}")
                _, cmd = parse_operation_request(body)
                data_out = self._receive_data_out(conn) if self.camera.expects_data_out(cmd.code) else None
                if not self._respond(conn, cmd, data_out):
                    return
                conn.sock.settimeout(0.5)
        finally:
            self.camera.disconnect()
            with self._lock:
                entry = self._event_conns.pop(conn_id, None)
            if entry and entry[0] is not None:
                try:
                    entry[0].sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def _receive_data_out(self, conn: _Conn) -> bytes:
        kind, body = conn.recv_packet()
        if kind != START_DATA:
            raise ProtocolError(f"expected StartData, got packet type {kind}")
        _, total = parse_start_data(body)
        if total > MAX_DATA_OUT_BYTES:
            raise ProtocolError(f"data-out of {total} bytes is larger than the camera accepts")
        out = bytearray()
        while True:
            kind, body = conn.recv_packet(MAX_DATA_PACKET_BYTES)
            if kind not in (DATA, END_DATA):
                raise ProtocolError(f"expected Data/EndData, got packet type {kind}")
            out += body[4:]
            if len(out) > total:
                raise ProtocolError("initiator sent more data than it announced")
            if kind == END_DATA:
                return bytes(out)

    def _respond(self, conn: _Conn, cmd, data_out) -> bool:
        f = self.faults
        if f.stall_op is not None and cmd.code == f.stall_op:
            f.stall_op = None
            time.sleep(30.0 if not self._stop.is_set() else 0)  # the initiator times out and hangs up
            return False
        if f.busy_count:
            self.camera.busy_responses += f.busy_count
            f.busy_count = 0
        self.camera.short_partial_bytes = f.short_read_bytes
        reply = self.camera.handle(cmd, data_out)
        cut_after = None
        if f.disconnect_after_in_bytes is not None and cmd.code in DOWNLOAD_OPS:
            cut_after, f.disconnect_after_in_bytes = f.disconnect_after_in_bytes, None
        if reply.data is not None:
            data = memoryview(reply.data).cast("B")
            conn.send(pack_start_data(cmd.transaction_id, len(data)))
            if len(data) == 0:
                conn.send(pack_data_packet(cmd.transaction_id, b"", end=True))
            for start in range(0, len(data), DATA_CHUNK_BYTES):
                piece = data[start : start + DATA_CHUNK_BYTES]
                if cut_after is not None and start + len(piece) > cut_after:
                    conn.send(
                        pack_data_packet(cmd.transaction_id, piece[: max(0, cut_after - start)], end=False)[
                            : max(0, 12 + cut_after - start)
                        ]
                    )
                    return False
                conn.send(pack_data_packet(cmd.transaction_id, piece, end=start + DATA_CHUNK_BYTES >= len(data)))
        resp = pack_operation_response(reply.response.code, reply.response.transaction_id, reply.response.params)
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
