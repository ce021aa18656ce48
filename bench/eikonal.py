"""Benchmark: block FIM (pipeline.distance.eikonal) vs scikit-fmm's dense fast marching on a sphere.

For each resolution n (domain [-1, 1]^3, n voxels per side, sphere of radius 0.6 off the
grid's symmetry): scikit-fmm ``distance`` (order 1 and 2) on the dense array of the exact
signed distance; our solver on the dense domain (``max_distance=None``) and sparse
(``max_distance = 3 voxels``: band plus the whole interior). Errors are against the
analytic distance, over every voxel (dense runs) and over the voxels the sparse run solves
(inside plus 3 voxels out), so all columns compare like with like. Our solver runs with the
first-order scheme and with the default second-order one; the ratios are against
scikit-fmm order 1 and order 2.

    .venv/bin/python bench/eikonal.py --sizes 128 256 512 --skfmm-max 256 --order2-max 256
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np
import skfmm

from pipeline.distance.eikonal import signed_distance_blocks, solve_distance
from pipeline.sparse.grid import LEAF, BlockGrid

CENTRE = np.array([0.013, -0.021, 0.007])
RADIUS = 0.6


def exact(p: np.ndarray) -> np.ndarray:
    """Signed distance, level-set convention (negative inside)."""
    return np.linalg.norm(p - CENTRE, axis=-1) - RADIUS


def frep_band(n: int, band: float = 3.0) -> tuple[BlockGrid, tuple[np.ndarray, np.ndarray]]:
    """frep (positive inside) on the leaves near the sphere only (as the voxeliser makes it)."""
    h = 2.0 / n
    lo = np.full(3, -(n // 2), dtype=np.int64)
    hi = lo + n - 1
    axes = [np.arange(lo[a] >> 3, (hi[a] >> 3) + 1) for a in range(3)]
    origins = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) << 3
    centre = (origins + 3.5) * h
    near = np.abs(exact(centre)) < (band + 4 * np.sqrt(3)) * h
    origins = origins[near]
    r = np.arange(LEAF)
    ijk = origins[:, None, None, None, :] + np.stack(np.meshgrid(r, r, r, indexing="ij"), -1)[None]
    f = -exact(ijk * h)
    act = (np.abs(f) < band * h) & np.all((ijk >= lo) & (ijk <= hi), axis=-1)
    keep = act.reshape(len(origins), -1).any(axis=1)
    return BlockGrid(h, band * h, origins[keep], f[keep].astype(np.float32), act[keep]), (lo, hi)


def errors(values: np.ndarray, ref: np.ndarray, h: float) -> str:
    e = np.abs(values - ref)
    return f"{e.max() / h:6.3f} {e.mean() / h:7.4f}"


def run_ours(n: int, max_vox: float | None, order: int = 2) -> tuple[float, str, str, dict]:
    frep, dom = frep_band(n)
    h = 2.0 / n
    t = time.perf_counter()
    res = solve_distance(frep, None if max_vox is None else max_vox * h, dom, order=order)
    seconds = time.perf_counter() - t
    ijk, v = signed_distance_blocks(res).active_voxels()
    ref = exact(ijk * h)
    sub = ref <= 3 * h
    return seconds, errors(v, ref, h), errors(v[sub], ref[sub], h), res.stats


def run_skfmm(n: int, order: int) -> tuple[float, str, str]:
    h = 2.0 / n
    x = (np.arange(n) - n // 2) * h
    dx, dy, dz = (x - CENTRE[a] for a in range(3))
    ref = np.sqrt(dx[:, None, None] ** 2 + dy[None, :, None] ** 2 + dz[None, None, :] ** 2) - RADIUS
    t = time.perf_counter()
    phi = skfmm.distance(ref, dx=h, order=order)
    seconds = time.perf_counter() - t
    sub = ref <= 3 * h
    out = seconds, errors(phi, ref, h), errors(phi[sub], ref[sub], h)
    del phi, ref
    gc.collect()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--skfmm-max", type=int, default=512, help="largest n for scikit-fmm order 1")
    ap.add_argument("--order2-max", type=int, default=256, help="largest n for scikit-fmm order 2")
    args = ap.parse_args()
    run_ours(32, 3.0)  # JIT warm-up (cached kernels load)
    print("errors in voxels: max mean over all voxels | max mean over inside + 3 voxels out")
    print(f"{'n':>4} {'method':<26} {'seconds':>8} {'all: max  mean':>15} {'sparse set: max mean':>22}"
          f" {'vs skfmm1':>9} {'vs skfmm2':>9}")
    for n in args.sizes:
        base = {}
        rows = []
        for order, limit in ((1, args.skfmm_max), (2, args.order2_max)):
            if n <= limit:
                s, e_all, e_sub = run_skfmm(n, order)
                base[order] = s
                rows.append((f"skfmm order {order} (dense)", s, e_all, e_sub))
        for order in (1, 2):
            s, e_all, e_sub, _ = run_ours(n, None, order)
            rows.append((f"FIM order {order} dense", s, e_all, e_sub))
            s, e_all, e_sub, st = run_ours(n, 3.0, order)
            rows.append((f"FIM order {order} sparse ({st['blocks']} blk)", s, "     -       -", e_sub))
        for name, s, e_all, e_sub in rows:
            ratios = " ".join(f"{base[o] / s:8.1f}x" if o in base else "        -" for o in (1, 2))
            print(f"{n:4d} {name:<26} {s:8.2f} {e_all:>15} {e_sub:>22} {ratios}", flush=True)


if __name__ == "__main__":
    main()
