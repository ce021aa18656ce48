"""Sparse access: which block lies next to which, and a block loaded with ghost layers of its
neighbours -- the one place block and voxel addressing is written (in the spirit of OpenVDB's
ValueAccessor): the neighbour tables (:func:`block_neighbours`, :func:`block_neighbours27`), the
dense lattice of block rows for lookups by voxel index (:func:`block_lattice`, :func:`lattice_row`) and
:func:`load_ghosts`, which copies a block and any number of layers of its face, edge and corner
neighbours into a buffer, so that a kernel's voxel loop runs without lookups. The solvers, the
spline, the quality report and the component labelling use them; the stencils that read the
buffers are in :mod:`pipeline.field.stencils`.

Blocks are BlockGrid's 8^3 leaves, identified by their origins (multiples of 8); a table row
lists, per block, the row of the block at each offset (in blocks), -1 where there is none.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from pipeline.sparse.grid import LEAF, BlockGrid, pack_keys
from pipeline.util.jit import njit

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


def block_lattice(origins: np.ndarray, lat_lo: np.ndarray | None = None,
                  dims: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lattice, lat_lo): a dense int64 array of block rows (-1 where there is none) over the
    blocks ``lat_lo .. lat_lo + dims - 1`` (in blocks; default: the bounding box of ``origins``),
    for lookups by voxel index (:func:`lattice_row`). Origins outside the frame are left out."""
    b = np.asarray(origins, np.int64).reshape(-1, 3) >> 3
    if lat_lo is None:
        lat_lo = b.min(axis=0) if len(b) else np.zeros(3, np.int64)
        dims = (b.max(axis=0) - lat_lo + 1) if len(b) else np.ones(3, np.int64)
    lat_lo = np.asarray(lat_lo, np.int64)
    lattice = np.full(tuple(int(d) for d in dims), -1, dtype=np.int64)
    p = b - lat_lo
    ok = np.all((p >= 0) & (p < np.asarray(dims)), axis=1)
    lattice[p[ok, 0], p[ok, 1], p[ok, 2]] = np.flatnonzero(ok)
    return lattice, lat_lo


@njit(cache=True, inline="always")
def lattice_row(lattice, lat_lo, i, j, k):
    """Row of the block holding voxel (i, j, k) in a :func:`block_lattice`, -1 when absent."""
    bi = (i >> 3) - lat_lo[0]
    bj = (j >> 3) - lat_lo[1]
    bk = (k >> 3) - lat_lo[2]
    if bi < 0 or bj < 0 or bk < 0:
        return -1
    if bi >= lattice.shape[0] or bj >= lattice.shape[1] or bk >= lattice.shape[2]:
        return -1
    return lattice[bi, bj, bk]


@njit(cache=True, parallel=True)
def _lookup_rows(table, q, offsets, out):
    for b in prange(q.shape[0]):
        for f in range(offsets.shape[0]):
            out[b, f] = table[q[b, 0] + offsets[f, 0], q[b, 1] + offsets[f, 1], q[b, 2] + offsets[f, 2]]


@njit(cache=True)
def load_ghosts(vals, act, rows, nbr, cols, b, w, missing, buf, abuf):
    """Block b and ``w`` (1..8) layers of the neighbours that ``cols`` lists into ((8 + 2w)^3)
    buffers: voxel (i, j, k) of block b at (i + w, j + w, k + w), ``act`` into ``abuf``.

    ``cols[o]`` is the column of ``nbr`` that holds the neighbour at offset ``OFFSETS27[o]``, -1
    for an offset not to load (:data:`FACES6`, :data:`FACES27`, :data:`ALL27`); the centre is
    always loaded. Block n's values are row ``rows[n]`` of ``vals`` (another grid's blocks), row
    n itself when ``rows`` is empty. Where a block or its row is absent the buffer holds
    ``missing`` and abuf False; cells of offsets not loaded are left as they are."""
    same = rows.shape[0] == 0
    for o in range(27):
        if o == 13:
            n = np.int64(b)  # a prange index is unsigned: unified with int64 rows it would become float
        elif cols[o] < 0:
            continue
        else:
            n = nbr[b, cols[o]]
        r = n if same or n < 0 else rows[n]
        x0, nx, sx = _span(o // 9 - 1, w)
        y0, ny, sy = _span((o // 3) % 3 - 1, w)
        z0, nz, sz = _span(o % 3 - 1, w)
        for i in range(nx):
            for j in range(ny):
                for k in range(nz):
                    if r < 0:
                        buf[x0 + i, y0 + j, z0 + k] = missing
                        abuf[x0 + i, y0 + j, z0 + k] = False
                    else:
                        buf[x0 + i, y0 + j, z0 + k] = vals[r, sx + i, sy + j, sz + k]
                        abuf[x0 + i, y0 + j, z0 + k] = act[r, sx + i, sy + j, sz + k]


@njit(cache=True, inline="always")
def _span(d, w):
    """(first buffer cell, count, first source voxel) along one axis for a block offset d in -1..1."""
    if d < 0:
        return 0, w, 8 - w
    if d == 0:
        return w, 8, 0
    return 8 + w, w, 0


def _columns(offset_rows: list[int], table_cols: list[int]) -> np.ndarray:
    out = np.full(27, -1, np.int64)
    out[offset_rows] = table_cols
    return out


#: rows of :data:`OFFSETS27` (and columns of a :func:`block_neighbours27` table) of the six faces -x, +x, -y, +y, -z, +z
FACE_ROWS27 = np.array([4, 22, 10, 16, 12, 14], dtype=np.int64)
#: :func:`load_ghosts` columns: the six faces of a :func:`block_neighbours` table
FACES6 = _columns(list(FACE_ROWS27), list(range(6)))
#: :func:`load_ghosts` columns: the six faces of a :func:`block_neighbours27` table
FACES27 = _columns(list(FACE_ROWS27), list(FACE_ROWS27))
#: :func:`load_ghosts` columns: every offset of a :func:`block_neighbours27` table (edges, corners)
ALL27 = np.arange(27, dtype=np.int64)
#: load_ghosts ``rows`` for a grid read from its own rows (block n is row n of the values)
OWN_ROWS = np.zeros(0, np.int64)


@njit(cache=True)
def load_padded(vals, act, nbr, b, buf, abuf):
    """Block b and its six face layers (a :func:`block_neighbours` table) into (10,10,10)
    buffers; edges and corners and absent faces read as inactive zeros."""
    load_padded_rows(vals, act, OWN_ROWS, nbr, b, buf, abuf)


@njit(cache=True)
def load_padded_rows(vals, act, rows, nbr, b, buf, abuf):
    """:func:`load_padded` of another grid's blocks: block n is row ``rows[n]`` of ``vals``
    (row n itself when ``rows`` is empty)."""
    buf[:] = 0.0
    abuf[:] = False
    load_ghosts(vals, act, rows, nbr, FACES6, b, 1, 0.0, buf, abuf)
