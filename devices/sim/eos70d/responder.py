"""The simulated EOS 70D's PTP responder: sessions, storage, properties, remote release, GetEvent, RAM buffer, live view.

Transport-agnostic: `handle(command, data_out)` takes a parsed command
container (and the data-out payload) and returns the data-in payload and the
response, using the same codec as the host side. The body behaves like the real
one as public sources describe it (`facts_70d`): it reports Microsoft's
vendor extension id 6 and the 70D's 169 operations; its settings arrive spread
over several GetEvent polls; the half press takes time (autofocus) and a
FocusInfoEx report follows; the release is answered at once and the new file
announced in a later poll, after the frame is "written"; records no host has
a parser for appear in the event lists. `exposures` counts shutter actuations.
"""

from __future__ import annotations

import hashlib
import queue
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mca.devices.ptp.codec import Container, pack_array, pack_string
from mca.devices.ptp.codes import (
    CAPTURE_DESTINATION_CARD,
    CAPTURE_DESTINATION_RAM,
    ContainerType,
    EosEventCode,
    EosProp,
    Event,
    ObjectFormat,
    Op,
    Resp,
)
from mca.devices.ptp.datasets import (
    DeviceInfo,
    DevicePropDesc,
    EosDeviceInfoEx,
    EosFolderEntry,
    ObjectInfo,
    StorageInfo,
    pack_device_info,
    pack_eos_device_info_ex,
    pack_eos_folder_entries,
    pack_object_info,
    pack_prop_desc,
    pack_storage_info,
)
from mca.devices.ptp.events import (
    AVAIL_LIST_ENUM,
    EosAvailListChanged,
    EosCameraStatus,
    EosEvent,
    EosObjectAdded,
    EosObjectRemoved,
    EosPropValueChanged,
    EosRequestObjectTransfer,
    EosUnknownEvent,
    image_format_of,
    pack_eos_events,
    pack_focus_info_ex,
    pack_image_format,
)
from mca.devices.ptp.liveview import pack_viewfinder_data
from mca.devices.ptp.properties import EOS_APERTURE, EOS_ISO, EOS_SHUTTER
from mca.devices.sim.eos70d import facts_70d

#: A frame source gives the bytes of shot number `index` (1-based), or `(file name, bytes)`.
FrameSource = Callable[[int], "bytes | tuple[str, bytes]"]
#: A live-view source gives the JPEG bytes of live-view frame number `index` (1-based).
LiveViewSource = Callable[[int], bytes]

CARD_STORAGE_ID = 0x00020001
DCIM_HANDLE = 0x90000001
FOLDER_HANDLE = 0x90000002
FIRST_FILE_HANDLE = 0x91000001
CARD_CAPACITY_BYTES = 16 * 1024**3
#: The 70D's live-view JPEG: 960 x 540 px, about 160 kB (a PTP/IP study of the 70D, julianschroden.com, 2023).
LIVE_VIEW_SIZE_PX = (960, 540)
SHOTS_PER_CARD = 999
AF_POINTS = 19  # the 70D's 19 cross-type points
IMAGE_SIZE_PX = (5472, 3648)

# The user's settings on the simulated body (the dump's owner had another lens and mode; see facts_70d):
# manual exposure (M) with the MCA lens, a 50 mm f/1.8, RAW, ISO 100.
ISO_VALUES = (0x00, *(k for k in EOS_ISO if 0x48 <= k <= 0x80), 0x88)  # Auto, 100 ... 12800, H (25600)
SHUTTER_VALUES = tuple(k for k in EOS_SHUTTER if 0x10 <= k <= 0xA0 and (k - 0x10) % 8 in (0, 3, 5))
APERTURE_VALUES = tuple(k for k in EOS_APERTURE if 0x15 <= k <= 0x50 and (k - 0x08) % 8 in (0, 3, 5))
IMAGE_FORMATS = (
    ((6, 0, 4),),  # RAW
    ((1, 0, 3),),  # Large Fine JPEG
    ((1, 0, 2),),  # Large Normal JPEG
    ((6, 0, 4), (1, 0, 3)),  # RAW + Large Fine JPEG
)
USER_SETTINGS: dict[int, int] = {
    EosProp.AUTO_EXPOSURE_MODE: 3,  # M
    EosProp.APERTURE: 0x15,  # f/1.8
    EosProp.SHUTTER_SPEED: 0x70,  # 1/125 s
    EosProp.ISO_SPEED: 0x48,  # ISO 100
    EosProp.AVAILABLE_SHOTS: SHOTS_PER_CARD,
}
USER_LENS = "EF50mm f/1.8 II"


def deterministic_frame(index: int, size_bytes: int = 256 * 1024) -> bytes:
    """A reproducible stand-in file for shot `index`: a TIFF-like CR2 header then hash-derived bytes."""
    head = b"II*\x00\x10\x00\x00\x00CR\x02\x00" + f"SIM-EOS70D shot {index:06d}".encode()
    block = hashlib.sha256(f"frame {index}".encode()).digest() * 64
    body = (block * (size_bytes // len(block) + 1))[: max(0, size_bytes - len(head))]
    return head + body


def default_frame_source(index: int) -> tuple[str, bytes]:
    return f"IMG_{index:04d}.CR2", deterministic_frame(index)


def jpeg_twin(name: str, index: int) -> tuple[str, bytes]:
    """The JPEG file of a RAW+JPEG shot: same base name, a small deterministic JPEG-like body."""
    base = name.rsplit(".", 1)[0]
    body = hashlib.sha256(f"jpeg {index}".encode()).digest() * 512
    return f"{base}.JPG", b"\xff\xd8\xff\xe1" + body + b"\xff\xd9"


def default_live_view_source(index: int) -> bytes:
    """A stand-in live-view JPEG (a moving gradient) when no scene renderer is attached."""
    import cv2
    import numpy as np

    w, h = LIVE_VIEW_SIZE_PX
    x = np.linspace(0, 255, w, dtype=np.float32)[None, :]
    y = np.linspace(0, 255, h, dtype=np.float32)[:, None]
    image = np.stack([np.broadcast_to((x + 3 * index) % 256, (h, w)), np.broadcast_to(y, (h, w)), (x + y) / 2], -1)
    ok, encoded = cv2.imencode(".jpg", image.astype(np.uint8))
    if not ok:
        raise RuntimeError("could not encode a live-view frame")
    return encoded.tobytes()


@dataclass
class SimObject:
    handle: int
    storage_id: int
    parent: int
    object_format: int
    filename: str
    data: bytes = field(repr=False, default=b"")
    capture_date: str = ""
    written: bool = True  # False while a shot in camera RAM is still being processed

    def info(self) -> ObjectInfo:
        is_folder = self.object_format == ObjectFormat.ASSOCIATION
        return ObjectInfo(
            storage_id=self.storage_id,
            object_format=self.object_format,
            compressed_size_bytes=len(self.data),
            image_width_px=0 if is_folder else IMAGE_SIZE_PX[0],
            image_height_px=0 if is_folder else IMAGE_SIZE_PX[1],
            image_bit_depth=0 if is_folder else 14,
            parent_object=self.parent,
            association_type=1 if is_folder else 0,
            filename=self.filename,
            capture_date=self.capture_date,
            modification_date=self.capture_date,
        )


@dataclass(frozen=True)
class Reply:
    """What the responder sends back: an optional data-in payload and the response.

    `delay_s`: the reply is ready only this long after the command (a half press while focusing, a slow
    body); `dropped`: the camera acted but its reply never comes (the host times out).
    """

    response: Container
    data: bytes | memoryview | None = None
    delay_s: float = 0.0
    dropped: bool = False


@dataclass
class SimBehaviour:
    """How the simulated body behaves; the defaults follow the real 70D, scenarios change single values."""

    vendor_extension_id: int = facts_70d.VENDOR_EXTENSION_ID
    #: The initial settings are spread over this many GetEvent polls (one batch per poll).
    settings_polls: int = 3
    #: ... and the first batch is ready only this long after SetEventMode(1).
    settings_delay_s: float = 0.0
    #: The half press answers after the autofocus ran this long (a slow lens takes up to 8 s).
    half_press_s: float = 0.05
    #: "focused", "failed" (no point in focus), or "none" (the body sends no FocusInfoEx).
    af_result: str = "focused"
    #: The full press answers DeviceBusy and nothing is taken (an EOS R10 trace shows this).
    full_press_busy: bool = False
    #: Camera status stays busy this long after a shot (card write); a release meanwhile answers busy.
    busy_after_shot_s: float = 0.0
    #: Event lists carry records no host has a parser for (0xC1F6, an OLC block, lists of types 1 and 7).
    unknown_records: bool = False
    #: The card already holds this many files (in 100CANON and 101CANON) when the session starts.
    files_on_card: int = 0
    #: Focus mode (0xD108) to start in: 0 One-Shot AF, 1 AI Servo, 2 AI Focus (the dump's), 3 manual.
    focus_mode: int | None = None


#: MTP GetObjectPropsSupported (the 70D lists MTP's object-property operations 0x9801-0x9805).
MTP_GET_OBJECT_PROPS_SUPPORTED = 0x9801
_DATA_OUT_OPS = {Op.SET_DEVICE_PROP_VALUE, Op.EOS_SET_DEVICE_PROP_VALUE_EX, Op.SEND_OBJECT_INFO, Op.SEND_OBJECT}
#: Operations a busy body still answers normally.
_ALWAYS_ANSWERED = {Op.EOS_GET_EVENT, Op.CLOSE_SESSION, Op.EOS_REMOTE_RELEASE_OFF, Op.EOS_KEEP_DEVICE_ON}
_RELEASES = {Op.EOS_REMOTE_RELEASE, Op.INITIATE_CAPTURE}


def _u32(value: int) -> bytes:
    return struct.pack("<I", value)


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
        behaviour: SimBehaviour | None = None,
        live_view_source: LiveViewSource | None = None,
    ) -> None:
        self.frame_source = frame_source or default_frame_source
        self.live_view_source = live_view_source or default_live_view_source
        self.serial_number = serial_number
        self.ram_buffer_slots = ram_buffer_slots
        self.shot_delay_s = shot_delay_s
        self.eos = eos
        self.behaviour = behaviour or SimBehaviour()
        self.lock = threading.RLock()
        self.session_id = 0
        self.event_mode = 0
        self.remote_mode = 0
        self.exposures = 0  # shutter actuations: the fault suite checks one per requested shot
        self.full_presses = 0
        self.half_pressed = False
        self.live_view_frames = 0
        self._next_handle = FIRST_FILE_HANDLE
        self.card: dict[int, SimObject] = {
            DCIM_HANDLE: SimObject(DCIM_HANDLE, CARD_STORAGE_ID, 0, ObjectFormat.ASSOCIATION, "DCIM"),
            FOLDER_HANDLE: SimObject(FOLDER_HANDLE, CARD_STORAGE_ID, DCIM_HANDLE, ObjectFormat.ASSOCIATION, "100CANON"),
        }
        self.ram: dict[int, SimObject] = {}
        self.values: dict[int, bytes] = {}
        self.lists: dict[int, tuple[int, int, bytes]] = {}
        self._load_facts()  # after `behaviour`: it may override a setting
        self._batches: list[tuple[float, list[EosEvent]]] = []
        self._std_events: list[Container] = []
        self.operations_log: list[int] = []
        self.busy_responses = 0  # fault: answer the next N operations (not releases, not GetEvent) with DeviceBusy
        self.short_partial_bytes = 0  # fault: GetPartialObject sends at most this many bytes (0 = off)
        self.std_event_listeners: list[Callable[[Container], None]] = []
        self._busy_until = 0.0
        self._writes: queue.Queue = queue.Queue()  # shots are processed one after the other, in order
        self._writer: threading.Thread | None = None
        self._populate_card(self.behaviour.files_on_card)

    # -- the body's settings, from the public facts ----------------------------------------------------------------
    def _load_facts(self) -> None:
        self._initial_order = [prop for prop, _raw in facts_70d.INITIAL_VALUES]  # 0xD1A0 comes three times
        self._initial_raw = [bytes.fromhex(raw) for _prop, raw in facts_70d.INITIAL_VALUES]
        for prop, raw in facts_70d.INITIAL_VALUES:
            self.values[prop] = bytes.fromhex(raw)
        for prop, kind, count, raw in facts_70d.INITIAL_LISTS:
            self.lists[prop] = (kind, count, bytes.fromhex(raw))
        self._requested = {prop: bytes.fromhex(raw) for prop, raw in facts_70d.REQUESTED_VALUES}
        for prop, value in USER_SETTINGS.items():
            self.values[prop] = _u32(value)
        lens = USER_LENS.encode()
        self.values[EosProp.LENS_NAME] = lens + bytes(max(0, len(self.values[EosProp.LENS_NAME]) - len(lens)))
        self.values[EosProp.IMAGE_FORMAT] = pack_image_format(IMAGE_FORMATS[0])
        for prop, values in (
            (EosProp.ISO_SPEED, ISO_VALUES),
            (EosProp.SHUTTER_SPEED, SHUTTER_VALUES),
            (EosProp.APERTURE, APERTURE_VALUES),
        ):
            self.lists[prop] = (AVAIL_LIST_ENUM, len(values), b"".join(_u32(v) for v in values))
        raws = [pack_image_format(f) for f in IMAGE_FORMATS]
        self.lists[EosProp.IMAGE_FORMAT] = (AVAIL_LIST_ENUM, len(raws), b"".join(raws))
        self.values[EosProp.CAMERA_TIME] = _u32(int(time.time()))
        if self.behaviour.focus_mode is not None:
            self.values[EosProp.FOCUS_MODE] = _u32(self.behaviour.focus_mode)

    def value(self, prop: int) -> int:
        return int.from_bytes(self.values.get(prop, b"")[:4], "little")

    def allowed(self, prop: int) -> tuple[int, ...]:
        kind, count, raw = self.lists.get(prop, (0, 0, b""))
        if kind != AVAIL_LIST_ENUM or not count or prop == EosProp.IMAGE_FORMAT:
            return ()
        size = len(raw) // count
        return tuple(int.from_bytes(raw[i * size : i * size + 4], "little") for i in range(count))

    @property
    def props(self) -> dict[int, int]:
        """The u32 value of every property (a read-only view for tests)."""
        return {p: self.value(p) for p in self.values}

    @property
    def shots_taken(self) -> int:
        return self.exposures

    @property
    def image_format(self) -> tuple[tuple[int, int, int], ...]:
        return image_format_of(self.values[EosProp.IMAGE_FORMAT]) or IMAGE_FORMATS[0]

    def _populate_card(self, count: int) -> None:
        """Files already on the card: JPEGs in 100CANON, and a second folder 101CANON."""
        if not count:
            return
        second = self._next_handle + 10_000
        self.card[second] = SimObject(second, CARD_STORAGE_ID, DCIM_HANDLE, ObjectFormat.ASSOCIATION, "101CANON")
        for i in range(count):
            handle = self._next_handle
            self._next_handle += 1
            parent = FOLDER_HANDLE if i % 2 == 0 else second
            name = f"IMG_{9000 + i:04d}.JPG"
            data = hashlib.sha256(name.encode()).digest() * (64 + i)
            self.card[handle] = SimObject(
                handle, CARD_STORAGE_ID, parent, ObjectFormat.JPEG, name, data, "20240101T120000"
            )

    # -- description -----------------------------------------------------
    def device_info(self) -> DeviceInfo:
        if not self.eos:
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
                Op.INITIATE_CAPTURE,
            ]
            return DeviceInfo(
                standard_version=100,
                vendor_extension_id=0,
                vendor_extension_version=100,
                operations=tuple(int(o) for o in ops),
                events=(Event.OBJECT_ADDED, Event.OBJECT_REMOVED, Event.CAPTURE_COMPLETE),
                properties=(0x5001, 0x500D, 0x500F),
                capture_formats=(ObjectFormat.JPEG,),
                image_formats=(ObjectFormat.ASSOCIATION, ObjectFormat.JPEG),
                manufacturer="Generic",
                model="Generic PTP Camera",
                device_version="1.0",
                serial_number=self.serial_number,
            )
        return DeviceInfo(
            standard_version=facts_70d.STANDARD_VERSION,
            vendor_extension_id=self.behaviour.vendor_extension_id,
            vendor_extension_version=facts_70d.VENDOR_EXTENSION_VERSION,
            vendor_extension_desc=facts_70d.VENDOR_EXTENSION_DESC,
            functional_mode=facts_70d.FUNCTIONAL_MODE,
            operations=facts_70d.OPERATIONS,
            events=facts_70d.EVENTS,
            properties=facts_70d.DEVICE_PROPS,
            capture_formats=facts_70d.CAPTURE_FORMATS,
            image_formats=facts_70d.IMAGE_FORMATS,
            manufacturer=facts_70d.MANUFACTURER,
            model=facts_70d.MODEL,
            device_version=facts_70d.FIRMWARE,
            serial_number=self.serial_number,
        )

    def device_info_ex(self) -> EosDeviceInfoEx:
        return EosDeviceInfoEx(facts_70d.EX_EVENTS, facts_70d.EX_PROPS, facts_70d.EX_UNKNOWN)

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

    def std_prop_desc(self, code: int) -> bytes | None:
        """GetDevicePropDesc of the standard properties the 70D lists; BatteryLevel with its u16 enumeration."""
        entry = facts_70d.STD_PROPS.get(code)
        if entry is None:
            return None
        datatype, writable, value, enum = entry
        if code == 0x5001 and isinstance(value, int):
            head = struct.pack("<HHB", code, datatype, int(writable)) + bytes([value, value])
            return head + b"\x02" + struct.pack(f"<H{len(enum)}H", len(enum), *enum)
        return pack_prop_desc(DevicePropDesc(code, datatype, writable, value, value))

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
            self.half_pressed = False
            self.ram.clear()
            self._batches.clear()
            self.values[EosProp.EVF_OUTPUT_DEVICE] = _u32(0)

    def press_shutter_button(self) -> int:
        """The photographer presses the camera's own shutter button; returns the new handle."""
        with self.lock:
            return self._expose()

    def wait_idle(self, timeout_s: float = 60.0) -> None:
        """Wait until every shot has been written (tests use it before checking the card)."""
        deadline = time.monotonic() + timeout_s
        while self._writes.unfinished_tasks and time.monotonic() < deadline:
            time.sleep(0.005)

    def file_on_card(self, filename: str) -> bytes:
        self.wait_idle()
        for obj in self.card.values():
            if obj.filename == filename:
                return obj.data
        raise KeyError(filename)

    def card_files(self) -> dict[str, bytes]:
        self.wait_idle()
        return {o.filename: o.data for o in self.card.values() if o.object_format != ObjectFormat.ASSOCIATION}

    def all_props_events(self) -> list[EosEvent]:
        """The initial dump: every value record then every list record, in the 70D's order (a property the
        dump repeats, 0xD1A0, is repeated; the others carry their current value)."""
        out: list[EosEvent] = []
        repeated = {p for p in self._initial_order if self._initial_order.count(p) > 1}
        for prop, initial in zip(self._initial_order, self._initial_raw, strict=True):
            raw = initial if prop in repeated else self.values[prop]
            out.append(EosPropValueChanged(prop, int.from_bytes(raw[:4], "little"), raw))
        for prop, raw in self.values.items():
            if prop not in self._initial_order and prop not in self._requested:
                out.append(EosPropValueChanged(prop, int.from_bytes(raw[:4], "little"), raw))
        for prop, (kind, count, raw) in self.lists.items():
            out.append(self._list_event(prop, kind, count, raw))
        return out

    @staticmethod
    def _list_event(prop: int, kind: int, count: int, raw: bytes) -> EosAvailListChanged:
        if not count:
            return EosAvailListChanged(prop, kind, (), (raw,) if raw else ())
        if prop == EosProp.IMAGE_FORMAT or prop in (EosProp.IMAGE_FORMAT_CF, EosProp.IMAGE_FORMAT_SD):
            items, pos = [], 0
            while pos < len(raw):
                n = int.from_bytes(raw[pos : pos + 4], "little")
                size = 4 + 16 * n
                items.append(raw[pos : pos + size])
                pos += size
            return EosAvailListChanged(prop, kind, tuple(range(len(items))), tuple(items))
        size = len(raw) // count
        items = [raw[i * size : (i + 1) * size] for i in range(count)]
        return EosAvailListChanged(prop, kind, tuple(int.from_bytes(x[:4], "little") for x in items), tuple(items))

    # -- internals -------------------------------------------------------
    def _queue(self, events: list[EosEvent], delay_s: float = 0.0) -> None:
        """One batch for one GetEvent poll, ready after `delay_s`; batches come out in order of readiness."""
        ready = time.monotonic() + delay_s
        at = len(self._batches)
        while at and self._batches[at - 1][0] > ready:
            at -= 1
        self._batches.insert(at, (ready, list(events)))

    def _queue_value(self, prop: int, delay_s: float = 0.0) -> None:
        raw = self.values[prop]
        self._queue([EosPropValueChanged(prop, int.from_bytes(raw[:4], "little"), raw)], delay_s)

    def _unknown_records(self) -> list[EosEvent]:
        if not self.behaviour.unknown_records:
            return []
        olc = struct.pack("<IH", 20, 0x0001) + bytes(14)
        return [
            EosUnknownEvent(0xC1F6, _u32(0)),  # an R10 sends this one
            EosUnknownEvent(EosEventCode.OLC_INFO_CHANGED, olc),
            EosAvailListChanged(0xD1FE, 7, (), ()),
            EosUnknownEvent(0xC1FF, b"\x01\x02\x03"),  # an odd size, not a multiple of 4
        ]

    def _take_frame(self, index: int) -> tuple[str, bytes]:
        produced = self.frame_source(index)
        if isinstance(produced, tuple):
            name, data = produced
        else:
            name, data = f"IMG_{index:04d}.CR2", produced
        return name, bytes(data)

    def _expose(self) -> int:
        """The shutter fires: count it, answer at once, write the file(s) in the background and announce them."""
        self.exposures += 1
        index = self.exposures
        handle = self._next_handle
        files = self.image_format
        self._next_handle += len(files)
        to_ram = self.value(EosProp.CAPTURE_DESTINATION) == CAPTURE_DESTINATION_RAM
        if to_ram:  # reserve the buffer slot now; the camera reports busy on the next release if it is full
            self.ram[handle] = SimObject(handle, 0, 0, ObjectFormat.CANON_CR2, f"IMG_{index:04d}.CR2", written=False)
        if self.eos:
            self._queue([EosCameraStatus(1)])
        self._busy_until = time.monotonic() + self.behaviour.busy_after_shot_s
        shutter_counter = EosProp.SHUTTER_COUNTER
        if shutter_counter in self.values:
            self.values[shutter_counter] = _u32(self.value(shutter_counter) + 1)
        if not self.eos:  # a generic camera here writes before it answers
            self._write_shot(index, handle, files, to_ram)
            return handle
        self._writes.put((index, handle, files, to_ram))
        if self._writer is None:  # (under self.lock; the writer clears it under the same lock when it ends)
            self._writer = threading.Thread(target=self._write_loop, name="sim-eos70d-writer", daemon=True)
            self._writer.start()
        return handle

    def _write_loop(self) -> None:
        while True:
            try:
                job = self._writes.get(timeout=1.0)
            except queue.Empty:
                with self.lock:
                    if self._writes.empty():
                        self._writer = None  # idle: end; the next shot starts a new writer
                        return
                continue
            try:
                self._write_shot(*job)
            finally:
                self._writes.task_done()

    def _write_shot(self, index: int, handle: int, files: tuple, to_ram: bool) -> None:
        name, data = self._take_frame(index)
        made = [(name, data)]
        if len(files) == 2:
            made.append(jpeg_twin(name, index))
        if self.shot_delay_s:
            time.sleep(self.shot_delay_s)
        stamp = time.strftime("%Y%m%dT%H%M%S")
        with self.lock:
            events: list[EosEvent] = []
            for k, (fname, fdata) in enumerate(made):
                h = handle + k
                fmt = ObjectFormat.JPEG if fname.upper().endswith(".JPG") else ObjectFormat.CANON_CR2
                if to_ram:
                    self.ram[h] = SimObject(h, 0, 0, fmt, fname, fdata, stamp)
                    events.append(EosRequestObjectTransfer(h, fmt, len(fdata), fname))
                else:
                    self.card[h] = SimObject(h, CARD_STORAGE_ID, FOLDER_HANDLE, fmt, fname, fdata, stamp)
                    events.append(EosObjectAdded(h, CARD_STORAGE_ID, fmt, len(fdata), FOLDER_HANDLE, fname))
            if not to_ram:
                self.values[EosProp.AVAILABLE_SHOTS] = _u32(max(0, self.value(EosProp.AVAILABLE_SHOTS) - 1))
            if self.eos:  # the status turns back to ready when the card write (busy_after_shot_s) is over
                self._queue(events + [self._value_event(EosProp.AVAILABLE_SHOTS)])
                self._queue([EosCameraStatus(0)], max(0.0, self._busy_until - time.monotonic()))
                return
            for h in range(handle, handle + len(made)):
                for ev in (Container(ContainerType.EVENT, Event.OBJECT_ADDED, 0, (h,)),):
                    self._std_events.append(ev)
                    for listener in self.std_event_listeners:
                        listener(ev)
            ev = Container(ContainerType.EVENT, Event.CAPTURE_COMPLETE, 0, ())
            self._std_events.append(ev)
            for listener in self.std_event_listeners:
                listener(ev)

    def _value_event(self, prop: int) -> EosPropValueChanged:
        raw = self.values[prop]
        return EosPropValueChanged(prop, int.from_bytes(raw[:4], "little"), raw)

    def take_std_events(self) -> list[Container]:
        with self.lock:
            out, self._std_events = self._std_events, []
            return out

    def _object(self, handle: int) -> SimObject | None:
        obj = self.card.get(handle) or self.ram.get(handle)
        return obj if obj is not None and obj.written else None

    def _initial_dump(self) -> None:
        """The settings after SetEventMode(1): values then lists, spread over `settings_polls` batches."""
        events = self.all_props_events() + self._unknown_records()
        n = max(1, self.behaviour.settings_polls)
        size = -(-len(events) // n)
        for k in range(n):
            chunk = events[k * size : (k + 1) * size]
            if chunk:
                self._queue(chunk, self.behaviour.settings_delay_s)  # one batch per poll, in order

    def _focus_report(self) -> EosPropValueChanged | None:
        result = self.behaviour.af_result
        if result == "none":
            return None
        points = [((i % 5 - 2) * 400, (i // 5 - 2) * 300, 229, 277) for i in range(AF_POINTS)]
        focused = {AF_POINTS // 2} if result == "focused" else set()
        raw = pack_focus_info_ex(points, focused, IMAGE_SIZE_PX)
        self.values[EosProp.FOCUS_INFO_EX] = raw
        return EosPropValueChanged(EosProp.FOCUS_INFO_EX, int.from_bytes(raw[:4], "little"), raw)

    # -- the responder ---------------------------------------------------
    def handle(self, cmd: Container, data_out: bytes | None = None) -> Reply:
        with self.lock:
            self.operations_log.append(cmd.code)
            code, tid, p = cmd.code, cmd.transaction_id, cmd.params

            def ok(*params: int, data: bytes | memoryview | None = None, delay_s: float = 0.0) -> Reply:
                return Reply(Container(ContainerType.RESPONSE, Resp.OK, tid, tuple(params)), data, delay_s)

            def fail(resp: int, *params: int) -> Reply:
                return Reply(Container(ContainerType.RESPONSE, resp, tid, tuple(params)))

            if code == Op.GET_DEVICE_INFO:
                return ok(data=pack_device_info(self.device_info()))
            if code == Op.OPEN_SESSION:
                if not p or p[0] == 0:
                    return fail(Resp.INVALID_PARAMETER)
                if self.session_id:
                    return fail(Resp.SESSION_ALREADY_OPEN, self.session_id)
                self.session_id = p[0]
                return ok()
            if not self.session_id:
                return fail(Resp.SESSION_NOT_OPEN)
            is_release = code in _RELEASES or (code == Op.EOS_REMOTE_RELEASE_ON and p and p[0] != 1)
            if self.busy_responses > 0 and code not in _ALWAYS_ANSWERED and not is_release:
                self.busy_responses -= 1
                return fail(Resp.DEVICE_BUSY)
            if code == Op.CLOSE_SESSION:
                self.disconnect()
                return ok()
            if code in (Op.GET_STORAGE_IDS, Op.EOS_GET_STORAGE_IDS):
                return ok(data=pack_array("I", [CARD_STORAGE_ID]))
            if code in (Op.GET_STORAGE_INFO, Op.EOS_GET_STORAGE_INFO):
                if not p or p[0] != CARD_STORAGE_ID:
                    return fail(Resp.INVALID_STORAGE_ID)
                return ok(data=pack_storage_info(self.storage_info()))
            if code in (Op.GET_OBJECT_HANDLES, Op.GET_NUM_OBJECTS):
                storage = p[0] if p else 0xFFFFFFFF
                fmt = p[1] if len(p) > 1 else 0
                parent = p[2] if len(p) > 2 else 0
                if storage not in (0xFFFFFFFF, CARD_STORAGE_ID):
                    return fail(Resp.INVALID_STORAGE_ID)
                handles = [
                    h
                    for h, o in self.card.items()
                    if self._object(h) is not None
                    and (not fmt or o.object_format == fmt)
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
                    self._queue([EosObjectRemoved(obj.handle)])
                return ok()
            if code == Op.GET_DEVICE_PROP_DESC:
                desc = self.std_prop_desc(p[0]) if p else None
                return ok(data=desc) if desc is not None else fail(Resp.DEVICE_PROP_NOT_SUPPORTED)
            if code == Op.GET_DEVICE_PROP_VALUE:
                entry = facts_70d.STD_PROPS.get(p[0]) if p else None
                if entry is None:
                    return fail(Resp.DEVICE_PROP_NOT_SUPPORTED)
                datatype, _writable, value, _enum = entry
                raw = (
                    pack_string(str(value))
                    if datatype == 0xFFFF
                    else struct.pack("<I" if datatype == 6 else "<B", int(value))
                )
                return ok(data=raw)
            if code == MTP_GET_OBJECT_PROPS_SUPPORTED:  # the 70D lists MTP's 0x9801; it offers none here
                return ok(data=pack_array("H", []))
            if code == Op.INITIATE_CAPTURE:
                if self.eos:
                    return fail(Resp.OPERATION_NOT_SUPPORTED)
                self._expose()
                return ok()
            if not self.eos:
                return fail(Resp.OPERATION_NOT_SUPPORTED)
            return self._handle_eos(code, p, data_out, ok, fail)

    def _handle_eos(self, code, p, data_out, ok, fail) -> Reply:
        b = self.behaviour
        if code == Op.EOS_SET_REMOTE_MODE:
            self.remote_mode = p[0] if p else 0
            return ok()
        if code == Op.EOS_SET_EVENT_MODE:
            if p and p[0] and not self.event_mode:
                self._initial_dump()
            self.event_mode = p[0] if p else 0
            return ok()
        if code == Op.EOS_GET_EVENT:
            now = time.monotonic()
            for i, (ready, events) in enumerate(self._batches):
                if ready <= now:
                    del self._batches[i]
                    return ok(data=pack_eos_events(events))
                break  # batches come out in order: a later one waits for an earlier one
            return ok(data=pack_eos_events([]))
        if code == Op.EOS_GET_DEVICE_INFO_EX:
            return ok(data=pack_eos_device_info_ex(self.device_info_ex()))
        if code == Op.EOS_GET_OBJECT_INFO_EX:
            return self._folder_listing(p, ok, fail)
        if code == Op.EOS_REQUEST_DEVICE_PROP_VALUE:
            prop = p[0] if p else 0
            if prop in self._requested:
                self.values[prop] = self._requested[prop]
                self._queue_value(prop)
                return ok()
            return fail(Resp.GENERAL_ERROR)
        if code == Op.EOS_SET_REQUEST_OLC_INFO_GROUP:
            if b.unknown_records:
                self._queue(
                    [EosUnknownEvent(EosEventCode.OLC_INFO_CHANGED, struct.pack("<IH", 20, 0x000F) + bytes(14))]
                )
            return ok()
        if code in (Op.EOS_KEEP_DEVICE_ON, Op.EOS_SET_UI_LOCK, Op.EOS_RESET_UI_LOCK, Op.EOS_AF_CANCEL):
            return ok()
        if code == Op.EOS_PC_HDD_CAPACITY:
            return ok()
        if code == Op.EOS_TRANSFER_COMPLETE:
            if not p or self.ram.pop(p[0], None) is None:
                return fail(Resp.INVALID_OBJECT_HANDLE)
            return ok()
        if code == Op.EOS_REMOTE_RELEASE_OFF:
            if p and p[0] in (1, 3):
                self.half_pressed = False
            return ok()
        if code == Op.EOS_REMOTE_RELEASE_ON and p and p[0] == 1:
            self.half_pressed = True
            manual = self.value(EosProp.FOCUS_MODE) == 3
            delay = 0.0 if manual else b.half_press_s
            if not manual:
                report = self._focus_report()
                if report is not None:
                    self._queue([report], delay + 0.01)
            return ok(delay_s=delay)
        if code in (Op.EOS_REMOTE_RELEASE, Op.EOS_REMOTE_RELEASE_ON):
            self.full_presses += 1
            if b.full_press_busy or time.monotonic() < self._busy_until:
                return fail(Resp.DEVICE_BUSY)
            to_ram = self.value(EosProp.CAPTURE_DESTINATION) == CAPTURE_DESTINATION_RAM
            if to_ram and len(self.ram) >= self.ram_buffer_slots:
                return fail(Resp.DEVICE_BUSY)
            one_shot_unfocused = self.value(EosProp.FOCUS_MODE) == 0 and b.af_result == "failed"
            if one_shot_unfocused:  # One-Shot AF does not fire without focus
                return ok(1) if code == Op.EOS_REMOTE_RELEASE else ok()
            self._expose()
            return ok(0) if code == Op.EOS_REMOTE_RELEASE else ok()
        if code == Op.EOS_SET_DEVICE_PROP_VALUE_EX:
            return self._set_prop(data_out, ok, fail)
        if code == Op.EOS_GET_VIEWFINDER_DATA:
            if not self.value(EosProp.EVF_OUTPUT_DEVICE) & 2:
                return fail(Resp.CANON_OBJECT_NOT_READY)
            self.live_view_frames += 1
            return ok(data=pack_viewfinder_data(self.live_view_source(self.live_view_frames)))
        return fail(Resp.OPERATION_NOT_SUPPORTED)

    def _folder_listing(self, p, ok, fail) -> Reply:
        """EOS GetObjectInfoEx(storage, folder or 0xFFFFFFFF for the root, 0x100000): the folder's entries."""
        if len(p) < 2 or p[0] not in (CARD_STORAGE_ID, 0xFFFFFFFF):
            return fail(Resp.INVALID_STORAGE_ID)
        parent = 0 if p[1] == 0xFFFFFFFF else p[1]
        if parent and parent not in self.card:
            return fail(Resp.INVALID_OBJECT_HANDLE)
        stamp = int(time.time())
        entries = [
            EosFolderEntry(h, CARD_STORAGE_ID, o.object_format, 0, len(o.data), o.filename, stamp)
            for h, o in sorted(self.card.items())
            if o.parent == parent and self._object(h) is not None
        ]
        return ok(data=pack_eos_folder_entries(entries))

    def _set_prop(self, data_out, ok, fail) -> Reply:
        if data_out is None or len(data_out) < 12:
            return fail(Resp.INVALID_PARAMETER)
        size, prop = struct.unpack_from("<II", data_out)
        if size != len(data_out):
            return fail(Resp.INVALID_PARAMETER)
        raw = bytes(data_out[8:])
        if prop == EosProp.IMAGE_FORMAT:
            if image_format_of(raw) not in IMAGE_FORMATS:
                return fail(Resp.INVALID_DEVICE_PROP_VALUE)
            self.values[prop] = raw
            self._queue_value(prop)
            return ok()
        (value,) = struct.unpack_from("<I", data_out, 8)
        if prop == EosProp.CAPTURE_DESTINATION:
            if value not in self.allowed(prop):
                return fail(Resp.INVALID_DEVICE_PROP_VALUE)
            if value == self.value(prop):
                return fail(Resp.DEVICE_BUSY)  # EOS bodies answer busy when set to the value they have
        elif prop in (EosProp.EVF_OUTPUT_DEVICE, EosProp.EVF_MODE) or prop in (
            EosProp.ISO_SPEED,
            EosProp.SHUTTER_SPEED,
            EosProp.APERTURE,
        ):
            if value not in self.allowed(prop):
                return fail(Resp.INVALID_DEVICE_PROP_VALUE)
        else:
            return fail(Resp.DEVICE_PROP_NOT_SUPPORTED)
        self.values[prop] = _u32(value)
        self._queue_value(prop)
        return ok()


# keep the old name for callers that used the capture-destination constant from here
__all__ = ["CAPTURE_DESTINATION_CARD", "Reply", "SimBehaviour", "SimEos70D", "deterministic_frame"]
