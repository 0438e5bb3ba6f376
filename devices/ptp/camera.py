"""`Camera`: a PTP session over any transport, with the Canon EOS capture sequence, downloads and named properties."""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import BinaryIO

from mca.devices.ptp.codec import ProtocolError, Reader
from mca.devices.ptp.codes import (
    ALL_STORAGES,
    CANON_VENDOR_EXTENSION_ID,
    CAPTURE_DESTINATION_RAM,
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
    ObjectInfo,
    StorageInfo,
    pack_prop_value,
    parse_device_info,
    parse_object_info,
    parse_prop_desc,
    parse_storage_info,
)
from mca.devices.ptp.events import (
    EosAvailListChanged,
    EosCameraStatus,
    EosEvent,
    EosObjectAdded,
    EosPropValueChanged,
    EosRequestObjectTransfer,
    pack_image_format,
    parse_eos_events,
    parse_image_format,
)
from mca.devices.ptp.properties import CAPTURE_TARGET_ALIASES, EOS_IMAGE_FORMATS, spec_for
from mca.devices.ptp.transport import Transport, TransportError

DOWNLOAD_BLOCK_BYTES = 1024 * 1024
KEEP_ALIVE_INTERVAL_S = 10.0
#: The largest file the host accepts from a camera (a 70D RAW is about 25 MB).
MAX_OBJECT_BYTES = 2 * 1024**3
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


class CaptureError(Exception):
    """A capture did not produce a file."""


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
class PropertyValue:
    name: str
    value: str
    allowed: tuple[str, ...]
    code: int


class Camera:
    """One open PTP session. Not thread-safe: drive it from one thread."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        self.name = transport.name
        self._tid = 0
        self.session_open = False
        self.info: DeviceInfo = DeviceInfo()
        self._eos_values: dict[int, EosPropValueChanged] = {}
        self._eos_allowed: dict[int, EosAvailListChanged] = {}
        self._pending_events: list[EosEvent] = []
        self._last_keep_alive = time.monotonic()
        self.busy = False

    # -- session ---------------------------------------------------------
    @classmethod
    def open(cls, transport: Transport, session_id: int = 1) -> Camera:
        cam = cls(transport)
        cam.info = parse_device_info(cam._data(Op.GET_DEVICE_INFO))
        resp = cam._call(Op.OPEN_SESSION, (session_id,), check=False, new_session=True)
        if resp.code == Resp.SESSION_ALREADY_OPEN:
            cam._call(Op.CLOSE_SESSION, check=False)
            cam._tid = 0
            resp = cam._call(Op.OPEN_SESSION, (session_id,), check=False, new_session=True)
        if resp.code != Resp.OK:
            raise PtpError(cam.name, Op.OPEN_SESSION, resp.code, "switch the camera off and on")
        cam.session_open = True
        cam.info = parse_device_info(cam._data(Op.GET_DEVICE_INFO))
        if cam.is_eos:
            cam._call(Op.EOS_SET_REMOTE_MODE, (1,))
            cam._call(Op.EOS_SET_EVENT_MODE, (1,))
            cam.poll_events()
        return cam

    @property
    def is_eos(self) -> bool:
        return (
            self.info.vendor_extension_id == CANON_VENDOR_EXTENSION_ID
            and self.info.supports(Op.EOS_GET_EVENT)
            and self.info.supports(Op.EOS_REMOTE_RELEASE)
        )

    @property
    def serial_number(self) -> str:
        return self.info.serial_number

    def close(self) -> None:
        try:
            if self.session_open:
                if self.is_eos:
                    self._call(Op.EOS_SET_REMOTE_MODE, (0,), check=False)
                    self._call(Op.EOS_SET_EVENT_MODE, (0,), check=False)
                self._call(Op.CLOSE_SESSION, check=False)
        except TransportError:
            pass
        finally:
            self.session_open = False
            self.transport.close()

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
        sink=None,
        max_data_bytes: int = 16 * 1024 * 1024,
        check: bool = True,
        new_session: bool = False,
        timeout_s: float | None = None,
    ):
        tid = self._next_tid(new_session or not self.session_open)
        try:
            resp = self.transport.transaction(
                op, tid, tuple(params), data_out=data_out, sink=sink, max_data_bytes=max_data_bytes, timeout_s=timeout_s
            )
        except ProtocolError as exc:
            self._recover()
            raise ProtocolError(f"{self.name}: {name_of(Op, op)}: {exc}") from exc
        except TransportError as exc:
            if type(exc).__name__ != "DeviceDisconnected":
                self._recover()
            raise
        if check and resp.code != Resp.OK:
            cls = DeviceBusyError if resp.code == Resp.DEVICE_BUSY else PtpError
            hint = (
                "wait for the camera to finish writing, or download the shots waiting in its RAM"
                if resp.code == Resp.DEVICE_BUSY
                else ""
            )
            raise cls(self.name, op, resp.code, hint)
        return resp

    def _recover(self) -> None:
        try:
            self.transport.recover()
        except TransportError:
            pass

    def _data(self, op: int, params: tuple[int, ...] = (), max_data_bytes: int = 16 * 1024 * 1024) -> bytes:
        resp = self._call(op, params, max_data_bytes=max_data_bytes)
        if resp.data is None:
            raise ProtocolError(f"{self.name}: {name_of(Op, op)} answered OK without its data phase")
        return resp.data

    # -- storage and objects ---------------------------------------------
    def storage_ids(self) -> list[int]:
        r = Reader(self._data(Op.GET_STORAGE_IDS))
        return list(r.array("I"))

    def storages(self) -> dict[int, StorageInfo]:
        return {sid: parse_storage_info(self._data(Op.GET_STORAGE_INFO, (sid,))) for sid in self.storage_ids()}

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
        self._call(Op.DELETE_OBJECT, (handle,))

    def download(
        self,
        handle: int,
        size_bytes: int,
        out: BinaryIO,
        *,
        block_bytes: int = DOWNLOAD_BLOCK_BYTES,
        progress: ProgressFn | None = None,
    ) -> int:
        """Copy an object into `out` in GetPartialObject blocks; returns the bytes written (== size_bytes)."""
        if not 0 <= size_bytes <= MAX_OBJECT_BYTES:
            raise ProtocolError(f"{self.name}: object size {size_bytes} is outside 0..{MAX_OBJECT_BYTES}")
        op = (
            Op.EOS_GET_PARTIAL_OBJECT
            if self.is_eos and self.info.supports(Op.EOS_GET_PARTIAL_OBJECT)
            else Op.GET_PARTIAL_OBJECT
        )
        done = 0
        while done < size_bytes:
            want = min(block_bytes, size_bytes - done)
            got = 0

            def sink(piece: memoryview) -> None:
                nonlocal got
                out.write(piece)
                got += len(piece)

            resp = self._call(op, (handle, done, want), sink=sink, max_data_bytes=want)
            if got == 0:
                raise ProtocolError(f"{self.name}: GetPartialObject at offset {done} returned no data")
            done += got
            if progress is not None:
                progress(done, size_bytes)
            if resp.params and resp.params[0] != got and op == Op.GET_PARTIAL_OBJECT:
                raise ProtocolError(f"{self.name}: GetPartialObject said {resp.params[0]} bytes but sent {got}")
        return done

    def transfer_complete(self, handle: int) -> None:
        """Tell an EOS body that a RAM shot is safely on the host, freeing its buffer."""
        if self.is_eos:
            self._call(Op.EOS_TRANSFER_COMPLETE, (handle,))

    # -- events ----------------------------------------------------------
    def poll_events(self) -> list[EosEvent]:
        """One EOS GetEvent: returns the records and updates the property cache."""
        events = parse_eos_events(self._data(Op.EOS_GET_EVENT))
        for e in events:
            if isinstance(e, EosPropValueChanged):
                self._eos_values[e.prop] = e
            elif isinstance(e, EosAvailListChanged):
                self._eos_allowed[e.prop] = e
            elif isinstance(e, EosCameraStatus):
                self.busy = e.busy
        return events

    def keep_alive(self, force: bool = False) -> None:
        """Stop the camera from powering off while tethered (EOS KeepDeviceOn about every 10 s)."""
        now = time.monotonic()
        if force or now - self._last_keep_alive >= KEEP_ALIVE_INTERVAL_S:
            if self.is_eos and self.info.supports(Op.EOS_KEEP_DEVICE_ON):
                self._call(Op.EOS_KEEP_DEVICE_ON, check=False)
            self._last_keep_alive = now

    def wait_for_object(self, timeout_s: float, *, stop: Callable[[], bool] | None = None) -> CapturedObject | None:
        """Wait for a new file (a remote capture or the camera's own shutter button); None after the timeout."""
        deadline = time.monotonic() + timeout_s
        delay_s = 0.005
        while True:
            if self._pending_events:
                found = self._take_object(self._pending_events)
                if found:
                    return found
            if self.is_eos:
                found = self._take_object(self.poll_events())
                if found:
                    return found
            else:
                ev = self.transport.read_event(min(0.2, max(0.001, deadline - time.monotonic())))
                if ev is not None and ev.code == Event.OBJECT_ADDED and ev.params:
                    handle = ev.params[0]
                    info = self.object_info(handle)
                    if info.object_format != ObjectFormat.ASSOCIATION:
                        return CapturedObject(
                            handle,
                            info.filename,
                            info.compressed_size_bytes,
                            info.object_format,
                            info.storage_id,
                            False,
                        )
            self.keep_alive()
            if time.monotonic() >= deadline or (stop is not None and stop()):
                return None
            if self.is_eos:
                time.sleep(min(delay_s, max(0.0, deadline - time.monotonic())))
                delay_s = min(delay_s * 2, 0.2)

    def _take_object(self, events: list[EosEvent]) -> CapturedObject | None:
        for i, e in enumerate(events):
            if isinstance(e, EosObjectAdded) and not e.changed and e.object_format != ObjectFormat.ASSOCIATION:
                self._pending_events = [
                    x for x in events[i + 1 :] if isinstance(x, (EosObjectAdded, EosRequestObjectTransfer))
                ] + [x for x in self._pending_events if x not in events]
                return CapturedObject(e.handle, e.filename, e.size_bytes, e.object_format, e.storage_id, False)
            if isinstance(e, EosRequestObjectTransfer):
                self._pending_events = [
                    x for x in events[i + 1 :] if isinstance(x, (EosObjectAdded, EosRequestObjectTransfer))
                ] + [x for x in self._pending_events if x not in events]
                return CapturedObject(e.handle, e.filename, e.size_bytes, e.object_format, 0, True)
        if events is self._pending_events:
            self._pending_events = []
        return None

    # -- capture ---------------------------------------------------------
    def capture(self, timeout_s: float = 90.0) -> CapturedObject:
        """Take one picture and return the new file: EOS remote release on Canon bodies, InitiateCapture elsewhere."""
        if not self.is_eos:
            if not self.info.supports(Op.INITIATE_CAPTURE):
                raise CaptureError(f"{self.name} supports neither EOS remote release nor InitiateCapture")
            self._call(Op.INITIATE_CAPTURE, (0, 0))
            found = self.wait_for_object(timeout_s)
            if found is None:
                raise CaptureError(f"{self.name}: no new file within {timeout_s:.0f} s after InitiateCapture")
            return found
        for e in self.poll_events():  # drain, keeping any file that arrived meanwhile for later
            if isinstance(e, (EosObjectAdded, EosRequestObjectTransfer)):
                self._pending_events.append(e)
        if self.busy:
            raise DeviceBusyError(self.name, Op.EOS_REMOTE_RELEASE, Resp.DEVICE_BUSY, "the camera reports it is busy")
        backlog = list(self._pending_events)
        self._pending_events = []
        if self.info.supports(Op.EOS_REMOTE_RELEASE_ON):
            self._call(Op.EOS_REMOTE_RELEASE_ON, (1, 0))
            try:
                self._call(Op.EOS_REMOTE_RELEASE_ON, (2, 0))
            finally:
                self._call(Op.EOS_REMOTE_RELEASE_OFF, (2,), check=False)
                self._call(Op.EOS_REMOTE_RELEASE_OFF, (1,), check=False)
        else:
            resp = self._call(Op.EOS_REMOTE_RELEASE)
            if resp.params and resp.params[0]:
                raise CaptureError(
                    f"{self.name}: remote release failed: "
                    f"{RELEASE_ERRORS.get(resp.params[0], f'code {resp.params[0]}')}"
                )
        found = self.wait_for_object(timeout_s)
        self._pending_events = backlog + self._pending_events
        if found is None:
            raise CaptureError(
                f"{self.name}: no new file within {timeout_s:.0f} s after the release; "
                "check focus, the card, and that the camera is not in live view"
            )
        return found

    # -- properties ------------------------------------------------------
    def get_property(self, name: str) -> PropertyValue:
        spec = spec_for(name)
        if self.is_eos:
            if spec.eos_code is None or spec.eos_code not in self._eos_values:
                self.poll_events()
            if spec.eos_code not in self._eos_values:
                raise KeyError(f"{self.name} has not reported property {spec.name!r}")
            current = self._eos_values[spec.eos_code]
            allowed = self._eos_allowed.get(spec.eos_code)
            if spec.eos_code == EosProp.IMAGE_FORMAT:
                value = _image_format_name(parse_image_format(Reader(current.raw)))
                names = tuple(
                    _image_format_name(parse_image_format(Reader(r))) for r in (allowed.raw_values if allowed else ())
                )
                return PropertyValue(spec.name, value, names, spec.eos_code)
            table = spec.table or {}
            value = table.get(current.value, f"0x{current.value:X}")
            names = tuple(table.get(v, f"0x{v:X}") for v in (allowed.values if allowed else ()))
            return PropertyValue(spec.name, value, names, spec.eos_code)
        if spec.std_code is None or spec.std_code not in self.info.properties:
            raise KeyError(f"{self.name} does not offer property {spec.name!r}")
        desc = self.prop_desc(spec.std_code)
        allowed_std = tuple(str(v) for v in desc.allowed) if desc.form == "enum" else ()
        return PropertyValue(spec.name, str(desc.current), allowed_std, spec.std_code)

    def prop_desc(self, code: int) -> DevicePropDesc:
        return parse_prop_desc(self._data(Op.GET_DEVICE_PROP_DESC, (code,)))

    def set_property(self, name: str, value: str) -> PropertyValue:
        spec = spec_for(name)
        current = self.get_property(spec.name)
        wanted = (
            CAPTURE_TARGET_ALIASES.get(value.strip().lower(), value.strip())
            if spec.name == "capturetarget"
            else value.strip()
        )
        if self.is_eos:
            if spec.eos_code == EosProp.IMAGE_FORMAT:
                entries = {n.lower(): e for e, n in EOS_IMAGE_FORMATS.items()}
                if wanted.lower() not in entries:
                    raise ValueError(f"{wanted!r} is not an image format; choose from {', '.join(current.allowed)}")
                body = pack_image_format(entries[wanted.lower()])
            else:
                codes = {n.lower(): c for c, n in (spec.table or {}).items()}
                if wanted.lower() not in codes or (
                    current.allowed and (spec.table or {})[codes[wanted.lower()]] not in current.allowed
                ):
                    raise ValueError(
                        f"{wanted!r} is not allowed for {spec.name}; choose from {', '.join(current.allowed)}"
                    )
                body = struct.pack("<I", codes[wanted.lower()])
                if (
                    spec.eos_code == EosProp.CAPTURE_DESTINATION
                    and current.value == (spec.table or {})[codes[wanted.lower()]]
                ):
                    return current  # setting the same destination can answer DeviceBusy on EOS bodies
            data = struct.pack("<II", 8 + len(body), spec.eos_code) + body
            self._call(Op.EOS_SET_DEVICE_PROP_VALUE_EX, data_out=data)
            if (
                spec.eos_code == EosProp.CAPTURE_DESTINATION
                and codes[wanted.lower()] == CAPTURE_DESTINATION_RAM
                and self.info.supports(Op.EOS_PC_HDD_CAPACITY)
            ):
                self._call(Op.EOS_PC_HDD_CAPACITY, (0x0FFFFFF8, 0x1000, 1), check=False)
            self.poll_events()
            return self.get_property(spec.name)
        desc = self.prop_desc(spec.std_code)  # type: ignore[arg-type]
        try:
            raw: int | str = wanted if desc.datatype == 0xFFFF else int(wanted, 0)
        except ValueError as exc:
            raise ValueError(f"{spec.name} takes a number on {self.name}, got {wanted!r}") from exc
        self._call(Op.SET_DEVICE_PROP_VALUE, (spec.std_code,), data_out=pack_prop_value(desc.datatype, raw))  # type: ignore[arg-type]
        return self.get_property(spec.name)


def _image_format_name(entries: tuple[tuple[int, int, int], ...]) -> str:
    return EOS_IMAGE_FORMATS.get(entries, "+".join(f"type{t}/size{s}/q{c}" for t, s, c in entries))
