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

from collections.abc import Callable

import numpy as np
from numba import njit, prange

from pipeline.grid import LEAF, BlockGrid

BATCH = 4096  # blocks per batch: 8 MiB of float32 values


def write_batched(grid, origins: np.ndarray, fill: Callable[[int, int, np.ndarray, np.ndarray], None] | None,
                  scale: float = 1.0, batch: int = BATCH, source: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Write the blocks at ``origins`` (sorted as a BlockGrid keeps them) into ``grid``:
    ``fill(lo, hi, values, active)`` puts blocks lo..hi-1 into the (hi-lo, 8, 8, 8) float32 /
    bool arrays it is given (or, without ``fill``, ``source`` = (values, active) holds every
    block). Values times ``scale`` where active, the grid's background elsewhere (so
    ``copyFromArray`` leaves those voxels inactive), as ``write_blocks``."""
    o = np.asarray(origins, np.int64).reshape(-1, 3)
    if len(o) == 0:
        return
    bg = np.float32(grid.background)
    k = np.float32(scale)
    brk = np.ones(len(o), bool)  # a run starts where x, y change or z is not the next leaf
    brk[1:] = (o[1:, 0] != o[:-1, 0]) | (o[1:, 1] != o[:-1, 1]) | (o[1:, 2] != o[:-1, 2] + LEAF)
    size = min(batch, len(o))
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


def write_leaves(grid, blocks: BlockGrid, scale: float = 1.0, batch: int = BATCH) -> None:
    """:func:`pipeline.grid.write_blocks` (the same grid) through :func:`write_batched`."""
    write_batched(grid, blocks.origins, None, scale, batch, (blocks.values, blocks.active))


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
