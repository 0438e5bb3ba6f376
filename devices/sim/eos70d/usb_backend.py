"""A pure-Python pyusb backend that is a simulated EOS 70D: `usb.core.find(backend=SimUsbBackend())` finds it.

It implements the Still Image Capture class on the device side: the bulk-out
stream goes through the responder side of the host's own transaction engine
(`devices.ptp.engine`), each command runs through `SimEos70D.handle`, and the
engine's data and response containers are served as bulk-in transfers (ending each
with a zero-length packet when it fills whole packets). A reply may be ready
only after a delay (a half press while focusing, a late answer after the host
gave up); a halted endpoint answers reads with EPIPE until cleared; the
Still Image class requests (cancel, reset, status) act on the queue. Optional
pacing emulates a USB 2.0 link; `FaultPlan` injects failures. Any responder
with `handle(command, data_out)` plugs in: the simulated 70D, or
`devices.ptp.replay.ReplayResponder` replaying a real body's log.
"""

from __future__ import annotations

import errno
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import usb.backend
import usb.core

from mca.devices.ptp.codec import Container, ProtocolError
from mca.devices.ptp.codes import CANON_VENDOR_ID, EOS_70D_PRODUCT_ID, ContainerType, Op, Resp
from mca.devices.ptp.engine import NEED_DATA, CommandReceived, DataFinished, DataReceived, Responder
from mca.devices.ptp.events import EosObjectAdded, EosRequestObjectTransfer, parse_eos_events
from mca.devices.ptp.framing import UsbFraming
from mca.devices.sim.eos70d.faults import DOWNLOAD_OPS, FaultPlan, corrupt_container
from mca.devices.sim.eos70d.responder import SimEos70D

MAX_PACKET_BYTES = 512
EP_BULK_IN, EP_BULK_OUT, EP_INTR_IN = 0x81, 0x02, 0x83
#: Practical PTP throughput of a USB 2.0 high-speed link (about 2/3 of 480 Mbit/s).
USB2_BYTES_PER_S = 40e6


class _Desc:
    def __init__(self, **fields: Any) -> None:
        self.extra_descriptors: list[int] = []
        self.__dict__.update(fields)


@dataclass
class _Transfer:
    segments: list[memoryview]
    length: int
    offset: int = 0
    zlp: bool = False  # a zero-length packet marker
    ready_at: float = 0.0  # not served before this time (a slow or late reply)
    transaction_id: int = 0
    keep_on_cancel: bool = False  # a body that ignores the host's cancel request


@dataclass
class _DeviceId:
    bus: int
    address: int


@dataclass
class _Handle:
    device: _DeviceId
    claimed: set[int] = field(default_factory=set)


class SimUsbBackend(usb.backend.IBackend):
    """The simulated camera on a simulated bus."""

    def __init__(
        self,
        camera: SimEos70D | None = None,
        *,
        faults: FaultPlan | None = None,
        pace_bytes_per_s: float | None = None,
        bus: int = 1,
        address: int = 4,
    ) -> None:
        super().__init__()
        self.camera = camera or SimEos70D()
        self.faults = faults or FaultPlan()
        self.pace_bytes_per_s = pace_bytes_per_s
        self.device_id: _DeviceId | None = _DeviceId(bus, address)
        self.configuration = 0
        self._engine = Responder(UsbFraming(), name="host", expects_data_out=self.camera.expects_data_out)
        self._command: CommandReceived | None = None
        self._data_out = bytearray()
        self._in: deque[_Transfer] = deque()
        self._lock = threading.RLock()
        self._stalled = False
        self._halted = False  # the bulk-in endpoint answers EPIPE until the host clears the halt
        self._pace_free_at = 0.0
        self.in_bytes_total = 0
        self._disconnect_armed_at: int | None = None
        self._interrupt_at: int | None = None
        self.stalls_served = 0
        self.cancels_received = 0
        self.resets_received = 0
        self._strings = {1: "Canon Inc.", 2: self.camera.device_info().model, 3: self.camera.serial_number}

    # -- hot-plug --------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self.device_id is not None

    def unplug(self) -> None:
        with self._lock:
            if self.device_id is not None:
                self._last_id = self.device_id
            self.device_id = None
            self._in.clear()
            self._engine.reset()
            self.camera.disconnect()

    def replug(self) -> None:
        """The camera comes back at a new address, as after a real re-enumeration."""
        with self._lock:
            last = getattr(self, "_last_id", None) or _DeviceId(1, 3)
            if self.device_id is None:
                self.device_id = _DeviceId(last.bus, last.address + 1)
            self.configuration = 0
            self._stalled = False

    def _gone(self, dev: Any = None) -> None:
        if self.device_id is None or (dev is not None and getattr(dev, "device", dev) != self.device_id):
            raise usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)

    # -- descriptors -----------------------------------------------------
    def enumerate_devices(self):
        return [self.device_id] if self.device_id is not None else []

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return _Desc(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=CANON_VENDOR_ID,
            idProduct=EOS_70D_PRODUCT_ID,
            bcdDevice=0x0002,
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3,
            bNumConfigurations=1,
            address=dev.address,
            bus=dev.bus,
            port_number=1,
            port_numbers=(1,),
            speed=3,
        )

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError("the EOS 70D has one configuration")
        return _Desc(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=39,
            bNumInterfaces=1,
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0xC0,
            bMaxPower=1,
        )

    def get_interface_descriptor(self, dev, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError("no such interface or alternate setting")
        return _Desc(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=0,
            bAlternateSetting=0,
            bNumEndpoints=3,
            bInterfaceClass=6,
            bInterfaceSubClass=1,
            bInterfaceProtocol=1,
            iInterface=0,
        )

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        table = [(EP_BULK_IN, 2, MAX_PACKET_BYTES, 0), (EP_BULK_OUT, 2, MAX_PACKET_BYTES, 0), (EP_INTR_IN, 3, 64, 8)]
        if config != 0 or intf != 0 or alt != 0 or not 0 <= ep < len(table):
            raise IndexError("no such endpoint")
        address, attributes, size, interval = table[ep]
        return _Desc(
            bLength=7,
            bDescriptorType=5,
            bEndpointAddress=address,
            bmAttributes=attributes,
            wMaxPacketSize=size,
            bInterval=interval,
            bRefresh=0,
            bSynchAddress=0,
        )

    # -- device handle ---------------------------------------------------
    def open_device(self, dev):
        self._gone(dev)
        return _Handle(dev)

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        self._gone(dev_handle)
        self.configuration = config_value

    def get_configuration(self, dev_handle):
        self._gone(dev_handle)
        return self.configuration

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._gone(dev_handle)

    def claim_interface(self, dev_handle, intf):
        self._gone(dev_handle)
        dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        dev_handle.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        pass

    def attach_kernel_driver(self, dev_handle, intf):
        pass

    def clear_halt(self, dev_handle, ep):
        self._gone(dev_handle)
        self._stalled = False
        self._halted = False

    def reset_device(self, dev_handle):
        self._gone(dev_handle)
        with self._lock:
            self._in.clear()
            self._engine.reset()
            self.camera.disconnect()

    # -- transfers -------------------------------------------------------
    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        with self._lock:
            self._gone(dev_handle)
            raw = bytes(data)
            try:
                self._engine.receive_data(raw)
                self._process_out()
            except ProtocolError:
                self._engine.reset()  # a device would stall; the host recovers with a reset
                self._stalled = True
            return len(raw)

    def _process_out(self) -> None:
        while (event := self._engine.next_event()) is not NEED_DATA:
            if isinstance(event, CommandReceived):
                self._command, self._data_out = event, bytearray()
                if not event.data_out:
                    self._answer(event, None)
            elif isinstance(event, DataReceived):
                self._data_out += event.data
            elif isinstance(event, DataFinished) and self._command is not None:
                self._answer(self._command, bytes(self._data_out))

    def _answer(self, command: CommandReceived, data_out: bytes | None) -> None:
        try:
            self._run(Container(ContainerType.COMMAND, command.code, command.transaction_id, command.params), data_out)
        finally:
            self._engine.drop_reply()  # a reply not sent by now never comes (a stall, a dropped or lost reply)

    def _run(self, cmd, data_out) -> None:
        f = self.faults
        if f.stall_op is not None and cmd.code == f.stall_op:
            f.stall_op = None
            self._stalled = True
            return
        if f.busy_count:
            self.camera.busy_responses += f.busy_count
            f.busy_count = 0
        self.camera.short_partial_bytes = f.short_read_bytes
        reply = self.camera.handle(cmd, data_out)
        if getattr(reply, "dropped", False):
            return
        delay = getattr(reply, "delay_s", 0.0)
        keep = False
        if f.late_reply_op is not None and cmd.code == f.late_reply_op:
            f.late_reply_op = None
            delay += f.late_reply_s
            keep = f.ignore_cancel
        carries_file = (
            f.lose_object_event_reply
            and cmd.code == Op.EOS_GET_EVENT
            and reply.data is not None
            and any(isinstance(e, (EosObjectAdded, EosRequestObjectTransfer)) for e in parse_eos_events(reply.data))
        )
        if carries_file:
            f.lose_object_event_reply = False
            return  # the body dequeued the events; the host never hears of them
        if f.epipe_op is not None and cmd.code == f.epipe_op:
            f.epipe_op = None
            self._halted = True
        ready_at = max(time.monotonic() + delay, self._in[-1].ready_at if self._in else 0.0)
        tid = cmd.transaction_id
        data = memoryview(reply.data).cast("B") if reply.data is not None else None
        segments = [] if data is None else [memoryview(w) for w in self._engine.send_data(data)]
        resp_raw = self._engine.send_response(reply.response.code, reply.response.params)
        if f.corrupt_op is not None and cmd.code == f.corrupt_op:
            f.corrupt_op = None
            resp_raw = corrupt_container(resp_raw)
        if f.disconnect_after_in_bytes is not None and cmd.code in DOWNLOAD_OPS:
            self._disconnect_armed_at = self.in_bytes_total + f.disconnect_after_in_bytes
            f.disconnect_after_in_bytes = None
        if f.interrupt_after_in_bytes is not None and cmd.code in DOWNLOAD_OPS:
            self._interrupt_at = self.in_bytes_total + f.interrupt_after_in_bytes
            f.interrupt_after_in_bytes = None
        if segments:
            if f.coalesce_response:
                self._push([*segments, memoryview(resp_raw)], ready_at, tid, keep)
                return
            self._push(segments, ready_at, tid, keep)
        self._push([memoryview(resp_raw)], ready_at, tid, keep)

    def _push(self, segments: list[memoryview], ready_at: float = 0.0, tid: int = 0, keep: bool = False) -> None:
        length = sum(len(s) for s in segments)
        self._in.append(_Transfer(segments, length, ready_at=ready_at, transaction_id=tid, keep_on_cancel=keep))
        if length % MAX_PACKET_BYTES == 0:
            self._in.append(_Transfer([], 0, zlp=True, ready_at=ready_at, transaction_id=tid, keep_on_cancel=keep))

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        deadline = time.monotonic() + timeout / 1000.0
        while True:
            with self._lock:
                self._gone(dev_handle)
                if self._halted and self._in:
                    self.stalls_served += 1
                    raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
                if self._in and not self._stalled and self._in[0].ready_at <= time.monotonic():
                    return self._serve(buff)
            if time.monotonic() >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            time.sleep(min(0.002, max(0.0, deadline - time.monotonic())))

    def _serve(self, buff) -> int:
        transfer = self._in[0]
        if transfer.zlp:
            self._in.popleft()
            return 0
        out = memoryview(buff).cast("B")
        want = min(len(out), transfer.length - transfer.offset)
        if self._interrupt_at is not None and self.in_bytes_total >= self._interrupt_at:
            self._interrupt_at = None
            raise KeyboardInterrupt  # the photographer pressed Ctrl-C in the middle of a download
        if self._disconnect_armed_at is not None:
            allowed = self._disconnect_armed_at - self.in_bytes_total
            if allowed <= 0:
                self._disconnect_armed_at = None
                self.unplug()
                raise usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)
            want = min(want, allowed)
        written = 0
        pos = transfer.offset
        for seg in transfer.segments:  # copy the window [offset, offset+want) out of the segments
            if pos >= len(seg):
                pos -= len(seg)
                continue
            take = min(len(seg) - pos, want - written)
            out[written : written + take] = seg[pos : pos + take]
            written += take
            pos = 0
            if written == want:
                break
        transfer.offset += written
        self.in_bytes_total += written
        if transfer.offset >= transfer.length:
            self._in.popleft()
        self._pace(written)
        return written

    def _pace(self, n: int) -> None:
        if not self.pace_bytes_per_s:
            return
        now = time.monotonic()
        self._pace_free_at = max(now, self._pace_free_at) + n / self.pace_bytes_per_s
        if self._pace_free_at > now:
            time.sleep(self._pace_free_at - now)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        deadline = time.monotonic() + timeout / 1000.0
        while True:
            with self._lock:
                self._gone(dev_handle)
                events = self.camera.take_std_events()
                if events:
                    ev = events[0]
                    with self.camera.lock:
                        self.camera._std_events[:0] = events[1:]
                    raw = pack_event_raw(ev)
                    out = memoryview(buff).cast("B")
                    out[: len(raw)] = raw
                    return len(raw)
            if time.monotonic() >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            time.sleep(0.002)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        with self._lock:
            self._gone(dev_handle)
            out = memoryview(data).cast("B") if data is not None else memoryview(b"")
            if bmRequestType == 0x80 and bRequest == 6 and (wValue >> 8) == 3:
                index = wValue & 0xFF
                payload = b"\x09\x04" if index == 0 else self._strings.get(index, "").encode("utf-16-le")
                desc = bytes([2 + len(payload), 3]) + payload
                n = min(len(out), len(desc))
                out[:n] = desc[:n]
                return n
            if bmRequestType == 0x21 and bRequest == 0x64:  # cancel: the body drops the transaction's replies
                self.cancels_received += 1
                if self.faults.ignore_cancel:  # a body that goes on as if nothing was asked
                    return len(out)
                kept = [t for t in self._in if t.keep_on_cancel]
                self._in.clear()
                self._in.extend(kept)
                self._engine.abandon()
                self._stalled = False
                return len(out)
            if bmRequestType == 0x21 and bRequest == 0x66:  # device reset
                self.resets_received += 1
                self._in.clear()
                self._engine.reset()
                self._stalled = False
                self._halted = False
                return 0
            if bmRequestType == 0xA1 and bRequest == 0x67:  # get device status
                status = struct.pack("<HH", 4, Resp.DEVICE_BUSY if self._stalled or self._halted else Resp.OK)
                out[:4] = status
                return 4
            return 0


def pack_event_raw(ev) -> bytes:
    from mca.devices.ptp.codec import pack_event

    return pack_event(ev.code, ev.transaction_id, ev.params)
