"""How PTP phases travel on each link: USB containers and PTP/IP packets, turned into one frame vocabulary and back.

The transaction engine (`devices.ptp.engine`) sees only frames; a framing
knows the wire. Both framings stream a data phase: a header is parsed once its
bytes are in, then the payload leaves as `DataPiece` frames of whatever has
arrived, so nothing the peer claims is allocated before its bytes are here.
Only control containers and packets (a USB command/response/event, at most
32 bytes; a PTP/IP control packet, at most `MAX_CONTROL_PACKET_BYTES`) wait
whole in the buffer, and a header claiming more is a `ProtocolError` at once.

USB (Still Image class): a container is a 12-byte header (length, type,
code, transaction id) and its parameters or payload; one data container holds
the whole phase, so its header gives the operation code and the total.
PTP/IP: a packet is an 8-byte header (length, type) and a body; the data
phase is StartData (transaction id, total), then Data packets and a last
EndData, each opening with the transaction id. The engine checks the two
alike: `DataHead` gives the total (and the code when the wire carries it),
`DataPacket` each packet's share, `DataEnd` the end.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field

from mca.devices.ptp import ptpip_packets as ip
from mca.devices.ptp.codec import (
    HEADER_BYTES,
    MAX_CONTAINER_BYTES,
    ProtocolError,
    pack_command,
    pack_data_header,
    pack_event,
    pack_response,
    parse_container,
    parse_header,
)
from mca.devices.ptp.codes import ContainerType

_U32 = struct.Struct("<I")
#: Bytes as they go on the wire (a payload is passed on without a copy where the link allows).
Wire = bytes | bytearray | memoryview


# -- frames: one phase (or one piece of a data phase) as the engine sees it --------------------------------------
@dataclass(frozen=True)
class CommandFrame:
    """An operation request; `data_out` is what the wire says of a data-out phase (None: USB does not say)."""

    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    data_out: bool | None = None


@dataclass(frozen=True)
class DataHead:
    """A data phase begins: `total_bytes` announced; `code` is None where the wire does not carry it (PTP/IP)."""

    code: int | None
    transaction_id: int
    total_bytes: int


@dataclass(frozen=True)
class DataPacket:
    """One packet of a data phase: `payload_bytes` follow as `DataPiece` frames; `last` ends the phase."""

    transaction_id: int
    payload_bytes: int
    last: bool


@dataclass(frozen=True)
class DataPiece:
    data: bytes = field(repr=False)


@dataclass(frozen=True)
class DataEnd:
    """The last packet of a data phase is complete."""


@dataclass(frozen=True)
class ResponseFrame:
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()


@dataclass(frozen=True)
class EventFrame:
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()


@dataclass(frozen=True)
class PingFrame:
    pass


@dataclass(frozen=True)
class PongFrame:
    pass


@dataclass(frozen=True)
class OtherFrame:
    """A packet no transaction has a place for (a PTP/IP init or cancel packet); `wire` names it for errors."""

    wire: str
    body: bytes = field(default=b"", repr=False)


Frame = (
    CommandFrame
    | DataHead
    | DataPacket
    | DataPiece
    | DataEnd
    | ResponseFrame
    | EventFrame
    | PingFrame
    | PongFrame
    | OtherFrame
)


class Framing:
    """Bytes in, frames out (bounded), and frames packed into bytes; one per connection or endpoint."""

    #: Names the link in error messages ("USB", "PTP/IP").
    wire_name = "?"

    def __init__(self) -> None:
        # What has arrived and is not framed yet: the rest of the bytes last fed, read in place (`_view`, not
        # ours: it is copied into `_buf` before `next_frame` asks for more), or owned bytes (`_buf`) once a frame
        # was cut by the end of a read. Never both: a payload is copied once, into the piece handed out.
        self._buf = bytearray()
        self._view: memoryview | None = None
        self._ready: deque[Frame] = deque()
        self._payload_left = 0
        self._payload_last = False
        #: A header broke the rules: nothing after it can be framed (the link must be reset).
        self.broken = False

    # -- receiving ---------------------------------------------------------------------------------------------
    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Take bytes as they arrived, in any chunking; nothing is parsed until `next_frame`.

        `data` may be a view into a buffer the caller reuses: it is read only until `next_frame` returns None.
        """
        if not len(data):
            return
        if self._view is not None:  # fed twice without framing in between
            self.keep()
        if self._buf:
            self._buf += data
        else:
            self._view = memoryview(data).cast("B") if isinstance(data, memoryview) else memoryview(data)

    @property
    def buffered_bytes(self) -> int:
        return len(self._buf) + (len(self._view) if self._view is not None else 0)

    @property
    def at_boundary(self) -> bool:
        """Nothing of a frame is half-received: the stream can be read on from here."""
        return not self.buffered_bytes and not self._payload_left and not self._ready

    def clear(self) -> None:
        """Drop everything buffered (after a device reset, the link starts afresh)."""
        self._buf.clear()
        self._view = None
        self._ready.clear()
        self._payload_left = 0
        self._payload_last = False
        self.broken = False

    def next_frame(self) -> Frame | None:
        """The next complete frame, or None until more bytes arrive; a broken header is a `ProtocolError`."""
        if self._ready:
            return self._ready.popleft()
        if self._payload_left:
            window = self._window()
            if not len(window):
                self.keep()
                return None
            n = min(len(window), self._payload_left)
            piece = self._take(n)
            self._take_payload(n)
            return DataPiece(piece)
        if self.broken:
            raise ProtocolError(f"the {self.wire_name} stream is out of step after a broken header")
        before = self.buffered_bytes
        try:
            frame = self._parse()
        except ProtocolError:
            if self.buffered_bytes == before:  # a header: a bad body is consumed before it is parsed
                self.broken = True
            raise
        if frame is None:
            self.keep()
        return frame

    def _window(self) -> bytearray | memoryview:
        """The bytes not framed yet, from the start of the next frame."""
        if self._buf or self._view is None:
            return self._buf
        return self._view

    def _take(self, n: int) -> bytes:
        """The next `n` bytes (there must be as many), consumed."""
        if self._buf:
            out = bytes(self._buf[:n])
            del self._buf[:n]
            return out
        assert self._view is not None
        out = self._view[:n].tobytes()
        self._view = self._view[n:] if n < len(self._view) else None
        return out

    def _skip(self, n: int) -> None:
        if self._buf:
            del self._buf[:n]
        else:
            assert self._view is not None
            self._view = self._view[n:] if n < len(self._view) else None

    def keep(self) -> None:
        """Copy what is left of the caller's bytes into our own buffer (more bytes are needed, or they will wait)."""
        if self._view is not None:
            self._buf += self._view
            self._view = None

    def _take_payload(self, n: int) -> None:
        self._payload_left -= n
        if not self._payload_left and self._payload_last:
            self._ready.append(DataEnd())

    def _start_payload(self, n: int, last: bool) -> None:
        self._payload_left, self._payload_last = n, last
        if not n and last:
            self._ready.append(DataEnd())

    def _parse(self) -> Frame | None:
        raise NotImplementedError

    def describe(self, frame: Frame) -> str:
        """How a misplaced frame is named in an error message."""
        if isinstance(frame, OtherFrame):
            return frame.wire
        return type(frame).__name__

    # -- sending -----------------------------------------------------------------------------------------------
    def pack_command(self, code: int, transaction_id: int, params: tuple[int, ...], data_out: bool) -> bytes:
        raise NotImplementedError

    def pack_data_start(self, code: int, transaction_id: int, total_bytes: int) -> bytes:
        raise NotImplementedError

    def pack_data_piece(self, transaction_id: int, piece: bytes | bytearray | memoryview, last: bool) -> Wire:
        raise NotImplementedError

    def pack_data(self, code: int, transaction_id: int, payload: bytes | bytearray | memoryview) -> list[Wire]:
        """A whole data phase, as the writes it takes (USB: one container, one transfer)."""
        return [
            self.pack_data_start(code, transaction_id, len(payload)),
            self.pack_data_piece(transaction_id, payload, True),
        ]

    def pack_response(self, code: int, transaction_id: int, params: tuple[int, ...]) -> bytes:
        raise NotImplementedError

    def pack_event(self, code: int, transaction_id: int, params: tuple[int, ...]) -> bytes:
        raise NotImplementedError

    def pack_pong(self) -> bytes:
        raise ProtocolError(f"{self.wire_name} has no ping/pong")


class UsbFraming(Framing):
    """PTP containers as the Still Image class sends them on the bulk pipes (and events on the interrupt pipe)."""

    wire_name = "USB"

    def __init__(self, max_container_bytes: int = MAX_CONTAINER_BYTES) -> None:
        super().__init__()
        self.max_container_bytes = max_container_bytes

    def _parse(self) -> Frame | None:
        window = self._window()
        if len(window) < HEADER_BYTES:
            return None
        header = parse_header(window[:HEADER_BYTES], self.max_container_bytes)
        if header.type == ContainerType.DATA:
            self._skip(HEADER_BYTES)
            self._ready.append(DataPacket(header.transaction_id, header.payload_bytes, True))
            self._start_payload(header.payload_bytes, True)
            return DataHead(header.code, header.transaction_id, header.payload_bytes)
        if len(window) < header.length:
            return None
        c = parse_container(self._take(header.length))
        if c.type == ContainerType.COMMAND:
            return CommandFrame(c.code, c.transaction_id, c.params, None)
        if c.type == ContainerType.RESPONSE:
            return ResponseFrame(c.code, c.transaction_id, c.params)
        return EventFrame(c.code, c.transaction_id, c.params)

    def describe(self, frame: Frame) -> str:
        kind = {CommandFrame: "COMMAND", DataHead: "DATA", ResponseFrame: "RESPONSE", EventFrame: "EVENT"}.get(
            type(frame)
        )
        return f"a {kind} container" if kind else super().describe(frame)

    def pack_command(self, code: int, transaction_id: int, params: tuple[int, ...], data_out: bool) -> bytes:
        return pack_command(code, transaction_id, params)

    def pack_data_start(self, code: int, transaction_id: int, total_bytes: int) -> bytes:
        return pack_data_header(code, transaction_id, total_bytes)

    def pack_data_piece(self, transaction_id: int, piece: bytes | bytearray | memoryview, last: bool) -> Wire:
        return piece  # one container carries the whole phase: the payload follows its header as it is

    def pack_data(self, code: int, transaction_id: int, payload: bytes | bytearray | memoryview) -> list[Wire]:
        return [pack_data_header(code, transaction_id, len(payload)) + bytes(payload)]

    def pack_response(self, code: int, transaction_id: int, params: tuple[int, ...]) -> bytes:
        return pack_response(code, transaction_id, params)

    def pack_event(self, code: int, transaction_id: int, params: tuple[int, ...]) -> bytes:
        return pack_event(code, transaction_id, params)


class PtpIpFraming(Framing):
    """PTP/IP packets on the command/data connection (or the event connection)."""

    wire_name = "PTP/IP"

    def __init__(self, max_control_packet_bytes: int = ip.MAX_CONTROL_PACKET_BYTES) -> None:
        super().__init__()
        self.max_control_packet_bytes = max_control_packet_bytes

    def _parse(self) -> Frame | None:
        window = self._window()
        if len(window) < 8:
            return None
        length, kind = struct.unpack_from("<II", window)
        if length < 8:
            raise ProtocolError(f"PTP/IP packet length {length} is shorter than its header")
        if not 1 <= kind <= 14:
            raise ProtocolError(f"unknown PTP/IP packet type {kind}")
        if kind in (ip.DATA, ip.END_DATA):
            if length < 12:
                raise ProtocolError("PTP/IP data packet without its transaction id")
            if len(window) < 12:
                return None
            (tid,) = _U32.unpack_from(window, 8)
            self._skip(12)
            last = kind == ip.END_DATA
            self._start_payload(length - 12, last)
            return DataPacket(tid, length - 12, last)
        if length - 8 > self.max_control_packet_bytes:
            raise ProtocolError(
                f"PTP/IP packet of {length} bytes exceeds the {self.max_control_packet_bytes}-byte limit"
            )
        if len(window) < length:
            return None
        body = self._take(length)[8:]  # consumed whole before its body is parsed: a bad body leaves the stream in step
        if kind == ip.START_DATA:
            tid, total = ip.parse_start_data(body)
            return DataHead(None, tid, total)
        if kind == ip.OPERATION_RESPONSE:
            c = ip.parse_operation_response(body)
            return ResponseFrame(c.code, c.transaction_id, c.params)
        if kind == ip.OPERATION_REQUEST:
            dataphase, c = ip.parse_operation_request(body)
            return CommandFrame(c.code, c.transaction_id, c.params, dataphase == ip.DATAPHASE_OUT)
        if kind == ip.EVENT:
            c = ip.parse_event_packet(body)
            return EventFrame(c.code, c.transaction_id, c.params)
        if kind == ip.PING:
            return PingFrame()
        if kind == ip.PONG:
            return PongFrame()
        return OtherFrame(f"PTP/IP packet type {kind}", body)

    def describe(self, frame: Frame) -> str:
        kind = {
            CommandFrame: ip.OPERATION_REQUEST,
            ResponseFrame: ip.OPERATION_RESPONSE,
            EventFrame: ip.EVENT,
            DataHead: ip.START_DATA,
            PingFrame: ip.PING,
            PongFrame: ip.PONG,
        }.get(type(frame))
        return f"PTP/IP packet type {kind}" if kind else super().describe(frame)

    def pack_command(self, code: int, transaction_id: int, params: tuple[int, ...], data_out: bool) -> bytes:
        phase = ip.DATAPHASE_OUT if data_out else ip.DATAPHASE_NONE_OR_IN
        return ip.pack_operation_request(code, transaction_id, params, phase)

    def pack_data_start(self, code: int, transaction_id: int, total_bytes: int) -> bytes:
        return ip.pack_start_data(transaction_id, total_bytes)

    def pack_data_piece(self, transaction_id: int, piece: bytes | bytearray | memoryview, last: bool) -> Wire:
        return ip.pack_data_packet(transaction_id, piece, end=last)

    def pack_response(self, code: int, transaction_id: int, params: tuple[int, ...]) -> bytes:
        return ip.pack_operation_response(code, transaction_id, params)

    def pack_event(self, code: int, transaction_id: int, params: tuple[int, ...]) -> bytes:
        return ip.pack_event_packet(code, transaction_id, params)

    def pack_pong(self) -> bytes:
        return ip.pack_packet(ip.PONG)
