"""`Camera`: a PTP session over any transport, with the Canon EOS capture sequence, downloads and named properties.

Behaviour follows what real EOS bodies need (libgphoto2's camlibs/ptp2, read for
facts): the Canon extension id is restored when a body reports Microsoft's 6;
start-up polls until the settings the body lists have arrived; the shutter
release is sent once per shot and never repeated (`trigger` then
`wait_for_capture`); only operations in `policy.SAFE_TO_REPEAT` are retried;
a half press is always released; the autofocus result is read between half and
full press; shots in camera RAM are announced capacity for, downloaded (both
files of RAW+JPEG) and confirmed; closing restores the capture destination and
the camera's display.
"""

from __future__ import annotations

import struct
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import BinaryIO

from mca.devices.ptp.codec import ProtocolError, Reader
from mca.devices.ptp.codes import (
    ALL_STORAGES,
    CANON_VENDOR_EXTENSION_ID,
    CANON_VENDOR_ID,
    CAPTURE_DESTINATION_CARD,
    CAPTURE_DESTINATION_RAM,
    EVF_OUTPUT_PC,
    MICROSOFT_VENDOR_EXTENSION_ID,
    MTP_VENDOR_EXTENSION_ID,
    VIEWFINDER_DATA_PARAM,
    EosProp,
    Event,
    ObjectFormat,
    Op,
    Resp,
    name_of,
)
from mca.devices.ptp.datasets import (
    DeviceInfo,
    DevicePropDesc,
    EosDeviceInfoEx,
    ObjectInfo,
    StorageInfo,
    pack_prop_value,
    parse_device_info,
    parse_eos_device_info_ex,
    parse_object_info,
    parse_prop_desc,
    parse_storage_ids,
    parse_storage_info,
)
from mca.devices.ptp.events import (
    EosAvailListChanged,
    EosCameraStatus,
    EosEvent,
    EosObjectAdded,
    EosObjectRemoved,
    EosPropValueChanged,
    EosRequestObjectTransfer,
    EosUndecodedRecord,
    EosUnknownEvent,
    FocusInfo,
    image_format_of,
    pack_image_format,
    parse_eos_events,
    parse_focus_info_ex,
)
from mca.devices.ptp.liveview import parse_viewfinder_data
from mca.devices.ptp.policy import DEFAULT_POLICY, PtpPolicy, is_safe_to_repeat
from mca.devices.ptp.properties import (
    CAPTURE_TARGET_ALIASES,
    EOS_IMAGE_FORMAT_NAMES,
    code_for,
    image_format_name,
    spec_for,
)
from mca.devices.ptp.transport import DeviceDisconnected, Response, Transport, TransportError

#: The largest file the host accepts from a camera (a 70D RAW is about 25 MB).
MAX_OBJECT_BYTES = 2 * 1024**3
ONE_SHOT_AF = 0
MANUAL_FOCUS = 3
#: libgphoto2 announces this much free space on the host when shots go to camera RAM (PCHDDCapacity).
HOST_CAPACITY_PARAMS = (0x0FFFFFFF, 0x00001000, 0x00000001)
#: The EOS props start-up waits for, when the body lists them in GetDeviceInfoEx.
SETTLE_PROPS = (EosProp.CAPTURE_DESTINATION, EosProp.IMAGE_FORMAT, EosProp.FOCUS_MODE, EosProp.AVAILABLE_SHOTS)
#: Owner, Artist, Copyright and SerialNumber arrive only when asked for (RequestDevicePropValue), in a later poll.
REQUESTED_PROPS = (EosProp.OWNER, EosProp.ARTIST, EosProp.COPYRIGHT, EosProp.SERIAL_NUMBER)
OLC_INFO_ALL = 0x00001FFF
MAX_ANOMALIES = 200
RELEASE_ERRORS = {
    1: "could not focus (try manual focus, more light, or a textured target)",
    3: "mirror lock-up is enabled (turn it off in the camera menu)",
    7: "the memory card is full",
    8: "the memory card is write-protected",
}

ProgressFn = Callable[[int, int], None]


class PtpError(Exception):
    """The camera answered an operation with a response code other than OK."""

    def __init__(self, device: str, op: int, code: int, hint: str = "") -> None:
        self.device, self.op, self.code = device, op, code
        message = f"{device}: {name_of(Op, op)} answered {name_of(Resp, code)}"
        super().__init__(message + (f"; {hint}" if hint else ""))


class DeviceBusyError(PtpError):
    """The camera is busy (writing to the card, its RAM buffer full, autofocus running)."""


class CameraNotReady(DeviceBusyError):
    """The camera stayed busy before a release; nothing was sent, so trying again later is safe."""


class CaptureError(Exception):
    """A capture did not produce a file."""


class ReleaseRefused(CaptureError):
    """The camera refused the release (busy, no focus, card full): it took no picture. Not retried."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


class ReleaseUncertain(CaptureError):
    """The link failed while the shutter command was out: the camera may have taken a picture.

    `ticket` lets `wait_for_capture` (on this or a reconnected camera) find the file without releasing again.
    """

    def __init__(self, message: str, ticket: CaptureTicket) -> None:
        super().__init__(message)
        self.ticket = ticket


class PropertyNotReported(LookupError):
    """The camera has not reported a property (not on this body, or not yet after the start-up wait)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "property not reported"


@dataclass(frozen=True)
class CapturedObject:
    """A new file the camera made, on its card or waiting in its RAM."""

    handle: int
    filename: str
    size_bytes: int
    object_format: int
    storage_id: int
    in_ram: bool


@dataclass(frozen=True)
class CaptureTicket:
    """What the host knew when it released the shutter: enough to find the new file(s) afterwards."""

    serial_number: str
    card_handles: frozenset[int] | None  # the card before the release (None when shots go to RAM)
    files_expected: int
    in_ram: bool
    released_at: float = field(default_factory=time.monotonic)


@dataclass(frozen=True)
class PropertyValue:
    name: str
    value: str
    allowed: tuple[str, ...]
    code: int


def effective_device_info(wire: DeviceInfo, usb_vendor_id: int | None = None) -> DeviceInfo:
    """DeviceInfo as this stack uses it: a Canon body reporting Microsoft's (6) or MTP's extension id gets Canon's.

    EOS 70D, 60D, 600D, 100D, R10 ... send 6 on the wire; libgphoto2 restores 0xB from the USB vendor id or,
    over PTP/IP, from the manufacturer name ("Canon Inc.", "Canon.Inc").
    """
    canon = usb_vendor_id == CANON_VENDOR_ID or "canon" in wire.manufacturer.lower()
    if canon and wire.vendor_extension_id in (MICROSOFT_VENDOR_EXTENSION_ID, MTP_VENDOR_EXTENSION_ID):
        return replace(wire, vendor_extension_id=CANON_VENDOR_EXTENSION_ID)
    return wire


class Camera:
    """One open PTP session. Not thread-safe: drive it from one thread."""

    def __init__(self, transport: Transport, policy: PtpPolicy = DEFAULT_POLICY) -> None:
        self.transport = transport
        self.policy = policy
        self.name = transport.name
        self._tid = 0
        self.session_open = False
        self.wire_info: DeviceInfo = DeviceInfo()
        self.info: DeviceInfo = DeviceInfo()
        self.info_ex: EosDeviceInfoEx | None = None
        self._eos_values: dict[int, EosPropValueChanged] = {}
        self._eos_allowed: dict[int, EosAvailListChanged] = {}
        self._pending: list[EosEvent] = []  # object events polled but not yet claimed by a capture or wait
        self._late: list[EosEvent] = []  # events recovered from late (stale) GetEvent replies
        self.unclaimed: list[CapturedObject] = []  # files that appeared without our release (shutter button)
        self._card_handles: set[int] | None = None
        self._claimed: set[tuple[int, bool]] = set()  # (handle, in RAM) already handed out as new files
        self._events_lost = False  # a GetEvent reply went missing: object events may have been lost
        self._last_keep_alive = time.monotonic()
        self.camera_status = 0
        self.focus: FocusInfo | None = None
        self._focus_seen = 0
        self.anomalies: list[str] = []  # unexpected things the body did, for `mca camera doctor`
        self.initial_capture_destination: int | None = None
        self._live_view_restore: int | None = None
        self.operations_sent: deque[int] = deque(maxlen=10_000)
        self.poll_sizes: list[int] = []  # records per GetEvent poll, for the first 64 polls (start-up)
        transport.on_stale_data = self._on_stale_data

    # -- session ---------------------------------------------------------
    @classmethod
    def open(cls, transport: Transport, session_id: int = 1, *, policy: PtpPolicy = DEFAULT_POLICY) -> Camera:
        """OpenSession (retried with a device reset after I/O failures), GetDeviceInfo, and the EOS start-up."""
        cam = cls(transport, policy)
        try:
            cam._open_session(session_id)
            cam.wire_info = parse_device_info(cam._data(Op.GET_DEVICE_INFO))
            cam.info = effective_device_info(cam.wire_info, transport.usb_vendor_id)
            if cam.is_eos:
                cam._prepare_eos()
        except BaseException:
            transport.close()
            raise
        return cam

    def _open_session(self, session_id: int) -> None:
        last: Exception | None = None
        for attempt in range(self.policy.open_session_tries):
            try:
                resp = self._call(
                    Op.OPEN_SESSION,
                    (session_id,),
                    check=False,
                    new_session=True,
                    timeout_s=self.policy.start_timeout_s,
                    repeat=False,
                )
            except DeviceDisconnected:
                raise
            except (TransportError, ProtocolError) as exc:
                last = exc
                self.transport.reset_device()  # libgphoto2 "whacks" the device and tries again
                continue
            if resp.code in (Resp.OK, Resp.SESSION_ALREADY_OPEN):  # libgphoto2 accepts an open session
                self.session_open = True
                return
            if resp.code == Resp.INVALID_TRANSACTION_ID and attempt + 1 < self.policy.open_session_tries:
                self.transport.reset_device()
                continue
            raise PtpError(self.name, Op.OPEN_SESSION, resp.code, "switch the camera off and on")
        raise TransportError(f"{self.name}: could not open a session: {last}; switch the camera off and on")

    def _prepare_eos(self) -> None:
        """libgphoto2's EOS start-up: remote and event mode, OLC info, the initial event dump, the settings."""
        self._call(Op.EOS_SET_REMOTE_MODE, (1,))
        self._call(Op.EOS_SET_EVENT_MODE, (1,))
        if self.info.supports(Op.EOS_SET_REQUEST_OLC_INFO_GROUP):
            self._call(Op.EOS_SET_REQUEST_OLC_INFO_GROUP, (OLC_INFO_ALL,), check=False)
        self.drain_events()
        requested = []
        if self.info.supports(Op.EOS_REQUEST_DEVICE_PROP_VALUE):
            for prop in REQUESTED_PROPS:  # a body without one answers GeneralError: log, go on
                resp = self._call(Op.EOS_REQUEST_DEVICE_PROP_VALUE, (prop,), check=False)
                if resp.code == Resp.OK:
                    requested.append(prop)
                else:
                    self.anomalies.append(f"RequestDevicePropValue(0x{prop:04X}) answered {name_of(Resp, resp.code)}")
        if self.info.supports(Op.EOS_GET_DEVICE_INFO_EX):
            self.info_ex = parse_eos_device_info_ex(self._data(Op.EOS_GET_DEVICE_INFO_EX))
        self.settle((*SETTLE_PROPS, *requested))
        current = self._eos_values.get(EosProp.CAPTURE_DESTINATION)
        self.initial_capture_destination = current.value if current else None

    @property
    def is_canon(self) -> bool:
        return self.info.vendor_extension_id == CANON_VENDOR_EXTENSION_ID

    @property
    def is_eos(self) -> bool:
        return (
            self.is_canon
            and self.info.supports(Op.EOS_GET_EVENT)
            and (self.info.supports(Op.EOS_REMOTE_RELEASE) or self.info.supports(Op.EOS_REMOTE_RELEASE_ON))
        )

    @property
    def serial_number(self) -> str:
        return self.info.serial_number

    def close(self) -> None:
        """libgphoto2's EOS close: AF cancel, the capture destination restored, events drained, remote mode
        0 then 1 (which turns the camera's display back on), event mode 0; then CloseSession."""
        try:
            if self.session_open and self.is_eos:
                for step in (self._stop_live_view_quietly, self._restore_capture_destination):
                    step()
                if self.info.supports(Op.EOS_AF_CANCEL):
                    self._call(Op.EOS_AF_CANCEL, check=False, repeat=False)
                self.poll_events()
                self._call(Op.EOS_SET_REMOTE_MODE, (0,), check=False, repeat=False)
                self._call(Op.EOS_SET_REMOTE_MODE, (1,), check=False, repeat=False)
                self._call(Op.EOS_SET_EVENT_MODE, (0,), check=False, repeat=False)
            if self.session_open:
                self._call(Op.CLOSE_SESSION, check=False, repeat=False)
        except (TransportError, ProtocolError, PtpError):
            pass
        finally:
            self.session_open = False
            self.transport.close()

    def _restore_capture_destination(self) -> None:
        current = self._eos_values.get(EosProp.CAPTURE_DESTINATION)
        wanted = self.initial_capture_destination
        if wanted is not None and current is not None and current.value != wanted:
            self._set_eos_u32(EosProp.CAPTURE_DESTINATION, wanted, check=False)

    def __enter__(self) -> Camera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transactions ----------------------------------------------------
    def _next_tid(self, new_session: bool) -> int:
        if new_session:
            self._tid = 0
            return 0
        self._tid = (self._tid + 1) & 0xFFFFFFFF or 1
        return self._tid

    def _call(
        self,
        op: int,
        params: tuple[int, ...] = (),
        *,
        data_out: bytes | None = None,
        sink: Callable[[memoryview], None] | None = None,
        sink_reset: Callable[[], None] | None = None,
        max_data_bytes: int = 16 * 1024 * 1024,
        check: bool = True,
        new_session: bool = False,
        timeout_s: float | None = None,
        repeat: bool | None = None,
    ) -> Response:
        """One transaction; operations safe to repeat are retried after DeviceBusy and after link faults.

        A streaming `sink` is retried only when `sink_reset` can undo what it received.
        """
        safe = (is_safe_to_repeat(op) if repeat is None else repeat) and (sink is None or sink_reset is not None)
        timeout = self.policy.transaction_timeout_s if timeout_s is None else timeout_s
        busy_tries = link_tries = 0
        while True:
            tid = self._next_tid(new_session or not self.session_open)
            self.operations_sent.append(op)
            try:
                resp = self.transport.transaction(
                    op,
                    tid,
                    tuple(params),
                    data_out=data_out,
                    sink=sink,
                    max_data_bytes=max_data_bytes,
                    timeout_s=timeout,
                )
            except DeviceDisconnected:
                self._mark_events_lost(op)
                raise
            except (ProtocolError, TransportError) as exc:
                self._mark_events_lost(op)
                self._recover(tid)
                if safe and link_tries < self.policy.transient_retries and self.transport.can_resume:
                    link_tries += 1
                    if sink_reset is not None:
                        sink_reset()
                    continue
                if isinstance(exc, ProtocolError):
                    raise ProtocolError(f"{self.name}: {name_of(Op, op)}: {exc}") from exc
                raise
            finally:
                self._absorb_late_events()
            if resp.code == Resp.DEVICE_BUSY and safe and check and busy_tries < self.policy.busy_retries:
                time.sleep(min(self.policy.busy_backoff_max_s, self.policy.busy_backoff_s * 2**busy_tries))
                busy_tries += 1
                if sink_reset is not None:
                    sink_reset()
                continue
            if check and resp.code != Resp.OK:
                cls = DeviceBusyError if resp.code == Resp.DEVICE_BUSY else PtpError
                hint = (
                    "wait for the camera to finish writing, or download the shots waiting in its RAM"
                    if resp.code == Resp.DEVICE_BUSY
                    else ""
                )
                raise cls(self.name, op, resp.code, hint)
            return resp

    def _mark_events_lost(self, op: int) -> None:
        """A GetEvent reply went missing: object events may be gone, and the status word is unknown again
        (libgphoto2 starts from "unknown" too); the card is compared with the snapshot instead."""
        if op == Op.EOS_GET_EVENT:
            self._events_lost = True
            self.camera_status = -1

    def _recover(self, tid: int) -> None:
        try:
            self.transport.recover(tid)
        except DeviceDisconnected:
            raise
        except (TransportError, ProtocolError):
            pass

    def _data(self, op: int, params: tuple[int, ...] = (), max_data_bytes: int = 16 * 1024 * 1024) -> bytes:
        resp = self._call(op, params, max_data_bytes=max_data_bytes)
        if resp.data is None:
            raise ProtocolError(f"{self.name}: {name_of(Op, op)} answered OK without its data phase")
        return resp.data

    def _on_stale_data(self, code: int, _tid: int, payload: bytes) -> None:
        """A GetEvent reply that came after we gave up on it: keep its events (a new file may be among them)."""
        if code != Op.EOS_GET_EVENT:
            return
        try:
            self._late.extend(parse_eos_events(payload))
        except ProtocolError:
            pass

    def _absorb_late_events(self) -> None:
        if self._late:
            late, self._late = self._late, []
            self._note_events(late)

    # -- storage and objects ---------------------------------------------
    def storage_ids(self) -> list[int]:
        return list(parse_storage_ids(self._data(Op.GET_STORAGE_IDS)))

    def storages(self) -> dict[int, StorageInfo]:
        out = {}
        for sid in self.storage_ids():
            if sid & 0xFFFF == 0:  # an empty slot (no card): GetStorageInfo would fail
                continue
            out[sid] = parse_storage_info(self._data(Op.GET_STORAGE_INFO, (sid,)))
        return out

    def object_handles(self, storage_id: int = ALL_STORAGES, parent: int = 0) -> list[int]:
        r = Reader(self._data(Op.GET_OBJECT_HANDLES, (storage_id, 0, parent), max_data_bytes=4 * 1024 * 1024))
        return list(r.array("I"))

    def object_info(self, handle: int) -> ObjectInfo:
        return parse_object_info(self._data(Op.GET_OBJECT_INFO, (handle,)))

    def files(self) -> list[tuple[int, ObjectInfo]]:
        """Every non-folder object on every storage."""
        out = []
        for handle in self.object_handles():
            info = self.object_info(handle)
            if info.object_format != ObjectFormat.ASSOCIATION:
                out.append((handle, info))
        return out

    def delete(self, handle: int) -> None:
        self._call(Op.DELETE_OBJECT, (handle,), repeat=False)
        if self._card_handles is not None:
            self._card_handles.discard(handle)

    def download(
        self,
        handle: int,
        size_bytes: int,
        out: BinaryIO,
        *,
        block_bytes: int | None = None,
        progress: ProgressFn | None = None,
    ) -> int:
        """Copy an object into `out` in GetPartialObject blocks; returns the bytes written (== size_bytes).

        Each block is collected first and written once complete, so a block that fails (stall, timeout,
        busy) is fetched again without duplicating bytes in `out`.
        """
        if not 0 <= size_bytes <= MAX_OBJECT_BYTES:
            raise ProtocolError(f"{self.name}: object size {size_bytes} is outside 0..{MAX_OBJECT_BYTES}")
        block_bytes = block_bytes or self.policy.download_block_bytes
        op = (
            Op.EOS_GET_PARTIAL_OBJECT
            if self.is_eos and self.info.supports(Op.EOS_GET_PARTIAL_OBJECT)
            else Op.GET_PARTIAL_OBJECT
        )
        block = bytearray(min(block_bytes, max(1, size_bytes)))  # one buffer, reused for every block
        view = memoryview(block)
        filled = 0

        def sink(piece: memoryview) -> None:
            nonlocal filled
            end = filled + len(piece)
            if end > len(block):
                raise ProtocolError(f"{self.name}: GetPartialObject sent more than the {len(block)} bytes asked for")
            view[filled:end] = piece
            filled = end

        def reset() -> None:
            nonlocal filled
            filled = 0

        done = 0
        while done < size_bytes:
            want = min(block_bytes, size_bytes - done)
            reset()
            resp = self._call(op, (handle, done, want), sink=sink, sink_reset=reset, max_data_bytes=want)
            got = filled
            if got == 0:
                raise ProtocolError(f"{self.name}: GetPartialObject at offset {done} returned no data")
            if resp.params and resp.params[0] != got and op == Op.GET_PARTIAL_OBJECT:
                raise ProtocolError(f"{self.name}: GetPartialObject said {resp.params[0]} bytes but sent {got}")
            out.write(view[:got])
            done += got
            if progress is not None:
                progress(done, size_bytes)
        return done

    def transfer_complete(self, handle: int) -> None:
        """Tell an EOS body that a RAM shot is safely on the host, freeing its buffer."""
        if self.is_eos:
            resp = self._call(Op.EOS_TRANSFER_COMPLETE, (handle,), check=False)
            if resp.code not in (Resp.OK, Resp.INVALID_OBJECT_HANDLE):  # a repeat after a lost reply: done
                raise PtpError(self.name, Op.EOS_TRANSFER_COMPLETE, resp.code)

    # -- events ----------------------------------------------------------
    def poll_events(self) -> list[EosEvent]:
        """One EOS GetEvent: returns the records and updates the property cache (late records first)."""
        events = self._late + parse_eos_events(self._data(Op.EOS_GET_EVENT))
        self._late = []
        if len(self.poll_sizes) < 64:
            self.poll_sizes.append(len(events))
        self._note_events(events)
        return events

    def drain_events(self, max_polls: int = 64) -> list[EosEvent]:
        """Poll until the camera reports nothing more (libgphoto2 does the same before a capture)."""
        out: list[EosEvent] = []
        for _ in range(max_polls):
            events = self.poll_events()
            out += events
            if not events:
                break
        return out

    def _note_events(self, events: list[EosEvent]) -> None:
        for e in events:
            if isinstance(e, EosPropValueChanged):
                self._eos_values[e.prop] = e
                if e.prop == EosProp.FOCUS_INFO_EX:
                    try:
                        self.focus = parse_focus_info_ex(e.raw)
                    except ProtocolError as exc:
                        self.anomalies.append(f"FocusInfoEx did not decode: {exc}")
                        self.focus = None
                    self._focus_seen += 1
            elif isinstance(e, EosAvailListChanged):
                self._eos_allowed[e.prop] = e
            elif isinstance(e, EosCameraStatus):
                self.camera_status = e.status
            elif isinstance(e, (EosObjectAdded, EosRequestObjectTransfer)):
                if not (isinstance(e, EosObjectAdded) and e.changed):
                    self._pending.append(e)
            elif isinstance(e, EosObjectRemoved):
                if self._card_handles is not None:
                    self._card_handles.discard(e.handle)
            elif isinstance(e, EosUnknownEvent):
                note = f"event record 0x{e.code:04X} ({len(e.body)} bytes) has no decoder; skipped"
                if note not in self.anomalies:
                    self.anomalies.append(note)
            elif isinstance(e, EosUndecodedRecord) and len(self.anomalies) < MAX_ANOMALIES:
                self.anomalies.append(f"event record 0x{e.code:04X} did not decode: {e.reason}; skipped")

    @property
    def busy(self) -> bool:
        """The camera's status word says busy (1); libgphoto2 treats only 1 as busy."""
        return self.camera_status == 1

    def settle(self, props: tuple[int, ...] = SETTLE_PROPS, budget_s: float | None = None) -> bool:
        """Poll until every prop in `props` that the body lists (GetDeviceInfoEx) has been reported.

        A 70D delivers its settings over several polls, some a few hundred ms late. Returns whether all arrived.
        """
        listed = set(self.info_ex.properties) if self.info_ex else set(props)
        wanted = [p for p in props if p in listed]
        deadline = time.monotonic() + (self.policy.settle_s if budget_s is None else budget_s)
        delay = 0.0
        while True:
            events = self.poll_events()
            missing = [p for p in wanted if p not in self._eos_values]
            if not missing and not events:
                return True
            if time.monotonic() >= deadline:
                if missing:
                    self.anomalies.append(
                        "after the start-up wait the body had not reported " + ", ".join(f"0x{p:04X}" for p in missing)
                    )
                return not missing
            delay = 0.0 if events else min(self.policy.poll_max_s, delay + self.policy.poll_step_s)
            time.sleep(delay)

    def keep_alive(self, force: bool = False) -> None:
        """Stop the camera from powering off while tethered (EOS KeepDeviceOn about every 10 s)."""
        now = time.monotonic()
        if force or now - self._last_keep_alive >= self.policy.keep_alive_s:
            if self.is_eos and self.info.supports(Op.EOS_KEEP_DEVICE_ON):
                self._call(Op.EOS_KEEP_DEVICE_ON, check=False)
            self._last_keep_alive = now

    def _claim(self, exclude: frozenset[int] | None = None) -> list[CapturedObject]:
        """Take the new-file events out of the pending list (folders and `exclude`d handles skipped)."""
        found: list[CapturedObject] = []
        rest: list[EosEvent] = []
        for e in self._pending:
            if isinstance(e, EosObjectAdded):
                if e.object_format == ObjectFormat.ASSOCIATION or (exclude and e.handle in exclude):
                    continue
                if self._card_handles is not None:
                    self._card_handles.add(e.handle)
                obj = CapturedObject(e.handle, e.filename, e.size_bytes, e.object_format, e.storage_id, False)
            elif isinstance(e, EosRequestObjectTransfer):
                obj = CapturedObject(e.handle, e.filename, e.size_bytes, e.object_format, 0, True)
            else:
                rest.append(e)
                continue
            if (obj.handle, obj.in_ram) not in self._claimed:
                self._claimed.add((obj.handle, obj.in_ram))
                found.append(obj)
        self._pending = rest
        return found

    def wait_for_object(self, timeout_s: float, *, stop: Callable[[], bool] | None = None) -> CapturedObject | None:
        """Wait for a new file (the camera's own shutter button, or an earlier shot); None after the timeout."""
        deadline = time.monotonic() + timeout_s
        delay = 0.0
        while True:
            if self.unclaimed:
                return self.unclaimed.pop(0)
            if self.is_eos:
                events = self.poll_events()
                found = self._claim()
                if found:
                    self.unclaimed.extend(found[1:])
                    return found[0]
                delay = 0.0 if events else min(self.policy.poll_max_s, delay + self.policy.poll_step_s)
            else:
                ev = self.transport.read_event(min(0.2, max(0.001, deadline - time.monotonic())))
                if ev is not None and ev.code == Event.OBJECT_ADDED and ev.params:
                    obj = self._std_object(ev.params[0])
                    if obj is not None:
                        return obj
            self.keep_alive()
            if time.monotonic() >= deadline or (stop is not None and stop()):
                return None
            if self.is_eos:
                time.sleep(min(delay, max(0.0, deadline - time.monotonic())))

    def _std_object(self, handle: int) -> CapturedObject | None:
        info = self.object_info(handle)
        if info.object_format == ObjectFormat.ASSOCIATION:
            return None
        return CapturedObject(
            handle, info.filename, info.compressed_size_bytes, info.object_format, info.storage_id, False
        )

    # -- capture ---------------------------------------------------------
    def _prop_value(self, prop: int) -> int | None:
        current = self._eos_values.get(prop)
        return current.value if current else None

    def files_per_shot(self) -> int:
        current = self._eos_values.get(EosProp.IMAGE_FORMAT)
        entries = image_format_of(current.raw) if current else None
        return len(entries) if entries else 1

    def trigger(self, before_release: Callable[[CaptureTicket], None] | None = None) -> CaptureTicket:
        """Release the shutter once. Never repeated: a failure before the release raises `CameraNotReady`, a
        refusal `ReleaseRefused` (no picture), a link failure while the command was out `ReleaseUncertain`.

        `before_release(ticket)` is called once the ticket (the card before the release) is known and just
        before the shutter command goes out: the host can note the release durably first."""
        if not self.is_eos:
            if not self.info.supports(Op.INITIATE_CAPTURE):
                raise CaptureError(f"{self.name} supports neither EOS remote release nor InitiateCapture")
            ticket = CaptureTicket(self.serial_number, None, 1, False)
            if before_release is not None:
                before_release(ticket)
            resp = self._release_once(Op.INITIATE_CAPTURE, (0, 0), ticket)
            if resp.code != Resp.OK:
                raise ReleaseRefused(
                    f"{self.name}: InitiateCapture answered {name_of(Resp, resp.code)}; no picture was taken", resp.code
                )
            return ticket
        self.drain_events()
        self.unclaimed.extend(self._claim())  # files that arrived before this release are not this shot's
        self._wait_until_ready()
        in_ram = self._prop_value(EosProp.CAPTURE_DESTINATION) == CAPTURE_DESTINATION_RAM
        if in_ram:
            shots = self._prop_value(EosProp.AVAILABLE_SHOTS)
            if shots is not None and shots < 100 and self.info.supports(Op.EOS_PC_HDD_CAPACITY):
                self._call(Op.EOS_PC_HDD_CAPACITY, HOST_CAPACITY_PARAMS, check=False)
        elif self._card_handles is None or self._events_lost:
            self._card_handles = set(self.object_handles())
            self._events_lost = False
        ticket = CaptureTicket(
            self.serial_number,
            None if in_ram else frozenset(self._card_handles or ()),
            self.files_per_shot(),
            in_ram,
        )
        if before_release is not None:
            before_release(ticket)
        if self.info.supports(Op.EOS_REMOTE_RELEASE_ON):
            self._half_press()
            self._check_focus()
            self._full_press(ticket)
        else:
            resp = self._release_once(Op.EOS_REMOTE_RELEASE, (), ticket)
            if resp.code != Resp.OK:
                raise ReleaseRefused(f"{self.name}: remote release answered {name_of(Resp, resp.code)}")
            if resp.params and resp.params[0]:
                raise ReleaseRefused(
                    f"{self.name}: remote release failed: "
                    f"{RELEASE_ERRORS.get(resp.params[0], f'code {resp.params[0]}')}"
                )
        return ticket

    def _wait_until_ready(self) -> None:
        deadline = time.monotonic() + self.policy.ready_wait_s
        delay = 0.0
        while self.busy:
            if time.monotonic() >= deadline:
                raise CameraNotReady(
                    self.name, Op.EOS_REMOTE_RELEASE_ON, Resp.DEVICE_BUSY, "the camera stayed busy; nothing was taken"
                )
            delay = min(self.policy.poll_max_s, delay + self.policy.poll_step_s)
            time.sleep(delay)
            self.poll_events()
            self.unclaimed.extend(self._claim())

    def _release_once(self, op: int, params: tuple[int, ...], ticket: CaptureTicket) -> Response:
        """Send a shutter command exactly once; a link failure means we cannot know whether it fired."""
        try:
            return self._call(op, params, check=False, repeat=False, timeout_s=self.policy.capture_timeout_s)
        except (TransportError, ProtocolError) as exc:
            raise ReleaseUncertain(
                f"{self.name}: the link failed while {name_of(Op, op)} was out ({exc}); "
                "looking for the new file instead of releasing again",
                ticket,
            ) from exc

    def _half_press(self) -> None:
        """RemoteReleaseOn(1, AF): focus. Busy is retried (nothing happens on a busy half press); any other
        failure releases the button (RemoteReleaseOff(1)), so the body is never left half-pressed."""
        try:
            resp = self._call(
                Op.EOS_REMOTE_RELEASE_ON, (1, 0), check=False, repeat=True, timeout_s=self.policy.capture_timeout_s
            )
        except DeviceDisconnected:
            raise
        except (TransportError, ProtocolError) as exc:
            self._release_button(1)
            raise ReleaseRefused(f"{self.name}: the half press failed ({exc}); no picture was taken") from exc
        if resp.code != Resp.OK:
            self._release_button(1)
            raise ReleaseRefused(
                f"{self.name}: the half press answered {name_of(Resp, resp.code)}; no picture was taken"
            )

    def _check_focus(self) -> None:
        """Between half and full press: poll up to `focus_wait_s` for the AF result (FocusInfoEx, as libgphoto2).

        A report with a point in focus ends the wait at once; with none and the body in One-Shot AF (which
        will not fire unfocused) the half press is released and the capture refused; otherwise, as
        libgphoto2 does, the full press follows. Manual focus waits for one poll (at most 0.1 s).
        """
        mode = self._prop_value(EosProp.FOCUS_MODE)
        seen = self._focus_seen
        start = time.monotonic()
        deadline = start + (min(0.1, self.policy.focus_wait_s) if mode == MANUAL_FOCUS else self.policy.focus_wait_s)
        delay = 0.0
        while True:
            events = self.poll_events()
            reported = self._focus_seen != seen
            if reported and self.focus is not None and self.focus.focused:
                return
            if mode == MANUAL_FOCUS and events:
                return
            if time.monotonic() >= deadline:
                break
            delay = 0.0 if events else min(self.policy.poll_max_s, delay + self.policy.poll_step_s)
            time.sleep(min(delay, max(0.0, deadline - time.monotonic())))
        if reported and self.focus is not None and not self.focus.focused and mode == ONE_SHOT_AF:
            self._release_button(1)
            raise ReleaseRefused(f"{self.name}: {RELEASE_ERRORS[1]}; no picture was taken")

    def _full_press(self, ticket: CaptureTicket) -> None:
        try:
            resp = self._release_once(Op.EOS_REMOTE_RELEASE_ON, (2, 0), ticket)
        except ReleaseUncertain:
            for button in (2, 1):
                self._release_button(button, quiet=True)
            raise
        if resp.code != Resp.OK:
            # libgphoto2: poll, release the half press, poll, report. The picture was not taken (the R10
            # answers DeviceBusy here and no file appears); it is not retried.
            self._poll_quietly()
            self._release_button(1)
            self._poll_quietly()
            raise ReleaseRefused(
                f"{self.name}: the full press answered {name_of(Resp, resp.code)}; no picture was taken "
                "(the camera may be writing, its RAM full of shots to download, in live view, or unable to focus)",
                resp.code,
            )
        self._release_button(2)
        self._poll_quietly()
        self._release_button(1)

    def _release_button(self, button: int, quiet: bool = False) -> None:
        try:
            self._call(Op.EOS_REMOTE_RELEASE_OFF, (button,), check=False)
        except (TransportError, ProtocolError):
            if not quiet:
                self.anomalies.append(f"RemoteReleaseOff({button}) did not go through")

    def _poll_quietly(self) -> None:
        try:
            self.poll_events()
        except (TransportError, ProtocolError, PtpError):
            pass

    def wait_for_capture(self, ticket: CaptureTicket, timeout_s: float | None = None) -> list[CapturedObject]:
        """The file(s) a release made: from the events, or (when a poll's reply was lost, or after a reconnect)
        by comparing the card with the ticket's snapshot. Safe to call again after a link failure."""
        timeout = self.policy.object_wait_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        exclude = ticket.card_handles
        found: list[CapturedObject] = []
        delay = 0.0
        fresh_camera = not self.is_eos or ticket.serial_number != self.serial_number or self._card_handles is None
        if ticket.card_handles is not None and self.is_eos and (self._events_lost or fresh_camera):
            found += self._card_diff(ticket, found)
        while len(found) < ticket.files_expected:
            if not self.is_eos:
                ev = self.transport.read_event(min(0.2, max(0.001, deadline - time.monotonic())))
                if ev is not None and ev.code == Event.OBJECT_ADDED and ev.params:
                    obj = self._std_object(ev.params[0])
                    if obj is not None:
                        found.append(obj)
            else:
                events = self.poll_events()
                new = [o for o in self._claim(exclude) if o.handle not in {f.handle for f in found}]
                if new and not found:
                    deadline = min(deadline, time.monotonic() + self.policy.second_file_wait_s)
                found += new
                if self._events_lost and ticket.card_handles is not None:
                    found += self._card_diff(ticket, found)
                delay = 0.0 if events else min(self.policy.poll_max_s, delay + self.policy.poll_step_s)
            if len(found) >= ticket.files_expected:
                break
            self.keep_alive()
            if time.monotonic() >= deadline:
                if ticket.card_handles is not None and self.is_eos and not found:
                    found += self._card_diff(ticket, found)
                break
            if self.is_eos:
                time.sleep(min(delay, max(0.0, deadline - time.monotonic())))
        if not found:
            raise CaptureError(
                f"{self.name}: no new file within {timeout:.0f} s after the release; "
                "check focus, the card, and that the camera is not in live view"
            )
        return found

    def _card_diff(self, ticket: CaptureTicket, already: list[CapturedObject]) -> list[CapturedObject]:
        """Files on the card now that were not there at the release (events about them may have been lost)."""
        before = ticket.card_handles or frozenset()
        known = {o.handle for o in already}
        handles = self.object_handles()
        self._events_lost = False
        out = []
        for handle in handles:
            if handle in before or handle in known or (handle, False) in self._claimed:
                continue
            obj = self._std_object(handle)
            if obj is not None:
                self._claimed.add((handle, False))
                out.append(obj)
        self._card_handles = set(handles)
        self._pending = [
            e for e in self._pending if not (isinstance(e, EosObjectAdded) and e.handle in {o.handle for o in out})
        ]
        return out

    def capture(self, timeout_s: float | None = None) -> CapturedObject:
        """Take one picture and return its (first) file; further files of the shot go to `unclaimed`."""
        ticket = self.trigger()
        found = self.wait_for_capture(ticket, timeout_s)
        self.unclaimed.extend(found[1:])
        return found[0]

    # -- live view -------------------------------------------------------
    def start_live_view(self) -> None:
        """EVF mode on, output to the computer (EOS 0xD1B1 / 0xD1B0), as libgphoto2's capture preview does."""
        if not (self.is_eos and self.info.supports(Op.EOS_GET_VIEWFINDER_DATA)):
            raise CaptureError(f"{self.name} offers no EOS live view (GetViewFinderData)")
        mode = self._prop_value(EosProp.EVF_MODE)
        if mode is not None and mode != 1:
            resp = self._set_eos_u32(EosProp.EVF_MODE, 1, check=False)
            if resp.code not in (Resp.OK, Resp.DEVICE_BUSY):  # busy in movie mode, live view works anyway
                raise PtpError(self.name, Op.EOS_SET_DEVICE_PROP_VALUE_EX, resp.code, "could not enable live view")
        output = self._prop_value(EosProp.EVF_OUTPUT_DEVICE) or 0
        if output & ~1 == 0:
            self._live_view_restore = output
            self._set_eos_u32(EosProp.EVF_OUTPUT_DEVICE, EVF_OUTPUT_PC)

    def live_view_frame(self) -> bytes:
        """One live-view JPEG; "not ready yet" (0xA102, busy) is waited out for up to `live_view_ready_s`."""
        deadline = time.monotonic() + self.policy.live_view_ready_s
        tries = 0
        while True:
            resp = self._call(Op.EOS_GET_VIEWFINDER_DATA, (VIEWFINDER_DATA_PARAM, 0, 0), check=False, repeat=True)
            if resp.code == Resp.OK and resp.data:
                frame = parse_viewfinder_data(resp.data)
                if frame.jpeg:
                    return frame.jpeg
                raise ProtocolError(f"{self.name}: live-view data without a JPEG block")
            if resp.code not in (Resp.CANON_OBJECT_NOT_READY, Resp.DEVICE_BUSY) or time.monotonic() >= deadline:
                raise PtpError(self.name, Op.EOS_GET_VIEWFINDER_DATA, resp.code, "is live view enabled on the camera?")
            tries += 1
            time.sleep(0.005 * tries)

    def stop_live_view(self) -> None:
        if self._live_view_restore is not None:
            self._set_eos_u32(EosProp.EVF_OUTPUT_DEVICE, self._live_view_restore, check=False)
            self._live_view_restore = None

    def _stop_live_view_quietly(self) -> None:
        try:
            self.stop_live_view()
        except (TransportError, ProtocolError, PtpError):
            pass

    # -- properties ------------------------------------------------------
    def _set_eos_u32(self, prop: int, value: int, *, check: bool = True) -> Response:
        """SetDevicePropValueEx: u32 size 12, u32 property, u32 value (also for 16-bit properties)."""
        data = struct.pack("<III", 12, prop, value)
        resp = self._call(Op.EOS_SET_DEVICE_PROP_VALUE_EX, data_out=data, check=check)
        if resp.code == Resp.OK:
            self._await_value(prop, lambda v: v.value == value)
        return resp

    def _await_value(self, prop: int, done: Callable[[EosPropValueChanged], bool]) -> None:
        """Poll until the body reports the property's new value (it comes in a later GetEvent)."""
        deadline = time.monotonic() + self.policy.settle_s
        delay = 0.0
        while True:
            events = self.poll_events()
            current = self._eos_values.get(prop)
            if current is not None and done(current):
                return
            if time.monotonic() >= deadline:
                return
            delay = 0.0 if events else min(self.policy.poll_max_s, delay + self.policy.poll_step_s)
            time.sleep(delay)

    def _eos_current(self, code: int, name: str) -> EosPropValueChanged:
        if code not in self._eos_values:
            listed = self.info_ex is None or code in self.info_ex.properties
            if listed:
                self.settle(props=(code,))
        if code not in self._eos_values:
            raise PropertyNotReported(
                f"{self.name} has not reported property {name!r} (0x{code:04X}); "
                "check the camera is in a shooting mode (P/Av/Tv/M) and not in a menu"
            )
        return self._eos_values[code]

    def card_capture_destination(self) -> int:
        """The value that means "memory card" on this body: the first listed value other than RAM (libgphoto2)."""
        allowed = self._eos_allowed.get(EosProp.CAPTURE_DESTINATION)
        for value in allowed.values if allowed else ():
            if value != CAPTURE_DESTINATION_RAM:
                return value
        current = self._prop_value(EosProp.CAPTURE_DESTINATION)
        if current is not None and current != CAPTURE_DESTINATION_RAM:
            return current
        return CAPTURE_DESTINATION_CARD

    def get_property(self, name: str) -> PropertyValue:
        spec = spec_for(name)
        if self.is_eos:
            if spec.eos_code is None:
                raise PropertyNotReported(f"{spec.name!r} has no EOS property code")
            current = self._eos_current(spec.eos_code, spec.name)
            allowed = self._eos_allowed.get(spec.eos_code)
            if spec.eos_code == EosProp.IMAGE_FORMAT:
                entries = image_format_of(current.raw)
                value = image_format_name(entries) if entries else f"raw value {current.raw.hex()}"
                names = tuple(
                    image_format_name(e)
                    for e in (image_format_of(r) for r in (allowed.raw_values if allowed else ()))
                    if e is not None
                )
                return PropertyValue(spec.name, value, names, spec.eos_code)
            table = spec.table or {}
            value = table.get(current.value, f"0x{current.value:X}")
            names = tuple(dict.fromkeys(table.get(v, f"0x{v:X}") for v in (allowed.values if allowed else ())))
            return PropertyValue(spec.name, value, names, spec.eos_code)
        if spec.std_code is None or spec.std_code not in self.info.properties:
            raise PropertyNotReported(f"{self.name} does not offer property {spec.name!r}")
        desc = self.prop_desc(spec.std_code)
        allowed_std = tuple(str(v) for v in desc.allowed) if desc.form == "enum" else ()
        return PropertyValue(spec.name, str(desc.current), allowed_std, spec.std_code)

    def prop_desc(self, code: int) -> DevicePropDesc:
        return parse_prop_desc(self._data(Op.GET_DEVICE_PROP_DESC, (code,)))

    def set_property(self, name: str, value: str) -> PropertyValue:
        spec = spec_for(name)
        current = self.get_property(spec.name)
        wanted = value.strip()
        if self.is_eos:
            assert spec.eos_code is not None
            if spec.eos_code == EosProp.IMAGE_FORMAT:
                entries = {n.lower(): e for e, n in EOS_IMAGE_FORMAT_NAMES.items()}
                allowed = self._eos_allowed.get(EosProp.IMAGE_FORMAT)
                for raw in allowed.raw_values if allowed else ():
                    decoded = image_format_of(raw)
                    if decoded:
                        entries[image_format_name(decoded).lower()] = decoded
                if wanted.lower() not in entries:
                    raise ValueError(f"{wanted!r} is not an image format; choose from {', '.join(current.allowed)}")
                body = pack_image_format(entries[wanted.lower()])
                data = struct.pack("<II", 8 + len(body), spec.eos_code) + body
                self._call(Op.EOS_SET_DEVICE_PROP_VALUE_EX, data_out=data)
                self._await_value(spec.eos_code, lambda v: v.raw == body)
                return self.get_property(spec.name)
            allowed_list = self._eos_allowed.get(spec.eos_code)
            offered = allowed_list.values if allowed_list else ()
            if spec.eos_code == EosProp.CAPTURE_DESTINATION:
                target = CAPTURE_TARGET_ALIASES.get(wanted.lower(), wanted)
                code = (
                    self.card_capture_destination()
                    if target == "Memory card"
                    else CAPTURE_DESTINATION_RAM
                    if target == "Internal RAM"
                    else None
                )
            else:
                code = code_for(spec.table or {}, wanted, offered)
            if code is None or (offered and code not in offered):
                offered_names = ", ".join(current.allowed) or "(none offered)"
                raise ValueError(f"{wanted!r} is not allowed for {spec.name}; choose from {offered_names}")
            if self._prop_value(spec.eos_code) == code:
                return current  # setting the same capture destination can answer DeviceBusy on EOS bodies
            self._set_eos_u32(spec.eos_code, code)
            to_ram = spec.eos_code == EosProp.CAPTURE_DESTINATION and code == CAPTURE_DESTINATION_RAM
            if to_ram and self.info.supports(Op.EOS_PC_HDD_CAPACITY):  # busy here is harmless (libgphoto2)
                self._call(Op.EOS_PC_HDD_CAPACITY, HOST_CAPACITY_PARAMS, check=False)
            return self.get_property(spec.name)
        desc = self.prop_desc(spec.std_code)  # type: ignore[arg-type]
        try:
            std_value: int | str = wanted if desc.datatype == 0xFFFF else int(wanted, 0)
        except ValueError as exc:
            raise ValueError(f"{spec.name} takes a number on {self.name}, got {wanted!r}") from exc
        data_out = pack_prop_value(desc.datatype, std_value)
        self._call(Op.SET_DEVICE_PROP_VALUE, (spec.std_code,), data_out=data_out)  # type: ignore[arg-type]
        return self.get_property(spec.name)

    # -- what the body reported (for `mca camera doctor`) ---------------
    def device_info_bytes(self) -> bytes:
        """GetDeviceInfo's dataset exactly as the body sends it."""
        return self._data(Op.GET_DEVICE_INFO)

    def reported_values(self) -> dict[int, EosPropValueChanged]:
        return dict(self._eos_values)

    def reported_allowed(self) -> dict[int, EosAvailListChanged]:
        return dict(self._eos_allowed)
