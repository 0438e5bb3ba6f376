"""pytest plugin loaded by `dev.py mutate` (mutation/mutate.py): makes hypothesis deterministic.

A mutant's verdict must not depend on which random examples one run happened to draw, so every
hypothesis test draws the same examples in every mutant's run, and no example database carries
failures from one mutant's run into the next.
"""

from __future__ import annotations

try:
    from hypothesis import settings
except ImportError:  # hypothesis is a test extra; a module whose tests do not use it does not need it
    settings = None

if settings is not None:
    settings.register_profile("mutation", derandomize=True, database=None, print_blob=False)
    settings.load_profile("mutation")
