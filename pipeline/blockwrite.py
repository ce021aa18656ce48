"""Writing 8^3 blocks into an OpenVDB grid in batches (the hfrep stage's grids).

:func:`pipeline.grid.write_blocks` builds each run of leaves (consecutive along z) with NumPy
(``where``, ``astype``, ``concatenate``: several temporaries per run) from one ``BlockGrid``
that holds every block. Here the blocks are produced a batch at a time by a callback (so a
grid derived from another, e.g. the narrow band of the distance, is never held whole), and a
compiled pass lays each batch out as the runs ``copyFromArray`` takes. The calls and their
arrays are the same as ``write_blocks``'s for the same blocks, except that a run is split where
a batch ends: ``copyFromDense`` decides every leaf from that leaf's values alone (leaf-aligned
boxes), so the tree is the same.
"""

from __future__ import annotations

import mmap
from collections.abc import Callable

import numpy as np
from numba import njit, prange

from pipeline.grid import LEAF, BlockGrid

BATCH = 4096  # blocks per batch (8 MiB of float32 values) unless a call says otherwise


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


def write_batched(grid, origins: np.ndarray, fill: Callable[[int, int, np.ndarray, np.ndarray], None] | None,
                  scale: float = 1.0, batch: int | None = None, source: tuple[np.ndarray, np.ndarray] | None = None,
                  done: Callable[[int], None] | None = None) -> None:
    """Write the blocks at ``origins`` (sorted as a BlockGrid keeps them) into ``grid``:
    ``fill(lo, hi, values, active)`` puts blocks lo..hi-1 into the (hi-lo, 8, 8, 8) float32 /
    bool arrays it is given (or, without ``fill``, ``source`` = (values, active) holds every
    block). Values times ``scale`` where active, the grid's background elsewhere (so
    ``copyFromArray`` leaves those voxels inactive), as ``write_blocks``. ``done(hi)`` is called
    after blocks ..hi-1 are written (to release what produced them)."""
    o = np.asarray(origins, np.int64).reshape(-1, 3)
    if len(o) == 0:
        return
    bg = np.float32(grid.background)
    k = np.float32(scale)
    brk = np.ones(len(o), bool)  # a run starts where x, y change or z is not the next leaf
    brk[1:] = (o[1:, 0] != o[:-1, 0]) | (o[1:, 1] != o[:-1, 1]) | (o[1:, 2] != o[:-1, 2] + LEAF)
    size = min(BATCH if batch is None else batch, len(o))
    if fill is not None:
        values = np.empty((size, LEAF, LEAF, LEAF), np.float32)
        active = np.empty((size, LEAF, LEAF, LEAF), bool)
    packed = np.empty(size * LEAF**3, np.float32)
    for lo in range(0, len(o), size):
        hi = min(lo + size, len(o))
        n = hi - lo
        if fill is not None:
            fill(lo, hi, values[:n], active[:n])
            src_v, src_a, first = values, active, 0
        else:
            src_v, src_a, first = source[0], source[1], lo
        starts = np.flatnonzero(brk[lo:hi])
        if len(starts) == 0 or starts[0] != 0:  # a run that goes on from the previous batch restarts here
            starts = np.concatenate([[0], starts])
        ends = np.append(starts[1:], n)
        _pack_runs(src_v, src_a, first, starts, ends, k, bg, packed)
        for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
            arr = packed[s * LEAF**3:e * LEAF**3].reshape(LEAF, LEAF, LEAF * (e - s))
            grid.copyFromArray(arr, (int(o[lo + s, 0]), int(o[lo + s, 1]), int(o[lo + s, 2])))
        if done is not None:
            done(hi)


def write_leaves(grid, blocks: BlockGrid, scale: float = 1.0, batch: int | None = None, consume: bool = False) -> None:
    """:func:`pipeline.grid.write_blocks` (the same grid) through :func:`write_batched`.
    ``consume``: release the blocks' values and active flags as they are written (arrays from
    :func:`mapped_empty`; ``blocks`` must not be read afterwards)."""
    def done(hi):
        release_rows(blocks.values, hi)
        release_rows(blocks.active, hi)
    write_batched(grid, blocks.origins, None, scale, batch, (blocks.values, blocks.active), done if consume else None)


@njit(cache=True, parallel=True)
def _pack_runs(values, active, first, starts, ends, k, bg, out):
    """Each run of blocks first + starts[r] .. first + ends[r] - 1 as one C-ordered (8, 8, 8 m)
    array at ``out[512 starts[r]:]``: ``values * k`` where active, ``bg`` elsewhere."""
    for r in prange(starts.shape[0]):
        s, e = starts[r], ends[r]
        m = e - s
        base = s * 512
        for q in range(m):
            b = first + s + q
            for i in range(8):
                for j in range(8):
                    row = base + (i * 8 + j) * 8 * m + 8 * q
                    for kk in range(8):
                        out[row + kk] = values[b, i, j, kk] * k if active[b, i, j, kk] else bg
