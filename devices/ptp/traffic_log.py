"""A PTP traffic log (`--debug-logfile FILE`): every transaction and event of a transport, one line each.

`log_traffic(transport, write)` wraps the transport's `transaction` and `read_event` on that instance (the
transport keeps its class, so code that asks what kind of link it is still gets the answer), and hands
`write` one text line per command, response and event:

    2024-05-01T10:15:02.123Z -> 0x1008 GetObjectInfo tid=5 params=0x0000000A
    2024-05-01T10:15:02.131Z <- OK tid=5 params=- data-in=166 B 8.1 ms  00 00 01 00 ...
    2024-05-01T10:15:02.140Z <- event ObjectAdded params=0x0000000B
    2024-05-01T10:15:02.150Z <- error tid=6 after 5003.0 ms: TransportError: no answer within 5.0 s

Data phases are summarised (size and the first `PREVIEW_BYTES` in hex), not stored: an image download is
one line, not 25 MB of hex. Times are UTC.
"""

from __future__ import annotations

import datetime
import time
from collections.abc import Callable
from typing import Any

from mca.devices.ptp.codes import Event, Resp, name_of, op_name

PREVIEW_BYTES = 16


def timestamp() -> str:
    """UTC now, to the millisecond, as the log writes it."""
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _params(params: tuple[int, ...] | list[int]) -> str:
    return ",".join(f"0x{int(p):08X}" for p in params) or "-"


def _preview(data: bytes | bytearray | memoryview | None) -> str:
    if not data:
        return ""
    head = bytes(data[:PREVIEW_BYTES]).hex(" ")
    return f"  {head}{' ...' if len(data) > PREVIEW_BYTES else ''}"


def log_traffic(transport: Any, write: Callable[[str], None]) -> Any:
    """Log every transaction and event of `transport` through `write(line)`; returns the same transport."""
    transaction = transport.transaction
    read_event = transport.read_event

    def logged_transaction(code: int, transaction_id: int, params: tuple[int, ...] = (), **kwargs: Any) -> Any:
        data_out = kwargs.get("data_out")
        out = f" data-out={len(data_out)} B{_preview(data_out)}" if data_out is not None else ""
        write(f"{timestamp()} -> {op_name(code)} tid={transaction_id} params={_params(params)}{out}")
        sink = kwargs.get("sink")
        received = [0]
        if sink is not None:

            def counting_sink(piece: memoryview) -> None:
                received[0] += len(piece)
                sink(piece)

            kwargs["sink"] = counting_sink
        started = time.perf_counter()
        try:
            response = transaction(code, transaction_id, params, **kwargs)
        except BaseException as exc:
            took = (time.perf_counter() - started) * 1000.0
            write(f"{timestamp()} <- error tid={transaction_id} after {took:.1f} ms: {type(exc).__name__}: {exc}")
            raise
        took = (time.perf_counter() - started) * 1000.0
        data = getattr(response, "data", None)
        size = received[0] if sink is not None else (len(data) if data is not None else 0)
        data_in = f" data-in={size} B" if size or data is not None else ""
        write(
            f"{timestamp()} <- {name_of(Resp, response.code)} tid={transaction_id} params={_params(response.params)}"
            f"{data_in} {took:.1f} ms{_preview(data)}"
        )
        return response

    def logged_read_event(timeout_s: float) -> Any:
        event = read_event(timeout_s)
        if event is not None:
            write(f"{timestamp()} <- event {name_of(Event, event.code)} params={_params(event.params)}")
        return event

    transport.transaction = logged_transaction
    transport.read_event = logged_read_event
    return transport


class TrafficLogFile:
    """An append-only log file for `log_traffic`: each line written and flushed at once (a crash keeps it)."""

    def __init__(self, path: str, header: str = "") -> None:
        self.path = path
        self._file = open(path, "a", encoding="utf-8", buffering=1)  # noqa: SIM115 (kept open for the run)
        if header:
            self.write(f"{timestamp()} # {header}")

    def write(self, line: str) -> None:
        if not self._file.closed:
            self._file.write(line + "\n")

    def close(self) -> None:
        self._file.close()
