"""hfrep: eikonal distance (FIM) -> ``surface`` level set, ``hfrep`` (hfrep eq. 21) and a
``density`` fog volume; field-quality numbers for the manifest.

Library calls: pipeline.eikonal.solve_distance / surface_grid, pipeline.hfrep.hfrep_blocks,
pipeline.quality.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from pipeline.grid import frep_to_vdb
from stages.base import StageParams

REQUIRES = ("voxelise",)


class Params(StageParams):
    solver: Literal["fim"] = "fim"
    smoothing: Literal["tricubic"] = "tricubic"
    step: Literal["sigmoid", "tanh", "rational"] = Field(default="sigmoid", description="C1 step of eq. 21")
    slope: float = Field(default=0.01, gt=0, description="slope of the step (eq. 23), FRep units")
    max_distance: float | Literal["domain"] | None = Field(
        default=None, description="how far outside to solve, world units; 'domain' = everywhere; default 10 voxels")
    density: bool = Field(default=True, description="also write a 'density' fog volume (0..1) for Blender")
    quality: bool = Field(default=True, description="field-quality report into the manifest")

    @field_validator("max_distance")
    @classmethod
    def _positive(cls, v):
        if isinstance(v, float) and v <= 0:
            raise ValueError("must be > 0")
        return v


def run(ctx, p: Params) -> dict:
    from pipeline.eikonal import solve_distance, surface_grid
    from pipeline.hfrep import density_grid, hfrep_blocks
    from pipeline.quality import field_report

    dom, frep = ctx.job.domain, ctx.blocks["frep"]
    h, band = dom.voxel_size, float(ctx.data["band"])
    maxd = 10 * h if p.max_distance is None else p.max_distance
    res = solve_distance(frep, maxd, (dom.index_min, dom.index_max), ctx.data["inside_boxes"])
    meta = ctx.grid_metadata("hfrep", p)
    surface = surface_grid(res, band)
    surface.updateMetadata(meta)
    hf = hfrep_blocks(frep, res, p.step, p.slope)
    hgrid = frep_to_vdb(hf, np.zeros((0, 2, 3), np.int64), "hfrep")
    hgrid.updateMetadata({**meta, "step": p.step, "slope": p.slope})
    ctx.grids["surface"], ctx.grids["hfrep"] = surface, hgrid
    ctx.blocks["hfrep"] = hf
    ctx.data["eikonal"] = res
    if p.density:
        ctx.grids["density"] = density_grid(res, band * h)
        ctx.grids["density"].updateMetadata(meta)
    if p.quality:
        ctx.manifest.setdefault("quality", {}).update(field_report(frep, res, hf))
    return dict(res.stats)
