"""Memory for the large block arrays of the hfrep stage, and leaves handed to a writer as they are made.

:func:`mapped_empty` puts an array on its own anonymous mapping so that :func:`release_rows`
can give its leading rows back to the OS once they are written; a :class:`LeafSource` is the
leaves of a grid as the writer (pipeline.io.vdbgrids) takes them: made a batch at a time by a
``fill`` callback, or held whole, and released (``done``) as they are written.
"""

from __future__ import annotations

import mmap
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.sparse.grid import BlockGrid


def mapped_empty(shape, dtype) -> np.ndarray:
    """An array on its own anonymous mapping, its pages faulted in by the kernel at once
    (``MAP_POPULATE``; the caller writes every element next): :func:`release_rows` can give its
    leading rows back to the OS once they are not read again, so a large working or output array
    shrinks while it is consumed instead of being freed only at the end.

    No transparent huge pages (NumPy advises them for its large arrays): with
    ``MADV_HUGEPAGE`` a fault compacts memory to find a free 2 MiB page, and on a VM that hands
    freed pages back to its host (free page reporting, docs/performance.md session 21) 558 MB
    first touched in 1.2 s against 0.19 s populated with small pages (session 22)."""
    dtype = np.dtype(dtype)
    count = int(np.prod(shape))
    # private: a released page is freed (a shared anonymous mapping would keep it in shmem)
    flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_POPULATE", 0)
    mm = mmap.mmap(-1, max(count * dtype.itemsize, 1), flags=flags)
    return np.frombuffer(mm, dtype, count=count).reshape(shape)


def release_rows(arr: np.ndarray, rows: int, start: int = 0) -> None:
    """Give the whole pages of ``arr``'s rows start..rows-1 back to the OS (they read as zeros
    afterwards: the caller never reads them again). Only for arrays from :func:`mapped_empty`
    (or views of them); for any other array nothing happens."""
    base = arr
    while base is not None and not isinstance(base, mmap.mmap):
        base = base.obj if isinstance(base, memoryview) else getattr(base, "base", None)
    rows = min(rows, len(arr))
    if base is None or rows <= start:
        return
    origin = np.frombuffer(base, np.uint8, count=0).__array_interface__["data"][0]
    offset = arr.__array_interface__["data"][0] - origin
    row = arr[0].nbytes
    page = mmap.PAGESIZE
    lo = -(-(offset + start * row) // page) * page  # whole pages only
    hi = (offset + rows * row) // page * page
    if hi > lo:
        base.madvise(mmap.MADV_DONTNEED, lo, hi - lo)


@dataclass
class LeafSource:
    """The 8^3 leaves of one grid as a writer takes them, a batch at a time.

    ``origins``: (L, 3), sorted as a BlockGrid keeps them. Either ``fill(lo, hi, values,
    active)`` puts leaves lo..hi-1 into the (hi - lo, 8, 8, 8) float32 / bool arrays it is given,
    or ``arrays`` = (values, active) holds every leaf. ``done(hi)``, when given, is called once
    leaves ..hi-1 are written (to release what made them). ``background``: the grid's."""

    voxel_size: float
    background: float
    origins: np.ndarray
    fill: Callable[[int, int, np.ndarray, np.ndarray], None] | None = None
    arrays: tuple[np.ndarray, np.ndarray] | None = None
    done: Callable[[int], None] | None = None

    @classmethod
    def of(cls, blocks: BlockGrid, consume: bool = False) -> LeafSource:
        """The leaves of ``blocks``; ``consume``: release its values and active flags as they are
        written (arrays from :func:`mapped_empty`; ``blocks`` must not be read afterwards)."""
        def done(hi: int) -> None:
            release_rows(blocks.values, hi)
            release_rows(blocks.active, hi)
        return cls(blocks.voxel_size, blocks.background, blocks.origins, arrays=(blocks.values, blocks.active),
                   done=done if consume else None)
