"""Live view: the disparity preview recovers known channel shifts along the profile's filter geometry, and
`mca capture --live` streams frames and previews from the simulated 70D into a rerun recording."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from mca.capture.cli import app
from mca.capture.live import LiveError, decode_jpeg, run_live
from mca.devices.cameras import make_sim_rig, open_camera
from mca.devices.profiles import load_profile
from mca.devices.ptp.codec import ProtocolError
from mca.devices.sim.eos70d.responder import default_frame_source
from mca.processing.live_preview import LivePreviewParams, disparity_colours, live_disparity


def _mca_frame(disparity_px: float, profile: str = "paper-70d", size: tuple[int, int] = (960, 540)) -> np.ndarray:
    """A textured plane whose channels are displaced as the MCA would at `disparity_px` (each channel by
    disparity x its filter's direction), as 8-bit RGB."""
    aperture = load_profile(profile).aperture
    rng = np.random.default_rng(3)
    w, h = size
    texture = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    planes = []
    for channel in ("red", "green", "blue"):
        sx, sy = aperture.shift_per_disparity(channel)
        m = np.float32([[1, 0, disparity_px * sx], [0, 1, disparity_px * sy]])
        planes.append(cv2.warpAffine(texture, m, (w, h), borderMode=cv2.BORDER_REFLECT))
    return (np.stack(planes, -1) * 255).astype(np.uint8)


@pytest.mark.parametrize("profile", ["paper-70d", "bando2008"])
@pytest.mark.parametrize("disparity_px", [-7.0, -2.5, 0.0, 1.5, 6.0])
def test_the_preview_recovers_a_known_disparity(profile: str, disparity_px: float) -> None:
    preview = live_disparity(_mca_frame(disparity_px, profile), load_profile(profile).aperture)
    inner = preview.disparity_px[10:-10, 10:-10]
    assert np.mean(np.abs(inner - disparity_px) < 0.75) > 0.9
    assert preview.disparity_px.shape[1] <= LivePreviewParams().max_width_px and preview.scale == pytest.approx(3.0)
    assert np.median(preview.confidence[10:-10, 10:-10]) > 0.3


def test_the_sign_follows_the_convention_farther_is_positive() -> None:
    """README: a farther object shows red displaced to the right (paper-70d: red filter at x = +6 mm)."""
    aperture = load_profile("paper-70d").aperture
    assert aperture.shift_per_disparity("red")[0] > 0
    far = live_disparity(_mca_frame(4.0), aperture)
    near = live_disparity(_mca_frame(-4.0), aperture)
    assert np.median(far.disparity_px) > 3 and np.median(near.disparity_px) < -3


def test_a_flat_frame_has_low_confidence_and_bad_frames_are_refused() -> None:
    aperture = load_profile("paper-70d").aperture
    flat = live_disparity(np.full((540, 960, 3), 128, np.uint8), aperture)
    assert float(flat.confidence.max()) < 0.05
    assert disparity_colours(flat).shape == flat.disparity_px.shape + (3,)
    with pytest.raises(ValueError):
        live_disparity(np.zeros((540, 960), np.uint8), aperture)
    with pytest.raises(ValueError):
        live_disparity(np.zeros((8, 8, 3), np.uint8), aperture)
    with pytest.raises(ProtocolError):
        decode_jpeg(b"not a jpeg")


def test_live_view_from_the_simulated_70d_into_a_recording(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    record = tmp_path / "live.rrd"
    stats = run_live(open_camera("sim", rig=rig), record=record, frames=4)
    assert (stats.frames, stats.width_px, stats.height_px) == (4, 960, 540)  # the 70D's live-view size
    assert rig.camera.live_view_frames == 4 and rig.camera.value(0xD1B0) == 0  # output back to the camera
    assert record.stat().st_size > 10_000
    assert stats.preview_ms_median > 0 and stats.frames_per_s > 0


def test_live_view_on_a_body_without_it_is_a_clear_error(tmp_path: Path) -> None:
    from mca.devices.ptp.camera import Camera
    from mca.devices.ptp.transport_usb import UsbTransport, find_cameras
    from mca.devices.sim.eos70d.responder import SimEos70D
    from mca.devices.sim.eos70d.usb_backend import SimUsbBackend

    backend = SimUsbBackend(SimEos70D(default_frame_source, eos=False))
    with pytest.raises(LiveError, match="live view"):
        run_live(lambda: Camera.open(UsbTransport(find_cameras(backend)[0])), record=tmp_path / "x.rrd", frames=1)


def test_capture_live_command(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mca.devices.sim import world

    monkeypatch.setattr(world, "scene_frame_source", lambda *a, **k: default_frame_source)
    record = tmp_path / "live.rrd"
    result = CliRunner().invoke(app, ["capture", "--camera", "sim", "--live", "--frames", "3", "--record", str(record)])
    assert result.exit_code == 0, result.output
    assert "3 frames of 960x540 px" in result.output and record.exists()
    missing = CliRunner().invoke(app, ["capture", "--camera", "sim", "--live", "--frames", "1"])
    assert missing.exit_code == 2 and "--record" in missing.output
