"""The one place pyopenvdb grids are made: the algorithms hand over BlockGrids, streams of leaves
(:class:`pipeline.sparse.blockwrite.LeafSource`) and tile lists, and the functions here build the
OpenVDB grids of SPEC's conventions from them (frep with its signs on tiles and background, level
sets, fog volumes, tiled distances, attributes, labels); the stages put those grids on the
context for the writers (pipeline.io.vdbio, vtkio, meshout, previews).

Leaves are written with ``copyFromArray`` (pyopenvdb calls Python per voxel in its iterators, so
bulk NumPy is the only fast path), runs of leaves that follow each other along z in one call,
laid out by a compiled pass a batch at a time. Index space: voxel (i, j, k) has its centre at
world position (i, j, k) * voxel_size (OpenVDB's plain linear transform).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

import numpy as np
from numba import prange

from pipeline.sparse.blockwrite import LeafSource
from pipeline.sparse.grid import (
    LEAF,
    LEAF_LOG2,
    BlockGrid,
    coalesce_boxes,
    leaf_has_active,
    max_abs_active,
    pack_keys,
)
from pipeline.util.jit import njit

try:  # the compiled leaf builder, built by the package's build where OpenVDB's headers are (setup.py)
    from pipeline.io import _leafbuild  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - copyFromArray then, as before
    _leafbuild = None
if os.environ.get("FREPVDB_COPY_FROM_ARRAY") == "1":  # the old path, for comparisons (bench/leaves.py)
    _leafbuild = None

try:  # OpenVDB >= 11 names the module openvdb
    import openvdb as vdb  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the platform
    import pyopenvdb as vdb  # type: ignore[import-not-found,no-redef]


def compiled_for(grid):
    """The compiled module (pipeline/io/leafbuild.cpp: leaves, tiles and bulk reads with
    OpenVDB's C++ API) for a FloatGrid; None where it does not apply (other grid types, the
    extension not built, FREPVDB_COPY_FROM_ARRAY=1): the pyopenvdb paths then."""
    return _leafbuild if _leafbuild is not None and isinstance(grid, vdb.FloatGrid) else None


def compiled_writer(grids: list):
    """The compiled module's ``write_file`` (a .vdb written without the GIL) when it takes every
    grid (FloatGrid, Vec3SGrid, BoolGrid: the types pyopenvdb 10 registers); None otherwise."""
    if _leafbuild is None or not all(isinstance(g, (vdb.FloatGrid, vdb.Vec3SGrid, vdb.BoolGrid)) for g in grids):
        return None
    return _leafbuild.write_file


# --- writing leaves ------------------------------------------------------------------------------
def linear_transform(voxel_size: float):
    """OpenVDB transform with voxel centres at integer multiples of ``voxel_size``."""
    return vdb.createLinearTransform(voxelSize=float(voxel_size))


BATCH = 4096  # blocks per batch (8 MiB of float32 values) unless a call says otherwise


def write_batched(grid, origins: np.ndarray, fill: Callable[[int, int, np.ndarray, np.ndarray], None] | None,
                  scale: float = 1.0, batch: int | None = None, source: tuple[np.ndarray, np.ndarray] | None = None,
                  done: Callable[[int], None] | None = None) -> None:
    """Write the blocks at ``origins`` (sorted as a BlockGrid keeps them) into ``grid``:
    ``fill(lo, hi, values, active)`` puts blocks lo..hi-1 into the (hi-lo, 8, 8, 8) float32 /
    bool arrays it is given (or, without ``fill``, ``source`` = (values, active) holds every
    block). Values times ``scale`` where active, the grid's background elsewhere (so
    ``copyFromArray`` leaves those voxels inactive), as :func:`write_leaves`. ``done(hi)`` is called
    after blocks ..hi-1 are written (to release what produced them)."""
    o = np.asarray(origins, np.int64).reshape(-1, 3)
    if len(o) == 0:
        return
    batches = _batches(len(o), fill, batch, source, done)
    k = np.float32(scale)
    compiled = compiled_for(grid)
    if compiled is not None:  # the same voxels, values and tiles, leaves made in parallel
        for lo, hi, v, a in batches:
            kv = k
            if v.dtype != np.float32:  # scaled in the source's precision and rounded once, as _pack_runs does
                v, kv = (v * k).astype(np.float32), np.float32(1.0)
            compiled.add_blocks(grid, np.ascontiguousarray(o[lo:hi]), np.ascontiguousarray(v),
                                np.ascontiguousarray(a, dtype=bool), float(kv))
        compiled.finish(grid)  # the tiles pruned once, where copyFromArray prunes after every call
        return
    bg = np.float32(grid.background)
    brk = np.ones(len(o), bool)  # a run starts where x, y change or z is not the next leaf
    brk[1:] = (o[1:, 0] != o[:-1, 0]) | (o[1:, 1] != o[:-1, 1]) | (o[1:, 2] != o[:-1, 2] + LEAF)
    packed = np.empty(min(BATCH if batch is None else batch, len(o)) * LEAF**3, np.float32)
    for lo, hi, v, a in batches:
        starts = np.flatnonzero(brk[lo:hi])
        if len(starts) == 0 or starts[0] != 0:  # a run that goes on from the previous batch restarts here
            starts = np.concatenate([[0], starts])
        ends = np.append(starts[1:], hi - lo)
        _pack_runs(v, a, starts, ends, k, bg, packed)
        for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
            arr = packed[s * LEAF**3:e * LEAF**3].reshape(LEAF, LEAF, LEAF * (e - s))
            grid.copyFromArray(arr, (int(o[lo + s, 0]), int(o[lo + s, 1]), int(o[lo + s, 2])))


def _batches(n: int, fill, batch: int | None, source, done):
    """(lo, hi, values, active) of blocks lo..hi-1, a batch at a time: filled by ``fill`` into
    reused arrays, or slices of ``source``; ``done(hi)`` once the consumer asks for the next."""
    size = min(BATCH if batch is None else batch, n)
    if fill is not None:
        values = np.empty((size, LEAF, LEAF, LEAF), np.float32)
        active = np.empty((size, LEAF, LEAF, LEAF), bool)
    for lo in range(0, n, size):
        hi = min(lo + size, n)
        if fill is not None:
            fill(lo, hi, values[:hi - lo], active[:hi - lo])
            yield lo, hi, values[:hi - lo], active[:hi - lo]
        else:
            yield lo, hi, source[0][lo:hi], source[1][lo:hi]
        if done is not None:
            done(hi)


@njit(cache=True, parallel=True)
def _pack_runs(values, active, starts, ends, k, bg, out):
    """Each run of blocks starts[r] .. ends[r] - 1 as one C-ordered (8, 8, 8 m)
    array at ``out[512 starts[r]:]``: ``values * k`` where active, ``bg`` elsewhere."""
    for r in prange(starts.shape[0]):
        s, e = starts[r], ends[r]
        m = e - s
        base = s * 512
        for q in range(m):
            b = s + q
            for i in range(8):
                for j in range(8):
                    row = base + (i * 8 + j) * 8 * m + 8 * q
                    for kk in range(8):
                        out[row + kk] = values[b, i, j, kk] * k if active[b, i, j, kk] else bg


def write_leaves(grid, leaves: LeafSource | BlockGrid, scale: float = 1.0, batch: int | None = None) -> None:
    """Copy every leaf (values times ``scale``) into ``grid``; inactive voxels are written as the
    grid's background, so ``copyFromArray`` (which activates every value that differs from the
    background) leaves them inactive. A LeafSource's leaves are made (``fill``) and released
    (``done``) a batch at a time."""
    if isinstance(leaves, BlockGrid):
        leaves = LeafSource.of(leaves)
    write_batched(grid, leaves.origins, leaves.fill, scale, batch, leaves.arrays, leaves.done)


# --- grids of the SPEC's kinds ---------------------------------------------------------------
def frep_to_vdb(blocks: BlockGrid, inside_boxes: np.ndarray, name: str = "frep",
                outside_boxes: np.ndarray | None = None, domain: tuple[np.ndarray, np.ndarray] | None = None):
    """FloatGrid in FRep convention (f > 0 inside) from band blocks plus boxes proven inside.

    Active voxels carry the field; inactive voxels and tiles inside hold +bg, outside -bg
    (SPEC's ``frep`` row). pyopenvdb 10 cannot write inactive values other than the
    background, so we build the level-set-signed grid (-f, background +bg), let OpenVDB's
    signedFloodFill set inside to -bg, negate the active values with OpenVDB AX and set the
    background to -bg, which swaps +bg and -bg on every inactive value.

    The flood fill is right in every leaf whose voxels all carry their sign and whose band is
    closed (pipeline.voxel.voxelise.mark_band): its scan lines then never cross a sign change between
    inactive voxels. Where that does not hold it is not trusted (issue 12):

    * boxes proven inside (+bg) and, when given, ``outside_boxes`` (-bg) are filled explicitly,
      so no tile takes its sign from a neighbouring leaf's corner;
    * with ``domain`` (the index box): leaves without an active voxel are filled with their one
      sign, and leaves cut by the domain's faces (whose voxels beyond the domain carry no sign,
      so the scan lines may cross them) are read back and every voxel of the wrong sign is set.
    """
    grid = _frep_signed(blocks, name)
    bg = abs(float(blocks.background))
    has_active = leaf_has_active(blocks.active)
    _fill_boxes(grid, coalesce_boxes(_boxes_to_fill(blocks, inside_boxes, has_active)), bg)
    if outside_boxes is not None:
        _fill_boxes(grid, coalesce_boxes(outside_boxes), -bg)
    if domain is not None:
        _fix_untrusted_leaves(grid, blocks, np.asarray(domain[0]), np.asarray(domain[1]), bg, has_active)
    grid.prune()
    return grid


def _fill_boxes(grid, boxes: np.ndarray, value: float) -> None:
    """Inactive ``value`` over every (lo, hi) index box (corners as Python lists: one fill call
    costs ~0.7 us, converting each corner's NumPy integers ~2 us more)."""
    b = np.asarray(boxes, np.int64).reshape(-1, 2, 3)
    fill = grid.fill
    for lo, hi in zip(b[:, 0].tolist(), b[:, 1].tolist(), strict=True):
        fill(lo, hi, value, False)


def _fix_untrusted_leaves(grid, blocks: BlockGrid, imin: np.ndarray, imax: np.ndarray, bg: float,
                         has_active: np.ndarray | None = None) -> int:
    """Set the sign of the leaves the flood fill cannot be trusted with (see frep_to_vdb)."""
    o = blocks.origins
    if len(o) == 0:
        return 0
    cut = np.any(o < imin, axis=1) | np.any(o + LEAF - 1 > imax, axis=1)
    empty = ~(leaf_has_active(blocks.active) if has_active is None else has_active)
    whole = np.flatnonzero(empty & ~cut)  # uniform by the closure: filled with their one sign
    boxes = np.stack([o[whole], o[whole] + LEAF - 1], axis=1)
    inside = blocks.values[whole, 0, 0, 0] > 0
    _fill_boxes(grid, coalesce_boxes(boxes[inside]), bg)
    _fill_boxes(grid, coalesce_boxes(boxes[~inside]), -bg)
    fixed = 0
    r = np.arange(LEAF)
    for n in np.flatnonzero(cut):
        lo = np.maximum(o[n], imin)
        hi = np.minimum(o[n] + LEAF - 1, imax)
        if np.any(hi < lo):
            continue
        want = blocks.values[n] > 0
        got = np.zeros((LEAF, LEAF, LEAF), np.float32)
        grid.copyToArray(got, tuple(int(c) for c in o[n]))
        ok = [(o[n, a] + r >= imin[a]) & (o[n, a] + r <= imax[a]) for a in range(3)]
        in_dom = ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
        for i, j, k in np.argwhere(in_dom & ((got > 0) != want) & ~blocks.active[n]):
            ijk = (int(o[n, 0] + i), int(o[n, 1] + j), int(o[n, 2] + k))
            grid.fill(ijk, ijk, bg if want[i, j, k] else -bg, False)
            fixed += 1
    return fixed


def _boxes_to_fill(blocks: BlockGrid, inside_boxes: np.ndarray, leaf_active: np.ndarray | None = None) -> np.ndarray:
    """Inside boxes that need an explicit fill: all tile-sized ones, and the sub-leaf ones whose
    leaf has no active voxel (inside a leaf with active voxels the flood fill already set them).
    ``leaf_active``: :func:`leaf_has_active` of the blocks, when known."""
    boxes = np.asarray(inside_boxes, dtype=np.int64).reshape(-1, 2, 3)
    if len(boxes) == 0 or len(blocks.origins) == 0:
        return boxes
    lo, hi = boxes[:, 0], boxes[:, 1]
    leaf = (lo >> LEAF_LOG2) << LEAF_LOG2
    within_leaf = np.all((hi >> LEAF_LOG2) << LEAF_LOG2 == leaf, axis=1)
    row = blocks.block_index(leaf)
    if leaf_active is None:
        leaf_active = leaf_has_active(blocks.active)
    has_active = np.zeros(len(boxes), bool)
    ok = row >= 0
    has_active[ok] = leaf_active[row[ok]]
    return boxes[~(within_leaf & has_active)]


def frep_grid_of_leaves(leaves: LeafSource | BlockGrid, name: str):
    """:func:`frep_to_vdb` of leaves without boxes (their signs all carried by the leaves),
    written a batch at a time (the ``hfrep`` grid)."""
    grid = _frep_signed(leaves, name)
    grid.prune()
    return grid


def _frep_signed(leaves: LeafSource | BlockGrid, name: str):
    """The FRep-signed grid of leaves before any box fill: the level-set-signed values written
    (background +bg), sign flood fill, the active values negated, the background swapped to -bg."""
    bg = abs(float(leaves.background))
    grid = _new_grid(name, leaves.voxel_size, bg)
    write_leaves(grid, leaves, scale=-1.0)
    compiled = compiled_for(grid)
    if compiled is not None:  # the same three steps in one call, without the GIL
        compiled.frep_signs(grid)
        return grid
    grid.signedFloodFill()
    negate_active(grid)
    grid.background = -bg  # swaps +bg <-> -bg on inactive values and tiles
    return grid


def _new_grid(name: str, voxel_size: float, background: float, grid_class=None):
    """An empty FloatGrid with our transform (voxel centres at integer multiples of the size)."""
    grid = vdb.FloatGrid(float(background))
    grid.name = name
    grid.transform = linear_transform(voxel_size)
    if grid_class is not None:
        grid.gridClass = grid_class
    return grid


def level_set_grid(leaves: LeafSource | BlockGrid, name: str):
    """A LEVEL_SET FloatGrid (negative inside) of signed leaves, background +|bg|, the signs of
    tiles and inactive voxels set by OpenVDB's signedFloodFill (the ``surface`` grid)."""
    grid = _new_grid(name, leaves.voxel_size, abs(float(leaves.background)), vdb.GridClass.LEVEL_SET)
    write_leaves(grid, leaves)
    grid.signedFloodFill()
    grid.prune()
    return grid


def tiled_grid(blocks: BlockGrid, tiles: list[tuple[np.ndarray, np.ndarray, int]], name: str,
               level_set: bool):
    """A FloatGrid of fine leaves and active constant tiles ``(origins, values, cell)`` (a
    hierarchical distance: leaf-sized and 128^3 tiles), background ``blocks.background``;
    class LEVEL_SET when ``level_set``. ``grid.fill`` over whole nodes makes tiles."""
    grid = _new_grid(name, blocks.voxel_size, blocks.background, vdb.GridClass.LEVEL_SET if level_set else None)
    for origins, values, cell in tiles:
        for o, v in zip(np.asarray(origins).tolist(), np.asarray(values).tolist(), strict=True):
            grid.fill(tuple(o), tuple(x + cell - 1 for x in o), float(v), True)
    write_leaves(grid, blocks)
    return grid


def fog_grid(leaves: LeafSource, tile_origins: np.ndarray, tile_values: np.ndarray, name: str):
    """A FOG_VOLUME FloatGrid (background 0) of leaves and active leaf-sized tiles; tiles of
    value 1 are merged into boxes (:func:`fill_tiles`), so a solid interior costs a few calls."""
    grid = _new_grid(name, leaves.voxel_size, 0.0, vdb.GridClass.FOG_VOLUME)
    write_leaves(grid, leaves)
    fill_tiles(grid, tile_origins, tile_values, merge_value=1.0)
    grid.prune()
    return grid


def float_grid(leaves: LeafSource | BlockGrid, name: str, background: float | None = None):
    """A plain FloatGrid of leaves (the ``component`` labels), background ``background``
    (default ``leaves.background``)."""
    grid = _new_grid(name, leaves.voxel_size, leaves.background if background is None else background)
    write_leaves(grid, leaves)
    return grid


def attribute_grid(name: str, values: np.ndarray, origins: np.ndarray, active: np.ndarray, voxel_size: float):
    """pyopenvdb FloatGrid (values (L,8,8,8)) or Vec3SGrid (values (L,8,8,8,3)), background 0.

    Every voxel of ``active`` is active, also where its value equals the background 0: a
    Vec3S grid's leaves are made so by the compiled builder (leafbuild.cpp add_vec3_blocks);
    ``copyFromArray`` deactivates values equal to the grid's background, so elsewhere the grid
    is written with a sentinel background that no value takes and then switched to 0
    (OpenVDB's changeBackground replaces only inactive sentinel values).
    """
    vector = values.ndim == 5
    if vector and _leafbuild is not None and hasattr(_leafbuild, "add_vec3_blocks"):
        grid = vdb.Vec3SGrid((0.0, 0.0, 0.0))  # every active voxel on, whatever its value: no sentinel
        _leafbuild.add_vec3_blocks(grid, np.ascontiguousarray(origins, dtype=np.int64),
                                   np.ascontiguousarray(values, dtype=np.float32), np.ascontiguousarray(active))
        grid.prune((0.0, 0.0, 0.0))
    elif vector:
        grid = vdb.Vec3SGrid((_sentinel(values, active),) * 3)
        dense = np.where(active[..., None], values, grid.background[0]).astype(np.float32)
        for b, o in enumerate(origins):
            if active[b].any():
                grid.copyFromArray(np.ascontiguousarray(dense[b]), tuple(int(c) for c in o))
        grid.background = (0.0, 0.0, 0.0)
        grid.prune((0.0, 0.0, 0.0))
    else:
        sentinel = _sentinel(values, active)
        grid = vdb.FloatGrid(sentinel)
        write_leaves(grid, BlockGrid(voxel_size, sentinel, origins, values.astype(np.float32), active))
        grid.background = 0.0
        grid.prune()
    grid.name = name
    grid.transform = linear_transform(voxel_size)
    return grid


def _sentinel(values: np.ndarray, active: np.ndarray) -> float:
    """A float32 background that no active value takes (an even integer above them all)."""
    top = max(max_abs_active(np.ascontiguousarray(values), np.ascontiguousarray(active)), 0.0)
    return float(np.float32(2.0 * math.floor(top) + 2.0))


# --- tiles ----------------------------------------------------------------------------------
def fill_tiles(grid, origins: np.ndarray, values: np.ndarray, cell: int = LEAF,
               merge_value: float | None = None) -> None:
    """Active constant tiles of edge ``cell`` voxels (``grid.fill`` over whole leaves makes
    tiles). Tiles that follow each other along z with the same value go in one call; those of
    value ``merge_value`` are merged into boxes along y and x too, so a solid region of it
    costs a few calls and OpenVDB makes it coarser tiles (a density's interior of 1: at 2048^3
    7.6M leaf tiles). The calls take coordinates from per-axis lists of Python ints built
    once (the tile lattice indices are small ints Python shares): at 1M tiles 0.65 s instead
    of 0.94 s with a list per corner."""
    o = np.asarray(origins, np.int64).reshape(-1, 3)
    v = np.asarray(values, np.float32).reshape(-1)
    if len(o) == 0:
        return
    keys = pack_keys(o)  # in x, y, z order
    if len(o) > 1 and not (np.diff(keys) > 0).all():  # interior_tiles gives them in order already
        order = np.argsort(keys, kind="stable")
        o, v = o[order], v[order]
    if merge_value is not None:
        same = v == np.float32(merge_value)
        if same.any():
            lo, hi = _merged_boxes(o[same], cell)
            fill = grid.fill
            x = float(np.float32(merge_value))
            for a, b in zip(lo.tolist(), hi.tolist(), strict=True):
                fill(a, b, x, True)
            o, v = o[~same], v[~same]
            if len(o) == 0:
                return
    compiled = compiled_for(grid)
    if compiled is not None and cell in (LEAF, 128):  # the tiles grid.fill makes, one C++ call
        compiled.add_tiles(grid, np.ascontiguousarray(o), np.ascontiguousarray(v), cell)
        return
    starts, ends = _z_runs(o, v, cell)
    _fill_runs(grid, o, v, starts, ends, cell)


def _z_runs(o: np.ndarray, v: np.ndarray | None, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """First and last row of every run of tiles (sorted by x, y, z) that follow each other
    along z with the same value (any value when ``v`` is None)."""
    brk = np.ones(len(o), bool)
    brk[1:] = (o[1:, 0] != o[:-1, 0]) | (o[1:, 1] != o[:-1, 1]) | (o[1:, 2] != o[:-1, 2] + cell)
    if v is not None:
        brk[1:] |= v[1:] != v[:-1]
    starts = np.flatnonzero(brk)
    return starts, np.append(starts[1:], len(o)) - 1


def _merged_boxes(o: np.ndarray, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive (lo, hi) voxel boxes covering the sorted tiles ``o`` exactly: runs along z,
    then runs with the same z extent joined along y, then boxes with the same y, z extent
    joined along x (not the fewest boxes, but a solid region becomes a handful)."""
    s, e = _z_runs(o, None, cell)
    lo, hi = o[s], o[e] + (cell - 1)
    for axis in (1, 0):  # join along y, then along x
        rest = [a for a in range(3) if a != axis]
        keys = (lo[:, axis],) + tuple(hi[:, a] for a in reversed(rest)) + tuple(lo[:, a] for a in reversed(rest))
        order = np.lexsort(keys)  # by the other axes' extents, then along this axis
        lo, hi = lo[order], hi[order]
        brk = np.ones(len(lo), bool)
        brk[1:] = (lo[1:, axis] != hi[:-1, axis] + 1)
        for a in rest:
            brk[1:] |= (lo[1:, a] != lo[:-1, a]) | (hi[1:, a] != hi[:-1, a])
        first = np.flatnonzero(brk)
        last = np.append(first[1:], len(lo)) - 1
        lo, hi = lo[first], hi[last]  # the other axes' extents are equal within a group
    return lo, hi


def _fill_runs(grid, o: np.ndarray, v: np.ndarray, starts: np.ndarray, ends: np.ndarray, cell: int) -> None:
    """One ``grid.fill`` per run (:func:`_z_runs`), its corners taken from per-axis lists of
    Python ints made once (no new int objects per call: lattice indices up to 256 are ints
    Python shares)."""
    base = o.min(axis=0)
    idx = (o - base) // cell
    span = int(idx.max()) + 1
    lo_ax = [[int(base[a]) + cell * n for n in range(span)] for a in range(3)]
    hi_ax = [[int(base[a]) + cell * n + cell - 1 for n in range(span)] for a in range(3)]
    (x0, y0, z0), (x1, y1, z1) = lo_ax, hi_ax
    fill = grid.fill
    for c in range(0, len(starts), FILL_CHUNK):  # a chunk's lists at a time: 7.6M at once is ~2 GB of objects
        s, e = starts[c:c + FILL_CHUNK], ends[c:c + FILL_CHUNK]
        # flat lists per column: a list of rows makes an inner list per tile (0.86 -> 0.55 s at 0.9M tiles)
        cols = (idx[s, 0].tolist(), idx[s, 1].tolist(), idx[s, 2].tolist(), idx[e, 2].tolist(), v[s].tolist())
        for i, j, k, kk, x in zip(*cols, strict=True):
            fill((x0[i], y0[j], z0[k]), (x1[i], y1[j], z1[kk]), x, True)


FILL_CHUNK = 1 << 16


# --- operations and statistics ----------------------------------------------------------------
def negate_active(grid) -> None:
    """Negate every active value in place (OpenVDB AX; Python iteration only as a fallback)."""
    ax = getattr(vdb, "ax", None)
    if ax is not None:
        ax(f"@{grid.name} = -@{grid.name};", grid)
        return
    for item in grid.iterOnValues():  # pragma: no cover - builds without AX
        item.value = -item.value


def min_max(grid) -> tuple:
    """(min, max) of the active values, voxels and tiles: ``grid.evalMinMax()``, for a FloatGrid
    through the compiled threaded reduction (without the GIL)."""
    compiled = compiled_for(grid)
    return compiled.min_max(grid) if compiled is not None else grid.evalMinMax()


def grid_stats(grid, voxel_size: float) -> dict:
    """Manifest entry for a grid: active voxels, world bbox of the active voxels, min/max."""
    n = int(grid.activeVoxelCount())
    entry: dict = {"class": str(grid.gridClass), "type": grid.valueTypeName, "active_voxels": n}
    if n:
        lo, hi = grid.evalActiveVoxelBoundingBox()
        entry["bbox"] = [[float(c) * voxel_size for c in lo], [float(c) * voxel_size for c in hi]]
        vmin, vmax = min_max(grid)
        entry["min"], entry["max"] = _scalar(vmin), _scalar(vmax)
    return entry


def _scalar(v):
    return [float(c) for c in v] if isinstance(v, tuple) else float(v)


def stored_values(grid, count_tiles: bool = False) -> dict:
    """Leaves, voxels held by tiles, memory (bytes) and stored values (leaves * 512 + tiles).

    ``count_tiles`` walks ``iterOnValues`` (one Python call per active voxel: small grids only)
    to count the active tiles by size; without it the tile count is left out."""
    leaves = int(grid.leafCount())
    out = {"leaves": leaves, "tile_voxels": int(grid.activeVoxelCount() - grid.activeLeafVoxelCount()),
           "mem_bytes": int(grid.memUsage())}
    if count_tiles:
        tiles: dict[int, int] = {}
        for item in grid.iterOnValues():
            if item["depth"] < 3:  # depth 3: voxels of leaves
                tiles[item["count"]] = tiles.get(item["count"], 0) + 1
        out["tiles_by_voxels"] = tiles
        out["tiles"] = sum(tiles.values())
        out["stored_values"] = leaves * 512 + out["tiles"]
    return out
