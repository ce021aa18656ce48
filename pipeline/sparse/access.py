"""Sparse access: which block lies next to which, and the voxel a stencil reaches across a block
face -- the one place block and voxel addressing is written (in the spirit of OpenVDB's
ValueAccessor and math/Stencils.h): the neighbour tables, the voxel a face stencil reaches
(:func:`resolve_voxel`, :func:`face_value`) and a block loaded with its six face layers
(:func:`load_padded`). The solvers, the spline, the quality report and the component labelling
use them; the FIM keeps its own two-layer loader in its hot loop (pipeline.distance.fim).

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


@njit(cache=True, inline="always")
def face_value(vals, act, nbr, b, i, j, k, f):
    """(value, active) of the face neighbour f (-x,+x,-y,+y,-z,+z) of voxel (b,i,j,k)."""
    if f == 0:
        i -= 1
    elif f == 1:
        i += 1
    elif f == 2:
        j -= 1
    elif f == 3:
        j += 1
    elif f == 4:
        k -= 1
    else:
        k += 1
    b, i, j, k = resolve_voxel(nbr, b, i, j, k)
    if b < 0:
        return 0.0, False
    return vals[b, i, j, k], act[b, i, j, k]


@njit(cache=True)
def load_padded(vals, act, nbr, b, buf, abuf):
    """Block b and its six face layers (from the face neighbours) into (10,10,10) buffers."""
    load_padded_rows(vals, act, _SAME_ROWS, nbr, b, buf, abuf)


_SAME_ROWS = np.zeros(0, np.int64)  # load_padded_rows: block b is row b of the values


@njit(cache=True)
def load_padded_rows(vals, act, rows, nbr, b, buf, abuf):
    """:func:`load_padded` of another grid's blocks: block b (and face neighbour n) is row
    ``rows[b]`` (``rows[n]``) of ``vals``, row b itself when ``rows`` is empty; missing rows
    read as inactive zeros."""
    same = rows.shape[0] == 0
    abuf[:] = False
    buf[:] = 0.0
    r = b if same else rows[b]
    if r >= 0:
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    buf[i + 1, j + 1, k + 1] = vals[r, i, j, k]
                    abuf[i + 1, j + 1, k + 1] = act[r, i, j, k]
    for f in range(6):
        n = nbr[b, f]
        r = n if same or n < 0 else rows[n]
        if r < 0:
            continue
        for u in range(8):
            for v in range(8):
                if f == 0:
                    buf[0, u + 1, v + 1], abuf[0, u + 1, v + 1] = vals[r, 7, u, v], act[r, 7, u, v]
                elif f == 1:
                    buf[9, u + 1, v + 1], abuf[9, u + 1, v + 1] = vals[r, 0, u, v], act[r, 0, u, v]
                elif f == 2:
                    buf[u + 1, 0, v + 1], abuf[u + 1, 0, v + 1] = vals[r, u, 7, v], act[r, u, 7, v]
                elif f == 3:
                    buf[u + 1, 9, v + 1], abuf[u + 1, 9, v + 1] = vals[r, u, 0, v], act[r, u, 0, v]
                elif f == 4:
                    buf[u + 1, v + 1, 0], abuf[u + 1, v + 1, 0] = vals[r, u, v, 7], act[r, u, v, 7]
                else:
                    buf[u + 1, v + 1, 9], abuf[u + 1, v + 1, 9] = vals[r, u, v, 0], act[r, u, v, 0]
