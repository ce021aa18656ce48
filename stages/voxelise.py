"""voxelise: the model tree -> the sparse ``frep`` grid (pipeline.voxel.voxelise).

With ``bricks:`` in the config, the domain is split into bricks that workers voxelise (each
loads the job itself and sends back its blocks as NumPy arrays); the blocks are assembled here
into one grid, identical to the unsplit run.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.sparse.grid import frep_to_vdb
from pipeline.voxel.voxelise import assemble, bricks_for, merge_samples, root_size_for, sample_blocks, voxelise
from stages.base import FrepBand, StageParams, band_only


class Params(StageParams):
    band: float = Field(default=3.0, gt=0, le=64, description="narrow-band half-width in voxels")
    block: Literal[2, 4, 8] = Field(default=4, description="voxels per side of an evaluated block")


def run(ctx, p: Params) -> dict:
    job, dom = ctx.job, ctx.job.domain
    imin, imax, h = dom.index_min, dom.index_max, dom.voxel_size
    if job.bricks:
        root = root_size_for(dom.dims, p.block)
        tasks = [(lo, hi, root, p.band, p.block) for lo, hi in bricks_for(imin, imax, job.bricks, p.block)]
        res = assemble(merge_samples(ctx.map_with(sample_brick, tasks)), imin, imax, h, p.band)
    else:
        res = voxelise(job.model, imin, imax, h, p.band, p.block, job.t, progress=ctx.progress)
    grid = frep_to_vdb(res.blocks, res.inside_boxes, "frep", outside_boxes=res.outside_boxes, domain=(imin, imax))
    grid.updateMetadata({**ctx.grid_metadata("voxelise", p), "band_voxels": float(p.band)})
    ctx.grids["frep"] = grid
    # every voxel of the leaves holds a value of its true sign (evaluated, or +-background by its
    # cell's proof; close_band puts each sign change in the band): hfrep needs no flood fill
    ctx.put(FrepBand(res.blocks, res.inside_boxes, p.band, signed=True))
    return res.stats


def grids(p: Params) -> list[str]:
    return ["frep"]


estimate_bytes = band_only  # the loader's band estimate is this stage's own peak


def sample_brick(job, task):
    """Worker side of a bricked voxelise: sample the blocks of one brick of ``job``."""
    lo, hi, root, band, block = task
    dom = job.domain
    s = sample_blocks(job.model, dom.index_min, dom.index_max, dom.voxel_size, band, block, job.t,
                      root_size=root, clip=(lo, hi))
    s.values = s.values.astype("float32")  # halves the transfer; the grid stores float32 anyway
    return s
