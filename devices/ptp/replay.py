"""Replaying real cameras: `gphoto2 --debug` logs parsed into the containers each side sent, and a responder that
answers a host stack's commands with what the recorded camera sent.

The logs (libgphoto2 2.4 and 2.5 formats) hold hexdumps of every USB read and
write. `load_trace` turns them into hexdump blocks (with their direction),
whole containers (reads reassembled across blocks, e.g. 512 + 10240 + 376
bytes) and transactions (command, data phases, response). `ReplayResponder`
plugs into the simulated USB backend in place of the simulated camera, so the
real `UsbTransport` and `Camera` run against a real body's answers.

`printed_*` read what libgphoto2 itself printed about the same data, the
independent reference the replay tests compare our decoding with.
"""

from __future__ import annotations

import re
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from mca.devices.ptp.codec import HEADER_BYTES, Container, ProtocolError, parse_header
from mca.devices.ptp.codes import ContainerType, Op, Resp
from mca.devices.ptp.framing import CommandFrame, DataEnd, DataHead, DataPiece, EventFrame, ResponseFrame, UsbFraming

IN, OUT, UNKNOWN = "in", "out", "?"
_HEX_LINE = re.compile(r"^([0-9a-fA-F]{4,8})  (.*)$")
_HEX_PAIR = re.compile(r"[0-9a-fA-F]{2}")
_COUNT = re.compile(r"[Hh]exdump of (\d+)")
_OUT_WORDS = re.compile(r"\b(Wrote|Writing)\b")
_IN_WORDS = re.compile(r"\b(Read|Reading|read)\b")


@dataclass(frozen=True)
class HexBlock:
    """One hexdump in the log: where it starts, which way the bytes went, the bytes, and whether all are there."""

    line: int
    direction: str
    data: bytes = field(repr=False)
    complete: bool = True


@dataclass(frozen=True)
class TraceContainer:
    line: int
    direction: str
    container: Container


@dataclass(frozen=True)
class RecordedTransaction:
    """One transaction as the log shows it; `command` is None for a camera reply whose command was cut away."""

    line: int
    command: Container | None
    data_out: bytes | None = field(default=None, repr=False)
    data_in: bytes | None = field(default=None, repr=False)
    response: Container | None = None

    @property
    def code(self) -> int | None:
        if self.command is not None:
            return self.command.code
        if self.response is not None:
            return None
        return None


@dataclass
class Trace:
    path: Path
    lines: list[str] = field(repr=False)
    blocks: list[HexBlock] = field(repr=False)
    containers: list[TraceContainer] = field(repr=False)
    transactions: list[RecordedTransaction] = field(repr=False)

    def data_in(self, code: int) -> list[tuple[int, bytes]]:
        """(log line, payload) of every camera-to-host data phase of operation `code`."""
        return [
            (c.line, c.container.payload)
            for c in self.containers
            if c.direction == IN and c.container.type == ContainerType.DATA and c.container.code == code
        ]


def _hex_bytes(rest: str) -> bytes:
    out = bytearray()
    for i in range(16):
        pair = rest[3 * i : 3 * i + 2]
        if not _HEX_PAIR.fullmatch(pair):
            break
        out.append(int(pair, 16))
    return bytes(out)


def _direction(lines: list[str], start: int) -> str:
    """Which way a hexdump went, from the log lines just before it (2.5: "Wrote"/"Read"; 2.4: "Writing"/"read")."""
    seen = 0
    i = start - 1
    while i >= 0 and seen < 4:
        text = lines[i]
        if text.strip():
            if _HEX_LINE.match(text):
                return UNKNOWN
            seen += 1
            if _OUT_WORDS.search(text):
                return OUT
            if _IN_WORDS.search(text):
                return IN
        i -= 1
    return UNKNOWN


def parse_hexdumps(text: str) -> list[HexBlock]:
    """Every hexdump block of a gphoto2 debug log, in order."""
    lines = text.splitlines()
    blocks: list[HexBlock] = []
    i = 0
    while i < len(lines):
        m = _HEX_LINE.match(lines[i])
        if not m or int(m.group(1), 16) != 0:
            i += 1
            continue
        start = i
        data = bytearray()
        expected_offset = 0
        while i < len(lines):
            m = _HEX_LINE.match(lines[i])
            if not m or int(m.group(1), 16) != expected_offset or (expected_offset == 0 and data):
                break
            chunk = _hex_bytes(m.group(2))
            data += chunk
            expected_offset += 16
            i += 1
            if len(chunk) < 16:
                break
        claimed = None
        for back in range(start - 1, max(-1, start - 3), -1):
            c = _COUNT.search(lines[back])
            if c:
                claimed = int(c.group(1))
                break
        if claimed is not None and claimed < len(data):
            del data[claimed:]  # a short last line whose text column reads as hex ("... 39 00 08 ... 422199")
        blocks.append(HexBlock(start + 1, _direction(lines, start), bytes(data), claimed in (None, len(data))))
    return blocks


def _infer_direction(data: bytes) -> str:
    try:
        header = parse_header(data[:HEADER_BYTES])
    except ProtocolError:
        return UNKNOWN
    return IN if header.type in (ContainerType.DATA, ContainerType.RESPONSE, ContainerType.EVENT) else OUT


def assemble_containers(blocks: list[HexBlock]) -> list[TraceContainer]:
    """Whole containers from the blocks, framed as the transports frame them (`framing.UsbFraming`): reads of one
    container across several blocks are joined, a block holding more than one container (a response read together
    with the end of a data phase) is split, and a broken header drops what that direction had buffered."""
    framings: dict[str, UsbFraming] = {}
    started: dict[str, int] = {}
    payloads: dict[str, tuple[DataHead, bytearray]] = {}
    out: list[TraceContainer] = []
    for block in blocks:
        direction = block.direction if block.direction != UNKNOWN else _infer_direction(block.data)
        if direction == UNKNOWN:
            continue
        framing = framings.setdefault(direction, UsbFraming())
        if framing.at_boundary:
            started[direction] = block.line
        framing.receive_data(block.data)
        while True:
            try:
                frame = framing.next_frame()
            except ProtocolError:
                framing.clear()
                payloads.pop(direction, None)
                break
            if frame is None:
                break
            container: Container | None = None
            if isinstance(frame, DataHead):
                payloads[direction] = (frame, bytearray())
            elif isinstance(frame, DataPiece):
                payloads[direction][1].extend(frame.data)
            elif isinstance(frame, DataEnd):
                head, payload = payloads.pop(direction)
                container = Container(ContainerType.DATA, head.code or 0, head.transaction_id, (), bytes(payload))
            elif isinstance(frame, CommandFrame | ResponseFrame | EventFrame):
                kind = {CommandFrame: ContainerType.COMMAND, ResponseFrame: ContainerType.RESPONSE}
                container = Container(
                    kind.get(type(frame), ContainerType.EVENT), frame.code, frame.transaction_id, frame.params
                )
            if container is not None:
                out.append(TraceContainer(started[direction], direction, container))
                started[direction] = block.line
    return out


def group_transactions(containers: list[TraceContainer]) -> list[RecordedTransaction]:
    """Commands with their data phases and responses, in log order."""
    out: list[RecordedTransaction] = []
    current: dict | None = None

    def flush() -> None:
        nonlocal current
        if current is not None:
            out.append(RecordedTransaction(**current))
            current = None

    for tc in containers:
        c = tc.container
        if tc.direction == OUT and c.type == ContainerType.COMMAND:
            flush()
            current = dict(line=tc.line, command=c)
            continue
        same = (
            current is not None
            and current["command"] is not None
            and current["command"].transaction_id == c.transaction_id
        )
        if not same:
            flush()
            current = dict(line=tc.line, command=None)
        assert current is not None
        if c.type == ContainerType.DATA:
            current["data_out" if tc.direction == OUT else "data_in"] = c.payload
        elif c.type == ContainerType.RESPONSE:
            current["response"] = c
            flush()
    flush()
    return out


def load_trace(path: Path | str) -> Trace:
    path = Path(path)
    text = path.read_text(encoding="utf-8", errors="replace")
    blocks = parse_hexdumps(text)
    containers = assemble_containers(blocks)
    return Trace(path, text.splitlines(), blocks, containers, group_transactions(containers))


# -- what libgphoto2 printed -------------------------------------------------------------------------------------


def _message(line: str) -> str:
    """The log message after "...(2): " (2.4 and 2.5 layouts)."""
    m = re.search(r"\(\d\):\s?(.*)$", line)
    return m.group(1) if m else line


@dataclass
class PrintedDeviceInfo:
    line: int
    manufacturer: str = ""
    model: str = ""
    device_version: str = ""
    serial_number: str = ""
    vendor_extension_id: int | None = None
    vendor_extension_version: int | None = None
    standard_version: int | None = None
    operations: list[int] = field(default_factory=list)
    events: list[int] = field(default_factory=list)
    properties: list[int] = field(default_factory=list)


def printed_device_infos(lines: list[str]) -> list[PrintedDeviceInfo]:
    """Each "Device info:" block libgphoto2 printed (values after its vendor-id fix-up)."""
    out: list[PrintedDeviceInfo] = []
    section = None
    for i, raw in enumerate(lines):
        msg = _message(raw)
        if msg.strip() == "Device info:":
            out.append(PrintedDeviceInfo(i + 1))
            section = None
            continue
        if not out or i + 1 - out[-1].line > 400:
            continue
        info = out[-1]
        stripped = msg.strip()
        for key, attr in (
            ("Manufacturer: ", "manufacturer"),
            ("Model: ", "model"),
            ("device version: ", "device_version"),
            ("serial number: ", "serial_number"),
        ):
            if stripped.startswith(key) and not getattr(info, attr):
                setattr(info, attr, stripped[len(key) :].strip("'"))
        if stripped.startswith("Vendor extension ID: "):
            info.vendor_extension_id = int(stripped.split(": ")[1], 16)
        elif stripped.startswith("Vendor extension version: "):
            info.vendor_extension_version = int(stripped.split(": ")[1])
        elif stripped.startswith("PTP Standard Version: "):
            info.standard_version = int(stripped.split(": ")[1])
        elif stripped.startswith("Supported operations"):
            section = "operations"
        elif stripped.startswith("Events Supported") or stripped.startswith("Events supported"):
            section = "events"
        elif stripped.startswith("Device Properties Supported") or stripped.startswith("Device properties"):
            section = "properties"
        else:
            m = re.match(r"^0x([0-9a-fA-F]{4})\b", stripped)
            if m and section:
                getattr(info, section).append(int(m.group(1), 16))
            elif section and stripped and not m:
                section = None
    return out


@dataclass(frozen=True)
class PrintedEvent:
    """One "event N: ..." decode line group: an info (value) or desc (allowed values) record, or an unknown code."""

    line: int
    index: int
    kind: str  # "info", "desc", "unknown"
    prop: int
    datasize: int | None = None
    current: str | None = None
    propxtype: int | None = None
    suppvals: tuple[int, ...] = ()


_EV = re.compile(r"^event (\d+): (.*)$")


def printed_events(lines: list[str], start: int, end: int) -> list[PrintedEvent]:
    """The EOS event records libgphoto2 decoded and printed between log lines `start` and `end` (1-based)."""
    records: dict[int, dict] = {}
    order: list[int] = []
    for n in range(max(0, start - 1), min(len(lines), end - 1)):
        m = _EV.match(_message(lines[n]).strip())
        if not m:
            continue
        idx, rest = int(m.group(1)), m.group(2)
        if idx in records and records[idx]["line"] < n + 1 - 2000:
            continue
        info = re.match(r"EOS prop ([0-9a-f]{4})( \(.*?\))? info record, datasize is (\d+)", rest)
        desc = re.match(r"EOS prop ([0-9a-f]{4})( \(.*?\))? desc record, datasize (\d+), propxtype (\d+)", rest)
        unknown = re.match(r"unknown EOS event ([0-9a-f]{4})", rest) or re.match(
            r"unhandled EOS event (\w+) \(size", rest
        )
        if info or desc or unknown:
            if idx in records:  # a new poll restarted the numbering
                break
            if info:
                records[idx] = dict(
                    line=n + 1, index=idx, kind="info", prop=int(info.group(1), 16), datasize=int(info.group(3))
                )
            elif desc:
                records[idx] = dict(
                    line=n + 1,
                    index=idx,
                    kind="desc",
                    prop=int(desc.group(1), 16),
                    datasize=int(desc.group(3)),
                    propxtype=int(desc.group(4)),
                    suppvals=[],
                )
            elif unknown:  # "unknown EOS event c1f6" gives the code; "unhandled EOS event PowerZoomInfoChanged" a name
                code = int(unknown.group(1), 16) if re.fullmatch(r"[0-9a-f]{4}", unknown.group(1)) else -1
                records[idx] = dict(line=n + 1, index=idx, kind="unknown", prop=code)
            order.append(idx)
            continue
        if idx not in records:
            continue
        cur = re.match(r"currentvalue of ([0-9a-f]{4}) is (.*)$", rest)
        sup = re.match(r"suppval\[(\d+)\] of ([0-9a-f]{4}) is 0x([0-9a-f]+)\.", rest)
        if cur:
            records[idx]["current"] = cur.group(2)
        elif sup:
            records[idx]["suppvals"].append(int(sup.group(3), 16))
    return [PrintedEvent(**{**records[i], "suppvals": tuple(records[i].get("suppvals", ()))}) for i in order]


@dataclass(frozen=True)
class PrintedObjectInfo:
    line: int
    filename: str
    fields: dict[str, int]


def printed_object_infos(lines: list[str]) -> list[PrintedObjectInfo]:
    """Each "ObjectInfo for 'NAME':" block libgphoto2 2.4 printed, with its numeric fields."""
    out: list[PrintedObjectInfo] = []
    for i, raw in enumerate(lines):
        m = re.match(r"ObjectInfo for '(.*)':$", _message(raw).strip())
        if not m:
            continue
        fields: dict[str, int] = {}
        for follow in lines[i + 1 : i + 24]:
            f = re.match(r"^(\w+): (0x[0-9a-fA-F]+|\d+)$", _message(follow).strip())
            if not f:
                if fields:
                    break
                continue
            fields[f.group(1)] = int(f.group(2), 0)
        out.append(PrintedObjectInfo(i + 1, m.group(1), fields))
    return out


# -- the responder -----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReplayReply:
    response: Container
    data: bytes | None = None


#: Answers made up where the log has none: reads of empty lists and the mode switches of a start-up/close.
_SYNTHESIZED_OK = {
    Op.OPEN_SESSION,
    Op.CLOSE_SESSION,
    Op.EOS_SET_REMOTE_MODE,
    Op.EOS_SET_EVENT_MODE,
    Op.EOS_KEEP_DEVICE_ON,
    Op.EOS_REMOTE_RELEASE_OFF,
    Op.EOS_AF_CANCEL,
    Op.EOS_SET_REQUEST_OLC_INFO_GROUP,
    Op.EOS_REQUEST_DEVICE_PROP_VALUE,
}
_EMPTY_EVENT_LIST = b"\x08\x00\x00\x00\x00\x00\x00\x00"
_EMPTY_ARRAY = b"\x00\x00\x00\x00"


class ReplayResponder:
    """Answers each command with the next recorded reply to the same operation (same parameters first).

    Recorded GetEvent replies are served in order, then empty lists. Operations the log never shows get a
    made-up answer (listed in `synthesized`): OK for mode switches, empty lists for GetEvent and
    GetObjectHandles, OperationNotSupported otherwise. `operations_log` keeps every (code, params) received.
    """

    def __init__(self, transactions: list[RecordedTransaction], *, serial_number: str | None = None) -> None:
        self.lock = threading.RLock()
        self._by_code: dict[int, list[RecordedTransaction]] = defaultdict(list)
        for t in transactions:
            if t.command is not None and t.response is not None:
                self._by_code[t.command.code].append(t)
        self._used: set[int] = set()
        self.operations_log: list[tuple[int, tuple[int, ...]]] = []
        self.synthesized: list[int] = []
        self.busy_responses = 0
        self.short_partial_bytes = 0
        self.serial_number = serial_number or "REPLAY"
        self._data_out_ops = {
            t.command.code
            for ts in self._by_code.values()
            for t in ts
            if t.command is not None and t.data_out is not None
        }
        self._data_out_ops |= {Op.SET_DEVICE_PROP_VALUE, Op.EOS_SET_DEVICE_PROP_VALUE_EX}
        self._model = "replayed camera"

    def expects_data_out(self, code: int) -> bool:
        return code in self._data_out_ops

    def device_info(self):  # the USB backend reads the model for its string descriptor
        from mca.devices.ptp.datasets import DeviceInfo, parse_device_info

        for t in self._by_code.get(Op.GET_DEVICE_INFO, []):
            if t.data_in:
                try:
                    return parse_device_info(t.data_in)
                except ProtocolError:
                    break
        return DeviceInfo(model=self._model)

    def disconnect(self) -> None:
        pass

    def take_std_events(self) -> list[Container]:
        return []

    def _next(self, cmd: Container) -> RecordedTransaction | None:
        candidates = self._by_code.get(cmd.code, [])
        for match_params in (True, False):
            for t in candidates:
                if id(t) in self._used:
                    continue
                if match_params and t.command is not None and t.command.params != cmd.params:
                    continue
                if cmd.code != Op.EOS_GET_EVENT and not match_params and cmd.code in (Op.EOS_REMOTE_RELEASE_ON,):
                    continue  # never answer a release with another release's recorded reply
                return t
        return None

    def handle(self, cmd: Container, data_out: bytes | None = None) -> ReplayReply:
        with self.lock:
            self.operations_log.append((cmd.code, cmd.params))
            tid = cmd.transaction_id
            t = self._next(cmd)
            if t is not None:
                self._used.add(id(t))
                assert t.response is not None
                resp = Container(ContainerType.RESPONSE, t.response.code, tid, t.response.params)
                return ReplayReply(resp, t.data_in)
            self.synthesized.append(cmd.code)
            if cmd.code == Op.EOS_GET_EVENT:
                return ReplayReply(Container(ContainerType.RESPONSE, Resp.OK, tid), _EMPTY_EVENT_LIST)
            if cmd.code == Op.GET_OBJECT_HANDLES:
                return ReplayReply(Container(ContainerType.RESPONSE, Resp.OK, tid), _EMPTY_ARRAY)
            if cmd.code in _SYNTHESIZED_OK:
                return ReplayReply(Container(ContainerType.RESPONSE, Resp.OK, tid))
            return ReplayReply(Container(ContainerType.RESPONSE, Resp.OPERATION_NOT_SUPPORTED, tid))
