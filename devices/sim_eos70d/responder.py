"""The simulated EOS 70D's PTP responder: sessions, storage, properties, remote release, GetEvent, RAM buffer.

Transport-agnostic: `handle(command, data_out)` takes a parsed command
container (and the data-out payload) and returns the data-in payload and the
response, using the same codec as the host side.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mca.devices.ptp.codec import Container
from mca.devices.ptp.codes import (
    CANON_VENDOR_EXTENSION_ID,
    CAPTURE_DESTINATION_CARD,
    CAPTURE_DESTINATION_RAM,
    ContainerType,
    EosProp,
    Event,
    ObjectFormat,
    Op,
    Resp,
)
from mca.devices.ptp.datasets import (
    DeviceInfo,
    ObjectInfo,
    StorageInfo,
    pack_device_info,
    pack_object_info,
    pack_storage_info,
)
from mca.devices.ptp.events import (
    EosAvailListChanged,
    EosCameraStatus,
    EosEvent,
    EosObjectAdded,
    EosObjectRemoved,
    EosPropValueChanged,
    EosRequestObjectTransfer,
    pack_eos_events,
    pack_image_format,
)
from mca.devices.ptp.properties import EOS_SHUTTER

#: A frame source gives the bytes of shot number `index` (1-based), or `(file name, bytes)`.
FrameSource = Callable[[int], "bytes | tuple[str, bytes]"]

CARD_STORAGE_ID = 0x00020001
DCIM_HANDLE = 0x90000001
FOLDER_HANDLE = 0x90000002
FIRST_FILE_HANDLE = 0x91000001
CARD_CAPACITY_BYTES = 16 * 1024**3

ISO_VALUES = (0x00, 0x48, 0x4B, 0x4D, 0x50, 0x53, 0x55, 0x58, 0x5B, 0x5D, 0x60, 0x63, 0x65, 0x68, 0x70, 0x78, 0x80)
SHUTTER_VALUES = tuple(k for k in EOS_SHUTTER if k >= 0x10)
APERTURE_VALUES = (
    0x20,
    0x23,
    0x25,
    0x28,
    0x2B,
    0x2D,
    0x30,
    0x33,
    0x35,
    0x38,
    0x3B,
    0x3D,
    0x40,
    0x43,
    0x45,
    0x48,
    0x4B,
    0x4D,
    0x50,
)
IMAGE_FORMATS = (
    ((6, 0, 4),),  # RAW
    ((1, 0, 3),),  # Large Fine JPEG
    ((1, 0, 2),),  # Large Normal JPEG
    ((6, 0, 4), (1, 0, 3)),  # RAW + Large Fine JPEG
)


def deterministic_frame(index: int, size_bytes: int = 256 * 1024) -> bytes:
    """A reproducible stand-in file for shot `index`: a TIFF-like CR2 header then hash-derived bytes."""
    head = b"II*\x00\x10\x00\x00\x00CR\x02\x00" + f"SIM-EOS70D shot {index:06d}".encode()
    block = hashlib.sha256(f"frame {index}".encode()).digest() * 64
    body = (block * (size_bytes // len(block) + 1))[: max(0, size_bytes - len(head))]
    return head + body


def default_frame_source(index: int) -> tuple[str, bytes]:
    return f"IMG_{index:04d}.CR2", deterministic_frame(index)


@dataclass
class SimObject:
    handle: int
    storage_id: int
    parent: int
    object_format: int
    filename: str
    data: bytes = field(repr=False, default=b"")
    capture_date: str = ""

    def info(self) -> ObjectInfo:
        is_folder = self.object_format == ObjectFormat.ASSOCIATION
        return ObjectInfo(
            storage_id=self.storage_id,
            object_format=self.object_format,
            compressed_size_bytes=len(self.data),
            image_width_px=0 if is_folder else 5472,
            image_height_px=0 if is_folder else 3648,
            image_bit_depth=0 if is_folder else 14,
            parent_object=self.parent,
            association_type=1 if is_folder else 0,
            filename=self.filename,
            capture_date=self.capture_date,
            modification_date=self.capture_date,
        )


@dataclass(frozen=True)
class Reply:
    """What the responder sends back: an optional data-in payload and the response."""

    response: Container
    data: bytes | memoryview | None = None


_DATA_OUT_OPS = {Op.SET_DEVICE_PROP_VALUE, Op.EOS_SET_DEVICE_PROP_VALUE_EX, Op.SEND_OBJECT_INFO, Op.SEND_OBJECT}


class SimEos70D:
    """The camera's behaviour. Thread-safe: one lock around every operation."""

    def __init__(
        self,
        frame_source: FrameSource | None = None,
        *,
        serial_number: str = "SIM70D0000001",
        ram_buffer_slots: int = 2,
        shot_delay_s: float = 0.0,
        eos: bool = True,
    ) -> None:
        self.frame_source = frame_source or default_frame_source
        self.serial_number = serial_number
        self.ram_buffer_slots = ram_buffer_slots
        self.shot_delay_s = shot_delay_s
        self.eos = eos
        self.lock = threading.RLock()
        self.session_id = 0
        self.event_mode = 0
        self.remote_mode = 0
        self.shots_taken = 0
        self._next_handle = FIRST_FILE_HANDLE
        self.card: dict[int, SimObject] = {
            DCIM_HANDLE: SimObject(DCIM_HANDLE, CARD_STORAGE_ID, 0, ObjectFormat.ASSOCIATION, "DCIM"),
            FOLDER_HANDLE: SimObject(FOLDER_HANDLE, CARD_STORAGE_ID, DCIM_HANDLE, ObjectFormat.ASSOCIATION, "100CANON"),
        }
        self.ram: dict[int, SimObject] = {}
        self.props: dict[int, int] = {
            EosProp.APERTURE: 0x30,
            EosProp.SHUTTER_SPEED: 0x60,
            EosProp.ISO_SPEED: 0x48,
            EosProp.FOCUS_MODE: 3,
            EosProp.CAPTURE_DESTINATION: CAPTURE_DESTINATION_CARD,
            EosProp.AVAILABLE_SHOTS: 999,
        }
        self.image_format_index = 0
        self._events: list[tuple[float, EosEvent]] = []
        self._std_events: list[Container] = []
        self.operations_log: list[int] = []
        self.busy_responses = 0  # fault: answer the next N operations with DeviceBusy
        self.short_partial_bytes = 0  # fault: GetPartialObject sends at most this many bytes (0 = off)
        self.std_event_listeners: list[Callable[[Container], None]] = []

    # -- description -----------------------------------------------------
    def device_info(self) -> DeviceInfo:
        ops = [
            Op.GET_DEVICE_INFO,
            Op.OPEN_SESSION,
            Op.CLOSE_SESSION,
            Op.GET_STORAGE_IDS,
            Op.GET_STORAGE_INFO,
            Op.GET_NUM_OBJECTS,
            Op.GET_OBJECT_HANDLES,
            Op.GET_OBJECT_INFO,
            Op.GET_OBJECT,
            Op.DELETE_OBJECT,
            Op.GET_PARTIAL_OBJECT,
        ]
        if self.eos:
            ops += [
                Op.EOS_GET_OBJECT,
                Op.EOS_GET_PARTIAL_OBJECT,
                Op.EOS_REMOTE_RELEASE,
                Op.EOS_SET_DEVICE_PROP_VALUE_EX,
                Op.EOS_SET_REMOTE_MODE,
                Op.EOS_SET_EVENT_MODE,
                Op.EOS_GET_EVENT,
                Op.EOS_TRANSFER_COMPLETE,
                Op.EOS_PC_HDD_CAPACITY,
                Op.EOS_SET_UI_LOCK,
                Op.EOS_RESET_UI_LOCK,
                Op.EOS_KEEP_DEVICE_ON,
                Op.EOS_REQUEST_DEVICE_PROP_VALUE,
                Op.EOS_REMOTE_RELEASE_ON,
                Op.EOS_REMOTE_RELEASE_OFF,
            ]
        else:
            ops += [Op.INITIATE_CAPTURE]
        return DeviceInfo(
            standard_version=100,
            vendor_extension_id=CANON_VENDOR_EXTENSION_ID if self.eos else 0,
            vendor_extension_version=100,
            vendor_extension_desc="",
            operations=tuple(int(o) for o in ops),
            events=(Event.OBJECT_ADDED, Event.OBJECT_REMOVED, Event.CAPTURE_COMPLETE),
            properties=(0x5001,) if self.eos else (0x5001, 0x500D, 0x500F),
            capture_formats=(ObjectFormat.CANON_CR2, ObjectFormat.JPEG),
            image_formats=(ObjectFormat.ASSOCIATION, ObjectFormat.JPEG, ObjectFormat.CANON_CR2),
            manufacturer="Canon Inc." if self.eos else "Generic",
            model="Canon EOS 70D" if self.eos else "Generic PTP Camera",
            device_version="3-1.1.1",
            serial_number=self.serial_number,
        )

    def storage_info(self) -> StorageInfo:
        used = sum(len(o.data) for o in self.card.values())
        return StorageInfo(
            storage_type=4,
            filesystem_type=2,
            access_capability=0,
            max_capacity_bytes=CARD_CAPACITY_BYTES,
            free_space_bytes=CARD_CAPACITY_BYTES - used,
            free_space_images=max(0, (CARD_CAPACITY_BYTES - used) // (25 * 1024 * 1024)),
            description="SD",
            volume_label="EOS_DIGITAL",
        )

    # -- state changes usable by tests and the app -----------------------
    @staticmethod
    def expects_data_out(code: int) -> bool:
        return code in _DATA_OUT_OPS

    def disconnect(self) -> None:
        """The USB cable or network went away: the session ends (the card keeps its files; RAM shots are lost)."""
        with self.lock:
            self.session_id = 0
            self.event_mode = 0
            self.remote_mode = 0
            self.ram.clear()
            self._events.clear()

    def press_shutter_button(self) -> int:
        """The photographer presses the camera's own shutter button; returns the new handle."""
        with self.lock:
            return self._shoot()

    def file_on_card(self, filename: str) -> bytes:
        for obj in self.card.values():
            if obj.filename == filename:
                return obj.data
        raise KeyError(filename)

    def card_files(self) -> dict[str, bytes]:
        return {o.filename: o.data for o in self.card.values() if o.object_format != ObjectFormat.ASSOCIATION}

    def all_props_events(self) -> list[EosEvent]:
        out: list[EosEvent] = []
        allowed = {
            EosProp.ISO_SPEED: ISO_VALUES,
            EosProp.SHUTTER_SPEED: SHUTTER_VALUES,
            EosProp.APERTURE: APERTURE_VALUES,
            EosProp.CAPTURE_DESTINATION: (CAPTURE_DESTINATION_CARD, CAPTURE_DESTINATION_RAM),
        }
        for prop, value in self.props.items():
            out.append(EosPropValueChanged(int(prop), value))
        out.append(
            EosPropValueChanged(int(EosProp.IMAGE_FORMAT), 0, pack_image_format(IMAGE_FORMATS[self.image_format_index]))
        )
        for prop, values in allowed.items():
            out.append(EosAvailListChanged(int(prop), 3, tuple(values)))
        out.append(
            EosAvailListChanged(
                int(EosProp.IMAGE_FORMAT),
                3,
                tuple(range(len(IMAGE_FORMATS))),
                tuple(pack_image_format(f) for f in IMAGE_FORMATS),
            )
        )
        return out

    # -- internals -------------------------------------------------------
    def _queue(self, event: EosEvent, delay_s: float = 0.0) -> None:
        self._events.append((time.monotonic() + delay_s, event))

    def _take_frame(self) -> tuple[str, bytes]:
        self.shots_taken += 1
        produced = self.frame_source(self.shots_taken)
        if isinstance(produced, tuple):
            name, data = produced
        else:
            name, data = f"IMG_{self.shots_taken:04d}.CR2", produced
        return name, bytes(data)

    def _shoot(self) -> int:
        name, data = self._take_frame()
        handle = self._next_handle
        self._next_handle += 1
        fmt = ObjectFormat.JPEG if name.upper().endswith(".JPG") else ObjectFormat.CANON_CR2
        stamp = time.strftime("%Y%m%dT%H%M%S")
        if self.props[EosProp.CAPTURE_DESTINATION] == CAPTURE_DESTINATION_RAM:
            self.ram[handle] = SimObject(handle, 0, 0, fmt, name, data, stamp)
            event: EosEvent = EosRequestObjectTransfer(handle, fmt, len(data), name)
        else:
            self.card[handle] = SimObject(handle, CARD_STORAGE_ID, FOLDER_HANDLE, fmt, name, data, stamp)
            event = EosObjectAdded(handle, CARD_STORAGE_ID, fmt, len(data), FOLDER_HANDLE, name)
            self.props[EosProp.AVAILABLE_SHOTS] = max(0, self.props[EosProp.AVAILABLE_SHOTS] - 1)
        if self.eos:
            self._queue(EosCameraStatus(True))
            self._queue(event, self.shot_delay_s)
            self._queue(EosCameraStatus(False), self.shot_delay_s)
        else:
            for ev in (
                Container(ContainerType.EVENT, Event.OBJECT_ADDED, 0, (handle,)),
                Container(ContainerType.EVENT, Event.CAPTURE_COMPLETE, 0, ()),
            ):
                self._std_events.append(ev)
                for listener in self.std_event_listeners:
                    listener(ev)
        return handle

    def take_std_events(self) -> list[Container]:
        with self.lock:
            out, self._std_events = self._std_events, []
            return out

    def _object(self, handle: int) -> SimObject | None:
        return self.card.get(handle) or self.ram.get(handle)

    # -- the responder ---------------------------------------------------
    def handle(self, cmd: Container, data_out: bytes | None = None) -> Reply:
        with self.lock:
            self.operations_log.append(cmd.code)
            code, tid, p = cmd.code, cmd.transaction_id, cmd.params

            def ok(*params: int, data: bytes | memoryview | None = None) -> Reply:
                return Reply(Container(ContainerType.RESPONSE, Resp.OK, tid, tuple(params)), data)

            def fail(resp: int) -> Reply:
                return Reply(Container(ContainerType.RESPONSE, resp, tid, ()))

            if code == Op.GET_DEVICE_INFO:
                return ok(data=pack_device_info(self.device_info()))
            if code == Op.OPEN_SESSION:
                if not p or p[0] == 0:
                    return fail(Resp.INVALID_PARAMETER)
                if self.session_id:
                    return Reply(Container(ContainerType.RESPONSE, Resp.SESSION_ALREADY_OPEN, tid, (self.session_id,)))
                self.session_id = p[0]
                return ok()
            if not self.session_id:
                return fail(Resp.SESSION_NOT_OPEN)
            if self.busy_responses > 0 and code not in (Op.EOS_GET_EVENT, Op.CLOSE_SESSION):
                self.busy_responses -= 1
                return fail(Resp.DEVICE_BUSY)
            if code == Op.CLOSE_SESSION:
                self.disconnect()
                return ok()
            if code in (Op.GET_STORAGE_IDS,):
                from mca.devices.ptp.codec import pack_array

                return ok(data=pack_array("I", [CARD_STORAGE_ID]))
            if code == Op.GET_STORAGE_INFO:
                if not p or p[0] != CARD_STORAGE_ID:
                    return fail(Resp.INVALID_STORAGE_ID)
                return ok(data=pack_storage_info(self.storage_info()))
            if code in (Op.GET_OBJECT_HANDLES, Op.GET_NUM_OBJECTS):
                from mca.devices.ptp.codec import pack_array

                storage = p[0] if p else 0xFFFFFFFF
                fmt = p[1] if len(p) > 1 else 0
                parent = p[2] if len(p) > 2 else 0
                if storage not in (0xFFFFFFFF, CARD_STORAGE_ID):
                    return fail(Resp.INVALID_STORAGE_ID)
                handles = [
                    h
                    for h, o in self.card.items()
                    if (not fmt or o.object_format == fmt)
                    and (parent == 0 or (parent == 0xFFFFFFFF and o.parent == 0) or o.parent == parent)
                ]
                if code == Op.GET_NUM_OBJECTS:
                    return ok(len(handles))
                return ok(data=pack_array("I", handles))
            if code == Op.GET_OBJECT_INFO:
                obj = self._object(p[0]) if p else None
                return ok(data=pack_object_info(obj.info())) if obj else fail(Resp.INVALID_OBJECT_HANDLE)
            if code in (Op.GET_OBJECT, Op.EOS_GET_OBJECT):
                obj = self._object(p[0]) if p else None
                return ok(data=memoryview(obj.data)) if obj else fail(Resp.INVALID_OBJECT_HANDLE)
            if code in (Op.GET_PARTIAL_OBJECT, Op.EOS_GET_PARTIAL_OBJECT):
                if len(p) < 3:
                    return fail(Resp.PARAMETER_NOT_SUPPORTED)
                obj = self._object(p[0])
                if obj is None:
                    return fail(Resp.INVALID_OBJECT_HANDLE)
                offset, want = p[1], p[2]
                if offset > len(obj.data):
                    return fail(Resp.INVALID_PARAMETER)
                if self.short_partial_bytes:
                    want = min(want, self.short_partial_bytes)
                piece = memoryview(obj.data)[offset : offset + want]
                return ok(len(piece), data=piece)
            if code == Op.DELETE_OBJECT:
                obj = self.card.pop(p[0], None) if p else None
                if obj is None:
                    return fail(Resp.INVALID_OBJECT_HANDLE)
                if self.eos:
                    self._queue(EosObjectRemoved(obj.handle))
                return ok()
            if code == Op.INITIATE_CAPTURE:
                if self.eos:
                    return fail(Resp.OPERATION_NOT_SUPPORTED)
                self._shoot()
                return ok()
            if not self.eos:
                return fail(Resp.OPERATION_NOT_SUPPORTED)
            return self._handle_eos(code, p, data_out, ok, fail)

    def _handle_eos(self, code, p, data_out, ok, fail) -> Reply:
        import struct

        if code == Op.EOS_SET_REMOTE_MODE:
            self.remote_mode = p[0] if p else 0
            return ok()
        if code == Op.EOS_SET_EVENT_MODE:
            if p and p[0] and not self.event_mode:
                for e in self.all_props_events():
                    self._queue(e)
            self.event_mode = p[0] if p else 0
            return ok()
        if code == Op.EOS_GET_EVENT:
            now = time.monotonic()
            ready = [e for t, e in self._events if t <= now]
            self._events = [(t, e) for t, e in self._events if t > now]
            return ok(data=pack_eos_events(ready))
        if code in (
            Op.EOS_KEEP_DEVICE_ON,
            Op.EOS_SET_UI_LOCK,
            Op.EOS_RESET_UI_LOCK,
            Op.EOS_PC_HDD_CAPACITY,
            Op.EOS_REQUEST_DEVICE_PROP_VALUE,
            Op.EOS_REMOTE_RELEASE_OFF,
        ):
            return ok()
        if code == Op.EOS_TRANSFER_COMPLETE:
            if not p or self.ram.pop(p[0], None) is None:
                return fail(Resp.INVALID_OBJECT_HANDLE)
            return ok()
        if code in (Op.EOS_REMOTE_RELEASE, Op.EOS_REMOTE_RELEASE_ON):
            if code == Op.EOS_REMOTE_RELEASE_ON and (not p or p[0] != 2):
                return ok()  # half press: focus only
            if (
                self.props[EosProp.CAPTURE_DESTINATION] == CAPTURE_DESTINATION_RAM
                and len(self.ram) >= self.ram_buffer_slots
            ):
                return fail(Resp.DEVICE_BUSY)
            self._shoot()
            return ok(0) if code == Op.EOS_REMOTE_RELEASE else ok()
        if code == Op.EOS_SET_DEVICE_PROP_VALUE_EX:
            if data_out is None or len(data_out) < 12:
                return fail(Resp.INVALID_PARAMETER)
            size, prop = struct.unpack_from("<II", data_out)
            if size != len(data_out):
                return fail(Resp.INVALID_PARAMETER)
            if prop == EosProp.IMAGE_FORMAT:
                raw = bytes(data_out[8:])
                packed = [pack_image_format(f) for f in IMAGE_FORMATS]
                if raw not in packed:
                    return fail(Resp.INVALID_DEVICE_PROP_VALUE)
                self.image_format_index = packed.index(raw)
                self._queue(EosPropValueChanged(prop, 0, raw))
                return ok()
            (value,) = struct.unpack_from("<I", data_out, 8)
            valid = {
                EosProp.ISO_SPEED: ISO_VALUES,
                EosProp.SHUTTER_SPEED: SHUTTER_VALUES,
                EosProp.APERTURE: APERTURE_VALUES,
                EosProp.CAPTURE_DESTINATION: (CAPTURE_DESTINATION_CARD, CAPTURE_DESTINATION_RAM),
            }
            if prop not in valid:
                return fail(Resp.DEVICE_PROP_NOT_SUPPORTED)
            if value not in valid[prop]:
                return fail(Resp.INVALID_DEVICE_PROP_VALUE)
            self.props[prop] = value
            self._queue(EosPropValueChanged(prop, value))
            return ok()
        return fail(Resp.OPERATION_NOT_SUPPORTED)
