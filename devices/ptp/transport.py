"""The transport interface a `Camera` talks through (USB, PTP/IP, ...), and the errors transports raise."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

from mca.devices.ptp.codec import Container

#: Receives each piece of a data-in phase as it arrives (streamed to a file without holding it all).
DataSink = Callable[[memoryview], None]


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


class Transport(ABC):
    """Runs PTP transactions; knows nothing about sessions or datasets."""

    #: A human name for error messages, e.g. "USB 001:004 Canon EOS 70D".
    name: str = "camera"

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
        (bounded by `max_data_bytes`; a larger claim is a `ProtocolError`).
        """

    @abstractmethod
    def read_event(self, timeout_s: float) -> Container | None:
        """The next standard event (interrupt endpoint / event channel), or None after the timeout."""

    def recover(self) -> None:
        """Bring the link back to idle after an aborted transaction (cancel, clear stalls, drain)."""

    @abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice."""
