"""The simulated EOS 70D through the real pyusb transport and through PTP/IP: capture, events, RAM buffer, properties."""

from __future__ import annotations

import io

import pytest

from mca.devices.ptp.camera import Camera, ReleaseRefused
from mca.devices.ptp.codes import Op, Resp
from mca.devices.ptp.transport_ptpip import PtpIpTransport
from mca.devices.ptp.transport_usb import UsbTransport, find_cameras
from mca.devices.sim.eos70d.faults import FaultPlan
from mca.devices.sim.eos70d.ptpip_server import PtpIpServer
from mca.devices.sim.eos70d.responder import SimEos70D, deterministic_frame
from mca.devices.sim.eos70d.usb_backend import SimUsbBackend


def _open(backend: SimUsbBackend) -> Camera:
    return Camera.open(UsbTransport(find_cameras(backend)[0], timeout_s=0.5))


def test_pyusb_finds_the_simulated_camera_as_a_still_image_interface() -> None:
    import usb.core

    backend = SimUsbBackend()
    dev = usb.core.find(idVendor=0x04A9, backend=backend)
    assert dev is not None and dev.idProduct == 0x3253
    cams = find_cameras(backend)
    assert [(c.port, c.product, c.serial_number) for c in cams] == [("usb:001:004", "Canon EOS 70D", "SIM70D0000001")]


def test_capture_to_card_uses_eos_remote_release_and_downloads_identical_bytes() -> None:
    backend = SimUsbBackend()
    with _open(backend) as cam:
        assert cam.is_eos
        obj = cam.capture(timeout_s=5)
        buf = io.BytesIO()
        progress = []
        cam.download(obj.handle, obj.size_bytes, buf, block_bytes=50_000, progress=lambda d, t: progress.append(d))
    assert buf.getvalue() == backend.camera.file_on_card("IMG_0001.CR2") == deterministic_frame(1)
    assert progress[-1] == obj.size_bytes and len(progress) == -(-obj.size_bytes // 50_000)
    log = backend.camera.operations_log
    assert Op.EOS_REMOTE_RELEASE_ON in log and Op.INITIATE_CAPTURE not in log and Op.EOS_GET_PARTIAL_OBJECT in log


def test_ram_capture_fills_the_buffer_until_downloaded() -> None:
    backend = SimUsbBackend(SimEos70D(ram_buffer_slots=1))
    with _open(backend) as cam:
        cam.set_property("capturetarget", "ram")
        obj = cam.capture(timeout_s=5)
        assert obj.in_ram
        with pytest.raises(ReleaseRefused) as refused:
            cam.capture(timeout_s=1)
        assert refused.value.code == Resp.DEVICE_BUSY and backend.camera.exposures == 1
        buf = io.BytesIO()
        cam.download(obj.handle, obj.size_bytes, buf)
        cam.transfer_complete(obj.handle)
        assert cam.capture(timeout_s=5).in_ram
    assert buf.getvalue() == deterministic_frame(1)


def test_properties_by_human_name_with_allowed_values() -> None:
    backend = SimUsbBackend()
    with _open(backend) as cam:
        iso = cam.get_property("ISO")
        assert iso.value == "100" and "6400" in iso.allowed
        assert cam.set_property("iso", "1600").value == "1600"
        assert cam.set_property("shutter speed", "1/250").value == "1/250"
        assert cam.set_property("imageformat", "RAW + Large Fine JPEG").value == "RAW + Large Fine JPEG"
        with pytest.raises(ValueError):
            cam.set_property("iso", "123")
    assert backend.camera.props[0xD103] == 0x68 and backend.camera.props[0xD102] == 0x78


def test_generic_ptp_camera_uses_initiate_capture_and_interrupt_events() -> None:
    backend = SimUsbBackend(SimEos70D(eos=False))
    with _open(backend) as cam:
        assert not cam.is_eos
        obj = cam.capture(timeout_s=5)
        buf = io.BytesIO()
        cam.download(obj.handle, obj.size_bytes, buf)
    assert Op.INITIATE_CAPTURE in backend.camera.operations_log
    assert buf.getvalue() == deterministic_frame(1)


def test_shutter_button_shots_arrive_through_events() -> None:
    backend = SimUsbBackend()
    with _open(backend) as cam:
        assert cam.wait_for_object(0.05) is None
        backend.camera.press_shutter_button()
        obj = cam.wait_for_object(2.0)
    assert obj is not None and obj.filename == "IMG_0001.CR2"


@pytest.mark.parametrize("faults", [FaultPlan(short_read_bytes=777), FaultPlan(coalesce_response=True)])
def test_short_reads_and_coalesced_responses_still_give_identical_bytes(faults: FaultPlan) -> None:
    backend = SimUsbBackend(faults=faults)
    with _open(backend) as cam:
        obj = cam.capture(timeout_s=5)
        buf = io.BytesIO()
        cam.download(obj.handle, obj.size_bytes, buf, block_bytes=65_536)
    assert buf.getvalue() == deterministic_frame(1)


def test_ptpip_capture_and_download() -> None:
    with PtpIpServer(port=0) as server, Camera.open(PtpIpTransport("127.0.0.1", server.port, timeout_s=2)) as cam:
        assert cam.info.model == "Canon EOS 70D"
        obj = cam.capture(timeout_s=5)
        buf = io.BytesIO()
        cam.download(obj.handle, obj.size_bytes, buf)
    assert buf.getvalue() == deterministic_frame(1)


def test_ptpip_server_refuses_non_loopback_addresses() -> None:
    with pytest.raises(ValueError):
        PtpIpServer(host="0.0.0.0", port=0)


# -- the 70D's other answers ---------------------------------------------------------------------------------------


def test_the_eos_folder_listing_and_standard_property_descriptions() -> None:
    from mca.devices.ptp.datasets import parse_eos_folder_entries
    from mca.devices.sim.eos70d.responder import SimBehaviour

    backend = SimUsbBackend(SimEos70D(behaviour=SimBehaviour(files_on_card=4)))
    with _open(backend) as cam:
        root = parse_eos_folder_entries(cam._data(Op.EOS_GET_OBJECT_INFO_EX, (0x20001, 0xFFFFFFFF, 0x100000)))
        assert [e.filename for e in root] == ["DCIM"]
        dcim = parse_eos_folder_entries(cam._data(Op.EOS_GET_OBJECT_INFO_EX, (0x20001, root[0].handle, 0x100000)))
        assert sorted(e.filename for e in dcim) == ["100CANON", "101CANON"]
        files = [info.filename for _h, info in cam.files()]
        assert len(files) == 4 and all(f.endswith(".JPG") for f in files)
        battery = cam.prop_desc(0x5001)
        assert (battery.current, battery.allowed) == (75, (100, 75, 50, 25, 0))
        assert cam.prop_desc(0xD402).current == "Canon EOS 70D"


def test_live_view_frames_come_only_while_the_output_goes_to_the_computer() -> None:
    from mca.devices.ptp.codes import Resp as R

    backend = SimUsbBackend(SimEos70D(live_view_source=lambda i: b"\xff\xd8frame%d" % i))
    with _open(backend) as cam:
        resp = cam._call(Op.EOS_GET_VIEWFINDER_DATA, (0x00200000, 0, 0), check=False)
        assert resp.code == R.CANON_OBJECT_NOT_READY  # live view is off
        cam.start_live_view()
        assert backend.camera.value(0xD1B0) == 2
        assert cam.live_view_frame() == b"\xff\xd8frame1" and cam.live_view_frame() == b"\xff\xd8frame2"
        cam.stop_live_view()
        assert backend.camera.value(0xD1B0) == 0
