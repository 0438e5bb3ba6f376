"""`mca capture --live`: EOS live-view frames with a live MCA disparity preview, streamed to the rerun viewer.

Frames come from GetViewFinderData (0x9153) on the camera or the simulated 70D
(which serves JPEGs rendered from its scene). Each frame is decoded, previewed
with `processing.live_preview.live_disparity` (the profile's filter geometry)
and logged on the `live_frame` timeline: the frame itself (the JPEG as the camera
sent it), the disparity in false colour, its confidence, and the frame rate.
The loop ends after `frames`, on Ctrl-C, or when `stop()` says so; live view
is switched off again and the camera closed in every case.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from mca.devices.ptp.camera import Camera, CaptureError, PtpError
from mca.devices.ptp.codec import ProtocolError
from mca.devices.ptp.transport import TransportError
from mca.processing.live_preview import LivePreviewParams, disparity_colours, live_disparity

if TYPE_CHECKING:
    from mca.capture.recording.serve import ViewerServer


class LiveError(Exception):
    """Live view could not run (the camera offers none, or the viewer could not start)."""


@dataclass
class LiveStats:
    frames: int = 0
    width_px: int = 0
    height_px: int = 0
    frames_per_s: float = 0.0
    preview_ms_median: float = 0.0
    preview_ms: list[float] = field(default_factory=list, repr=False)


def decode_jpeg(data: bytes) -> np.ndarray:
    """(H, W, 3) uint8 RGB from JPEG bytes; a frame that does not decode is a `ProtocolError`."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ProtocolError(f"a live-view frame of {len(data)} bytes is not a JPEG")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


class LiveRecorder:
    """A rerun stream for live view: to a .rrd file, to a local web viewer (`serve`), or both."""

    def __init__(self, record: Path | None, serve: bool = False) -> None:
        from mca.capture.recording import disable_rerun_analytics

        disable_rerun_analytics()
        import rerun as rr

        self._rr = rr
        self._server: ViewerServer | None = None
        self.viewer_url: str | None = None
        self.stream = rr.RecordingStream("mca-live")
        sinks: list[Any] = []
        if record is not None:
            Path(record).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(record)))
        if serve:
            sinks.append(rr.GrpcSink(self._start_server()))
        if not sinks:
            raise LiveError("live view needs a recording file or --serve")
        self.stream.set_sinks(*sinks)

    def _start_server(self) -> str:
        """The local web viewer, started as `mca process --serve` starts it (`capture.recording.serve`)."""
        from mca.capture.recording.serve import start_viewer_server

        try:
            self._server = start_viewer_server("127.0.0.1", None, None)
        except RuntimeError as exc:
            raise LiveError(str(exc)) from None
        self.viewer_url = self._server.viewer_url
        return self._server.grpc_url

    def log_frame(self, index: int, jpeg: bytes, preview_rgb: np.ndarray, confidence: np.ndarray, fps: float) -> None:
        rr = self._rr
        self.stream.set_time("live_frame", sequence=index)
        self.stream.log("live/frame", rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))
        self.stream.log("live/disparity", rr.Image(preview_rgb))
        self.stream.log("live/confidence", rr.Image((np.clip(confidence, 0, 1) * 255).astype(np.uint8)))
        self.stream.log("live/frames_per_s", rr.Scalars(fps))

    def close(self) -> None:
        try:
            self.stream.flush()
            self.stream.disconnect()
        finally:
            if self._server is not None:
                self._server.stop()
                self._server = None


def run_live(
    factory: Callable[[], Camera],
    *,
    profile_name: str | None = None,
    record: Path | None = None,
    serve: bool = False,
    frames: int | None = None,
    log: Callable[[str], None] = lambda msg: None,
    stop: Callable[[], bool] | None = None,
    params: LivePreviewParams | None = None,
) -> LiveStats:
    """Live view until `frames` frames, Ctrl-C or `stop()`; returns what it measured."""
    from mca.devices.profiles import DEFAULT_PROFILE, load_profile

    profile = load_profile(profile_name or DEFAULT_PROFILE)
    recorder = LiveRecorder(record, serve)
    if recorder.viewer_url:
        log(f"live preview at {recorder.viewer_url}")
    stats = LiveStats()
    cam: Camera | None = None
    started = time.monotonic()
    try:
        try:
            cam = factory()
            cam.start_live_view()
        except (CaptureError, PtpError) as exc:
            raise LiveError(f"live view could not start: {exc}") from exc
        log("live view on; Ctrl-C to stop")
        while frames is None or stats.frames < frames:
            if stop is not None and stop():
                break
            jpeg = cam.live_view_frame()
            rgb = decode_jpeg(jpeg)
            t0 = time.perf_counter()
            preview = live_disparity(rgb, profile.aperture, params)
            stats.preview_ms.append(1000 * (time.perf_counter() - t0))
            stats.frames += 1
            stats.height_px, stats.width_px = rgb.shape[:2]
            elapsed = time.monotonic() - started
            fps = stats.frames / elapsed if elapsed > 0 else 0.0
            recorder.log_frame(stats.frames, jpeg, disparity_colours(preview), preview.confidence, fps)
            cam.keep_alive()
    except KeyboardInterrupt:
        log("stopping live view (Ctrl-C)")
    except (TransportError, ProtocolError, PtpError) as exc:
        raise LiveError(f"live view stopped: {exc}") from exc
    finally:
        if cam is not None:
            try:
                cam.stop_live_view()
            except (TransportError, ProtocolError, PtpError):
                pass
            cam.close()
        recorder.close()
    elapsed = time.monotonic() - started
    stats.frames_per_s = stats.frames / elapsed if elapsed > 0 else 0.0
    stats.preview_ms_median = statistics.median(stats.preview_ms) if stats.preview_ms else 0.0
    return stats
