"""mca: accurate depth from one multi-colour-filter-aperture photograph.

The import package's front door. The repository keeps the design's three rooms as
top-level folders, mapped into this package by pyproject.toml:
`capture/` -> `mca.capture` (the application), `processing/` -> `mca.processing` (pure
algorithms), `devices/` -> `mca.devices` (hardware and its simulated twins).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mca-appliance")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
