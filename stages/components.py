"""components: count, label and separate the connected components of the voxelised model.

components seed: Algorithm 1 enumerates the model on an octree aligned with the voxel grid
(finest cell = the tolerance, a power-of-two multiple of the voxel size, cell faces on voxel
faces), section 4.2 labels the clusters, and every active voxel of the ``frep`` grid gets the
label of the cell holding it (band voxels outside every kept cell: the nearest finest cell).
With ``bricks:`` the enumeration and the local labelling run per brick on the workers and the
labels are unified across brick faces here (pipeline.topology.component_bricks); the result is the same.
Writes the ``component`` grid (labels 1..N, background 0), the manifest section
``components``, optionally one .vdb per separated component (section 4.3), and with ``keep``
replaces ``frep`` by the kept pieces (section 5: removing small components).
"""

from __future__ import annotations

import json
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from pipeline.field import rfunctions as rf
from pipeline.io import vdbgrids as vg
from pipeline.io.vdbio import write_vdb_beside
from pipeline.sparse.grid import BlockGrid
from pipeline.topology import component_bricks as cb
from pipeline.topology import components as cc
from pipeline.util.heap import retained_heap
from stages.base import FrepBand, StageParams, band_only

REQUIRES = (FrepBand,)
PRODUCES = (FrepBand,)  # the band without the pieces ``keep`` drops


class MinVolume(StageParams):
    min_volume: float = Field(ge=0, description="keep components whose volume is at least this")


class Params(StageParams):
    tolerance: float | None = Field(default=None, gt=0, description="finest cell edge (world); default: voxel size")
    depth: int | None = Field(default=None, ge=1, le=14, description="octree depth instead of a tolerance")
    separate: bool = Field(default=False, description="write one .vdb per component")
    keep: Literal["all", "largest"] | MinVolume = "all"
    method: Literal["surface", "cells"] = Field(default="surface", description="separation field (section 4.3)")
    adaptive: bool = Field(default=True, description="separate on the coarsest same-count octree (Alg. 2)")

    @model_validator(mode="after")
    def _one_precision(self):
        if self.tolerance is not None and self.depth is not None:
            raise ValueError("give tolerance or depth, not both")
        return self


def octree_frame(domain, tolerance: float | None, depth: int | None) -> tuple[np.ndarray, float, int, tuple]:
    """(origin, root size, depth, region) of an octree whose cells are aligned with voxel faces:
    the finest cell is voxel_size * 2^m (m may be negative), the root covers the domain."""
    h = domain.voxel_size
    n = float(domain.dims.max())
    if depth is not None:
        m = int(np.ceil(np.log2(n / 2**depth) - 1e-9))
    else:
        m = int(np.floor(np.log2((tolerance or h) / h) + 1e-9))
        depth = max(1, int(np.ceil(np.log2(n / 2.0**m) - 1e-9)))
    cell = h * 2.0**m
    origin = (domain.index_min - 0.5) * h
    region = (origin, (domain.index_max + 0.5) * h)
    return origin, cell * 2**depth, depth, region


def run(ctx, p: Params) -> dict:
    with retained_heap():  # short-lived arrays of several GiB at 2048^3 (pipeline.util.heap)
        return _run(ctx, p)


def _run(ctx, p: Params) -> dict:
    job = ctx.job
    origin, size, depth, region = octree_frame(job.domain, p.tolerance, p.depth)
    found = _detect(ctx, origin, size, depth, region)
    blocks = ctx.get(FrepBand).blocks
    fine_is_voxel = np.isclose(size / 2**depth, job.domain.voxel_size, rtol=1e-9)
    labels = _voxel_labels(found, blocks, job.domain.index_min if fine_is_voxel else None)
    kept = _kept(found, p.keep)
    section = {"count": found.count, "volumes": found.volumes.tolist(),
               "volume_bounds": found.volume_bounds.tolist(), "tolerance": size / 2**depth,
               "depth": depth, "kept": kept, "label_order": "scan (x, then y, then z) of the lowest cell",
               "labelling": {"bricked": bool(job.bricks), **found.tree.stats.get("bricked", {})}}
    if len(kept) < found.count:
        labels = _keep_pieces(ctx, found, labels, kept)
    # written and dropped: nothing after this stage reads the labels as blocks (export samples
    # the grid), and at 1024^3 they would hold ~0.5 GB through hfrep and export
    # the integer labels themselves: the batched writer converts them a batch at a time (a float32
    # copy of them all was 0.3 GB of fresh memory and 0.6 s at 1024^3)
    blocks = ctx.get(FrepBand).blocks  # the kept pieces' when keep: removed some
    pending = []
    try:
        if p.separate:
            sep, pending = _separate(ctx, p, found, labels, kept, depth if fine_is_voxel else None)
            section.update(sep)
        # the label grid is made while the last pieces' .vdb files are still being written
        lab = BlockGrid(blocks.voxel_size, 0.0, blocks.origins, labels, blocks.active)
        ctx.grids["component"] = _label_grid(ctx, p, lab, found)
        del lab
        while pending:
            pending.pop(0).wait()
    except BaseException:
        for w in pending:
            w.cancel()
        raise
    ctx.manifest["components"] = section
    st = dict(found.tree.stats)
    st.update({"count": found.count, "cells": len(found.tree), "labelling_seconds": round(found.seconds, 4)})
    return st


def grids(p: Params) -> list[str]:
    return ["component"]  # and with keep: a new frep; with separate: one .vdb per piece


estimate_bytes = band_only


def _detect(ctx, origin, size: float, depth: int, region) -> cc.Components:
    """Algorithm 1 + section 4.2 on the whole domain, or with ``bricks:`` brick by brick on the
    executor's workers (pipeline.topology.component_bricks; each worker loads the job by reference)."""
    job = ctx.job
    if not job.bricks:
        return cc.detect(job.model, origin, size, depth, job.t, region)

    cells, phase = cb.voxel_bricks(job.bricks, job.domain.index_min, job.domain.voxel_size, size, depth)
    return cb.detect_bricked(job.model, origin, size, depth, cells, job.t, region, phase=phase,
                             run_map=lambda fn, tasks: ctx.map_with(fn, tasks, part="model"))


def _voxel_labels(found: cc.Components, blocks: BlockGrid, index_min=None) -> np.ndarray:
    """(L,8,8,8) labels: every active voxel gets the label of its cell (cc.point_labels); with
    the voxel as the finest cell (``index_min`` given) by painting cells onto the leaves
    (cc.block_labels), the same labels without a per-voxel octree search."""
    if index_min is not None:
        return cc.block_labels(found, blocks, index_min)
    out = np.zeros(blocks.active.shape, np.int64)
    b, i, j, k = np.nonzero(blocks.active)
    ijk = blocks.origins[b] + np.stack([i, j, k], axis=1)
    out[b, i, j, k] = cc.point_labels(found, ijk * blocks.voxel_size)
    return out


def _kept(found: cc.Components, keep) -> list[int]:
    every = list(range(1, found.count + 1))
    if keep == "all" or found.count == 0:
        return every
    if keep == "largest":
        return [int(np.argmax(found.volumes)) + 1]
    return [k for k in every if found.volumes[k - 1] >= keep.min_volume]


def _keep_pieces(ctx, found: cc.Components, labels: np.ndarray, kept: list[int]) -> np.ndarray:
    """Replace ``frep`` by the kept pieces: voxels of removed pieces become outside (-bg,
    inactive), and only inside boxes of kept clusters stay filled."""
    prev = ctx.get(FrepBand)
    old = prev.blocks
    keep_mask = np.isin(labels, kept)
    active = old.active & keep_mask
    removed = old.active & ~keep_mask
    values = np.where(removed, np.float32(old.background), old.values)
    rows = np.nonzero(active.any(axis=(1, 2, 3)))[0]
    new = BlockGrid(old.voxel_size, old.background, old.origins[rows], values[rows], active[rows])
    boxes = np.asarray(prev.inside_boxes, np.int64).reshape(-1, 2, 3)
    if len(boxes):
        centre = 0.5 * (boxes[:, 0] + boxes[:, 1]) * old.voxel_size
        boxes = boxes[np.isin(cc.point_labels(found, centre), kept)]
    meta = dict(ctx.grids["frep"].metadata) if "frep" in ctx.grids else {}
    grid = vg.frep_to_vdb(new, boxes, "frep")
    grid.updateMetadata({k: v for k, v in meta.items() if k.startswith("frepvdb") or k == "band_voxels"})
    ctx.grids["frep"] = grid
    # inactive voxels of a removed piece may still hold + values: not signed
    ctx.put(FrepBand(new, boxes, prev.band, signed=False))
    return np.where(keep_mask, labels, 0)[rows]


def _label_grid(ctx, p: Params, lab: BlockGrid, found: cc.Components):
    grid = vg.float_grid(lab, "component", background=0.0)
    grid.updateMetadata({**ctx.grid_metadata("components", p), "component_count": int(found.count),
                         "component_volumes": json.dumps([round(float(v), 9) for v in found.volumes])})
    return grid


def _separate(ctx, p: Params, found: cc.Components, labels: np.ndarray, kept: list[int],
              voxel_depth: int | None) -> tuple[dict, list]:
    """One .vdb per component: the field f AND g_k (section 4.3) on the voxels labelled k
    (``voxel_depth``: the octree level whose cell is one voxel, None when there is none).
    Returns the section's numbers and the writers still at work (at most two; the caller
    waits for them, or cancels them if it fails)."""
    sep, mapping = cc.coarsest_same_count(found) if p.adaptive else (found, {k: k for k in kept})
    frep = ctx.get(FrepBand)
    blocks = frep.blocks
    boxes = np.asarray(frep.inside_boxes, np.int64).reshape(-1, 2, 3)
    box_labels = cc.point_labels(found, 0.5 * (boxes[:, 0] + boxes[:, 1]) * blocks.voxel_size) if len(boxes) \
        else np.zeros(0, np.int64)
    files, pending = [], []
    start, rows = cc.rows_by_label(blocks.active, labels, found.count)  # each piece's blocks, in one pass
    # every cluster's cells by one sort of the labels (not a scan of every cell per piece)
    order = np.argsort(sep.labels, kind="stable")
    cstart = np.searchsorted(sep.labels[order], np.arange(sep.count + 2))
    try:
        for k in kept:
            j = mapping[k]
            field = cc.ClusterField(sep, j, p.method, rows=order[cstart[j]:cstart[j + 1]])
            piece = _piece_blocks(blocks, labels, k, field, voxel_depth, ctx.job.domain.index_min,
                                  rows[start[k]:start[k + 1]])
            grid = vg.frep_to_vdb(piece, boxes[box_labels == k], "frep")
            del piece
            grid.updateMetadata({**ctx.grid_metadata("components", p), "component_index": int(k),
                                 "component_volume": float(found.volumes[k - 1])})
            path = ctx.out_dir / f"{ctx.job.name}_component_{k}.vdb"
            # written by a child process while the next piece is computed (at most two at once:
            # each holds its grid's memory until written)
            if len(pending) >= 2:
                pending.pop(0).wait()
            pending.append(write_vdb_beside(path, [grid], {"creator": "frepvdb", "config": ctx.job.name,
                                                           "component": int(k)}))
            ctx.add_output(path, "vdb")
            files.append(path.name)
    except BaseException:
        for w in pending:
            w.cancel()
        raise
    return {"files": files, "method": p.method, "separation_depth": int(sep.tree.depth)}, pending


def _piece_blocks(blocks: BlockGrid, labels: np.ndarray, k: int, field: cc.ClusterField,
                  voxel_depth: int | None = None, index_min=None, rows: np.ndarray | None = None) -> BlockGrid:
    """The piece's blocks; ``rows``: those holding an active voxel labelled k (None: found here)."""
    if voxel_depth is not None and field.method == "surface":  # compiled, block by block
        rows, vals, act = field.piece_blocks(blocks, labels, k, voxel_depth, index_min, rows)
        return BlockGrid(blocks.voxel_size, blocks.background, blocks.origins[rows], vals, act)
    if rows is None:
        rows = np.nonzero((blocks.active & (labels == k)).any(axis=(1, 2, 3)))[0]
    act = blocks.active[rows] & (labels[rows] == k)
    vals = np.full(act.shape, np.float32(blocks.background))
    b, i, j, kk = np.nonzero(act)
    ijk = blocks.origins[rows][b] + np.stack([i, j, kk], axis=1)
    f = blocks.values[rows][b, i, j, kk].astype(np.float64)
    g = field.value(ijk * blocks.voxel_size)
    vals[b, i, j, kk] = rf.r_and(f, g, "r0").astype(np.float32)
    return BlockGrid(blocks.voxel_size, blocks.background, blocks.origins[rows], vals, act)
