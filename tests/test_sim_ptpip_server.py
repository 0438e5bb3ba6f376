"""The simulated camera's PTP/IP server against many and hostile initiators (issue 13, item 9): bounded memory
per connection, a cap on connections, and one initiator's disconnect never ending another's session."""

from __future__ import annotations

import io
import socket
import struct
import time
import tracemalloc

import pytest

from mca.devices.ptp.camera import Camera
from mca.devices.ptp.transport import TransportError
from mca.devices.ptp.transport_ptpip import PtpIpTransport
from mca.devices.sim.eos70d.ptpip_server import PtpIpServer
from mca.devices.sim.eos70d.responder import deterministic_frame


def test_a_header_claiming_a_huge_packet_allocates_nothing_until_the_bytes_arrive() -> None:
    """After the handshake, a command-connection header claiming 60 MiB: the old server allocated the claim up
    front (64 MiB allowed per connection); now control packets are bounded and read in pieces."""
    with PtpIpServer(port=0) as server:
        transport = PtpIpTransport("127.0.0.1", server.port, timeout_s=2)
        tracemalloc.start()
        try:
            transport.cmd.sock.sendall(struct.pack("<II", 8 + 60 * 1024 * 1024, 6) + b"x" * 1000)
            time.sleep(0.5)
            _current, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
            transport.close()
    assert peak < 8 * 1024 * 1024


def test_the_server_caps_its_connections() -> None:
    with PtpIpServer(port=0) as server:
        clients = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(30)]
        time.sleep(0.5)
        held = len(server._sockets)
        for s in clients:
            s.close()
    assert held <= 8  # MAX_CONNECTIONS; the old server kept all 30 (and a thread and buffer for each)


def test_a_second_initiator_cannot_end_the_first_ones_session() -> None:
    with PtpIpServer(port=0) as server:
        first = Camera.open(PtpIpTransport("127.0.0.1", server.port, timeout_s=2))
        try:
            with pytest.raises(TransportError, match="busy"):
                PtpIpTransport("127.0.0.1", server.port, timeout_s=2)
            obj = first.capture(timeout_s=5)  # the first session goes on
            buf = io.BytesIO()
            first.download(obj.handle, obj.size_bytes, buf)
        finally:
            first.close()
        second = Camera.open(PtpIpTransport("127.0.0.1", server.port, timeout_s=2))  # free again once it left
        second.close()
    assert buf.getvalue() == deterministic_frame(1)


def test_a_host_that_closed_can_connect_again_at_once_while_the_camera_is_slow_to_let_go(monkeypatch) -> None:
    """The camera ends the session only after it sees the command connection close. `close()` waits for the
    camera's side to close too, so reconnecting right away finds the camera free, not busy (this raced in CI)."""
    with PtpIpServer(port=0) as server:
        end_session = server._end_session

        def slow_end_session(conn_id: int) -> None:
            time.sleep(0.3)  # a body still tidying up the old session
            end_session(conn_id)

        monkeypatch.setattr(server, "_end_session", slow_end_session)
        for _ in range(3):
            Camera.open(PtpIpTransport("127.0.0.1", server.port, timeout_s=2)).close()
    assert server.refused == 0
