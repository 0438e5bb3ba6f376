"""The PTP/IP transport against packets written by hand from the PTP/IP standard (CIPA DC-005) and a scripted
camera written here: a socket server that answers with those bytes, so the host side is checked against the
standard's layout rather than against our own simulated camera.

Packet: u32 length (header included), u32 type, body. Types: 1 InitCommandRequest, 2 InitCommandAck,
3 InitEventRequest, 4 InitEventAck, 5 InitFail, 6 OperationRequest, 7 OperationResponse, 8 Event,
9 StartData, 10 Data, 11 Cancel, 12 EndData, 13 Ping, 14 Pong.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from mca.devices.ptp import ptpip_packets as pk
from mca.devices.ptp import transport_ptpip as ip
from mca.devices.ptp.codec import ProtocolError
from mca.devices.ptp.transport import DeviceDisconnected, TransportError, TransportTimeout

GUID = bytes(range(16))
CAMERA_GUID = bytes(range(16, 32))


def packet(kind: int, body: bytes = b"") -> bytes:
    return struct.pack("<II", 8 + len(body), kind) + body


def utf16z(text: str) -> bytes:
    return text.encode("utf-16-le") + b"\x00\x00"


def response(code: int, tid: int, *params: int) -> bytes:
    return packet(7, struct.pack(f"<HI{len(params)}I", code, tid, *params))


def start_data(tid: int, total: int) -> bytes:
    return packet(9, struct.pack("<IQ", tid, total))


def data(tid: int, payload: bytes, end: bool = True) -> bytes:
    return packet(12 if end else 10, struct.pack("<I", tid) + payload)


# -- the pure packet functions ------------------------------------------------------------------------------------


def test_packets_have_the_standard_layout() -> None:
    assert pk.pack_packet(13) == bytes.fromhex("08000000 0d000000")
    req = pk.pack_init_command_request(GUID, "mca")
    assert req == packet(1, GUID + utf16z("mca") + struct.pack("<I", 0x00010000))
    with pytest.raises(ValueError, match="16 bytes"):
        pk.pack_init_command_request(b"short", "mca")
    parsed = pk.parse_init_command_request(req[8:])
    assert (parsed.guid, parsed.name, parsed.version) == (GUID, "mca", 0x00010000)
    assert pk.parse_init_command_request(GUID + utf16z("old")).version == 0  # no version field
    ack = pk.pack_init_command_ack(7, CAMERA_GUID, "Canon EOS 70D")
    assert ack == packet(
        2, struct.pack("<I", 7) + CAMERA_GUID + utf16z("Canon EOS 70D") + struct.pack("<I", 0x00010000)
    )
    assert pk.parse_init_command_ack(ack[8:]) == (7, CAMERA_GUID, "Canon EOS 70D")
    with pytest.raises(ProtocolError):
        pk.parse_init_command_ack(struct.pack("<I", 7) + CAMERA_GUID + b"A\x00")  # name without its NUL
    # OperationRequest: u32 dataphase, u16 code, u32 transaction id, params
    op = pk.pack_operation_request(0x1009, 5, (0x1234,), dataphase=2)
    assert op == packet(6, struct.pack("<IHII", 2, 0x1009, 5, 0x1234))
    phase, command = pk.parse_operation_request(op[8:])
    assert (phase, command.type, command.code, command.transaction_id, command.params) == (2, 1, 0x1009, 5, (0x1234,))
    assert pk.pack_operation_request(0x1001, 1) == packet(6, struct.pack("<IHI", 1, 0x1001, 1))
    with pytest.raises(ProtocolError, match="at most 5"):
        pk.pack_operation_request(0x1001, 1, (0,) * 6)
    pk.pack_operation_request(0x1001, 1, (0,) * 5)
    with pytest.raises(ProtocolError, match="shorter than 10"):
        pk.parse_operation_request(b"\x00" * 9)
    assert pk.parse_operation_request(b"\x00" * 10)[1].params == ()
    assert pk.pack_operation_response(0x2001, 5, (1, 2)) == response(0x2001, 5, 1, 2)
    got = pk.parse_operation_response(response(0x2019, 9, 3)[8:])
    assert (got.type, got.code, got.transaction_id, got.params) == (3, 0x2019, 9, (3,))
    with pytest.raises(ProtocolError, match="shorter than 6"):
        pk.parse_operation_response(b"\x00" * 5)
    assert pk.parse_operation_response(b"\x01\x20" + b"\x00" * 4).params == ()
    ev = pk.pack_event_packet(0x4002, 3, (9,))
    assert ev == packet(8, struct.pack("<HII", 0x4002, 3, 9))
    got = pk.parse_event_packet(ev[8:])
    assert (got.type, got.code, got.params) == (4, 0x4002, (9,))
    with pytest.raises(ProtocolError):
        pk.parse_event_packet(struct.pack("<HI4I", 0x4002, 3, 1, 2, 3, 4))  # four params: too many for an event
    with pytest.raises(ProtocolError, match="shorter than 6"):
        pk.parse_event_packet(b"\x00" * 5)
    assert pk.pack_start_data(4, 2**33) == packet(9, struct.pack("<IQ", 4, 2**33))
    assert pk.parse_start_data(struct.pack("<IQ", 4, 2**33)) == (4, 2**33)
    assert pk.parse_start_data(struct.pack("<II", 4, 99)) == (4, 99)  # a short (u32) length, as some bodies send
    with pytest.raises(ProtocolError, match="shorter than 8"):
        pk.parse_start_data(b"\x00" * 7)
    assert pk.pack_data_packet(4, b"abc", end=True) == packet(12, struct.pack("<I", 4) + b"abc")
    assert pk.pack_data_packet(4, memoryview(b"ab"), end=False) == packet(10, struct.pack("<I", 4) + b"ab")


def test_packet_header_bounds() -> None:
    assert pk.parse_packet_header(packet(7, b"x" * 10)) == (10, 7)
    assert pk.parse_packet_header(struct.pack("<II", 8, 1)) == (0, 1)
    assert pk.parse_packet_header(struct.pack("<II", 8, 14)) == (0, 14)
    with pytest.raises(ProtocolError, match="needs 8 bytes, got 7"):
        pk.parse_packet_header(b"\x00" * 7)
    with pytest.raises(ProtocolError, match="length 7 is shorter"):
        pk.parse_packet_header(struct.pack("<II", 7, 1))
    for kind in (0, 15):
        with pytest.raises(ProtocolError, match=f"unknown PTP/IP packet type {kind}"):
            pk.parse_packet_header(struct.pack("<II", 8, kind))
    assert pk.parse_packet_header(struct.pack("<II", 108, 10), max_bytes=100) == (100, 10)
    with pytest.raises(ProtocolError, match="109 bytes exceeds the 100-byte limit"):
        pk.parse_packet_header(struct.pack("<II", 109, 10), max_bytes=100)


def test_host_guid_is_stable_per_machine_and_falls_back_to_the_hostname(tmp_path: Path) -> None:
    machine = tmp_path / "machine-id"
    machine.write_text("abc\n")
    first = ip.host_guid(machine)
    assert len(first) == 16 and first == ip.host_guid(machine)
    machine.write_text("def\n")
    assert ip.host_guid(machine) != first
    assert len(ip.host_guid(tmp_path / "missing")) == 16


# -- a scripted camera ----------------------------------------------------------------------------------------------


def recv_packet(conn: socket.socket) -> tuple[int, bytes]:
    head = b""
    while len(head) < 8:
        chunk = conn.recv(8 - len(head))
        if not chunk:
            raise ConnectionError("closed")
        head += chunk
    length, kind = struct.unpack("<II", head)
    body = b""
    while len(body) < length - 8:
        chunk = conn.recv(length - 8 - len(body))
        if not chunk:
            raise ConnectionError("closed")
        body += chunk
    return kind, body


class ScriptedCamera:
    """Accepts the two PTP/IP connections, then runs `script(cmd, evt, camera)` in a thread."""

    def __init__(self, script: Callable[[socket.socket, socket.socket, ScriptedCamera], None], init_fail: int = 0):
        self.server = socket.socket()
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(2)
        self.port = self.server.getsockname()[1]
        self.script = script
        self.init_fail = init_fail
        self.received: list[tuple[int, bytes]] = []
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            cmd, _ = self.server.accept()
            kind, body = recv_packet(cmd)
            self.received.append((kind, body))
            if self.init_fail:
                cmd.sendall(packet(5, struct.pack("<I", self.init_fail)))
                cmd.close()
                return
            cmd.sendall(
                packet(2, struct.pack("<I", 42) + CAMERA_GUID + utf16z("Canon EOS 70D") + struct.pack("<I", 0x10000))
            )
            evt, _ = self.server.accept()
            kind, body = recv_packet(evt)
            self.received.append((kind, body))
            evt.sendall(packet(4))
            self.script(cmd, evt, self)
        except BaseException as exc:  # reported by the test
            self.error = exc
        finally:
            self.done.set()

    def close(self) -> None:
        self.server.close()


def connect(camera: ScriptedCamera, **kwargs) -> ip.PtpIpTransport:
    return ip.PtpIpTransport("127.0.0.1", camera.port, guid=GUID, name="mca-test", **kwargs)


def idle(cmd: socket.socket, evt: socket.socket, camera: ScriptedCamera) -> None:
    camera.done.wait(0)  # nothing to do


def test_the_host_introduces_itself_and_opens_the_event_connection() -> None:
    hold = threading.Event()
    camera = ScriptedCamera(lambda c, e, cam: hold.wait(5))
    transport = connect(camera)
    try:
        assert (transport.connection_id, transport.camera_guid, transport.camera_name) == (
            42,
            CAMERA_GUID,
            "Canon EOS 70D",
        )
        (k1, b1), (k2, b2) = camera.received
        assert k1 == 1 and b1 == GUID + utf16z("mca-test") + struct.pack("<I", 0x00010000)
        assert (k2, b2) == (3, struct.pack("<I", 42))  # InitEventRequest names the connection number
        assert transport.can_resume
    finally:
        hold.set()
        transport.close()
        camera.close()
    assert not transport.can_resume
    with pytest.raises(DeviceDisconnected, match="closed"):
        transport.transaction(0x1001, 1)
    transport.close()  # twice is fine


@pytest.mark.parametrize(("reason", "text"), [(1, "5, rejected"), (2, "5, busy"), (3, "5, unspecified"), (9, r"5\)")])
def test_a_refusing_camera_is_reported_with_its_reason(reason: int, text: str) -> None:
    camera = ScriptedCamera(idle, init_fail=reason)
    try:
        with pytest.raises(TransportError, match=f"refused the connection \\(packet type {text}.*accept this computer"):
            connect(camera)
    finally:
        camera.close()


def test_nobody_listening_is_a_clear_error() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(TransportError, match=f"cannot reach ptpip:127.0.0.1:{port}.*serve-sim"):
        ip.PtpIpTransport("127.0.0.1", port, guid=GUID)


def run(script, *, timeout_s: float = 5.0, **kwargs):
    """Connect to a scripted camera, run `kwargs['then'](transport)`, return (its result, camera)."""
    then = kwargs.pop("then")
    camera = ScriptedCamera(script)
    transport = connect(camera, timeout_s=timeout_s)
    try:
        return then(transport), camera, transport
    finally:
        transport.close()
        camera.close()
        camera.done.wait(5)


def test_a_data_in_transaction() -> None:
    def script(cmd, evt, cam):
        cam.received.append(recv_packet(cmd))
        cmd.sendall(start_data(5, 10) + data(5, b"01234", end=False) + data(5, b"56789") + response(0x2001, 5, 7))

    result, camera, _ = run(script, then=lambda t: t.transaction(0x1009, 5, (0x99,)))
    assert camera.received[-1] == (6, struct.pack("<IHII", 1, 0x1009, 5, 0x99))  # dataphase 1: none or in
    assert (result.code, result.params, result.data) == (0x2001, (7,), b"0123456789")


def test_a_data_in_transaction_into_a_sink() -> None:
    pieces: list[bytes] = []
    payload = bytes(range(256)) * 4000  # more than one receive piece

    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(start_data(6, len(payload)) + data(6, payload) + response(0x2001, 6))

    result, _, _ = run(script, then=lambda t: t.transaction(0x1009, 6, sink=lambda v: pieces.append(bytes(v))))
    assert b"".join(pieces) == payload and result.data is None


def test_a_data_out_transaction_sends_start_data_then_end_data() -> None:
    def script(cmd, evt, cam):
        for _ in range(3):
            cam.received.append(recv_packet(cmd))
        cmd.sendall(response(0x2001, 8))

    result, camera, _ = run(script, then=lambda t: t.transaction(0x9110, 8, data_out=b"\x0c\x00\x00\x00"))
    assert camera.received[-3:] == [
        (6, struct.pack("<IHI", 2, 0x9110, 8)),  # dataphase 2: out
        (9, struct.pack("<IQ", 8, 4)),
        (12, struct.pack("<I", 8) + b"\x0c\x00\x00\x00"),
    ]
    assert result.code == 0x2001 and result.data is None


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        (data(5, b"abc"), "data without StartData"),
        (start_data(5, 2) + data(5, b"abc"), "sent 3 data bytes after announcing 2"),
        (start_data(5, 4) + data(5, b"abc") + response(0x2001, 5), "sent 3 of the 4 data bytes"),
        (start_data(5, 100), "announced 100 data bytes, more than the 10 expected"),
        (packet(12, b"\x05\x00"), "data packet without its transaction id"),
        (response(0x2001, 9), "answered transaction 9, expected 5"),
        (packet(11, struct.pack("<I", 5)), "packet type 11 during a transaction"),
    ],
)
def test_a_camera_breaking_the_protocol_is_reported(reply: bytes, message: str) -> None:
    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(reply)

    def then(t):
        with pytest.raises(ProtocolError, match=message):
            t.transaction(0x1009, 5, max_data_bytes=10)

    run(script, then=then)


def test_pings_are_answered_and_late_replies_of_given_up_transactions_discarded() -> None:
    stale: list[tuple[int, int, bytes]] = []

    def script(cmd, evt, cam):
        recv_packet(cmd)  # transaction 4, whose answer comes too late
        recv_packet(cmd)  # transaction 5
        cmd.sendall(packet(13))  # ping on the command connection
        cam.received.append(recv_packet(cmd))  # the pong
        cmd.sendall(start_data(4, 3) + data(4, b"old") + response(0x2001, 4) + response(0x2001, 5, 1))

    def then(t):
        t.on_stale_data = lambda code, tid, payload: stale.append((code, tid, payload))
        t.cmd.send(pk.pack_operation_request(0x9116, 4))  # as if transaction 4 had timed out
        t._codes[4] = 0x9116
        return t.transaction(0x1001, 5)

    result, camera, transport = run(script, then=then)
    assert camera.received[-1] == (14, b"")
    assert (result.code, result.params) == (0x2001, (1,))
    assert stale == [(0x9116, 4, b"old")]
    assert transport.counters.stale_replies_discarded == 1


def test_a_reply_from_the_future_or_too_many_stale_ones_are_errors() -> None:
    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(b"".join(response(0x2001, tid) for tid in (1, 2, 3, 4)) * 10)

    def then(t):
        with pytest.raises(ProtocolError, match="answered transaction"):
            t.transaction(0x1001, 5)
        return t.counters.stale_replies_discarded

    discarded, _, transport = run(script, then=then)
    assert discarded == transport.policy.stale_replies_max


def test_a_silent_camera_times_out_and_a_cut_packet_closes_the_link() -> None:
    release = threading.Event()

    def script(cmd, evt, cam):
        recv_packet(cmd)  # transaction 1: no answer at all
        recv_packet(cmd)
        # transaction 2: a data packet whose header claims 4 + 10 bytes, of which 4 + 4 arrive
        cmd.sendall(start_data(2, 10) + struct.pack("<III", 8 + 14, 12, 2) + b"0123")
        release.wait(5)

    def then(t):
        with pytest.raises(TransportTimeout, match="did not answer in time"):
            t.transaction(0x1001, 1, timeout_s=0.3)
        t.recover(1)
        assert t.can_resume  # nothing was cut: the stream is in step
        with pytest.raises(TransportTimeout):
            t.transaction(0x1009, 2, timeout_s=0.5)
        t.recover(2)
        assert not t.can_resume  # a packet cut mid-way: closed, the session reconnects
        release.set()

    run(script, then=then)


def test_a_camera_closing_the_connection_is_a_disconnect() -> None:
    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(struct.pack("<II", 20, 7) + b"\x01\x20")  # a response header, then gone mid-packet
        cmd.close()

    def then(t):
        with pytest.raises(DeviceDisconnected, match="closed the connection"):
            t.transaction(0x1001, 1)

    run(script, then=then)


def test_events_are_queued_and_pings_on_the_event_connection_answered() -> None:
    got_pong = threading.Event()

    def script(cmd, evt, cam):
        evt.sendall(packet(13))
        if recv_packet(evt) == (14, b""):
            got_pong.set()
        evt.sendall(packet(8, struct.pack("<HII", 0x4002, 0, 0x1234)))
        evt.sendall(packet(8, struct.pack("<HI4I", 0x4002, 0, 1, 2, 3, 4)))  # malformed: skipped
        time.sleep(1.2)  # a quiet event connection (longer than the reader's 0.5 s timeout) is not a lost one
        evt.sendall(packet(8, struct.pack("<HI", 0x400D, 0)))
        cam.done.wait(3)

    def then(t):
        first = t.read_event(3.0)
        second = t.read_event(3.0)
        none = t.read_event(0.2)
        return first, second, none

    (first, second, none), _, _ = run(script, then=then)
    assert got_pong.is_set()
    assert (first.code, first.params) == (0x4002, (0x1234,))
    assert (second.code, second.params) == (0x400D, ())
    assert none is None


def test_old_events_are_dropped_beyond_the_queue() -> None:
    def script(cmd, evt, cam):
        evt.sendall(b"".join(packet(8, struct.pack("<HII", 0x4002, 0, i)) for i in range(ip.MAX_QUEUED_EVENTS + 10)))
        cam.done.wait(3)

    def then(t):
        deadline = time.monotonic() + 5
        while len(t._events) < ip.MAX_QUEUED_EVENTS and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.2)
        return t.read_event(1.0)

    first, _, _ = run(script, then=then)
    assert first.params == (10,)


def test_the_standard_port_and_the_default_data_limit() -> None:
    assert pk.DEFAULT_PORT == 15740  # CIPA DC-005
    assert (pk.INIT_COMMAND_REQUEST, pk.INIT_COMMAND_ACK, pk.INIT_EVENT_REQUEST, pk.INIT_EVENT_ACK, pk.INIT_FAIL) == (
        1,
        2,
        3,
        4,
        5,
    )
    assert (pk.OPERATION_REQUEST, pk.START_DATA, pk.END_DATA, pk.PING, pk.PONG) == (6, 9, 12, 13, 14)
    request = pk.InitCommandRequest(GUID, "x", 1)
    from dataclasses import FrozenInstanceError

    with pytest.raises(FrozenInstanceError):
        request.name = "y"  # type: ignore[misc]

    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(start_data(5, 64 * 1024 * 1024 + 1))

    def then(t):
        with pytest.raises(ProtocolError, match="announced 67108865 data bytes, more than the 67108864 expected"):
            t.transaction(0x1009, 5)

    run(script, then=then)


def test_a_control_packet_of_64_kib_is_accepted_and_a_larger_one_refused() -> None:
    body = b"\x01\x20" + struct.pack("<I", 5) + bytes(64 * 1024 - 6)

    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(packet(7, body[:6]))  # an ordinary response first

    run(script, then=lambda t: t.transaction(0x1001, 5))
    a, b = socket.socketpair()
    try:
        conn = ip._Conn(a, "test")
        b.sendall(packet(7, body))
        assert conn.recv_packet() == (7, body)
        b.sendall(packet(7, body + b"x"))
        with pytest.raises(ProtocolError, match="exceeds the 65536-byte limit"):
            conn.recv_packet()
    finally:
        a.close()
        b.close()


def test_a_late_data_phase_is_handed_on_whole_up_to_4_mib_with_its_operation_code() -> None:
    stale: list[tuple[int, int, int]] = []
    big = bytes(range(256)) * (14 * 1024)  # 3.5 MiB

    def script(cmd, evt, cam):
        recv_packet(cmd)
        cmd.sendall(start_data(3, 5) + data(3, b"small") + response(0x2001, 3))  # an operation we do not know
        cmd.sendall(start_data(4, len(big)) + data(4, big, end=False) + data(4, b"") + response(0x2001, 4))
        cmd.sendall(response(0x2001, 5))

    def then(t):
        t.on_stale_data = lambda code, tid, payload: stale.append((code, tid, len(payload)))
        t._codes[4] = 0x1009
        return t.transaction(0x1001, 5)

    result, _, _ = run(script, then=then)
    assert result.code == 0x2001
    assert stale == [(0, 3, 5), (0x1009, 4, len(big))]
