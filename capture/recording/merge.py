"""Several .rrd recordings merged into one (`rerun rrd merge`), landing atomically."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from mca.capture.recording.rerun_env import child_environment, rerun_executable


def merge_recordings(paths: list[Path], out_path: Path) -> None:
    """Merge several .rrd files into one (`rerun rrd merge`); each shot keeps its own recording inside."""
    if not paths:
        raise ValueError("merge_recordings needs at least one recording")
    missing = [str(p) for p in paths if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(f"no such recording: {', '.join(missing)}")
    exe = rerun_executable()
    if exe is None:
        raise RuntimeError("merging recordings needs the `rerun` command of rerun-sdk; reinstall rerun-sdk")
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.{os.getpid()}.tmp.rrd")
    try:
        proc = subprocess.run(
            [exe, "rrd", "merge", *[str(p) for p in paths], "-o", str(tmp)],
            env=child_environment(),
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"rerun rrd merge failed for {', '.join(map(str, paths))}: {proc.stderr.strip()[-500:]}")
        os.replace(tmp, out_path)
    except BaseException:  # a failed merge, or Ctrl-C while it ran: no half-written merge left beside the parts
        tmp.unlink(missing_ok=True)
        raise
