"""PTP over USB (Still Image Capture class) on pyusb: device discovery, endpoints, class requests, bulk I/O.

A thin shell around the transaction engine (`devices.ptp.engine` with
`framing.UsbFraming`), which frames the containers, checks the phases and
transaction ids, keeps bytes beyond the current container and discards late
replies. This shell moves bytes and keeps the USB rules (zero-length packets
after full packets, stray ZLPs), and copes with what real bodies do: a stalled endpoint
(EPIPE) is cleared and the read retried once if nothing was read yet; the data
of a late reply goes to `on_stale_data`; after a timeout the transaction is cancelled (class request
0x64), the device status polled, and the device reset (0x66) if it stays
busy. The simulated EOS 70D is reached through this very code with
`find_cameras(backend=SimUsbBackend(...))`.
"""

from __future__ import annotations

import array
import errno
import struct
import time
from dataclasses import dataclass
from typing import Any

from mca.devices.ptp.codec import Container, ProtocolError
from mca.devices.ptp.codes import CANON_VENDOR_ID, ContainerType, Resp
from mca.devices.ptp.engine import EventReader, EventReceived, Initiator
from mca.devices.ptp.framing import UsbFraming
from mca.devices.ptp.policy import DEFAULT_POLICY, PtpPolicy
from mca.devices.ptp.transport import (
    DeviceDisconnected,
    Response,
    Transport,
    TransportError,
    TransportTimeout,
    run_to_response,
)

PTP_CLASS = (6, 1, 1)
REQ_CANCEL = 0x64
REQ_GET_EXTENDED_EVENT_DATA = 0x65
REQ_DEVICE_RESET = 0x66
REQ_GET_DEVICE_STATUS = 0x67
#: Size of the reusable bulk-in buffer: large reads go straight into it.
READ_CHUNK_BYTES = 1024 * 1024
DEFAULT_TIMEOUT_S = DEFAULT_POLICY.transaction_timeout_s
MAX_STRAY_ZLPS = 8
LIBUSB_ERROR_PIPE = -9


@dataclass(frozen=True)
class UsbCameraInfo:
    """A PTP interface found on the bus."""

    bus: int
    address: int
    vendor_id: int
    product_id: int
    configuration_value: int
    interface_number: int
    manufacturer: str
    product: str
    serial_number: str
    device: Any  # the pyusb Device

    @property
    def port(self) -> str:
        return f"usb:{self.bus:03d}:{self.address:03d}"

    @property
    def is_canon(self) -> bool:
        return self.vendor_id == CANON_VENDOR_ID


def default_backend() -> Any:
    """libusb-1.0 through `libusb-package` when installed (a bench without system packages), else pyusb's default."""
    try:
        import libusb_package

        return libusb_package.get_libusb1_backend()
    except Exception:
        return None


def _string(dev: Any, index: int) -> str:
    if not index:
        return ""
    try:
        import usb.util

        return usb.util.get_string(dev, index) or ""
    except Exception:
        return ""


def find_cameras(backend: Any = None) -> list[UsbCameraInfo]:
    """Every Still Image Capture interface (class 6/1/1) on the bus, Canon bodies first."""
    import usb.core

    if backend is None:
        backend = default_backend()
    found: list[UsbCameraInfo] = []
    try:
        devices = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.NoBackendError as exc:
        raise TransportError("no libusb backend: install libusb-1.0 or `pip install libusb-package`") from exc
    for dev in devices:
        try:
            configs = list(dev)
        except Exception:
            continue
        for cfg in configs:
            for intf in cfg:
                if (intf.bInterfaceClass, intf.bInterfaceSubClass, intf.bInterfaceProtocol) != PTP_CLASS:
                    continue
                found.append(
                    UsbCameraInfo(
                        bus=int(dev.bus or 0),
                        address=int(dev.address or 0),
                        vendor_id=dev.idVendor,
                        product_id=dev.idProduct,
                        configuration_value=cfg.bConfigurationValue,
                        interface_number=intf.bInterfaceNumber,
                        manufacturer=_string(dev, dev.iManufacturer),
                        product=_string(dev, dev.iProduct),
                        serial_number=_string(dev, dev.iSerialNumber),
                        device=dev,
                    )
                )
                break
    found.sort(key=lambda c: (not c.is_canon, c.bus, c.address))
    return found


def _is_gone(exc: Exception) -> bool:
    code = getattr(exc, "backend_error_code", None)
    return getattr(exc, "errno", None) in (errno.ENODEV, errno.EIO, errno.ESHUTDOWN) or code in (-4, -1)


def _is_stall(exc: Exception) -> bool:
    """libusb's LIBUSB_ERROR_PIPE: the endpoint halted (a real body stalls it when it aborts a transfer)."""
    return getattr(exc, "errno", None) == errno.EPIPE or getattr(exc, "backend_error_code", None) == LIBUSB_ERROR_PIPE


class UsbTransport(Transport):
    """Bulk-out commands and data, bulk-in data and responses, interrupt-in events."""

    def __init__(
        self, info: UsbCameraInfo, *, timeout_s: float | None = None, policy: PtpPolicy = DEFAULT_POLICY
    ) -> None:
        import usb.core
        import usb.util

        super().__init__()
        self._usb_core = usb.core
        self.info = info
        self.dev = info.device
        self.policy = policy
        self.timeout_s = policy.transaction_timeout_s if timeout_s is None else timeout_s
        self.usb_vendor_id = info.vendor_id
        self.name = f"{info.port} {info.product or 'camera'}".strip()
        self._closed = False
        self._rx = array.array("B", bytes(READ_CHUNK_BYTES))
        self._rx_view = memoryview(self._rx)
        # The transaction state machine and the containers' framing live in the engine; this shell moves bytes.
        self.engine = Initiator(UsbFraming(), name=self.name, stale_replies_max=policy.stale_replies_max)
        try:
            try:
                if self.dev.is_kernel_driver_active(info.interface_number):
                    self.dev.detach_kernel_driver(info.interface_number)
            except (NotImplementedError, usb.core.USBError):
                pass
            try:
                active = self.dev.get_active_configuration()
            except usb.core.USBError:
                active = None
            if active is None or active.bConfigurationValue != info.configuration_value:
                self.dev.set_configuration(info.configuration_value)
            cfg = self.dev.get_active_configuration()
            intf = usb.util.find_descriptor(cfg, bInterfaceNumber=info.interface_number)
            usb.util.claim_interface(self.dev, info.interface_number)
        except usb.core.USBError as exc:
            hint = (
                "another program holds the camera (stop gvfs-gphoto2-volume-monitor)"
                if exc.errno == errno.EBUSY
                else "check the udev rule for PTP cameras (see docs/tethering.md)"
                if exc.errno == errno.EACCES
                else "unplug and replug the camera"
            )
            raise TransportError(f"could not claim {self.name}: {exc}; {hint}") from exc
        self.interface_number = info.interface_number
        self.ep_in: Any = None
        self.ep_out: Any = None
        self.ep_int: Any = None
        for ep in intf:
            kind = usb.util.endpoint_type(ep.bmAttributes)
            is_in = usb.util.endpoint_direction(ep.bEndpointAddress) == usb.util.ENDPOINT_IN
            if kind == usb.util.ENDPOINT_TYPE_BULK and is_in:
                self.ep_in = ep
            elif kind == usb.util.ENDPOINT_TYPE_BULK:
                self.ep_out = ep
            elif kind == usb.util.ENDPOINT_TYPE_INTR and is_in:
                self.ep_int = ep
        if self.ep_in is None or self.ep_out is None:
            raise TransportError(f"{self.name} has no bulk endpoint pair on interface {info.interface_number}")
        self.max_packet_bytes = int(self.ep_out.wMaxPacketSize) or 512

    # -- raw I/O ---------------------------------------------------------
    def _ms(self, timeout_s: float | None) -> int:
        return max(1, int(1000 * (self.timeout_s if timeout_s is None else timeout_s)))

    def _wrap(self, exc: Exception, what: str) -> TransportError:
        if isinstance(exc, self._usb_core.USBTimeoutError):
            self.counters.timeouts += 1
            return TransportTimeout(f"{self.name} did not answer {what} in time; is it asleep or busy?")
        if _is_stall(exc):
            return TransportError(f"{self.name} stalled its endpoint during {what}")
        if _is_gone(exc):
            return DeviceDisconnected(f"{self.name} disconnected during {what}; reconnect the cable and retry")
        return TransportError(f"USB error on {self.name} during {what}: {exc}")

    def _write(self, data: bytes | bytearray | memoryview, timeout_s: float | None) -> None:
        stalls = 0
        while True:
            try:
                sent = self.ep_out.write(data, self._ms(timeout_s))
                if sent != len(data):
                    raise TransportError(f"{self.name} accepted {sent} of {len(data)} bytes")
                if len(data) % self.max_packet_bytes == 0:
                    self.ep_out.write(b"", self._ms(timeout_s))  # a zero-length packet ends the transfer
                return
            except self._usb_core.USBError as exc:
                if _is_stall(exc) and stalls < self.policy.stall_retries:
                    stalls += 1
                    self._clear_halt(self.ep_out)
                    continue
                raise self._wrap(exc, "a write") from exc

    def _clear_halt(self, ep: Any) -> None:
        try:
            self.dev.clear_halt(ep.bEndpointAddress)
            self.counters.stalls_cleared += 1
        except self._usb_core.USBError as exc:
            raise self._wrap(exc, "clearing a stalled endpoint") from exc

    def _read_chunk(self, timeout_s: float | None, *, at_boundary: bool = False) -> memoryview:
        """The next non-empty piece of the bulk-in stream (the engine copies what it keeps before the next read).

        `at_boundary`: nothing of the current container has been read yet, so a stalled endpoint may be
        cleared and the read retried (libgphoto2 retries once, only then).
        """
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        zlps = stalls = 0
        while True:
            try:
                n = self.dev.read(
                    self.ep_in.bEndpointAddress, self._rx, self._ms(max(0.001, deadline - time.monotonic()))
                )
            except self._usb_core.USBError as exc:
                if _is_stall(exc) and at_boundary and stalls < self.policy.stall_retries:
                    stalls += 1
                    self._clear_halt(self.ep_in)
                    continue
                raise self._wrap(exc, "a read") from exc
            if n:
                return self._rx_view[:n]
            zlps += 1  # a stray zero-length packet
            if zlps > MAX_STRAY_ZLPS or time.monotonic() > deadline:
                raise TransportTimeout(f"{self.name} sent only zero-length packets")

    # -- transactions ----------------------------------------------------
    def transaction(
        self,
        code,
        transaction_id,
        params=(),
        *,
        data_out=None,
        sink=None,
        max_data_bytes=64 * 1024 * 1024,
        timeout_s=None,
    ) -> Response:
        if self._closed:
            raise TransportError(f"{self.name} is closed")
        engine = self.engine
        for write in engine.send_command(
            code, transaction_id, tuple(params), data_out=data_out, max_data_bytes=max_data_bytes
        ):
            self._write(write, timeout_s)
        return run_to_response(
            self, engine, lambda: self._read_chunk(timeout_s, at_boundary=engine.framing.at_boundary), sink
        )

    def read_event(self, timeout_s: float) -> Container | None:
        if self.ep_int is None:
            time.sleep(timeout_s)
            return None
        try:
            raw = self.ep_int.read(64, self._ms(timeout_s))
        except self._usb_core.USBTimeoutError:
            return None
        except self._usb_core.USBError as exc:
            raise self._wrap(exc, "an event read") from exc
        if not raw:
            return None
        events = EventReader(UsbFraming(), self.name)  # one interrupt transfer holds one event container
        events.receive_data(bytes(raw))
        event = events.next_event()
        if not isinstance(event, EventReceived):
            raise ProtocolError(f"{self.name} sent a part of a container on the interrupt endpoint")
        return Container(ContainerType.EVENT, event.code, event.transaction_id, event.params)

    # -- class requests --------------------------------------------------
    def cancel(self, transaction_id: int) -> None:
        """Still Image class Cancel Request (0x64): u16 0x4001 (CancelTransaction) and the transaction id."""
        self._ctrl(0x21, REQ_CANCEL, struct.pack("<HI", 0x4001, transaction_id))
        self.counters.cancels_sent += 1

    def device_reset(self) -> None:
        """Still Image class Device Reset Request (0x66): the device drops its transaction state."""
        self._ctrl(0x21, REQ_DEVICE_RESET, None)
        self.counters.resets_sent += 1

    def reset_device(self) -> None:
        try:
            self.device_reset()
        except TransportError:
            pass

    def device_status(self) -> int:
        """The response code of Get Device Status (OK, DeviceBusy, ...)."""
        raw = bytes(self._ctrl(0xA1, REQ_GET_DEVICE_STATUS, 20))
        if len(raw) < 4:
            raise ProtocolError(f"{self.name} sent a {len(raw)}-byte device status")
        length, code = struct.unpack_from("<HH", raw)
        if length < 4 or length > len(raw):
            raise ProtocolError(f"{self.name} device status claims {length} bytes")
        return code

    def _ctrl(self, request_type: int, request: int, data: Any) -> Any:
        try:
            return self.dev.ctrl_transfer(request_type, request, 0, self.interface_number, data, self._ms(None))
        except self._usb_core.USBError as exc:
            raise self._wrap(exc, f"class request 0x{request:02X}") from exc

    def recover(self, transaction_id: int | None = None) -> None:
        """After a timeout or a broken container: cancel the transaction, wait until the device is idle
        (Get Device Status), reset it if it stays busy, clear stalls and drop what is buffered."""
        if self._closed:
            return
        self.engine.reset()
        if transaction_id is not None:
            try:
                self.cancel(transaction_id)
            except DeviceDisconnected:
                raise
            except TransportError:
                pass
        deadline = time.monotonic() + self.policy.recover_wait_s
        idle = False
        while time.monotonic() < deadline:
            try:
                status = self.device_status()
            except DeviceDisconnected:
                raise
            except (TransportError, ProtocolError):
                break
            if status == Resp.OK:
                idle = True
                break
            time.sleep(0.02)
        if not idle:
            self.reset_device()
        for ep in (self.ep_in, self.ep_out):
            try:
                self.dev.clear_halt(ep.bEndpointAddress)
            except Exception:
                pass
        while True:  # drain anything still queued
            try:
                n = self.dev.read(self.ep_in.bEndpointAddress, self._rx, 20)
            except Exception:
                break
            if not n:
                break

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            import usb.util

            usb.util.release_interface(self.dev, self.interface_number)
            usb.util.dispose_resources(self.dev)
        except Exception:
            pass


def open_usb(
    port: str | None = None, backend: Any = None, *, timeout_s: float | None = None, policy: PtpPolicy = DEFAULT_POLICY
) -> UsbTransport:
    """Open the first camera, or the one at `usb:BUS:ADDR`."""
    cameras = find_cameras(backend)
    if port:
        cameras = [c for c in cameras if c.port == _normal_port(port)]
    if not cameras:
        where = f" at {port}" if port else ""
        raise TransportError(f"no PTP camera found{where}: is it switched on, connected, and not held by gvfs?")
    return UsbTransport(cameras[0], timeout_s=timeout_s, policy=policy)


def _normal_port(port: str) -> str:
    parts = port.split(":")
    if len(parts) != 3 or parts[0] != "usb":
        raise ValueError(f"USB port must look like usb:BUS:ADDR, got {port!r}")
    return f"usb:{int(parts[1]):03d}:{int(parts[2]):03d}"
