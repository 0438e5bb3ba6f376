"""A process that has more captures to do keeps the memory it frees (glibc's allocator) for the next one.

glibc's `malloc` maps every block above its mmap threshold (at most 32 MiB) on its own and unmaps it when freed.
A 20 MP capture's cost volumes, shifted bands and planes are such blocks: each capture takes them from fresh pages
again, which the kernel must zero and, in a virtual machine that hands freed memory back to its host (free page
reporting, as on the development machine), the host must back again: there a fresh 512 MiB array took 1.6 s to
touch the first time, 0.07 s when taken again at once, and 0.9-2.4 s again once it had been free for 2 s or more.

`keep_freed_memory` makes the allocator serve large blocks from its heap and never give the heap back, so the next
capture reuses the pages the last one freed. It is not for a process's first capture: the heap then has to grow
from nothing, in smaller pieces than the mapped blocks, and ends about 300 MiB larger than their peak (a single
20 MP `mca process` took 7.6-8.6 s with it from the start against 6.7-6.9 s without, four runs each). The batch
runner and the tether session call it once a capture is done (`capture.batch`, `capture.tether`); a single
photograph never sees it. Throughput over 20 copies of a 20 MP CR2 (docs/batch.md): 8.1 -> 10.1 files per
minute with one worker, 11.3 -> 13.1 with two; each process then holds its high-water mark (about 1.3 GiB)
between captures. `MCA_RETURN_MEMORY=1` leaves the allocator as it is. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys

# mallopt(3) parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_NEVER = 2**31 - 1  # the largest value the parameter takes: the heap's top is never given back

RETURN_MEMORY_ENV = "MCA_RETURN_MEMORY"

_kept = False


def keep_freed_memory() -> bool:
    """From now on, serve large blocks from the heap and keep what is freed for reuse (module docstring). True
    when it is in effect (also when an earlier call set it), False elsewhere than glibc or when
    `MCA_RETURN_MEMORY` is set to anything but 0."""
    global _kept
    if _kept:
        return True
    if os.environ.get(RETURN_MEMORY_ENV, "0") not in ("", "0") or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)  # the process's own symbols, libc's among them: no search for the library file
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 - glibc's alone: musl has mallopt as a stub that does nothing
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 when it took the value: no block mapped on its own, and the heap never trimmed
    _kept = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_NEVER))
    return _kept


__all__ = ["RETURN_MEMORY_ENV", "keep_freed_memory"]
