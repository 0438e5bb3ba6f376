"""pytest plugin loaded by `dev.py mutate` (mutation/mutate.py): makes hypothesis deterministic and bounded.

A mutant's verdict must not depend on which random examples one run happened to draw, so every
hypothesis test draws the same examples in every mutant's run, and no example database carries
failures from one mutant's run into the next. Each hypothesis test draws at most
MCA_MUTATION_EXAMPLES examples (default 50; the fuzz tests ask for 10,000, which would make one
mutant's run take minutes on two cores).
"""

from __future__ import annotations

import os

try:
    from hypothesis import settings
except ImportError:  # hypothesis is a test extra; a module whose tests do not use it does not need it
    settings = None

MAX_EXAMPLES = int(os.environ.get("MCA_MUTATION_EXAMPLES", "50"))

if settings is not None:
    settings.register_profile(
        "mutation", derandomize=True, database=None, print_blob=False, max_examples=MAX_EXAMPLES, deadline=None
    )
    settings.load_profile("mutation")


def pytest_collection_modifyitems(items: list) -> None:
    """Cap the examples of tests whose own @settings ask for more than MAX_EXAMPLES."""
    if settings is None:
        return
    for item in items:
        test = getattr(item, "obj", None)
        own = getattr(test, "_hypothesis_internal_use_settings", None)
        if own is not None and own.max_examples > MAX_EXAMPLES:
            test._hypothesis_internal_use_settings = settings(
                own, max_examples=MAX_EXAMPLES, derandomize=True, database=None, deadline=None
            )
