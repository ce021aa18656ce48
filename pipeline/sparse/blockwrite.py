"""Memory for the large block arrays of the hfrep stage, and writing blocks as they are consumed.

:func:`mapped_empty` puts an array on its own anonymous mapping so that :func:`release_rows`
can give its leading rows back to the OS once they are written; :func:`write_leaves` writes a
``BlockGrid`` through :func:`pipeline.sparse.grid.write_batched` (runs of leaves laid out by a compiled
pass, a batch at a time) and can release the blocks as it goes.
"""

from __future__ import annotations

import mmap

import numpy as np

from pipeline.sparse.grid import BlockGrid, write_batched


def mapped_empty(shape, dtype) -> np.ndarray:
    """An uninitialised array on its own anonymous mapping (transparent huge pages advised, as
    NumPy does for large arrays): :func:`release_rows` can give its leading rows back to the OS
    once they are not read again, so a large working or output array shrinks while it is
    consumed instead of being freed only at the end."""
    dtype = np.dtype(dtype)
    count = int(np.prod(shape))
    # private: a released page is freed (a shared anonymous mapping would keep it in shmem)
    mm = mmap.mmap(-1, max(count * dtype.itemsize, 1), flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    if hasattr(mmap, "MADV_HUGEPAGE"):
        mm.madvise(mmap.MADV_HUGEPAGE)
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


def write_leaves(grid, blocks: BlockGrid, scale: float = 1.0, batch: int | None = None, consume: bool = False) -> None:
    """:func:`pipeline.sparse.grid.write_blocks` (the same grid) through :func:`write_batched`.
    ``consume``: release the blocks' values and active flags as they are written (arrays from
    :func:`mapped_empty`; ``blocks`` must not be read afterwards)."""
    def done(hi):
        release_rows(blocks.values, hi)
        release_rows(blocks.active, hi)
    write_batched(grid, blocks.origins, None, scale, batch, (blocks.values, blocks.active), done if consume else None)
