"""export: the grids the stages made -> .vdb, VTK files, previews and report.html.

Library calls: pipeline.io.vdbio.write_vdb_beside, pipeline.io.vtkio.write_vtk_outputs,
pipeline.io.previews.write_previews, pipeline.io.report.write_report (after the manifest).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from pipeline.io.meshout import export_meshes
from pipeline.io.report import write_report
from pipeline.io.vdbio import write_vdb_beside
from stages.base import FrepBand, StageParams, band_only

REQUIRES = (FrepBand,)
VTKKind = Literal["vti", "vtp", "vtu", "ply", "obj"]


class Params(StageParams):
    vdb: bool = True
    grids: list[str] | None = Field(default=None, description="grid names to write (default: all)")
    half_float: bool | list[str] = Field(default=False, description="16-bit storage: all float grids or a list")
    vtk: list[VTKKind] = Field(default_factory=list, description="VTK files: vti vtp vtu ply obj")
    max_points: int = Field(default=16_000_000, gt=0, description="largest .vti; beyond it a stride is used")
    adaptivity: float = Field(default=0.0, ge=0, le=1, description="volumeToMesh adaptivity for the surface")
    previews: bool = False
    report: bool = Field(default=True, description="report.html (with previews when they are made)")
    mesh: list[Literal["stl", "3mf", "ply", "obj"]] = Field(
        default_factory=list, description="printable meshes of the zero set (pipeline.io.meshout): <name>_mesh.<kind>")
    mesh_per_component: bool = Field(default=False, description="also one mesh per component (components stage)")


def grids(p: Params) -> list[str]:
    return []


estimate_bytes = band_only


def run(ctx, p: Params) -> dict:
    names = [n for n in ctx.grids if p.grids is None or n in p.grids]
    grids = {n: ctx.grids[n] for n in names}
    stats: dict = {"grids": names}
    pending = None
    if p.vdb:  # written by a child process while the VTK files and previews are made here
        path = ctx.out_dir / f"{ctx.job.name}.vdb"
        pending = write_vdb_beside(path, list(grids.values()), {
            "creator": "frepvdb", "config": ctx.job.name, "config_sha256": ctx.job.config_sha256},
            half_float=p.half_float)
        ctx.add_output(path, "vdb")
    try:
        _files_beside_vdb(ctx, p, grids, stats)
    except BaseException:
        if pending is not None:
            pending.cancel()
        raise
    if pending is not None:
        pending.wait()
    if p.report:
        ctx.after_manifest.append(_write_report)
        ctx.outputs.append({"path": "report.html", "kind": "report"})
    return stats


def _files_beside_vdb(ctx, p: Params, grids: dict, stats: dict) -> None:
    """VTK files, printable meshes and previews (they read the grids, as the .vdb writer does)."""
    mesh = None
    if p.vtk:
        from pipeline.io.vtkio import write_vtk_outputs  # VTK takes ~1 s to import: only when asked for

        entries, mesh = write_vtk_outputs(ctx.out_dir, ctx.job.name, grids, ctx.voxel_size, p.vtk,
                                          max_points=p.max_points, adaptivity=p.adaptivity)
        for e in entries:
            ctx.add_output(ctx.out_dir / Path(e["path"]).name, e["kind"], **{k: v for k, v in e.items()
                                                                         if k not in ("path", "kind")})
        stats["vtk"] = [e["path"] for e in entries]
    if p.mesh:
        stats["mesh"] = export_meshes(ctx, ctx.grids, p.mesh, p.mesh_per_component)
    if p.previews:
        from pipeline.io.previews import write_previews  # matplotlib: only when previews are asked for

        for png in write_previews(ctx.out_dir / "previews", grids, ctx.voxel_size, mesh=mesh):
            ctx.add_output(png, "preview")


def _write_report(ctx, manifest: dict) -> None:
    write_report(ctx.out_dir / "report.html", manifest)
