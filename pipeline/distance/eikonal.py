"""Eikonal solver on sparse 8^3 blocks: Fast Iterative Method (FIM) for HFRep step 2.

HFRep (hfrep seed, section 5.1 step 2 and section 6.1) needs the unsigned distance
``F_DF(p) = d(p, dG)`` (eq. 19) to the zero set of the FRep function, obtained as the
viscosity solution of the eikonal equation ``|grad phi| = 1`` (eq. 22 with speed 1).
We solve it with the Fast Iterative Method of Jeong & Whitaker (2008) in its block form
(kernels in :mod:`pipeline.distance.fim`): an active list of 8^3 blocks (the OpenVDB leaves of
``BlockGrid``); a block on the list is relaxed with Gauss-Seidel sweeps of the upwind update
until it converges, and a converged block puts those neighbours whose ghost (face) values it
changed back on the list. ``order=1`` is the first-order Godunov scheme, the fixed point of
the same monotone scheme that fast marching solves; ``order=2`` (default) continues from it
with the second-order upwind differences of Sethian's second-order fast marching.

Pipeline of ``solve_distance``:

1. signs: the ``frep`` band carries the sign of every active voxel; a voxel flood fill
   inside the band blocks signs their inactive voxels, and a block-level labelling of the
   remaining domain (scipy ``ndimage.label`` on the block lattice) signs every other block
   by a vote of the band voxels on its faces (``inside_boxes`` vote too);
2. block set: the band blocks, every inside block (attributes need distances everywhere
   inside, hfrep seed section 7) and the outside blocks that can hold a voxel closer than
   ``max_distance`` to the surface;
3. initialisation at sub-voxel accuracy: a voxel with a sign change towards an axis
   neighbour gets the distance to the zero set of the quadratic fit of frep on its 3x3x3
   neighbourhood (closest-point iteration), or ``|f| / |grad f|`` where that is not
   available (order 1, or a neighbour outside the band); those voxels are frozen;
4. block FIM (Numba, on a block-neighbour table: no hashing in the kernel); outside
   voxels farther than ``max_distance`` are never accepted, so the outward front stops
   there while the interior is always solved completely.

Conventions: voxel (i, j, k) is centred at (i, j, k) * voxel_size (``pipeline.sparse.grid``);
distances are in world units; ``surface`` is the OpenVDB level set (negative inside,
background = band * voxel_size, inactive voxels hold +-background).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import prange
from scipy import ndimage

from pipeline.distance.eikonal_bricks import BrickedFIM
from pipeline.distance.fim import EXCLUDED, FREE, FROZEN, block_colour, fim, init_interface
from pipeline.sparse.access import FACE_DIRS, block_lattice, block_neighbours, block_neighbours27
from pipeline.sparse.blockwrite import LeafSource, mapped_empty, release_rows
from pipeline.sparse.grid import LEAF, BlockGrid, merge_sorted, pack_keys, put_rows
from pipeline.util.jit import njit

SECOND_ORDER_VISITS = 50  # block visits per block before a second-order pass is abandoned


@dataclass
class EikonalResult:
    """Output of :func:`solve_distance`.

    ``distance``: unsigned distance (world units) on every solved voxel (active); inactive
    voxels are unsolved (outside, farther than ``max_distance``) and hold the background.
    ``inside``: bool (L,8,8,8) aligned with ``distance.origins``, True where frep > 0.
    ``stats``: counters and timings for the manifest.
    """

    distance: BlockGrid
    inside: np.ndarray
    max_distance: float | None
    stats: dict = field(default_factory=dict)
    coarse_inside: np.ndarray | None = None  # (C,3) origins of inside blocks left to a coarse solve
    # with ``inside_distance``: rows of the solved blocks that hold inside voxels (in the domain)
    # deeper than the limit, left unsolved, and those voxels (R,8,8,8); the coarse solve fills them
    deep_rows: np.ndarray | None = None
    deep_mask: np.ndarray | None = None


# --- Numba kernels ----------------------------------------------------------------------
@njit(cache=True)
def _flood_sign(sign, nbr):
    """Give every voxel with sign 0 the sign of a 6-neighbour (breadth-first flood fill).

    Sound for an frep band of at least one voxel: a sign change between two voxels puts
    both in the band, where the sign is known. Returns the number of voxels left at 0.
    """
    nb = sign.shape[0]
    n_zero = 0
    has_zero = np.zeros(nb, dtype=np.bool_)
    for b in range(nb):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if sign[b, i, j, k] == 0:
                        n_zero += 1
                        has_zero[b] = True
    if n_zero == 0:
        return 0
    queue = np.empty(7 * n_zero + 1, dtype=np.int64)
    tail = 0
    for b in range(nb):
        # a seed has a 0 neighbour: in its block or a face neighbour (the same seeds, in the same order)
        near_zero = has_zero[b]
        for f in range(6):
            n = nbr[b, f]
            if n >= 0 and has_zero[n]:
                near_zero = True
        if not near_zero:
            continue
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if sign[b, i, j, k] == 0:
                        continue
                    for f in range(6):
                        di, dj, dk = _dir(f)
                        ni, nj, nk, n = _step(nbr, b, i + di, j + dj, k + dk)
                        if n >= 0 and sign[n, ni, nj, nk] == 0:
                            queue[tail] = ((b * 8 + i) * 8 + j) * 8 + k
                            tail += 1
                            break
    head = 0
    while head < tail:
        q = queue[head]
        head += 1
        b, r = q // 512, q % 512
        i, j, k = r // 64, (r // 8) % 8, r % 8
        s = sign[b, i, j, k]
        for f in range(6):
            di, dj, dk = _dir(f)
            ni, nj, nk, n = _step(nbr, b, i + di, j + dj, k + dk)
            if n >= 0 and sign[n, ni, nj, nk] == 0:
                sign[n, ni, nj, nk] = s
                n_zero -= 1
                queue[tail] = ((n * 8 + ni) * 8 + nj) * 8 + nk
                tail += 1
    return n_zero


@njit(cache=True, inline="always")
def _dir(f):
    if f == 0:
        return -1, 0, 0
    if f == 1:
        return 1, 0, 0
    if f == 2:
        return 0, -1, 0
    if f == 3:
        return 0, 1, 0
    if f == 4:
        return 0, 0, -1
    return 0, 0, 1


@njit(cache=True, inline="always")
def _step(nbr, b, i, j, k):
    """Local coordinates and block of a voxel one step outside block b (or inside it)."""
    if i < 0:
        return 7, j, k, nbr[b, 0]
    if i > 7:
        return 0, j, k, nbr[b, 1]
    if j < 0:
        return i, 7, k, nbr[b, 2]
    if j > 7:
        return i, 0, k, nbr[b, 3]
    if k < 0:
        return i, j, 7, nbr[b, 4]
    if k > 7:
        return i, j, 0, nbr[b, 5]
    return i, j, k, b


# --- block selection (NumPy / SciPy on the block lattice) ----------------------------------
def _domain_blocks(frep: BlockGrid, domain_index_bounds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(voxel lo, voxel hi inclusive, block-lattice origin in block units, lattice dims)."""
    if domain_index_bounds is None:
        lo = frep.origins.min(axis=0)
        hi = frep.origins.max(axis=0) + LEAF - 1
    else:
        lo, hi = (np.asarray(v, dtype=np.int64) for v in domain_index_bounds)
    return lo, hi, np.stack([lo >> 3, (hi >> 3) - (lo >> 3) + 1])


def _face_sign_sums(sign: np.ndarray) -> np.ndarray:
    """(L,6) sum of voxel signs on each block face (-x,+x,-y,+y,-z,+z)."""
    n = len(sign)  # sums over the int8 faces: no int64 copy of the whole band
    faces = [sign[:, 0], sign[:, 7], sign[:, :, 0], sign[:, :, 7], sign[:, :, :, 0], sign[:, :, :, 7]]
    return np.stack([f.reshape(n, -1).sum(axis=1, dtype=np.int64) for f in faces], axis=1)


def _block_signs(
    band_mask: np.ndarray, band_row: np.ndarray, face_sums: np.ndarray, inside_blocks: np.ndarray
) -> np.ndarray:
    """Sign (+1 inside, -1 outside) of every non-band lattice block by component vote.

    Components of the non-band blocks (6-connected) cannot contain a sign change, so each
    takes the majority sign of the band voxels on the faces it shares with band blocks;
    blocks proven inside (``inside_boxes``) add a decisive vote. Components without any
    vote are outside.
    """
    labels, n = ndimage.label(~band_mask)
    votes = np.zeros(n + 1, dtype=np.float64)
    dims = np.array(band_mask.shape)
    q = np.argwhere(band_mask)  # walk from the band blocks (the surface), not the lattice (the volume)
    q_rows = band_row[q[:, 0], q[:, 1], q[:, 2]]
    for f, step in enumerate(FACE_DIRS):  # face f of a band block touches the block at q + step
        p = q + step
        ok = np.all((p >= 0) & (p < dims), axis=1)
        pp, rows = p[ok], q_rows[ok]
        hit = ~band_mask[pp[:, 0], pp[:, 1], pp[:, 2]]
        pp, rows = pp[hit], rows[hit]
        np.add.at(votes, labels[pp[:, 0], pp[:, 1], pp[:, 2]], face_sums[rows, f])  # integers: exact in any order
    inside_labels = labels[inside_blocks & ~band_mask]
    np.add.at(votes, inside_labels, 1e12)
    block_sign = np.where(votes[labels] > 0, 1, -1).astype(np.int8)
    block_sign[band_mask] = 0
    return block_sign


def _inside_box_blocks(inside_boxes, lattice_lo: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """Lattice blocks entirely contained in one of the inside boxes (index lo, hi inclusive)."""
    if inside_boxes is None:
        return np.zeros(tuple(dims), dtype=bool)
    boxes = np.asarray(inside_boxes, dtype=np.int64).reshape(-1, 2, 3)
    b_lo = np.maximum(-((-boxes[:, 0]) >> 3) - lattice_lo, 0)  # first block starting >= lo
    b_hi = np.minimum(((boxes[:, 1] + 1) >> 3) - 1 - lattice_lo, dims - 1)  # last block ending <= hi
    ok = np.all(b_hi >= b_lo, axis=1)
    b_lo, b_hi = b_lo[ok], b_hi[ok] + 1
    # union of the boxes by a 3-D difference array: +-1 at the 8 corners, then prefix sums
    acc = np.zeros(tuple(int(x) + 1 for x in dims), np.int32)
    for cx in range(2):
        for cy in range(2):
            for cz in range(2):
                c = np.stack([(b_lo, b_hi)[cx][:, 0], (b_lo, b_hi)[cy][:, 1], (b_lo, b_hi)[cz][:, 2]])
                np.add.at(acc, tuple(c), (-1) ** (cx + cy + cz))
    for a in range(3):
        np.cumsum(acc, axis=a, out=acc)
    return acc[: dims[0], : dims[1], : dims[2]] > 0


def _near_band(band_mask: np.ndarray, max_vox: float | None) -> np.ndarray:
    """Blocks that may hold a voxel within ``max_vox`` voxels of a band block."""
    if max_vox is None:
        return np.ones_like(band_mask)
    # a voxel c blocks away (Chebyshev) from every band block is >= 8(c-1)+1 voxels from it
    reach = int(math.floor(max(max_vox - 1.0, 0.0) / LEAF)) + 1
    return ndimage.maximum_filter(band_mask, size=2 * reach + 1, mode="constant", cval=False)


# voxels the fine solve goes on past the inside reach: without them a voxel just inside the reach
# can end up to 0.12 voxel off the unlimited solve (demo 512^3; the second-order scheme is not
# monotone, so the voxels beyond, missing, change the order of its updates)
INSIDE_MARGIN = 1.0
SURFACE_MARGIN = 2.0  # voxels added to a limit before a block is left out: above the FIM's error (< 1 voxel)


def _far_blocks(band: BlockGrid, band_sign, band_row, block_sign, candidates, limit_in: float,
                limit_out: float | None) -> np.ndarray:
    """Lattice mask of the ``candidates`` (non-band blocks) that hold no voxel within their
    limit (``limit_in`` inside, ``limit_out`` outside, voxels) of the surface, by a lower bound:
    the surface lies within one voxel of the interface voxels (an active voxel with f = 0 or a
    face neighbour of the other sign, all in band blocks), so no voxel of a block is closer to
    it than the gap between the block and the box of each band block's interface voxels,
    minus one. A block is left out when that bound exceeds its limit by ``SURFACE_MARGIN``:
    the FIM would accept none of its voxels, so the solve is the same without it."""
    cand = np.argwhere(candidates)
    out = np.zeros(candidates.shape, bool)
    if len(cand) == 0:
        return out
    ilo = np.empty((len(band.origins), 3), np.int64)
    ihi = np.empty((len(band.origins), 3), np.int64)
    _interface_boxes(band.values, band.active, band_sign, block_neighbours(band), ilo, ihi)
    lim_out = np.inf if limit_out is None else float(limit_out)
    lim = np.where(block_sign[tuple(cand.T)] > 0, float(limit_in), lim_out) + SURFACE_MARGIN
    top = float(lim[np.isfinite(lim)].max(initial=0.0))
    reach = int(math.ceil((top + 1.0) / LEAF)) + 1  # band blocks farther away have a larger gap
    lb = np.empty(len(cand))
    _surface_lower_bound(cand, band_row, ilo, ihi, reach, lb)
    far = lb > lim
    out[tuple(cand[far].T)] = True
    return out


@njit(cache=True, parallel=True)
def _interface_boxes(f, fact, sign, nbr, ilo, ihi):
    """Per band block: box (local, inclusive; empty lo > hi) of its interface voxels (each block
    writes only its own rows: in parallel)."""
    for b in prange(sign.shape[0]):
        _interface_box(f, fact, sign, nbr, np.int64(b), ilo, ihi)  # prange index may be unsigned


@njit(cache=True)
def _interface_box(f, fact, sign, nbr, b, ilo, ihi):
    """Block b's box of interface voxels (see :func:`_interface_boxes`)."""
    for a in range(3):
        ilo[b, a] = LEAF
        ihi[b, a] = -1
    for i in range(8):
        for j in range(8):
            for k in range(8):
                s = sign[b, i, j, k]
                if s == 0:
                    continue
                hit = fact[b, i, j, k] and f[b, i, j, k] == 0.0
                if not hit:
                    for q in range(6):
                        di, dj, dk = _dir(q)
                        ni, nj, nk, n = _step(nbr, b, i + di, j + dj, k + dk)
                        if n >= 0 and sign[n, ni, nj, nk] == -s:
                            hit = True
                            break
                if hit:
                    ilo[b, 0], ihi[b, 0] = min(ilo[b, 0], i), max(ihi[b, 0], i)
                    ilo[b, 1], ihi[b, 1] = min(ilo[b, 1], j), max(ihi[b, 1], j)
                    ilo[b, 2], ihi[b, 2] = min(ilo[b, 2], k), max(ihi[b, 2], k)


@njit(cache=True, parallel=True)
def _surface_lower_bound(cand, band_row, ilo, ihi, reach, out):
    """Per candidate lattice block: least Euclidean gap (voxels) to the interface box of a band
    block within ``reach`` blocks, minus one (inf when there is none)."""
    na, nb, nc = band_row.shape
    for t in prange(cand.shape[0]):
        p0, p1, p2 = cand[t, 0], cand[t, 1], cand[t, 2]
        best = np.inf
        for q0 in range(max(p0 - reach, 0), min(p0 + reach + 1, na)):
            for q1 in range(max(p1 - reach, 0), min(p1 + reach + 1, nb)):
                for q2 in range(max(p2 - reach, 0), min(p2 + reach + 1, nc)):
                    r = band_row[q0, q1, q2]
                    if r < 0 or ilo[r, 0] > ihi[r, 0]:
                        continue
                    g2 = 0.0
                    for a in range(3):
                        p = (p0, p1, p2)[a]
                        q = (q0, q1, q2)[a]
                        lo = LEAF * q + ilo[r, a] - (LEAF * p + LEAF - 1)
                        hi = LEAF * p - (LEAF * q + ihi[r, a])
                        g = max(0, lo, hi)
                        g2 += g * g
                    best = min(best, g2)
        out[t] = math.sqrt(best) - 1.0


# --- public API ----------------------------------------------------------------------------
def solve_distance(
    frep: BlockGrid,
    max_distance: float | str | None,
    domain_index_bounds=None,
    inside_boxes=None,
    tol: float = 1e-6,
    max_sweeps: int = 64,
    order: int = 2,
    brick: int | None = None,
    map_fn=None,
    inside_distance: float | None = None,
    signed_values: bool = False,
) -> EikonalResult:
    """Unsigned distance to the zero set of ``frep`` by the block Fast Iterative Method.

    ``frep``: FRep values (f > 0 inside) whose active voxels form the narrow band around
    f = 0. ``max_distance``: how far (world units) to grow outside the object; ``None`` or
    ``"domain"`` solves the whole domain box. The interior is always solved completely.
    ``domain_index_bounds``: ((i0,j0,k0), (i1,j1,k1)) inclusive voxel bounds of the domain
    (default: the bounding box of the frep blocks). ``inside_boxes``: (B,2,3) inclusive
    index boxes proven inside (from the voxeliser), used to sign unbanded regions.
    ``tol``: convergence tolerance in voxel units. ``order``: 1 (first-order Godunov) or 2
    (first order, then the second-order scheme from that solution; see :mod:`pipeline.distance.fim`).
    ``brick``: split the FIM into bricks of this many voxels run through ``map_fn`` (an
    executor's ``map``; inline when None) with ghost exchange (:mod:`pipeline.distance.eikonal_bricks`).
    ``inside_distance``: how deep (world units) to solve inside; None: the whole interior. The
    inside blocks that cannot hold a voxel that close to the band are left out and listed in
    ``coarse_inside`` (pipeline.distance.hfim.interior_tiles solves them on leaf-sized cells); inside
    voxels of the kept blocks whose distance exceeds it are not accepted (the same per-voxel
    cut-off as ``max_distance`` outside): blocks left without a solved voxel join
    ``coarse_inside``, the others are listed in ``deep_rows`` / ``deep_mask``.
    ``signed_values``: the inactive voxels of ``frep``'s blocks hold values of the right sign,
    as voxelise's leaves do (evaluated values, or +-background by their cell's proof; its
    ``mark_band`` puts every sign change in the band): no flood fill of the band's signs
    (at 2048^3 the serial flood took 6.7 s).
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, not {order!r}")
    t0 = time.perf_counter()
    h = float(frep.voxel_size)
    if isinstance(max_distance, str):
        if max_distance != "domain":
            raise ValueError(f"max_distance must be a number, None or 'domain', not {max_distance!r}")
        max_distance = None
    max_vox = None if max_distance is None else float(max_distance) / h
    lo, hi, (lat_lo, dims) = _domain_blocks(frep, domain_index_bounds)

    band, band_sign, unsigned = _band_in_domain(frep, lat_lo, dims, lo, hi, signed_values)
    band_row = block_lattice(band.origins, lat_lo, dims)[0]
    band_mask = band_row >= 0
    inside_blocks = _inside_box_blocks(inside_boxes, lat_lo, dims)
    block_sign = _block_signs(band_mask, band_row, _face_sign_sums(band_sign), inside_blocks)
    deep = None if inside_distance is None else float(inside_distance) / h + INSIDE_MARGIN
    near_in = _near_band(band_mask, deep)
    keep = band_mask | ((block_sign > 0) & near_in) | ((block_sign < 0) & _near_band(band_mask, max_vox))
    coarse_inside = None
    if deep is not None:  # with the inside limit, leave out the blocks the FIM cannot reach
        far = _far_blocks(band, band_sign, band_row, block_sign, keep & ~band_mask, deep, max_vox)
        keep &= ~far
        n_far = int(far.sum())
        coarse_inside = (np.argwhere((block_sign > 0) & (~near_in | far)) + lat_lo) << 3

    grid, sign, brow = _assemble(band, band_sign, block_sign, keep, lat_lo)
    del band_sign, band_mask, band_row, block_sign, keep
    if unsigned:  # band voxels the flood could not reach inside the band blocks: on through the rest
        _flood_sign(sign, block_neighbours(grid))
    inside = mapped_empty(sign.shape, bool)  # compacted in place to the kept blocks after the solve
    _positive(sign, inside)
    del sign
    state = _excluded_state(grid.origins, lo, hi)
    # float32 as the output (the FIM rounds to it as it computes): half the memory of float64
    # (1.1 GB at 1024^3); its pages go back to the OS while the output is made
    d = mapped_empty(inside.shape, np.float32)
    _fill_inf(d)
    nbr27 = block_neighbours27(grid)
    # frep is read in its own blocks through brow (no copy of it in the working layout)
    n_frozen, n_quadric = init_interface(band.values, band.active, d, state, nbr27, order == 2, brow)
    t1 = time.perf_counter()
    seeds = np.flatnonzero(_blocks_holding(state, FROZEN))  # no full-size temporary (1.1 GB at 2048^3)
    limit = np.inf if max_vox is None else max_vox
    limit_in = np.inf if deep is None else deep
    if brick:
        solver = BrickedFIM(d, state, inside, nbr27, brick, grid.origins, map_fn)
        passes = {"bricks": solver.n_bricks,
                  **run_passes(solver.pass_runner(limit, tol, max_sweeps, limit_in), d, state, seeds, order)}
    else:
        passes = run_passes(_flat_pass(d, state, inside, nbr27, block_colour(grid.origins), limit, tol, max_sweeps,
                                   limit_in), d, state, seeds, order)
    t2 = time.perf_counter()

    origins = grid.origins
    deep_rows = deep_mask = None
    rows = None
    if deep is not None:  # the inside beyond ``limit_in`` goes to the coarse solve
        has_band = np.zeros(len(d), bool)  # rows of band blocks with an active voxel
        has_band[brow >= 0] = band.active.reshape(len(band.active), -1).any(axis=1)[brow[brow >= 0]]
        rows, coarse_inside, n_dropped = _drop_unsolved(d, inside, origins, has_band, coarse_inside)
        if len(rows) < len(inside):  # rows ascend: in place, then the tail goes back to the OS
            _compact(inside, rows)
            release_rows(inside, len(inside), len(rows))
            inside = inside[:len(rows)]
        origins = origins[rows]
    del grid, brow  # free the working copies before the output is made
    bg = float(max_distance) if max_distance is not None else h * _finite_max(d)
    if rows is None:
        rows = np.arange(len(d))
    # the output values are written over the working array's leading rows (rows ascend, so a
    # chunk reads only rows at or after its own; each is read into a scratch first), and the
    # rest goes back to the OS: no second array of the distance to fault in, and a lower peak;
    # both on mappings the stage can release as it writes the grids (blockwrite.release_rows)
    solved = mapped_empty((len(rows), LEAF, LEAF, LEAF), bool)
    scratch = np.empty((min(FINISH_CHUNK, len(rows)), LEAF, LEAF, LEAF), np.float32)
    n_solved = 0
    for a in range(0, len(rows), FINISH_CHUNK):
        b = min(a + FINISH_CHUNK, len(rows))
        n_solved += _finish(d, rows, a, b, h, bg, scratch, solved)
    release_rows(d, len(d), len(rows))
    values = d[:len(rows)]
    del d, scratch
    if deep is not None:  # inside, unsolved, in the domain: one pass, no full-size temporaries
        deep_rows = np.flatnonzero(_any_left(inside, solved, state, rows))  # state is not compacted
        deep_mask = np.empty((len(deep_rows), LEAF, LEAF, LEAF), bool)
        _left(inside, solved, state, rows, deep_rows, deep_mask)
    del state
    dist = BlockGrid(h, bg, origins, values, solved)
    stats = {
        "blocks": int(len(origins)),
        "band_blocks": int(len(band.origins)),
        "solved_voxels": int(n_solved),
        "frozen_voxels": int(n_frozen),
        "quadric_initialised": int(n_quadric),
        "order": int(order),
        **passes,
        "setup_seconds": round(t1 - t0, 4),
        "fim_seconds": round(t2 - t1, 4),
    }
    if coarse_inside is not None:
        stats["inside_distance"] = float(inside_distance)
        stats["coarse_inside_blocks"] = int(len(coarse_inside))
        stats["far_blocks_left_out"] = n_far
        stats["unsolved_blocks_dropped"] = int(n_dropped)
        stats["deep_voxels_in_fine_blocks"] = int(deep_mask.sum())
    return EikonalResult(dist, inside, None if max_distance is None else float(max_distance), stats,
                         coarse_inside, deep_rows, deep_mask)


FINISH_CHUNK = 16384  # blocks per chunk of the output pass (its scratch: 32 MiB of float32)


def _drop_unsolved(d, inside, origins, has_band, coarse_inside):
    """The blocks without a solved voxel and without an active frep voxel (``has_band``; the
    inside limit left them to the coarse solve, or they lie beyond max_distance outside) are
    dropped; the inside ones join ``coarse_inside``. Returns (rows kept, the new coarse list,
    the number dropped)."""
    none = ~_any_finite(d) & ~has_band
    if not none.any():
        return np.arange(len(d)), coarse_inside, 0
    gone_inside = none & ~_blocks_holding(inside, False)  # every voxel inside
    coarse_inside = merge_sorted(coarse_inside, origins[gone_inside])[0]  # linear, not a sort of 7.6M rows
    return np.flatnonzero(~none), coarse_inside, int(none.sum())


@njit(cache=True, parallel=True)
def _any_finite(d):
    """Per block: does it hold a finite (solved) value."""
    out = np.zeros(d.shape[0], np.bool_)
    for b in prange(d.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if np.isfinite(d[b, i, j, k]):
                        out[b] = True
                        break
                if out[b]:
                    break
            if out[b]:
                break
    return out


@njit(cache=True, parallel=True)
def _any_left(inside, solved, state, srows):
    """Per block b: does it hold an inside voxel left unsolved in the domain (state of block b
    is row ``srows[b]`` of ``state``)."""
    out = np.zeros(inside.shape[0], np.bool_)
    for b in prange(inside.shape[0]):
        s = srows[b]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if inside[b, i, j, k] and not solved[b, i, j, k] and state[s, i, j, k] != EXCLUDED:
                        out[b] = True
    return out


@njit(cache=True, parallel=True)
def _left(inside, solved, state, srows, rows, out):
    """out[t] = inside & ~solved & (state != EXCLUDED) of block rows[t] (its state: row srows[rows[t]])."""
    for t in prange(rows.shape[0]):
        b = rows[t]
        s = srows[b]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    out[t, i, j, k] = inside[b, i, j, k] and not solved[b, i, j, k] and state[s, i, j, k] != EXCLUDED


@njit(cache=True, parallel=True)
def _positive(sign, out):
    """out = sign > 0, block by block on every core (np.greater: 0.39 s on one at 1024^3)."""
    for b in prange(sign.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    out[b, i, j, k] = sign[b, i, j, k] > 0


@njit(cache=True)
def _compact(arr, rows):
    """arr[t] = arr[rows[t]] for ascending rows (rows[t] >= t: in place, serially)."""
    for t in range(rows.shape[0]):
        if rows[t] != t:
            arr[t] = arr[rows[t]]


@njit(cache=True, parallel=True)
def _fill_inf(d):
    for b in prange(d.shape[0]):
        d[b] = np.inf


@njit(cache=True)
def _finite_max(d):
    m = 0.0
    for x in d.ravel():
        if np.isfinite(x) and x > m:
            m = x
    return m


@njit(cache=True, parallel=True)
def _finish(d, rows, a, b, h, bg, scratch, solved):
    """For t in a..b-1: d[t] = float32(d[rows[t]] * h) where solved (finite), else ``bg``, and
    solved[t] set. ``rows`` ascend (rows[t] >= t): the chunk's sources are read into
    ``scratch`` before any of them is written over. Returns the number solved."""
    for t in prange(b - a):
        scratch[t] = d[rows[a + t]]
    count = 0
    for t in prange(b - a):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    x = scratch[t, i, j, k]
                    if np.isfinite(x):
                        d[a + t, i, j, k] = x * h
                        solved[a + t, i, j, k] = True
                        count += 1
                    else:
                        d[a + t, i, j, k] = bg
                        solved[a + t, i, j, k] = False
    return count


@njit(cache=True, parallel=True)
def _blocks_holding(state, value):
    """Per block: does it hold a voxel in ``value`` state."""
    out = np.zeros(state.shape[0], np.bool_)
    for b in prange(state.shape[0]):
        flat = state[b].ravel()
        for n in range(flat.size):
            if flat[n] == value:
                out[b] = True
                break
    return out


def run_passes(run_pass, d, state, seeds, order: int) -> dict:
    """The FIM passes of ``order`` (see :mod:`pipeline.distance.fim`). Counters for the manifest.

    ``run_pass(seeds, order2, visits_per_block)`` runs one FIM pass (flat, over bricks, or on
    the coarse interior's node lattice: pipeline.distance.hfim.interior_tiles) and
    returns its counters with ``converged``. Order 2 runs the second-order FIM straight from
    the initial layer (measured: the same result as from the first-order solution, at a
    quarter of the work). It is not monotone, so its work is bounded; if it does not converge
    within the bound, the free voxels are reset and the robust path runs: the first-order
    fixed point, then the second-order pass from it.
    """
    if order == 1:
        return {"scheme": "first order", **run_pass(seeds, False, 1 << 40)}
    out = run_pass(seeds, True, SECOND_ORDER_VISITS)
    if out["converged"]:
        return {"scheme": "second order", **out}
    d[state == FREE] = np.inf
    first = run_pass(seeds, False, 1 << 40)
    solved = np.nonzero(np.isfinite(d).reshape(len(d), -1).any(axis=1))[0]
    second = run_pass(solved, True, SECOND_ORDER_VISITS)
    return {"scheme": "second order did not converge from the initial layer: first order, then second order",
            "abandoned": out, **first, **{f"order2_{k}": v for k, v in second.items()},
            "converged": second["converged"]}


def _flat_pass(d, state, inside, nbr27, colour, limit, tol, max_sweeps, limit_in=np.inf):
    def run(seeds, order2, visits_per_block):
        cap = visits_per_block * max(len(d), 1)
        visits, updates, sweeps, ok = fim(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2,
                                          cap, limit_in)
        return {"block_visits": int(visits), "voxel_updates": int(updates), "sweeps": int(sweeps),
                "converged": bool(ok)}
    return run


def _band_in_domain(frep: BlockGrid, lat_lo: np.ndarray, dims: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    signed_values: bool = False) -> tuple[BlockGrid, np.ndarray]:
    """frep blocks inside the block lattice, the sign (+1 inside, -1 outside) of their voxels
    and how many are left at 0 (not connected to a known one inside the band blocks).

    The active voxels' signs are those of their values. The others take the sign of the band
    by a flood fill, unless ``signed_values``: then every voxel in the domain carries the sign
    of its value, and only those outside the domain bounds ``lo..hi`` are flooded."""
    b = (frep.origins >> 3) - lat_lo
    ok = np.all((b >= 0) & (b < dims), axis=1)
    band = frep if ok.all() else BlockGrid(frep.voxel_size, frep.background, frep.origins[ok], frep.values[ok],
                                           frep.active[ok])
    sign = np.empty(band.values.shape, np.int8)
    left = _value_signs(band.values, band.active, band.origins, lo, hi, signed_values, sign)
    if left:
        left = _flood_sign(sign, block_neighbours(band))
    return band, sign, int(left)


@njit(cache=True, parallel=True)
def _value_signs(values, active, origins, lo, hi, signed_values, sign):
    """sign[v] = +1 / -1 by values[v] > 0 where known (active, or ``signed_values`` and in
    lo..hi), else 0. Returns the number of zeros (voxels left to the flood fill)."""
    zeros = 0
    for b in prange(values.shape[0]):
        o = origins[b]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    known = active[b, i, j, k]
                    if signed_values and not known:
                        known = (lo[0] <= o[0] + i <= hi[0]) and (lo[1] <= o[1] + j <= hi[1]) \
                            and (lo[2] <= o[2] + k <= hi[2])
                    if known:
                        sign[b, i, j, k] = 1 if values[b, i, j, k] > 0 else -1
                    else:
                        sign[b, i, j, k] = 0
                        zeros += 1
    return zeros


def _assemble(band: BlockGrid, band_sign: np.ndarray, block_sign: np.ndarray, keep: np.ndarray, lat_lo):
    """Working blocks: the band blocks plus the kept non-band blocks (sign filled per block).

    Returns (grid of the working origins: no values, sign int8, band row of every working
    block or -1): the frep values stay in the band's own arrays, read through that row map."""
    extra = np.argwhere(keep & (block_sign != 0))
    origins = np.concatenate([band.origins, (extra + lat_lo) << 3])
    order = np.argsort(pack_keys(origins), kind="stable")
    pos = np.empty(len(origins), np.int64)  # new row of every band block, then every extra one
    pos[order] = np.arange(len(origins))
    nb = len(band.origins)
    sign = np.empty((len(origins), LEAF, LEAF, LEAF), dtype=np.int8)
    put_rows(sign, pos[:nb], band_sign)  # in parallel: 2.4 s of NumPy fancy assignment at 2048^3
    put_rows(sign, pos[nb:], block_sign[tuple(extra.T)])
    brow = np.full(len(origins), -1, np.int64)
    brow[pos[:nb]] = np.arange(nb)
    empty = np.zeros((0, LEAF, LEAF, LEAF), np.float32)  # block_index / neighbour tables need the origins only
    grid = BlockGrid(band.voxel_size, band.background, origins[order], empty, empty.astype(bool))
    return grid, sign, brow


def _excluded_state(origins: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """State array: EXCLUDED for voxels outside the inclusive domain bounds, FREE elsewhere.

    Only blocks that cross the domain's boundary are computed voxel by voxel."""
    state = np.zeros((len(origins), LEAF, LEAF, LEAF), np.int8)  # FREE == 0
    cut = np.nonzero(np.any((origins < lo) | (origins + LEAF - 1 > hi), axis=1))[0]
    if len(cut):
        r = np.arange(LEAF)
        ijk = origins[cut, :, None] + r[None, None, :]  # (C,3,8)
        inside = (ijk >= lo[None, :, None]) & (ijk <= hi[None, :, None])
        ok = inside[:, 0, :, None, None] & inside[:, 1, None, :, None] & inside[:, 2, None, None, :]
        state[cut] = np.where(ok, FREE, EXCLUDED)
    return state


def signed_distance_blocks(result: EikonalResult) -> BlockGrid:
    """Signed distance in level-set convention (negative inside), unclamped, solved voxels active."""
    dist = result.distance
    values = np.empty(dist.values.shape, np.float32)
    _signed(dist.values, result.inside, values)
    return BlockGrid(dist.voxel_size, dist.background, dist.origins, values, dist.active)


@njit(cache=True, parallel=True)
def _signed(values, inside, out):
    """out = -values inside, values outside (one parallel pass, no temporaries)."""
    for b in prange(values.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    v = values[b, i, j, k]
                    out[b, i, j, k] = -v if inside[b, i, j, k] else v


def surface_blocks(result: EikonalResult, band: float, full: bool = False) -> BlockGrid:
    """The ``surface`` level set (SPEC): negative inside, world units, background = band * h.

    By default a narrow band, as OpenVDB level sets are: voxels within ``band`` voxels of the
    surface are active, the rest hold -background inside and +background outside. ``full``
    keeps every solved voxel active (the whole interior and the outside up to max_distance).
    """
    bg = float(band) * result.distance.voxel_size
    if not full:  # the blocks that hold a band voxel, made all at once
        leaves = surface_leaves(result, band)
        values = np.empty((len(leaves.origins), LEAF, LEAF, LEAF), np.float32)
        active = np.empty(values.shape, bool)
        leaves.fill(0, len(leaves.origins), values, active)
        return BlockGrid(leaves.voxel_size, bg, leaves.origins, values, active)
    sd = signed_distance_blocks(result)
    values = sd.values
    values[~sd.active] = np.where(result.inside[~sd.active], -bg, bg)
    return BlockGrid(sd.voxel_size, bg, sd.origins, values, sd.active)


@njit(cache=True, parallel=True)
def _near_blocks(values, active, bg):
    """Per block: does it hold an active voxel with value <= bg (float32 comparison)."""
    out = np.zeros(values.shape[0], np.bool_)
    for b in prange(values.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if active[b, i, j, k] and values[b, i, j, k] <= bg:
                        out[b] = True
    return out


@njit(cache=True, parallel=True)
def _band_values(values, active, inside, rows, bg, out_v, out_a):
    """Level-set values of the blocks ``rows``: -+d where active and d <= bg, else -+bg."""
    for t in prange(rows.shape[0]):
        b = rows[t]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    v = values[b, i, j, k]
                    a = active[b, i, j, k] and v <= bg
                    out_a[t, i, j, k] = a
                    if not a:
                        v = bg
                    out_v[t, i, j, k] = -v if inside[b, i, j, k] else v


def surface_leaves(result: EikonalResult, band: float, full: bool = False, consume: bool = False) -> LeafSource:
    """The leaves of the ``surface`` level set (:func:`surface_blocks`; background ``band`` voxels
    in world units), for pipeline.io.vdbgrids.level_set_grid. The narrow band is made a batch of
    blocks at a time as it is written (never held whole), only on the blocks that hold a voxel
    within the band (the unsigned distance is compared, so no signed copy of the grid is made;
    signedFloodFill does the rest). ``consume`` (narrow band only): the
    distance and side arrays of ``result`` are released as the band is written (``result`` is
    not to be read afterwards: the last use of a solve)."""
    bg = float(band) * result.distance.voxel_size
    if full:
        return LeafSource.of(surface_blocks(result, band, full))
    dist = result.distance
    bg32 = np.float32(bg)
    rows = np.flatnonzero(_near_blocks(dist.values, dist.active, bg32))

    def fill(lo, hi, values, active):
        _band_values(dist.values, dist.active, result.inside, rows[lo:hi], bg32, values, active)

    def done(hi):  # no later batch reads the blocks before the next band block
        upto = int(rows[hi]) if hi < len(rows) else len(dist.values)
        for arr in (dist.values, dist.active, result.inside):
            release_rows(arr, upto)
    return LeafSource(dist.voxel_size, bg, dist.origins[rows], fill=fill, done=done if consume else None)
