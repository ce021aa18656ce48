"""The sign of the WRITTEN frep grid against trimesh containment, everywhere (issue 12).

For every closed mesh (../shared/meshes, or the paths given), every R-function family and each
resolution: run the job through the CLI's runner (voxelise band 3, export vdb), read the .vdb
back with pyopenvdb and compare the sign of the stored value at random points of the padded
domain box — active voxels, inactive tiles and background alike — with trimesh containment, at
points farther than 1.5 voxels from the surface. Prints one row per case:

    mesh faces family res  seconds  grid_min grid_max background  agree  points

Usage: ``.venv/bin/python bench/written_sign.py [--res 32 64] [--max-faces 1500] [mesh.off ...]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.io.vdbgrids import vdb  # noqa: E402
from pipeline.job.config import load_job  # noqa: E402
from pipeline.job.runner import run_job  # noqa: E402

MESHES = ROOT.parent / "shared" / "meshes"
FAMILIES = ("r0", "min_max", "sardf")

CONFIG = """name: {name}
domain:
  bounds: [{lo}, {hi}]
  resolution: {res}
model:
  mesh: {{path: {path}, rfunc: {family}, planes: optimised}}
stages:
  - voxelise: {{band: 3}}
  - export: {{vdb: true}}
"""


def padded_bounds(mesh: trimesh.Trimesh, pad: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = mesh.bounds
    ext = float(np.max(hi - lo))
    return lo - pad * ext, hi + pad * ext


def written_values(vdb_path: Path, points: np.ndarray, grid: str = "frep") -> tuple[np.ndarray, object]:
    """Values of the written grid at the voxels nearest to ``points`` (active or not)."""
    g = vdb.read(str(vdb_path), grid)
    h = g.transform.voxelSize()[0]
    acc = g.getConstAccessor()
    ijk = np.rint(points / h).astype(int)
    vals = np.array([acc.getValue(tuple(int(c) for c in q)) for q in ijk])
    return vals, g


def sign_check(mesh: trimesh.Trimesh, vdb_path: Path, lo, hi, h: float, n: int = 3000, seed: int = 0,
               grid: str = "frep", inside_positive: bool = True) -> dict:
    """Fraction of random points > 1.5 voxels from the surface whose written sign is containment."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(lo, hi, (n, 3))
    p = np.rint(p / h) * h  # voxel centres: the value read back is the value of that voxel
    _, dist, _ = trimesh.proximity.closest_point(mesh, p)
    p = p[dist > 1.5 * h]
    inside = mesh.contains(p)
    vals, g = written_values(vdb_path, p, grid)
    got = vals > 0 if inside_positive else vals < 0
    vmin, vmax = g.evalMinMax()
    return {"agree": float(np.mean((got == inside) & np.isfinite(vals))), "points": int(len(p)),
            "finite": bool(np.all(np.isfinite(vals)) and np.isfinite(vmin) and np.isfinite(vmax)),
            "min": float(vmin), "max": float(vmax), "background": float(g.background),
            "wrong": p[(got != inside) | ~np.isfinite(vals)]}


def run_case(mesh_path: Path, family: str, res: int, work: Path) -> dict:
    mesh = trimesh.load(str(mesh_path), force="mesh")
    lo, hi = padded_bounds(mesh)
    name = f"{mesh_path.stem}_{family}_{res}"
    cfg = work / f"{name}.yaml"
    cfg.write_text(CONFIG.format(name=name, lo=list(map(float, lo)), hi=list(map(float, hi)), res=res,
                                 path=mesh_path.resolve(), family=family))
    t0 = time.perf_counter()
    job = load_job(cfg)
    run_job(job, work / "out")
    secs = time.perf_counter() - t0
    res_ = sign_check(mesh, work / "out" / name / f"{name}.vdb", lo, hi, job.domain.voxel_size)
    res_.update(mesh=mesh_path.stem, faces=len(mesh.faces), family=family, res=res, seconds=secs)
    return res_


def closed_meshes(max_faces: int) -> list[Path]:
    out = []
    for p in sorted(MESHES.glob("*.off")):
        m = trimesh.load(str(p), force="mesh")
        if m.is_watertight and len(m.faces) <= max_faces:
            out.append(p)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("meshes", nargs="*", type=Path)
    ap.add_argument("--res", nargs="+", type=int, default=[32, 64])
    ap.add_argument("--families", nargs="+", default=list(FAMILIES))
    ap.add_argument("--max-faces", type=int, default=1500)
    args = ap.parse_args()
    meshes = args.meshes or closed_meshes(args.max_faces)
    print(f"{'mesh':<14}{'faces':>7} {'family':<8}{'res':>5}{'seconds':>9} {'grid min':>11} {'grid max':>11}"
          f" {'background':>11} {'agree':>8} {'points':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        for mp in meshes:
            for fam in args.families:
                for res in args.res:
                    r = run_case(mp, fam, res, Path(tmp))
                    print(f"{r['mesh']:<14}{r['faces']:>7} {fam:<8}{res:>5}{r['seconds']:>9.2f} {r['min']:>11.3g}"
                          f" {r['max']:>11.3g} {r['background']:>11.3g} {100 * r['agree']:>7.2f}% {r['points']:>7}",
                          flush=True)


if __name__ == "__main__":
    main()
