"""PTP benchmarks: download throughput through the simulated USB backend, and shot-to-result latency at USB 2.0 pace.

Run: `.venv/bin/python benchmarks/bench_ptp.py`. Prints medians; asserts nothing about time.
"""

from __future__ import annotations

import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mca.devices.ptp.camera import Camera
from mca.devices.ptp.transport_usb import UsbTransport, find_cameras
from mca.devices.sim.eos70d.responder import SimEos70D, deterministic_frame
from mca.devices.sim.eos70d.usb_backend import USB2_BYTES_PER_S, SimUsbBackend

RAW_20MP_BYTES = 25 * 1024 * 1024  # a 70D RAW (20.2 MP, 14 bit, lossless JPEG) is about 25 MB


class _Null(io.RawIOBase):
    def write(self, b):  # type: ignore[override]
        return len(b)


def download_throughput(size_bytes: int = 64 * 1024 * 1024, repeats: int = 5, block_bytes: int = 1024 * 1024) -> float:
    frame = deterministic_frame(1, size_bytes)
    backend = SimUsbBackend(SimEos70D(lambda i: ("BIG.CR2", frame)))
    cam = Camera.open(UsbTransport(find_cameras(backend)[0]))
    obj = cam.capture(timeout_s=5)
    rates = []
    for _ in range(repeats):
        t = time.perf_counter()
        cam.download(obj.handle, obj.size_bytes, _Null(), block_bytes=block_bytes)
        rates.append(size_bytes / (time.perf_counter() - t))
    cam.close()
    return statistics.median(rates)


def shot_to_result_latency(repeats: int = 3) -> tuple[float, float]:
    """Seconds from the release to the verified, catalogued file (and to a processed result when the pipeline exists)."""
    from mca.capture.tether import TetherSession
    from mca.devices.cameras import make_sim_rig, open_camera

    frame = deterministic_frame(1, RAW_20MP_BYTES)
    rig = make_sim_rig(lambda i: (f"IMG_{i:04d}.CR2", frame), pace_bytes_per_s=USB2_BYTES_PER_S)
    times = []
    with tempfile.TemporaryDirectory() as out:
        session = TetherSession(open_camera("sim", rig=rig), Path(out))
        session.connect()
        for _ in range(repeats):
            t = time.perf_counter()
            session.capture(1)
            times.append(time.perf_counter() - t)
        session.close()
    return statistics.median(times), RAW_20MP_BYTES / statistics.median(times)


def shot_to_processed_latency(repeats: int = 3) -> tuple[float, float]:
    """Seconds from the release of a simulated 20 MP MCA shot (a real CR2 of a paper scene) to its written results.

    Returns (median latency, median seconds of that spent downloading and verifying).
    """
    from mca.capture.tether import TetherSession
    from mca.devices.cameras import make_sim_rig, open_camera
    from mca.devices.profiles import load_profile
    from mca.devices.sim.world import capture_cr2_bytes, render_scene

    profile = load_profile("paper-70d")
    frame = capture_cr2_bytes(render_scene("paper-c", profile, size="full", seed=1), profile)
    rig = make_sim_rig(lambda i: (f"IMG_{i:04d}.CR2", frame), pace_bytes_per_s=USB2_BYTES_PER_S)
    totals, transfers = [], []
    with tempfile.TemporaryDirectory() as out:
        fetch = TetherSession(open_camera("sim", rig=rig), Path(out) / "fetch")
        fetch.connect()
        t = time.perf_counter()
        fetch.capture(1)
        transfers.append(time.perf_counter() - t)
        fetch.close()
        session = TetherSession(open_camera("sim", rig=rig), Path(out) / "shots", process=True, profile="paper-70d")
        session.connect()
        session.capture(1)  # warm-up: imports, thread pools
        for _ in range(repeats):
            t = time.perf_counter()
            [result] = session.capture(1)
            totals.append(time.perf_counter() - t)
            assert result.status == "processed", result.message
        session.close()
    return statistics.median(totals), statistics.median(transfers)


def main() -> None:
    rate = download_throughput()
    print(f"download throughput, simulated USB backend, 1 MiB GetPartialObject blocks: median {rate / 1e6:.0f} MB/s")
    rate16 = download_throughput(block_bytes=16 * 1024 * 1024)
    print(f"download throughput, 16 MiB blocks: median {rate16 / 1e6:.0f} MB/s")
    latency_s, effective = shot_to_result_latency()
    print(
        f"shot-to-file latency, 25 MB RAW at USB 2.0 pace ({USB2_BYTES_PER_S / 1e6:.0f} MB/s): median {latency_s:.2f} s "
        f"({effective / 1e6:.1f} MB/s end to end; processing time not included)"
    )
    total_s, transfer_s = shot_to_processed_latency()
    print(
        f"shot-to-result latency, simulated 20 MP MCA shot (paper-c CR2) at USB 2.0 pace: median {total_s:.2f} s "
        f"(release, download and verify {transfer_s:.2f} s; the rest is decoding, the pipeline and writing the "
        f"results)"
    )


if __name__ == "__main__":
    main()
