"""Freed memory kept in the process for the length of a stage (glibc malloc), then given back.

glibc serves every allocation above its mmap threshold (at most 32 MiB) with a fresh mapping
and unmaps it when it is freed, so each large NumPy or Numba array is faulted in page by page
when first written. On this project's VMs a first touch costs 0.4-1.7 s per GiB
(docs/performance.md, session 24: the host takes freed pages back), and the components stage
allocates and frees several GiB of short-lived arrays per level at 2048^3. Inside
:func:`retained_heap` malloc takes everything from its heap and does not trim it, so a freed
array's pages are reused by the next one; on leaving, the old limits are set and
``malloc_trim`` returns what is free to the system. The cost is the heap's fragmentation: the
stage's own peak grows (2048^3: 8.8 -> 9.2 GiB); whole jobs kept so were 0.7 GiB higher at
1024^3, which is why only the components stage uses it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Iterator
from contextlib import contextmanager

# mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
M_MMAP_MAX = -4
_INT_MAX = 2**31 - 1
# what glibc's dynamic thresholds reach once a job has freed a large array (mallopt turns the
# dynamic adjustment off, so leaving sets them explicitly)
_AFTER = {M_MMAP_MAX: 65536, M_MMAP_THRESHOLD: 32 << 20, M_TRIM_THRESHOLD: 64 << 20}


def _glibc() -> ctypes.CDLL | None:
    if os.environ.get("FREPVDB_HEAP_RETAIN") == "0":  # the plain allocator, for comparisons
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None


@contextmanager
def retained_heap() -> Iterator[None]:
    """Allocate from malloc's heap without unmapping or trimming inside the block (glibc; a
    no-op elsewhere or with FREPVDB_HEAP_RETAIN=0)."""
    libc = _glibc()
    if libc is None:
        yield
        return
    libc.mallopt(M_MMAP_MAX, 0)
    libc.mallopt(M_TRIM_THRESHOLD, _INT_MAX)
    try:
        yield
    finally:
        for param, value in _AFTER.items():
            libc.mallopt(param, value)
        libc.malloc_trim(0)
