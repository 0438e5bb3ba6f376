"""What every numba kernel of the pipeline is compiled with.

`FASTMATH` holds only the fastmath flags that cannot change a finite result: the kernels may assume that no
value is NaN or infinite (`nnan`, `ninf`), which lets the compiler vectorise comparisons and min / max, and
nothing else. The flags that let it re-associate sums (`reassoc`), fuse a multiply and an add (`contract`),
replace a division by a reciprocal (`arcp`) or use approximate functions (`afn`) give results that depend on
how a loop was compiled: vectorised or not, inlined or not, compiled in this process or loaded from numba's
cache. Under numba 0.60 the colour-alignment cost compiled in one process and the same cost loaded from the
cache in another differed in the last bits, and a batch's two workers then wrote a region's confidence 1e-10
apart from one worker's (CI's lowest-versions job). Without those four flags the same input gives the same
bits in every process; `tests/test_kernel_determinism.py` checks it.
"""

from __future__ import annotations

FASTMATH = {"nnan", "ninf"}

__all__ = ["FASTMATH"]
