"""Tests that open the exported files in the real programs: ParaView (pvpython), Blender, Chromium.

They are not part of `make test`: nothing here is collected unless FREPVDB_CLIENTS=1 (set by
`make test-clients`, which also installs the programs with apt when they are missing).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ENABLED = os.environ.get("FREPVDB_CLIENTS") == "1"
collect_ignore_glob = [] if ENABLED else ["test_*.py"]

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests/: the sample scene


@pytest.fixture(scope="session")
def outputs(tmp_path_factory) -> dict:
    """Every export file for the two-sphere scene, written by the pipeline's own writers."""
    from test_export_files import VOXEL, sample_grids, sample_manifest

    from pipeline.io import previews, report, vtkio
    from pipeline.io.vdbgrids import vdb
    from pipeline.io.vdbio import set_grid_metadata, write_vdb

    out = tmp_path_factory.mktemp("spheres")
    grids = sample_grids()
    for g in grids.values():
        set_grid_metadata(g, {"config_name": "spheres"})
    write_vdb(out / "spheres.vdb", list(grids.values()), {"config": "spheres.yaml"})
    vti = vtkio.write_vti(out / "spheres.vti", grids, VOXEL)
    mesh = vtkio.extract_surface(grids, VOXEL)
    vtkio.write_vtp(out / "spheres.vtp", mesh)
    vtkio.write_ply(out / "spheres.ply", mesh)
    vtkio.write_obj(out / "spheres.obj", mesh)
    frames = []
    for t in range(3):  # a frame series: the frep grid of the spheres grown by 0.05 per frame
        frame = grids["frep"].deepCopy()
        frame.name = "frep"
        vdb.ax(f"@frep = @frep + {0.05 * t}f;", frame)
        vtkio.write_vti(out / f"frame_{t}.vti", {"frep": frame}, VOXEL)
        frames.append((float(t), f"frame_{t}.vti"))
    vtkio.write_pvd(out / "series.pvd", frames)
    paths = previews.write_previews(out / "previews", grids, VOXEL, mesh=mesh)
    report.write_report(out / "report.html", sample_manifest(grids))
    return {"dir": out, "grids": grids, "mesh": mesh, "vti": vti, "previews": paths, "voxel": VOXEL}
