"""Tests that open the exported files in the real programs: ParaView (pvpython), Blender, Chromium.

They are not part of `make test`: nothing here is collected unless FREPVDB_CLIENTS=1 (set by
`make test-clients`, which also installs the programs with apt when they are missing).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ENABLED = os.environ.get("FREPVDB_CLIENTS") == "1"
collect_ignore_glob = [] if ENABLED else ["test_*.py"]

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # tests/: the sample scene of test_export_files

TIMEOUT = 300  # seconds per program run


def require(program: str) -> str:
    """Absolute path of ``program``; fails (not skips) when absent: `make test-clients` installs it."""
    path = shutil.which(program)
    if path is None:
        pytest.fail(f"{program} is not installed; run `make test-clients` (it installs paraview, blender, "
                    f"chromium and xvfb with apt-get)")
    return path


def run(cmd: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run a client program; on a non-zero exit show its output in the failure."""
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT,
                          env={**os.environ, **(env or {})})
    if proc.returncode != 0:
        pytest.fail(f"{cmd[0]} exited {proc.returncode}\nstdout:\n{proc.stdout[-4000:]}\n"
                    f"stderr:\n{proc.stderr[-4000:]}")
    return proc


def with_display(cmd: list[str]) -> list[str]:
    """Prefix ``xvfb-run`` when there is no X display (Debian's ParaView renders through X only)."""
    if os.environ.get("DISPLAY"):
        return cmd
    return [require("xvfb-run"), "-a", "-s", "-screen 0 1280x1024x24", *cmd]


def foreground_fraction(png: Path) -> float:
    """Fraction of pixels that differ clearly from the image's corner (background) colour."""
    import matplotlib.image as mpimg

    img = mpimg.imread(png)[..., :3].astype(np.float64)
    background = img[0, 0]
    return float((np.abs(img - background).max(axis=2) > 0.08).mean())


@pytest.fixture(scope="session")
def outputs(tmp_path_factory) -> dict:
    """Every export file for the two-sphere scene, written by the pipeline's own writers."""
    from test_export_files import VOXEL, sample_grids, sample_manifest

    from pipeline import previews, report, vtkio
    from pipeline.grid import vdb
    from pipeline.vdbio import set_grid_metadata, write_vdb

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
