"""Benchmark: flat whole-domain FIM (``max_distance: domain``) vs the hierarchical FIM
(pipeline.distance.hfim) on a sphere of radius 0.25 in the domain [-1, 1]^3 (n voxels per side).

Columns: solve time, time to build the OpenVDB grid, leaves, tiles, stored values
(leaves * 512 + tiles), the grid's ``memUsage``, and the max / mean error against the
analytic distance (world units and in voxels) over random far voxels (more than 16 voxels
outside the sphere, where hfim uses coarse cells). The flat grid is ``level_set_grid(surface_leaves(full=True))``.

    .venv/bin/python bench/hfim.py --sizes 128 256 --flat-max 256
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np

from pipeline.distance.eikonal import solve_distance, surface_leaves
from pipeline.distance.hfim import hierarchical_distance, hierarchical_tiles
from pipeline.io.vdbgrids import level_set_grid, stored_values, tiled_grid
from pipeline.sparse.grid import LEAF, BlockGrid

CENTRE = np.array([0.013, -0.021, 0.007])
RADIUS = 0.25
FAR_VOX = 16.0


def frep(p: np.ndarray) -> np.ndarray:
    return RADIUS - np.linalg.norm(p - CENTRE, axis=-1)


def frep_band(n: int, band: float = 3.0) -> tuple[BlockGrid, tuple[np.ndarray, np.ndarray]]:
    """frep (positive inside) on the leaves near the sphere only (as the voxeliser makes it)."""
    h = 2.0 / n
    lo = np.full(3, -(n // 2), dtype=np.int64)
    hi = lo + n - 1
    reach = RADIUS + (band + 2 * LEAF) * h
    b0 = ((np.floor((CENTRE - reach) / h).astype(np.int64)) >> 3) << 3
    b1 = ((np.ceil((CENTRE + reach) / h).astype(np.int64)) >> 3) << 3
    axes = [np.arange(b0[a], b1[a] + 1, LEAF) for a in range(3)]
    origins = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    r = np.arange(LEAF)
    local = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1)
    keep_o, vals, act = [], [], []
    for o in origins:
        f = frep((o + local) * h)
        a = np.abs(f) < band * h
        if a.any():
            keep_o.append(o)
            vals.append(f.astype(np.float32))
            act.append(a)
    return BlockGrid(h, band * h, np.array(keep_o), np.array(vals), np.array(act)), (lo, hi)


def far_points(n: int, lo, hi, count: int = 20000) -> np.ndarray:
    rng = np.random.default_rng(0)
    ijk = rng.integers(lo, hi + 1, size=(4 * count, 3))
    far = ijk[-frep(ijk * (2.0 / n)) > FAR_VOX * 2.0 / n]
    return far[:count]


def errors(grid, ijk: np.ndarray, h: float) -> tuple[float, float]:
    acc = grid.getConstAccessor()
    got = np.array([acc.getValue(tuple(int(x) for x in p)) for p in ijk])
    err = np.abs(got + frep(ijk * h))  # level-set sign: positive outside
    return float(err.max()), float(err.mean())


def run_flat(n: int) -> dict:
    band, (lo, hi) = frep_band(n)
    h = 2.0 / n
    t0 = time.perf_counter()
    res = solve_distance(band, "domain", (lo, hi))
    t1 = time.perf_counter()
    grid = level_set_grid(surface_leaves(res, 3.0, full=True), "surface")
    t2 = time.perf_counter()
    emax, emean = errors(grid, far_points(n, lo, hi), h)
    st = stored_values(grid)
    out = {"solver": "flat", "n": n, "solve_s": t1 - t0, "grid_s": t2 - t1, "leaves": st["leaves"], "tiles": 0,
           "stored": st["leaves"] * 512, "mem_MB": st["mem_bytes"] / 2**20, "emax": emax, "emean": emean, "h": h}
    del res, grid
    gc.collect()
    return out


def run_hfim(n: int) -> dict:
    band, (lo, hi) = frep_band(n)
    h = 2.0 / n
    t0 = time.perf_counter()
    res = hierarchical_distance(band, (lo, hi))
    t1 = time.perf_counter()
    grid = tiled_grid(*hierarchical_tiles(res), "distance", level_set=True)
    t2 = time.perf_counter()
    emax, emean = errors(grid, far_points(n, lo, hi), h)
    st = stored_values(grid)
    w = res.stats["written"]
    return {"solver": "hfim", "n": n, "solve_s": t1 - t0, "grid_s": t2 - t1, "leaves": w["leaves"],
            "tiles": w["leaf_tiles"] + w["big_tiles"], "stored": w["stored_values"],
            "mem_MB": st["mem_bytes"] / 2**20, "emax": emax, "emean": emean, "h": h}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--flat-max", type=int, default=256, help="largest n for the flat solve")
    args = ap.parse_args()
    hierarchical_distance(*frep_band(32))  # compile the Numba kernels outside the timings
    rows = []
    for n in args.sizes:
        if n <= args.flat_max:
            rows.append(run_flat(n))
        rows.append(run_hfim(n))
    head = (f"{'solver':6} {'n':>5} {'solve s':>8} {'grid s':>7} {'leaves':>7} {'tiles':>7} {'stored':>10} "
            f"{'mem MB':>8} {'far max err':>16} {'far mean err':>16}")
    print(head)
    for r in rows:
        print(f"{r['solver']:6} {r['n']:5d} {r['solve_s']:8.2f} {r['grid_s']:7.2f} {r['leaves']:7d} {r['tiles']:7d} "
              f"{r['stored']:10d} {r['mem_MB']:8.1f} {r['emax']:9.4f} ({r['emax'] / r['h']:4.1f}v) "
              f"{r['emean']:9.4f} ({r['emean'] / r['h']:4.1f}v)")
    by = {(r["solver"], r["n"]): r for r in rows}
    for n in args.sizes:
        if ("flat", n) in by:
            f, g = by[("flat", n)], by[("hfim", n)]
            print(f"n={n}: flat/hfim  time x{(f['solve_s'] + f['grid_s']) / (g['solve_s'] + g['grid_s']):.1f}, "
                  f"stored values x{f['stored'] / g['stored']:.1f}, memory x{f['mem_MB'] / g['mem_MB']:.1f}")
    for s in ("flat", "hfim"):
        ns = [n for n in args.sizes if (s, n) in by]
        for a, b in zip(ns, ns[1:], strict=False):
            print(f"{s}: stored values {a} -> {b}: x{by[(s, b)]['stored'] / by[(s, a)]['stored']:.2f}")


if __name__ == "__main__":
    main()
