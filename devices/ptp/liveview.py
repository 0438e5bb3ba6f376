"""EOS live view: the GetViewFinderData (0x9153) data phase, a list of blocks, packed and parsed by pure functions.

Each block is u32 length (header included), u32 type, then data. Type 1 is the
live-view JPEG (11 on newer bodies, 9 a movie-mode raw frame); other types carry
overlay information and are kept as they are. libgphoto2's capture-preview reads
the same layout (read for facts).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from mca.devices.ptp.codec import ProtocolError

BLOCK_JPEG = 1
BLOCK_JPEG_NEW = 11
BLOCK_MOVIE = 9
JPEG_BLOCKS = (BLOCK_JPEG, BLOCK_JPEG_NEW)
#: A live-view frame is a few hundred kB; anything near this is not one.
MAX_VIEWFINDER_BYTES = 8 * 1024 * 1024


@dataclass(frozen=True)
class ViewfinderData:
    """One GetViewFinderData answer: the JPEG (empty when the body sent none) and the other blocks."""

    jpeg: bytes = field(repr=False)
    other_blocks: tuple[tuple[int, bytes], ...] = field(default=(), repr=False)


def pack_viewfinder_data(jpeg: bytes, other_blocks: tuple[tuple[int, bytes], ...] = ()) -> bytes:
    blocks = [(BLOCK_JPEG, jpeg), *other_blocks]
    return b"".join(struct.pack("<II", 8 + len(data), kind) + data for kind, data in blocks)


def parse_viewfinder_data(buf: bytes | bytearray | memoryview) -> ViewfinderData:
    """The blocks of a GetViewFinderData data phase; a block claiming more than is left is a `ProtocolError`."""
    if len(buf) > MAX_VIEWFINDER_BYTES:
        raise ProtocolError(f"viewfinder data of {len(buf)} bytes exceeds the {MAX_VIEWFINDER_BYTES}-byte limit")
    data = bytes(buf)
    pos = 0
    jpeg = b""
    others: list[tuple[int, bytes]] = []
    while pos < len(data):
        if len(data) - pos < 8:
            raise ProtocolError(f"viewfinder block header truncated at offset {pos}")
        length, kind = struct.unpack_from("<II", data, pos)
        if length < 8 or length > len(data) - pos:
            raise ProtocolError(f"viewfinder block at offset {pos} claims {length} bytes, {len(data) - pos} left")
        body = data[pos + 8 : pos + length]
        if kind in JPEG_BLOCKS and not jpeg:
            jpeg = body
        else:
            others.append((kind, body))
        pos += length
    return ViewfinderData(jpeg, tuple(others))
