"""Benchmark (issue 13): mesh -> frep grid with `frepvdb run` vs OpenVDB's meshToVolume, same run.

    .venv/bin/python bench/mesh.py [--quick] [--res 64 256 512] [--meshes anchor ico20k ...]
                                   [--max-faces F] [--timeout S] [--rfuncs r0 min_max]

For every mesh and resolution N, the voxel size is h = extent / N, extent = the longest side of
the mesh's bounding box padded by 10 % on each side. At that h, in this run:

* anchor 1: ``vdb_tool -read mesh.obj -mesh2ls voxel=h width=3 -write out.vdb`` (Debian
  ``libopenvdb-tools``; the .off is converted to .obj with trimesh first), wall time of the
  process;
* anchor 2: pyopenvdb's ``FloatGrid.createLevelSetFromPolygons(points, triangles, transform,
  halfWidth=3)`` in a child Python process, the call alone timed;
* ours: the whole process ``frepvdb run`` on ``mesh: {path, rfunc, planes: optimised}``,
  voxelise band 3, export vdb, wall time minus the start-up of a trivial run (a tiny sphere at
  8^3, printed separately), for ``rfunc: r0`` and ``rfunc: min_max``.

Sign agreement: 3000 random points of the padded box, each moved to its voxel centre and kept
only farther than 1.5 voxels from the surface; the value read back from our written ``frep``
grid (positive inside) and from the mesh2ls level set (negative inside) is compared with mesh
containment: ``trimesh.contains`` for the CGAL meshes; for the generated icospheres (trimesh
without embree needs minutes per 3000 points there) the radial inequality |p| < r(p/|p|) of the
displacement, whose distance to the triangulated surface is far below 1.5 voxels. Peak RSS of
every child is ``/usr/bin/time -f %M``. A run over ``--timeout`` is killed and printed as
"> T s (stopped)". Prints one Markdown table; meshes over ``--max-faces`` are listed as skipped.

Meshes: the closed CGAL meshes of ../shared/meshes (anchor, pinion, blobby, couplingdown,
elephant, knot2, fandisk: 1k-13k faces) and noise-displaced icospheres (radial displacement
0.05 sin(5x) sin(7y) sin(6z)) of subdivision 5..8: ico20k, ico80k, ico320k, ico1.3M; torus50k, the
marching-cubes surface of a noisy torus formula (genus 1, ~50k faces; sign reference: the
formula, farther than its Lipschitz bound allows the surface to be).
Default (about 10 minutes on 2 cores): anchor pinion blobby elephant fandisk ico20k torus50k at 64^3,
timeout 45 s, --max-faces 60000. Everything: ``--meshes all --max-faces 2000000 --res 64 256
512 --timeout 1800``. ``--quick``: anchor at 32^3 (about 20 s).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from pipeline.io.vdbgrids import vdb  # noqa: E402

MESH_DIR = ROOT.parent / "shared" / "meshes"
FREPVDB = ROOT / ".venv" / "bin" / "frepvdb"
CGAL = ("anchor", "pinion", "couplingdown", "blobby", "elephant", "knot2", "fandisk")
ICO = {"ico20k": 5, "ico80k": 6, "ico320k": 7, "ico1.3M": 8}
TORUS = {"torus50k": 100}  # marching-cubes grid points per side of the bumpy torus
DEFAULT = ("anchor", "pinion", "blobby", "elephant", "fandisk", "ico20k", "torus50k")  # one per size class
AMPLITUDE = 0.05
POINTS = 3000

CONFIG = """name: {name}
domain:
  bounds: [{lo}, {hi}]
  voxel_size: {h!r}
model:
  mesh: {{path: {path}, rfunc: {rfunc}, planes: optimised}}
stages:
  - voxelise: {{band: 3}}
  - export: {{vdb: true}}
"""

TINY = """name: tiny
domain:
  bounds: [[-1, -1, -1], [1, 1, 1]]
  resolution: 8
model:
  sphere: {radius: 0.5}
stages:
  - voxelise: {band: 3}
  - export: {vdb: true}
"""


@dataclass
class Run:
    """One timed child process: wall seconds, peak RSS (MiB), 'ok' | 'stopped' | 'failed: ...'."""

    seconds: float | None
    rss_mib: float | None
    status: str
    stdout: str = ""


@dataclass
class Case:
    name: str
    mesh: trimesh.Trimesh
    off: Path
    obj: Path
    lo: np.ndarray
    hi: np.ndarray
    results: dict[str, Run] = field(default_factory=dict)


# --- child processes -----------------------------------------------------------------------------

def timed(cmd: list[str], timeout: float, cwd: Path | None = None) -> Run:
    """Run ``cmd`` under /usr/bin/time in its own session; kill the whole group on timeout."""
    with tempfile.NamedTemporaryFile(suffix=".rss", delete=False) as f:
        rss_file = Path(f.name)
    full = ["/usr/bin/time", "-o", str(rss_file), "-f", "%M", *cmd]
    t0 = time.perf_counter()
    p = subprocess.Popen(full, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd,
                         start_new_session=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        rss_file.unlink(missing_ok=True)
        return Run(None, None, "stopped")
    dt = time.perf_counter() - t0
    rss = _read_rss(rss_file)
    if p.returncode != 0:
        tail = (err.strip().splitlines() or ["?"])[-1][:120]
        return Run(dt, rss, f"failed (exit {p.returncode}): {tail}", out)
    return Run(dt, rss, "ok", out)


def _read_rss(path: Path) -> float | None:
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip().isdigit()]
    finally:
        path.unlink(missing_ok=True)
    return int(lines[-1]) / 1024 if lines else None


def cls_child(obj: str, h: float) -> None:
    """Child mode: time createLevelSetFromPolygons alone (mesh loading excluded); print JSON."""
    mesh = trimesh.load(obj, force="mesh", process=False)
    pts = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    tris = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    xform = vdb.createLinearTransform(voxelSize=h)
    t0 = time.perf_counter()
    grid = vdb.FloatGrid.createLevelSetFromPolygons(pts, triangles=tris, transform=xform, halfWidth=3.0)
    dt = time.perf_counter() - t0
    print(json.dumps({"seconds": dt, "active": int(grid.activeVoxelCount())}))


# --- meshes --------------------------------------------------------------------------------------

def icosphere(k: int) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=k)
    return trimesh.Trimesh(m.vertices * radius(m.vertices)[:, None], m.faces, process=False)


def radius(u: np.ndarray) -> np.ndarray:
    """Displaced radius at unit directions ``u`` (rows)."""
    return 1.0 + AMPLITUDE * np.sin(5 * u[:, 0]) * np.sin(7 * u[:, 1]) * np.sin(6 * u[:, 2])


def torus_field(p: np.ndarray) -> np.ndarray:
    """A torus (R 0.7, r 0.3) with a noise of amplitude 0.03 (genus 1, not convex), > 0 inside;
    Lipschitz constant at most 1 + 0.03 sqrt(8^2 + 9^2 + 7^2) < 1.42."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return (0.3 - np.sqrt((np.sqrt(x ** 2 + y ** 2) - 0.7) ** 2 + z ** 2)
            + 0.03 * np.sin(8 * x) * np.sin(9 * y) * np.sin(7 * z))


def bumpy_torus(n: int) -> trimesh.Trimesh:
    """The zero set of :func:`torus_field` by VTK's flying edges on n^3 points of [-1.1, 1.1]^3
    (n = 100: about 50k faces)."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

    ax = np.linspace(-1.1, 1.1, n)
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    img = vtk.vtkImageData()
    img.SetDimensions(n, n, n)
    img.SetSpacing(*[float(ax[1] - ax[0])] * 3)
    img.SetOrigin(-1.1, -1.1, -1.1)
    vals = torus_field(grid).reshape(n, n, n)
    img.GetPointData().SetScalars(numpy_to_vtk(vals.ravel(order="F"), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.0)
    fe.Update()
    poly = fe.GetOutput()
    verts = vtk_to_numpy(poly.GetPoints().GetData()).astype(float)
    tris = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    return trimesh.Trimesh(verts, tris, process=True)


def load_case(name: str, folder: Path) -> Case:
    if name in ICO or name in TORUS:
        mesh = icosphere(ICO[name]) if name in ICO else bumpy_torus(TORUS[name])
        off = folder / f"{name}.off"
        mesh.export(off)
    else:
        off = MESH_DIR / f"{name}.off"
        mesh = trimesh.load(off, force="mesh")
    obj = folder / f"{name}.obj"
    mesh.export(obj)
    lo, hi = mesh.bounds
    ext = float(np.max(hi - lo))
    return Case(name, mesh, off, obj, lo - 0.1 * ext, hi + 0.1 * ext)


def face_count(name: str) -> int:
    if name in ICO:
        return 20 * 4 ** ICO[name]
    if name in TORUS:
        return 50_000
    return len(trimesh.load(MESH_DIR / f"{name}.off", force="mesh").faces)


def voxel_size(case: Case, res: int) -> float:
    return float(np.max(case.hi - case.lo)) / res


# --- the runs ------------------------------------------------------------------------------------

def run_mesh2ls(case: Case, h: float, folder: Path, timeout: float) -> tuple[Run, Path]:
    out = folder / f"{case.name}_mesh2ls.vdb"
    cmd = ["vdb_tool", "-read", str(case.obj), "-mesh2ls", f"voxel={h!r}", "width=3", "-write", str(out)]
    if shutil.which("vdb_tool") is None:
        return Run(None, None, "failed: vdb_tool not installed (apt-get install libopenvdb-tools)"), out
    return timed(cmd, timeout), out


def run_cls(case: Case, h: float, timeout: float) -> Run:
    r = timed([sys.executable, __file__, "--cls", str(case.obj), repr(h)], timeout)
    if r.status == "ok":
        r.seconds = float(json.loads(r.stdout.strip().splitlines()[-1])["seconds"])
    return r


def run_ours(case: Case, h: float, rfunc: str, folder: Path, timeout: float) -> tuple[Run, Path]:
    name = f"{case.name}_{rfunc}"
    cfg = folder / f"{name}.yaml"
    cfg.write_text(CONFIG.format(name=name, lo=list(map(float, case.lo)), hi=list(map(float, case.hi)), h=h,
                                 path=str(case.off), rfunc=rfunc))
    run = timed([str(FREPVDB), "run", str(cfg), "--out", str(folder / "out"), "--force"], timeout)
    return run, folder / "out" / name / f"{name}.vdb"


def startup(folder: Path) -> Run:
    cfg = folder / "tiny.yaml"
    cfg.write_text(TINY)
    timed([str(FREPVDB), "run", str(cfg), "--out", str(folder / "out"), "--force"], 120)  # warm caches
    return timed([str(FREPVDB), "run", str(cfg), "--out", str(folder / "out"), "--force"], 120)


# --- sign agreement ------------------------------------------------------------------------------

def sample_points(case: Case, h: float, seed: int = 13) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centres of random points of the padded box farther than 1.5 h from the surface, and
    their containment."""
    rng = np.random.default_rng(seed)
    ijk = np.rint(rng.uniform(case.lo, case.hi, size=(3 * POINTS, 3)) / h).astype(np.int64)
    centres = ijk * h
    if case.name in ICO:
        r = np.linalg.norm(centres, axis=1)
        gap = r - radius(centres / np.maximum(r, 1e-12)[:, None])
        far = 0.9 * np.abs(gap) > 1.5 * h  # |grad r| <= 0.05 * sqrt(5^2+7^2+6^2) < 0.55: 0.9 is safe
        keep = np.flatnonzero(far)[:POINTS]
        return ijk[keep], gap[keep] < 0
    if case.name in TORUS:  # the formula's sign, farther than 1.5 h (Lipschitz 1.42) + the mesh's error
        g = torus_field(centres)
        keep = np.flatnonzero(np.abs(g) > 1.42 * 1.5 * h + 2e-3)[:POINTS]
        return ijk[keep], g[keep] > 0
    dist = trimesh.proximity.closest_point(case.mesh, centres)[1]
    keep = np.flatnonzero(dist > 1.5 * h)[:POINTS]
    return ijk[keep], case.mesh.contains(centres[keep])


def agreement(vdb_path: Path, grid_name: str | None, ijk: np.ndarray, inside: np.ndarray,
              positive_inside: bool) -> float | None:
    if not vdb_path.exists():
        return None
    grid = vdb.readAll(str(vdb_path))[0][0] if grid_name is None else vdb.read(str(vdb_path), grid_name)
    acc = grid.getConstAccessor()
    vals = np.array([acc.getValue(tuple(int(c) for c in p)) for p in ijk])
    sign_inside = vals > 0 if positive_inside else vals < 0
    return 100.0 * float(np.mean(sign_inside == inside))


# --- table ---------------------------------------------------------------------------------------

def fmt_run(r: Run | None, timeout: float, minus: float = 0.0) -> str:
    if r is None:
        return "-"
    if r.status == "stopped":
        return f"> {timeout:.0f} s (stopped)"
    if r.status != "ok" or r.seconds is None:
        return r.status.split(":")[0]  # the message is printed in a comment line above the row
    if minus:
        return f"{r.seconds - minus:.2f} (wall {r.seconds:.2f})"  # < 0: within the start-up's noise
    return f"{r.seconds:.2f}"


def fmt_ratio(ours: Run | None, anchor: Run | None, minus: float) -> str:
    if ours is None or anchor is None or anchor.status != "ok" or not anchor.seconds:
        return "-"
    if ours.status == "stopped" and anchor.seconds:
        return "> stopped"
    if ours.status != "ok" or ours.seconds is None:
        return "-"
    if ours.seconds <= minus:
        return "(below start-up noise)"
    return f"{(ours.seconds - minus) / anchor.seconds:.1f}x"


def fmt_pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def fmt_rss(runs: list[Run | None]) -> str:
    return " / ".join("-" if r is None or r.rss_mib is None else f"{r.rss_mib:.0f}" for r in runs)


HEADER = ("| mesh | faces | res | h | mesh2ls s | createLevelSetFromPolygons s | frepvdb r0 s | r0/mesh2ls |"
          " frepvdb min_max s | min_max/mesh2ls | sign ours % (r0 / min_max) | sign mesh2ls % |"
          " peak RSS MiB (mesh2ls / cLSFP / r0 / min_max) |\n|" + "---|" * 13)


def row(case: Case, res: int, h: float, res_: dict, signs: dict, start: float, timeout: float) -> str:
    a, c, r0, mm = (res_.get(k) for k in ("mesh2ls", "cls", "r0", "min_max"))
    ours_sign = " / ".join(fmt_pct(signs.get(k)) for k in ("r0", "min_max") if k in res_)
    return (f"| {case.name} | {len(case.mesh.faces):,} | {res} | {h:.4g} | {fmt_run(a, timeout)} |"
            f" {fmt_run(c, timeout)} | {fmt_run(r0, timeout, start)} | {fmt_ratio(r0, a, start)} |"
            f" {fmt_run(mm, timeout, start)} | {fmt_ratio(mm, a, start)} | {ours_sign} |"
            f" {fmt_pct(signs.get('mesh2ls'))} | {fmt_rss([a, c, r0, mm])} |")


def bench_case(case: Case, res: int, rfuncs: list[str], folder: Path, timeout: float,
               start: float) -> str:
    h = voxel_size(case, res)
    runs: dict[str, Run] = {}
    runs["mesh2ls"], anchor_vdb = run_mesh2ls(case, h, folder, timeout)
    runs["cls"] = run_cls(case, h, timeout)
    ours_vdb: dict[str, Path] = {}
    for rf in rfuncs:
        runs[rf], ours_vdb[rf] = run_ours(case, h, rf, folder, timeout)
    ijk, inside = sample_points(case, h)
    signs = {rf: agreement(ours_vdb[rf], "frep", ijk, inside, True) for rf in rfuncs if runs[rf].status == "ok"}
    if runs["mesh2ls"].status == "ok":
        signs["mesh2ls"] = agreement(anchor_vdb, None, ijk, inside, False)
    for key, r in runs.items():
        if r.status.startswith("failed"):
            print(f"<!-- {case.name} res {res} {key}: {r.status} -->", flush=True)
    return row(case, res, h, runs, signs, start, timeout)


def load_avg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one small mesh at 32^3 (smoke run, < 60 s)")
    ap.add_argument("--res", type=int, nargs="+", default=[64])
    ap.add_argument("--meshes", nargs="+", default=list(DEFAULT),
                    help=f"of {', '.join([*CGAL, *ICO])}, or 'all' (default: {' '.join(DEFAULT)})")
    ap.add_argument("--max-faces", type=int, default=60_000, help="skip larger meshes (default 60000)")
    ap.add_argument("--timeout", type=float, default=45.0, help="seconds per run (default 45)")
    ap.add_argument("--rfuncs", nargs="+", default=["r0", "min_max"], choices=["r0", "min_max", "sardf"])
    ap.add_argument("--cls", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.cls:
        cls_child(args.cls[0], float(args.cls[1]))
        return
    if args.quick:
        args.res, args.meshes, args.timeout = [32], ["anchor"], 40.0
    if args.meshes == ["all"]:
        args.meshes = [*CGAL, *ICO, *TORUS]
    run_all(args)


def run_all(args: argparse.Namespace) -> None:
    with tempfile.TemporaryDirectory(prefix="bench_mesh_") as tmp:
        folder = Path(tmp)
        start = startup(folder)
        if start.status != "ok" or start.seconds is None:
            print(f"frepvdb start-up run failed: {start.status}")
            return
        print(f"## Mesh -> grid: frepvdb vs OpenVDB meshToVolume (band 3, same h)\n\nload average at start:"
              f" {load_avg()} (2 cores; other processes share the machine)\n"
              f"frepvdb start-up (tiny sphere 8^3, whole process): {start.seconds:.2f} s,"
              f" peak RSS {start.rss_mib or 0:.0f} MiB; subtracted from the frepvdb columns\n"
              f"timeout per run: {args.timeout:.0f} s\n")
        print(HEADER, flush=True)
        skipped = []
        for name in args.meshes:
            faces = face_count(name)
            if faces > args.max_faces:
                skipped.append(f"{name} ({faces:,} faces)")
                continue
            case = load_case(name, folder)
            for res in args.res:
                print(bench_case(case, res, args.rfuncs, folder, args.timeout, start.seconds), flush=True)
        if skipped:
            print(f"\nskipped (over --max-faces {args.max_faces:,}): {', '.join(skipped)}")
        print(f"\nload average at end: {load_avg()}")


if __name__ == "__main__":
    main()
