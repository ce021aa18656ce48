"""The narrow band of a voxelised field, marked on its 8^3 leaves once they hold their evaluated
values: which voxels are active.

approximate-distance-fields 1.2: |f| / |grad f| is a first-order estimate of the distance to the
zero set; a voxel is in the band when that estimate is at most ``band`` voxels. Two amendments
make the band a function of the field alone, not of how the voxeliser visited it:

* **S, the sign changes.** A voxel whose sign (f > 0, of the stored float32 value) differs from
  that of an evaluated face neighbour, or whose value is 0, is always active: the band is closed
  (issue 12), so a flood fill of the signs cannot leak through it.
* **The reach.** The estimate is trusted only within ``ceil(band) - 1`` voxels (L-infinity) of
  S (:func:`reach_voxels`: along an axis, every voxel nearer than ``band`` voxels to the zero
  set, as in OpenVDB's narrow band of that half-width), and the gradient is taken by differences
  between voxels of the reach (central where both neighbours are in it:
  :func:`pipeline.field.stencils.half_difference`). The voxeliser bounds each cell over its box
  dilated by ceil(band) voxels (:func:`cull_pad_voxels`), so every voxel of the reach is
  evaluated whatever the block size. Farther out a field may still have |f| / |grad f| <= band
  (a min/max of plane distances underestimates the distance), but whether such a voxel was
  evaluated depends on the block size: it is left out. The dilation is separable through the
  leaves that exist (every voxel between S and its reach is evaluated, so its leaf exists): it
  equals the L-infinity dilation.

The masks are held as bit rows, one byte per (leaf, x, y) with bit z (OpenVDB's own leaf mask
layout, one bit per voxel), so the sign test and the dilation of S into the reach are a few
word operations per row; only the distance test reads values.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from pipeline.field.stencils import half_difference
from pipeline.sparse.access import block_neighbours
from pipeline.sparse.grid import LEAF, BlockGrid
from pipeline.util.jit import njit

MAX_STEP = LEAF - 1  # voxels a dilation pass may reach into a neighbour leaf


def reach_voxels(band: float) -> int:
    """How far (voxels, L-infinity) from S the distance test runs: ceil(band) - 1. Along an axis
    the S voxel is within one voxel of the zero set and the next ``ceil(band) - 1`` voxels are
    within ``band`` of it: OpenVDB's narrow band of half-width ``band`` (|d| < band voxels)."""
    return int(np.ceil(max(float(band), 1.0) - 1e-9)) - 1


def cull_pad_voxels(band: float) -> float:
    """How far (voxels) the voxeliser dilates a cell's box before bounding it: a zero within that
    distance keeps the cell. The reach plus one voxel (the zero next to an S voxel is at most one
    voxel away from it), so every voxel of the reach is evaluated: ceil(band), at least 1."""
    return float(reach_voxels(band) + 1)


def mark_band(grid: BlockGrid, known: np.ndarray, band: float) -> int:
    """Set ``grid.active`` from the evaluated (``known``) voxels of its leaves, reading face
    neighbours across leaves. Returns how many voxels only the sign test made active."""
    if len(grid.origins) == 0:
        return 0
    nbr, sign, reach = _reach_rows(grid, known, band)
    return int(_band_test(grid.values, reach, sign, nbr, float(band), grid.active))


def reach_bits(grid: BlockGrid, known: np.ndarray, band: float) -> np.ndarray:
    """(L, 8, 8) uint8 bit rows (bit z) of the known voxels whose values :func:`mark_band` reads:
    S and its reach. Every other voxel of the leaves counts by its sign alone."""
    if len(grid.origins) == 0:
        return np.zeros((0, LEAF, LEAF), np.uint8)
    return _reach_rows(grid, known, band)[2]


def _reach_rows(grid: BlockGrid, known: np.ndarray, band: float):
    """(face neighbours, S, S's reach among the known voxels) as bit rows."""
    nbr = block_neighbours(grid)  # -x, +x, -y, +y, -z, +z
    pos, kn, zero = _row_bits(grid.values, known)
    sign = _sign_changes(pos, kn, zero, nbr)
    near = sign
    reach = reach_voxels(band)
    while reach > 0:  # separable L-infinity dilation: exact, since every voxel between S and
        step = min(reach, MAX_STEP)  # the reach is evaluated (so its leaf exists)
        for axis in range(3):
            near = _dilate_axis(near, nbr, axis, step)
        reach -= step
    return nbr, sign, near & kn


@njit(cache=True, parallel=True)
def _row_bits(values, known):
    """(positive, known, zero) bit rows (L, 8, 8) uint8 of the known voxels' values."""
    n = values.shape[0]
    pos = np.zeros((n, LEAF, LEAF), np.uint8)
    kn = np.zeros((n, LEAF, LEAF), np.uint8)
    zero = np.zeros((n, LEAF, LEAF), np.uint8)
    for r in prange(n):
        for i in range(LEAF):
            for j in range(LEAF):
                p, q, z = 0, 0, 0
                for k in range(LEAF):
                    if known[r, i, j, k]:
                        q |= 1 << k
                        f = values[r, i, j, k]
                        if f > 0:
                            p |= 1 << k
                        elif f == 0:
                            z |= 1 << k
                pos[r, i, j], kn[r, i, j], zero[r, i, j] = p, q, z
    return pos, kn, zero


@njit(cache=True, inline="always")
def _row(bits, nbr, r, i, j, lo_col):
    """Bit row (i, j) of leaf r where 0 <= i, j < 8; else of the neighbour leaf across the face
    (``lo_col``: nbr column of the -axis neighbour, the +axis one is next), 0 when absent."""
    if i < 0 or j < 0 or i >= LEAF or j >= LEAF:
        up = i >= LEAF or j >= LEAF
        q = nbr[r, lo_col + 1] if up else nbr[r, lo_col]
        if q < 0:
            return 0
        return np.int64(bits[q, i & (LEAF - 1), j & (LEAF - 1)])
    return np.int64(bits[r, i, j])


@njit(cache=True, inline="always")
def _z_word(bits, nbr, r, i, j):
    """24-bit word of row (i, j): the -z neighbour leaf's row, this row, the +z leaf's row."""
    lo = nbr[r, 4]
    hi = nbr[r, 5]
    w = np.int64(bits[r, i, j]) << 8
    if lo >= 0:
        w |= np.int64(bits[lo, i, j])
    if hi >= 0:
        w |= np.int64(bits[hi, i, j]) << 16
    return w


@njit(cache=True, parallel=True)
def _sign_changes(pos, kn, zero, nbr):
    """S as bit rows: known voxels that are 0 or have a known face neighbour of the other sign."""
    n = pos.shape[0]
    out = np.zeros((n, LEAF, LEAF), np.uint8)
    for r in prange(n):
        for i in range(LEAF):
            for j in range(LEAF):
                p = np.int64(pos[r, i, j])
                q = np.int64(kn[r, i, j])
                pw, qw = _z_word(pos, nbr, r, i, j), _z_word(kn, nbr, r, i, j)
                ch = np.int64(zero[r, i, j])
                for s in (-1, 1):  # z: shifted words; y and x: neighbour rows
                    ch |= (((pw >> (8 + s)) ^ p) & (qw >> (8 + s))) & 0xFF
                    pn, qn = _row(pos, nbr, r, i, j + s, 2), _row(kn, nbr, r, i, j + s, 2)
                    ch |= (pn ^ p) & qn
                    pn, qn = _row(pos, nbr, r, i + s, j, 0), _row(kn, nbr, r, i + s, j, 0)
                    ch |= (pn ^ p) & qn
                out[r, i, j] = ch & q
    return out


@njit(cache=True, parallel=True)
def _dilate_axis(bits, nbr, axis, step):
    """Bit rows dilated by ``step`` (<= 7) voxels along one axis, across the face neighbours."""
    n = bits.shape[0]
    out = np.zeros_like(bits)
    for r in prange(n):
        for i in range(LEAF):
            for j in range(LEAF):
                acc = np.int64(0)
                if axis == 2:
                    w = _z_word(bits, nbr, r, i, j)
                    for s in range(-step, step + 1):
                        acc |= w >> (8 + s)
                elif axis == 1:
                    for s in range(-step, step + 1):
                        acc |= _row(bits, nbr, r, i, j + s, 2)
                else:
                    for s in range(-step, step + 1):
                        acc |= _row(bits, nbr, r, i + s, j, 0)
                out[r, i, j] = acc & 0xFF
    return out


@njit(cache=True, inline="always")
def _load_reach(values, reach, nbr, r, buf, ok):
    """Leaf r's values and reach flags with the face layer of each of its six neighbours into
    (10, 10, 10) buffers (local index + 1); edges, corners and absent leaves read as out of the
    reach. The stencil then reads buffers instead of finding the leaf of every neighbour."""
    ok[:] = False
    for i in range(LEAF):
        for j in range(LEAF):
            rb = reach[r, i, j]
            for k in range(LEAF):
                buf[i + 1, j + 1, k + 1] = values[r, i, j, k]
                ok[i + 1, j + 1, k + 1] = (rb >> k) & 1 == 1
    for f in range(6):
        q = nbr[r, f]
        if q < 0:
            continue
        axis, up = f // 2, f % 2 == 1
        src = 0 if up else LEAF - 1  # the neighbour's layer that touches leaf r
        dst = LEAF + 1 if up else 0
        for a in range(LEAF):
            for b in range(LEAF):
                if axis == 0:
                    buf[dst, a + 1, b + 1] = values[q, src, a, b]
                    ok[dst, a + 1, b + 1] = (reach[q, src, a] >> b) & 1 == 1
                elif axis == 1:
                    buf[a + 1, dst, b + 1] = values[q, a, src, b]
                    ok[a + 1, dst, b + 1] = (reach[q, a, src] >> b) & 1 == 1
                else:
                    buf[a + 1, b + 1, dst] = values[q, a, b, src]
                    ok[a + 1, b + 1, dst] = (reach[q, a, b] >> src) & 1 == 1


@njit(cache=True, parallel=True)
def _band_test(values, reach, sign, nbr, band, active) -> int:
    """active = S, or in the reach and |f| <= band * |grad f|; returns how many S voxels the
    distance test alone leaves out. Each leaf is read once into buffers with its face layers
    (:func:`_load_reach`): 31 -> 20 ms per call on the sphere at 512^3, the demo's 116 -> 59 ms,
    the same bits (checked on 21 models and sizes, band 2.5 and 3, a mesh among them)."""
    n = values.shape[0]
    by_sign = np.zeros(n, np.int64)
    b2 = band * band
    for r in prange(n):
        buf = np.empty((LEAF + 2, LEAF + 2, LEAF + 2))
        ok = np.empty((LEAF + 2, LEAF + 2, LEAF + 2), np.bool_)
        _load_reach(values, reach, nbr, r, buf, ok)
        m = 0
        for i in range(1, LEAF + 1):
            for j in range(1, LEAF + 1):
                sb = sign[r, i - 1, j - 1]
                for k in range(1, LEAF + 1):
                    if not ok[i, j, k]:
                        active[r, i - 1, j - 1, k - 1] = False
                        continue
                    f = buf[i, j, k]
                    dx = half_difference(buf[i - 1, j, k], ok[i - 1, j, k], f, buf[i + 1, j, k], ok[i + 1, j, k])
                    dy = half_difference(buf[i, j - 1, k], ok[i, j - 1, k], f, buf[i, j + 1, k], ok[i, j + 1, k])
                    dz = half_difference(buf[i, j, k - 1], ok[i, j, k - 1], f, buf[i, j, k + 1], ok[i, j, k + 1])
                    near = f * f <= b2 * (dx * dx + dy * dy + dz * dz)
                    s = (sb >> (k - 1)) & 1 == 1
                    active[r, i - 1, j - 1, k - 1] = s or near
                    if s and not near:
                        m += 1
        by_sign[r] = m
    return by_sign.sum()
