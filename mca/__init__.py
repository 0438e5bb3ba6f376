"""mca: accurate depth from one multi-colour-filter-aperture photograph.

The import package's front door. The repository keeps the design's three rooms as
top-level folders, mapped into this package by pyproject.toml:
`capture/` -> `mca.capture` (the application), `processing/` -> `mca.processing` (pure
algorithms), `devices/` -> `mca.devices` (hardware and its simulated twins).

The Python API (README, "Use from Python")::

    import mca
    result = mca.depth_from_file("IMG_0001.CR2", "paper-70d")   # a DepthResult
    frame = mca.read_raw("IMG_0001.CR2")                        # or arrays: mca.RawFrame.from_planes(...)
    result = mca.depth_from_frame(frame, mca.load_profile("paper-70d"))

The names below are imported on first use, so that `import mca` (and the `mca` command) stays fast.
"""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

try:
    __version__ = version("mca-appliance")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

_EXPORTS = {
    "depth_from_file": "mca.capture.api",
    "depth_from_frame": "mca.capture.api",
    "read_raw": "mca.capture.raw",
    "RawFrame": "mca.capture.raw",
    "RawReadError": "mca.capture.raw",
    "load_profile": "mca.devices.profiles",
    "CameraProfile": "mca.processing.camera",
    "DepthResult": "mca.processing.result",
    "CameraColour": "mca.processing.colour",
    "PinholeCamera": "mca.processing.pinhole",
}

__all__ = [
    "CameraColour",
    "CameraProfile",
    "DepthResult",
    "PinholeCamera",
    "RawFrame",
    "RawReadError",
    "__version__",
    "depth_from_file",
    "depth_from_frame",
    "load_profile",
    "read_raw",
]

if TYPE_CHECKING:
    from mca.capture.api import depth_from_file, depth_from_frame
    from mca.capture.raw import RawFrame, RawReadError, read_raw
    from mca.devices.profiles import load_profile
    from mca.processing.camera import CameraProfile
    from mca.processing.colour import CameraColour
    from mca.processing.pinhole import PinholeCamera
    from mca.processing.result import DepthResult


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'mca' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
