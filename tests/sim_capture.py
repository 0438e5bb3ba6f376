"""One small simulated capture (the paper's Fig. 4 row g, a knife before a wall), processed once by `mca process`.

Shared by the API, colour and 3D-file tests: the CR2 the simulated camera writes, and the output folder
`mca process --record` makes of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

SCALE = 0.15  # of the 70D's 5472 x 3648: 820 x 548 photosites, about a second through the pipeline


@dataclass(frozen=True)
class ProcessedCapture:
    cr2: Path
    out_dir: Path  # OUT/<stem>/ with every output
    recording: Path


def make_capture(folder: Path, scene: str = "paper-g") -> ProcessedCapture:
    from typer.testing import CliRunner

    from mca.capture.cli import app
    from mca.devices.profiles import load_profile
    from mca.devices.sim.world import capture_cr2_bytes, render_scene

    profile = load_profile("paper-70d")
    folder.mkdir(parents=True, exist_ok=True)
    cr2 = folder / f"{scene}.CR2"
    cr2.write_bytes(capture_cr2_bytes(render_scene(scene, profile, size=SCALE), profile))
    recording = folder / "out" / "all.rrd"
    result = CliRunner().invoke(
        app,
        ["process", str(cr2), "--out", str(folder / "out"), "--profile", "paper-70d", "--record", str(recording), "-q"],
    )
    assert result.exit_code == 0, result.output
    return ProcessedCapture(cr2, folder / "out" / scene, recording)
