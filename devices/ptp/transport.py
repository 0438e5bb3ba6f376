"""The transport interface a `Camera` talks through (USB, PTP/IP, ...), and the errors transports raise."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

from mca.devices.ptp.codec import Container
from mca.devices.ptp.engine import (
    NEED_DATA,
    DataReceived,
    DataStarted,
    Initiator,
    LateDataReceived,
    LateReplyDiscarded,
    PingReceived,
    ResponseReceived,
)

#: Receives each piece of a data-in phase as it arrives (streamed to a file without holding it all).
DataSink = Callable[[memoryview], None]
#: Receives the data phase of a late reply to an earlier transaction (operation code, transaction id, payload).
StaleDataHook = Callable[[int, int, bytes], None]


class TransportError(Exception):
    """The link to the camera failed (I/O error, timeout, disconnect)."""


class TransportTimeout(TransportError):
    """The camera did not answer within the timeout."""


class DeviceDisconnected(TransportError):
    """The camera went away (cable pulled, powered off, auto power-off)."""


@dataclass(frozen=True)
class Response:
    """The outcome of one transaction: response code and parameters, and the data-in phase when collected."""

    code: int
    params: tuple[int, ...] = ()
    data: bytes | None = None
    data_bytes: int = 0


@dataclass
class LinkCounters:
    """What a transport had to cope with; `mca camera doctor` and the fault tests read these."""

    stale_replies_discarded: int = 0
    stalls_cleared: int = 0
    cancels_sent: int = 0
    resets_sent: int = 0
    timeouts: int = 0


class Transport(ABC):
    """Runs PTP transactions; knows nothing about sessions or datasets."""

    #: A human name for error messages, e.g. "USB 001:004 Canon EOS 70D".
    name: str = "camera"
    #: The USB vendor id when the camera is on USB (libgphoto2 restores Canon's extension id from it).
    usb_vendor_id: int | None = None
    #: Called with the data phase of a reply that arrived after its transaction was given up (a late GetEvent
    #: reply carries events the host must not lose).
    on_stale_data: StaleDataHook | None = None

    def __init__(self) -> None:
        self.counters = LinkCounters()

    @abstractmethod
    def transaction(
        self,
        code: int,
        transaction_id: int,
        params: tuple[int, ...] = (),
        *,
        data_out: bytes | None = None,
        sink: DataSink | None = None,
        max_data_bytes: int = 64 * 1024 * 1024,
        timeout_s: float | None = None,
    ) -> Response:
        """Send a command (and its data-out phase), receive any data-in phase and the response.

        Data-in goes to `sink` when given, else it is collected into `Response.data`
        (bounded by `max_data_bytes`; a larger claim is a `ProtocolError`). Replies to earlier
        transactions that arrive first are discarded (their data goes to `on_stale_data`).
        """

    @abstractmethod
    def read_event(self, timeout_s: float) -> Container | None:
        """The next standard event (interrupt endpoint / event channel), or None after the timeout."""

    def recover(self, transaction_id: int | None = None) -> None:  # noqa: B027 (a no-op unless overridden)
        """Bring the link back to idle after an aborted transaction (cancel, clear stalls, drain)."""

    def reset_device(self) -> None:  # noqa: B027 (a no-op where there is no such request)
        """Ask the device to reset its PTP state (USB class request 0x66); a no-op where there is none."""

    @property
    def can_resume(self) -> bool:
        """Whether a transaction may follow a failed one on this link (False once the link is closed)."""
        return True

    @abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice."""


def run_to_response(
    transport: Transport,
    engine: Initiator,
    read: Callable[[], bytes | memoryview],
    sink: DataSink | None,
    send: Callable[[bytes], None] | None = None,
) -> Response:
    """Feed `read()` to the engine until the open transaction's response: collect or stream the data-in phase,
    count late replies and hand their data to `on_stale_data`, and answer pings with `send` (PTP/IP)."""
    data: bytearray | None = None
    got = 0
    while True:
        event = engine.next_event()
        if event is NEED_DATA:
            engine.receive_data(read())
        elif isinstance(event, DataReceived):
            if data is None:
                assert sink is not None
                sink(memoryview(event.data))
            else:
                data[got : got + len(event.data)] = event.data
            got += len(event.data)
        elif isinstance(event, DataStarted):
            if sink is None:
                data = bytearray(event.total_bytes)
        elif isinstance(event, ResponseReceived):
            return Response(event.code, event.params, bytes(data) if data is not None else None, got)
        elif isinstance(event, PingReceived) and send is not None:
            send(engine.pong())
        elif isinstance(event, LateReplyDiscarded):
            transport.counters.stale_replies_discarded += 1
        elif isinstance(event, LateDataReceived) and transport.on_stale_data is not None:
            transport.on_stale_data(event.code, event.transaction_id, event.data)
