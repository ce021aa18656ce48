"""Sparse access: which block lies next to which, and the voxel a stencil reaches across a block
face -- the one place block and voxel addressing is written (in the spirit of OpenVDB's
ValueAccessor and math/Stencils.h). The solvers, the spline, the quality report and the
component labelling all use these tables and kernels.

Blocks are BlockGrid's 8^3 leaves, identified by their origins (multiples of 8); a table row
lists, per block, the row of the block at each offset (in blocks), -1 where there is none.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from pipeline.sparse.grid import LEAF, BlockGrid, pack_keys

#: the six face directions, in the column order of :func:`block_neighbours` (-x, +x, -y, +y, -z, +z)
FACE_DIRS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)
#: every offset in (-1..1)^3, row (dx+1)*9 + (dy+1)*3 + (dz+1) (column order of :func:`block_neighbours27`)
OFFSETS27 = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)


def block_neighbours(blocks: BlockGrid | np.ndarray) -> np.ndarray:
    """(L,6) rows of the face neighbours (-x,+x,-y,+y,-z,+z) of every block, -1 if absent."""
    return neighbour_rows(_origins(blocks), FACE_DIRS)


def block_neighbours27(blocks: BlockGrid | np.ndarray) -> np.ndarray:
    """(L,27) rows of the blocks at every offset (-1..1)^3 (:data:`OFFSETS27`), -1 if absent."""
    return neighbour_rows(_origins(blocks), OFFSETS27)


def _origins(blocks: BlockGrid | np.ndarray) -> np.ndarray:
    return blocks.origins if isinstance(blocks, BlockGrid) else np.asarray(blocks, np.int64).reshape(-1, 3)


def neighbour_rows(origins: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Row (in ``origins``) of the block at each offset (in blocks) from every block, -1 where
    absent: looked up in a dense int32 lattice of rows when that costs at most 16 entries per
    block (a parallel pass), else by binary search over the packed keys."""
    n = len(origins)
    out = np.empty((n, len(offsets)), dtype=np.int64)
    if n == 0:
        return out
    p = origins >> 3
    lo = p.min(axis=0) - 1
    dims = p.max(axis=0) - lo + 2
    if int(np.prod(dims)) > 16 * n + (1 << 20) or n >= 2**31:
        keys = pack_keys(origins)
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        for f, step in enumerate(offsets):
            q = pack_keys(origins + LEAF * np.asarray(step))
            pos = np.minimum(np.searchsorted(sorted_keys, q), n - 1)
            out[:, f] = np.where(sorted_keys[pos] == q, order[pos], -1)
        return out
    table = np.full(tuple(int(x) for x in dims), -1, dtype=np.int32)
    q = p - lo
    table[q[:, 0], q[:, 1], q[:, 2]] = np.arange(n, dtype=np.int32)
    _lookup_rows(table, q, np.ascontiguousarray(offsets, dtype=np.int64), out)
    return out


@njit(cache=True, parallel=True)
def _lookup_rows(table, q, offsets, out):
    for b in prange(q.shape[0]):
        for f in range(offsets.shape[0]):
            out[b, f] = table[q[b, 0] + offsets[f, 0], q[b, 1] + offsets[f, 1], q[b, 2] + offsets[f, 2]]


@njit(cache=True, inline="always")
def resolve_voxel(nbr, b, i, j, k):
    """(block, i, j, k) of a voxel given in block b's local coordinates, where one index may be
    -1 or 8 (a face neighbour in the next block, ``nbr`` from :func:`block_neighbours`); block
    -1 when that block does not exist."""
    if i < 0:
        b, i = nbr[b, 0], 7
    elif i > 7:
        b, i = nbr[b, 1], 0
    elif j < 0:
        b, j = nbr[b, 2], 7
    elif j > 7:
        b, j = nbr[b, 3], 0
    elif k < 0:
        b, k = nbr[b, 4], 7
    elif k > 7:
        b, k = nbr[b, 5], 0
    return b, i, j, k
