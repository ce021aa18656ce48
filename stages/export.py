"""export: write the grids the stages made to <out>/<name>/<name>.vdb."""

from __future__ import annotations

from pydantic import Field

from pipeline.atomic import atomic_path
from pipeline.grid import vdb
from stages.base import StageParams

REQUIRES = ("voxelise",)


class Params(StageParams):
    vdb: bool = True
    grids: list[str] | None = Field(default=None, description="grid names to write (default: all)")
    half_float: bool = Field(default=False, description="store float grids as 16-bit half floats")


def run(ctx, p: Params) -> dict:
    stats: dict = {}
    if p.vdb:
        names = [n for n in ctx.grids if p.grids is None or n in p.grids]
        grids = [ctx.grids[n] for n in names]
        for g in grids:
            g.saveFloatAsHalf = p.half_float
        path = ctx.out_dir / f"{ctx.job.name}.vdb"
        with atomic_path(path) as tmp:
            vdb.write(str(tmp), grids=grids, metadata={"creator": "frepvdb", "config": ctx.job.name,
                                                      "config_sha256": ctx.job.config_sha256})
        ctx.add_output(path, "vdb")
        stats["vdb_grids"] = names
    return stats
