"""Reproduce Table 1 of bsp-fields.txt for the shared meshes: faces, planes, splits and set
operations of naive and optimised BSP-trees, plus evaluation speed (points/second, r0).

Usage: .venv/bin/python bench/bsp_table1.py [--max-faces N] [--points N] [mesh.off ...]
       .venv/bin/python bench/bsp_table1.py --generated [--max-faces N]

``--generated``: build scaling (section 3.3 build, pipeline.mesh.bsp_build) on icospheres of 5k, 20k,
80k, 320k and 1.3M faces displaced radially by 0.05 sin(5x) sin(7y) sin(6z) (not convex): build
seconds (merge, tree, special cases), nodes, depth, splits, and the time ratio per doubling of
faces (n log n gives about 2.1, n^2 gives 4).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import trimesh

from pipeline.mesh.bsp import BSPField
from pipeline.mesh.meshio import load_mesh

MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"


def _speed(field: BSPField, lo: np.ndarray, hi: np.ndarray, n: int) -> float:
    p = np.random.default_rng(0).uniform(lo, hi, (n, 3))
    field.evaluate(p[:8])
    t = time.perf_counter()
    field.evaluate(p)
    return n / (time.perf_counter() - t)


def row(path: Path, points: int) -> str:
    """One table row: both trees of one mesh."""
    mesh, rep = load_mesh(path)
    cells = [path.stem, str(rep.vertices), str(rep.faces)]
    for planes in ("naive", "optimised"):
        t = time.perf_counter()
        field = BSPField.from_mesh(mesh, rfunc="r0", planes=planes, seed=0)
        build = time.perf_counter() - t
        s = field.stats
        if planes == "naive":
            cells.append(str(s["planes"]))
        speed = _speed(field, *mesh.bounds, points)
        cells += [str(s["splits"]), str(s["set_operations"]), f"{build:.2f}", f"{speed:.3g}"]
    return "| " + " | ".join(cells) + " |"


def bumpy_sphere(subdivisions: int) -> trimesh.Trimesh:
    """Icosphere (20 * 4^s faces) displaced radially by a smooth noise."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = m.vertices
    r = 1.0 + 0.05 * np.sin(5 * v[:, 0]) * np.sin(7 * v[:, 1]) * np.sin(6 * v[:, 2])
    return trimesh.Trimesh(v * r[:, None], m.faces, process=False)


def generated(max_faces: int) -> None:
    """Build time against faces on displaced icospheres (subdivisions 4..8)."""
    BSPField.from_mesh(bumpy_sphere(1))  # compile outside the timings
    print("| faces | build s | nodes | depth | splits | special cases | time ratio per doubling |")
    print("|" + "---|" * 7)
    prev = None
    for sub in range(4, 9):
        mesh = bumpy_sphere(sub)
        if len(mesh.faces) > max_faces:
            break
        t = time.perf_counter()
        s = BSPField.from_mesh(mesh).stats
        dt = time.perf_counter() - t
        ratio = f"{(dt / prev[1]) ** (1 / np.log2(len(mesh.faces) / prev[0])):.2f}" if prev else "-"
        prev = (len(mesh.faces), dt)
        print(f"| {len(mesh.faces)} | {dt:.2f} | {s['nodes']} | {s['depth']} | {s['splits']} "
              f"| {s['special_cases']} | {ratio} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("meshes", nargs="*", type=Path)
    ap.add_argument("--max-faces", type=int, default=20000)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--generated", action="store_true", help="build scaling on displaced icospheres")
    args = ap.parse_args()
    if args.generated:
        generated(args.max_faces if args.max_faces != 20000 else 2_000_000)
        return
    paths = args.meshes or sorted(MESHES.glob("*.off"))
    print("| model | vertices | faces | planes | naive splits | naive set ops | naive build s "
          "| naive pts/s | opt splits | opt set ops | opt build s | opt pts/s |")
    print("|" + "---|" * 12)
    for path in paths:
        _, rep = load_mesh(path)
        if not rep.watertight or rep.faces > args.max_faces:
            continue
        print(row(path, args.points), flush=True)


if __name__ == "__main__":
    main()
