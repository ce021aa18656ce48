"""Hierarchical Fast Iterative Method (HFIM) in 3D: far space on coarse, VDB-aligned cells.

The hfrep seed (section 6.1, "ADF generation") outlines an HFIM for quadtree/octree grids:
subdivide the boundary to the maximum depth and the exterior/interior with a small depth,
initialise the vertices on the zero set to 0 and the rest to a huge value, and iterate the
first-order upwind Godunov scheme (eq. 22 with f = 1) "modified for computations on the
grid with irregular steps" until the active list is empty. Here the octree is the OpenVDB
tree itself and the levels are solved one after the other, each from the finer one:

* level 0 (fine): :func:`pipeline.distance.eikonal.solve_distance` out to ``fine_distance_vox``
  voxels outside (the interior is always solved completely), 8^3 leaves;
* level 1: one node at the centre of every leaf-sized cell (8^3 voxels, spacing 8 h);
* level 2: one node at the centre of every 128^3-voxel cell (spacing 128 h): the child
  size of OpenVDB's upper internal node, so a level-2 cell is written as ONE tile there.

On level 1 a node whose leaf the fine level solved completely is frozen at the fine value at
the node (trilinear: the mean of the 8 voxels around the leaf centre); on level 2 a node is
frozen where the trilinear value of level 1 is defined (its 8 surrounding nodes solved); the other
nodes are solved by a node FIM (active list, Jeong & Whitaker 2008) with the Godunov update
:func:`pipeline.distance.fim.upwind3` at spacing s_l (then the second-order pass, as the fine
solve). Level 1 first runs out to ``coarse_distance_vox`` (as the fine level stops at its
reach); every level-2 cell it reached is then solved completely on level 1, and level 2 keeps
only the cells wholly beyond the reach, each written as one 128^3 tile.
Finer entries left unsolved (a leaf the fine front only partly reached, a level-1 node past
its reach) are filled by trilinear interpolation of the next level.

The written grid (:func:`hierarchical_tiles`) stores fine leaves where the fine level solved,
leaf-sized tiles for level-1 cells and 128^3 tiles for level-2 cells, so the far field costs
one value per cell: the memory grows with the object's area, not with the domain's volume.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba
import numpy as np
from numba import prange
from scipy import ndimage

from pipeline.distance.eikonal import SECOND_ORDER_VISITS, EikonalResult, run_passes, solve_distance
from pipeline.distance.fim import EXCLUDED, FREE, FROZEN, fim, upwind3
from pipeline.sparse.access import FACES6, OWN_ROWS, block_neighbours, block_neighbours27, load_ghosts
from pipeline.sparse.grid import LEAF, BlockGrid
from pipeline.util.jit import njit

LEVEL_CELLS = (8, 128)  # cell edge in voxels of levels 1, 2: an OpenVDB leaf and an internal-node child


@dataclass
class CoarseLevel:
    """One coarse level: a dense lattice of cells of ``cell`` voxels aligned to multiples of
    ``cell``; cell (a, b, c) covers voxels ``(lat_lo + (a, b, c)) * cell + [0, cell)`` and its
    node sits at the cell centre. ``values``: distance in voxel units (inf = not solved on this
    level), ``frozen``: taken from the finer level, ``solved``: finite after this level's FIM."""

    cell: int
    lat_lo: np.ndarray
    values: np.ndarray
    frozen: np.ndarray
    limit: float
    inside: np.ndarray | None = None

    @property
    def solved(self) -> np.ndarray:
        return np.isfinite(self.values)

    def node_index(self) -> np.ndarray:
        """(A,B,C,3) voxel index (float) of every node."""
        axes = [(self.lat_lo[a] + np.arange(self.values.shape[a])) * self.cell + (self.cell - 1) / 2
                for a in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1)

    def sample(self, ijk: np.ndarray) -> np.ndarray:
        """Trilinear interpolation (voxel units) at voxel indices (N,3); inf where a corner is unsolved."""
        q = (np.asarray(ijk, float) - (self.cell - 1) / 2) / self.cell - self.lat_lo
        q = np.clip(q, 0, np.array(self.values.shape) - 1)
        v = np.where(np.isfinite(self.values), self.values, 1e30)
        out = ndimage.map_coordinates(v, q.T, order=1, mode="nearest")
        return np.where(out > 1e29, np.inf, out)


@dataclass
class HierarchicalResult:
    """Fine :class:`EikonalResult` plus the coarse levels (finest first) and counters."""

    fine: EikonalResult
    levels: list[CoarseLevel]
    domain: tuple[np.ndarray, np.ndarray]
    stats: dict = field(default_factory=dict)

    @property
    def voxel_size(self) -> float:
        return float(self.fine.distance.voxel_size)


@njit(cache=True)
def node_fim(d, state, inside, spacing, limit, tol, order2, max_visits):
    """Node FIM on a dense lattice (Jeong & Whitaker 2008, Alg. 1, one node per list item).

    ``d`` (A,B,C) distance in voxel units (inf = unknown), ``state`` FREE/FROZEN/EXCLUDED,
    ``inside`` the side of the surface of every node. First order (``order2`` False): the
    list starts with the free neighbours of frozen nodes and only decreases are accepted (the
    monotone Godunov scheme, from above). Second order: every solved free node starts on the
    list and changes in either direction are accepted, at most ``max_visits`` list visits.
    A value above ``limit`` is never accepted. Returns (updates, visits)."""
    na, nb, nc = d.shape
    n = na * nb * nc
    queue = np.empty(n + 1, dtype=np.int64)
    on_list = np.zeros(n, dtype=np.bool_)
    head = 0
    tail = 0
    for p in range(n):
        a, r = divmod(p, nb * nc)
        b, c = divmod(r, nc)
        if state[a, b, c] != FREE:
            continue
        start = order2 and d[a, b, c] < np.inf
        if not order2:  # free neighbours of frozen nodes start the first-order list
            for ax in range(6):
                x, y, z = _nb(a, b, c, ax, 1)
                if 0 <= x < na and 0 <= y < nb and 0 <= z < nc and state[x, y, z] == FROZEN:
                    start = True
        if start:
            on_list[p] = True
            queue[tail] = p
            tail += 1
    updates = 0
    visits = 0
    while head != tail and visits < max_visits:
        visits += 1
        p = queue[head]
        head = (head + 1) % (n + 1)
        on_list[p] = False
        a, r = divmod(p, nb * nc)
        b, c = divmod(r, nc)
        u = _node_update(d, state, inside, a, b, c, spacing, order2)
        if u > limit:
            continue
        if order2:
            if not abs(u - d[a, b, c]) > tol:
                continue
        elif not u < d[a, b, c] - tol:
            continue
        d[a, b, c] = u
        updates += 1
        for ax in range(6):  # neighbours that may change go (back) on the list
            x, y, z = _nb(a, b, c, ax, 1)
            if not (0 <= x < na and 0 <= y < nb and 0 <= z < nc) or state[x, y, z] != FREE:
                continue
            q = (x * nb + y) * nc + z
            if not on_list[q] and (order2 or d[x, y, z] > u):
                on_list[q] = True
                queue[tail] = q
                tail = (tail + 1) % (n + 1)
    return updates, visits


def lattice_fim(d, state, inside, spacing: float, tol: float, order2: bool, visits_per_block: int,
                limit: float = np.inf) -> tuple[int, int, bool]:
    """:func:`node_fim` by the block FIM of the fine solve (pipeline.distance.fim.fim: 8^3
    blocks of nodes, red-black waves on both cores, Gauss-Seidel sweeps inside a block) instead
    of one node per list item on one core. The same Godunov update, in units of ``spacing`` (a
    power of two: the scaling is exact); excluded nodes read as unknown, as node_fim reads them.
    First order converges to the same fixed point (to ``tol``); second order is the same
    non-monotone scheme, at most ``visits_per_block`` visits per block. In place; returns
    (updates, block visits, converged: False when stopped by the visit bound)."""
    where = np.argwhere(_live_blocks(state))
    if len(where) == 0:
        return 0, 0, True
    db, sb, ib = _gather_blocks(d, state, inside, where, 1.0 / spacing)
    colour = (where.sum(axis=1) & 1).astype(np.int64)
    seeds = np.flatnonzero((sb == FREE).reshape(len(sb), -1).any(axis=1)).astype(np.int64)
    cap = limit / spacing  # node_fim's limit holds on both sides of the surface
    visits, updates, _, ok = fim(db, sb, ib, block_neighbours27(where * LEAF), colour, seeds, cap, tol / spacing, 64,
                                 order2, visits_per_block * len(db), cap)
    _scatter_free(d, db, sb, where, spacing)
    return int(updates), int(visits), bool(ok)


@njit(cache=True, parallel=True)
def _live_blocks(state):
    """(ceil(A/8), ceil(B/8), ceil(C/8)): the 8^3 blocks of the lattice with a node not excluded."""
    na, nb, nc = state.shape
    ba, bb, bc = (na + 7) // 8, (nb + 7) // 8, (nc + 7) // 8
    live = np.zeros((ba, bb, bc), np.bool_)
    for x in prange(ba):
        for a in range(8 * x, min(8 * x + 8, na)):
            for b in range(nb):
                for c in range(nc):
                    if state[a, b, c] != EXCLUDED:
                        live[x, b >> 3, c >> 3] = True
    return live


@njit(cache=True, parallel=True)
def _gather_blocks(d, state, inside, where, scale):
    """The blocks ``where`` (block coordinates) of the lattice: d * scale (inf where excluded or
    past the lattice), state (excluded past it), inside."""
    na, nb, nc = d.shape
    n = where.shape[0]
    db = np.empty((n, 8, 8, 8))
    sb = np.empty((n, 8, 8, 8), np.int8)
    ib = np.zeros((n, 8, 8, 8), np.bool_)
    for t in prange(n):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    a, b, c = 8 * where[t, 0] + i, 8 * where[t, 1] + j, 8 * where[t, 2] + k
                    if a < na and b < nb and c < nc and state[a, b, c] != EXCLUDED:
                        db[t, i, j, k] = d[a, b, c] * scale
                        sb[t, i, j, k] = state[a, b, c]
                        ib[t, i, j, k] = inside[a, b, c]
                    else:
                        db[t, i, j, k] = np.inf
                        sb[t, i, j, k] = EXCLUDED
    return db, sb, ib


@njit(cache=True, parallel=True)
def _scatter_free(d, db, sb, where, scale):
    """The free nodes' values of the blocks back into the lattice, times ``scale``."""
    for t in prange(where.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if sb[t, i, j, k] == FREE:
                        d[8 * where[t, 0] + i, 8 * where[t, 1] + j, 8 * where[t, 2] + k] = db[t, i, j, k] * scale


@njit(cache=True, inline="always")
def _nb(a, b, c, f, step):
    """Node ``step`` steps from (a, b, c) in face direction f (-x, +x, -y, +y, -z, +z)."""
    sgn = step if f & 1 else -step
    if f < 2:
        return a + sgn, b, c
    if f < 4:
        return a, b + sgn, c
    return a, b, c + sgn


@njit(cache=True, inline="always")
def _node_update(d, state, inside, a, b, c, spacing, order2):
    """Godunov update of node (a, b, c), voxel units: per axis the smaller neighbour; second
    order (Sethian 1999, section 4.3) where the next node on that side is known and not larger,
    with the value across the surface negated (the signed distance is smooth there)."""
    bx, wx = _node_axis(d, state, inside, a, b, c, 0, order2)
    by, wy = _node_axis(d, state, inside, a, b, c, 1, order2)
    bz, wz = _node_axis(d, state, inside, a, b, c, 2, order2)
    if bx == np.inf and by == np.inf and bz == np.inf:
        return np.inf
    return upwind3(bx / spacing, wx, by / spacing, wy, bz / spacing, wz) * spacing


@njit(cache=True, inline="always")
def _node_axis(d, state, inside, a, b, c, ax, order2):
    """(b, c^2) of one axis at node (a, b, c), as :func:`pipeline.distance.fim.upwind3` takes them."""
    na, nb, nc = d.shape
    best = np.inf
    side = 0
    for f in (2 * ax, 2 * ax + 1):
        x, y, z = _nb(a, b, c, f, 1)
        if 0 <= x < na and 0 <= y < nb and 0 <= z < nc and state[x, y, z] != EXCLUDED and d[x, y, z] < best:
            best = d[x, y, z]
            side = f
    if best == np.inf or not order2:
        return best, 1.0
    x, y, z = _nb(a, b, c, side, 2)
    if 0 <= x < na and 0 <= y < nb and 0 <= z < nc and state[x, y, z] != EXCLUDED:
        a2 = d[x, y, z] if inside[x, y, z] == inside[a, b, c] else -d[x, y, z]
        if a2 <= best:
            return (4.0 * best - a2) / 3.0, 2.25
    return best, 1.0


def _lattice(lo: np.ndarray, hi: np.ndarray, cell: int) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Cells of edge ``cell`` (aligned to multiples of it) that meet the inclusive voxel box."""
    a, b = np.floor_divide(lo, cell), np.floor_divide(hi, cell)
    return a.astype(np.int64), tuple(int(x) for x in b - a + 1)


def _parents(lat_lo: np.ndarray, shape, cell: int, coarser: int) -> np.ndarray:
    """(A,B,C,3) index of the coarser cell holding every node, relative to the coarser lattice."""
    axes = [lat_lo[a] + np.arange(shape[a]) for a in range(3)]
    idx = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    r = coarser // cell
    return idx // r - np.floor_divide(lat_lo, r)


def _fine_nodes(fine: EikonalResult, lat_lo: np.ndarray, shape, centre: bool = False):
    """Level-1 (leaf) node values from the fine solve: mean of the 8 voxels around each leaf
    centre (the trilinear value there); frozen where the whole leaf is solved (``centre``:
    where those 8 voxels are solved); inside where most of those 8 voxels are."""
    dist = fine.distance
    vals = np.full(shape, np.inf)
    frozen = np.zeros(shape, bool)
    inside = np.zeros(shape, bool)
    _leaf_nodes(dist.values, dist.active, fine.inside, dist.origins, np.asarray(lat_lo, np.int64),
                np.float32(dist.voxel_size), centre, vals, frozen, inside)
    return vals, frozen, inside


@njit(cache=True, parallel=True)
def _leaf_nodes(values, active, inside_v, origins, lat_lo, h32, centre, vals, frozen, inside):
    """:func:`_fine_nodes` in one parallel pass over the blocks (each writes its own node).
    The mean is NumPy's float32 ``mean`` of the 8 centre voxels (its pairwise sum), divided by
    ``h32`` in float32, as the NumPy code it replaces computed it (bit for bit, checked on the
    demo at 512^3); inside: more than 4 of the 8."""
    na, nb, nc = vals.shape
    for t in prange(origins.shape[0]):
        a = (origins[t, 0] >> 3) - lat_lo[0]
        b = (origins[t, 1] >> 3) - lat_lo[1]
        c = (origins[t, 2] >> 3) - lat_lo[2]
        if not (0 <= a < na and 0 <= b < nb and 0 <= c < nc):
            continue
        n_in = 0
        full = True
        for q in range(8):
            i, j, k = 3 + (q >> 2), 3 + ((q >> 1) & 1), 3 + (q & 1)
            n_in += inside_v[t, i, j, k]
            full = full and active[t, i, j, k]
        inside[a, b, c] = n_in > 4
        if not centre and full:
            for i in range(8):
                for j in range(8):
                    for k in range(8):
                        full = full and active[t, i, j, k]
        if full:
            v = values[t, 3:5, 3:5, 3:5]
            lo = (v[0, 0, 0] + v[0, 0, 1]) + (v[0, 1, 0] + v[0, 1, 1])
            hi = (v[1, 0, 0] + v[1, 0, 1]) + (v[1, 1, 0] + v[1, 1, 1])
            vals[a, b, c] = ((lo + hi) / np.float32(8.0)) / h32
            frozen[a, b, c] = True


def _coarser_nodes(level: CoarseLevel, cell: int, lat_lo: np.ndarray, shape):
    """Nodes of the level with cells ``cell``, frozen at the trilinear value of the finer
    ``level`` wherever that is defined (the 8 finer nodes around the node are solved; the
    node position is clamped to the finer lattice for cells that stick out of the domain)."""
    vals = np.full(shape, np.inf)
    frozen = np.zeros(shape, bool)
    nodes = CoarseLevel(cell, lat_lo, vals, frozen, np.inf).node_index().reshape(-1, 3)
    centre = level.sample(nodes).reshape(shape)
    ok = np.isfinite(centre)
    vals[ok] = centre[ok]
    frozen[ok] = True
    near = np.floor_divide(nodes, level.cell).astype(np.int64) - level.lat_lo  # finer cell of each node
    near = np.clip(near, 0, np.array(level.values.shape) - 1)
    inside = level.inside[tuple(near.T)].reshape(shape)
    return vals, frozen, inside


def hierarchical_distance(
    frep,
    domain_index_bounds,
    inside_boxes=None,
    fine_distance_vox: float = 16.0,
    coarse_distance_vox: float = 256.0,
    order: int = 2,
    levels: tuple[int, ...] = LEVEL_CELLS,
    tol: float = 1e-6,
    brick: int | None = None,
    map_fn=None,
    signed_values: bool = False,
) -> HierarchicalResult:
    """Unsigned distance to frep's zero set over the whole domain box on mixed-depth cells.

    ``fine_distance_vox``: reach (voxels) of the fine solve outside the object;
    ``coarse_distance_vox``: reach of every coarse level but the last (voxels), beyond which
    the next level takes over; ``levels``: cell edges in voxels (default 8, 128). ``brick``,
    ``map_fn``: the fine solve on bricks over an executor; ``signed_values``: frep's inactive
    voxels carry their sign (both :func:`solve_distance`).
    """
    t0 = time.perf_counter()
    lo, hi = (np.asarray(b, dtype=np.int64) for b in domain_index_bounds)
    h = float(frep.voxel_size)
    fine = solve_distance(frep, fine_distance_vox * h, (lo, hi), inside_boxes, order=order, brick=brick,
                          map_fn=map_fn, signed_values=signed_values)
    t1 = time.perf_counter()
    out: list[CoarseLevel] = []
    updates = []
    for n, cell in enumerate(levels):
        lat_lo, shape = _lattice(lo, hi, cell)
        if n == 0:
            vals, frozen, inside = _fine_nodes(fine, lat_lo, shape)
        else:
            vals, frozen, inside = _coarser_nodes(out[-1], cell, lat_lo, shape)
        limit = np.inf if n == len(levels) - 1 else float(coarse_distance_vox)
        state = np.where(frozen, FROZEN, FREE).astype(np.int8)
        seeded = vals.copy()
        up, _, _ = lattice_fim(vals, state, inside, float(cell), tol * cell, False, 1 << 40, limit)
        if n < len(levels) - 1:
            # every next-level cell this level reached within its limit is solved completely
            # here; the next level keeps only the cells wholly beyond the reach
            parent = _parents(lat_lo, shape, cell, levels[n + 1])
            reached = np.zeros(tuple(parent.max(axis=(0, 1, 2)) + 1), bool)
            reached[tuple(parent[np.isfinite(vals)].T)] = True
            state[~reached[tuple(np.moveaxis(parent, -1, 0))]] = EXCLUDED
            vals[...] = seeded
            up2, _, _ = lattice_fim(vals, state, inside, float(cell), tol * cell, False, 1 << 40)
            up += up2
        if order == 2:  # second order from the first-order fixed point, as the fine solve
            up2, _, _ = lattice_fim(vals, state, inside, float(cell), tol * cell, True, SECOND_ORDER_VISITS)
            up += up2
        updates.append(int(up))
        out.append(CoarseLevel(cell, lat_lo, vals, frozen, limit, inside))
    t2 = time.perf_counter()
    stats = {
        "fine": fine.stats,
        "levels": [{"cell": lv.cell, "nodes": int(lv.values.size), "frozen": int(lv.frozen.sum()),
                    "solved": int(lv.solved.sum()), "updates": u} for lv, u in zip(out, updates, strict=True)],
        "fine_seconds": round(t1 - t0, 4),
        "coarse_seconds": round(t2 - t1, 4),
    }
    return HierarchicalResult(fine, out, (lo, hi), stats)


def interior_tiles(fine: EikonalResult, domain_index_bounds, order: int = 2, tol: float = 1e-6
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Distance on the inside blocks the fine solve left out (``fine.coarse_inside``), one value
    per leaf-sized cell: the level-1 step of :func:`hierarchical_distance` turned inwards. Nodes
    sit at leaf centres (spacing 8 voxels); a node whose 8 centre voxels the fine level solved is
    frozen at the fine value there (their mean); the other nodes of the left-out blocks and of
    the fine blocks with inside voxels left unsolved (``fine.deep_rows``: deeper than the fine
    solve's inside limit) are solved by the node FIM (:func:`_interior_solve`: second order from
    the frozen nodes, as the fine solve); every other node is excluded. Returns (tile origins (C,3), distance in world
    units at each tile's centre, the node value of each ``deep_rows`` block (at least the
    limit; :func:`fill_deep` uses it where a block has no solved shell), counters). A tile
    holds that one value for its 8^3 voxels: within the node's FIM error plus 4 sqrt(3) voxels
    (the distance is 1-Lipschitz) of the fine solve; docs/hfim.md gives the measured error."""
    t0 = time.perf_counter()
    origins = np.zeros((0, 3), np.int64) if fine.coarse_inside is None else fine.coarse_inside
    deep_rows = np.zeros(0, np.int64) if fine.deep_rows is None else fine.deep_rows
    if len(origins) == 0 and len(deep_rows) == 0:
        return origins, np.zeros(0), np.zeros(0), {"tiles": 0}
    lo, hi = (np.asarray(b, dtype=np.int64) for b in domain_index_bounds)
    cell = LEVEL_CELLS[0]
    lat_lo, shape = _lattice(lo, hi, cell)
    # with the fine solve cut off inside (and outside at max_distance) few leaves are solved
    # completely: a node is frozen where the fine solve covers its 8 centre voxels
    vals, frozen, inside = _fine_nodes(fine, lat_lo, shape, centre=True)
    state = np.where(frozen, FROZEN, EXCLUDED).astype(np.int8)
    # flat lattice index of every node to solve, by one compiled pass each (the NumPy index
    # tuples of 8.6M nodes took 2.5 s at 2048^3); a deep block's node stays frozen where its
    # centre voxels are solved
    tiles_at = _free_nodes(origins, np.arange(len(origins)), lat_lo, cell, state, inside, vals)
    deep_at = _free_nodes(fine.distance.origins, deep_rows, lat_lo, cell, state, inside, vals)
    # the block FIM over 8^3 blocks of nodes, both cores (node_fim: 1.5 -> 0.5 s at 1024^3)
    up = _interior_solve(vals, state, inside, float(cell), tol * cell, order)
    h = float(fine.distance.voxel_size)
    d_tiles, d_deep = vals.ravel()[tiles_at], vals.ravel()[deep_at]
    limit = fine.stats.get("inside_distance", 0.0) / h
    fill = np.maximum(d_deep, limit)  # inf where unreached: the caller leaves those voxels unsolved
    ok = np.isfinite(d_tiles)  # a left-out block with no solved path to the fine level stays unsolved
    st = {"tiles": int(ok.sum()), "unreached": int((~ok).sum() + (~np.isfinite(fill)).sum()),
          "deep_blocks": int(len(deep_rows)), "updates": int(up), "seconds": round(time.perf_counter() - t0, 4)}
    return origins[ok], d_tiles[ok] * h, fill * h, st


@njit(cache=True)
def _free_nodes(origins, rows, lat_lo, cell, state, inside, vals):
    """For the blocks ``origins[rows]``: the flat index of the node of the cell holding each in
    the lattice of ``state`` (cells of ``cell`` voxels from ``lat_lo``); every such node that is
    not FROZEN becomes FREE, inside, unknown (inf). Returns the flat indices."""
    nb, nc = state.shape[1], state.shape[2]
    st, ins, v = state.ravel(), inside.ravel(), vals.ravel()
    out = np.empty(rows.shape[0], np.int64)
    for t in range(rows.shape[0]):
        o = origins[rows[t]]
        q = ((o[0] // cell - lat_lo[0]) * nb + (o[1] // cell - lat_lo[1])) * nc + (o[2] // cell - lat_lo[2])
        out[t] = q
        if st[q] != FROZEN:
            st[q] = FREE
            ins[q] = True
            v[q] = np.inf
    return out


def _interior_solve(vals, state, inside, cell: float, tol: float, order: int) -> int:
    """The node FIM of :func:`interior_tiles` (block FIM over 8^3 blocks of nodes, both cores),
    its passes chosen as the fine solve's (pipeline.distance.eikonal.run_passes): order 2 runs
    the second-order scheme straight from the frozen nodes and, if it stops at its visit bound,
    resets the free nodes and runs from the first-order fixed point. Returns the updates. At
    1024^3 (demo): 6.07M -> 2.77M updates, 0.72 -> 0.46 s against first then second order; the
    tile values move by at most 1.1e-3 voxel (two paths of a non-monotone scheme to its fixed
    point), far below the tiles' 4 sqrt(3) voxels."""
    updates = []

    def run(seeds, order2, visits_per_block):  # lattice_fim finds its own seeds
        up, visits, ok = lattice_fim(vals, state, inside, cell, tol, order2, visits_per_block)
        updates.append(up)
        return {"voxel_updates": up, "block_visits": visits, "converged": ok}

    run_passes(run, vals, state, None, order)
    return sum(updates)


def fill_deep(blocks, fine: EikonalResult, fill: np.ndarray, sign: float = 1.0) -> None:
    """Give the unsolved deep inside voxels of ``fine.deep_rows`` (``blocks`` aligned with
    ``fine.distance``) a distance and make them active: ``min(d(y) + |x - y|)`` over the solved
    inside voxels y next to an unsolved one, in the block and the face layers of its six
    neighbours (the distance is 1-Lipschitz, so each term is an upper bound; the least is
    close where the nearest point of the solved shell lies there), and the node value ``fill``
    (from :func:`interior_tiles`) plus the distance to the leaf centre; never less than the
    inside limit. Written as ``sign`` times the distance; unreached ones (inf) are left. Written
    in place by one parallel pass (``blocks`` must not share arrays with ``fine.distance``)."""
    if fine.deep_rows is None or len(fine.deep_rows) == 0:
        return
    h = float(fine.distance.voxel_size)
    rows, mask = fine.deep_rows, fine.deep_mask
    dist = fine.distance
    limit = fine.stats.get("inside_distance", 0.0) / h
    nbr = block_neighbours(dist)
    if np.shares_memory(blocks.values, dist.values) or np.shares_memory(blocks.active, dist.active):
        raise ValueError("fill_deep writes blocks while it reads fine.distance: give it a copy")
    _shell_fill(dist.values, dist.active, fine.inside, rows, nbr, mask, fill / h, limit, 1.0 / h, sign * h,
                blocks.values, blocks.active)


@njit(cache=True, parallel=True)
def _shell_fill(vals, active, inside, rows, nbr, mask, fallback, limit, inv_h, scale, out_v, out_a):
    """Per deep block t (block ``rows[t]``; ``nbr``: the face table of every block), at its ``mask[t]``
    voxels: d = min over the solved inside voxels of the block and of its neighbours' face
    layers that touch a mask voxel of (value * inv_h + Euclidean distance in voxels), and of
    ``fallback[t]`` + the distance to the leaf centre; at least ``limit``. Where d is finite,
    ``out_v[rows[t]]`` = float32(scale * d) and ``out_a[rows[t]]`` = True."""
    for t in numba.prange(rows.shape[0]):  # each block writes only its own row of ``out``
        b = rows[t]
        buf = np.empty((10, 10, 10))
        ok = np.zeros((10, 10, 10), np.bool_)
        ins = np.zeros((10, 10, 10), np.bool_)
        ci, cj, ck, cv = np.empty(1000), np.empty(1000), np.empty(1000), np.empty(1000)  # the candidates
        term = np.empty(1000)
        # the block and its six face layers: a voxel counts where it is solved and inside
        load_ghosts(vals, active, OWN_ROWS, nbr, FACES6, b, 1, 0.0, buf, ok)
        load_ghosts(inside, inside, OWN_ROWS, nbr, FACES6, b, 1, False, ins, ins)
        for i in range(10):
            for j in range(10):
                for k in range(10):
                    ok[i, j, k] = ok[i, j, k] and ins[i, j, k]
        m = 0
        for i in range(10):
            for j in range(10):
                for k in range(10):
                    if not ok[i, j, k]:
                        continue
                    touch = False
                    for f in range(6):
                        a = i + (f == 1) - (f == 0) - 1
                        bb = j + (f == 3) - (f == 2) - 1
                        c = k + (f == 5) - (f == 4) - 1
                        if 0 <= a < 8 and 0 <= bb < 8 and 0 <= c < 8 and mask[t, a, bb, c]:
                            touch = True
                    if touch:
                        ci[m], cj[m], ck[m] = i - 1, j - 1, k - 1
                        cv[m] = buf[i, j, k] * inv_h
                        m += 1
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if not mask[t, i, j, k]:
                        continue
                    x, y, z = i - 3.5, j - 3.5, k - 3.5  # from the leaf centre
                    best = fallback[t] + math.sqrt(x * x + y * y + z * z)
                    # the terms first, the least after: a loop without the reduction vectorises
                    # (4 square roots at once; 1.32 -> 1.04 s at 1024^3, the same values)
                    for q in range(m):
                        di, dj, dk = i - ci[q], j - cj[q], k - ck[q]
                        term[q] = cv[q] + math.sqrt(di * di + dj * dj + dk * dk)
                    for q in range(m):
                        if term[q] < best:
                            best = term[q]
                    best = max(best, limit)
                    if np.isfinite(best):
                        out_v[b, i, j, k] = np.float32(scale * best)
                        out_a[b, i, j, k] = True


def sample_distance(res: HierarchicalResult, ijk: np.ndarray) -> np.ndarray:
    """Distance (voxel units) at voxel indices from the coarse levels: the finest level whose
    trilinear interpolation is defined there (no fine level: use the fine grid for that)."""
    out = np.full(len(ijk), np.inf)
    for lv in res.levels:
        miss = ~np.isfinite(out)
        if miss.any():
            out[miss] = lv.sample(np.asarray(ijk)[miss])
    return out


def _tile_plan(res: HierarchicalResult):
    """(leaf-tile origins, their values in voxel units, big-tile origins, values, big edge)."""
    l1 = res.levels[0]
    big = res.levels[1] if len(res.levels) > 1 else None
    # level-2 cells without any level-1 node solved on level 1 become one tile each
    if big is not None:
        r = big.cell // l1.cell
        has_fine = np.zeros(big.values.shape, bool)
        a = np.argwhere(l1.solved)
        c = (l1.lat_lo + a) // r - big.lat_lo
        has_fine[tuple(c.T)] = True
        big_cells = np.argwhere(~has_fine)
        big_vals = big.values[tuple(big_cells.T)]
        big_origins = (big.lat_lo + big_cells) * big.cell
    else:
        big_origins, big_vals, r = np.zeros((0, 3), np.int64), np.zeros(0), 1
    # level-1 cells that the fine level did not solve completely and that lie in no big tile
    has_leaf = np.zeros(l1.values.shape, bool)  # cells written as fine leaves
    p = (res.fine.distance.origins >> 3) - l1.lat_lo
    ok = np.all((p >= 0) & (p < np.array(l1.values.shape)), axis=1)
    has_leaf[tuple(p[ok].T)] = True
    cells = np.argwhere(~l1.frozen & ~has_leaf)
    origins = (l1.lat_lo + cells) * l1.cell
    if big is not None and len(big_origins):
        in_big = np.zeros(big.values.shape, bool)
        in_big[tuple(((big_origins // big.cell) - big.lat_lo).T)] = True
        bc = (l1.lat_lo + cells) // r - big.lat_lo
        keep = ~in_big[tuple(bc.T)]
        cells, origins = cells[keep], origins[keep]
    vals = l1.values[tuple(cells.T)]
    miss = ~np.isfinite(vals)
    if miss.any() and big is not None:
        vals[miss] = big.sample(origins[miss] + (l1.cell - 1) / 2)
    return origins, vals, big_origins, big_vals


def hierarchical_blocks(res: HierarchicalResult, signed: bool = True):
    """Fine leaves of the written grid (world units, negative inside when ``signed``): every
    voxel of a fine leaf is active; voxels the fine front did not reach get the trilinear
    value of the coarse levels."""
    dist = res.fine.distance
    h = res.voxel_size
    todo = ~dist.active
    sampled = np.zeros(0)
    if todo.any():
        b, i, j, k = np.nonzero(todo)
        sampled = sample_distance(res, dist.origins[b] + np.stack([i, j, k], 1))
    first = np.concatenate([[0], np.cumsum(todo.reshape(len(todo), -1).sum(axis=1))]).astype(np.int64)
    lo, hi = (np.asarray(a, np.int64) for a in res.domain)
    values = np.empty(dist.values.shape, np.float32)
    active = np.empty(dist.active.shape, np.bool_)
    top = _leaf_values(dist.values, dist.active, res.fine.inside, dist.origins, sampled, first, lo, hi, float(h),
                       bool(signed), values, active)
    bg = float(top.max(initial=0.0))
    _fill_inactive(values, active, np.float32(bg))
    return BlockGrid(h, bg, dist.origins, values, active)


@njit(cache=True, parallel=True)
def _leaf_values(dist, solved, inside, origins, sampled, first, lo, hi, h, signed, values, active):
    """:func:`hierarchical_blocks` in one pass: the fine value (d / h * h, as the NumPy form
    computed it) or the coarse sample (``sampled``: the unsolved voxels in C order, block b's
    from ``first[b]``), negated inside when ``signed``; active where in the domain box and
    finite. Returns each block's largest |value| over its active voxels (the background)."""
    top = np.zeros(dist.shape[0])
    for b in prange(dist.shape[0]):
        n = first[b]
        m = 0.0
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if solved[b, i, j, k]:
                        v = np.float64(dist[b, i, j, k]) / h
                    else:
                        v = sampled[n]
                        n += 1
                    ok = math.isfinite(v) and lo[0] <= origins[b, 0] + i <= hi[0] \
                        and lo[1] <= origins[b, 1] + j <= hi[1] and lo[2] <= origins[b, 2] + k <= hi[2]
                    active[b, i, j, k] = ok
                    if ok:
                        v = v * h
                        if signed and inside[b, i, j, k]:
                            v = -v
                        values[b, i, j, k] = np.float32(v)
                        m = max(m, abs(v))
        top[b] = m
    return top


@njit(cache=True, parallel=True)
def _fill_inactive(values, active, bg):
    """values = bg at the inactive voxels (the background is known only after every block's
    largest active value: :func:`_leaf_values`)."""
    for b in prange(values.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if not active[b, i, j, k]:
                        values[b, i, j, k] = bg


def hierarchical_tiles(res: HierarchicalResult, signed: bool = True, background: float | None = None,
                       ) -> tuple[BlockGrid, list[tuple[np.ndarray, np.ndarray, int]]]:
    """What ONE grid of the solve holds (pipeline.io.vdbgrids.tiled_grid): fine leaves near the
    object (and inside), leaf-sized tiles for level-1 cells, 128^3 tiles for level-2 cells, as
    (leaves, [(origins, values, cell)] big tiles first). World units; negative inside when
    ``signed`` (OpenVDB level-set convention). ``background``: the grid's (default: the largest
    distance stored); every voxel of the domain box is active, so it only shows outside it."""
    blocks = hierarchical_blocks(res, signed)
    h = res.voxel_size
    origins, vals, big_origins, big_vals = _tile_plan(res)
    bg = float(max(blocks.background, np.max(vals * h, initial=0.0), np.max(big_vals * h, initial=0.0))) \
        if background is None else float(background)
    big_cell = res.levels[1].cell if len(res.levels) > 1 else 0
    blocks.background = bg
    res.stats["written"] = {"leaves": int(len(blocks.origins)), "leaf_tiles": int(len(origins)),
                            "big_tiles": int(len(big_origins)),
                            "stored_values": int(len(blocks.origins) * LEAF**3 + len(origins) + len(big_origins))}
    return blocks, [(big_origins, big_vals * h, big_cell), (origins, vals * h, res.levels[0].cell)]


