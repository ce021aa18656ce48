"""Reproduce Table 1 of bsp-fields.txt for the shared meshes: faces, planes, splits and set
operations of naive and optimised BSP-trees, plus evaluation speed (points/second, r0).

Usage: .venv/bin/python bench/bsp_table1.py [--max-faces N] [--points N] [mesh.off ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pipeline.bsp import BSPField
from pipeline.meshio import load_mesh

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("meshes", nargs="*", type=Path)
    ap.add_argument("--max-faces", type=int, default=20000)
    ap.add_argument("--points", type=int, default=20000)
    args = ap.parse_args()
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
