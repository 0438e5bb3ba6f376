"""The sans-I/O PTP transaction engine: real EOS traces through both sides in any chunking, initiator <-> responder
round trips over both framings, and hostile bytes giving the documented `ProtocolError`.

The trace reference is independent of our code: `derived/*.transactions.txt` in the shared EOS trace folder lists
every container of each gphoto2 log (direction, type, code, transaction id, length), made by another tool.
"""

from __future__ import annotations

import re
import struct
import tracemalloc
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_ptp_replay import SESSIONS as REPLAY_SESSIONS
from test_ptp_replay import TRACES
from test_ptp_replay import pytestmark as needs_traces  # the trace folder, or a skip (a failure on CI)

from mca.devices.ptp.codec import ProtocolError, pack_command, pack_data, pack_event, pack_response
from mca.devices.ptp.engine import (
    MAX_LATE_KEEP_BYTES,
    NEED_DATA,
    CommandReceived,
    DataFinished,
    DataReceived,
    DataStarted,
    EventReader,
    EventReceived,
    Initiator,
    LateDataReceived,
    LateReplyDiscarded,
    PingReceived,
    Responder,
    ResponseReceived,
)
from mca.devices.ptp.framing import Framing, PtpIpFraming, UsbFraming
from mca.devices.ptp.ptpip_packets import (
    PING,
    pack_data_packet,
    pack_event_packet,
    pack_operation_response,
    pack_packet,
    pack_start_data,
)
from mca.devices.ptp.replay import IN, OUT, HexBlock, parse_hexdumps

#: The four sessions with complete camera->host hexdumps: the independent listing's name -> the log it was made from.
SESSIONS = {Path(log).name.removesuffix(".log").removesuffix(".unwrapped"): log for log in REPLAY_SESSIONS.values()}
#: Operations with a data-out phase (SetDevicePropValue, EOS SetDevicePropValueEx): USB does not say so on the wire.
DATA_OUT_OPS = {0x1016, 0x9110}
_ROW = re.compile(r"^\s*\d+ ([WR]) (CMD|DATA|RESP)\s+0x([0-9a-fA-F]{4}).*?tid=(\d+) len=(\d+) got=(\d+)")
Row = tuple[str, str, int, int, int]


def reference_rows(name: str) -> list[Row]:
    """(direction, kind, code, transaction id, container length) of every container, from the independent listing."""
    rows = []
    for line in (TRACES / "derived" / f"{name}.transactions.txt").read_text().splitlines():
        m = _ROW.match(line)
        if m:
            rows.append((m.group(1), m.group(2), int(m.group(3), 16), int(m.group(4)), int(m.group(5))))
    return rows


def trace_blocks(name: str) -> list[HexBlock]:
    """The log's hexdumps (cut to the byte count the log announces), in order, with their direction."""
    return parse_hexdumps((TRACES / SESSIONS[name]).read_text(encoding="utf-8", errors="replace"))


def chunks(data: bytes, sizes: list[int]) -> list[bytes]:
    """`data` cut into pieces of the given sizes, cycled; [] sizes means one byte at a time."""
    out, pos, k = [], 0, 0
    while pos < len(data):
        n = sizes[k % len(sizes)] if sizes else 1
        out.append(data[pos : pos + n])
        pos, k = pos + n, k + 1
    return out


def replay_both_sides(name: str, sizes: list[int]) -> tuple[list[Row], list[bytes], list[bytes]]:
    """The host's writes through a `Responder`, the camera's reads through an `Initiator`, chunked by `sizes`.

    Returns the containers both engines reported, and, per camera reply, the bytes the camera sent and the bytes
    our responder packs for the same reply (they must be identical).
    """
    host = Initiator(UsbFraming(), name="camera")
    camera = Responder(UsbFraming(), name="host", expects_data_out=DATA_OUT_OPS.__contains__)
    mirror = Responder(UsbFraming(), name="host")  # packs the same replies from the camera's side
    rows: list[Row] = []
    sent: list[bytes] = []
    repacked: list[bytes] = []
    command: CommandReceived | None = None
    data_out = bytearray()
    data_in = bytearray()
    reply = bytearray()
    for block in trace_blocks(name):
        if block.direction == OUT:
            for piece in chunks(block.data, sizes):
                camera.receive_data(piece)
                while (event := camera.next_event()) is not NEED_DATA:
                    if isinstance(event, CommandReceived):
                        command, data_out = event, bytearray()
                        rows.append(("W", "CMD", event.code, event.transaction_id, 12 + 4 * len(event.params)))
                        if not event.data_out:
                            host.send_command(event.code, event.transaction_id, event.params)
                    elif isinstance(event, DataReceived):
                        data_out += event.data
                    elif isinstance(event, DataFinished):
                        assert command is not None
                        rows.append(("W", "DATA", command.code, command.transaction_id, 12 + len(data_out)))
                        writes = host.send_command(
                            command.code, command.transaction_id, command.params, data_out=bytes(data_out)
                        )
                        assert b"".join(map(bytes, writes)) == pack_command(
                            command.code, command.transaction_id, command.params
                        ) + pack_data(command.code, command.transaction_id, bytes(data_out))
            camera.drop_reply()  # the log's replies are checked on the host's side
        elif block.direction == IN:
            reply += block.data
            for piece in chunks(block.data, sizes):
                host.receive_data(piece)
                while (event := host.next_event()) is not NEED_DATA:
                    if isinstance(event, DataStarted):
                        data_in = bytearray()
                        rows.append(("R", "DATA", event.code or 0, event.transaction_id, 12 + event.total_bytes))
                    elif isinstance(event, DataReceived):
                        data_in += event.data
                    elif isinstance(event, ResponseReceived):
                        rows.append(("R", "RESP", event.code, event.transaction_id, 12 + 4 * len(event.params)))
                        assert command is not None and event.transaction_id == command.transaction_id
                        mirror.receive_data(pack_command(command.code, command.transaction_id, command.params))
                        assert mirror.next_event() == CommandReceived(
                            command.code, command.transaction_id, command.params, False
                        )
                        packed = mirror.send_data(bytes(data_in)) if rows[-2][:2] == ("R", "DATA") else []
                        packed.append(mirror.send_response(event.code, event.params))
                        sent.append(bytes(reply))
                        repacked.append(b"".join(map(bytes, packed)))
                        reply, data_in = bytearray(), bytearray()
                    elif not isinstance(event, DataFinished):
                        raise AssertionError(f"unexpected {event} in a real camera's replies")
    return rows, sent, repacked


@needs_traces
@pytest.mark.parametrize("name", sorted(SESSIONS))
def test_real_eos_traces_byte_by_byte_give_every_container_of_the_independent_listing(name: str) -> None:
    rows, sent, repacked = replay_both_sides(name, [])
    reference = reference_rows(name)
    assert len(reference) > 20
    assert rows == reference
    assert sent == repacked  # our responder packs each reply exactly as the real camera sent it


@needs_traces
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    name=st.sampled_from(sorted(SESSIONS)),
    sizes=st.lists(st.integers(1, 5000), min_size=1, max_size=12),
)
def test_real_eos_traces_in_random_chunkings_give_the_same_transactions(name: str, sizes: list[int]) -> None:
    rows, sent, repacked = replay_both_sides(name, sizes)
    assert rows == reference_rows(name)
    assert sent == repacked


# -- round trips -----------------------------------------------------------------------------------------------------
FRAMINGS: dict[str, type[Framing]] = {"usb": UsbFraming, "ptpip": PtpIpFraming}
u32 = st.integers(0, 0xFFFFFFFF)
transactions = st.lists(
    st.tuples(
        st.integers(0x1000, 0x9FFF),  # operation code
        st.lists(u32, max_size=5).map(tuple),  # command parameters
        st.one_of(st.none(), st.binary(max_size=700)),  # data out
        st.one_of(st.none(), st.binary(max_size=3000)),  # data in
        st.integers(0x2000, 0xA1FF),  # response code
        st.lists(u32, max_size=5).map(tuple),  # response parameters
    ),
    min_size=1,
    max_size=6,
)


def drain(engine: Initiator | Responder) -> list:
    out = []
    while (event := engine.next_event()) is not NEED_DATA:
        out.append(event)
    return out


def merged(events: list) -> list:
    """Events with consecutive data pieces joined (their chunking depends on the reads)."""
    out: list = []
    for e in events:
        if isinstance(e, DataReceived) and out and isinstance(out[-1], DataReceived):
            out[-1] = DataReceived(e.transaction_id, out[-1].data + e.data)
        else:
            out.append(e)
    return out


@settings(max_examples=150, deadline=None)
@given(
    framing=st.sampled_from(sorted(FRAMINGS)),
    script=transactions,
    sizes=st.lists(st.integers(1, 900), min_size=1, max_size=8),
    piece_bytes=st.integers(1, 4000),
    first_tid=st.integers(0, 0xFFFFFFFF),
)
def test_initiator_and_responder_round_trip_any_transaction_in_any_chunking(
    framing: str, script: list, sizes: list[int], piece_bytes: int, first_tid: int
) -> None:
    host = Initiator(FRAMINGS[framing]())
    this = {"data_out": False}  # USB does not say whether data follows a command: the camera knows its operations
    camera = Responder(
        FRAMINGS[framing](), expects_data_out=(lambda _code: this["data_out"]) if framing == "usb" else None
    )
    for k, (code, params, data_out, data_in, resp_code, resp_params) in enumerate(script):
        tid = (first_tid + k) & 0xFFFFFFFF
        this["data_out"] = data_out is not None
        writes = host.send_command(code, tid, params, data_out=data_out)
        got = []
        for piece in chunks(b"".join(map(bytes, writes)), sizes):
            camera.receive_data(piece)
            got += drain(camera)
        expected: list = [CommandReceived(code, tid, params, data_out is not None)]
        if data_out is not None:
            expected.append(DataStarted(code if framing == "usb" else None, tid, len(data_out)))
            expected += [DataReceived(tid, data_out)] if data_out else []
            expected.append(DataFinished(tid, len(data_out)))
        assert merged(got) == expected
        reply: list = []
        if data_in is not None:  # a data phase in several PTP/IP packets (USB: one container whatever the pieces)
            reply.append(camera.send_data_start(len(data_in)))
            starts = range(0, len(data_in), piece_bytes)
            for start in starts:
                reply.append(camera.send_data_piece(data_in[start : start + piece_bytes], start == starts[-1]))
            if not data_in:
                reply.append(camera.send_data_piece(b"", True))
        reply.append(camera.send_response(resp_code, resp_params))
        got = []
        for piece in chunks(b"".join(map(bytes, reply)), sizes):
            host.receive_data(piece)
            got += drain(host)
        expected = []
        if data_in is not None:
            expected.append(DataStarted(code if framing == "usb" else None, tid, len(data_in)))
            expected += [DataReceived(tid, data_in)] if data_in else []
            expected.append(DataFinished(tid, len(data_in)))
        expected.append(ResponseReceived(resp_code, tid, resp_params))
        assert merged(got) == expected
        assert host.state == camera.state == "idle"


@pytest.mark.parametrize("framing", sorted(FRAMINGS))
def test_the_usb_bytes_are_the_codec_containers_and_ptpip_sends_dataphase_start_and_end(framing: str) -> None:
    host = Initiator(FRAMINGS[framing]())
    writes = [bytes(w) for w in host.send_command(0x9110, 7, (1,), data_out=b"\x0c\x00\x00\x00")]
    if framing == "usb":  # the command, then one transfer with the whole data container
        assert writes == [pack_command(0x9110, 7, (1,)), pack_data(0x9110, 7, b"\x0c\x00\x00\x00")]
    else:  # OperationRequest with dataphase 2, StartData, EndData
        assert writes == [
            pack_packet(6, struct.pack("<IHII", 2, 0x9110, 7, 1)),
            pack_start_data(7, 4),
            pack_data_packet(7, b"\x0c\x00\x00\x00", end=True),
        ]


# -- late replies ----------------------------------------------------------------------------------------------------
def test_a_late_reply_is_discarded_and_its_data_handed_on_whole_with_its_code() -> None:
    host = Initiator(UsbFraming())
    host.send_command(0x9116, 4)
    host.abandon()  # transaction 4 timed out
    host.send_command(0x1001, 5)
    late = pack_data(0x9116, 4, b"old events") + pack_response(0x2001, 4)
    for k in range(len(late)):  # byte by byte, the late reply is read past, then the answer comes
        host.receive_data(late[k : k + 1])
    host.receive_data(pack_response(0x2001, 5, (1,)))
    assert drain(host) == [
        LateReplyDiscarded(4),
        LateDataReceived(0x9116, 4, b"old events"),
        ResponseReceived(0x2001, 5, (1,)),
    ]


def test_a_late_data_phase_beyond_the_keep_limit_is_drained_not_kept() -> None:
    host = Initiator(PtpIpFraming())
    host.send_command(0x1001, 9)
    host.sent_codes[8] = 0x9116
    big = MAX_LATE_KEEP_BYTES + 1
    host.receive_data(
        pack_start_data(8, big) + pack_data_packet(8, bytes(big), end=True) + pack_operation_response(0x2001, 8)
    )
    host.receive_data(pack_operation_response(0x2001, 9))
    assert drain(host) == [LateReplyDiscarded(8), ResponseReceived(0x2001, 9)]


def test_late_replies_beyond_the_policy_limit_are_an_error() -> None:
    host = Initiator(UsbFraming(), stale_replies_max=3)
    host.send_command(0x1001, 10)
    host.receive_data(b"".join(pack_response(0x2001, tid) for tid in (6, 7, 8, 9)))
    assert [host.next_event() for _ in range(3)] == [
        LateReplyDiscarded(6),
        LateReplyDiscarded(7),
        LateReplyDiscarded(8),
    ]
    with pytest.raises(ProtocolError, match="answered transaction 9, expected 10"):
        host.next_event()


def test_while_a_session_opens_any_other_transaction_id_is_late() -> None:
    host = Initiator(UsbFraming())
    host.send_command(0x1002, 0, (1,))  # OpenSession: transaction id 0 after a previous session's 41
    host.receive_data(pack_response(0x2001, 41) + pack_response(0x2001, 0))
    assert drain(host) == [LateReplyDiscarded(41), ResponseReceived(0x2001, 0)]


# -- hostile bytes ---------------------------------------------------------------------------------------------------
def opened(framing: Framing, code: int = 0x1009, tid: int = 5, max_data_bytes: int = 10) -> Initiator:
    host = Initiator(framing, name="cam")
    host.send_command(code, tid, max_data_bytes=max_data_bytes)
    return host


HOSTILE_TO_THE_HOST = [
    # oversized lengths
    ("usb", pack_data(0x1009, 5, bytes(11)), "cam announced 11 data bytes, more than the 10 expected"),
    ("usb", struct.pack("<IHHI", 40, 3, 0x2001, 5), "response container of 40 bytes is not a header plus at most 5"),
    ("ptpip", pack_start_data(5, 100), "cam announced 100 data bytes, more than the 10 expected"),
    ("ptpip", pack_packet(7, bytes(64 * 1024 + 1)), "PTP/IP packet of 65545 bytes exceeds the 65536-byte limit"),
    # lengths shorter than a header
    ("usb", struct.pack("<IHHI", 8, 3, 0x2001, 5), "container length 8 is shorter than its header"),
    ("ptpip", struct.pack("<II", 4, 7), "PTP/IP packet length 4 is shorter than its header"),
    ("ptpip", pack_packet(12, b"\x05\x00"), "PTP/IP data packet without its transaction id"),
    # phases out of order
    ("usb", pack_event(0x4002, 5, (1,)), "cam sent a EVENT container during a transaction"),
    ("usb", pack_command(0x1001, 5), "cam sent a COMMAND container during a transaction"),
    ("usb", pack_data(0x1009, 5, b"ab") + pack_data(0x1009, 5, b"cd"), "cam sent two data phases for one transaction"),
    ("usb", pack_data(0x1001, 5, b"ab"), "cam data phase code 0x1001 for operation 0x1009"),
    ("ptpip", pack_data_packet(5, b"abc", end=True), "cam sent data without StartData"),
    ("ptpip", pack_packet(11, struct.pack("<I", 5)), "cam sent PTP/IP packet type 11 during a transaction"),
    ("ptpip", pack_event_packet(0x4002, 5), "cam sent PTP/IP packet type 8 during a transaction"),
    # transaction ids
    ("usb", pack_response(0x2001, 9), "cam answered transaction 9, expected 5"),
    ("usb", pack_data(0x1009, 6, b"ab"), "cam answered transaction 6, expected 5"),
    ("ptpip", pack_start_data(5, 4) + pack_data_packet(4, b"abcd", end=True), "cam sent data of transaction 4 in"),
    # bytes beyond (or short of) the announced total
    (
        "ptpip",
        pack_start_data(5, 2) + pack_data_packet(5, b"abc", end=True),
        "cam sent 3 data bytes after announcing 2",
    ),
    (
        "ptpip",
        pack_start_data(5, 4) + pack_data_packet(5, b"abc", end=True) + pack_operation_response(0x2001, 5),
        "cam sent 3 of the 4 data bytes it announced",
    ),
    ("usb", struct.pack("<IHHI", 12, 9, 0x2001, 5), "unknown container type 9"),
]


@pytest.mark.parametrize(("framing", "reply", "message"), HOSTILE_TO_THE_HOST)
@pytest.mark.parametrize("one_byte_at_a_time", [False, True])
def test_hostile_replies_are_a_protocol_error_naming_the_field(
    framing: str, reply: bytes, message: str, one_byte_at_a_time: bool
) -> None:
    host = opened(FRAMINGS[framing]())
    with pytest.raises(ProtocolError, match=re.escape(message)):
        for piece in chunks(reply, [] if one_byte_at_a_time else [len(reply)]):
            host.receive_data(piece)
            drain(host)
    with pytest.raises(ProtocolError, match="out of step"):  # it stays in error until recovered
        host.next_event()
    host.reset()
    host.send_command(0x1001, 6)
    host.receive_data(pack_response(0x2001, 6) if framing == "usb" else pack_operation_response(0x2001, 6))
    assert drain(host) == [ResponseReceived(0x2001, 6)]


def test_a_claim_of_four_gibibytes_allocates_nothing_before_its_bytes_arrive() -> None:
    host = opened(UsbFraming(), max_data_bytes=2**32)
    tracemalloc.start()
    try:
        host.receive_data(struct.pack("<IHHI", 0xFFFFFFFF, 2, 0x1009, 5) + bytes(1000))
        events = drain(host)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert events == [DataStarted(0x1009, 5, 0xFFFFFFFF - 12), DataReceived(5, bytes(1000))]
    assert peak < 256 * 1024
    assert not host.in_step  # a timeout now would leave the stream cut mid-container


def test_bytes_while_no_transaction_is_open_wait_for_it_up_to_a_bound() -> None:
    host = Initiator(UsbFraming(), max_idle_bytes=100)
    host.send_command(0x1001, 1)
    host.receive_data(pack_response(0x2001, 1) + pack_response(0x2001, 2))  # one read brought the next answer too
    assert drain(host) == [ResponseReceived(0x2001, 1)]
    host.send_command(0x1001, 2)
    assert drain(host) == [ResponseReceived(0x2001, 2)]
    with pytest.raises(ProtocolError, match="sent 101 bytes while no transaction was open"):
        host.receive_data(bytes(101))


def test_a_cut_packet_leaves_the_stream_out_of_step_and_a_quiet_one_in_step() -> None:
    host = opened(PtpIpFraming())
    assert host.in_step
    host.receive_data(pack_start_data(5, 10))
    assert drain(host) == [DataStarted(None, 5, 10)]
    assert host.in_step  # nothing of a packet half-read
    host.receive_data(pack_data_packet(5, b"0123456789", end=True)[:16])
    drain(host)
    assert not host.in_step


HOSTILE_TO_THE_CAMERA = [
    ("usb", pack_data(0x1009, 5, b"x"), "expected an operation request, got a DATA container"),
    ("usb", pack_response(0x2001, 5), "expected an operation request, got a RESPONSE container"),
    ("usb", struct.pack("<IHHIH", 14, 1, 0x1001, 5, 0), "command container of 14 bytes is not a header plus"),
    ("usb", pack_command(0x9110, 5) + pack_data(0x9110, 6, b"ab"), "host sent data of transaction 6 in transaction 5"),
    ("usb", pack_command(0x9110, 5) + pack_data(0x9110, 5, bytes(17)), "announced 17 data bytes, more than the 16"),
    ("usb", pack_command(0x9110, 5) + pack_command(0x9110, 6), "host sent a COMMAND container during the data-out"),
    ("ptpip", pack_packet(6, struct.pack("<IHI", 2, 0x9110, 5)) + pack_data_packet(5, b"ab", end=True), "without"),
    ("ptpip", pack_packet(7, struct.pack("<HI", 0x2001, 5)), "expected an operation request, got PTP/IP packet type 7"),
]


@pytest.mark.parametrize(("framing", "sent", "message"), HOSTILE_TO_THE_CAMERA)
def test_hostile_commands_are_a_protocol_error_naming_the_field(framing: str, sent: bytes, message: str) -> None:
    camera = Responder(
        FRAMINGS[framing](), name="host", expects_data_out=DATA_OUT_OPS.__contains__, max_data_out_bytes=16
    )
    camera.receive_data(sent)
    with pytest.raises(ProtocolError, match=re.escape(message)):
        drain(camera)


def test_the_responder_refuses_to_send_what_breaks_the_transaction() -> None:
    camera = Responder(UsbFraming())
    with pytest.raises(ProtocolError, match="no command is waiting"):
        camera.send_response(0x2001)
    camera.receive_data(pack_command(0x1009, 3))
    drain(camera)
    camera.send_data_start(4)
    with pytest.raises(ProtocolError, match="announced 4 bytes, 5 given"):
        camera.send_data_piece(b"12345")
    camera.abandon()
    camera.receive_data(pack_command(0x1009, 4))
    assert drain(camera) == [CommandReceived(0x1009, 4)]
    camera.receive_data(pack_command(0x1001, 5))  # the host's next command waits until this reply is sent
    assert drain(camera) == []
    assert b"".join(camera.send_data(b"abc")) == pack_data(0x1009, 4, b"abc")
    assert camera.send_response(0x2001) == pack_response(0x2001, 4)
    assert drain(camera) == [CommandReceived(0x1001, 5)]


def test_events_and_pings_on_their_own_channel_and_a_malformed_event_skipped() -> None:
    reader = EventReader(PtpIpFraming(), "cam")
    bad = pack_packet(8, struct.pack("<HI4I", 0x4002, 0, 1, 2, 3, 4))  # four parameters: at most three
    reader.receive_data(pack_event_packet(0x4002, 0, (7,)) + pack_packet(PING) + bad + pack_event_packet(0x400D, 0))
    assert reader.next_event() == EventReceived(0x4002, 0, (7,))
    assert reader.next_event() == PingReceived()
    assert reader.pong() == pack_packet(14)
    with pytest.raises(ProtocolError):
        reader.next_event()
    assert not reader.framing.broken
    assert reader.next_event() == EventReceived(0x400D, 0, ())
    assert reader.next_event() is NEED_DATA
    usb = EventReader(UsbFraming(), "cam")
    usb.receive_data(pack_response(0x2001, 1))
    with pytest.raises(ProtocolError, match="cam sent a RESPONSE container where an event was due"):
        usb.next_event()
    usb.reset()
    usb.receive_data(struct.pack("<IHHI", 4, 4, 0x4002, 0))
    with pytest.raises(ProtocolError, match="shorter than its header"):
        usb.next_event()
    assert usb.framing.broken


def test_the_callers_read_buffer_may_be_reused_once_the_engine_asks_for_more_or_the_reply_is_in() -> None:
    """The transports read into one reusable buffer and feed views of it: the engine copies each payload once
    and keeps what it has not framed yet before asking for more (or before its transaction ends)."""
    payload = bytes(range(256)) * 4
    wire = pack_data(0x1009, 5, payload) + pack_response(0x2001, 5) + pack_response(0x2001, 6)
    host = Initiator(UsbFraming())
    host.send_command(0x1009, 5)
    rx = bytearray(100)
    pos, got = 0, []
    while not got or not isinstance(got[-1], ResponseReceived):
        event = host.next_event()
        if event is NEED_DATA:
            n = min(len(rx), len(wire) - pos)
            rx[:] = bytes(len(rx))
            rx[:n] = wire[pos : pos + n]
            host.receive_data(memoryview(rx)[:n])
            pos += n
        else:
            got.append(event)
    rx[:] = b"\xff" * len(rx)  # the next read reuses the buffer; the answer to transaction 6 came with this one
    assert merged(got) == [
        DataStarted(0x1009, 5, len(payload)),
        DataReceived(5, payload),
        DataFinished(5, len(payload)),
        ResponseReceived(0x2001, 5),
    ]
    host.send_command(0x1001, 6)
    assert drain(host) == [ResponseReceived(0x2001, 6)]
