"""The PTP transaction engine, sans I/O in the style of h11: bytes in, events out, bytes to send, bounded buffers.

A PTP transaction is a command, an optional data phase (out from the
initiator, or in from the responder) and a response, all with the command's
transaction id. The engine keeps that state machine and nothing else: it
never reads, writes, sleeps or times out. The shells around it move the
bytes and keep the link's own rules: `transport_usb` (zero-length packets,
stalls, class requests), `transport_ptpip` (sockets, the event connection),
and on the other side the simulated camera's `usb_backend` and `ptpip_server`.

**Two layers.** The wire differs between USB and PTP/IP (a 12-byte container
holding a whole phase, against 8-byte packets with StartData/Data/EndData),
the transaction does not. So a `Framing` per link (`devices.ptp.framing`)
turns bytes into one vocabulary of frames and packs frames into bytes, and
one state machine per role runs over those frames: `Initiator` (the host),
`Responder` (the camera) and `EventReader` (the interrupt pipe or event
connection). A third link would need a framing, not another state machine.

**Use (initiator).** `send_command(...)` gives the writes (the command, then
the data-out phase); `receive_data(bytes)` takes what arrived in any chunking
(split headers, several containers in one read); `next_event()` returns the
next `Event` or `NEED_DATA`. A transaction ends with `ResponseReceived`.
`receive_data` may be given a view into a read buffer the caller reuses: the
engine frames it in place and copies what it has not framed yet before it
returns NEED_DATA or ends a transaction (each payload byte is copied once).

**Use (responder).** `next_event()` gives `CommandReceived`, whose `data_out`
says whether a data-out phase follows (PTP/IP says so on the wire; USB does
not, so the responder asks `expects_data_out(code)`), then that phase; then
`send_data_start`/`send_data_piece` (or `send_data`) and `send_response`
give the reply's bytes, or `drop_reply()` says none will come.

**Bounds and errors.** A data phase is streamed as `DataReceived` pieces of
what has arrived; only control containers wait whole, and they are small
(framing). A claim beyond the caller's `max_data_bytes`, a length shorter
than a header, a phase out of order, a transaction id that matches neither
this transaction nor an earlier one, or bytes beyond the announced total are a
`ProtocolError` naming the field; the engine then stays in error until
`abandon()` or `reset()`. Late replies to transactions given up earlier (a
camera answering after the host timed out) are discarded, at most
`stale_replies_max` per transaction; a late data phase of at most
`MAX_LATE_KEEP_BYTES` is handed on whole (`LateDataReceived`: a late GetEvent
list carries events the host must not lose).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

from mca.devices.ptp.codec import ProtocolError, is_older_transaction
from mca.devices.ptp.codes import Op
from mca.devices.ptp.framing import (
    CommandFrame,
    DataEnd,
    DataHead,
    DataPacket,
    DataPiece,
    EventFrame,
    Frame,
    Framing,
    PingFrame,
    PongFrame,
    ResponseFrame,
    Wire,
)

#: A late reply's data phase is kept and handed on up to this size (a GetEvent list); larger ones are drained.
MAX_LATE_KEEP_BYTES = 4 * 1024 * 1024
#: Bytes that may wait while no transaction is open (what a read brought beyond the last response).
MAX_IDLE_BYTES = 4 * 1024 * 1024
#: Operation codes remembered per transaction id, so a late data phase is handed on with its operation.
MAX_REMEMBERED_CODES = 64
DEFAULT_MAX_DATA_BYTES = 64 * 1024 * 1024


class _NeedData:
    def __repr__(self) -> str:
        return "NEED_DATA"


#: `next_event()` has nothing complete: feed more bytes with `receive_data`.
NEED_DATA = _NeedData()


# -- events ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CommandReceived:
    """(responder) An operation request; `data_out` says whether a data-out phase follows before the reply."""

    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    data_out: bool = False


@dataclass(frozen=True)
class DataStarted:
    """A data phase of `total_bytes` begins; `code` is None where the wire does not carry it (PTP/IP)."""

    code: int | None
    transaction_id: int
    total_bytes: int


@dataclass(frozen=True)
class DataReceived:
    """A piece of the data phase, as it arrived."""

    transaction_id: int
    data: bytes = field(repr=False)


@dataclass(frozen=True)
class DataFinished:
    transaction_id: int
    total_bytes: int


@dataclass(frozen=True)
class ResponseReceived:
    """(initiator) The transaction's response: it is over."""

    code: int
    transaction_id: int
    params: tuple[int, ...] = ()


@dataclass(frozen=True)
class EventReceived:
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()


@dataclass(frozen=True)
class LateReplyDiscarded:
    """(initiator) A reply to an earlier, given-up transaction began; it is read past."""

    transaction_id: int


@dataclass(frozen=True)
class LateDataReceived:
    """(initiator) The whole data phase of a late reply (code 0 when its operation is not known)."""

    code: int
    transaction_id: int
    data: bytes = field(repr=False)


@dataclass(frozen=True)
class PingReceived:
    """(PTP/IP) The peer asks whether we are alive: send `pong()`."""


Event = (
    CommandReceived
    | DataStarted
    | DataReceived
    | DataFinished
    | ResponseReceived
    | EventReceived
    | LateReplyDiscarded
    | LateDataReceived
    | PingReceived
)


class _State(Enum):
    IDLE = "idle"
    AWAIT_REPLY = "awaiting the data-in phase or the response"
    DATA_OUT = "receiving the data-out phase"
    REPLY_DUE = "the reply is due"
    SENDING_DATA = "sending the data-in phase"
    ERROR = "error"


@dataclass
class _DataPhase:
    """Bookkeeping of one data phase being received."""

    transaction_id: int
    total_bytes: int
    got_bytes: int = 0
    ended: bool = False


@dataclass
class _LateReply:
    transaction_id: int
    code: int
    data: bytearray | None = None  # kept while the phase fits MAX_LATE_KEEP_BYTES
    total_bytes: int | None = None
    handed_on: bool = False


class _Engine:
    """What both roles share: the framing, the error state, the bytes waiting, the data phase's checks."""

    #: States in which arriving bytes wait unparsed (up to `max_idle_bytes`), and how an excess is worded.
    _WAITING: tuple[_State, ...] = ()
    _WAITING_WORDS = ""

    def __init__(self, framing: Framing, name: str, max_idle_bytes: int = MAX_IDLE_BYTES) -> None:
        self.framing = framing
        self.name = name
        self.max_idle_bytes = max_idle_bytes
        self._state = _State.IDLE
        self._error: ProtocolError | None = None
        self._data: _DataPhase | None = None

    @property
    def state(self) -> str:
        return self._state.value

    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Bytes as they arrived (any chunking); parsed by `next_event`."""
        self.framing.receive_data(data)
        if self._state in self._WAITING:
            self.framing.keep()  # they wait: the caller may reuse its buffer
            if self.framing.buffered_bytes > self.max_idle_bytes:
                raise self._fail(f"{self.name} sent {self.framing.buffered_bytes} bytes {self._WAITING_WORDS}")

    def next_event(self) -> Event | _NeedData:
        """The next event, or NEED_DATA: feed more bytes (or, in a waiting state, act first: bytes wait for it)."""
        while True:
            if self._state in self._WAITING:
                return NEED_DATA
            frame = self._next_frame()
            if frame is None:
                return NEED_DATA
            event = self._on_frame(frame)
            if event is not None:
                if self._state in self._WAITING:
                    self.framing.keep()  # bytes beyond this frame wait: the caller may reuse its buffer
                return event

    def _on_frame(self, frame: Frame) -> Event | None:
        raise NotImplementedError

    @property
    def in_step(self) -> bool:
        """No frame is half-received: after a timeout here the stream can be read on (else the link is lost)."""
        return self.framing.at_boundary

    def _fail(self, message: str) -> ProtocolError:
        self._state = _State.ERROR
        self._error = ProtocolError(message)
        return self._error

    def _next_frame(self) -> Frame | None:
        if self._state is _State.ERROR:
            raise ProtocolError(f"{self.name}: the link is out of step after: {self._error}; recover it first")
        try:
            return self.framing.next_frame()
        except ProtocolError as exc:
            self._state, self._error = _State.ERROR, exc
            raise

    def _begin_data(self, frame: DataHead, code: int, limit_bytes: int, limit_word: str) -> DataStarted:
        """Check a data phase's head against the transaction (`code`) and the size limit; start counting it."""
        if self._data is not None:
            raise self._fail(f"{self.name} sent two data phases for one transaction")
        if frame.code is not None and frame.code != code:
            raise self._fail(f"{self.name} data phase code 0x{frame.code:04X} for operation 0x{code:04X}")
        if frame.total_bytes > limit_bytes:
            raise self._fail(
                f"{self.name} announced {frame.total_bytes} data bytes, more than the {limit_bytes} {limit_word}"
            )
        self._data = _DataPhase(frame.transaction_id, frame.total_bytes)
        return DataStarted(frame.code, frame.transaction_id, frame.total_bytes)

    def _count_packet(self, frame: DataPacket, transaction_id: int) -> None:
        """A data packet's share, counted at its header (its pieces are bounded by it) against the total."""
        data = self._data
        if data is None:
            raise self._fail(f"{self.name} sent data without StartData")
        if frame.transaction_id != transaction_id:
            raise self._fail(
                f"{self.name} sent data of transaction {frame.transaction_id} in transaction {transaction_id}"
            )
        if data.got_bytes + frame.payload_bytes > data.total_bytes:
            raise self._fail(
                f"{self.name} sent {data.got_bytes + frame.payload_bytes} data bytes after announcing {data.total_bytes}"
            )
        data.got_bytes += frame.payload_bytes

    def reset(self) -> None:
        """Back to idle with nothing buffered (after a device reset or a reconnect)."""
        self.framing.clear()
        self._state, self._error = _State.IDLE, None

    def pong(self) -> bytes:
        return self.framing.pack_pong()


class Initiator(_Engine):
    """The host's side: commands and data-out go out, data-in and responses come in.

    While no transaction is open, arriving bytes wait for the next command (a read may bring more than a reply).
    """

    _WAITING = (_State.IDLE,)
    _WAITING_WORDS = "while no transaction was open"

    def __init__(
        self,
        framing: Framing,
        *,
        name: str = "camera",
        stale_replies_max: int = 16,
        max_idle_bytes: int = MAX_IDLE_BYTES,
    ) -> None:
        super().__init__(framing, name, max_idle_bytes)
        self.stale_replies_max = stale_replies_max
        #: Operation code of each recent transaction id (a late data phase is handed on with its code).
        self.sent_codes: dict[int, int] = {}
        self.transaction_id: int | None = None
        self.code = 0
        self.max_data_bytes = DEFAULT_MAX_DATA_BYTES
        self._late: _LateReply | None = None
        self._late_count = 0
        self._pieces_to_late = False

    # -- sending ---------------------------------------------------------------------------------------------------
    def send_command(
        self,
        code: int,
        transaction_id: int,
        params: tuple[int, ...] = (),
        *,
        data_out: bytes | bytearray | memoryview | None = None,
        max_data_bytes: int = DEFAULT_MAX_DATA_BYTES,
    ) -> list[Wire]:
        """Start a transaction; returns the writes, in order (each one transfer): the command, then the data phase.

        A transaction still open is given up (its reply, if it comes, is discarded as late).
        """
        if self._state is not _State.IDLE:
            self.abandon()
        writes: list[Wire] = [self.framing.pack_command(code, transaction_id, tuple(params), data_out is not None)]
        if data_out is not None:
            writes.extend(self.framing.pack_data(code, transaction_id, data_out))
        self.transaction_id, self.code, self.max_data_bytes = transaction_id, code, max_data_bytes
        self.sent_codes[transaction_id] = code
        while len(self.sent_codes) > MAX_REMEMBERED_CODES:
            del self.sent_codes[next(iter(self.sent_codes))]
        self._state = _State.AWAIT_REPLY
        self._data, self._late, self._late_count, self._pieces_to_late = None, None, 0, False
        return writes

    @property
    def in_step(self) -> bool:
        """No frame and no data phase is half-received: after a timeout here the stream can be read on."""
        data = self._data
        mid_data = data is not None and data.got_bytes > 0 and not data.ended
        return self.framing.at_boundary and not mid_data and not self._pieces_to_late

    def abandon(self) -> None:
        """Give up the open transaction (a timeout, an error); bytes already buffered are kept and read on."""
        self._state, self._error = _State.IDLE, None
        self._data, self._late, self._pieces_to_late = None, None, False

    def reset(self) -> None:
        super().reset()
        self.abandon()

    # -- receiving -------------------------------------------------------------------------------------------------
    def _late_ok(self, tid: int) -> bool:
        assert self.transaction_id is not None
        older = is_older_transaction(tid, self.transaction_id) or self.code == Op.OPEN_SESSION
        return older and self._late_count < self.stale_replies_max and self._data is None

    def _unexpected_tid(self, tid: int) -> ProtocolError:
        return self._fail(f"{self.name} answered transaction {tid}, expected {self.transaction_id}")

    def _start_late(self, tid: int, code: int | None) -> Event:
        self._late_count += 1
        known = self.sent_codes.get(tid, 0)
        self._late = _LateReply(tid, code if code is not None else known)
        return LateReplyDiscarded(tid)

    def _on_frame(self, frame: Frame) -> Event | None:
        tid = self.transaction_id
        if isinstance(frame, DataHead):
            if frame.transaction_id != tid:
                if self._late is not None and self._late.transaction_id == frame.transaction_id:
                    self._late.total_bytes = frame.total_bytes
                    self._late.data = bytearray() if frame.total_bytes <= MAX_LATE_KEEP_BYTES else None
                    return None
                if self._late_ok(frame.transaction_id):
                    event = self._start_late(frame.transaction_id, frame.code)
                    assert self._late is not None
                    self._late.total_bytes = frame.total_bytes
                    self._late.data = bytearray() if frame.total_bytes <= MAX_LATE_KEEP_BYTES else None
                    return event
                raise self._unexpected_tid(frame.transaction_id)
            return self._begin_data(frame, self.code, self.max_data_bytes, "expected")
        if isinstance(frame, DataPacket):
            if self._late is not None and frame.transaction_id == self._late.transaction_id:
                self._pieces_to_late = True
                return None
            self._pieces_to_late = False
            assert tid is not None
            self._count_packet(frame, tid)
            return None
        if isinstance(frame, DataPiece):
            if self._pieces_to_late:
                late = self._late
                if late is not None and late.data is not None:
                    late.data += frame.data
                return None
            assert self._data is not None and tid is not None
            return DataReceived(tid, frame.data)
        if isinstance(frame, DataEnd):
            if self._pieces_to_late:
                self._pieces_to_late = False
                return self._hand_on_late()
            assert self._data is not None and tid is not None
            self._data.ended = True
            return DataFinished(tid, self._data.got_bytes)
        if isinstance(frame, ResponseFrame):
            if frame.transaction_id != tid:
                if self._late is not None and self._late.transaction_id == frame.transaction_id:
                    return self._end_late()
                if self._late_ok(frame.transaction_id):
                    self._start_late(frame.transaction_id, None)
                    self._late = None
                    return LateReplyDiscarded(frame.transaction_id)
                raise self._unexpected_tid(frame.transaction_id)
            data = self._data
            if data is not None and data.got_bytes != data.total_bytes:
                raise self._fail(f"{self.name} sent {data.got_bytes} of the {data.total_bytes} data bytes it announced")
            self._state = _State.IDLE
            self._late = None
            return ResponseReceived(frame.code, frame.transaction_id, frame.params)
        if isinstance(frame, PingFrame):
            return PingReceived()
        if isinstance(frame, PongFrame):
            return None
        raise self._fail(f"{self.name} sent {self.framing.describe(frame)} during a transaction")

    def _hand_on_late(self) -> Event | None:
        late = self._late
        if late is None or late.handed_on or late.data is None:
            return None
        late.handed_on = True
        if late.total_bytes is not None and len(late.data) != late.total_bytes:
            return None
        return LateDataReceived(late.code, late.transaction_id, bytes(late.data))

    def _end_late(self) -> Event | None:
        event = self._hand_on_late()  # a late data phase that ended without EndData is handed on at its response
        self._late, self._pieces_to_late = None, False
        return event


class Responder(_Engine):
    """The camera's side: commands and data-out come in, data-in and responses go out.

    While the reply is due, arriving bytes (the host's next command) wait for it.
    """

    _WAITING = (_State.REPLY_DUE, _State.SENDING_DATA)
    _WAITING_WORDS = "before its reply"

    def __init__(
        self,
        framing: Framing,
        *,
        name: str = "initiator",
        expects_data_out: Callable[[int], bool] | None = None,
        max_data_out_bytes: int = 16 * 1024 * 1024,
        max_idle_bytes: int = MAX_IDLE_BYTES,
    ) -> None:
        super().__init__(framing, name, max_idle_bytes)
        self.expects_data_out = expects_data_out
        self.max_data_out_bytes = max_data_out_bytes
        self.command: CommandReceived | None = None
        self._sending_total = 0
        self._sent_bytes = 0

    def _on_frame(self, frame: Frame) -> Event | None:
        if isinstance(frame, PingFrame):
            return PingReceived()
        if isinstance(frame, PongFrame):
            return None
        if self._state is _State.IDLE:
            if not isinstance(frame, CommandFrame):
                raise self._fail(f"expected an operation request, got {self.framing.describe(frame)}")
            if self.expects_data_out is not None:
                data_out = self.expects_data_out(frame.code)
            else:
                data_out = bool(frame.data_out)
            self.command = CommandReceived(frame.code, frame.transaction_id, frame.params, data_out)
            self._data = None
            self._state = _State.DATA_OUT if data_out else _State.REPLY_DUE
            return self.command
        assert self.command is not None
        tid = self.command.transaction_id
        if isinstance(frame, DataHead):
            if frame.transaction_id != tid:
                raise self._fail(f"{self.name} sent data of transaction {frame.transaction_id} in transaction {tid}")
            return self._begin_data(frame, self.command.code, self.max_data_out_bytes, "accepted")
        if isinstance(frame, DataPacket):
            self._count_packet(frame, tid)
            return None
        if isinstance(frame, DataPiece):
            return DataReceived(tid, frame.data)
        if isinstance(frame, DataEnd):
            data = self._data
            assert data is not None
            if data.got_bytes != data.total_bytes:
                raise self._fail(f"{self.name} sent {data.got_bytes} of the {data.total_bytes} data bytes it announced")
            self._state = _State.REPLY_DUE
            return DataFinished(tid, data.got_bytes)
        raise self._fail(f"{self.name} sent {self.framing.describe(frame)} during the data-out phase")

    # -- sending the reply -----------------------------------------------------------------------------------------
    def _reply_due(self, what: str) -> CommandReceived:
        if self._state not in (_State.REPLY_DUE, _State.SENDING_DATA) or self.command is None:
            raise ProtocolError(f"cannot send {what}: no command is waiting for its reply ({self.state})")
        return self.command

    def send_data_start(self, total_bytes: int) -> bytes:
        """The data-in phase's opening (USB: the container header; PTP/IP: StartData)."""
        cmd = self._reply_due("a data phase")
        if self._state is _State.SENDING_DATA:
            raise ProtocolError("cannot send a second data phase in one transaction")
        self._state, self._sending_total, self._sent_bytes = _State.SENDING_DATA, total_bytes, 0
        return self.framing.pack_data_start(cmd.code, cmd.transaction_id, total_bytes)

    def send_data_piece(self, piece: bytes | memoryview, last: bool = False) -> Wire:
        """A piece of the data-in phase (USB: the bytes as they are; PTP/IP: a Data or, `last`, an EndData packet)."""
        cmd = self._reply_due("data")
        if self._state is not _State.SENDING_DATA:
            raise ProtocolError("cannot send data before the data phase's start")
        self._sent_bytes += len(piece)
        if self._sent_bytes > self._sending_total or (last and self._sent_bytes != self._sending_total):
            raise ProtocolError(f"data phase announced {self._sending_total} bytes, {self._sent_bytes} given")
        return self.framing.pack_data_piece(cmd.transaction_id, piece, last)

    def send_data(self, payload: bytes | memoryview) -> list[Wire]:
        """A whole data-in phase, as the pieces to send in order (USB: the header, then the payload uncopied)."""
        return [self.send_data_start(len(payload)), self.send_data_piece(payload, last=True)]

    def send_response(self, code: int, params: tuple[int, ...] = ()) -> bytes:
        """The response ending the transaction (the command's transaction id)."""
        cmd = self._reply_due("a response")
        if self._state is _State.SENDING_DATA and self._sent_bytes != self._sending_total:
            raise ProtocolError(f"data phase announced {self._sending_total} bytes, {self._sent_bytes} sent")
        self._state = _State.IDLE
        return self.framing.pack_response(code, cmd.transaction_id, tuple(params))

    def send_event(self, code: int, transaction_id: int = 0, params: tuple[int, ...] = ()) -> bytes:
        return self.framing.pack_event(code, transaction_id, tuple(params))

    def drop_reply(self) -> None:
        """The camera acted but never answers (the host times out); the next command may come."""
        if self._state in (_State.REPLY_DUE, _State.SENDING_DATA):
            self._state = _State.IDLE

    def abandon(self) -> None:
        """The host cancelled the transaction: back to idle, keeping bytes already buffered."""
        self._state, self._error, self._data = _State.IDLE, None, None

    def reset(self) -> None:
        super().reset()
        self.abandon()


class EventReader(_Engine):
    """Events on their own channel (USB interrupt pipe, PTP/IP event connection); pings answered by the shell.

    An event whose body breaks the rules is a `ProtocolError`, but it was read whole: the reader goes on. A
    broken header is not (`framing.broken`): the channel is lost.
    """

    def next_event(self) -> Event | _NeedData:
        while True:
            frame = self.framing.next_frame()
            if frame is None:
                return NEED_DATA
            if isinstance(frame, EventFrame):
                return EventReceived(frame.code, frame.transaction_id, frame.params)
            if isinstance(frame, PingFrame):
                return PingReceived()
            if isinstance(frame, PongFrame):
                continue
            raise ProtocolError(f"{self.name} sent {self.framing.describe(frame)} where an event was due")
