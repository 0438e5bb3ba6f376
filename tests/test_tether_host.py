"""What a real EOS body needs from the host (issue 14), point by point, each against the simulated 70D made to
behave as a real body does. Most tests change the simulator only through wrappers around its responder, so
they run against older host code too and show what it got wrong."""

from __future__ import annotations

import io
import socket
import struct
import threading
from dataclasses import replace
from pathlib import Path

import pytest

from mca.capture.tether import TetherSession
from mca.devices.cameras import make_sim_rig, open_camera
from mca.devices.ptp.camera import Camera, CaptureError, PtpError
from mca.devices.ptp.codec import Container
from mca.devices.ptp.codes import ContainerType, Op, Resp
from mca.devices.ptp.properties import EOS_APERTURE, EOS_ISO, EOS_SHUTTER, spec_for
from mca.devices.ptp.transport_usb import UsbTransport, find_cameras
from mca.devices.sim.eos70d.faults import FaultPlan
from mca.devices.sim.eos70d.responder import Reply, SimEos70D, default_frame_source
from mca.devices.sim.eos70d.usb_backend import SimUsbBackend

EVENT_TERMINATOR = struct.pack("<II", 8, 0)


def _open(backend: SimUsbBackend, timeout_s: float = 2.0) -> Camera:
    return Camera.open(UsbTransport(find_cameras(backend)[0], timeout_s=timeout_s))


def _wrap(sim: SimEos70D, hook) -> None:
    """Route every command through `hook(command, data_out, original_handle) -> Reply`."""
    original = sim.handle
    sim.handle = lambda cmd, data_out=None: hook(cmd, data_out, original)  # type: ignore[method-assign]


def _ops(sim: SimEos70D) -> list[int]:
    return list(sim.operations_log)


# 1. vendor extension id 6 ------------------------------------------------------------------------------------------


def test_a_body_that_reports_vendor_id_6_on_the_wire_is_driven_as_a_canon_eos(tmp_path: Path) -> None:
    """Real 70D, 60D, 600D, R10 ... send Microsoft's 6; with that alone the old host found no EOS remote mode,
    no properties and no capture."""
    rig = make_sim_rig(default_frame_source)
    sim = rig.camera
    real = SimEos70D.device_info
    sim.device_info = lambda: replace(real(sim), vendor_extension_id=6)  # type: ignore[method-assign]
    cam = _open(rig.backend)
    try:
        assert cam.is_eos
        assert cam.get_property("iso").value == "100"
        obj = cam.capture()
        buf = io.BytesIO()
        cam.download(obj.handle, obj.size_bytes, buf)
    finally:
        cam.close()
    assert buf.getvalue() == sim.file_on_card("IMG_0001.CR2") and sim.exposures == 1


# 2. a retry must never fire the shutter twice ---------------------------------------------------------------------


def test_an_unanswered_event_poll_after_the_release_does_not_fire_the_shutter_again(tmp_path: Path) -> None:
    """The first GetEvent after each full press gets no reply (the host times out). The old session retried the
    whole capture, release included: two exposures, only the second one downloaded."""
    rig = make_sim_rig(default_frame_source, faults=FaultPlan())
    sim, backend = rig.camera, rig.backend

    def hook(cmd, data_out, handle):
        if cmd.code == Op.EOS_REMOTE_RELEASE_ON and cmd.params[:1] == (2,):
            backend.faults.stall_op = Op.EOS_GET_EVENT  # the next poll is never answered
        return handle(cmd, data_out)

    _wrap(sim, hook)
    session = TetherSession(open_camera("sim", rig=rig, timeout_s=0.3), tmp_path)
    session.connect()
    results = session.capture(2)
    session.close()
    assert sim.exposures == 2
    assert [r.status for r in results] == ["downloaded", "downloaded"]
    assert sorted(p.name for p in tmp_path.glob("IMG_*.CR2")) == ["IMG_0001.CR2", "IMG_0002.CR2"]


# 3. slow answers --------------------------------------------------------------------------------------------------


def test_timeouts_follow_libgphoto2() -> None:
    from mca.devices.ptp.policy import DEFAULT_POLICY, SAFE_TO_REPEAT

    assert DEFAULT_POLICY.transaction_timeout_s == 20.0 and DEFAULT_POLICY.object_wait_s == 90.0
    assert DEFAULT_POLICY.capture_timeout_s >= 8.0 and DEFAULT_POLICY.start_timeout_s == 1.5
    assert Op.EOS_REMOTE_RELEASE_ON not in SAFE_TO_REPEAT and Op.EOS_REMOTE_RELEASE not in SAFE_TO_REPEAT
    assert Op.INITIATE_CAPTURE not in SAFE_TO_REPEAT and Op.EOS_GET_EVENT in SAFE_TO_REPEAT
    backend = SimUsbBackend()
    transport = UsbTransport(find_cameras(backend)[0])
    assert transport.timeout_s == 20.0
    transport.close()


def test_a_half_press_slower_than_five_seconds_is_waited_for(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source, scenario="slow-half-press")
    session = TetherSession(open_camera("sim", rig=rig), tmp_path)
    session.connect()
    results = session.capture(1)
    session.close()
    assert [r.status for r in results] == ["downloaded"] and rig.camera.exposures == 1


def test_a_reply_that_comes_after_the_timeout_is_discarded_and_its_events_kept(tmp_path: Path) -> None:
    """The body answers a GetEvent 0.8 s late and ignores the host's cancel: the late reply arrives in the next
    transaction. The old host took the transaction-id mismatch as fatal."""
    rig = make_sim_rig(default_frame_source, scenario="late-response")
    session = TetherSession(open_camera("sim", rig=rig, timeout_s=0.3), tmp_path)
    session.connect()
    results = session.capture(2)
    counters = session.camera.transport.counters
    session.close()
    assert [r.status for r in results] == ["downloaded"] * 2 and rig.camera.exposures == 2
    assert counters.stale_replies_discarded >= 1 and counters.cancels_sent >= 1


def test_after_a_timeout_the_host_cancels_the_transaction_and_resets_a_device_that_stays_busy(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source, faults=FaultPlan(stall_op=Op.EOS_GET_PARTIAL_OBJECT, ignore_cancel=True))
    requests: list[tuple[int, int, bytes]] = []
    original = rig.backend.ctrl_transfer

    def spy(dev_handle, request_type, request, value, index, data, timeout):
        if request_type == 0x21:
            requests.append((request, index, bytes(data) if data is not None else b""))
        return original(dev_handle, request_type, request, value, index, data, timeout)

    rig.backend.ctrl_transfer = spy  # type: ignore[method-assign]
    session = TetherSession(open_camera("sim", rig=rig, timeout_s=0.3), tmp_path)
    session.connect()
    results = session.capture(1)
    session.close()
    assert [r.status for r in results] == ["downloaded"]
    cancels = [r for r in requests if r[0] == 0x64]
    assert cancels and cancels[0][2][:2] == struct.pack("<H", 0x4001) and len(cancels[0][2]) == 6
    assert any(r[0] == 0x66 for r in requests)  # the stalled body stayed busy: device reset


def test_a_failed_half_press_is_released() -> None:
    """RemoteReleaseOn(1) fails: the host must send RemoteReleaseOff(1), or a real body stays half-pressed."""
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    sim = backend.camera

    def hook(cmd, data_out, handle):
        if cmd.code == Op.EOS_REMOTE_RELEASE_ON and cmd.params[:1] == (1,):
            handle(cmd, data_out)  # the body did press
            return Reply(Container(ContainerType.RESPONSE, Resp.GENERAL_ERROR, cmd.transaction_id, ()))
        return handle(cmd, data_out)

    _wrap(sim, hook)
    cam = _open(backend)
    with pytest.raises((CaptureError, PtpError)):
        cam.capture()
    cam.close()
    ops = _ops(sim)
    on = ops.index(Op.EOS_REMOTE_RELEASE_ON)
    assert Op.EOS_REMOTE_RELEASE_OFF in ops[on:] and ops.count(Op.EOS_REMOTE_RELEASE_ON) == 1
    assert not sim.half_pressed and sim.exposures == 0


def test_a_stalled_endpoint_is_cleared_and_the_read_retried(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source, scenario="epipe-download")
    session = TetherSession(open_camera("sim", rig=rig), tmp_path)
    session.connect()
    results = session.capture(1)
    stalls = session.camera.transport.counters.stalls_cleared
    session.close()
    assert [r.status for r in results] == ["downloaded"] and rig.backend.stalls_served == 1 and stalls == 1


# 4. settings that arrive late --------------------------------------------------------------------------------------


def test_settings_that_arrive_late_and_over_several_polls_are_waited_for() -> None:
    """For 0.3 s after SetEventMode(1) the body's polls are empty; the old host gave up with a KeyError."""
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    sim = backend.camera
    started: list[float] = []

    def hook(cmd, data_out, handle):
        import time

        if cmd.code == Op.EOS_SET_EVENT_MODE and cmd.params[:1] == (1,):
            started.append(time.monotonic())
        if cmd.code == Op.EOS_GET_EVENT and started and time.monotonic() - started[0] < 0.3:
            return Reply(Container(ContainerType.RESPONSE, Resp.OK, cmd.transaction_id, ()), EVENT_TERMINATOR)
        return handle(cmd, data_out)

    _wrap(sim, hook)
    cam = _open(backend)
    try:
        assert cam.get_property("capturetarget").value == "Memory card"
        assert cam.get_property("iso").value == "100"
        assert cam.capture().filename == "IMG_0001.CR2"
    finally:
        cam.close()


# 5. one odd event record must not cost the batch -------------------------------------------------------------------


def _append_to_event_lists(sim: SimEos70D, record: bytes) -> None:
    def hook(cmd, data_out, handle):
        reply = handle(cmd, data_out)
        if cmd.code == Op.EOS_GET_EVENT and reply.data is not None and len(reply.data) > 8:
            return Reply(reply.response, record + bytes(reply.data))
        return reply

    _wrap(sim, hook)


def test_an_event_record_nobody_can_parse_does_not_discard_the_new_file_in_the_same_poll() -> None:
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    # a list record of type 7 with one odd byte: the old parser refused the whole poll
    _append_to_event_lists(backend.camera, struct.pack("<IIIII", 21, 0xC18A, 0xD14D, 7, 1) + b"\x05")
    cam = _open(backend)
    try:
        assert cam.capture(timeout_s=5).filename == "IMG_0001.CR2"
    finally:
        cam.close()


def test_only_status_one_means_busy() -> None:
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    _append_to_event_lists(backend.camera, struct.pack("<III", 12, 0xC18B, 2))
    cam = _open(backend)
    try:
        assert cam.capture(timeout_s=5).filename == "IMG_0001.CR2"
    finally:
        cam.close()


# 7. capture destination, autofocus, RAM, tables, close, PTP/IP ----------------------------------------------------


def test_the_card_value_of_the_capture_destination_is_read_from_the_body(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    sim = rig.camera
    sim.lists[0xD11C] = (3, 2, struct.pack("<2I", 1, 4))  # a body whose card is 1
    sim.values[0xD11C] = struct.pack("<I", 4)
    session = TetherSession(open_camera("sim", rig=rig), tmp_path, capture_target="card")
    session.connect()
    assert sim.value(0xD11C) == 1
    session.capture(1)
    session.close()
    assert sim.card_files()


def test_the_host_asks_for_focus_information_and_reads_it_between_half_and_full_press() -> None:
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    cam = _open(backend)
    cam.capture()
    cam.close()
    ops = _ops(backend.camera)
    assert Op.EOS_SET_REQUEST_OLC_INFO_GROUP in ops[: ops.index(Op.EOS_REMOTE_RELEASE_ON)]
    half = ops.index(Op.EOS_REMOTE_RELEASE_ON)
    full = ops.index(Op.EOS_REMOTE_RELEASE_ON, half + 1)
    assert Op.EOS_GET_EVENT in ops[half:full]
    assert cam.focus is not None and cam.focus.focused


def test_one_shot_af_without_focus_is_refused_and_the_half_press_released(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source, scenario="af-fail")
    session = TetherSession(open_camera("sim", rig=rig), tmp_path)
    session.connect()
    [result] = session.capture(1)
    session.close()
    assert result.status == "refused" and "could not focus" in result.message
    assert rig.camera.full_presses == 0 and not rig.camera.half_pressed


def test_raw_plus_jpeg_to_ram_downloads_both_files_of_every_shot_and_frees_the_buffer(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    sim = rig.camera
    sim.ram_buffer_slots = 2  # one RAW+JPEG shot fills it
    session = TetherSession(open_camera("sim", rig=rig), tmp_path, capture_target="ram")
    session.connect()
    session.camera.set_property("imageformat", "RAW + Large Fine JPEG")
    results = session.capture(3)
    session.close()
    names = sorted(r.path.name for r in results)
    assert names == sorted(f"IMG_000{i}.{ext}" for i in (1, 2, 3) for ext in ("CR2", "JPG"))
    assert sim.exposures == 3 and sim.ram == {}
    assert _ops(sim).count(Op.EOS_TRANSFER_COMPLETE) == 6


def test_host_capacity_is_announced_before_a_ram_capture_when_the_body_counts_few_shots(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    sim = rig.camera
    sim.values[0xD11B] = struct.pack("<I", 5)
    session = TetherSession(open_camera("sim", rig=rig), tmp_path, capture_target="ram")
    session.connect()
    before = _ops(sim).count(Op.EOS_PC_HDD_CAPACITY)
    session.capture(1)
    session.close()
    assert _ops(sim).count(Op.EOS_PC_HDD_CAPACITY) > before


def test_closing_restores_the_capture_destination_and_turns_the_display_back_on(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    sim = rig.camera
    session = TetherSession(open_camera("sim", rig=rig), tmp_path, capture_target="ram")
    session.connect()
    assert sim.props[0xD11C] == 4
    session.capture(1)
    session.close()
    assert sim.props[0xD11C] == 2
    ops = _ops(sim)
    tail = [
        op
        for op in ops[ops.index(Op.EOS_REMOTE_RELEASE_ON) :]
        if op in (Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_EVENT_MODE, Op.CLOSE_SESSION)
    ]
    assert tail == [Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_EVENT_MODE, Op.CLOSE_SESSION]
    assert sim.remote_mode == 0 or sim.session_id == 0


def test_the_remote_mode_at_close_is_zero_then_one() -> None:
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    modes: list[int] = []

    def hook(cmd, data_out, handle):
        if cmd.code == Op.EOS_SET_REMOTE_MODE:
            modes.append(cmd.params[0])
        return handle(cmd, data_out)

    _wrap(backend.camera, hook)
    _open(backend).close()
    assert modes[-2:] == [0, 1]


def test_property_tables_cover_fast_lenses_expansion_iso_and_half_stops() -> None:
    assert EOS_APERTURE[0x15] == "1.8" and EOS_APERTURE[0x14] == "1.8" and EOS_APERTURE[0x18] == "2"
    assert EOS_APERTURE[0x1B] == "2.2" and EOS_APERTURE[0x1D] == "2.5" and EOS_APERTURE[0x10] == "1.4"
    assert EOS_APERTURE[0x24] == "3.5" and EOS_APERTURE[0x2C] == "4.5" and EOS_APERTURE[0x34] == "6.7"
    assert EOS_ISO[0x88] == "25600" and EOS_ISO[0x80] == "12800" and EOS_ISO[0x48] == "100"
    assert EOS_SHUTTER[0x6C] == "1/90" and EOS_SHUTTER[0x74] == "1/180" and EOS_SHUTTER[0xA0] == "1/8000"
    assert spec_for("aperture").table is EOS_APERTURE


def test_setting_f18_picks_the_code_the_body_offers() -> None:
    backend = SimUsbBackend(SimEos70D(default_frame_source))
    sim = backend.camera
    sim.values[0xD101] = struct.pack("<I", 0x30)
    cam = _open(backend)
    try:
        assert cam.set_property("aperture", "1.8").value == "1.8"
    finally:
        cam.close()
    assert sim.value(0xD101) == 0x15  # the third-stop code this body lists, not the half-stop 0x14


def test_ptpip_host_sends_the_same_guid_on_every_connection(monkeypatch: pytest.MonkeyPatch) -> None:
    from mca.devices.ptp.transport_ptpip import PtpIpTransport
    from mca.devices.sim.eos70d import ptpip_server

    seen: list[bytes] = []
    original = ptpip_server.parse_init_command_request

    def spy(body):
        request = original(body)
        seen.append(request.guid)
        return request

    monkeypatch.setattr(ptpip_server, "parse_init_command_request", spy)
    with ptpip_server.PtpIpServer(SimEos70D(default_frame_source), port=0) as server:
        for _ in range(2):
            Camera.open(PtpIpTransport("127.0.0.1", server.port, timeout_s=2)).close()
    assert len(seen) == 2 and seen[0] == seen[1]


def test_ptpip_host_reads_the_event_channel_and_answers_pings() -> None:
    """A camera pings its initiator on the event connection; a host that never reads it never answers."""
    from mca.devices.ptp.ptpip_packets import (
        INIT_COMMAND_ACK,
        INIT_EVENT_ACK,
        PING,
        PONG,
        pack_event_packet,
        pack_init_command_ack,
        pack_packet,
    )
    from mca.devices.ptp.transport_ptpip import PtpIpTransport, _Conn

    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    got_pong = threading.Event()

    def camera() -> None:
        cmd_sock, _ = listener.accept()
        cmd = _Conn(cmd_sock, "camera")
        cmd.recv_packet()
        cmd.send(pack_init_command_ack(1, b"\x01" * 16, "EOS70D"))
        evt_sock, _ = listener.accept()
        evt = _Conn(evt_sock, "camera")
        evt.recv_packet()
        evt.send(pack_packet(INIT_EVENT_ACK))
        evt.send(pack_event_packet(0x4002, 0, (7,)))
        evt.send(pack_packet(PING))
        evt_sock.settimeout(3.0)
        try:
            kind, _ = evt.recv_packet()
            if kind == PONG:
                got_pong.set()
        except Exception:
            pass
        cmd_sock.close()
        evt_sock.close()

    thread = threading.Thread(target=camera, daemon=True)
    thread.start()
    transport = PtpIpTransport("127.0.0.1", port, timeout_s=2)
    try:
        assert got_pong.wait(3.0)
        event = transport.read_event(1.0)
        assert event is not None and (event.code, event.params) == (0x4002, (7,))
    finally:
        transport.close()
        listener.close()
        thread.join(5)
    assert INIT_COMMAND_ACK == 2
