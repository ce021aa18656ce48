"""Numba kernels of the block Fast Iterative Method (Jeong & Whitaker 2008) on 8^3 blocks.

Used by :mod:`pipeline.distance.eikonal`. The distance array ``d`` is (L,8,8,8) in voxel units; the
(L,27) table ``nbr27`` gives, for every block, the block at each offset (-1..1)^3 (row
``(dx+1)*9 + (dy+1)*3 + (dz+1)``, -1 where absent), so a kernel can read any voxel up to 8
steps outside its block without hashing.

Two upwind discretisations of |grad u| = 1 share one solver (:func:`upwind3`):

* first order (Godunov): per axis the smaller neighbour ``a1``, term ``(u - a1)^2``;
* second order (Sethian 1999, "Fast marching methods", section 4.3): where the next voxel
  on the same side ``a2`` is known and ``a2 <= a1``, the one-sided difference
  ``(3u - 4a1 + a2) / 2`` replaces ``u - a1``: term ``(9/4) (u - (4a1 - a2)/3)^2``. When
  that voxel lies across the surface its value enters with a minus sign: the stencil then
  differentiates the signed distance, which is smooth there (the unsigned one has a kink).

The second-order scheme is not monotone, so it is not run from scratch: the first-order
fixed point is computed first (monotone, converges from above) and the second-order FIM then
iterates from it, accepting changes in either direction, until no voxel moves by more than
``tol``. Its accuracy also needs an initial layer accurate to better than second order:
:func:`init_interface` projects every voxel next to a sign change onto the zero set of the
local quadratic fit of frep (Chopp 2001, "Some improvements of the fast marching method",
closest-point iteration).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from pipeline.field.stencils import central_gradient_at, half_difference
from pipeline.field.zeroset import zero_set_distance
from pipeline.sparse.access import ALL27, FACE_ROWS27, FACES27, OWN_ROWS, load_ghosts
from pipeline.util.jit import njit

FREE, FROZEN, EXCLUDED = 0, 1, 2
PARALLEL_BLOCKS = 4096  # blocks (2 M voxels) from which the FIM runs its waves on all threads
CHUNKS_PER_THREAD = 1  # one strided share of every wave per thread (measured best: 1, 2, 4, 8)
QUADRIC_RESIDUAL = 0.02  # voxels: largest miss of the quadratic model at its stencil corners
REL32 = 2.0**-22  # two float32 units relative: changes below them are rounding, not progress
# a wave relaxes only the listed blocks whose key (a lower bound of the values that put them on
# the list) is within WINDOW voxels of the smallest key (see fim). Measured on a sphere's interior
# at 512^3 (FIM seconds / voxel updates per voxel): no window 4.4 s / 9.5, 32: 3.5 / 7.9,
# 8: 2.4 / 4.9, 4: 2.2 / 4.4, 2: 2.0 / 4.2, 1: 2.3 / 4.2, 0.5: 2.6 / 4.1 (smaller waves)
WINDOW = 2.0


@njit(cache=True, inline="always")
def upwind3(b0, w0, b1, w1, b2, w2):
    """Solve sum_a w_a (u - b_a)^2 = 1 with the Godunov choice of upwind axes: ``w = c^2`` per
    axis (1 first order, 9/4 second order), ``b = inf`` for an axis without an upwind
    neighbour (at least one finite). Axes join in increasing ``b`` while the solution exceeds
    the next value (Jeong & Whitaker 2008, eq. 3; Sethian 1999, eq. 4.6): a three-element
    sorting network and the closed forms for one, two and three axes."""
    if b0 > b1:
        b0, b1, w0, w1 = b1, b0, w1, w0
    if b1 > b2:
        b1, b2, w1, w2 = b2, b1, w2, w1
    if b0 > b1:
        b0, b1, w0, w1 = b1, b0, w1, w0
    u = b0 + (1.0 if w0 == 1.0 else 2.0 / 3.0)  # 1 / c: no square root and division on the chain
    if u <= b1:
        return u
    a = w0 + w1
    s = w0 * b0 + w1 * b1
    disc = s * s - a * (w0 * b0 * b0 + w1 * b1 * b1 - 1.0)
    if disc < 0.0:
        return u
    u = (s + math.sqrt(disc)) * 0.5 if a == 2.0 else (s + math.sqrt(disc)) / a  # both first order: exact halving
    if u <= b2:
        return u
    a += w2
    s += w2 * b2
    disc = s * s - a * (w0 * b0 * b0 + w1 * b1 * b1 + w2 * b2 * b2 - 1.0)
    if disc < 0.0:
        return u
    return (s + math.sqrt(disc)) / a


@njit(cache=True, inline="always")
def _load_block(d, inside, nbr27, b, buf, sbuf):
    """Block b with two ghost layers on each face into the (12,12,12) buffers (distance and side
    of the surface; an absent neighbour reads as unknown, inf and outside; edges and corners are
    not read by the axis stencils)."""
    load_ghosts(d, inside, OWN_ROWS, nbr27, FACES27, b, 2, np.inf, buf, sbuf)


@njit(cache=True, inline="always")
def _axis_term(buf, sbuf, i, j, k, di, dj, dk, me, order2):
    """(b, c^2) of one axis at buffer voxel (i, j, k): the upwind side's value (b = inf when
    neither neighbour is known)."""
    lo1 = buf[i - di, j - dj, k - dk]
    hi1 = buf[i + di, j + dj, k + dk]
    if lo1 <= hi1:
        a1, a2, s2 = lo1, buf[i - 2 * di, j - 2 * dj, k - 2 * dk], sbuf[i - 2 * di, j - 2 * dj, k - 2 * dk]
    else:
        a1, a2, s2 = hi1, buf[i + 2 * di, j + 2 * dj, k + 2 * dk], sbuf[i + 2 * di, j + 2 * dj, k + 2 * dk]
    if a1 == np.inf:
        return np.inf, 1.0
    # across the surface the unsigned distance has a kink but the signed one is smooth: use
    # the signed value of a second neighbour on the other side. An unknown one (inf; a ghost of
    # an absent block reads as outside) stays unknown: negated it would pass the test below
    # and make the axis term inf, dropping the known neighbour a1
    if s2 != me and a2 != np.inf:
        a2 = -a2
    if order2 and a2 <= a1:
        return (4.0 * a1 - a2) / 3.0, 2.25
    return a1, 1.0


@njit(cache=True)
def relax_block(d, state, inside, nbr27, b, limit, tol, max_sweeps, order2, buf, sbuf, mask, limit_in=np.inf,
                dirty=63):
    """Gauss-Seidel sweeps (alternating the 8 orderings) until block b converges.

    First order accepts only decreases (monotone scheme from above); second order accepts
    any change larger than ``tol`` (plus two float32 units: values are rounded to float32,
    the distance array's type, as they are computed). A value above ``limit`` (outside voxels) or ``limit_in``
    (inside voxels) is never accepted. Returns (bitmask of faces whose ghost layers changed,
    voxel updates, sweeps).

    ``mask`` (12,12) int64 flags, per buffer row (i, j), the voxels whose stencil changed (bit
    k of the row for buffer voxel k): the first sweep evaluates every voxel, later ones only
    those with an axis neighbour within ``depth`` (the stencil's reach) updated since their
    last evaluation, and a row without a flagged free voxel is passed over at once. The update
    of a voxel is a function of those neighbours (its own value only enters the acceptance
    test, and it is unchanged since the voxel's last evaluation, or set by it), so a skipped
    voxel would not have changed: the same updates in the same order as evaluating every voxel
    in every sweep, at less cost.
    """
    _load_block(d, inside, nbr27, b, buf, sbuf)
    depth = 2 if order2 else 1  # ghost layers a neighbour reads
    faces = 0
    updates = 0
    sweeps = 0
    free = _free_rows(state[b])
    _start_mask(mask, dirty, depth)
    changed = False
    for it in range(max_sweeps):
        sweeps += 1
        changed = False
        for ii in range(8):
            i = ii if (it & 1) == 0 else 7 - ii
            for jj in range(8):
                j = jj if (it & 2) == 0 else 7 - jj
                fr = free[i, j]
                if (mask[i + 2, j + 2] & fr) == 0:  # nothing to evaluate in this row
                    mask[i + 2, j + 2] = 0
                    continue
                up = (it & 4) == 0
                kb = 1 if up else 10  # bit of the last voxel evaluated in this row (k + 2)
                while True:
                    # the next flagged free voxel in sweep order, the row read again: an update
                    # flags k +- 1, 2, and those ahead are evaluated in this sweep
                    row = mask[i + 2, j + 2]
                    if up:
                        ahead = row & fr & -(2 << kb)
                        if ahead == 0:
                            break
                        kb = trailing_zeros(ahead)
                    else:
                        ahead = row & fr & ((1 << kb) - 1)
                        if ahead == 0:
                            break
                        kb = 63 - leading_zeros(ahead)
                    bit = 1 << kb
                    mask[i + 2, j + 2] = row & ~bit
                    k = kb - 2
                    me = sbuf[i + 2, j + 2, k + 2]
                    bx, wx = _axis_term(buf, sbuf, i + 2, j + 2, k + 2, 1, 0, 0, me, order2)
                    by, wy = _axis_term(buf, sbuf, i + 2, j + 2, k + 2, 0, 1, 0, me, order2)
                    bz, wz = _axis_term(buf, sbuf, i + 2, j + 2, k + 2, 0, 0, 1, me, order2)
                    if bx == np.inf and by == np.inf and bz == np.inf:
                        continue
                    u = upwind3(bx, wx, by, wy, bz, wz)
                    if u > (limit_in if me else limit):
                        continue
                    # values are kept as float32 (what d stores): a block then stores exactly
                    # what it computed, and a change below two float32 units is no change, so
                    # rounding cannot move a voxel back and forth between visits
                    u = np.float64(np.float32(u))
                    thr = tol + REL32 * u
                    old = buf[i + 2, j + 2, k + 2]
                    if order2:
                        if not abs(u - old) > thr:
                            continue
                    elif not u < old - thr:
                        continue
                    buf[i + 2, j + 2, k + 2] = u
                    updates += 1
                    changed = True
                    along = 0
                    for r in range(1, depth + 1):  # the voxels whose stencil holds this one
                        mask[i + 2 - r, j + 2] |= bit
                        mask[i + 2 + r, j + 2] |= bit
                        mask[i + 2, j + 2 - r] |= bit
                        mask[i + 2, j + 2 + r] |= bit
                        along |= (bit >> r) | (bit << r)
                    mask[i + 2, j + 2] |= along
                    faces |= (i < depth) * 1 | (i >= 8 - depth) * 2 | (j < depth) * 4
                    faces |= (j >= 8 - depth) * 8 | (k < depth) * 16 | (k >= 8 - depth) * 32
        if not changed:
            break
    if changed:  # stopped by max_sweeps: not stable, the next visit starts from every voxel
        faces |= 64
    if updates:
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    d[b, i, j, k] = buf[i + 2, j + 2, k + 2]
    return faces, updates, sweeps


ROW_BITS = 0x3FC  # bits 2..9: the block's own voxels of a (12,)-row of the ghosted buffer


@njit(cache=True, inline="always")
def _free_rows(st):
    """(8,8) bit rows of the block's FREE voxels (bit k + 2 for voxel k), the layout of the mask."""
    free = np.empty((8, 8), np.int64)
    for i in range(8):
        for j in range(8):
            m = 0
            for k in range(8):
                if st[i, j, k] == FREE:
                    m |= 1 << (k + 2)
            free[i, j] = m
    return free


@njit(cache=True, inline="always")
def _start_mask(mask, dirty, depth):
    """The first sweep's flags: every voxel (dirty = 63), or the ``depth`` layers next to each
    face whose ghost layers changed since the block was last stable."""
    mask[:] = 0
    if dirty == 63:
        mask[2:10, 2:10] = ROW_BITS
        return
    for r in range(depth):
        if dirty & 1:
            mask[2 + r, 2:10] = ROW_BITS
        if dirty & 2:
            mask[9 - r, 2:10] = ROW_BITS
        if dirty & 4:
            mask[2:10, 2 + r] = ROW_BITS
        if dirty & 8:
            mask[2:10, 9 - r] = ROW_BITS
        if dirty & 16:
            mask[2:10, 2:10] |= 1 << (2 + r)
        if dirty & 32:
            mask[2:10, 2:10] |= 1 << (9 - r)


def fim(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2, max_visits, limit_in=np.inf,
        window=WINDOW):
    """Block Fast Iterative Method (Jeong & Whitaker 2008, Alg. 1 with blocks as list items),
    red-black over the block lattice, the list taken in order of distance.

    ``colour``: parity of each block's lattice coordinates (0/1). The active list is kept per
    colour and processed in waves, one colour at a time: blocks of one colour are never face
    neighbours, so a wave relaxes its blocks in parallel without races - each writes only its
    own voxels and reads ghost layers of the other colour, which no one writes during the
    wave. The result does not depend on the number of threads. A relaxed block puts the face
    neighbours whose ghost layers it changed on the list (of the other colour), with a key:
    the smallest value of the block that changed them. A wave takes only the blocks whose key
    is within ``window`` voxels of the smallest key on the list, the others wait (the
    bucketed order of the group marching method, Kim 2001, "An O(N) level set method for
    eikonal equations"): a block's values then come from upwind blocks that have settled,
    where taking the whole list relaxes blocks far ahead of the front again for every small
    change behind it. A sphere's interior at 512^3: 9.5 -> 4.2 updates per voxel, 4.4 -> 2.0 s
    (``window=inf`` is the plain FIM). The fixed point is the same; the second-order scheme is
    not monotone, so the values it stops at differ within its tolerance.
    ``max_visits`` bounds the work of the (non-monotone) second-order pass. ``limit`` /
    ``limit_in``: largest value accepted outside / inside (voxels). Small problems
    run the serial kernel (a parallel launch costs more than they take). Returns (block
    visits, voxel updates, sweeps, converged).
    """
    if len(d) < PARALLEL_BLOCKS:
        return _fim_serial(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2, max_visits,
                           float(limit_in), float(window))
    chunks = CHUNKS_PER_THREAD * numba.get_num_threads()
    return _fim_parallel(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2, max_visits,
                         chunks, float(limit_in), float(window))


@njit(cache=True)
def _seed_lists(colour, seeds, nb):
    """(per-colour lists, their lengths, on-list flags, dirty faces per block: all at first,
    keys: 0 for the seeds, inf for the blocks not on a list)."""
    lists = np.empty((2, nb), dtype=np.int64)
    counts = np.zeros(2, dtype=np.int64)
    on_list = np.zeros(nb, dtype=np.bool_)
    for s in seeds:
        if not on_list[s]:
            on_list[s] = True
            c = colour[s]
            lists[c, counts[c]] = s
            counts[c] += 1
    dirty = np.full(nb, 63, dtype=np.int64)
    key = np.full(nb, np.inf)
    for s in seeds:
        key[s] = 0.0
    return lists, counts, on_list, dirty, key


@njit(cache=True)
def _window_end(lists, counts, key, window):
    """The largest key a wave takes: the smallest key on either list plus ``window``."""
    kmin = np.inf
    for c in range(2):
        for t in range(counts[c]):
            kmin = min(kmin, key[lists[c, t]])
    return kmin + window


@njit(cache=True)
def _take_wave(lists, counts, on_list, c, key, end):
    """The blocks of colour c on the list with key <= ``end``, removed from it (the others stay
    on it, in their order)."""
    m = counts[c]
    work = np.empty(m, np.int64)
    nw = 0
    keep = 0
    for t in range(m):
        b = lists[c, t]
        if key[b] <= end:
            work[nw] = b
            nw += 1
            on_list[b] = False
            key[b] = np.inf
        else:
            lists[c, keep] = b
            keep += 1
    counts[c] = keep
    return work[:nw]


@njit(cache=True)
def _finish_wave(work, out, nbr27, colour, lists, counts, on_list, dirty, key, bmin):
    """After a wave (``out`` rows: faces, updates, sweeps per block): the face neighbours whose
    ghost layers changed go on their colour's list and have that face marked dirty (serial, in
    list order: the result is deterministic), their key lowered to the smallest value of the
    block that changed them (``bmin``: every value it passed on is at least that); the wave's
    blocks are clean again unless they stopped at max_sweeps. Returns (visits, updates, sweeps)
    of the wave."""
    for t in range(len(work)):
        dirty[work[t]] = 63 if out[t, 0] & 64 else 0
    for t in range(len(work)):
        b = work[t]
        for f in range(6):
            if out[t, 0] & (1 << f):
                n = nbr27[b, FACE_ROWS27[f]]
                if n >= 0:
                    dirty[n] |= 1 << (f ^ 1)  # n's ghost layer on the face it shares with b
                    key[n] = min(key[n], bmin[t])
                if n >= 0 and not on_list[n]:
                    on_list[n] = True
                    cn = colour[n]
                    lists[cn, counts[cn]] = n
                    counts[cn] += 1
    return len(work), out[:, 1].sum(), out[:, 2].sum()


@njit(cache=True)
def _relax_range(d, state, inside, nbr27, work, lo, hi, limit, tol, max_sweeps, order2, buf, sbuf, out, limit_in,
                 dirty, bmin, stride=1):
    mask = np.empty((12, 12), dtype=np.int64)
    for t in range(lo, hi, stride):
        out[t, 0], out[t, 1], out[t, 2] = relax_block(d, state, inside, nbr27, work[t], limit, tol, max_sweeps,
                                                      order2, buf, sbuf, mask, limit_in, dirty[work[t]])
        bmin[t] = d[work[t]].min()


@njit(cache=True)
def _fim_serial(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2, max_visits, limit_in, window):
    """:func:`fim` on one thread (the same waves, so the same result)."""
    lists, counts, on_list, dirty, key = _seed_lists(colour, seeds, d.shape[0])
    buf = np.empty((12, 12, 12))
    sbuf = np.zeros((12, 12, 12), dtype=np.bool_)
    visits, updates, sweeps = 0, 0, 0
    c = 0 if counts[0] >= counts[1] else 1
    while counts[0] + counts[1] > 0:
        if visits >= max_visits:
            return visits, updates, sweeps, False
        work = _take_wave(lists, counts, on_list, c, key, _window_end(lists, counts, key, window))
        if len(work) > 0:
            out = np.zeros((len(work), 3), dtype=np.int64)
            bmin = np.empty(len(work))
            _relax_range(d, state, inside, nbr27, work, 0, len(work), limit, tol, max_sweeps, order2, buf, sbuf, out,
                         limit_in, dirty, bmin)
            v, u, w = _finish_wave(work, out, nbr27, colour, lists, counts, on_list, dirty, key, bmin)
            visits, updates, sweeps = visits + v, updates + u, sweeps + w
        c = 1 - c
    return visits, updates, sweeps, True


@njit(cache=True, parallel=True)
def _fim_parallel(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2, max_visits, chunks,
                  limit_in, window):
    """:func:`fim` with each wave split into ``chunks`` strided shares relaxed in parallel (one
    buffer per share): share c takes the wave's blocks c, c + chunks, ... The list is in
    spatial order and the work of a block varies a lot along it (the front), so contiguous
    ranges left one thread idle at the end of a wave (FIM at 512^3: 2.49 s with two ranges per
    thread, 2.26 s strided)."""
    lists, counts, on_list, dirty, key = _seed_lists(colour, seeds, d.shape[0])
    bufs = np.empty((chunks, 12, 12, 12))
    sbufs = np.zeros((chunks, 12, 12, 12), dtype=np.bool_)
    visits, updates, sweeps = 0, 0, 0
    c = 0 if counts[0] >= counts[1] else 1
    while counts[0] + counts[1] > 0:
        if visits >= max_visits:
            return visits, updates, sweeps, False
        work = _take_wave(lists, counts, on_list, c, key, _window_end(lists, counts, key, window))
        m = len(work)
        if m > 0:
            out = np.zeros((m, 3), dtype=np.int64)
            bmin = np.empty(m)
            k = min(chunks, m)
            for ch in numba.prange(k):
                _relax_range(d, state, inside, nbr27, work, ch, m, limit, tol, max_sweeps,
                             order2, bufs[ch], sbufs[ch], out, limit_in, dirty, bmin, k)
            v, u, w = _finish_wave(work, out, nbr27, colour, lists, counts, on_list, dirty, key, bmin)
            visits, updates, sweeps = visits + v, updates + u, sweeps + w
        c = 1 - c
    return visits, updates, sweeps, True


def block_colour(origins: np.ndarray) -> np.ndarray:
    """Red-black colour (0/1) of blocks: parity of the sum of their lattice coordinates."""
    return (((origins >> 3).sum(axis=1)) & 1).astype(np.int8)


# --- initialisation next to the zero set -------------------------------------------------------
@njit(cache=True, inline="always")
def _load_frep(f, fact, brow, nbr27, b, fb, ab):
    """Block b's frep values and their known flags with one layer of every neighbour (faces,
    edges, corners) into (10,10,10) buffers (local index + 1; block n of the working set is
    row ``brow[n]`` of ``f``, unknown where -1)."""
    load_ghosts(f, fact, brow, nbr27, ALL27, b, 1, 0.0, fb, ab)


# _quadric_fit, _crossing_cap and closest_point_distance are inlined into _init_rows: called per
# voxel next to the surface, they cost 1.27-1.42 s as calls, 0.91 s inlined (demo 1024^3, the same bits)
@njit(cache=True, inline="always")
def _quadric_fit(fb, ab, i, j, k, g, hess, vals):
    """Gradient and Hessian of frep at buffer voxel (i, j, k) (:func:`_load_frep`) by central
    differences on its 3x3x3 neighbourhood (the local quadratic model). False when a neighbour
    is not in the band, or when the model misses the eight corner samples (which it does not
    use) by more than ``QUADRIC_RESIDUAL`` voxels: a kink of frep (a CSG edge, min/max) inside
    the stencil. ``vals``: a (3,3,3) work buffer."""
    for di in range(3):
        for dj in range(3):
            for dk in range(3):
                if not ab[i + di - 1, j + dj - 1, k + dk - 1]:
                    return False
                vals[di, dj, dk] = fb[i + di - 1, j + dj - 1, k + dk - 1]
    c = vals[1, 1, 1]
    g[0], g[1], g[2], _ = central_gradient_at(fb, ab, i, j, k)
    hess[0, 0] = vals[2, 1, 1] - 2.0 * c + vals[0, 1, 1]
    hess[1, 1] = vals[1, 2, 1] - 2.0 * c + vals[1, 0, 1]
    hess[2, 2] = vals[1, 1, 2] - 2.0 * c + vals[1, 1, 0]
    hess[0, 1] = hess[1, 0] = 0.25 * (vals[2, 2, 1] - vals[2, 0, 1] - vals[0, 2, 1] + vals[0, 0, 1])
    hess[0, 2] = hess[2, 0] = 0.25 * (vals[2, 1, 2] - vals[2, 1, 0] - vals[0, 1, 2] + vals[0, 1, 0])
    hess[1, 2] = hess[2, 1] = 0.25 * (vals[1, 2, 2] - vals[1, 2, 0] - vals[1, 0, 2] + vals[1, 0, 0])
    gn = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    if gn == 0.0:
        return False
    for si in (-1, 1):
        for sj in (-1, 1):
            for sk in (-1, 1):
                q = c + si * g[0] + sj * g[1] + sk * g[2]
                q += 0.5 * (hess[0, 0] + hess[1, 1] + hess[2, 2])
                q += si * sj * hess[0, 1] + si * sk * hess[0, 2] + sj * sk * hess[1, 2]
                if abs(q - vals[si + 1, sj + 1, sk + 1]) > QUADRIC_RESIDUAL * gn:
                    return False
    return True


@njit(cache=True, inline="always")
def closest_point_distance(f0, g, hess, iterations=12):
    """Distance from the origin to the zero set of q(x) = f0 + g.x + x.H.x / 2 (voxel units).

    Chopp (2001) closest-point iteration: a Newton step onto q = 0 along grad q plus the step
    that removes the tangential part of (origin - x). Returns inf when it does not converge.
    """
    x0 = x1 = x2 = 0.0  # scalars, not arrays: this runs for every voxel next to the surface
    step = np.inf
    for _ in range(iterations):
        g0 = g[0] + hess[0, 0] * x0 + hess[0, 1] * x1 + hess[0, 2] * x2
        g1 = g[1] + hess[1, 0] * x0 + hess[1, 1] * x1 + hess[1, 2] * x2
        g2_ = g[2] + hess[2, 0] * x0 + hess[2, 1] * x1 + hess[2, 2] * x2
        qx = f0
        qx += x0 * (g[0] + 0.5 * (hess[0, 0] * x0 + hess[0, 1] * x1 + hess[0, 2] * x2))
        qx += x1 * (g[1] + 0.5 * (hess[1, 0] * x0 + hess[1, 1] * x1 + hess[1, 2] * x2))
        qx += x2 * (g[2] + 0.5 * (hess[2, 0] * x0 + hess[2, 1] * x1 + hess[2, 2] * x2))
        gg = g0 * g0 + g1 * g1 + g2_ * g2_
        if gg == 0.0:
            return np.inf
        yg = -(x0 * g0 + x1 * g1 + x2 * g2_)
        d0 = -qx * g0 / gg + (-x0 - yg * g0 / gg)
        d1 = -qx * g1 / gg + (-x1 - yg * g1 / gg)
        d2 = -qx * g2_ / gg + (-x2 - yg * g2_ / gg)
        x0, x1, x2 = x0 + d0, x1 + d1, x2 + d2
        step = d0 * d0 + d1 * d1 + d2 * d2
        if step < 1e-24:
            break
    if step > 1e-12:
        return np.inf
    return math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


def init_interface(f, fact, d, state, nbr27, quadric, brow=None):
    """Freeze the voxels next to a sign change with sub-voxel distances (voxel units).

    A voxel with an axis neighbour of opposite sign gets, when ``quadric`` is set and its
    3x3x3 neighbourhood is in the band, the distance to the zero set of the local quadratic
    model (third-order accurate for a smooth surface: what the second-order scheme needs);
    otherwise ``|f| / |grad f|``, the distance to the tangent plane. Both are capped by the
    linearly interpolated axis crossings (points on the surface up to O(h^2)); the quadric
    distance is rejected when it exceeds that cap by more than a tenth of a voxel (a kink of
    the surface inside the stencil). Only blocks with band voxels are visited, in parallel
    (each writes only its own voxels and reads frep, which nobody writes: the result does not
    depend on the threads). ``brow``: row of ``f`` / ``fact`` of every block of ``d`` (-1: no
    frep values there); None when they are aligned with ``d``. Returns (frozen voxels, voxels
    initialised by the quadric).
    """
    if brow is None:
        brow = np.arange(len(d))
    has = np.zeros(len(d), bool)  # blocks with an active frep voxel
    has[brow >= 0] = fact.reshape(len(fact), -1).any(axis=1)[brow[brow >= 0]]
    rows = np.flatnonzero(has)
    counts = np.zeros((len(rows), 2), np.int64)
    if len(rows):
        _init_rows(f, fact, brow, d, state, nbr27, quadric, rows, counts)
    return int(counts[:, 0].sum()), int(counts[:, 1].sum())


@njit(cache=True, inline="always")
def _side_rows(fb, ab, pos, neg, zero):
    """Per buffer row (a, b) of the (10,10,10) frep buffers (:func:`_load_frep`), bit c for the
    known voxel (a, b, c) with f > 0 (``pos``), f <= 0 (``neg``: the other side, as the
    crossing tests count it) and f == 0 (``zero``)."""
    for a in range(10):
        for b in range(10):
            p = 0
            n = 0
            z = 0
            for c in range(10):
                if ab[a, b, c]:
                    v = fb[a, b, c]
                    if v > 0.0:
                        p |= 1 << c
                    else:
                        n |= 1 << c
                        if v == 0.0:
                            z |= 1 << c
            pos[a, b] = p
            neg[a, b] = n
            zero[a, b] = z


@njit(cache=True, inline="always")
def _near_crossing(pos, neg, zero, i, j):
    """Bits (buffer index k + 1, 1..8) of the block's voxels in buffer row (i, j) whose 3x3x3
    neighbourhood holds a known voxel across the surface, or which are zero themselves: the only
    voxels that can be frozen (an axis crossing, or a diagonal one next to a kink). A row
    operation per voxel instead of the 26 neighbour tests of each (most band voxels have none)."""
    dp = 0
    dn = 0
    for a in range(i - 1, i + 2):
        for b in range(j - 1, j + 2):
            dp |= pos[a, b]
            dn |= neg[a, b]
    dp |= (dp << 1) | (dp >> 1)
    dn |= (dn << 1) | (dn >> 1)
    return ((pos[i, j] & dn) | (neg[i, j] & dp) | zero[i, j]) & 0x1FE


@njit(cache=True, parallel=True)
def _init_rows(f, fact, brow, d, state, nbr27, quadric, rows, counts):
    """:func:`init_interface` over the blocks ``rows``; (frozen, quadric) per row into ``counts``.
    Only the voxels with a known voxel across the surface in their 3x3x3 neighbourhood (from
    bit rows of the signs) are looked at: the others cannot be frozen."""
    for t in numba.prange(len(rows)):
        b = rows[t]
        r = brow[b]
        fbuf = np.empty((10, 10, 10))  # the block with a layer of its neighbours: no lookups per voxel
        abuf = np.empty((10, 10, 10), np.bool_)
        _load_frep(f, fact, brow, nbr27, b, fbuf, abuf)
        pos = np.empty((10, 10), np.int64)
        neg = np.empty((10, 10), np.int64)
        zero = np.empty((10, 10), np.int64)
        _side_rows(fbuf, abuf, pos, neg, zero)
        g = np.empty(3)
        hess = np.empty((3, 3))
        vals = np.empty((3, 3, 3))
        count = 0
        n_quad = 0
        for i in range(8):
            for j in range(8):
                near = _near_crossing(pos, neg, zero, i + 1, j + 1)
                while near:
                    kb = trailing_zeros(near)
                    near &= near - 1
                    k = kb - 1
                    if not fact[r, i, j, k] or state[b, i, j, k] == EXCLUDED:
                        continue
                    fv = f[r, i, j, k]
                    if fv == 0.0:
                        d[b, i, j, k] = 0.0
                        state[b, i, j, k] = FROZEN
                        count += 1
                        continue
                    cap, g2 = _crossing_cap(fbuf, abuf, i + 1, j + 1, k + 1, fv)
                    kink = cap == np.inf  # no axis neighbour across the surface
                    if kink:
                        if not quadric:
                            continue  # not next to the surface along an axis
                        if _quadric_fit(fbuf, abuf, i + 1, j + 1, k + 1, g, hess, vals):
                            continue  # smooth there: the FIM solves it from its neighbours
                        # next to a kink (a convex corner or edge, where the surface passes
                        # diagonally): the FIM's fan from the axis-crossing layer is up to a
                        # voxel too far, so it is frozen like the others, capped by the zero
                        # set of the piecewise-linear interpolant in its cells
                        cap = zero_set_distance(fbuf, abuf, i + 1, j + 1, k + 1)
                        if cap == np.inf:
                            continue
                    dist = np.inf
                    if quadric and not kink and _quadric_fit(fbuf, abuf, i + 1, j + 1, k + 1, g, hess, vals):
                        dist = closest_point_distance(fv, g, hess)
                        if dist > cap + 0.1:
                            dist = np.inf
                        else:
                            n_quad += 1
                    if dist == np.inf:
                        dist = min(abs(fv) / math.sqrt(g2) if g2 > 0.0 else cap, cap)
                    d[b, i, j, k] = dist
                    state[b, i, j, k] = FROZEN
                    count += 1
        counts[t, 0] = count
        counts[t, 1] = n_quad


@njit(cache=True, inline="always")
def _crossing_cap(fb, ab, i, j, k, fv):
    """(nearest linearly interpolated axis crossing, |grad f|^2 by central differences) at
    buffer voxel (i, j, k) (:func:`_load_frep`)."""
    cap = np.inf
    g2 = 0.0
    for axis in range(3):
        di, dj, dk = int(axis == 0), int(axis == 1), int(axis == 2)
        fl, al = fb[i - di, j - dj, k - dk], ab[i - di, j - dj, k - dk]
        fh, ah = fb[i + di, j + dj, k + dk], ab[i + di, j + dj, k + dk]
        if al and (fv > 0.0) != (fl > 0.0):
            cap = min(cap, fv / (fv - fl))
        if ah and (fv > 0.0) != (fh > 0.0):
            cap = min(cap, fv / (fv - fh))
        gg = half_difference(fl, al, fv, fh, ah)
        g2 += gg * gg
    return cap, g2
