"""Independent check: libgphoto2 (python-gphoto2 and Debian's gphoto2 CLI) drives `mca camera serve-sim` over PTP/IP."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from tools import require


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def served_sim():
    port = _free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from mca.capture.cli import main; main()",
            "camera",
            "serve-sim",
            "--ptpip",
            f"127.0.0.1:{port}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    pytest.fail(
                        f"serve-sim did not start: {proc.stderr.read().decode() if proc.poll() is not None else 'timeout'}"
                    )
                time.sleep(0.1)
        yield port
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _clean(run: subprocess.CompletedProcess) -> None:
    """gphoto2 printed no error and no warning (it once printed "Canon EOS Full-Press failed" and "ERROR:
    Could not capture image" against the simulator, and an "error 0x2005" for a missing folder listing)."""
    text = (run.stdout + run.stderr).lower()
    for word in ("error", "warning", "failed"):
        assert word not in text, run.stdout + run.stderr


def _expected_first_shot() -> bytes:
    from mca.devices.sim.world import scene_frame_source

    produced = scene_frame_source()(1)
    return produced[1] if isinstance(produced, tuple) else produced


def _check_with_libraw(path: Path) -> None:
    """What gphoto2 downloaded, decoded by LibRaw, is the mosaic the simulated 70D shot: size, crop and pixels.

    Shot 1 of the simulated camera is the simulator's rendering of scene paper-a with seed 1 (tether.
    scene_frame_source); the mosaic is taken from the renderer itself, before any CR2 encoding.
    """
    import rawpy

    from mca.devices.profiles import load_profile
    from mca.devices.sim.world import render_scene

    shot = render_scene("paper-a", load_profile("paper-70d"), size=os.environ.get("MCA_SIM_SIZE", "full"), seed=1)
    with rawpy.imread(str(path)) as raw:
        visible = raw.raw_image_visible
        assert visible.shape == shot.mosaic.shape  # size of the crop
        assert (raw.sizes.iheight, raw.sizes.iwidth) == shot.mosaic.shape
        assert raw.sizes.raw_height > visible.shape[0] and raw.sizes.raw_width > visible.shape[1]
        assert np.array_equal(visible, shot.mosaic)  # lossless: every photosite as shot
        assert raw.color_desc == b"RGBG" and raw.raw_pattern.tolist() == [[0, 1], [3, 2]]  # RGGB, as the 70D
        # the masked border around the crop holds the black level (optical black), not image data
        top, left = raw.sizes.top_margin, raw.sizes.left_margin
        assert top > 0 and left > 0
        border = raw.raw_image[:, :left]
        assert float(np.median(border)) == pytest.approx(shot.sensor.black_level, abs=2)
        assert list(raw.black_level_per_channel) == [shot.sensor.black_level] * 4


def test_python_gphoto2_summary_then_capture_and_download(served_sim: int) -> None:
    try:
        import gphoto2 as gp
    except ImportError:
        message = "python-gphoto2 (bundles libgphoto2) is not installed (pip install gphoto2, the test extra)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    cam = gp.Camera()
    ports = gp.PortInfoList()
    ports.load()
    # libgphoto2 takes the event port from a second ":PORT" (it defaults to 15740).
    cam.set_port_info(ports[ports.lookup_path(f"ptpip:127.0.0.1:{served_sim}:{served_sim}")])
    abilities = gp.CameraAbilitiesList()
    abilities.load()
    cam.set_abilities(abilities[abilities.lookup_model("PTP/IP Camera")])
    cam.init()
    try:
        summary = str(cam.get_summary())
        assert "Canon EOS 70D" in summary and "SIM70D0000001" in summary and "Canon EOS Capture" in summary
        path = cam.capture(gp.GP_CAPTURE_IMAGE)
        camera_file = cam.file_get(path.folder, path.name, gp.GP_FILE_TYPE_NORMAL)  # keep it alive while copying
        data = bytes(memoryview(camera_file.get_data_and_size()))
    finally:
        cam.exit()
    assert data == _expected_first_shot()


def test_gphoto2_cli_capture_and_download_gives_a_cr2_rawpy_opens(served_sim: int, tmp_path: Path) -> None:
    require("gphoto2", "apt-get install gphoto2")
    port = f"ptpip:127.0.0.1:{served_sim}:{served_sim}"
    summary = subprocess.run(
        ["gphoto2", "--port", port, "--summary"], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert summary.returncode == 0, summary.stderr
    assert "Model: Canon EOS 70D" in summary.stdout
    _clean(summary)
    run = subprocess.run(
        ["gphoto2", "--port", port, "--capture-image-and-download", "--filename", "shot.cr2"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr
    _clean(run)
    data = (tmp_path / "shot.cr2").read_bytes()
    assert data == _expected_first_shot()
    _check_with_libraw(tmp_path / "shot.cr2")
    to_card = subprocess.run(
        [
            "gphoto2",
            "--port",
            port,
            "--set-config",
            "capturetarget=1",
            "--capture-image-and-download",
            "--filename",
            "card.cr2",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert to_card.returncode == 0, to_card.stderr
    _clean(to_card)
    assert "/store_00020001/DCIM/100CANON/IMG_0002.CR2" in to_card.stdout and (tmp_path / "card.cr2").stat().st_size
    assert data[8:10] == b"CR"  # a CR2 (TIFF with Canon's "CR" marker)
    import rawpy

    with rawpy.imread(str(tmp_path / "card.cr2")) as card, rawpy.imread(str(tmp_path / "shot.cr2")) as first:
        assert card.raw_image_visible.shape == first.raw_image_visible.shape  # shot 2 (scene paper-b), same frame
        assert not np.array_equal(card.raw_image_visible, first.raw_image_visible)
