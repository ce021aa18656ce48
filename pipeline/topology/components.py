"""Reliable detection, labelling and separation of connected components on an adaptive octree.

Implements the components seed (Fryazinov & Pasko):

* Algorithm 1 / section 4.1 - adaptive spatial continuation: every cell gets its corner
  "control range" (eq. 3); a sign change on an edge proves a zero inside the cell, so it is
  subdivided without an affine test, and the cells across that edge are continued into;
  otherwise the revised affine range (section 3.2) rejects or keeps the cell. At the finest
  level (size <= tolerance) only the control range decides. The traversal is level-synchronous
  so that one vectorised affine call bounds every cell of a level.
* Section 4.2 - marking with propagation over face neighbours of the same, finer and coarser
  level (Figure 1 rules) on inside and border cells: count, label per cell, volume per cluster.
* Algorithm 2 / section 4.4 - the coarsest level that keeps the same count.
* Section 4.3 - separation fields: surface approach (signed distance to the cluster's octree
  surface, clamped) and set-theoretic approach (union of merged cells, eq. 4-5, Fig. 2), each
  with exact evaluation and a rigorous bound so they can be recombined like any FRep node.

Cells are addressed by (level, i, j, k) inside a root cube ``origin .. origin + size``; a cell of
level l has edge ``size / 2**l``. Corner values are cached on the finest lattice.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.spatial import cKDTree

from pipeline.field.rkernels import r0_and
from pipeline.model import ops
from pipeline.model.base import Node
from pipeline.model.tape import TapePool, compile_model, evaluate_with
from pipeline.model.tape_affine import affine_bounds
from pipeline.sparse.access import ALL27, OWN_ROWS, block_neighbours27, load_ghosts
from pipeline.sparse.grid import KEY_BITS, KEY_OFFSET, LEAF, LEAF_LOG2, key3, key_of, pack_keys
from pipeline.util.jit import njit

INSIDE, BORDER = 1, 2
_BITS = KEY_BITS  # packed keys of cell coordinates (< 2**21): pipeline.sparse.grid.key_of
_MASK = (1 << _BITS) - 1
BOUND_CHUNK = 100_000
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int64)
# the 12 cube edges as pairs of corner numbers (corner c = 4 i + 2 j + k)
_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                   if bin(a ^ b).count("1") == 1], np.int64)
_FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.int64)


def pack(ijk: np.ndarray) -> np.ndarray:
    """(N,3) non-negative integer coordinates -> int64 keys in x-major (scan) order."""
    a = np.asarray(ijk, np.int64)
    if len(a) < _PACK_SMALL:
        return key_of(a[:, 0], a[:, 1], a[:, 2])
    return pack_rows(a)


_PACK_SMALL = 1 << 14  # below this NumPy's three shifts are cheaper than a kernel call


def pack_rows(coords: np.ndarray, rows: np.ndarray | None = None, shift: np.ndarray | None = None) -> np.ndarray:
    """pack(coords[rows] >> shift[:, None]) in one compiled pass, both cores, without the
    (N,3) gathered and shifted temporaries (1 s of a 10M-cell octree's search tables, most of
    it first touches of the temporaries). ``rows`` None: every row; ``shift`` None: none."""
    coords = np.ascontiguousarray(coords, dtype=np.int64)
    every = rows is None
    rows = np.zeros(0, np.int64) if every else np.asarray(rows, np.int64)
    n = len(coords) if every else len(rows)
    shift = np.zeros(n, np.int64) if shift is None else np.asarray(shift, np.int64)
    return _pack_rows(coords, rows, every, shift)


@njit(cache=True, parallel=True)
def _pack_rows(coords, rows, every, shift):
    n = shift.shape[0]
    out = np.empty(n, np.int64)
    for i in numba.prange(n):
        r = np.int64(i) if every else rows[i]
        s = shift[i]
        out[i] = key3(coords[r, 0] >> s, coords[r, 1] >> s, coords[r, 2] >> s)
    return out


@njit(cache=True)
def _level_keys(level, coords, c, off):
    """Packed keys and rows of the cells of the levels finer than ``c``, level l at
    ``off[l]:off[l+1]`` in row order (one pass, one array each)."""
    n = off[-1]
    keys = np.empty(n, np.int64)
    rows = np.empty(n, np.int64)
    at = off[:-1].copy()
    for r in range(level.shape[0]):
        lv = level[r]
        if lv > c:
            keys[at[lv]] = key3(coords[r, 0], coords[r, 1], coords[r, 2])
            rows[at[lv]] = r
            at[lv] += 1
    return keys, rows


def unique_keys(keys: np.ndarray, inverse: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """np.unique(keys, return_inverse=True) by a stable (tim)sort: the octree's keys come in long
    sorted runs (cells are made in key order level by level, parents of sorted children are a
    few interleaved runs), which timsort merges in near-linear time where np.unique's quicksort
    does not (10M ancestor keys: 0.39 s instead of 1.3 s). ``inverse`` False: (unique, None)."""
    keys = np.asarray(keys, np.int64).reshape(-1)
    if len(keys) == 0:
        return keys.copy(), np.zeros(0, np.int64)
    if not inverse:
        s = np.sort(keys, kind="stable")
        first = np.empty(len(s), bool)
        first[0] = True
        np.not_equal(s[1:], s[:-1], out=first[1:])
        return s[first], None
    return _ranks(keys, np.argsort(keys, kind="stable"))


@njit(cache=True)
def _ranks(keys, order):
    """(unique keys, inverse) of ``keys`` given their stable sorting order, in one pass (the
    gathered, compared, summed and scattered temporaries of 10M keys took ~0.4 s at 1024^3)."""
    n = order.shape[0]
    uniq = np.empty(n, np.int64)
    inv = np.empty(n, np.int64)
    u = -1
    prev = 0
    for i in range(n):
        k = keys[order[i]]
        if i == 0 or k != prev:
            u += 1
            uniq[u] = k
            prev = k
        inv[order[i]] = u
    return uniq[:u + 1].copy(), inv


def unpack(keys: np.ndarray) -> np.ndarray:
    return np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1)


def depth_for(size: float, tolerance: float) -> int:
    """Smallest depth whose finest cell edge size / 2**depth is <= tolerance."""
    return max(0, int(np.ceil(np.log2(size / tolerance) - 1e-9)))


# --- the octree ---------------------------------------------------------------------------------


@dataclass
class Octree:
    """Leaf cells kept by the enumeration (inside and border), at mixed levels."""

    origin: np.ndarray  # (3,) world corner of the root cube
    size: float  # root edge
    depth: int  # finest level
    level: np.ndarray  # (N,) int64
    coords: np.ndarray  # (N,3) int64 index of the cell at its level
    kind: np.ndarray  # (N,) int8 INSIDE / BORDER
    pos_frac: np.ndarray  # (N,) fraction of positive corners (1 for inside cells)
    stats: dict = field(default_factory=dict)
    _flat: tuple | None = field(default=None, repr=False)
    _ancestors: list | None = field(default=None, repr=False)  # _ancestor_sets, made once per tree

    def __len__(self) -> int:
        return len(self.level)

    def cell_size(self, level: np.ndarray | int) -> np.ndarray:
        return self.size / np.power(2.0, level)

    @property
    def finest(self) -> float:
        return self.size / 2**self.depth

    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """World (lo, hi) of every cell."""
        c = self.cell_size(self.level)[:, None]
        lo = self.origin + self.coords * c
        return lo, lo + c

    def volumes(self) -> np.ndarray:
        return self.cell_size(self.level) ** 3

    def flat_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """The search tables of the compiled lookups: the sorted keys and rows of the levels
        finer than ``c = min(depth, COARSE_LEVEL)`` in one array each (level l at
        ``off[l]:off[l+1]``), the cells' levels, and a dense table over the level-c lattice
        holding the row of the kept cell of level <= c covering each of its cells (-1: none),
        so that a search stops after one lookup for every coarse level; and c."""
        if self._flat is None:
            c = min(self.depth, COARSE_LEVEL)
            level = np.ascontiguousarray(self.level, dtype=np.int64)
            coords = np.ascontiguousarray(self.coords, dtype=np.int64)
            counts = np.bincount(level, minlength=self.depth + 1)[:self.depth + 1]
            counts[:c + 1] = 0  # only the levels finer than c are searched by key
            off = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            keys, rows = _level_keys(level, coords, c, off)
            for lv in range(c + 1, self.depth + 1):
                a, b = off[lv], off[lv + 1]
                if b - a > 1 and not (keys[a + 1:b] > keys[a:b - 1]).all():
                    # the enumeration makes each level's inside and border cells in key order
                    # (two runs: timsort merges them in linear time); appended continuation
                    # cells and truncated ancestors are not
                    order = np.argsort(keys[a:b], kind="stable")
                    keys[a:b], rows[a:b] = keys[a:b][order], rows[a:b][order]
            coarse = np.full(1 << (3 * c), -1, np.int64)
            _paint_coarse(level, coords, c, coarse)
            self._flat = (keys, rows, off, level, coarse, c)
        return self._flat

    def find(self, level: int, coords: np.ndarray) -> np.ndarray:
        """Row of the kept cell (level, coords) or of its kept ancestor; -1 when none."""
        c = np.ascontiguousarray(np.asarray(coords, np.int64).reshape(-1, 3))
        if len(c) == 0 or len(self) == 0:
            return np.full(len(c), -1, np.int64)
        return _find_rows(c, int(level), *self.flat_tables())

    def locate(self, points: np.ndarray) -> np.ndarray:
        """Row of the kept cell containing each world point, -1 outside every kept cell."""
        p = (np.asarray(points, float).reshape(-1, 3) - self.origin) / self.finest
        ijk = np.floor(p).astype(np.int64)
        return self.find(self.depth, ijk)


@njit(cache=True, inline="always")
def _lower_bound(keys, lo, hi, q):
    """First index in the sorted keys[lo:hi] whose key is not below q (hi when none)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < q:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, inline="always")
def _walk_to(keys, lo, hi, q, j):
    """The forward pointer of a merge: the first index in the sorted keys[lo:hi] not below q,
    moved on from ``j`` (queries ascend), or searched for when ``j`` is -1."""
    if j < 0:
        j = _lower_bound(keys, lo, hi, q)
    while j < hi and keys[j] < q:
        j += 1
    return j


@njit(cache=True, inline="always")
def _bsearch(keys, lo, hi, q):
    """Index of ``q`` in the sorted ``keys[lo:hi]``, -1 when absent."""
    at = _lower_bound(keys, lo, hi, q)
    return at if at < hi and keys[at] == q else -1


COARSE_LEVEL = 7  # levels up to this one are looked up in a dense table (8^7 rows: 16 MiB)


@njit(cache=True, parallel=True)
def _paint_coarse(level, coords, c, coarse):
    """Every kept cell of level <= c writes its row over the level-c cells it covers (kept
    cells never overlap: the writes never meet)."""
    for r in numba.prange(level.shape[0]):
        if level[r] > c:
            continue
        sh = c - level[r]
        x0, y0, z0 = coords[r, 0] << sh, coords[r, 1] << sh, coords[r, 2] << sh
        for x in range(x0, x0 + (1 << sh)):
            for y in range(y0, y0 + (1 << sh)):
                for z in range(z0, z0 + (1 << sh)):
                    coarse[(x << (2 * c)) | (y << c) | z] = r


@njit(cache=True, inline="always")
def _find_one(x, y, z, level, keys, rows, off, levels, coarse, c):
    """Row of the kept cell (level, x, y, z) or of its nearest kept ancestor, -1 when none:
    a binary search per level finer than c, then one lookup in the dense level-c table."""
    lim = 1 << level
    if x < 0 or y < 0 or z < 0 or x >= lim or y >= lim or z >= lim:
        return -1
    for lv in range(level, c, -1):
        s, e = off[lv], off[lv + 1]
        if s == e:
            continue
        sh = level - lv
        q = key3(x >> sh, y >> sh, z >> sh)
        pos = _bsearch(keys, s, e, q)
        if pos >= 0:
            return rows[pos]
    if level >= c:
        sh = level - c
        return coarse[((x >> sh) << (2 * c)) | ((y >> sh) << c) | (z >> sh)]
    sh = c - level  # a coarse query: the entry of its first level-c cell, if not finer than it
    r = coarse[((x << sh) << (2 * c)) | ((y << sh) << c) | (z << sh)]
    return r if r >= 0 and levels[r] <= level else -1


@njit(cache=True, parallel=True)
def _find_rows(coords, level, keys, rows, off, levels, coarse, c):
    """Octree.find compiled, both cores."""
    out = np.empty(coords.shape[0], np.int64)
    for n in numba.prange(coords.shape[0]):
        out[n] = _find_one(coords[n, 0], coords[n, 1], coords[n, 2], level, keys, rows, off, levels, coarse, c)
    return out


@njit(cache=True, inline="always")
def _root(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]  # path halving
        a = parent[a]
    return a


UNION_CHUNK = 1 << 20  # cells whose neighbours are searched at once (both cores), 48 MB of them


def _face_union(level, coords, keys, rows, off, levels, coarse, c):
    """Section 4.2 marking as union-find: every kept cell is joined with the same-level or
    coarser kept cell across each of its six faces (Figure 1: green and yellow; the orange,
    finer neighbours are the same pairs seen from the finer cell). Returns the cluster id of
    every cell (0..count-1, in order of first appearance) and the count. The cells of the
    levels with search tables are taken in key order, a chunk at a time, so that their
    same-level neighbours are found by merging (:func:`_level_neighbours`); the cells of the
    coarse levels one by one."""
    parent = np.arange(level.shape[0])
    for lv in range(c + 1, off.shape[0] - 1):
        for i0 in range(off[lv], off[lv + 1], UNION_CHUNK):
            i1 = min(off[lv + 1], i0 + UNION_CHUNK)
            _union_rows(parent, rows[i0:i1], _level_neighbours(keys, rows, off, levels, coarse, c, lv, i0, i1))
    small = np.flatnonzero(level <= c)
    _union_rows(parent, small, _face_neighbours(level, coords, keys, rows, off, levels, coarse, c, small))
    return _cluster_ids(parent)


@njit(cache=True)
def _union_rows(parent, rows, nbr):
    """Join cell rows[i] with every neighbour nbr[i, f] >= 0 (union by smaller root)."""
    for i in range(rows.shape[0]):
        r = rows[i]
        for f in range(6):
            nb = nbr[i, f]
            if nb < 0:
                continue
            a, b = _root(parent, r), _root(parent, nb)
            if a != b:
                if a < b:
                    parent[b] = a
                else:
                    parent[a] = b


@njit(cache=True)
def _cluster_ids(parent):
    """(cluster id of every cell, count), ids in order of first appearance, written over
    ``parent`` in one forward pass without a new array (two fresh arrays of the cell count
    cost page faults, not work: ~1 s at 2048^3). Every union keeps the smaller root and path
    halving only moves a cell to its grandparent, so parent[r] <= r: when r is reached, its
    parent's slot already holds -(its cluster id + 1), and a root (parent[r] == r) opens the
    next cluster - the same numbering as looking up every cell's root."""
    n = parent.shape[0]
    count = 0
    for r in range(n):
        p = parent[r]
        if p == r:
            count += 1
            parent[r] = -count
        else:
            parent[r] = parent[p]
    for r in range(n):
        parent[r] = -parent[r] - 1
    return parent, count


@njit(cache=True, parallel=True)
def _face_neighbours(level, coords, keys, rows, off, levels, coarse, c, which):
    """(len(which), 6): the row of the same-level or coarser kept cell across each face of the
    cells ``which`` (+x, -x, +y, -y, +z, -z), -1 where none; both cores."""
    nbr = np.empty((which.shape[0], 6), np.int64)
    for i in numba.prange(which.shape[0]):
        r = which[i]
        lv = level[r]
        for f in range(6):
            d = 1 - 2 * (f & 1)
            x = coords[r, 0] + (d if f >> 1 == 0 else 0)
            y = coords[r, 1] + (d if f >> 1 == 1 else 0)
            z = coords[r, 2] + (d if f >> 1 == 2 else 0)
            nbr[i, f] = _find_one(x, y, z, lv, keys, rows, off, levels, coarse, c)
    return nbr


@njit(cache=True, parallel=True)
def _level_neighbours(keys, rows, off, levels, coarse, c, lv, i0, i1):
    """:func:`_face_neighbours` of the level-``lv`` cells keys[i0:i1] (a slice of that level's
    sorted table, c < lv): moving every key one cell along an axis keeps their order, so the
    same-level neighbours are found by a merge of the moved keys with the level's keys (a
    pointer that only moves forward) instead of a binary search each; a face without one
    searches the coarser levels (:func:`_find_one` from the parent). The same rows."""
    n = i1 - i0
    nbr = np.empty((n, 6), np.int64)
    s, e = off[lv], off[lv + 1]
    lim = 1 << lv
    parts = 64
    for part in numba.prange(parts):
        a, b = i0 + n * part // parts, i0 + n * (part + 1) // parts
        if a >= b:
            continue
        for f in range(6):
            axis, d = f >> 1, 1 - 2 * (f & 1)
            shift = 42 - 21 * axis
            j = -1
            for i in range(a, b):
                x, y, z = (keys[i] >> 42) & _MASK, (keys[i] >> 21) & _MASK, keys[i] & _MASK
                x, y, z = _moved(x, y, z, axis, d)
                if min(x, min(y, z)) < 0 or max(x, max(y, z)) >= lim:
                    nbr[i - i0, f] = -1
                    continue
                q = keys[i] + (d << shift)
                j = _walk_to(keys, s, e, q, j)
                if j < e and keys[j] == q:
                    nbr[i - i0, f] = rows[j]
                else:
                    nbr[i - i0, f] = _find_one(x >> 1, y >> 1, z >> 1, lv - 1, keys, rows, off, levels, coarse, c)
    return nbr


# --- Algorithm 1: adaptive spatial continuation --------------------------------------------------


SHORT_TAPE = 64  # clauses: shorter tapes are not shortened further in Algorithm 1's descent


@dataclass
class CellTapes:
    """The shortened tape of every cell of a level of Algorithm 1's descent: per-cell
    specialisation, as in voxelise's descent (pipeline.voxel.voxelise.enumerate_cells_tape).
    Before its children are bounded and their corners evaluated, a parent's tape is shortened
    to the parent's own closed box (pipeline.model.tape.TapePool.specialised: the min / max
    operands that the interval bounds prove irrelevant there are removed, so the values are the
    same to the bit everywhere in the box). For a model of many parts this is the difference
    between bounding every part and a few per cell; the revised affine form of the shortened
    tape is also tighter (an affine min / max of overlapping forms adds error, and a union of
    1,000 spheres folded into a tree of them had no cell rejected above the finest levels)."""

    pool: TapePool
    tape_of: np.ndarray  # (cells,) the tape of each cell of the level, into pool

    @classmethod
    def start(cls, model: Node, tape) -> CellTapes | None:
        """The root cell's tape; None when there is nothing to shorten (no tape, a model with
        a bound of its own, or a tape without min / max: an r0 or sardf model)."""
        if tape is None or _own_bound(model) or not tape.shortens:
            return None
        return cls(TapePool.single(tape), np.zeros(1, np.int64))

    def worth_shortening(self, which: np.ndarray, level: int, depth: int) -> bool:
        """Whether the tapes of the cells ``which`` of ``level`` are shortened for their children:
        not for the finest cells (they need only their corners: once more cost 1.8 s and saved
        0.4 s on 10^4 spheres at 128^3), nor once the tapes average fewer than SHORT_TAPE
        clauses (deciding costs about what it saves: a CSG of five parts, 89 -> 46 clauses, at
        1024 cells a side: 2.76-3.30 s with SHORT_TAPE = 64, 3.38-3.51 s shortening every level)."""
        lengths = self.pool.length[self.tape_of[which]]
        return level < depth - 1 and len(lengths) > 0 and lengths.mean() >= SHORT_TAPE

    def take(self, which: np.ndarray) -> CellTapes:
        """The tapes of the cells ``which`` (a mask, or rows: the children's parents)."""
        return CellTapes(self.pool, self.tape_of[which])

    def affine(self, lo: np.ndarray, hi: np.ndarray, which: np.ndarray | None = None):
        """Revised affine bounds of the cells (those of ``which``) over their boxes lo..hi."""
        return affine_bounds(self.pool, lo, hi, self.tape_of if which is None else self.tape_of[which])

    def specialised(self, which: np.ndarray, lo: np.ndarray, hi: np.ndarray, st: dict) -> CellTapes:
        """The tapes of the cells of ``which`` shortened to their boxes lo..hi: tape i of the
        result is that of the i-th such cell."""
        pool = self.pool.specialised(self.tape_of[which], lo, hi)
        if st["levels"] and len(pool.length):
            st["levels"][-1]["mean_tape"] = round(float(pool.length.mean()), 2)
        return CellTapes(pool, np.arange(len(lo), dtype=np.int64))

    def evaluate(self, points: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Values at points, point i by the tape of cell ``rows[i]`` (in that cell's box)."""
        return self.pool.evaluate(points, self.tape_of[rows])


class _CornerCache:
    """Field values at lattice points of the finest level, evaluated once (eq. 3 control range)."""

    def __init__(self, model: Node, origin: np.ndarray, step: float, t: float):
        self.model, self.origin, self.step, self.t = model, origin, step, t
        self.keys = np.zeros(0, np.int64)
        self.vals = np.zeros(0)
        self.evaluations = 0
        self.tape = compile_model(model, t)  # the compiled model; None: the node tree evaluates

    def evaluate(self, points: np.ndarray, cells: CellTapes | None = None, rows: np.ndarray | None = None
                 ) -> np.ndarray:
        """f at world points (N,3), NaN as -inf (outside): point i by the shortened tape of cell
        ``rows[i]`` of ``cells`` (the point lies in that cell's closed box; give the points of a
        cell together), else by the model's tape when it has one, else by the node tree."""
        if cells is not None:
            fv = cells.evaluate(points, rows)
        elif self.tape is not None:
            fv = evaluate_with(self.tape, points)
        else:
            fv = self.model.evaluate(points, self.t)
        self.evaluations += len(points)
        return np.where(np.isnan(fv), -np.inf, fv)

    def values(self, lattice: np.ndarray) -> np.ndarray:
        keys = pack(lattice.reshape(-1, 3))
        uniq, inv = unique_keys(keys)
        pos = np.minimum(np.searchsorted(self.keys, uniq), max(len(self.keys) - 1, 0))
        known = (self.keys[pos] == uniq) if len(self.keys) else np.zeros(len(uniq), bool)
        vals = np.empty(len(uniq))
        vals[known] = self.vals[pos[known]]
        new = uniq[~known]
        if len(new):
            vals[~known] = self.evaluate(self.origin + unpack(new) * self.step)
            allk = np.concatenate([self.keys, new])
            order = np.argsort(allk, kind="stable")
            self.keys, self.vals = allk[order], np.concatenate([self.vals, vals[~known]])[order]
        return vals[inv.reshape(-1)].reshape(lattice.shape[:-1])


def _corner_signs(cache: _CornerCache, coords: np.ndarray, scale: int) -> np.ndarray:
    """Corner signs of cells, one byte each: bit a set when f > 0 at corner a (a = 4i + 2j + k;
    NaN counts as outside). Algorithm 1 and the marking use the signs only (eq. 3: the control
    range decides by them), so a cell carries one byte instead of its 8 values."""
    lattice = (coords[:, None, :] + _CORNERS[None]) * scale
    return _sign_bits(cache.values(lattice) > 0)


def _sign_bits(positive: np.ndarray) -> np.ndarray:
    """(N, 8) booleans -> (N,) uint8, bit a = column a."""
    return np.packbits(positive.reshape(-1, 8), axis=1, bitorder="little")[:, 0]


_POPCOUNT = np.array([bin(b).count("1") for b in range(256)], np.int64)


_LAT27 = np.array([[i, j, k] for i in range(3) for j in range(3) for k in range(3)], np.int64)
_EVEN27 = np.all(_LAT27 % 2 == 0, axis=1)
_FROM_PARENT = np.array([int(np.dot(o // 2, (4, 2, 1))) for o in _LAT27[_EVEN27]])
_CHILD_IDX = np.array([[int(np.dot(o + c, (9, 3, 1))) for c in _CORNERS] for o in _CORNERS])  # (child, corner)
_NEW19 = _LAT27[~_EVEN27]  # the lattice points of the children that are not parent corners


def _earlier_sharers() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which earlier parents share each new lattice point. A point 2p + o of parent p lies on the
    parent's face or edge along every axis where o is even (0 or 2), so the parents p + d with
    d_a in {0, o_a - 1} there (d_a = 0 on odd axes) hold it too, as their point o - 2d. Returned:
    the face/edge offsets d that come before p in key order (first non-zero component -1),
    (9, 3); per new point, the indices of its sharers among them in key order, -1 padded,
    (19, 3); and the sharer's index of the point among its own 19, (19, 3)."""
    deltas = [d for d in _LAT27 - 1 if 0 < np.count_nonzero(d) <= 2 and d[np.flatnonzero(d)[0]] < 0]
    index19 = {tuple(o): j for j, o in enumerate(_NEW19)}
    who, where = np.full((19, 3), -1, np.int64), np.full((19, 3), -1, np.int64)
    for j, o in enumerate(_NEW19):
        even = [a for a in range(3) if o[a] % 2 == 0]
        cands = []
        for bits in range(1, 1 << len(even)):
            d = np.zeros(3, np.int64)
            for i, a in enumerate(even):
                if bits >> i & 1:
                    d[a] = o[a] - 1
            if d[np.flatnonzero(d)[0]] < 0:
                cands.append(tuple(d))
        for k, d in enumerate(sorted(cands)):  # key order of the sharers: x, then y, then z
            who[j, k] = next(i for i, e in enumerate(deltas) if tuple(e) == d)
            where[j, k] = index19[tuple(np.asarray(o) - 2 * np.asarray(d))]
    return np.array(deltas, np.int64), who, where


_SHARER_D, _SHARER_OF, _SHARER_IDX = _earlier_sharers()


CHILD_CHUNK = 1 << 16  # parents per evaluation of their new lattice points (19 points each)


def _child_corner_signs(cache: _CornerCache, parents: np.ndarray, psigns: np.ndarray, scale: int,
                        tapes: CellTapes | None = None) -> np.ndarray:
    """Corner signs of the 8 children of every parent, (P*8,) bytes in child order: the
    parent's corners are reused and the 19 new lattice points per parent are evaluated once
    each. A point shared by neighbouring parents (on a common face or edge: half of them at
    1024^3) belongs to the first of them in key order, which evaluates it; the others copy its
    sign. The parents come in key order (every level of the descent does); otherwise each
    parent evaluates all its 19 points. ``tapes``: the parents' tapes, cell i of it being parent
    i (its 19 points lie in its closed box, where its tape gives the model's values)."""
    parents = np.ascontiguousarray(parents, dtype=np.int64)
    keys = pack(parents)
    if len(keys) > 1 and not np.all(keys[1:] > keys[:-1]):
        return _child_corner_signs_each(cache, parents, psigns, scale, tapes)
    sharers = _sharer_rows(parents, keys, _SHARER_D)
    first = _first_sharers(sharers, _SHARER_OF)
    origin, step = np.asarray(cache.origin, np.float64), float(cache.step)
    pos = np.zeros((len(parents), 19), np.bool_)
    for s in range(0, len(parents), CHILD_CHUNK):
        e = min(s + CHILD_CHUNK, len(parents))
        rows, cols = np.nonzero(first[s:e] < 0)
        pts = _lattice_points_at(parents, rows + s, cols, _NEW19, int(scale), origin, step)
        pos[rows + s, cols] = cache.evaluate(pts, tapes, rows + s) > 0
    _copy_shared(pos, first, sharers, _SHARER_OF, _SHARER_IDX)
    return _assemble_children(psigns, pos, _FROM_PARENT, np.flatnonzero(_EVEN27), np.flatnonzero(~_EVEN27),
                              _CHILD_IDX)


def _child_corner_signs_each(cache: _CornerCache, parents: np.ndarray, psigns: np.ndarray,
                             scale: int, tapes: CellTapes | None = None) -> np.ndarray:
    """:func:`_child_corner_signs` with every parent evaluating its 19 points (any order)."""
    out = np.empty(len(parents) * 8, np.uint8)
    parents = np.ascontiguousarray(parents, dtype=np.int64)
    origin, step = np.asarray(cache.origin, np.float64), float(cache.step)
    for s in range(0, len(parents), CHILD_CHUNK):
        e = min(s + CHILD_CHUNK, len(parents))
        rows, cols = np.divmod(np.arange(19 * (e - s), dtype=np.int64), 19)
        pts = _lattice_points_at(parents, rows + s, cols, _NEW19, int(scale), origin, step)
        pos = (cache.evaluate(pts, tapes, rows + s) > 0).reshape(e - s, 19)
        out[8 * s:8 * e] = _assemble_children(psigns[s:e], pos, _FROM_PARENT, np.flatnonzero(_EVEN27),
                                              np.flatnonzero(~_EVEN27), _CHILD_IDX)
    return out


@njit(cache=True, parallel=True)
def _sharer_rows(parents, keys, deltas):
    """Row of the parent p + d for each offset d (-1: none), (P, D); parents in key order. The
    targets keys + key(d) increase with the row, so each range of rows walks them forward."""
    n, nd = parents.shape[0], deltas.shape[0]
    out = np.full((n, nd), -1, np.int64)
    parts = 64
    for part in numba.prange(parts):
        a, b = n * part // parts, n * (part + 1) // parts
        for t in range(nd):
            dk = (deltas[t, 0] << (2 * _BITS)) + (deltas[t, 1] << _BITS) + deltas[t, 2]
            j = -1
            for i in range(a, b):
                if (parents[i, 0] + deltas[t, 0] < 0 or parents[i, 1] + deltas[t, 1] < 0
                        or parents[i, 2] + deltas[t, 2] < 0):
                    continue
                j = _walk_to(keys, 0, n, keys[i] + dk, j)
                if j < n and keys[j] == keys[i] + dk:
                    out[i, t] = j
    return out


@njit(cache=True, parallel=True)
def _first_sharers(sharers, sharer_of):
    """(P, 19): per new point, which of its earlier sharers (k into ``sharer_of``) is the first
    present one in key order, -1 when none: the parent owns and evaluates the point."""
    n = sharers.shape[0]
    out = np.full((n, 19), -1, np.int8)
    for i in numba.prange(n):
        for j in range(19):
            for k in range(3):
                t = sharer_of[j, k]
                if t >= 0 and sharers[i, t] >= 0:
                    out[i, j] = k
                    break
    return out


@njit(cache=True, parallel=True)
def _copy_shared(pos, first, sharers, sharer_of, sharer_idx):
    """Signs of the points a parent does not own, from their owner (its first earlier sharer,
    which owns them: no parent holding the point comes before it)."""
    for i in numba.prange(pos.shape[0]):
        for j in range(19):
            k = first[i, j]
            if k >= 0:
                pos[i, j] = pos[sharers[i, sharer_of[j, k]], sharer_idx[j, k]]


@njit(cache=True, parallel=True)
def _lattice_points_at(parents, rows, cols, offsets, scale, origin, step):
    """World points of new lattice points (rows[i], cols[i]): parent row, point index. The
    integer lattice coordinate is formed first, so a point shared by parents gets the same
    float from each."""
    out = np.empty((rows.shape[0], 3))
    for i in numba.prange(rows.shape[0]):
        for a in range(3):
            out[i, a] = origin[a] + ((2 * parents[rows[i], a] + offsets[cols[i], a]) * scale) * step
    return out


@njit(cache=True, parallel=True)
def _assemble_children(psigns, new, from_parent, even, odd, child_idx):
    """(P*8,) child corner signs from the parents' corner signs and the new lattice points'."""
    n = psigns.shape[0]
    out = np.empty(n * 8, np.uint8)
    for p in numba.prange(n):
        lat = np.empty(27, np.bool_)
        for e in range(even.shape[0]):
            lat[even[e]] = (psigns[p] >> from_parent[e]) & 1
        for o in range(odd.shape[0]):
            lat[odd[o]] = new[p, o]
        for c in range(8):
            b = 0
            for k in range(8):
                if lat[child_idx[c, k]]:
                    b |= 1 << k
            out[p * 8 + c] = b
    return out


def _affine(model: Node, lo: np.ndarray, hi: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Revised affine bounds of the model over boxes (section 3.2): compiled over the model's tape
    when it has one (pipeline.model.tape_affine: the same rules, ~4x faster than the node-by-node
    NumPy forms), else ``model.bound`` a chunk at a time. A model whose class defines its own
    ``bound`` (not the formula's RAA of pipeline.model.base) keeps it: the tape knows only the
    formula."""
    tape = compile_model(model, t) if not _own_bound(model) else None
    if tape is not None:
        return affine_bounds(tape, lo, hi)
    flo, fhi = np.empty(len(lo)), np.empty(len(lo))
    for s in range(0, len(lo), BOUND_CHUNK):
        flo[s:s + BOUND_CHUNK], fhi[s:s + BOUND_CHUNK] = model.bound(lo[s:s + BOUND_CHUNK], hi[s:s + BOUND_CHUNK], t)
    return flo, fhi


def _own_bound(model) -> bool:
    """Whether the model's class overrides Node.bound (the bound of the root is what
    ``model.bound`` returns; children's ``bound`` methods are never called by it)."""
    owner = next((c for c in type(model).__mro__ if "bound" in c.__dict__), None)
    return owner is not None and owner.__module__ != "pipeline.model.base"


def _in_region(coords: np.ndarray, level: int, origin, size, rlo, rhi) -> np.ndarray:
    """Cells of ``level`` whose box meets the region [rlo, rhi] (closed)."""
    return _region_mask(np.ascontiguousarray(coords, dtype=np.int64), size / 2**level, np.asarray(origin, float),
                        np.broadcast_to(np.asarray(rlo, float), 3).copy(),
                        np.broadcast_to(np.asarray(rhi, float), 3).copy())


@njit(cache=True, parallel=True)
def _region_mask(coords, c, origin, rlo, rhi):
    out = np.empty(coords.shape[0], np.bool_)
    for r in numba.prange(coords.shape[0]):
        ok = True
        for a in range(3):
            lo = origin[a] + coords[r, a] * c
            ok = ok and lo <= rhi[a] and lo + c >= rlo[a]
        out[r] = ok
    return out


def _unique_rows(a: np.ndarray) -> np.ndarray:
    return unpack(unique_keys(pack(a), inverse=False)[0]) if len(a) else a.reshape(0, 3)


def _children(coords: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
    """The 8 children of each cell (of the cells where ``which`` is set), corner order."""
    coords = np.ascontiguousarray(coords, dtype=np.int64)
    rows = np.arange(len(coords)) if which is None else np.flatnonzero(which)
    return _child_coords(coords, rows, _CORNERS)


def _sorted_children(parents: np.ndarray, csigns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 8 children of key-sorted parents in key order, their parents' rows, and their
    corner signs (``csigns``:
    parent-major, corner order, as :func:`_child_corner_signs` makes them; empty: none). The
    descent starts from one cell and keeps subsets, so every level comes sorted and the finest
    cells need no sort (an argsort of the ~10M finest keys cost 0.5 s at 1024^3, twice)."""
    if len(parents) == 0:
        return np.zeros((0, 3), np.int64), csigns[:0], np.zeros(0, np.int64)
    x = parents[:, 0]
    starts = np.flatnonzero(np.concatenate([[True], x[1:] != x[:-1], [True]])).astype(np.int64)
    cells, signs, rows = _children_in_key_order(parents, csigns, starts)
    return cells, signs, rows


@njit(cache=True, parallel=True)
def _children_in_key_order(parents, csigns, starts):
    """Children of the sorted parents, x-run by x-run (run [i, j) fills rows 8i..8j): per child
    x, the parents' y-runs, per child y, each parent's two children in z. Returns the children,
    their corner signs and their parents' rows."""
    n = parents.shape[0]
    out = np.empty((8 * n, 3), np.int64)
    pout = np.empty(8 * n, np.int64)
    sout = np.empty(8 * n if csigns.shape[0] else 0, np.uint8)
    for r in numba.prange(starts.shape[0] - 1):
        i, j = starts[r], starts[r + 1]
        o = 8 * i
        for dx in range(2):
            u = i
            while u < j:
                v = u + 1
                while v < j and parents[v, 1] == parents[u, 1]:
                    v += 1
                for dy in range(2):
                    for p in range(u, v):
                        for dz in range(2):
                            out[o, 0] = 2 * parents[p, 0] + dx
                            out[o, 1] = 2 * parents[p, 1] + dy
                            out[o, 2] = 2 * parents[p, 2] + dz
                            pout[o] = p
                            if sout.shape[0]:
                                sout[o] = csigns[8 * p + 4 * dx + 2 * dy + dz]
                            o += 1
                u = v
    return out, sout, pout


@njit(cache=True, parallel=True)
def _child_coords(coords, rows, corners):
    out = np.empty((rows.shape[0] * 8, 3), np.int64)
    for i in numba.prange(rows.shape[0]):
        for c in range(8):
            for a in range(3):
                out[8 * i + c, a] = 2 * coords[rows[i], a] + corners[c, a]
    return out


@njit(cache=True, parallel=True)
def _missing_edge_neighbours(keys, signs, have, limit):
    """Algorithm 1, continuation: for every edge whose end signs differ, the cells sharing the
    edge that are not in ``have`` (sorted packed keys). ``keys``: the cells' packed keys,
    sorted, ``signs`` in the same order. Returns the missing cells' coordinates (repeats).
    The cells are taken in key order, a range per thread, with one pointer into ``have`` per
    neighbour offset: a cell moved by a fixed offset keeps the key order, so each pointer only
    moves forward (:func:`_gallop`). Two passes (count, then write at each range's offset)."""
    n = keys.shape[0]
    parts = min(n, 256)
    count = np.zeros(parts + 1, np.int64)
    dummy = np.empty((0, 3), np.int64)
    for p in numba.prange(parts):
        ptr = np.full(27, -1, np.int64)
        c = 0
        for i in range(n * p // parts, n * (p + 1) // parts):
            c += _edge_neighbours(keys, signs, have, limit, i, ptr, dummy, 0)
        count[p + 1] = c
    start = np.cumsum(count)
    out = np.empty((start[parts], 3), np.int64)
    for p in numba.prange(parts):
        if start[p + 1] > start[p]:
            ptr = np.full(27, -1, np.int64)
            at = start[p]
            for i in range(n * p // parts, n * (p + 1) // parts):
                at += _edge_neighbours(keys, signs, have, limit, i, ptr, out, at)
    return out


@njit(cache=True, inline="always")
def _moved(q0, q1, q2, axis, d):
    """(q0, q1, q2) moved by d along ``axis``."""
    return q0 + d * (axis == 0), q1 + d * (axis == 1), q2 + d * (axis == 2)


@njit(cache=True, inline="always")
def _gallop(keys, j, hi, q):
    """First index >= j in the sorted keys[:hi] whose key is not below q (hi when none): steps
    of 1, 2, 4, ... from j, then a binary search in the last step (cost log of the distance)."""
    step = 1
    lo = j
    while j < hi and keys[j] < q:
        lo = j + 1
        j += step
        step <<= 1
    return _lower_bound(keys, lo, min(j, hi), q)


@njit(cache=True, inline="always")
def _edge_neighbours(keys, signs, have, limit, i, ptr, out, at):
    """The missing edge neighbours of the cell keys[i], written to out[at:] when out has rows;
    their count. ``ptr``: per neighbour offset, the position in ``have`` of the previous query
    (-1: none yet); the queries of one offset must come in increasing key order."""
    found = 0
    x, y, z = (keys[i] >> 42) & _MASK, (keys[i] >> 21) & _MASK, keys[i] & _MASK
    for a in range(8):
        for axis in range(3):
            bit = 4 >> axis
            if a & bit:
                continue
            if ((signs[i] >> a) & 1) == ((signs[i] >> (a | bit)) & 1):
                continue
            u = (axis + 1) % 3
            v = (axis + 2) % 3
            su = 1 if a & (4 >> u) else -1
            sv = 1 if a & (4 >> v) else -1
            for du in range(2):
                for dv in range(2):
                    if du == 0 and dv == 0:
                        continue
                    q0, q1, q2 = _moved(x, y, z, u, su * du)
                    q0, q1, q2 = _moved(q0, q1, q2, v, sv * dv)
                    if min(q0, min(q1, q2)) < 0 or max(q0, max(q1, q2)) >= limit:
                        continue  # only the moved coordinates can leave the lattice
                    q = key3(q0, q1, q2)
                    o = (q0 - x + 1) * 9 + (q1 - y + 1) * 3 + (q2 - z + 1)
                    j = ptr[o]
                    j = _lower_bound(have, 0, have.shape[0], q) if j < 0 else _gallop(have, j, have.shape[0], q)
                    ptr[o] = j
                    if j < have.shape[0] and have[j] == q:
                        continue
                    if out.shape[0]:
                        out[at + found, 0], out[at + found, 1], out[at + found, 2] = q0, q1, q2
                    found += 1
    return found


def enumerate_octree(model: Node, origin, size: float, depth: int, t: float = 0.0,
                    region: tuple[np.ndarray, np.ndarray] | None = None,
                    continuation: bool = True) -> Octree:
    """Algorithm 1 (adaptive spatial continuation), one vectorised pass per level.

    ``continuation=False`` is the plain revised-affine subdivision of [17]: every cell gets the
    affine test and the finest ambiguous cells are kept as border. ``region`` (world lo, hi)
    clips the cells (the job's domain box).
    """
    return enumerate_in_brick(model, origin, size, depth, t, region, continuation)[0]


def enumerate_in_brick(model: Node, origin, size: float, depth: int, t: float = 0.0,
                       region: tuple[np.ndarray, np.ndarray] | None = None, continuation: bool = True,
                       brick: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[Octree, np.ndarray]:
    """Algorithm 1 restricted to a brick: ``brick`` = (lo, hi), a half-open box of finest-level
    cell indices. Only the cells that meet the brick are visited, so a coarse kept cell that
    reaches into the brick from outside is returned too (exactly as the whole-domain pass keeps
    it: a cell's fate depends on itself and its ancestors only). The continuation stays inside
    the brick; the finest cells it would enter outside are returned as ``escaped`` (unique
    coordinates) for the caller to finish (pipeline.topology.component_bricks). Without ``brick``: the
    whole domain, nothing escapes.
    """
    t0 = time.perf_counter()
    origin = np.asarray(origin, float)
    rlo, rhi = (np.full(3, -np.inf), np.full(3, np.inf)) if region is None else map(np.asarray, region)
    cache = _CornerCache(model, origin, size / 2**depth, t)
    tapes = CellTapes.start(model, cache.tape)  # None: the model is bounded and evaluated as a whole
    whole = TapePool.single(cache.tape) if tapes is None and cache.tape is not None else None
    st = {"affine_tests": 0, "affine_skipped": 0, "surface_tests": 0, "cells_visited": 0, "continuation_cells": 0,
          "levels": []}
    kept_l, kept_c, kept_k, kept_p = [], [], [], []
    cells = np.zeros((1, 3), np.int64)
    signs = _corner_signs(cache, cells, 1 << depth) if continuation else None
    escaped = np.zeros((0, 3), np.int64)
    finest = None  # (cells, corner signs) of the finest level
    for lv in range(depth + 1):
        ok = _in_region(cells, lv, origin, size, rlo, rhi)
        if brick is not None:
            ok &= _meets(cells, lv, depth, brick)
        if not ok.all():  # (at the finest level of the demo at 1024^3: 10M cells, all in the region)
            cells = cells[ok]
            signs = signs[ok] if continuation else None
            tapes = tapes.take(ok) if tapes is not None else None
        if len(cells) == 0:
            break
        st["cells_visited"] += len(cells)
        if lv == depth:
            finest, escaped = _finest(model, cells, signs, origin, size, depth, t, cache, st, continuation,
                                      (rlo, rhi), brick, tapes)
            st["levels"].append({"level": lv, "cells": int(len(cells))})
            break
        inside, split = _classify(model, cells, signs, lv, origin, size, t, st, tapes, whole)
        kept_l.append(np.full(int(inside.sum()), lv)), kept_c.append(cells[inside])
        kept_k.append(np.full(int(inside.sum()), INSIDE, np.int8)), kept_p.append(np.ones(int(inside.sum())))
        st["levels"].append({"level": lv, "cells": int(len(cells)), "inside": int(inside.sum()),
                             "subdivided": int(split.sum())})
        parents = np.ascontiguousarray(cells[split], dtype=np.int64)
        if tapes is not None and tapes.worth_shortening(split, lv, depth):  # each parent's tape to its own box
            c = size / 2**lv
            tapes = tapes.specialised(split, origin + parents * c, origin + (parents + 1) * c, st)
        elif tapes is not None:
            tapes = tapes.take(split)
        csigns = (_child_corner_signs(cache, parents, signs[split], 1 << (depth - lv - 1), tapes) if continuation
                  else np.zeros(0, np.uint8))
        cells, signs, rows = _sorted_children(parents, csigns)
        tapes = tapes.take(rows) if tapes is not None else None  # each child starts from its parent's
        signs = signs if continuation else None
    st["corner_evaluations"] = cache.evaluations
    coarse = (_cat(kept_l, (0,), np.int64), _cat(kept_c, (0, 3), np.int64), _cat(kept_k, (0,), np.int8),
              _cat(kept_p, (0,), np.float64))
    tree = Octree(origin, float(size), depth, *_with_finest(coarse, finest, depth), st)
    st["seconds"] = round(time.perf_counter() - t0, 4)
    st["inside_cells"] = int((tree.kind == INSIDE).sum())
    st["border_cells"] = int((tree.kind == BORDER).sum())
    return tree, escaped


def _meets(coords: np.ndarray, level: int, depth: int, brick) -> np.ndarray:
    """Cells of ``level`` whose finest-index span meets the half-open brick (lo, hi)."""
    lo = coords << (depth - level)
    return np.all((lo < brick[1]) & (lo + (1 << (depth - level)) > brick[0]), axis=1)


def _cat(parts: list, shape: tuple, dtype) -> np.ndarray:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(shape, dtype)


def _classify(model, cells, signs, lv, origin, size, t, st, tapes: CellTapes | None = None,
              whole: TapePool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Coarse level: (inside, subdivide) masks. A sign change on the corners proves a zero
    (control range, eq. 3) and skips the bounds; the other cells are bounded by :func:`_bounds`."""
    # mixed corner signs (bits neither all clear nor all set) prove a zero
    known = (signs != 0) & (signs != 255) if signs is not None else np.zeros(len(cells), bool)
    test = ~known
    c = size / 2**lv
    lo = origin + cells[test] * c
    flo, fhi = _bounds(model, lo, lo + c, t, st, np.flatnonzero(test), tapes, whole)
    st["affine_skipped"] += int(known.sum())
    inside = np.zeros(len(cells), bool)
    split = known.copy()
    inside[test] = flo > 0
    split[test] = ~(flo > 0) & ~(fhi < 0)
    return inside, split


def _bounds(model, lo, hi, t, st, rows, tapes: CellTapes | None, whole: TapePool | None):
    """Bounds of the cells ``rows`` (boxes lo..hi), each with its own shortened tape when
    ``tapes`` are given, else the model's (``whole``, or the node tree when None). A cell whose
    tape is a closed mesh's clause alone is decided by the mesh's surface, as voxelise's descent
    does (TapePool.surface_sides): no triangle near it, the sign of one point; one near, split.
    The others get RAA. (A knot's mesh at 512^3: the interval bounds of its min_max tree
    left a third of a million cells 6-7 voxels inside unproven down to the finest level.)"""
    pool, tape_of = (tapes.pool, tapes.tape_of[rows]) if tapes is not None else (whole, None)
    flo, fhi = np.full(len(lo), -np.inf), np.full(len(lo), np.inf)
    rest = np.ones(len(lo), bool)
    if pool is not None:
        kind, v = pool.surface_sides(lo, hi, tape_of)
        flo[kind == 1] = fhi[kind == 1] = v[kind == 1]
        rest = kind == 0
        st["surface_tests"] += int(len(lo) - rest.sum())
    if rest.any():
        sel = np.flatnonzero(rest)
        flo[sel], fhi[sel] = (_affine(model, lo[sel], hi[sel], t) if tapes is None
                              else tapes.affine(lo[sel], hi[sel], rows[sel]))
    st["affine_tests"] += int(rest.sum())
    return flo, fhi


def _finest(model, cells, signs, origin, size, depth, t, cache, st, continuation, region,
            brick=None, tapes: CellTapes | None = None) -> tuple[tuple, np.ndarray]:
    """Finest level: control range only (continuation) or affine only ([17]); also the
    continuation's cells outside ``brick`` (see enumerate_in_brick). Returns the finest cells
    and their corner signs (the kinds follow from them, :func:`_split_into`), and the escaped."""
    if not continuation:
        c = size / 2**depth
        lo = origin + cells * c
        flo, fhi = _affine(model, lo, lo + c, t) if tapes is None else tapes.affine(lo, lo + c)
        st["affine_tests"] += len(cells)
        # the affine kinds as corner signs: all set inside, one bit (fraction 1/2 below) at the border
        signs = np.where(flo > 0, 255, np.where(fhi < 0, 0, 15)).astype(np.uint8)
        return (cells, signs), np.zeros((0, 3), np.int64)
    cells, signs, escaped = _continuation(cells, signs, cache, depth, origin, size, region, st, brick)
    return (cells, signs), escaped


def _with_finest(coarse: tuple, finest: tuple | None, depth: int) -> tuple:
    """(level, coords, kind, pos_frac) of the octree: the coarse levels' kept cells, then the
    finest inside cells, then the finest border cells, written once into arrays of the final
    size (concatenating the ~10M finest cells of the demo at 1024^3 copied 0.4 GB: 1 s)."""
    if finest is None:
        return coarse
    cells, signs = finest
    return _split_into(*coarse, np.ascontiguousarray(cells, dtype=np.int64), signs, depth,
                       _chunk_count(len(signs) + len(coarse[0])))


def _chunk_count(n: int) -> int:
    """Ranges for the order-keeping parallel passes (a few per thread; one for small inputs)."""
    return max(1, min(8 * numba.get_num_threads(), n // 65536))


@njit(cache=True, parallel=True)
def _split_into(level, coords, kind, frac, cells, signs, depth, chunks):
    """The coarse cells (level, coords, kind, frac) followed by the finest ``cells`` by their
    corner ``signs`` (a bit per corner): inside (255) in order, then border (mixed) in order,
    outside (0) dropped. In parallel over ``chunks`` ranges of the finest cells: counted, then
    written at their ranges' offsets, so the order is that of a serial pass."""
    n0, m = level.shape[0], signs.shape[0]
    cnt = np.zeros((chunks + 1, 2), np.int64)
    for c in numba.prange(chunks):
        for r in range(c * m // chunks, (c + 1) * m // chunks):
            s = signs[r]
            if s == 255:
                cnt[c + 1, 0] += 1
            elif s != 0:
                cnt[c + 1, 1] += 1
    for c in range(chunks):
        cnt[c + 1] += cnt[c]
    n_in, n_bo = cnt[chunks, 0], cnt[chunks, 1]
    n = n0 + n_in + n_bo
    lv, co, ki, fr = np.empty(n, np.int64), np.empty((n, 3), np.int64), np.empty(n, np.int8), np.empty(n)
    for c in numba.prange(chunks):  # pages first touched by the threads that write them
        for r in range(c * n0 // chunks, (c + 1) * n0 // chunks):
            lv[r], ki[r], fr[r] = level[r], kind[r], frac[r]
            co[r, 0], co[r, 1], co[r, 2] = coords[r, 0], coords[r, 1], coords[r, 2]
        a, b = n0 + cnt[c, 0], n0 + n_in + cnt[c, 1]
        for r in range(c * m // chunks, (c + 1) * m // chunks):
            s = signs[r]
            if s == 255:
                lv[a], ki[a], fr[a] = depth, INSIDE, 1.0
                co[a, 0], co[a, 1], co[a, 2] = cells[r, 0], cells[r, 1], cells[r, 2]
                a += 1
            elif s != 0:
                lv[b], ki[b], fr[b] = depth, BORDER, _POPCOUNT[s] / 8.0
                co[b, 0], co[b, 1], co[b, 2] = cells[r, 0], cells[r, 1], cells[r, 2]
                b += 1
    return lv, co, ki, fr


def _finest_kinds(cells: np.ndarray, signs: np.ndarray) -> dict:
    """Finest cells by the control range (eq. 3): all corners positive -> inside, mixed -> border
    (:func:`_split_into`, one compiled pass: the masks and gathers over ~10M cells took 0.7-0.9 s
    at 1024^3)."""
    _, co, ki, fr = _with_finest(no_cells(), (cells, signs), 0)
    n_in = int(np.count_nonzero(ki == INSIDE))  # inside first, then border
    return {INSIDE: (co[:n_in], fr[:n_in]), BORDER: (co[n_in:], fr[n_in:])}


def no_cells() -> tuple:
    """(level, coords, kind, pos_frac) of no cells, typed as the octree keeps them."""
    return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int8), np.zeros(0)


def _continuation(cells, signs, cache, depth, origin, size, region, st, brick=None, have=None):
    """Algorithm 1: from every cell with a sign-changing edge, enumerate the not yet enumerated
    cells that share the edge, until no new cell appears (they hold a zero of f on that edge).
    ``have``: sorted packed keys already enumerated (default: ``cells``). With ``brick`` the
    walk stays inside it and the cells it would enter outside are returned as escaped."""
    keys = pack(cells)
    if len(keys) > 1 and not (keys[1:] > keys[:-1]).all():  # the enumeration's cells may come sorted
        order = np.argsort(keys, kind="stable")
        keys, signs_sorted = keys[order], signs[order]
    else:
        signs_sorted = signs
    frontier_k, frontier_s = keys, signs_sorted
    have = frontier_k if have is None else have
    added_c, added_s, escaped = [cells], [signs], [np.zeros((0, 3), np.int64)]
    while len(frontier_k):
        nb = _unique_rows(_missing_edge_neighbours(frontier_k, frontier_s, have, 1 << depth))
        new = nb[_in_region(nb, depth, origin, size, *region)]
        if brick is not None:
            inner = _meets(new, depth, depth, brick)
            escaped.append(new[~inner])
            new = new[inner]
        if len(new) == 0:
            break
        ns = _corner_signs(cache, new, 1)
        st["continuation_cells"] += len(new)
        frontier_k = pack(new)  # sorted: _unique_rows orders by key
        have = np.sort(np.concatenate([have, frontier_k]), kind="stable")  # timsort: merges the two sorted runs
        added_c.append(new)
        added_s.append(ns)
        frontier_s = ns
    if len(added_c) == 1:  # nothing new (the usual case): no copy of the whole list (0.5 s at 1024^3)
        return cells, signs, _unique_rows(np.concatenate(escaped))
    return np.concatenate(added_c), np.concatenate(added_s), _unique_rows(np.concatenate(escaped))


# --- section 4.2: marking with propagation ---------------------------------------------------------


@dataclass
class Components:
    """Result of section 4.2 on an octree: ``labels`` per cell (1..count, scan order)."""

    tree: Octree
    labels: np.ndarray
    count: int
    volumes: np.ndarray  # estimate: inside cells + border cells x fraction of positive corners
    volume_bounds: np.ndarray  # (count, 2): inside cells only, inside + border cells
    seconds: float = 0.0


def label_cells(tree: Octree) -> Components:
    """Count and label the clusters of inside and border cells (marking with propagation).

    Components are numbered in scan order of their lowest cell (x, then y, then z), the order
    in which ``scipy.ndimage.label`` numbers a dense grid.
    """
    t0 = time.perf_counter()
    raw, count = mark_union(tree)
    return summarise(tree, _scan_order(tree, raw, count), int(count), t0)


def mark_union(tree: Octree) -> tuple[np.ndarray, int]:
    """Raw cluster labels 1..count of the kept cells by face adjacency (section 4.2: the
    clusters the marking with propagation finds, here by a compiled union-find)."""
    if len(tree) == 0:
        return np.zeros(0, np.int64), 0
    ids, count = _face_union(np.ascontiguousarray(tree.level, dtype=np.int64),
                             np.ascontiguousarray(tree.coords, dtype=np.int64), *tree.flat_tables())
    return ids + 1, int(count)


def summarise(tree: Octree, labels: np.ndarray, count: int, t0: float) -> Components:
    """Components from scan-ordered labels: volume estimate and bounds per cluster (section 4.2)."""
    table = tree.cell_size(np.arange(tree.depth + 1)) ** 3  # per level: no power per cell (10M at 1024^3)
    est, lo, hi = _volume_sums(np.asarray(labels, np.int64), np.asarray(tree.level, np.int64), tree.kind,
                               np.asarray(tree.pos_frac, np.float64), table, int(count))
    return Components(tree, labels, int(count), est, np.stack([lo, hi], 1), time.perf_counter() - t0)


@njit(cache=True)
def _volume_sums(labels, level, kind, frac, table, count):
    """Per label 1..count: the sums of cell volume x fraction, of inside cells' volumes and of all
    volumes, in row order (what np.bincount with those weights adds)."""
    est, lo, hi = np.zeros(count + 1), np.zeros(count + 1), np.zeros(count + 1)
    for r in range(labels.shape[0]):
        v = table[level[r]]
        k = labels[r]
        est[k] += v * frac[r]
        lo[k] += v * (kind[r] == INSIDE)
        hi[k] += v
    return est[1:], lo[1:], hi[1:]


def _scan_order(tree: Octree, raw: np.ndarray, count: int) -> np.ndarray:
    if count == 0:
        return raw
    first = _first_keys(np.ascontiguousarray(tree.coords, dtype=np.int64),
                        np.ascontiguousarray(tree.level, dtype=np.int64), tree.depth, raw, count)
    order = np.argsort(first[1:], kind="stable")
    remap = np.zeros(count + 1, np.int64)
    remap[order + 1] = np.arange(1, count + 1)
    return remap[raw]


@njit(cache=True)
def _first_keys(coords, level, depth, raw, count):
    """Per label 1..count (index 0 unused): the smallest packed key of its cells' lowest
    finest-level corners (np.minimum.at of pack(coords << (depth - level)), 1 s at 10M cells)."""
    first = np.full(count + 1, np.iinfo(np.int64).max)
    for i in range(raw.shape[0]):
        s = depth - level[i]
        k = key3(coords[i, 0] << s, coords[i, 1] << s, coords[i, 2] << s)
        if k < first[raw[i]]:
            first[raw[i]] = k
    return first


def detect(model: Node, origin, size: float, depth: int, t: float = 0.0,
           region=None, continuation: bool = True) -> Components:
    """Algorithm 1 then section 4.2: the components of {f > 0} at tolerance size / 2**depth.
    They depend on the sign of f alone, so the model's sign proxy (Node.sign_proxy: an r0 mesh's
    min_max twin) is enumerated: the same cells where interval bounds decide (an R-function's
    interval has min/max's signs), with the pruned tape instead of every BSP node per cell."""
    return label_cells(enumerate_octree(model.sign_proxy(), origin, size, depth, t, region, continuation))


# --- Algorithm 2: coarsest level with the same count --------------------------------------------------


def truncate(tree: Octree, level: int) -> Octree:
    """The octree without the cells below ``level``: their ancestors at ``level`` become border
    cells (Algorithm 2, "remove the cells of the level")."""
    return _truncate(tree, level)[0]


def _truncate(tree: Octree, level: int) -> tuple[Octree, np.ndarray]:
    """:func:`truncate`, and the row of every cell of ``tree`` in the truncated tree (itself, or
    its ancestor at ``level``)."""
    lv = np.ascontiguousarray(tree.level, dtype=np.int64)
    drows = np.flatnonzero(lv > level)
    keys, inv = unique_keys(pack_rows(tree.coords, drows, lv[drows] - level))
    out = _truncated(lv, np.ascontiguousarray(tree.coords, dtype=np.int64), tree.kind,
                     np.ascontiguousarray(tree.pos_frac, dtype=np.float64), int(level), keys,
                     inv.reshape(-1) if inv is not None else np.zeros(0, np.int64), _chunk_count(len(lv)))
    return Octree(tree.origin, tree.size, level, *out[:4], dict(tree.stats)), out[4]


@njit(cache=True, parallel=True)
def _truncated(level, coords, kind, frac, lv, anc_keys, inv, chunks):
    """:func:`_truncate`'s arrays in one pass: the cells of level <= lv in order, then the
    ancestors (``anc_keys``, sorted; ``inv``: each deep cell's, in row order) as border cells;
    and the row of every old cell in the new arrays. In parallel over ``chunks`` ranges of the
    old cells (kept and deep cells counted per range first: the serial pass's order)."""
    n_old = level.shape[0]
    nk = n_old - inv.shape[0]
    n = nk + anc_keys.shape[0]
    kept = np.zeros(chunks + 1, np.int64)
    for c in numba.prange(chunks):
        for r in range(c * n_old // chunks, (c + 1) * n_old // chunks):
            kept[c + 1] += level[r] <= lv
    for c in range(chunks):
        kept[c + 1] += kept[c]
    ol, oc, ok, of = np.empty(n, np.int64), np.empty((n, 3), np.int64), np.empty(n, np.int8), np.empty(n)
    rows = np.empty(n_old, np.int64)
    for c in numba.prange(chunks):
        lo = c * n_old // chunks
        a = kept[c]
        d = lo - kept[c]  # deep cells before this range
        for r in range(lo, (c + 1) * n_old // chunks):
            if level[r] > lv:
                rows[r] = nk + inv[d]
                d += 1
                continue
            ol[a], ok[a], of[a] = level[r], kind[r], frac[r]
            oc[a, 0], oc[a, 1], oc[a, 2] = coords[r, 0], coords[r, 1], coords[r, 2]
            rows[r] = a
            a += 1
    for u in numba.prange(anc_keys.shape[0]):
        q = anc_keys[u]
        ol[nk + u], ok[nk + u], of[nk + u] = lv, BORDER, 0.5
        oc[nk + u, 0], oc[nk + u, 1], oc[nk + u, 2] = (q >> (2 * _BITS)) & _MASK, (q >> _BITS) & _MASK, q & _MASK
    return ol, oc, ok, of, rows


def coarsest_same_count(comp: Components) -> tuple[Components, dict[int, int]]:
    """Algorithm 2: remove the finest level while the count stays the same; returns the
    coarsest such labelling and the map original label -> its label there (a bijection,
    since coarsening only merges and the count is unchanged)."""
    best, best_rows = comp, None
    tree, rows = comp.tree, np.arange(len(comp.tree))
    for lv in range(comp.tree.depth - 1, -1, -1):
        # truncating the previous truncation gives the same tree as truncating the original (the
        # same kept cells in the same order, the same sorted new ancestors) from ~1/8 of the cells
        tree, step = _truncate(tree, lv)
        rows = step[rows]  # every original cell's own or ancestor's row in ``tree``
        cand = label_cells(tree)
        if cand.count != comp.count:
            break
        best, best_rows = cand, rows
    if best_rows is None:
        return best, {k: k for k in range(1, comp.count + 1)}
    return best, _label_map(comp.labels, best.labels[best_rows])  # once, for the level kept


def _label_map(a: np.ndarray, b: np.ndarray) -> dict[int, int]:
    """{a_i: b_i} of two label arrays over the same cells, a -> b being a function (one b per a):
    by scatter and check, not by a row-wise np.unique (a structured sort: 2 s of the demo's
    components at 512^3). Pairs that are not a function give np.unique's dict (the last pair per label)."""
    m = np.full(int(a.max(initial=0)) + 1, -1, np.int64)
    m[a] = b
    if not np.array_equal(m[a], b):
        return {int(x): int(y) for x, y in np.unique(np.stack([a, b], axis=1), axis=0)}
    present = np.zeros(len(m), bool)
    present[a] = True
    return {int(k): int(m[k]) for k in np.flatnonzero(present)}


# --- labels on arbitrary points (the VDB topology) ----------------------------------------------------


def point_labels(comp: Components, points: np.ndarray) -> np.ndarray:
    """Label of the kept cell holding each point; a point outside every kept cell takes the
    label of the nearest finest-level cell (by centre distance), i.e. of the piece whose
    surface, enclosed by border cells of tolerance size, is nearest. 0 when there is none."""
    points = np.asarray(points, float).reshape(-1, 3)
    if comp.count == 0:
        return np.zeros(len(points), np.int64)
    rows = comp.tree.locate(points)
    out = np.where(rows >= 0, comp.labels[np.maximum(rows, 0)], 0)
    miss = rows < 0
    if miss.any():
        tree = comp.tree
        fine = tree.level == tree.depth
        pick = np.nonzero(fine)[0] if fine.any() else np.arange(len(tree))
        lo, hi = tree.boxes()
        centres = 0.5 * (lo[pick] + hi[pick])
        _, nn = cKDTree(centres).query(points[miss])
        out[miss] = comp.labels[pick[nn]]
    return out


# inlined: called per cell and block by _paint_cells (0.50 -> 0.42 s at 1024^3)
@njit(cache=True, inline="always")
def _block_row(bkeys, x, y, z):
    """Row of the block with origin (x, y, z) in the sorted pack_keys ``bkeys``, -1 if absent."""
    q = key3(x + KEY_OFFSET, y + KEY_OFFSET, z + KEY_OFFSET)
    return _bsearch(bkeys, 0, bkeys.shape[0], q)


@njit(cache=True, parallel=True)
def _paint_cells(bkeys, level, coords, labels, depth, imin, lab, fine, mark_fine):
    """Write every kept cell's label into the voxels of the blocks it covers (a cell of level
    ``depth`` = one voxel: cell c holds voxel imin + c << (depth - level)); with ``mark_fine``,
    ``fine`` marks the voxels of level-``depth`` cells. A cell costs one block lookup per 8^3
    block it spans, not per voxel. Returns how many level-``depth`` cells fell on a block (the
    caller checks they all did)."""
    painted = 0
    for r in numba.prange(level.shape[0]):  # kept cells never overlap: the writes never meet
        sh = depth - level[r]
        span = 1 << sh
        x0, y0, z0 = imin[0] + (coords[r, 0] << sh), imin[1] + (coords[r, 1] << sh), imin[2] + (coords[r, 2] << sh)
        for bx in range((x0 >> 3) << 3, (((x0 + span - 1) >> 3) << 3) + 1, 8):
            for by in range((y0 >> 3) << 3, (((y0 + span - 1) >> 3) << 3) + 1, 8):
                for bz in range((z0 >> 3) << 3, (((z0 + span - 1) >> 3) << 3) + 1, 8):
                    row = _block_row(bkeys, bx, by, bz)
                    if row < 0:
                        continue
                    if span == 1:
                        painted += 1
                    i0, i1 = max(x0 - bx, 0), min(x0 + span - bx, 8)
                    j0, j1 = max(y0 - by, 0), min(y0 + span - by, 8)
                    k0, k1 = max(z0 - bz, 0), min(z0 + span - bz, 8)
                    for i in range(i0, i1):
                        for j in range(j0, j1):
                            for k in range(k0, k1):
                                lab[row, i, j, k] = labels[r]
                                if mark_fine:
                                    fine[row, i, j, k] = span == 1
    return painted


@njit(cache=True, parallel=True)
def _nearest_fine(active, lab, fine, nbr27, offsets):
    """Active voxels outside every kept cell take the label of the nearest finest-cell voxel
    (``offsets`` sorted by length, all shorter than a block: the first hit is the nearest).
    Returns the labels and a mask of the voxels with no hit within the offsets. Each block
    that has such voxels first copies the finest-cell labels of its 27 neighbours within
    reach into a window (access.load_ghosts; -1: not a finest cell, or no block), so that each
    offset costs one read instead of a block lookup."""
    out = lab  # in place: only non-finest voxels are written, and the windows read finest ones only
    miss = np.zeros(active.shape, np.bool_)
    r = _NEAR_R
    w = 8 + 2 * r
    for b in numba.prange(active.shape[0]):
        todo = False
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if active[b, i, j, k] and lab[b, i, j, k] == 0:
                        todo = True
        if not todo:
            continue
        win = np.empty((w, w, w), lab.dtype)
        wfine = np.empty((w, w, w), np.bool_)
        load_ghosts(lab, fine, OWN_ROWS, nbr27, ALL27, b, r, -1, win, wfine)
        for x in range(w):
            for y in range(w):
                for z in range(w):
                    if not wfine[x, y, z]:
                        win[x, y, z] = -1
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if not active[b, i, j, k] or lab[b, i, j, k] != 0:
                        continue
                    hit = False
                    for m in range(offsets.shape[0]):
                        v = win[i + offsets[m, 0] + r, j + offsets[m, 1] + r, k + offsets[m, 2] + r]
                        if v >= 0:
                            out[b, i, j, k] = v
                            hit = True
                            break
                    if not hit:
                        miss[b, i, j, k] = True
    return out, miss


_NEAR_R = 4
_NEAR_OFFSETS = np.array([[i, j, k] for i in range(-_NEAR_R, _NEAR_R + 1) for j in range(-_NEAR_R, _NEAR_R + 1)
                          for k in range(-_NEAR_R, _NEAR_R + 1) if 0 < i * i + j * j + k * k <= _NEAR_R**2],
                         np.int64)
_NEAR_OFFSETS = _NEAR_OFFSETS[np.argsort((_NEAR_OFFSETS**2).sum(axis=1), kind="stable")]
_NEAR_OFFSETS0 = np.concatenate([np.zeros((1, 3), np.int64), _NEAR_OFFSETS])  # and the voxel itself


def block_labels(comp: Components, blocks, index_min) -> np.ndarray:
    """(L,8,8,8) labels of every active voxel of a BlockGrid, equal to :func:`point_labels` at
    the voxel centres, for an octree whose finest cell is the voxel (cell c holds voxel
    ``index_min + c``): the kept cells paint their labels on the blocks they cover (one lookup
    per cell and block), and a voxel outside every kept cell takes the label of the nearest
    finest-cell voxel, searched in its 27 neighbouring blocks (within 4 voxels). The rare voxel
    farther from all of them, and every voxel within that reach of a finest cell on no block
    (which the search cannot see), goes to :func:`point_labels`."""

    n = len(blocks.origins)
    lab = np.zeros((n, LEAF, LEAF, LEAF), np.int32)  # labels < 2^31; int64 was 0.6 GB at 1024^3
    if comp.count == 0 or n == 0:
        return lab
    tree = comp.tree
    fine = np.zeros(lab.shape, bool)
    imin = np.asarray(index_min, np.int64)
    # np.asarray: no copy of arrays already of the kernel's types (the coordinates: 240 MB at 1024^3)
    painted = _paint_cells(blocks._keys, np.asarray(tree.level, np.int64), np.asarray(tree.coords, np.int64),
                           np.asarray(comp.labels, np.int32), int(tree.depth), imin, lab, fine, True)
    # the search reads the labels of finest cells at inactive voxels too (point_labels' nearest
    # finest cell is any): the inactive voxels are cleared after it
    lab, miss = _nearest_fine(blocks.active, lab, fine, block_neighbours27(blocks), _NEAR_OFFSETS)
    lab *= blocks.active
    finest = tree.level == tree.depth
    if painted != int(finest.sum()):
        # a finest cell on no block may be nearer than the one found: the voxels within reach of
        # such cells take the exact path (a knot's mesh at 512^3: 1.8M voxels went there, 1.3 s,
        # when one such cell sent every voxel outside the kept cells to point_labels)
        _near_off_block(tree, blocks, imin + tree.coords[finest], miss)
    if miss.any():
        b, i, j, k = np.nonzero(miss)
        ijk = blocks.origins[b] + np.stack([i, j, k], axis=1)
        lab[b, i, j, k] = point_labels(comp, ijk * blocks.voxel_size)
    return lab


def _near_off_block(tree: Octree, blocks, finest_voxels: np.ndarray, miss: np.ndarray) -> None:
    """Set ``miss`` at the active voxels outside every kept cell within _NEAR_R voxels of a
    finest cell (voxel ``finest_voxels``) that lies on no block."""
    off = finest_voxels[blocks.block_index((finest_voxels >> LEAF_LOG2) << LEAF_LOG2) < 0]
    near = (off[:, None, :] + _NEAR_OFFSETS0[None]).reshape(-1, 3)
    near = near[np.unique(pack_keys(near), return_index=True)[1]]  # not np.unique(axis=0): a row sort
    origin = (near >> LEAF_LOG2) << LEAF_LOG2
    row = blocks.block_index(origin)
    near, origin, row = near[row >= 0], origin[row >= 0], row[row >= 0]
    i, j, k = (near - origin).T
    act = blocks.active[row, i, j, k]
    near, row, i, j, k = near[act], row[act], i[act], j[act], k[act]
    outside = tree.locate(near * blocks.voxel_size) < 0  # voxels in a kept cell keep its label
    miss[row[outside], i[outside], j[outside], k[outside]] = True


# --- section 4.3: separation fields ------------------------------------------------------------------


@njit(cache=True, parallel=True)
def _box_query(qlo, qhi, blo, bhi, bkeys, border, binsize, reach, mode, init):
    """For query boxes (points when qlo == qhi): mode 0 -> min Euclidean distance from the query
    point to the boxes; mode 1 -> interval (lo, hi) of max_i min_axis g_i over the query box, with
    g = (x - lo)(hi - x)/(hi - lo) per axis (eq. 4, normalised). Only boxes whose bin is within
    ``reach`` of the query are visited; ``init`` is the clamp value."""
    nq = qlo.shape[0]
    out_lo = np.full(nq, init)
    out_hi = np.full(nq, init)
    for q in numba.prange(nq):  # queries are independent: both cores
        x0 = int(np.floor((qlo[q, 0] - reach) / binsize))
        x1 = int(np.floor((qhi[q, 0] + reach) / binsize))
        y0 = int(np.floor((qlo[q, 1] - reach) / binsize))
        y1 = int(np.floor((qhi[q, 1] + reach) / binsize))
        z0 = int(np.floor((qlo[q, 2] - reach) / binsize))
        z1 = int(np.floor((qhi[q, 2] + reach) / binsize))
        for bx in range(x0, x1 + 1):
            for by in range(y0, y1 + 1):
                for bz in range(z0, z1 + 1):
                    key = key3(bx + border, by + border, bz + border)
                    s = np.searchsorted(bkeys, key)
                    while s < bkeys.shape[0] and bkeys[s] == key:
                        if mode == 0:
                            d2 = 0.0
                            for a in range(3):
                                g = max(blo[s, a] - qlo[q, a], 0.0, qlo[q, a] - bhi[s, a])
                                d2 += g * g
                            d = np.sqrt(d2)
                            if d < out_lo[q]:
                                out_lo[q] = d
                        else:
                            mlo = np.inf
                            mhi = np.inf
                            for a in range(3):
                                w = bhi[s, a] - blo[s, a]
                                c = 0.5 * (bhi[s, a] + blo[s, a])
                                u0 = qlo[q, a] - c
                                u1 = qhi[q, a] - c
                                far = max(u0 * u0, u1 * u1)
                                near = 0.0 if u0 <= 0.0 <= u1 else min(u0 * u0, u1 * u1)
                                glo = (0.25 * w * w - far) / w
                                ghi = (0.25 * w * w - near) / w
                                mlo = min(mlo, glo)
                                mhi = min(mhi, ghi)
                            out_lo[q] = max(out_lo[q], mlo)
                            out_hi[q] = max(out_hi[q], mhi)
                        s += 1
    return out_lo, out_hi


@njit(cache=True)
def _gather(glo, ghi, c, rg, blo, bhi, bkeys, s0, s1, border, binsize, reach, init, rows, dist, n):
    """Append to rows/dist[n:] the boxes s0 <= s < s1 (one size class) that can be nearer than
    ``init`` to a point of the group (bounding box glo..ghi, centre c, radius rg), with their
    distances from c; the buffers double when full. Returns (rows, dist, n)."""
    x0 = int(np.floor((glo[0] - reach) / binsize))
    x1 = int(np.floor((ghi[0] + reach) / binsize))
    y0 = int(np.floor((glo[1] - reach) / binsize))
    y1 = int(np.floor((ghi[1] + reach) / binsize))
    z0 = int(np.floor((glo[2] - reach) / binsize))
    z1 = int(np.floor((ghi[2] + reach) / binsize))
    for bx in range(x0, x1 + 1):
        for by in range(y0, y1 + 1):
            # the bins z0..z1 of a column are consecutive in key order: one search per column
            s = s0 + np.searchsorted(bkeys[s0:s1], key3(bx + border, by + border, z0 + border))
            last = key3(bx + border, by + border, z1 + border)
            while s < s1 and bkeys[s] <= last:
                d2 = 0.0
                for a in range(3):
                    g = max(blo[s, a] - c[a], 0.0, c[a] - bhi[s, a])
                    d2 += g * g
                d = np.sqrt(d2)
                if d - rg < init:  # d(p, box) >= d(c, box) - |p - c|
                    if n == rows.shape[0]:
                        rows = np.concatenate((rows, np.empty(n, np.int64)))
                        dist = np.concatenate((dist, np.empty(n)))
                    rows[n] = s
                    dist[n] = d
                    n += 1
                s += 1
    return rows, dist, n


@njit(cache=True)
def _group_candidates(glo, ghi, c, rg, blo, bhi, bkeys, border, binsize, reach, init):
    """Boxes that can be nearer than ``init`` to a point of the group (bounding box glo..ghi,
    centre c, radius rg), sorted by their distance from c; returns (rows, distances)."""
    rows, dist, n = _gather(glo, ghi, c, rg, blo, bhi, bkeys, 0, bkeys.shape[0], border, binsize, reach, init,
                            np.empty(256, np.int64), np.empty(256), 0)
    order = np.argsort(dist[:n])
    return rows[:n][order], dist[:n][order]


@njit(cache=True, parallel=True)
def _grouped_distance(pts, order, gstart, blo, bhi, bkeys, border, binsize, reach, init):
    """Mode 0 of :func:`_box_query` (min distance from each point to the boxes, at most
    ``init``) for points grouped in space (``order[gstart[g]:gstart[g+1]]``): the candidate
    boxes are gathered once per group and sorted by distance from the group's centre, and a
    point stops at the first box whose lower bound d(c, box) - |p - c| reaches its best
    distance. Same boxes, same formula: the same values as the point-by-point query."""
    out = np.full(pts.shape[0], init)
    for g in numba.prange(gstart.shape[0] - 1):
        a, b = gstart[g], gstart[g + 1]
        glo = np.full(3, np.inf)
        ghi = np.full(3, -np.inf)
        for t in range(a, b):
            for ax in range(3):
                glo[ax] = min(glo[ax], pts[order[t], ax])
                ghi[ax] = max(ghi[ax], pts[order[t], ax])
        c = 0.5 * (glo + ghi)
        rg = 0.0
        for t in range(a, b):
            r2 = 0.0
            for ax in range(3):
                r2 += (pts[order[t], ax] - c[ax]) ** 2
            rg = max(rg, np.sqrt(r2))
        rows, dist = _group_candidates(glo, ghi, c, rg, blo, bhi, bkeys, border, binsize, reach, init)
        for t in range(a, b):
            q = order[t]
            r2 = 0.0
            for ax in range(3):
                r2 += (pts[q, ax] - c[ax]) ** 2
            dp = np.sqrt(r2)
            best = init
            for m in range(rows.shape[0]):
                if dist[m] - dp >= best:
                    break
                s = rows[m]
                d2 = 0.0
                for ax in range(3):
                    gg = max(blo[s, ax] - pts[q, ax], 0.0, pts[q, ax] - bhi[s, ax])
                    d2 += gg * gg
                d = np.sqrt(d2)
                if d < best:
                    best = d
            out[q] = best
    return out


_BIN_OFFSET = 1 << 19  # _BoxIndex's bin keys: (bin + offset) packed in 21 bits per axis


@njit(cache=True, parallel=True)
def _separated_piece(rows, origins, active, labels, piece, values, inside, h, blo, bhi, bkeys, cstart,
                     binsize, reach, clamp, background):
    """f AND g (r0) on the active voxels labelled ``piece`` of the blocks ``rows`` (section 4.3),
    where g is the surface ClusterField: the distance to the boundary faces clamped to ``clamp``
    (boxes of size class c are ``cstart[c]:cstart[c+1]`` of blo/bhi/bkeys), + where ``inside``,
    - elsewhere. Each block is one group of :func:`_grouped_distance` (the candidates of every
    size class gathered once, sorted by distance from the block's centre); the same boxes and
    formulas as ClusterField.value and rfunctions.r_and, so the same values. Returns the rows'
    values (background off the piece) and active masks."""
    n = rows.shape[0]
    out = np.empty((n, 8, 8, 8), np.float32)
    act = np.zeros((n, 8, 8, 8), np.bool_)
    bg = np.float32(background)
    nch = min(n, 256)
    for ch in numba.prange(nch):  # scratch per chunk of blocks: no allocation per block
        glo, ghi, c = np.empty(3), np.empty(3), np.empty(3)
        cand, cd = np.empty(256, np.int64), np.empty(256)
        clo, chi, cb = np.empty((256, 3)), np.empty((256, 3)), np.empty(256)
        nb = np.empty(BUCKETS + 1, np.int64)
        for r in range(ch * n // nch, (ch + 1) * n // nch):
            b = rows[r]
            r2 = 0.0
            for a in range(3):
                glo[a] = origins[b, a] * h
                ghi[a] = (origins[b, a] + 7) * h
                c[a] = 0.5 * (glo[a] + ghi[a])
                r2 += (0.5 * (ghi[a] - glo[a])) ** 2
            rg = np.sqrt(r2) * (1.0 + 1e-9)  # >= |p - c| for every voxel centre p of the block
            m_n = 0
            for cl in range(cstart.shape[0] - 1):
                cand, cd, m_n = _gather(glo, ghi, c, rg, blo, bhi, bkeys, cstart[cl], cstart[cl + 1], _BIN_OFFSET,
                                        binsize[cl], reach[cl], clamp, cand, cd, m_n)
            if m_n > clo.shape[0]:
                clo, chi, cb = np.empty((cand.shape[0], 3)), np.empty((cand.shape[0], 3)), np.empty(cand.shape[0])
            _bucket_order(cand, cd, m_n, clamp + rg, blo, bhi, nb, clo, chi, cb)
            _piece_voxels(b, r, origins, active, labels, piece, values, inside, h, c, clo, chi, cb[:m_n], clamp, bg,
                          out, act)
    return out, act


BUCKETS = 64  # distance classes of a block's candidate faces (_bucket_order)


@njit(cache=True)
def _bucket_order(cand, cd, n, reach, blo, bhi, nb, clo, chi, cb):
    """The candidates' boxes (rows cand[:n] of blo/bhi, at distances cd from the block's centre,
    all below ``reach``) into clo/chi ordered by distance class (a counting sort into BUCKETS
    classes of width reach / BUCKETS: cheaper than a sort of every block's list), with cb the
    lower edge of each one's class: a lower bound of its distance, non-decreasing in that order."""
    w = reach / BUCKETS
    nb[:] = 0
    for m in range(n):
        nb[min(int(cd[m] / w), BUCKETS - 1) + 1] += 1
    for q in range(BUCKETS):
        nb[q + 1] += nb[q]
    for m in range(n):
        q = min(int(cd[m] / w), BUCKETS - 1)
        t = nb[q]
        nb[q] += 1
        s = cand[m]
        for a in range(3):
            clo[t, a] = blo[s, a]
            chi[t, a] = bhi[s, a]
        cb[t] = q * w


@njit(cache=True, inline="always")
def _piece_voxels(b, r, origins, active, labels, piece, values, inside, h, c, clo, chi, cdist, clamp, bg, out, act):
    """Block b's voxels of :func:`_separated_piece` into row r: the nearest candidate face per
    voxel, visited in the order of their lower bounds ``cb`` of d(c, box) (c the block's
    centre) until cb - |p - c| reaches the best distance (the same minimum as visiting them all)."""
    for i in range(8):
        for j in range(8):
            for k in range(8):
                if not active[b, i, j, k] or labels[b, i, j, k] != piece:
                    out[r, i, j, k] = bg
                    continue
                p0, p1, p2 = (origins[b, 0] + i) * h, (origins[b, 1] + j) * h, (origins[b, 2] + k) * h
                dp = np.sqrt((p0 - c[0]) ** 2 + (p1 - c[1]) ** 2 + (p2 - c[2]) ** 2)
                best = clamp
                for m in range(cdist.shape[0]):
                    if cdist[m] - dp >= best:
                        break
                    g0 = max(clo[m, 0] - p0, 0.0, p0 - chi[m, 0])
                    g1 = max(clo[m, 1] - p1, 0.0, p1 - chi[m, 1])
                    g2 = max(clo[m, 2] - p2, 0.0, p2 - chi[m, 2])
                    d = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                    if d < best:
                        best = d
                g = best if inside[r, i, j, k] else -best
                out[r, i, j, k] = np.float32(r0_and(np.float64(values[b, i, j, k]), g))
                act[r, i, j, k] = True


def rows_by_label(active: np.ndarray, labels: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """For every label 1..count the rows of the blocks with an active voxel of that label, in
    order: rows[start[k]:start[k + 1]]. One pass over the voxels for all pieces (a scan per
    piece cost 17 % of separating a lattice's 242 pieces at 256^3)."""
    n_of, lab = _block_labels(active, labels)
    pair_block = np.repeat(np.arange(len(n_of), dtype=np.int64), n_of)
    order = np.argsort(lab, kind="stable")  # by label, blocks ascending within a label
    start = np.searchsorted(lab[order], np.arange(count + 2)).astype(np.int64)
    return start, pair_block[order]


@njit(cache=True, parallel=True)
def _block_labels(active, labels):
    """(number of distinct labels > 0 per block, those labels block after block)."""
    nb = active.shape[0]
    n_of = np.zeros(nb, np.int64)
    chunks = min(nb, 64)
    for c in numba.prange(chunks):
        found = np.empty(512, np.int64)
        for b in range(nb * c // chunks, nb * (c + 1) // chunks):
            n_of[b] = _distinct(active, labels, b, found)
    offs = np.zeros(nb + 1, np.int64)
    for b in range(nb):
        offs[b + 1] = offs[b] + n_of[b]
    out = np.empty(offs[nb], np.int64)
    for c in numba.prange(chunks):
        found = np.empty(512, np.int64)
        for b in range(nb * c // chunks, nb * (c + 1) // chunks):
            n = _distinct(active, labels, b, found)
            out[offs[b]:offs[b] + n] = found[:n]
    return n_of, out


@njit(cache=True)
def _distinct(active, labels, b, found):
    """The distinct labels > 0 of block b's active voxels into found[:n] (first-seen order); n."""
    n = 0
    last = 0
    for i in range(8):
        for j in range(8):
            for k in range(8):
                if not active[b, i, j, k]:
                    continue
                v = labels[b, i, j, k]
                if v <= 0 or v == last:  # runs of one label are the common case
                    continue
                last = v
                new = True
                for u in range(n):
                    if found[u] == v:
                        new = False
                        break
                if new:
                    found[n] = v
                    n += 1
    return n


class _BoxIndex:
    """Boxes of one size class binned by centre on a uniform grid (a sparse spatial hash)."""

    OFFSET = _BIN_OFFSET

    def __init__(self, lo: np.ndarray, hi: np.ndarray, clamp: float):
        half = 0.5 * (hi - lo).max(axis=1).max() if len(lo) else 0.0
        self.binsize = max(2.0 * half + clamp, 1e-12)
        self.reach = clamp + half
        centre = 0.5 * (lo + hi)
        b = np.floor(centre / self.binsize).astype(np.int64) + self.OFFSET
        keys = key_of(b[:, 0], b[:, 1], b[:, 2])
        order = np.argsort(keys, kind="stable")
        self.keys, self.lo, self.hi = keys[order], np.ascontiguousarray(lo[order]), np.ascontiguousarray(hi[order])

    def distance(self, points: np.ndarray, init: float) -> np.ndarray:
        """Min distance from each point to the boxes, at most ``init`` (mode 0 of query), with
        the points grouped in cubes of one bin (:func:`_grouped_distance`)."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0)
        g = np.floor(p / self.binsize).astype(np.int64)
        g -= g.min(axis=0)
        key = key_of(g[:, 0], g[:, 1], g[:, 2])
        order = np.argsort(key)  # the groups are what matters, not the order within one
        ks = key[order]
        gstart = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1], True]).astype(np.int64)
        return _grouped_distance(p, order, gstart, self.lo, self.hi, self.keys, self.OFFSET, self.binsize,
                                 self.reach, float(init))

    def query(self, qlo: np.ndarray, qhi: np.ndarray, mode: int, init: float) -> tuple[np.ndarray, np.ndarray]:
        return _box_query(np.ascontiguousarray(qlo, dtype=np.float64), np.ascontiguousarray(qhi, dtype=np.float64),
                          self.lo, self.hi, self.keys, self.OFFSET, self.binsize, self.reach, mode, float(init))


def _size_classes(lo: np.ndarray, hi: np.ndarray, clamp: float) -> list[_BoxIndex]:
    ext = (hi - lo).max(axis=1)
    cls = np.round(np.log2(np.maximum(ext, 1e-300))).astype(np.int64)
    return [_BoxIndex(lo[cls == c], hi[cls == c], clamp) for c in np.unique(cls)]


class ClusterField:
    """Scalar field of one cluster of the octree (section 4.3), positive inside the cluster.

    ``surface``: signed Euclidean distance to the cluster's boundary faces (the octree surface
    as a quad mesh, section 4.3.1), sign by point membership, clamped to [-clamp, clamp];
    1-Lipschitz. ``cells``: max over merged cells (eq. 5 with min/max R-functions) of
    min over axes of (x - xmin)(xmax - x)/(xmax - xmin) (eq. 4 normalised to first-order
    distance), clamped below at -clamp; cells are merged by the rules of Fig. 2 (section 4.3.2).
    """

    def __init__(self, comp: Components, label: int, method: str = "surface", clamp: float | None = None,
                 rows: np.ndarray | None = None):
        """``rows``: the rows of the cluster's cells in the tree, ascending, when known (a
        scan of every cell's label per piece: 1.9 s for the 89 pieces of the solid noise at 512^3)."""
        self.comp, self.label, self.method = comp, int(label), method
        self.rows = np.flatnonzero(comp.labels == self.label) if rows is None else rows
        tree = comp.tree
        # the distance is kept to 4 cells around the cluster, the cell union to 1 cell (its
        # evaluation visits every merged box within the clamp, so a short reach keeps it local)
        self.clamp = float(clamp if clamp is not None else (4.0 if method == "surface" else 1.0) * tree.finest)
        if method == "surface":
            lo, hi = boundary_faces(comp, label, self.rows)
        elif method == "cells":
            lo, hi = merged_cells(comp, label)
        else:
            raise ValueError(f"unknown separation method {method!r}")
        self.n_primitives = len(lo)
        self.index = _size_classes(lo, hi, self.clamp) if len(lo) else []

    def _inside(self, points: np.ndarray) -> np.ndarray:
        rows = self.comp.tree.locate(points)
        return (rows >= 0) & (self.comp.labels[np.maximum(rows, 0)] == self.label)

    def value(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float).reshape(-1, 3)
        if self.method == "surface":
            d = np.full(len(p), self.clamp)
            for ix in self.index:
                d = np.minimum(d, ix.distance(p, self.clamp))
            return np.where(self._inside(p), d, -d)
        g = np.full(len(p), -self.clamp)
        for ix in self.index:
            g = np.maximum(g, ix.query(p, p, 1, -self.clamp)[0])
        return g

    def piece_blocks(self, blocks, labels: np.ndarray, piece: int, depth: int,
                     index_min, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """f AND this field (r0, section 4.3) on the active voxels of ``blocks`` whose label is
        ``piece``, for an octree whose level-``depth`` cell is one voxel (cell c holds voxel
        ``index_min + c``): the rows of the blocks holding such voxels, their values (background
        elsewhere) and active masks. Equal to ``r_and(f, value(voxel centres), "r0")`` there,
        with the membership painted onto the blocks by the cluster's cells instead of an
        octree search per voxel, and the distance computed block by block in one compiled pass."""
        if self.method != "surface":
            raise ValueError("piece_blocks evaluates the surface field; use value() for the cell union")
        if rows is None:  # the rows of the blocks holding the piece (rows_by_label, for every piece at once)
            start, every = rows_by_label(blocks.active, labels, int(piece))
            rows = every[start[piece]:start[piece + 1]]
        tree = self.comp.tree
        mine = self.rows
        inside = np.zeros((len(rows), 8, 8, 8), np.int8)
        _paint_cells(blocks._keys[rows], np.asarray(tree.level[mine], np.int64),
                     np.asarray(tree.coords[mine], np.int64), np.ones(len(mine), np.int8), int(depth),
                     np.asarray(index_min, np.int64), inside,
                     np.zeros((1, 1, 1, 1), np.bool_), False)
        parts = [(ix.lo, ix.hi, ix.keys) for ix in self.index]
        cstart = np.cumsum([0] + [len(p[0]) for p in parts]).astype(np.int64)
        blo = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
        bhi = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 3))
        bkeys = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0, np.int64)
        vals, act = _separated_piece(rows, blocks.origins, blocks.active, labels, int(piece), blocks.values, inside,
                                     float(blocks.voxel_size), blo, bhi, bkeys, cstart,
                                     np.array([ix.binsize for ix in self.index], float),
                                     np.array([ix.reach for ix in self.index], float), self.clamp,
                                     float(blocks.background))
        return rows, vals, act

    def bound(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rigorous range over boxes: the distance is 1-Lipschitz (centre value +- half diagonal,
        as for iSDF [23]); the cell union gets exact interval ranges of its quadratics."""
        lo = np.asarray(lo, float).reshape(-1, 3)
        hi = np.asarray(hi, float).reshape(-1, 3)
        if self.method == "surface":
            c = 0.5 * (lo + hi)
            r = 0.5 * np.linalg.norm(hi - lo, axis=1)
            v = self.value(c)
            return np.maximum(v - r, -self.clamp), np.minimum(v + r, self.clamp)
        glo = np.full(len(lo), -self.clamp)
        ghi = np.full(len(lo), -self.clamp)
        for ix in self.index:
            a, b = ix.query(lo, hi, 1, -self.clamp)
            glo, ghi = np.maximum(glo, a), np.maximum(ghi, b)
        return glo, ghi


def boundary_faces(comp: Components, label: int, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Faces of the cluster's cells (``rows``, ascending, when known) not shared with a cell of
    the same cluster, as degenerate boxes (lo, hi). A face next to finer cells is split into
    quarters until each piece faces one kept cell, no cell, or a single finer level (section
    4.3.1, the octree surface). One compiled walk per cell and face, on both cores (in NumPy,
    level by level, the 89 pieces of the solid noise at 512^3 took 7.6 s); faces in the order of
    the cells, then the six directions, then the walk."""
    tree = comp.tree
    rows = np.flatnonzero(comp.labels == label) if rows is None else np.asarray(rows, np.int64)
    anc = _ancestor_sets(tree)
    aoff = np.concatenate([[0], np.cumsum([len(a) for a in anc])]).astype(np.int64)
    akeys = np.concatenate(anc).astype(np.int64) if len(anc) else np.zeros(0, np.int64)
    keys, trows, off, levels, coarse, c = tree.flat_tables()
    args = (rows, int(label), levels, np.ascontiguousarray(tree.coords, dtype=np.int64),
            np.ascontiguousarray(comp.labels, dtype=np.int64), keys, trows, off, coarse, c, akeys, aoff,
            np.asarray(tree.origin, np.float64), float(tree.size), tree.depth)
    count = np.zeros(len(rows) + 1, np.int64)
    dirs = np.zeros(len(rows), np.uint8)  # the directions with a face, per cell: the write walks only those
    _walk_faces(*args, count, dirs, np.zeros((0, 3)), np.zeros((0, 3)), False)
    start = np.concatenate([[0], np.cumsum(count[:-1])]).astype(np.int64)
    lo, hi = np.empty((int(start[-1]), 3)), np.empty((int(start[-1]), 3))
    _walk_faces(*args, start, dirs, lo, hi, True)
    return lo, hi


@njit(cache=True, parallel=True)
def _walk_faces(rows, label, levels, coords, labels, keys, trows, off, coarse, c, akeys, aoff, origin, size, depth,
                at, dirs, lo, hi, write):
    """Count (``write`` False: into at[t], and the directions that have faces into the bits of
    dirs[t]) or write (from at[t], those directions only) the boundary faces of cell rows[t]:
    per direction, a face against a cell of another label or none, or, against finer cells,
    the walk into the four children on that face (a stack per cell)."""
    for t in numba.prange(rows.shape[0]):
        r = rows[t]
        stack = np.empty((4 * (depth + 1) + 1, 4), np.int64)
        n = at[t] if write else 0
        for f in range(6):
            if write and not (dirs[t] >> f) & 1:
                continue
            first = n
            axis, sgn = f >> 1, 1 - 2 * (f & 1)
            stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = levels[r], coords[r, 0], coords[r, 1], coords[r, 2]
            top = 1
            while top > 0:
                top -= 1
                lv, x, y, z = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
                nx, ny, nz = x + sgn * (axis == 0), y + sgn * (axis == 1), z + sgn * (axis == 2)
                found = _find_one(nx, ny, nz, lv, keys, trows, off, levels, coarse, c)
                if found >= 0 and labels[found] == label:
                    continue
                if found < 0 and _has_descendant(akeys, aoff, lv, nx, ny, nz):
                    side = 1 if sgn > 0 else 0
                    for q in range(4):  # the children of (x, y, z) on this face: (u, v) on the other axes
                        u, v = q & 1, q >> 1
                        cx = 2 * x + (side if axis == 0 else u)
                        cy = 2 * y + (side if axis == 1 else (u if axis == 0 else v))
                        cz = 2 * z + (side if axis == 2 else v)
                        stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3] = lv + 1, cx, cy, cz
                        top += 1
                    continue
                if write:
                    e = size / (1 << lv)
                    for a in range(3):
                        lo[n, a] = origin[a] + (x, y, z)[a] * e
                        hi[n, a] = lo[n, a] + e
                    plane = hi[n, axis] if sgn > 0 else lo[n, axis]
                    lo[n, axis], hi[n, axis] = plane, plane
                n += 1
            if not write and n > first:
                dirs[t] |= 1 << f
        if not write:
            at[t] = n


@njit(cache=True, inline="always")
def _has_descendant(akeys, aoff, lv, x, y, z):
    """Whether the cell (lv, x, y, z) has kept descendants (:func:`_ancestor_sets`)."""
    if x < 0 or y < 0 or z < 0 or x >= (1 << lv) or y >= (1 << lv) or z >= (1 << lv):
        return False
    return _bsearch(akeys, aoff[lv], aoff[lv + 1], key3(x, y, z)) >= 0


def _ancestor_sets(tree: Octree) -> list[np.ndarray]:
    """Per level, sorted keys of the cells that have kept descendants (internal octree nodes).
    Made once per tree and kept on it: every separated piece asks for them (a lattice's 242
    pieces recomputed them 242 times, 15 minutes at 256^3)."""
    if tree._ancestors is not None:
        return tree._ancestors
    # bottom up: a cell has kept descendants when a child is kept or has them, so each level is
    # the parents of the next one's kept cells and ancestors (one sort of the finest level's
    # parents, then ever fewer keys; every level from all the cells took 9.3 s for the 89
    # pieces of the solid noise at 512^3)
    out = [np.zeros(0, np.int64)] * (tree.depth + 1)
    for lv in range(tree.depth - 1, -1, -1):
        kids = np.concatenate([tree.coords[tree.level == lv + 1], unpack(out[lv + 1])])
        out[lv] = unique_keys(pack(kids >> 1), inverse=False)[0]
    tree._ancestors = out
    return out


def _has_descendants(anc: list[np.ndarray], level: int, coords: np.ndarray) -> np.ndarray:
    keys = anc[level]
    ok = np.all((coords >= 0) & (coords < (1 << level)), axis=1)
    if len(keys) == 0:
        return np.zeros(len(coords), bool)
    q = pack(np.where(ok[:, None], coords, 0))
    pos = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
    return ok & (keys[pos] == q)


def _face_box(tree: Octree, level: int, coords: np.ndarray, d: np.ndarray, axis: int):
    c = tree.size / 2**level
    lo = tree.origin + coords * c
    hi = lo + c
    plane = np.where(d[axis] > 0, hi[:, axis], lo[:, axis])
    lo[:, axis] = plane
    hi[:, axis] = plane
    return lo, hi


def _face_children(coords: np.ndarray, d: np.ndarray, axis: int) -> np.ndarray:
    """The four children of each cell that touch its face in direction d."""
    kids = _children(coords).reshape(-1, 8, 3)
    side = 1 if d[axis] > 0 else 0
    sel = _CORNERS[:, axis] == side
    return kids[:, sel, :].reshape(-1, 3)


_DIRS26 = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                    if (i, j, k) != (0, 0, 0)], np.int64)


def merged_cells(comp: Components, label: int, margin: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of the cluster after the merging rules of Fig. 2, so that the union (eq. 5) has no
    internal zeros: a cell is extended across each face, edge or vertex into the neighbouring
    cells of its own cluster (Fig. 2a-b, same level: the shared face becomes interior; Fig. 2c-d,
    coarser neighbour: the cell reaches into it; finer neighbours reach into the cell themselves).
    The extension is ``margin`` x the finest cell and, per octant, only along axis sets whose
    face, edge and vertex neighbours all belong to the cluster; several boxes of one cell are
    combined by union (the last rule of section 4.3.2)."""
    tree = comp.tree
    rows = np.nonzero(comp.labels == label)[0]
    lo, hi = tree.boxes()
    lo, hi = lo[rows], hi[rows]
    ext = margin * tree.finest
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    member = np.zeros((len(rows), 27), bool)  # index (v + 1) . (9, 3, 1)
    member[:, 13] = True
    for v in _DIRS26:
        probe = centre + v * (half + 0.5 * ext)
        r = tree.locate(probe)
        member[:, int(np.dot(v + 1, (9, 3, 1)))] = (r >= 0) & (comp.labels[np.maximum(r, 0)] == label)
    boxes_lo, boxes_hi = [], []
    full = member.all(axis=1)
    boxes_lo.append(lo[full] - ext), boxes_hi.append(hi[full] + ext)
    part = ~full
    for octant in _CORNERS * 2 - 1:  # (+-1, +-1, +-1)
        for mask in _maximal_masks(member[part], octant):
            sel, axes = mask
            e = np.where(axes, ext, 0.0)
            blo = lo[part][sel] - np.where(octant < 0, e, 0.0)
            bhi = hi[part][sel] + np.where(octant > 0, e, 0.0)
            boxes_lo.append(blo), boxes_hi.append(bhi)
    blo, bhi = np.concatenate(boxes_lo), np.concatenate(boxes_hi)
    keys = np.round(np.concatenate([blo, bhi], axis=1) / (1e-6 * tree.finest)).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return blo[first], bhi[first]


def _maximal_masks(member: np.ndarray, octant: np.ndarray):
    """For one octant, yield (cells, axes) for every axis subset S that is closed (all the
    face/edge/vertex neighbours spanned by S in the octant are in the cluster) and maximal."""
    subsets = [np.array([(s >> a) & 1 for a in range(3)], bool) for s in range(8)]

    def closed(s: np.ndarray) -> np.ndarray:
        ok = np.ones(len(member), bool)
        for sub in subsets:
            if (sub & ~s).any() or not sub.any():
                continue
            v = np.where(sub, octant, 0)
            ok &= member[:, int(np.dot(v + 1, (9, 3, 1)))]
        return ok

    flags = [closed(s) for s in subsets]
    for i, s in enumerate(subsets):
        sup = [j for j, u in enumerate(subsets) if j != i and not (s & ~u).any()]
        maximal = flags[i].copy()
        for j in sup:
            maximal &= ~flags[j]
        if maximal.any():
            yield maximal, s


# --- bounding boxes for nodes without a domain ----------------------------------------------------


def enclosing_box(model: Node, t: float = 0.0, extent: float = 1.0e3, depth: int = 4,
                  rounds: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A box that encloses {f >= 0}, found by affine subdivision of [-extent, extent]^3 and
    shrinking to the bounding box of the cells not proven outside, repeated while the box
    shrinks by more than 5 %; ValueError when the set reaches the search cube (unbounded)."""
    lo, hi = np.full(3, -extent), np.full(3, extent)
    for r in range(rounds):
        size = float((hi - lo).max())
        cells = np.zeros((1, 3), np.int64)
        for lv in range(depth + 1):
            c = size / 2**lv
            blo = lo + cells * c
            flo, fhi = model.bound(blo, blo + c, t)
            cells = cells[fhi >= 0]
            if lv < depth:
                cells = _children(cells)
        if len(cells) == 0:
            raise ValueError("the model is empty (no point with f >= 0)")
        c = size / 2**depth
        nlo = lo + cells.min(axis=0) * c
        nhi = lo + (cells.max(axis=0) + 1) * c
        if r == 0 and (np.any(nlo <= lo) or np.any(nhi >= hi)):
            raise ValueError(f"the model reaches beyond +-{extent:g}; give 'bounds'")
        shrunk = (nhi - nlo).max() < 0.95 * (hi - lo).max()
        lo, hi = nlo, nhi
        if not shrunk:
            break
    return lo, hi


# --- section 5: collision / null-object detection --------------------------------------------------


@dataclass
class Collision:
    collide: bool
    count: int
    tolerance: float
    depth: int


def collide(model_a: Node, model_b: Node, box: tuple[np.ndarray, np.ndarray], tolerance: float,
            t_a: float = 0.0, t_b: float = 0.0) -> Collision:
    """Section 5: two solids collide iff their intersection (R-conjunction) has at least one
    component at the tolerance; inside ``box`` (world lo, hi)."""

    class _Both(Node):
        kind = "collision"

        def field(self, x, y, z, t):
            return ops.r_and(model_a.field(x, y, z, t_a), model_b.field(x, y, z, t_b), "r0")

    lo, hi = (np.asarray(b, float) for b in box)
    if np.any(hi <= lo):
        return Collision(False, 0, float(tolerance), 0)
    size = float((hi - lo).max())
    depth = depth_for(size, tolerance)
    found = detect(_Both(None), lo, size, depth, 0.0, (lo, hi))
    return Collision(found.count > 0, found.count, size / 2**depth, depth)
