"""Sparse voxelisation: affine-arithmetic cell enumeration aligned with OpenVDB's tree.

components seed, section 3.2: a cell whose affine range excludes 0 cannot hold the surface.
`enumerate_cells` subdivides the domain top-down in cells of 2^k voxels (aligned with VDB
internal and leaf nodes) and bounds *all cells of a level in one vectorised call*:

* cells whose bound is > 0 are inside: they become inactive tiles holding +background;
* cells whose bound is < 0 are outside: dropped;
* the rest are subdivided down to ``block`` voxels (<= the 8^3 leaf), and only those blocks are
  evaluated voxel by voxel.

Each cell is bounded over its box dilated by ceil(band) voxels (at least 1: band.cull_pad_voxels),
so every voxel nearer than band voxels to the zero set lies in an evaluated block (the narrow
band is never cut by culling), and a culled cell has the sign of its proof on the face
neighbours of its voxels too.

The band is marked once the evaluated blocks are in their 8^3 leaves (:func:`pipeline.voxel.band.mark_band`,
passes over the leaves reading their neighbours across block and leaf borders): a voxel is
active when its sign (of the float32 value the grid stores) differs from a face neighbour's, or
when it lies within ceil(band) - 1 voxels of such a voxel and its first-order distance estimate
|f| / |grad f| is at most ``band`` voxels. The band does not depend on the block size the
evaluation used.

**The band is closed by construction** (issue 12): since a culled voxel cannot differ in sign
from its neighbours (its proof covers them), no inactive voxel is next to a sign change, so the
sign of every inactive region is that of the band around it and
OpenVDB's signedFloodFill (scan lines and tile neighbours) cannot leak.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from numba import prange

from pipeline.model.base import Node
from pipeline.model.tape import (
    Tape,
    TapePool,
    bound_cull_decide,
    compile_model,
    eval_blocks,
    eval_leaves,
    first_nonfinite,
    specialise,
)
from pipeline.sparse.blockwrite import mapped_empty
from pipeline.sparse.grid import LEAF, LEAF_LOG2, BlockGrid, max_abs_active, pack_keys
from pipeline.util.jit import njit
from pipeline.voxel.band import cull_pad_voxels, mark_band, reach_bits

BOUND_CHUNK = 200_000  # boxes per affine call at most (memory ~ 100 bytes x ops x boxes)
EVAL_CHUNK = 1 << 20  # points per evaluation call at most
WORK_BYTES = 768 << 20  # working set of one bound / evaluation call, whatever the model's size
USE_TAPE = True  # compiled, per-cell specialised tapes where the model lowers to one
StopAfter = Callable[[int, int], bool]  # (cell size, ambiguous cells of the level) -> end the descent
FINITE_LIMIT = 1e30  # |values| beyond are clamped before the float32 grid (its max is 3.4e38)


class NonFiniteField(ValueError):
    """The model evaluated to NaN or infinity at ``point``."""

    def __init__(self, point: np.ndarray):
        super().__init__(f"field is not finite at ({point[0]:g}, {point[1]:g}, {point[2]:g})")
        self.point = point

    def __reduce__(self):  # travels back from worker processes intact
        return (NonFiniteField, (self.point,))


@dataclass
class CellLevels:
    """Result of the enumeration, all in index space (voxel coordinates)."""

    blocks: np.ndarray  # (N,3) origins of blocks to evaluate
    block: int
    inside: list[tuple[np.ndarray, int]] = field(default_factory=list)  # (origins, size) per level
    outside: list[tuple[np.ndarray, int]] = field(default_factory=list)  # cells proven outside
    stats: dict = field(default_factory=dict)


def root_size_for(dims: np.ndarray, block: int) -> int:
    """Size of the top-level cells: a power of two >= the domain (at most an upper internal node)."""
    size = max(block, LEAF)
    while size < dims.max() and size < 4096:
        size *= 2
    return size


def enumerate_cells_tape(tape: Tape, imin: np.ndarray, imax: np.ndarray, h: float, band: float, block: int,
                         progress: Callable[[str], None] | None = None, root_size: int | None = None,
                         clip: tuple[np.ndarray, np.ndarray] | None = None, stop_size: int | None = None,
                         stop_after: StopAfter | None = None) -> tuple[CellLevels, TapePool]:
    """:func:`enumerate_cells` on the compiled model with per-cell specialisation: every cell
    is bounded with its parent's shortened tape and passes its own shortened tape to its children
    (pipeline.model.tape). Same cells, same dilation; interval instead of affine bounds. Returns the
    levels and the tapes of the blocks (tape i for block i; of the last level's ambiguous cells
    when ``stop_size`` or ``stop_after`` ends the descent early)."""
    dims = imax - imin + 1
    size = root_size or root_size_for(dims, block)
    lo_c, hi_c = (imin, imax) if clip is None else (np.maximum(imin, clip[0]), np.minimum(imax, clip[1]))
    start = (lo_c // size) * size
    counts = ((hi_c - start) // size) + 1
    cells = start + np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3) * size
    pool, tape_of = TapePool.single(tape), np.zeros(len(cells), np.int64)
    pad = cull_pad_voxels(band) * h
    out = CellLevels(np.zeros((0, 3), np.int64), block)
    st = {"cells_visited": 0, "cells_culled_inside": 0, "cells_culled_outside": 0, "levels": [],
          "tape_clauses": int(len(tape))}
    while len(cells):
        lo, hi = _clip_boxes(cells, size, imin, imax)
        # Culling: the box dilated by the band. The shortened tape of a cell is decided on a
        # smaller box (much shorter tapes than the band-dilated one gives). A block's tape is only
        # evaluated at its own voxel centres (all of them, those past the domain's edge too: the
        # band's stencil reads them). Above, the cell's box grown by one voxel: the tape is then
        # the model itself at every voxel of the cell and at their neighbours, so a child holding
        # one side of a sign change between neighbouring voxels always has its zero inside its
        # dilated box and is never culled (the band is closed by construction; a tape decided on
        # the cell alone could hide it). Both in one pass (tape.bound_cull_decide).
        grow = 0 if size <= block else 1
        dlo, dhi = (cells - grow) * h, (cells + size - 1 + grow) * h
        flo, fhi, (choff, choices) = _bound_level(pool, tape_of, lo * h - pad, hi * h + pad, dlo, dhi)
        keep = _cull_level(out, st, cells, size, flo, fhi, progress)
        pool = pool.with_arrays(specialise(keep.astype(np.int64), tape_of, *pool.arrays(), choff, choices))
        st["levels"][-1]["mean_tape"] = round(float(pool.length.mean()), 2) if len(keep) else 0.0
        amb = cells[keep]
        if size <= max(block, stop_size or 0) or (stop_after is not None and stop_after(size, len(amb))):
            out.blocks = amb
            break
        size //= 2
        cells, tape_of = _children(amb, size, lo_c, hi_c, parents=True)
    out.stats = st
    return out, pool


def _bound_level(pool: TapePool, tape_of: np.ndarray, blo: np.ndarray, bhi: np.ndarray, dlo: np.ndarray,
                 dhi: np.ndarray):
    """Interval bounds of each box (blo..bhi) with its tape, and for the boxes not culled the
    min/max decisions over their decision boxes dlo..dhi (offsets, choices)."""
    choff, choices = pool.decision_arrays(tape_of)
    if len(tape_of) == 0:
        return np.zeros(0), np.zeros(0), (choff, choices)
    f64 = partial(np.ascontiguousarray, dtype=np.float64)
    flo, fhi = bound_cull_decide(f64(blo), f64(bhi), f64(dlo), f64(dhi), tape_of, *pool.arrays(),
                                 *pool.oracle.arrays(), int(pool.length[tape_of].max()), choff, choices)
    return flo, fhi, (choff, choices)


def _clip_boxes(origins: np.ndarray, size: int, imin: np.ndarray, imax: np.ndarray):
    lo = np.maximum(origins, imin)
    hi = np.minimum(origins + size - 1, imax)
    return lo, hi


def model_weight(model: Node) -> int:
    """How many arrays one evaluation of the model keeps alive at once, at most: its nodes (an
    n-ary node holds all its children's results) plus a formula's operations."""
    n = 0
    for node in model.walk():
        formula = getattr(node.params, "formula", None)
        n += 1 + (len(formula) // 2 if isinstance(formula, str) else 0)  # <= one operation per 2 characters
    return n


def chunk_for(model: Node, bytes_per_item: int, cap: int) -> int:
    """Items (boxes, points) per call so that the call's working set stays within WORK_BYTES."""
    return int(max(256, min(cap, WORK_BYTES // (bytes_per_item * model_weight(model)))))


def bound_cells(model: Node, lo_idx: np.ndarray, hi_idx: np.ndarray, h: float, pad: float, t: float):
    """Affine bounds of the model over index boxes (voxel centres lo..hi) dilated by ``pad``."""
    flo = np.empty(len(lo_idx))
    fhi = np.empty(len(lo_idx))
    chunk = chunk_for(model, 2 * 48, BOUND_CHUNK)  # an affine form: 6 float64 per box, ~2 alive per node
    for s in range(0, len(lo_idx), chunk):
        e = s + chunk
        a, b = model.bound(lo_idx[s:e] * h - pad, hi_idx[s:e] * h + pad, t)
        flo[s:e], fhi[s:e] = a, b
    return flo, fhi


def enumerate_cells(model: Node, imin: np.ndarray, imax: np.ndarray, h: float, band: float,
                    block: int, t: float = 0.0, stop_size: int | None = None,
                    progress: Callable[[str], None] | None = None, root_size: int | None = None,
                    clip: tuple[np.ndarray, np.ndarray] | None = None,
                    stop_after: StopAfter | None = None) -> CellLevels:
    """Top-down affine subdivision of the index box imin..imax (components seed, section 3.2).

    Returns the blocks (size ``block``) that may hold voxels within the band, and the cells
    proven inside at every level. ``stop_size`` ends the descent early (for estimates), and so
    does ``stop_after(size, ambiguous cells)`` when it returns True after a level (the blocks are
    then that level's ambiguous cells).
    ``clip`` restricts the work to a brick of the domain while keeping the cells (and hence
    the bounds) of the whole-domain run: a bricked run finds exactly the same blocks.
    """
    dims = imax - imin + 1
    size = root_size or root_size_for(dims, block)
    lo_c, hi_c = (imin, imax) if clip is None else (np.maximum(imin, clip[0]), np.minimum(imax, clip[1]))
    start = (lo_c // size) * size
    counts = ((hi_c - start) // size) + 1
    grid = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    cells = start + grid * size
    pad = cull_pad_voxels(band) * h  # >= one voxel: a culled cell's sign holds on its voxels' neighbours
    out = CellLevels(np.zeros((0, 3), np.int64), block)
    st = {"cells_visited": 0, "cells_culled_inside": 0, "cells_culled_outside": 0, "levels": []}
    stop = block if stop_size is None else max(block, stop_size)
    while len(cells):
        lo, hi = _clip_boxes(cells, size, imin, imax)
        flo, fhi = bound_cells(model, lo, hi, h, pad, t)
        amb = cells[_cull_level(out, st, cells, size, flo, fhi, progress)]
        if size <= stop or (stop_after is not None and stop_after(size, len(amb))):
            out.blocks = amb
            break
        size //= 2
        cells = _children(amb, size, lo_c, hi_c)
    out.stats = st
    return out


def _cull_level(out: CellLevels, st: dict, cells: np.ndarray, size: int, flo: np.ndarray, fhi: np.ndarray,
                progress: Callable[[str], None] | None) -> np.ndarray:
    """One level of the descent (both evaluators): cells whose bound is > 0 are recorded inside,
    < 0 outside, the statistics counted; returns the indices of the ambiguous cells."""
    inside, outside = flo > 0, fhi < 0
    keep = np.flatnonzero(~(inside | outside))
    st["cells_visited"] += len(cells)
    st["cells_culled_inside"] += int(inside.sum())
    st["cells_culled_outside"] += int(outside.sum())
    st["levels"].append({"size": size, "cells": len(cells), "ambiguous": int(len(keep))})
    if progress:
        progress(f"level {size}: {len(cells)} cells")
    if inside.any():
        out.inside.append((cells[inside], size))
    if outside.any():
        out.outside.append((cells[outside], size))
    return keep


def _children(cells: np.ndarray, size: int, imin: np.ndarray, imax: np.ndarray, parents: bool = False):
    """The 8 children of every cell, without those entirely outside the index box (and, with
    ``parents``, the index of each child's parent)."""
    offs = np.stack(np.meshgrid([0, size], [0, size], [0, size], indexing="ij"), -1).reshape(-1, 3)
    kids = (cells[:, None, :] + offs[None, :, :]).reshape(-1, 3)
    keep = np.all(kids <= imax, axis=1) & np.all(kids + size - 1 >= imin, axis=1)
    if parents:
        return kids[keep], np.repeat(np.arange(len(cells)), 8)[keep]
    return kids[keep]


def evaluate_blocks(model: Node, origins: np.ndarray, block: int, h: float, t: float) -> np.ndarray:
    """Field values at the voxel centres of every block: (N, b, b, b) float64."""
    b = block
    r = np.arange(b)
    out = np.empty((len(origins), b, b, b))
    per = max(1, chunk_for(model, 3 * 8, EVAL_CHUNK) // (b * b * b))
    for s in range(0, len(origins), per):
        o = origins[s:s + per]
        x = ((o[:, 0, None, None, None] + r[None, :, None, None]) * h)
        y = ((o[:, 1, None, None, None] + r[None, None, :, None]) * h)
        z = ((o[:, 2, None, None, None] + r[None, None, None, :]) * h)
        x, y, z = np.broadcast_arrays(x, y, z)
        out[s:s + per] = model.evaluate_xyz(x, y, z, t)
    return out


@dataclass
class Voxelised:
    blocks: BlockGrid  # leaf blocks: evaluated values (+-background where not evaluated), band mask
    inside_boxes: np.ndarray  # (K,2,3) index boxes proven inside (inclusive corners)
    stats: dict
    outside_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.int64))  # not in a leaf


@dataclass
class BlockSamples:
    """Evaluated blocks of one domain or brick, before assembly into leaves (picklable)."""

    blocks: np.ndarray  # (N,3) block origins
    values: np.ndarray  # (N,b,b,b) float64 field values
    valid: np.ndarray  # (N,b,b,b) inside the domain
    inside: list  # [(origins, size)] cells proven inside, per level
    stats: dict
    outside: list = field(default_factory=list)  # [(origins, size)] cells proven outside


def sample_blocks(model: Node, imin: np.ndarray, imax: np.ndarray, h: float, band: float = 3.0,
                  block: int = 4, t: float = 0.0, progress: Callable[[str], None] | None = None,
                  root_size: int | None = None, clip: tuple[np.ndarray, np.ndarray] | None = None) -> BlockSamples:
    """Enumerate and evaluate the blocks of the domain (or of one brick of it); the band is
    marked once the blocks are in their leaves (:func:`mark_band`, in :func:`assemble`).

    A model that lowers to a tape (pipeline.model.tape) is enumerated and evaluated with per-cell
    specialised tapes; one with an untraceable node (mesh, grid, hfrep, component oracles)
    with the node-by-node affine bounds and NumPy evaluation."""
    t0 = time.perf_counter()
    tape = compile_model(model, t) if USE_TAPE else None
    if tape is not None:
        levels, pool = enumerate_cells_tape(tape, imin, imax, h, band, block, progress, root_size, clip)
        blocks = levels.blocks
        t1 = time.perf_counter()
        vals = eval_blocks(blocks, block, float(h), np.arange(len(blocks), dtype=np.int64), *pool.arrays(),
                           *pool.oracle.arrays(), int(pool.length.max()) if len(blocks) else 1)
    else:
        levels = enumerate_cells(model, imin, imax, h, band, block, t, progress=progress, root_size=root_size,
                                 clip=clip)
        blocks = levels.blocks
        t1 = time.perf_counter()
        vals = evaluate_blocks(model, blocks, block, h, t)
    t2 = time.perf_counter()
    levels.stats["evaluator"] = "tape" if tape is not None else "nodes"
    levels.stats["enumerate_seconds"] = round(t1 - t0, 4)  # tracing, culling and specialisation
    levels.stats["evaluate_seconds"] = round(t2 - t1, 4)  # values of the blocks' voxels
    valid = _in_domain(blocks, block, imin, imax)
    bad = first_nonfinite(vals, valid)
    if bad >= 0:
        n, i, j, k = np.unravel_index(bad, vals.shape)
        raise NonFiniteField((blocks[n] + (i, j, k)) * h)
    if progress:
        progress(f"evaluated {len(blocks)} blocks")
    return BlockSamples(blocks, vals, valid, levels.inside, levels.stats, levels.outside)


def merge_samples(parts: list[BlockSamples]) -> BlockSamples:
    """Concatenate the samples of bricks (disjoint by construction) into one."""
    if len(parts) == 1:
        return parts[0]
    cat = [np.concatenate([getattr(p, k) for p in parts]) for k in ("blocks", "values", "valid")]
    keys = ("cells_visited", "cells_culled_inside", "cells_culled_outside", "enumerate_seconds", "evaluate_seconds")
    stats = {k: sum(p.stats[k] for p in parts) for k in keys}
    stats["bricks"] = len(parts)
    return BlockSamples(*cat, [lv for p in parts for lv in p.inside], stats, [lv for p in parts for lv in p.outside])


def assemble(s: BlockSamples, imin: np.ndarray, imax: np.ndarray, h: float, band: float,
             refine: Refine | None = None) -> Voxelised:
    """Leaves, inside boxes and statistics from the evaluated blocks; the band is closed
    (:func:`mark_band`) and every value is finite (clamped to +-FINITE_LIMIT, counted).
    ``refine``: the blocks hold a sign proxy's values (:func:`exact_in_reach`)."""
    block = s.values.shape[1] if len(s.values) else 4
    vals = s.values
    clamped = _count_beyond(vals, s.valid, FINITE_LIMIT)
    if clamped:
        vals = np.clip(vals, -FINITE_LIMIT, FINITE_LIMIT)
    grid, known = _assemble_leaves(s.blocks, block, vals, s.valid, s.inside, h, 1.0)
    stats = dict(s.stats)
    stats.update({"block": int(block), "blocks_evaluated": int(len(s.blocks)), "voxels_evaluated": int(s.valid.sum())})
    return _finish(grid, known, s.inside, s.outside, stats, clamped, imin, imax, h, band, refine)


def _finish(grid: BlockGrid, known: np.ndarray, inside: list, outside: list, stats: dict, clamped: int,
            imin: np.ndarray, imax: np.ndarray, h: float, band: float, refine: Refine | None = None) -> Voxelised:
    """The leaves' band marked, background and proxies set, the proven boxes and the statistics."""
    if refine is not None:
        more, extra = refine(grid, known, band)
        stats.update(more)
        clamped += extra
    added = mark_band(grid, known, band)
    # from the float32 values the grid stores, so bricked (float32 transfer) and unsplit runs agree
    bg = _background(grid.values, grid.active, band, h)
    _set_proxies(grid.values, known, np.float32(bg))
    grid.background = -bg
    inside_boxes = _inside_boxes(inside, imin, imax)
    outside_boxes = _outside_leaves(grid, _inside_boxes(outside, imin, imax))
    stats.update({
        "active_voxels": int(grid.active.sum()),
        "activated_by_sign": int(added),
        "values_clamped": int(clamped),
        "leaves": int(len(grid.origins)),
        "inside_tiles": int(len(inside_boxes)),
        "background": float(bg),
    })
    return Voxelised(grid, inside_boxes, stats, outside_boxes)


def voxelise_tape(tape: Tape, imin: np.ndarray, imax: np.ndarray, h: float, band: float = 3.0, block: int = 4,
                  progress: Callable[[str], None] | None = None, t0: float | None = None,
                  refine: Refine | None = None) -> Voxelised:
    """:func:`assemble` of :func:`sample_blocks` for a model that lowers to a tape, without the
    blocks' arrays: the blocks are evaluated and written into their leaves by one
    compiled pass over the leaves (tape.eval_leaves; at 1024^3 the demo's blocks held 0.4 GB
    of float64 values and 0.1 GB of band and domain masks, then scattered). The same grid, boxes
    and statistics; ``evaluate_seconds`` then includes the scatter."""
    t0 = time.perf_counter() if t0 is None else t0
    imin, imax = np.asarray(imin, np.int64), np.asarray(imax, np.int64)
    levels, pool = enumerate_cells_tape(tape, imin, imax, h, band, block, progress)
    blocks = levels.blocks
    t1 = time.perf_counter()
    if len(blocks) == 0:
        grid, known = BlockGrid(h, -1.0), np.zeros((0, LEAF, LEAF, LEAF), bool)
        bad, clamped, nvalid = -1, 0, 0
    else:
        leaf_of = (blocks >> LEAF_LOG2) << LEAF_LOG2
        keys = pack_keys(leaf_of)
        order = np.argsort(keys, kind="stable")
        sk = keys[order]
        first = np.flatnonzero(np.concatenate([[True], sk[1:] != sk[:-1]]))
        L = len(first)
        values = mapped_empty((L, LEAF, LEAF, LEAF), np.float32)
        known = mapped_empty((L, LEAF, LEAF, LEAF), bool)
        lstart = np.append(first, len(blocks)).astype(np.int64)
        bad, clamped, nvalid = eval_leaves(
            blocks, block, float(h), np.arange(len(blocks), dtype=np.int64), *pool.arrays(), *pool.oracle.arrays(),
            int(pool.length.max()), lstart, order.astype(np.int64), imin, imax, FINITE_LIMIT,
            np.float32(-1.0), values, known)
        if bad < 0:
            _fill_inside_cells(values, sk[first], levels.inside, 1.0)
            act = mapped_empty((L, LEAF, LEAF, LEAF), bool)  # every flag is set by mark_band
            grid = BlockGrid(h, -1.0, leaf_of[order[first]], values, act)  # sorted keys: rows stay valid
    t2 = time.perf_counter()
    levels.stats["evaluator"] = "tape"
    levels.stats["enumerate_seconds"] = round(t1 - t0, 4)
    levels.stats["evaluate_seconds"] = round(t2 - t1, 4)
    if bad >= 0:
        n, i, j, k = np.unravel_index(bad, (len(blocks), block, block, block))
        raise NonFiniteField((blocks[n] + (i, j, k)) * h)
    if progress:
        progress(f"evaluated {len(blocks)} blocks")
    stats = dict(levels.stats)
    stats.update({"block": int(block), "blocks_evaluated": int(len(blocks)), "voxels_evaluated": int(nvalid)})
    return _finish(grid, known, levels.inside, levels.outside, stats, clamped, imin, imax, h, band, refine)


def _outside_leaves(grid: BlockGrid, boxes: np.ndarray) -> np.ndarray:
    """Boxes proven outside that lie in no leaf of the grid (a leaf carries its own signs)."""
    if len(boxes) == 0 or len(grid.origins) == 0:
        return boxes
    leaf = (boxes[:, 0] >> LEAF_LOG2) << LEAF_LOG2
    sub = np.all((boxes[:, 1] >> LEAF_LOG2) << LEAF_LOG2 == leaf, axis=1)
    in_leaf = sub & (grid.block_index(leaf) >= 0)
    return boxes[~in_leaf]


@njit(cache=True)
def _set_proxies(values, known, bg):
    """Voxels of the leaves that were not evaluated hold +-bg with the sign of their cell's proof."""
    flat_v = values.reshape(-1)
    flat_k = known.reshape(-1)
    for n in range(flat_v.size):
        if not flat_k[n]:
            flat_v[n] = bg if flat_v[n] > 0 else -bg


def block_for(model: Node, block: int | str = "auto", h: float | None = None) -> int:
    """The edge of the evaluated blocks: ``block`` itself, or for ``"auto"`` 8 when every node
    of the model is a formula the tape records, 4 when one is an oracle (a mesh, a grid, a
    solved field: ``Node.oracle``) or without the tape, 2 when a mesh at voxel size ``h`` has
    more than DENSE_MESH faces per 4 x 4 voxels of its surface; from the node types and the
    meshes' face counts and areas, nothing is traced.

    With 8, a block is one leaf: the octree stops a level earlier (at 512^3 the demo's
    enumeration took 0.13 s with 4 and 0.025 s with 8), and a clause of one coordinate runs 8
    times per 512 voxels (:data:`pipeline.model.tape.SEPARABLE`); more voxels are evaluated
    (+24 % for the demo) but the stage was 1.3-2.3x faster for every FRep model measured
    (docs/performance.md, session 22). A mesh clause costs more per voxel, and there 4 was
    2-12 % faster; the other oracles run node by node in NumPy, where evaluation dominates.
    A block's mesh clause runs the part of the tree its bounds leave, so a mesh finer than the
    voxels makes every voxel pay for the faces of a larger block: for a 1.3M-face mesh at
    256^3 (~145 faces per 4 x 4 voxels) blocks of 2 took the stage from 17.9-18.9 s to 12.6 s,
    at 512^3 (~36) 13.2 -> 12.0 s; 327k faces at 256^3 (~36): the same; 82k faces (~9): 0.7 ->
    1.4 s, and every CGAL mesh 2-4x slower with 2."""
    if block != "auto":
        return int(block)
    if not USE_TAPE or any(node.oracle for node in model.walk()):
        dense = max((getattr(node, "faces_per_area", 0.0) for node in model.walk()), default=0.0)
        return 2 if h is not None and dense * (4.0 * h) ** 2 > DENSE_MESH else 4
    return 8


DENSE_MESH = 100.0  # faces per 4 x 4 voxels of a mesh's surface above which blocks of 2 pay


def voxelise(model: Node, imin: np.ndarray, imax: np.ndarray, h: float, band: float = 3.0,
             block: int = 4, t: float = 0.0, progress: Callable[[str], None] | None = None) -> Voxelised:
    """Voxelise ``model`` over the index box imin..imax: sparse narrow band plus inside tiles."""
    t0 = time.perf_counter()
    work, tape = _working_model(model, t)
    # the blocks from the sign proxy, the model's values in the reach
    refine = exact_in_reach(model, h, t) if work is not model else None
    if tape is not None:
        return voxelise_tape(tape, imin, imax, h, band, block, progress, t0, refine)
    return assemble(sample_blocks(work, imin, imax, h, band, block, t, progress), imin, imax, h, band, refine)


def _working_model(model: Node, t: float) -> tuple[Node, Tape | None]:
    """What :func:`voxelise` enumerates and evaluates the blocks with, and its tape (None where it
    does not lower to one): the model, or its sign proxy where the model has no tape of its own
    and a cheaper proxy (an r0 or sardf mesh)."""
    tape = compile_model(model, t) if USE_TAPE else None
    if tape is None and model.sign_proxy() is not model:
        model = model.sign_proxy()
        tape = compile_model(model, t) if USE_TAPE else None
    return model, tape


Refine = Callable[[BlockGrid, np.ndarray, float], tuple[dict, int]]


def exact_in_reach(model: Node, h: float, t: float) -> Refine | None:
    """For a model with a cheaper sign proxy (:meth:`pipeline.model.base.Node.sign_proxy`: an r0
    or sardf mesh, whose every voxel walks the whole BSP-tree): the step that puts the model's
    own values where the band reads them. The blocks are enumerated and evaluated with the
    proxy, which has the same sign, so S (the sign changes) and its reach are the model's; only
    the voxels of the reach are evaluated with the model (about a third of the blocks' voxels
    at a band of 3). None when the model is its own proxy."""
    if model.sign_proxy() is model:
        return None
    return partial(_evaluate_reach, model, float(h), float(t))


def _evaluate_reach(model: Node, h: float, t: float, grid: BlockGrid, known: np.ndarray,
                    band: float) -> tuple[dict, int]:
    """The model's values at the voxels of S's reach, again until the reach of the stored signs
    holds no proxy value (a sign the proxy and the model round differently, at a value within
    rounding of 0, can move S by a voxel). Returns statistics and the count of clamped values."""
    t0 = time.perf_counter()
    exact = np.zeros((len(grid.origins), LEAF, LEAF), np.uint8)
    per = chunk_for(model, 3 * 8, EVAL_CHUNK)
    count = rounds = clamped = 0
    while True:
        need = reach_bits(grid, known, band) & ~exact
        if not need.any():
            break
        rounds += 1
        exact |= need
        for lo in range(0, len(need), LEAVES_PER_PASS):  # bounds the unpacked masks' memory
            idx = lo * LEAF ** 3 + np.flatnonzero(np.unpackbits(need[lo:lo + LEAVES_PER_PASS].reshape(-1),
                                                               bitorder="little"))
            for s in range(0, len(idx), per):
                clamped += _evaluate_voxels(model, grid, idx[s:s + per], h, t)
            count += len(idx)
    return {"sign_proxy": True, "exact_voxels": count, "exact_rounds": rounds,
            "exact_seconds": round(time.perf_counter() - t0, 4)}, clamped


LEAVES_PER_PASS = 1 << 16  # leaves whose reach is unpacked at once (32 MiB of flags)


def _evaluate_voxels(model: Node, grid: BlockGrid, idx: np.ndarray, h: float, t: float) -> int:
    """The model at voxels of the leaves (flat indices into their values), clamped to
    +-FINITE_LIMIT and stored; returns how many were clamped."""
    at = np.unravel_index(idx, grid.values.shape)
    x, y, z = ((grid.origins[at[0], a] + at[1 + a]) * h for a in range(3))  # voxel centres, as evaluate_blocks
    v = np.array(model.evaluate_xyz(x, y, z, t), dtype=np.float64)
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.argmax(bad))
        raise NonFiniteField(np.array([x[i], y[i], z[i]]))
    big = int(np.count_nonzero(np.abs(v) > FINITE_LIMIT))
    grid.values[at] = np.clip(v, -FINITE_LIMIT, FINITE_LIMIT) if big else v
    return big


def bricks_for(imin: np.ndarray, imax: np.ndarray, brick: int, block: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Index boxes of the bricks (aligned to ``brick``, a multiple of the leaf) covering the domain."""
    start = (imin // brick) * brick
    counts = ((imax - start) // brick) + 1
    out = []
    for ijk in np.ndindex(*[int(c) for c in counts]):
        lo = start + np.array(ijk) * brick
        out.append((np.maximum(lo, imin), np.minimum(lo + brick - 1, imax)))
    return out


def _in_domain(blocks: np.ndarray, b: int, imin: np.ndarray, imax: np.ndarray) -> np.ndarray:
    """Voxels of each block inside the domain's index box (only boundary blocks are partial)."""
    valid = np.ones((len(blocks), b, b, b), bool)
    edge = np.flatnonzero(np.any(blocks < imin, axis=1) | np.any(blocks + b - 1 > imax, axis=1))
    r = np.arange(b)
    for n in edge:
        ok = [(blocks[n, a] + r >= imin[a]) & (blocks[n, a] + r <= imax[a]) for a in range(3)]
        valid[n] = ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
    return valid


def _background(values: np.ndarray, active: np.ndarray, band: float, h: float) -> float:
    """|background|: above every active value, so inactive +-bg never collide with band values."""
    top = max_abs_active(values, active)
    if top < 0:
        return float(band * h)
    return float(max(top * 1.01, 1e-6))


def _assemble_leaves(blocks, b, vals, valid, inside_levels, h, bg) -> tuple[BlockGrid, np.ndarray]:
    """Scatter evaluated blocks into 8^3 leaves; unevaluated voxels hold -bg, or +bg when a
    sub-leaf cell proved them inside. Also returns the mask of evaluated (known) voxels."""
    if len(blocks) == 0:
        return BlockGrid(h, -bg), np.zeros((0, LEAF, LEAF, LEAF), bool)
    leaf_of = (blocks >> LEAF_LOG2) << LEAF_LOG2
    keys, first, rows = np.unique(pack_keys(leaf_of), return_index=True, return_inverse=True)
    L = len(keys)
    values = np.full((L, LEAF, LEAF, LEAF), -bg, np.float32)
    act = np.empty((L, LEAF, LEAF, LEAF), bool)  # every flag is set by mark_band
    known = np.zeros((L, LEAF, LEAF, LEAF), bool)
    _scatter(values, known, rows.reshape(-1), blocks - leaf_of, vals, valid, np.float32(-bg))
    _fill_inside_cells(values, keys, inside_levels, bg)
    grid = BlockGrid(h, -bg, leaf_of[first], values, act)  # keys are sorted: rows stay valid
    return grid, known


def _fill_inside_cells(values: np.ndarray, keys: np.ndarray, inside_levels: list, bg: float) -> None:
    """+bg on the voxels of the sub-leaf cells proven inside, in the leaves (sorted ``keys``)."""
    L = len(keys)
    for origins, size in inside_levels:
        if size >= LEAF or len(origins) == 0:
            continue
        lkeys = pack_keys((origins >> LEAF_LOG2) << LEAF_LOG2)
        pos = np.minimum(np.searchsorted(keys, lkeys), L - 1)
        ok = keys[pos] == lkeys
        _fill_cells(values, pos[ok], origins[ok] - ((origins[ok] >> LEAF_LOG2) << LEAF_LOG2), size, bg)


@njit(cache=True, parallel=True)
def _count_beyond(vals, valid, limit) -> int:
    """How many valid values have |v| > limit (one parallel pass)."""
    flat_v, flat_ok = vals.reshape(-1), valid.reshape(-1)
    total = 0
    for n in prange(flat_v.size):
        if flat_ok[n] and abs(flat_v[n]) > limit:
            total += 1
    return total


@njit(cache=True, parallel=True)
def _scatter(values, known, rows, offs, vals, valid, outside):
    """Blocks into their leaves (blocks are disjoint: the parallel writes never meet); voxels
    outside the domain hold ``outside``."""
    b = vals.shape[1]
    for n in prange(len(rows)):
        r, oi, oj, ok = rows[n], offs[n, 0], offs[n, 1], offs[n, 2]
        for i in range(b):
            for j in range(b):
                for k in range(b):
                    values[r, oi + i, oj + j, ok + k] = vals[n, i, j, k] if valid[n, i, j, k] else outside
                    known[r, oi + i, oj + j, ok + k] = valid[n, i, j, k]


@njit(cache=True)
def _fill_cells(values, rows, offs, size, bg):
    for n in range(len(rows)):
        r, oi, oj, ok = rows[n], offs[n, 0], offs[n, 1], offs[n, 2]
        values[r, oi:oi + size, oj:oj + size, ok:ok + size] = bg


def _inside_boxes(inside_levels, imin, imax) -> np.ndarray:
    boxes = []
    for origins, size in inside_levels:
        lo, hi = _clip_boxes(origins, size, imin, imax)
        boxes.append(np.stack([lo, hi], axis=1))
    if not boxes:
        return np.zeros((0, 2, 3), np.int64)
    return unique_boxes(np.concatenate(boxes))


def unique_boxes(boxes: np.ndarray) -> np.ndarray:
    """``np.unique(boxes.reshape(-1, 6), axis=0)`` as (K, 2, 3): the boxes sorted by (lo, hi),
    each once. The cells of one run are disjoint, so their low corners are distinct and one
    sort of their packed keys gives that order (np.unique's row sort took 0.35 s for the 0.3M
    boxes of the demo at 1024^3); the bricks of one domain share their coarse cells, and boxes
    with equal low corners go to np.unique."""
    rows = np.asarray(boxes, np.int64).reshape(-1, 6)
    keys = pack_keys(rows[:, :3])
    order = np.argsort(keys, kind="stable")
    k = keys[order]
    if len(k) > 1 and not np.all(k[1:] > k[:-1]):
        return np.unique(rows, axis=0).reshape(-1, 2, 3)
    return rows[order].reshape(-1, 2, 3)


def estimate_band_bytes(model: Node, domain, band: float, t: float = 0.0) -> float:
    """Rough memory need of a voxelisation, from a coarse enumeration, plus the bounded working
    set of the evaluation calls (WORK_BYTES).

    The enumeration goes down until a level has ESTIMATE_CELLS ambiguous cells (or 1/64 of the
    domain); the growth of the ambiguous count between its last two levels says how the surface
    fills space: x4 per halving for a resolved surface, x8 for one that fills the volume (a
    gyroid finer than the cells). That ratio, clamped to [4, 8], extrapolates the count down to
    leaves; a leaf costs ~14 KiB at the peak of voxelise plus export (measured: a gyroid of
    36k leaves at 256^3 peaks at 0.80 GB, of 132k leaves at 400^3 at 1.92 GB: 11.7 KiB per leaf).
    """
    lv = _coarse_cells(model, domain, band, t)
    levels = lv.stats["levels"]
    s = levels[-1]["size"]
    amb = float(len(lv.blocks))
    if len(levels) >= 2 and levels[-2]["ambiguous"] > 0:
        ratio = float(np.clip(levels[-1]["ambiguous"] / levels[-2]["ambiguous"], 4.0, 8.0))
    else:
        ratio = 4.0
    leaves = amb * ratio ** max(0.0, np.log2(s / 8.0))
    leaves = min(leaves, float(np.prod(np.ceil(domain.dims / 8.0))))  # never more than the domain's leaves
    return leaves * LEAF_PEAK_BYTES + WORK_BYTES


def estimate_interior_voxels(model: Node, domain, band: float, t: float = 0.0) -> float:
    """Rough count of the voxels inside the object (what an interior distance solve touches):
    cells proven inside by the coarse enumeration, plus half of the undecided ones."""
    lv = _coarse_cells(model, domain, band, t)
    imin, imax = domain.index_min, domain.index_max
    total = 0.0
    for origins, size in lv.inside:
        lo, hi = _clip_boxes(origins, size, imin, imax)
        total += float(np.prod(hi - lo + 1, axis=1).sum())
    s = lv.stats["levels"][-1]["size"]
    return total + 0.5 * len(lv.blocks) * float(s) ** 3


LEAF_PEAK_BYTES = 14 << 10  # peak memory per band leaf through voxelise and export (measured ~11.7 KiB)
ESTIMATE_CELLS = 50_000  # ambiguous cells at which the estimating enumeration stops


def _coarse_cells(model: Node, domain, band: float, t: float) -> CellLevels:
    """The enumeration down to 1/64 of the domain, or less deep once a level has ESTIMATE_CELLS
    ambiguous cells (the cost of an estimate stays bounded whatever the model), with the
    evaluator the voxeliser uses: the compiled tape with per-cell specialisation where the
    model (or its sign proxy) lowers to one, else the model's affine bounds. The whole tree per
    box was 61 s of bounds for a 1.3M-face mesh at 512^3, whose voxelisation takes 15 s."""
    imin, imax = domain.index_min, domain.index_max
    stop = 1 << int(np.ceil(np.log2(max(8, domain.dims.max() / 64))))
    # at most ~16^3 top cells, whatever the resolution (the voxeliser's own top cells stop at
    # 4096 voxels: 10^6 voxels a side would be 10^7 of them)
    root = max(root_size_for(domain.dims, 8), 1 << int(np.ceil(np.log2(max(8, domain.dims.max() / 16)))))
    first = max(stop, root // 2)  # the descent reaches this level at least

    def enough(size: int, ambiguous: int) -> bool:
        return size <= first and ambiguous >= ESTIMATE_CELLS

    work, tape = _working_model(model, t)
    if tape is not None:
        lv, _ = enumerate_cells_tape(tape, imin, imax, domain.voxel_size, band, 8, root_size=root, stop_size=stop,
                                     stop_after=enough)
        return lv
    return enumerate_cells(work, imin, imax, domain.voxel_size, band, 8, t, stop_size=stop, root_size=root,
                           stop_after=enough)
