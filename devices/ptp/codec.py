"""PTP containers, strings and arrays: pure pack/parse functions with every length checked against bounds.

Nothing here does I/O. Parsers take bytes and return values or raise
`ProtocolError`; they never allocate more than the input justifies.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from mca.devices.ptp.codes import ContainerType

HEADER_BYTES = 12
MAX_PARAMS = 5
MAX_EVENT_PARAMS = 3
#: Largest container the engine accepts by default (a data phase is streamed, this bounds the header's claim).
MAX_CONTAINER_BYTES = 0xFFFFFFFF
#: Largest dataset (DeviceInfo, ObjectInfo, event list, ...) parsed into memory.
MAX_DATASET_BYTES = 16 * 1024 * 1024

_HEADER = struct.Struct("<IHHI")
_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class ProtocolError(Exception):
    """The peer sent bytes that break the PTP rules (bad length, truncated dataset, wrong phase)."""


@dataclass(frozen=True)
class Container:
    """One PTP container: command, data, response or event."""

    type: int
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    payload: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class ContainerHeader:
    length: int
    type: int
    code: int
    transaction_id: int

    @property
    def payload_bytes(self) -> int:
        return self.length - HEADER_BYTES


def _check_params(params: tuple[int, ...] | list[int], limit: int) -> None:
    if len(params) > limit:
        raise ProtocolError(f"{len(params)} parameters, at most {limit} allowed")
    for p in params:
        if not 0 <= p <= 0xFFFFFFFF:
            raise ProtocolError(f"parameter {p} does not fit in u32")


def pack_params_container(kind: int, code: int, transaction_id: int, params: tuple[int, ...] | list[int] = ()) -> bytes:
    """A command, response or event container."""
    limit = MAX_EVENT_PARAMS if kind == ContainerType.EVENT else MAX_PARAMS
    _check_params(params, limit)
    length = HEADER_BYTES + 4 * len(params)
    return _HEADER.pack(length, kind, code, transaction_id) + struct.pack(f"<{len(params)}I", *params)


def pack_command(code: int, transaction_id: int, params: tuple[int, ...] | list[int] = ()) -> bytes:
    return pack_params_container(ContainerType.COMMAND, code, transaction_id, params)


def pack_response(code: int, transaction_id: int, params: tuple[int, ...] | list[int] = ()) -> bytes:
    return pack_params_container(ContainerType.RESPONSE, code, transaction_id, params)


def pack_event(code: int, transaction_id: int, params: tuple[int, ...] | list[int] = ()) -> bytes:
    return pack_params_container(ContainerType.EVENT, code, transaction_id, params)


def pack_data_header(code: int, transaction_id: int, payload_bytes: int) -> bytes:
    """The 12-byte header of a data container whose payload follows separately."""
    length = HEADER_BYTES + payload_bytes
    if length > 0xFFFFFFFF:
        raise ProtocolError(f"data phase of {payload_bytes} bytes does not fit a USB container")
    return _HEADER.pack(length, ContainerType.DATA, code, transaction_id)


def pack_data(code: int, transaction_id: int, payload: bytes) -> bytes:
    return pack_data_header(code, transaction_id, len(payload)) + bytes(payload)


def parse_header(
    buf: bytes | bytearray | memoryview, max_container_bytes: int = MAX_CONTAINER_BYTES
) -> ContainerHeader:
    """Parse the 12-byte container header and check its claimed length."""
    if len(buf) < HEADER_BYTES:
        raise ProtocolError(f"container header needs {HEADER_BYTES} bytes, got {len(buf)}")
    length, kind, code, tid = _HEADER.unpack_from(buf, 0)
    if kind not in (1, 2, 3, 4):
        raise ProtocolError(f"unknown container type {kind}")
    if length < HEADER_BYTES:
        raise ProtocolError(f"container length {length} is shorter than its header")
    if length > max_container_bytes:
        raise ProtocolError(f"container claims {length} bytes, more than the {max_container_bytes} allowed")
    if kind != ContainerType.DATA:
        limit = MAX_EVENT_PARAMS if kind == ContainerType.EVENT else MAX_PARAMS
        extra = length - HEADER_BYTES
        if extra % 4 or extra // 4 > limit:
            raise ProtocolError(
                f"{ContainerType(kind).name.lower()} container of {length} bytes is not a header plus at most {limit} u32 parameters"
            )
    return ContainerHeader(length, kind, code, tid)


def parse_container(buf: bytes | bytearray | memoryview, max_container_bytes: int = MAX_CONTAINER_BYTES) -> Container:
    """Parse one complete container; the buffer must hold exactly its claimed length."""
    header = parse_header(buf, max_container_bytes)
    if len(buf) != header.length:
        raise ProtocolError(f"container claims {header.length} bytes but {len(buf)} were given")
    body = bytes(buf[HEADER_BYTES : header.length])
    if header.type == ContainerType.DATA:
        return Container(header.type, header.code, header.transaction_id, (), body)
    params = struct.unpack(f"<{len(body) // 4}I", body)
    return Container(header.type, header.code, header.transaction_id, params, b"")


def is_older_transaction(got: int, expected: int) -> bool:
    """Whether transaction id `got` comes before `expected` (ids count up by one and wrap at 2**32)."""
    return 0 < (expected - got) % 2**32 < 2**31


def parse_params(body: bytes | memoryview, limit: int = MAX_PARAMS) -> tuple[int, ...]:
    """u32 parameters from a body whose length must be a multiple of 4."""
    if len(body) % 4 or len(body) // 4 > limit:
        raise ProtocolError(f"parameter block of {len(body)} bytes is not at most {limit} u32 values")
    return struct.unpack(f"<{len(body) // 4}I", body)


class Reader:
    """A bounded cursor over a dataset: every read checks the bytes that remain."""

    __slots__ = ("_buf", "end", "pos")

    def __init__(self, buf: bytes | bytearray | memoryview, start: int = 0, end: int | None = None) -> None:
        self._buf = bytes(buf) if not isinstance(buf, bytes) else buf
        self.pos = start
        self.end = len(self._buf) if end is None else min(end, len(self._buf))

    @property
    def remaining(self) -> int:
        return self.end - self.pos

    def _need(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > self.end:
            raise ProtocolError(
                f"truncated dataset: {what} needs {n} bytes at offset {self.pos}, {self.remaining} left"
            )

    def u8(self) -> int:
        self._need(1, "u8")
        v = self._buf[self.pos]
        self.pos += 1
        return v

    def u16(self) -> int:
        self._need(2, "u16")
        (v,) = _U16.unpack_from(self._buf, self.pos)
        self.pos += 2
        return v

    def u32(self) -> int:
        self._need(4, "u32")
        (v,) = _U32.unpack_from(self._buf, self.pos)
        self.pos += 4
        return v

    def u64(self) -> int:
        self._need(8, "u64")
        (v,) = _U64.unpack_from(self._buf, self.pos)
        self.pos += 8
        return v

    def scalar(self, fmt: str) -> int:
        size = struct.calcsize("<" + fmt)
        self._need(size, fmt)
        (v,) = struct.unpack_from("<" + fmt, self._buf, self.pos)
        self.pos += size
        return v

    def take(self, n: int) -> bytes:
        self._need(n, "block")
        v = self._buf[self.pos : self.pos + n]
        self.pos += n
        return v

    def string(self) -> str:
        """PTP string: u8 count of UTF-16 units including the NUL, then UTF-16LE."""
        count = self.u8()
        if count == 0:
            return ""
        raw = self.take(2 * count)
        text = raw.decode("utf-16-le", errors="replace")
        nul = text.find("\x00")
        return text if nul < 0 else text[:nul]

    def array(self, fmt: str) -> tuple[int, ...]:
        """PTP array: u32 count then items; the count is checked against the bytes left before allocating."""
        count = self.u32()
        size = struct.calcsize("<" + fmt)
        if count * size > self.remaining:
            raise ProtocolError(f"array of {count} items of {size} bytes does not fit the {self.remaining} bytes left")
        values = struct.unpack_from(f"<{count}{fmt}", self._buf, self.pos)
        self.pos += count * size
        return values

    def cstring_ascii(self, max_bytes: int | None = None) -> str:
        """NUL-terminated ASCII (the EOS event file names); stops at the end of the record."""
        limit = self.end if max_bytes is None else min(self.end, self.pos + max_bytes)
        raw = self._buf[self.pos : limit]
        nul = raw.find(b"\x00")
        if nul >= 0:
            raw = raw[:nul]
        self.pos = min(limit, self.pos + len(raw) + 1)
        return raw.decode("ascii", errors="replace")


def pack_string(text: str) -> bytes:
    """PTP string; at most 254 UTF-16 units plus the NUL."""
    if not text:
        return b"\x00"
    encoded = text.encode("utf-16-le") + b"\x00\x00"
    units = len(encoded) // 2
    if units > 255:
        raise ProtocolError(f"string of {units} UTF-16 units exceeds the PTP limit of 255")
    return bytes([units]) + encoded


def pack_array(fmt: str, values: tuple[int, ...] | list[int]) -> bytes:
    return _U32.pack(len(values)) + struct.pack(f"<{len(values)}{fmt}", *values)


def u16(v: int) -> bytes:
    return _U16.pack(v)


def u32(v: int) -> bytes:
    return _U32.pack(v)


def u64(v: int) -> bytes:
    return _U64.pack(v)
