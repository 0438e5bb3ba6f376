"""`mca camera doctor`: what a camera reports on the wire, what this stack will use, and anything unexpected.

The report is plain text a user can attach to a bug report: the DeviceInfo
fields exactly as sent (vendor extension id and version, model, firmware,
operations, events and properties with human names, the raw dataset in hex),
the EOS DeviceInfoEx, the standard property descriptions, the settings the
body reported at start-up and over how many polls, storage, and then the
choices the stack makes (vendor-id fix-up, capture and download operations,
card value of the capture destination, files per shot, live view, timeouts)
and a list of findings. It reads only; with `live_view=True` it also fetches
one live-view frame (the camera's display output is restored afterwards).
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass, field, fields
from pathlib import Path

from mca.devices.ptp.camera import Camera, PtpError
from mca.devices.ptp.codec import ProtocolError
from mca.devices.ptp.codes import (
    CANON_VENDOR_EXTENSION_ID,
    CANON_VENDOR_ID,
    EOS_70D_PRODUCT_ID,
    EOS_EVENT_NAMES,
    MICROSOFT_VENDOR_EXTENSION_ID,
    EosProp,
    Op,
    name_of,
    op_name,
    prop_name,
)
from mca.devices.ptp.events import image_format_of
from mca.devices.ptp.properties import (
    EOS_APERTURE,
    EOS_CAPTURE_TARGET,
    EOS_ISO,
    EOS_SHUTTER,
    image_format_name,
)
from mca.devices.ptp.transport import TransportError

#: Operations the stack needs on an EOS body, and what each is for.
NEEDED_EOS_OPS = {
    Op.EOS_GET_EVENT: "events (new files, settings)",
    Op.EOS_SET_DEVICE_PROP_VALUE_EX: "changing settings",
    Op.EOS_GET_PARTIAL_OBJECT: "downloads in 1 MiB blocks",
    Op.EOS_TRANSFER_COMPLETE: "freeing shots in camera RAM",
    Op.EOS_SET_REMOTE_MODE: "remote control",
    Op.EOS_SET_EVENT_MODE: "event reporting",
}
AE_MODES = {
    0: "P",
    1: "Tv",
    2: "Av",
    3: "M",
    4: "Bulb",
    5: "A-DEP",
    6: "DEP",
    7: "Custom",
    8: "Lock",
    9: "Green (auto)",
}
FOCUS_MODES = {0: "One-Shot AF", 1: "AI Servo AF", 2: "AI Focus AF", 3: "manual focus"}


@dataclass
class DoctorReport:
    lines: list[str] = field(default_factory=list)
    findings: list[str] = field(default_factory=list)
    model: str = ""
    serial_number: str = ""

    def text(self) -> str:
        out = list(self.lines)
        out += ["", "== Findings =="]
        out += [f"- {f}" for f in self.findings] or ["- nothing unexpected"]
        return "\n".join(out) + "\n"


def _codes(values: tuple[int, ...], label) -> list[str]:
    return [f"    {label(v)}" for v in values]


def _value_text(prop: int, value: int, raw: bytes) -> str:
    tables: dict[int, dict[int, str]] = {
        EosProp.ISO_SPEED: EOS_ISO,
        EosProp.SHUTTER_SPEED: EOS_SHUTTER,
        EosProp.APERTURE: EOS_APERTURE,
        EosProp.CAPTURE_DESTINATION: EOS_CAPTURE_TARGET,
        EosProp.AUTO_EXPOSURE_MODE: AE_MODES,
        EosProp.FOCUS_MODE: FOCUS_MODES,
    }
    if prop in tables:
        return f"{tables[prop].get(value, '?')} (0x{value:X})"
    if prop == EosProp.IMAGE_FORMAT:
        entries = image_format_of(raw)
        return image_format_name(entries) if entries else f"undecoded {raw.hex()}"
    if prop in (EosProp.LENS_NAME, EosProp.SERIAL_NUMBER, EosProp.OWNER, EosProp.ARTIST, EosProp.COPYRIGHT):
        return repr(raw.split(b"\x00", 1)[0].decode("ascii", errors="replace"))
    return f"0x{value:X}" + (f" ({len(raw)} bytes)" if len(raw) != 4 else "")


def diagnose(cam: Camera, *, usb_ids: tuple[int, int] | None = None, live_view: bool = False) -> DoctorReport:
    """Everything `mca camera doctor` prints, from an open camera (read-only but for the live-view probe)."""
    r = DoctorReport(model=cam.wire_info.model, serial_number=cam.wire_info.serial_number)
    add, find = r.lines.append, r.findings.append
    wire = cam.wire_info
    add("== mca camera doctor ==")
    add(f"date:      {datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds')}")
    add(f"camera:    {cam.name}")
    if usb_ids:
        add(f"USB id:    {usb_ids[0]:04x}:{usb_ids[1]:04x}")
    add("")
    add("== What the body sends (GetDeviceInfo, as on the wire) ==")
    add(f"standard version:         {wire.standard_version}")
    add(f"vendor extension id:      0x{wire.vendor_extension_id:08X} ({wire.vendor_extension_id})")
    add(f"vendor extension version: {wire.vendor_extension_version}")
    add(f"vendor extension desc:    {wire.vendor_extension_desc!r}")
    add(f"functional mode:          0x{wire.functional_mode:04X}")
    add(f"manufacturer:             {wire.manufacturer!r}")
    add(f"model:                    {wire.model!r}")
    add(f"firmware:                 {wire.device_version!r}")
    add(f"serial number:            {wire.serial_number!r} ({len(wire.serial_number)} characters)")
    add(f"operations ({len(wire.operations)}):")
    r.lines += _codes(wire.operations, op_name)
    add(f"events ({len(wire.events)}):")
    r.lines += _codes(wire.events, lambda c: f"0x{c:04X}")
    add(f"device properties ({len(wire.properties)}):")
    r.lines += _codes(wire.properties, prop_name)
    add(f"capture formats: {' '.join(f'0x{c:04X}' for c in wire.capture_formats)}")
    add(f"image formats:   {' '.join(f'0x{c:04X}' for c in wire.image_formats)}")
    try:
        raw = cam.device_info_bytes()
        add(f"dataset ({len(raw)} bytes, hex):")
        r.lines += [f"    {raw[i : i + 32].hex(' ')}" for i in range(0, len(raw), 32)]
    except (TransportError, ProtocolError, PtpError) as exc:
        find(f"GetDeviceInfo failed a second time: {exc}")
    if cam.info_ex is not None:
        ex = cam.info_ex
        add("")
        add("== EOS GetDeviceInfoEx ==")
        add(f"event records ({len(ex.events)}): " + " ".join(f"0x{c:04X}" for c in ex.events))
        add(f"properties ({len(ex.properties)}):")
        r.lines += _codes(ex.properties, prop_name)
        add(f"third list: {' '.join(f'0x{c:04X}' for c in ex.unknown)}")
    add("")
    add("== Standard property descriptions (GetDevicePropDesc) ==")
    for code in wire.properties:
        try:
            desc = cam.prop_desc(code)
            allowed = f", allowed {list(desc.allowed)}" if desc.form == "enum" else ""
            add(
                f"    {prop_name(code)}: type 0x{desc.datatype:04X}, {'rw' if desc.writable else 'ro'}, {desc.current!r}{allowed}"
            )
        except (TransportError, ProtocolError, PtpError) as exc:
            add(f"    {prop_name(code)}: {exc}")
    values, lists = cam.reported_values(), cam.reported_allowed()
    if cam.is_eos:
        add("")
        add("== Settings the body reported (GetEvent) ==")
        add(f"records per poll at start-up: {cam.poll_sizes[:16]}")
        add(f"{len(values)} properties with values, {len(lists)} with lists of allowed values")
        for prop in (
            EosProp.AUTO_EXPOSURE_MODE,
            EosProp.CAPTURE_DESTINATION,
            EosProp.IMAGE_FORMAT,
            EosProp.ISO_SPEED,
            EosProp.APERTURE,
            EosProp.SHUTTER_SPEED,
            EosProp.FOCUS_MODE,
            EosProp.AVAILABLE_SHOTS,
            EosProp.BATTERY_POWER,
            EosProp.LENS_NAME,
            EosProp.EVF_OUTPUT_DEVICE,
            EosProp.SHUTTER_COUNTER,
        ):
            if prop in values:
                v = values[prop]
                listed = lists.get(prop)
                count = f", {len(listed.raw_values or listed.values)} allowed" if listed else ""
                add(f"    {prop_name(prop)}: {_value_text(prop, v.value, v.raw)}{count}")
            else:
                add(f"    {prop_name(prop)}: not reported")
    add("")
    add("== Storage ==")
    try:
        ids = cam.storage_ids()
        add("storage ids: " + " ".join(f"0x{s:08X}" for s in ids))
        if not any(s & 0xFFFF for s in ids):
            find("no memory card: the storage id has no card slot in use; insert a card (or use --target ram)")
        for sid, info in cam.storages().items():
            add(
                f"    0x{sid:08X}: {info.description!r} {info.volume_label!r}, "
                f"{info.free_space_bytes / 1e9:.1f} of {info.max_capacity_bytes / 1e9:.1f} GB free"
            )
    except (TransportError, ProtocolError, PtpError) as exc:
        find(f"storage could not be read: {exc}")

    add("")
    add("== What this stack will use ==")
    if wire.vendor_extension_id != cam.info.vendor_extension_id:
        add(
            f"vendor extension id: 0x{cam.info.vendor_extension_id:X} (the body sends "
            f"{wire.vendor_extension_id}; a Canon body's 6 is read as Canon's 0xB, as libgphoto2 does)"
        )
    else:
        add(f"vendor extension id: 0x{cam.info.vendor_extension_id:X} (as sent)")
    add(f"Canon EOS protocol:  {'yes' if cam.is_eos else 'no'}")
    if cam.is_eos:
        release = (
            "RemoteReleaseOn/Off 0x9128/0x9129 (half press, AF check, full press)"
            if cam.info.supports(Op.EOS_REMOTE_RELEASE_ON)
            else "RemoteRelease 0x910F"
        )
    else:
        release = (
            "InitiateCapture 0x100E"
            if cam.info.supports(Op.INITIATE_CAPTURE)
            else "none: this body cannot be triggered"
        )
    add(f"shutter release:     {release}")
    download = (
        "EOS GetPartialObject 0x9107"
        if cam.is_eos and cam.info.supports(Op.EOS_GET_PARTIAL_OBJECT)
        else "GetPartialObject 0x101B"
    )
    add(f"download:            {download}, {cam.policy.download_block_bytes // 1024} KiB blocks")
    if cam.is_eos:
        add(f"capture target card: value {cam.card_capture_destination()} (the first non-RAM value the body lists)")
        add(f"files per shot:      {cam.files_per_shot()}")
        add(
            f"live view:           {'GetViewFinderData 0x9153' if cam.info.supports(Op.EOS_GET_VIEWFINDER_DATA) else 'not offered'}"
        )
    add("timeouts and budgets:")
    for f in fields(cam.policy):
        add(f"    {f.name} = {getattr(cam.policy, f.name)}")

    # findings ------------------------------------------------------------
    if cam.is_canon and wire.vendor_extension_id == MICROSOFT_VENDOR_EXTENSION_ID:
        pass  # expected of every EOS body; reported above
    elif wire.vendor_extension_id not in (MICROSOFT_VENDOR_EXTENSION_ID, CANON_VENDOR_EXTENSION_ID):
        find(f"vendor extension id {wire.vendor_extension_id} is neither Canon's 0xB nor Microsoft's 6")
    if usb_ids and usb_ids[0] != CANON_VENDOR_ID:
        find(f"USB vendor id 0x{usb_ids[0]:04x} is not Canon's 0x04a9")
    if usb_ids and usb_ids[0] == CANON_VENDOR_ID and usb_ids[1] != EOS_70D_PRODUCT_ID:
        find(f"USB product id 0x{usb_ids[1]:04x} is not the EOS 70D's 0x3253 (another Canon body)")
    if "70D" not in wire.model:
        find(f"model {wire.model!r} is not an EOS 70D: the profiles and defaults assume one")
    if not cam.is_eos:
        find("not driven as a Canon EOS body: no EOS events, capture by InitiateCapture only")
    for op, what in NEEDED_EOS_OPS.items():
        if cam.is_eos and not cam.info.supports(op):
            find(f"the body does not list {op_name(op)}, needed for {what}")
    if cam.is_eos:
        fmt = values.get(EosProp.IMAGE_FORMAT)
        entries = image_format_of(fmt.raw) if fmt else None
        if entries is not None and not any(kind == 6 for kind, _s, _c in entries):
            find(
                f"image format is {image_format_name(entries)}: the depth pipeline wants RAW (mca camera config set imageformat RAW)"
            )
        ae = values.get(EosProp.AUTO_EXPOSURE_MODE)
        if ae is not None and ae.value not in (0, 1, 2, 3):
            find(
                f"the mode dial is on {AE_MODES.get(ae.value, hex(ae.value))}: settings cannot be changed remotely; use M"
            )
        shots = values.get(EosProp.AVAILABLE_SHOTS)
        if shots is not None and shots.value == 0:
            find("the body reports 0 available shots (card full or missing)")
        if cam.info_ex is not None:
            silent = [
                p
                for p in (EosProp.CAPTURE_DESTINATION, EosProp.IMAGE_FORMAT)
                if p in cam.info_ex.properties and p not in values
            ]
            for p in silent:
                find(f"{prop_name(p)} is listed in GetDeviceInfoEx but was never reported")
    if live_view and cam.is_eos:
        try:
            cam.start_live_view()
            frame = cam.live_view_frame()
            add(f"live-view probe:     one JPEG of {len(frame)} bytes ({_jpeg_size(frame)})")
        except (TransportError, ProtocolError, PtpError) as exc:
            find(f"live view failed: {exc}")
        finally:
            try:
                cam.stop_live_view()
            except (TransportError, ProtocolError, PtpError):
                pass
    seen_codes = sorted({int(a.split()[2], 16) for a in cam.anomalies if a.startswith("event record 0x")})
    for a in cam.anomalies:
        find(a)
    if seen_codes:
        add(
            "event records without a decoder (skipped): "
            + ", ".join(f"0x{c:04X} {EOS_EVENT_NAMES.get(c, '')}".strip() for c in seen_codes)
        )
    counters = cam.transport.counters
    add(
        f"link: {counters.timeouts} timeouts, {counters.stalls_cleared} stalls cleared, "
        f"{counters.stale_replies_discarded} late replies discarded, {counters.cancels_sent} cancels, "
        f"{counters.resets_sent} resets"
    )
    return r


def _jpeg_size(data: bytes) -> str:
    try:
        import cv2
        import numpy as np

        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_COLOR_2)
        if image is None:
            return "not a JPEG"
        return f"about {image.shape[1] * 2} x {image.shape[0] * 2} px"
    except Exception:
        return "size unknown"


def write_report(report: DoctorReport, path: Path | None = None) -> Path:
    """Write the report atomically; by default `mca-doctor-SERIAL-TIME.txt` in the current folder."""
    if path is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        serial = "".join(ch for ch in report.serial_number if ch.isalnum())[:32] or "camera"
        path = Path(f"mca-doctor-{serial}-{stamp}.txt")
    from mca.capture.outputs import write_bytes_atomic  # numpy comes with it: only when a report is written

    # the temporary is named, not made, before the writer's `try`: a Ctrl-C at any point leaves no part file
    return write_bytes_atomic(Path(path), report.text().encode("utf-8"))


__all__ = ["DoctorReport", "diagnose", "name_of", "write_report"]
