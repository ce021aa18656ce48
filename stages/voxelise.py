"""voxelise: the model tree -> the sparse ``frep`` grid (pipeline.voxelise)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.grid import frep_to_vdb
from pipeline.voxelise import voxelise
from stages.base import StageParams


class Params(StageParams):
    band: float = Field(default=3.0, gt=0, le=64, description="narrow-band half-width in voxels")
    block: Literal[2, 4, 8] = Field(default=4, description="voxels per side of an evaluated block")


def run(ctx, p: Params) -> dict:
    dom = ctx.job.domain
    res = voxelise(ctx.job.model, dom.index_min, dom.index_max, dom.voxel_size, p.band, p.block,
                   ctx.job.t, progress=ctx.progress)
    grid = frep_to_vdb(res.blocks, res.inside_boxes, "frep")
    grid.updateMetadata({**ctx.grid_metadata("voxelise", p), "band_voxels": float(p.band)})
    ctx.grids["frep"] = grid
    ctx.blocks["frep"] = res.blocks
    ctx.data["inside_boxes"] = res.inside_boxes
    ctx.data["band"] = p.band
    return res.stats
