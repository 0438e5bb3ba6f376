"""Fault injection for the simulated EOS 70D: disconnects mid-download, stalls, DeviceBusy, short reads, corrupt containers."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FaultPlan:
    """What should go wrong, armed on a backend or PTP/IP server; each fault fires once unless noted.

    - `disconnect_after_in_bytes`: the camera vanishes after sending this many more bytes in a data phase
      of GetPartialObject/GetObject (a cable pulled mid-download).
    - `stall_op`: the next command with this operation code gets no reply at all (the host times out).
    - `busy_count`: the next N operations (other than GetEvent) answer DeviceBusy.
    - `short_read_bytes`: every GetPartialObject sends at most this many bytes (persistent while set).
    - `corrupt_op`: the response to the next command with this code has a broken container header.
    - `coalesce_response`: the response shares the bulk transfer with the end of the data phase (persistent).
    """

    disconnect_after_in_bytes: int | None = None
    stall_op: int | None = None
    busy_count: int = 0
    short_read_bytes: int = 0
    corrupt_op: int | None = None
    coalesce_response: bool = False


DOWNLOAD_OPS = (0x1009, 0x101B, 0x9104, 0x9107)


def corrupt_container(raw: bytes) -> bytes:
    """A response container whose length field is impossible (shorter than its header)."""
    return b"\x05\x00\x00\x00" + raw[4:]
