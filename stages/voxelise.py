"""voxelise: the model tree -> the sparse ``frep`` grid (pipeline.voxel.voxelise).

With ``bricks:`` in the config, the domain is split into bricks that workers voxelise (each
loads the job itself and sends back its blocks as NumPy arrays); the blocks are assembled here
into one grid, identical to the unsplit run.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.io.vdbgrids import frep_to_vdb
from pipeline.sparse.grid import LEAF
from pipeline.voxel.voxelise import (
    assemble,
    block_for,
    bricks_for,
    estimate_band_bytes,
    exact_in_reach,
    merge_samples,
    root_size_for,
    sample_blocks,
    voxelise,
)
from stages.base import BandEstimate, FrepBand, StageParams, band_only

PRODUCES = (FrepBand,)
ROOT_CELL_BYTES = 160  # per top-level cell of the enumeration: its index arrays, boxes and bounds


class Params(StageParams):
    band: float = Field(default=3.0, gt=0, le=64, description="narrow-band half-width in voxels")
    block: Literal["auto", 2, 4, 8] = Field(
        default="auto", description="voxels per side of an evaluated block; auto: 8 (one leaf), 4 for models with "
        "meshes or oracle nodes, 2 for a mesh much finer than the voxels (pipeline.voxel.voxelise.block_for)")


def run(ctx, p: Params) -> dict:
    job, dom = ctx.job, ctx.job.domain
    imin, imax, h = dom.index_min, dom.index_max, dom.voxel_size
    block = block_for(job.model, p.block, h)
    if job.bricks:
        root = root_size_for(dom.dims, block)
        tasks = [(lo, hi, root, p.band, block) for lo, hi in bricks_for(imin, imax, job.bricks, block)]
        refine = exact_in_reach(job.model, h, job.t)  # bricks sample the sign proxy, if it has one
        res = assemble(merge_samples(ctx.map_with(sample_brick, tasks)), imin, imax, h, p.band, refine)
    else:
        res = voxelise(job.model, imin, imax, h, p.band, block, job.t, progress=ctx.progress)
    grid = frep_to_vdb(res.blocks, res.inside_boxes, "frep", outside_boxes=res.outside_boxes, domain=(imin, imax))
    grid.updateMetadata({**ctx.grid_metadata("voxelise", p), "band_voxels": float(p.band)})
    ctx.grids["frep"] = grid
    # every voxel of the leaves holds a value of its true sign (evaluated, or +-background by its
    # cell's proof; mark_band puts each sign change in the band): hfrep needs no flood fill
    ctx.put(FrepBand(res.blocks, res.inside_boxes, p.band, signed=True))
    return res.stats


def grids(p: Params) -> list[str]:
    return ["frep"]


estimate_bytes = band_only  # the band estimate is this stage's own peak


def enumeration_bytes(job, p: Params) -> tuple[float, str]:
    """Memory of the top-level cells every voxelisation (and :func:`estimate_band`) enumerates,
    counted in floats (a huge domain must not overflow an integer)."""
    # the top cells do not depend on a block of at most a leaf: no trace of the model here
    root = root_size_for(job.domain.dims, LEAF)
    roots = float(np.prod(np.ceil(job.domain.dims / root) + 1))
    return roots * ROOT_CELL_BYTES, f"the {roots:.3g} top-level cells of voxelise"


def estimate_band(job, p: Params) -> BandEstimate:
    return BandEstimate(estimate_band_bytes(job.model, job.domain, p.band, job.t), float(p.band))


def sample_brick(job, task):
    """Worker side of a bricked voxelise: sample the blocks of one brick of ``job``."""
    lo, hi, root, band, block = task
    dom = job.domain
    s = sample_blocks(job.model.sign_proxy(), dom.index_min, dom.index_max, dom.voxel_size, band, block, job.t,
                      root_size=root, clip=(lo, hi))
    s.values = s.values.astype("float32")  # halves the transfer; the grid stores float32 anyway
    return s
