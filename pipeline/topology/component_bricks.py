"""Components on bricks: Algorithm 1 and the marking of section 4.2 per brick, labels unified.

The components seed's detection (Algorithm 1, adaptive spatial continuation, then the marking
with propagation of section 4.2) is split over bricks: half-open boxes of finest-level cell
indices of the octree. Every kept cell belongs to exactly one brick, the one holding its lowest
corner (its *owner*).

Worker side (:func:`label_brick`): Algorithm 1 visits only the cells that meet the brick, so it
returns the owned cells plus *ghosts*, the coarse inside cells owned by another brick that reach
into this one; a cell's fate (inside, rejected, subdivided) depends on the cell and its ancestors
only, so every cell a brick returns is exactly the cell of the whole-domain pass. The
propagation of section 4.2 then labels the owned cells and the ghosts together (local labels).
The continuation of Algorithm 1 stays inside the brick; the finest cells it would enter in
another brick are sent back as *escaped*.

Driver side (:func:`unify`): the local labels are nodes of a graph whose edges are
 * ghost links: a ghost's local label and its owner's label are one cluster;
 * face pairs across brick planes: a cell whose face lies on an internal brick plane and the
   same-level or coarser cell on the other side (from both sides, so a coarse cell on one side
   meets every finer cell facing it); such pairs never share a brick, every other face pair
   (Figure 1) shares one and was seen by that brick's propagation;
 * escaped cells no brick enumerated (only when the affine bound missed a zero, which the
   continuation exists for): the driver finishes the continuation from them and links each
   to its six face neighbours.
``scipy.sparse.csgraph.connected_components`` merges the nodes; the clusters are renumbered in
scan order (``_scan_order``) and the cells sorted in the whole-domain pass's order (level, inside
before border, then packed key: the subdivision makes every level in key order), so the result
equals ``detect``: same cell set, same labels, same volumes (to rounding of the sums). The
continuation cells are the one exception to the row order: the whole-domain pass appends them
after the subdivided cells in the order it reaches them, here they are in key order among them;
set and labels agree.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pipeline.topology import components as cc

_STAT_SUMS = ("affine_tests", "affine_skipped", "surface_tests", "cells_visited", "continuation_cells",
              "corner_evaluations")


# --- the split -------------------------------------------------------------------------------------


def planes(origin, size: float, depth: int, brick_cells: int, phase=0, region=None) -> list[np.ndarray]:
    """Per axis, the internal brick planes (finest cell indices): ``phase + k * brick_cells``
    strictly inside the region's cell range (the last brick also takes the layer of cells that
    only touch the region's high face, which Algorithm 1 keeps)."""
    n = 1 << depth
    cell = size / n
    origin = np.asarray(origin, float)
    if region is None:
        rlo, rhi = np.zeros(3, np.int64), np.full(3, n, np.int64)
    else:
        rlo = np.clip(np.floor((np.asarray(region[0], float) - origin) / cell + 1e-9), 0, n).astype(np.int64)
        rhi = np.clip(np.ceil((np.asarray(region[1], float) - origin) / cell - 1e-9), 0, n).astype(np.int64)
    step = max(1, int(brick_cells))
    ph = np.broadcast_to(np.asarray(phase, np.int64), (3,)) % step
    out = []
    for a in range(3):
        p = np.arange(ph[a], n, step, dtype=np.int64)
        out.append(p[(p > rlo[a]) & (p < rhi[a])])
    return out


def bricks_of(depth: int, cuts: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The bricks (lo, hi) between the planes, covering the root's finest cells [0, 2**depth)."""
    n = 1 << depth
    edges = [np.concatenate([[0], c, [n]]).astype(np.int64) for c in cuts]
    out = []
    for ijk in np.ndindex(*[len(e) - 1 for e in edges]):
        lo = np.array([edges[a][ijk[a]] for a in range(3)], np.int64)
        hi = np.array([edges[a][ijk[a] + 1] for a in range(3)], np.int64)
        out.append((lo, hi))
    return out


def voxel_bricks(brick_voxels: int, index_min, voxel_size: float, size: float, depth: int) -> tuple[int, np.ndarray]:
    """(brick edge in finest cells, phase) for ``bricks:`` given in voxels: the planes fall on
    the voxel bricks' faces (multiples of ``brick_voxels`` in index space, the VDB leaves) when
    the finest cell is no larger than a voxel, else on the nearest cell face. The octree's origin
    is the face below voxel ``index_min`` (stages.components.octree_frame)."""
    ratio = (size / 2**depth) / voxel_size  # finest cell in voxels, a power of two
    cells = max(1, int(round(brick_voxels / ratio)))
    phase = np.round(((-np.asarray(index_min, np.int64)) % brick_voxels) / ratio).astype(np.int64)
    return cells, phase


# --- the worker ------------------------------------------------------------------------------------


@dataclass
class BrickTask:
    """What a worker needs for one brick besides the model (which :func:`label_brick` gets on its
    own: the stage's workers load it from the job's reference, so model trees are not pickled)."""

    t: float
    origin: np.ndarray
    size: float
    depth: int
    region: tuple | None
    continuation: bool
    lo: np.ndarray
    hi: np.ndarray


@dataclass
class BrickCells:
    """A brick's result, NumPy arrays only: its owned cells with local labels, its ghosts'
    lowest-corner keys with local labels, the escaped continuation cells, the enumeration stats."""

    level: np.ndarray
    coords: np.ndarray
    kind: np.ndarray
    pos_frac: np.ndarray
    labels: np.ndarray  # local labels of the owned cells, 1..count
    count: int
    ghost_keys: np.ndarray
    ghost_labels: np.ndarray
    escaped: np.ndarray
    stats: dict = field(default_factory=dict)


def label_brick(model, task: BrickTask) -> BrickCells:
    """Algorithm 1 on the cells meeting the brick, then the section 4.2 propagation over the
    owned cells and the ghosts (module docstring). On the model's sign proxy, as cc.detect."""
    t0 = time.perf_counter()
    tree, escaped = cc.enumerate_in_brick(model.sign_proxy(), task.origin, task.size, task.depth, task.t, task.region,
                                          task.continuation, (task.lo, task.hi))
    raw, count = cc.mark_union(tree)
    low = tree.coords << (task.depth - tree.level)[:, None]
    own = np.all((low >= task.lo) & (low < task.hi), axis=1)
    st = {k: tree.stats.get(k, 0) for k in _STAT_SUMS}
    st["seconds"] = time.perf_counter() - t0
    return BrickCells(tree.level[own], tree.coords[own], tree.kind[own], tree.pos_frac[own],
                      raw[own].astype(np.int64), int(count), cc.pack(low[~own]), raw[~own].astype(np.int64),
                      escaped, st)


# --- the driver ------------------------------------------------------------------------------------


def detect_bricked(model, origin, size: float, depth: int, brick_cells: int, t: float = 0.0, region=None,
                   continuation: bool = True, phase=0, run_map: Callable | None = None) -> cc.Components:
    """``cc.detect`` split over bricks of ``brick_cells`` finest cells (planes at ``phase`` +
    multiples): :func:`label_brick` on every brick, then :func:`unify`. ``run_map(fn, tasks)``
    returns ``[fn(model, task) for task in tasks]`` in order: inline by default, on the
    executor's workers in the stage (``JobContext.map_with``, each worker loading the model)."""
    origin = np.asarray(origin, float)
    cuts = planes(origin, size, depth, brick_cells, phase, region)
    tasks = [BrickTask(t, origin, float(size), depth, region, continuation, lo, hi)
             for lo, hi in bricks_of(depth, cuts)]
    parts = (run_map or (lambda fn, xs: [fn(model, x) for x in xs]))(label_brick, tasks)
    return unify(parts, cuts, model.sign_proxy(), origin, size, depth, t, region)


def unify(parts: list[BrickCells], cuts: list[np.ndarray], model, origin, size: float, depth: int,
          t: float = 0.0, region=None) -> cc.Components:
    """Merge the bricks' cells and unify their local labels (module docstring)."""
    t0 = time.perf_counter()
    origin = np.asarray(origin, float)
    rlo, rhi = (np.full(3, -np.inf), np.full(3, np.inf)) if region is None else map(np.asarray, region)
    offsets = np.concatenate([[0], np.cumsum([p.count for p in parts])]).astype(np.int64)
    level = np.concatenate([p.level for p in parts]).astype(np.int64)
    coords = np.concatenate([p.coords for p in parts]).reshape(-1, 3).astype(np.int64)
    kind = np.concatenate([p.kind for p in parts]).astype(np.int8)
    frac = np.concatenate([p.pos_frac for p in parts]).astype(np.float64)
    node = np.concatenate([p.labels - 1 + offsets[i] for i, p in enumerate(parts)]).astype(np.int64)
    nodes = int(offsets[-1])
    edges_a, edges_b = [], []
    st = {k: int(sum(p.stats.get(k, 0) for p in parts)) for k in _STAT_SUMS}

    # escaped continuation cells that no brick enumerated: finish Algorithm 1's continuation here
    fix = _finish_continuation(parts, level, coords, model, origin, size, depth, t, (rlo, rhi), st)
    if len(fix[0]):
        fc, fk, ff = fix
        level = np.concatenate([level, np.full(len(fc), depth)])
        coords = np.concatenate([coords, fc])
        kind = np.concatenate([kind, fk])
        frac = np.concatenate([frac, ff])
        node = np.concatenate([node, nodes + np.arange(len(fc))])
        nodes += len(fc)

    low = coords << (depth - level)[:, None]
    key = cc.pack(low)
    # ghost links: a ghost is one of the owner brick's coarse cells
    coarse = np.nonzero(level < depth)[0]
    ckeys = key[coarse]
    corder = np.argsort(ckeys)
    ghosts = 0
    for i, p in enumerate(parts):
        if len(p.ghost_keys) == 0:
            continue
        pos = np.searchsorted(ckeys, p.ghost_keys, sorter=corder)
        rows = coarse[corder[np.minimum(pos, len(corder) - 1)]]
        if len(corder) == 0 or not np.all(key[rows] == p.ghost_keys):
            raise RuntimeError("a ghost cell has no owner brick (bricks disagree on Algorithm 1)")
        edges_a.append(p.ghost_labels - 1 + offsets[i]), edges_b.append(node[rows])
        ghosts += len(rows)

    # face pairs across the brick planes
    ra, rb = _plane_pairs(level, coords, low, cuts, origin, size, depth)
    edges_a.append(node[ra]), edges_b.append(node[rb])
    if len(fix[0]):
        fa, fb = _fix_pairs(level, coords, kind, frac, origin, size, depth, len(fix[0]))
        edges_a.append(node[fa]), edges_b.append(node[fb])

    ea = np.concatenate(edges_a) if edges_a else np.zeros(0, np.int64)
    eb = np.concatenate(edges_b) if edges_b else np.zeros(0, np.int64)
    if nodes:
        graph = coo_matrix((np.ones(len(ea), np.int8), (ea, eb)), shape=(nodes, nodes))
        _, comp = connected_components(graph, directed=False)
        used, raw = np.unique(comp[node], return_inverse=True)
        count = len(used)
        raw = raw.reshape(-1).astype(np.int64) + 1
    else:
        count, raw = 0, np.zeros(0, np.int64)

    order = np.lexsort((cc.pack(coords), kind, level))  # the whole-domain pass's row order
    tree = cc.Octree(origin, float(size), depth, level[order], coords[order], kind[order], frac[order], st)
    st["inside_cells"] = int((tree.kind == cc.INSIDE).sum())
    st["border_cells"] = int((tree.kind == cc.BORDER).sum())
    labels = cc._scan_order(tree, raw[order], count)
    merge = time.perf_counter() - t0
    st["bricked"] = {"bricks": len(parts), "local_clusters": int(offsets[-1]), "ghost_links": ghosts,
                    "cross_face_pairs": int(len(ra)), "cross_face_unions": int(nodes - count),
                    "driver_cells": int(len(fix[0])),
                    "worker_seconds": round(float(sum(p.stats.get("seconds", 0.0) for p in parts)), 4),
                    "merge_seconds": round(merge, 4)}
    st["seconds"] = st["bricked"]["worker_seconds"]
    return cc.summarise(tree, labels, count, t0)


def _plane_pairs(level, coords, low, cuts, origin, size, depth) -> tuple[np.ndarray, np.ndarray]:
    """Rows (a, b) of face-adjacent cells on the two sides of an internal brick plane: from each
    cell whose face lies on a plane, the same-level or coarser cell across it. That cell's face
    lies on the plane too (it cannot reach below it without holding the querying cell), so the
    lookup only needs the cells touching the planes."""
    span = 1 << (depth - level)
    above = [np.isin(low[:, a], cuts[a]) for a in range(3)]
    below = [np.isin(low[:, a] + span, cuts[a]) for a in range(3)]
    touch = np.nonzero(np.any(above + below, axis=0))[0] if len(level) else np.zeros(0, np.int64)
    if len(touch) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    sub = cc.Octree(origin, float(size), depth, level[touch], coords[touch], np.zeros(len(touch), np.int8),
                    np.zeros(len(touch)))
    out_a, out_b = [], []
    for a in range(3):
        e = np.zeros(3, np.int64)
        e[a] = 1
        for side, d in ((below[a][touch], e), (above[a][touch], -e)):
            for lv in np.unique(level[touch][side]):
                sel = np.nonzero(side & (level[touch] == lv))[0]
                nb = sub.find(int(lv), coords[touch[sel]] + d)
                ok = nb >= 0
                out_a.append(touch[sel[ok]]), out_b.append(touch[nb[ok]])
    return np.concatenate(out_a), np.concatenate(out_b)


def _finish_continuation(parts, level, coords, model, origin, size, depth, t, region, st):
    """Escaped cells not enumerated by their own brick start the continuation again here, over
    the merged cells (Algorithm 1: enumerate until no new cell holds a sign-changing edge)."""
    none = (np.zeros((0, 3), np.int64), np.zeros(0, np.int8), np.zeros(0))
    esc = [p.escaped for p in parts if len(p.escaped)]
    if not esc:
        return none
    cand = cc._unique_rows(np.concatenate(esc))
    have = np.sort(cc.pack(coords[level == depth]))
    pos = np.minimum(np.searchsorted(have, cc.pack(cand)), max(len(have) - 1, 0))
    missing = cand[~((have[pos] == cc.pack(cand)) if len(have) else np.zeros(len(cand), bool))]
    if len(missing) == 0:
        return none
    cache = cc._CornerCache(model, origin, size / 2**depth, t)
    signs = cc._corner_signs(cache, missing, 1)
    have = np.sort(np.concatenate([have, cc.pack(missing)]))
    sub = {"continuation_cells": 0}
    cells, signs, _ = cc._continuation(missing, signs, cache, depth, origin, size, region, sub, have=have)
    st["continuation_cells"] += len(missing) + sub["continuation_cells"]
    st["corner_evaluations"] += cache.evaluations
    _, c, k, f = cc._with_finest(cc.no_cells(), (cells, signs), depth)  # inside, then border cells
    return c, k, f


def _fix_pairs(level, coords, kind, frac, origin, size, depth, n_fix) -> tuple[np.ndarray, np.ndarray]:
    """Face pairs of the driver's continuation cells (the last ``n_fix`` rows, all finest)."""
    tree = cc.Octree(origin, float(size), depth, level, coords, kind, frac)
    rows = np.arange(len(level) - n_fix, len(level))
    out_a, out_b = [], []
    for d in cc._FACES:
        nb = tree.find(depth, coords[rows] + d)
        ok = nb >= 0
        out_a.append(rows[ok]), out_b.append(nb[ok])
    return np.concatenate(out_a), np.concatenate(out_b)
