"""Benchmark: sparse voxelise vs dense NumPy evaluation and OpenVDB AX, plus a scaling table.

    .venv/bin/python bench/voxelise.py [--quick] [--repeat N]

Default sizes 256^3 and 512^3 (each run in a fresh subprocess; sparse, dense and AX alternated
``--repeat`` times, default 3, and the medians printed with the ratio of every round: this VM's
speed drifts within minutes); ``--quick``: 128^3 only, once, every run inside this process (a
smoke run of under a minute; peak RSS is then cumulative).

1. Sparse voxelise (affine culling + block evaluation + VDB build) vs dense NumPy evaluation
   of the same model on every voxel of the domain, at 256^3 and 512^3: time, voxels evaluated.
2. The same field through OpenVDB AX (`pyopenvdb.ax`, C++ JIT over the same active voxels)
   as a throughput ceiling for per-voxel evaluation: our frep grid is written to a .vdb
   (pipeline.io.vdbio.write_vdb) and read back, and AX evaluates the same formula (sphere, torus,
   box, and configs/demo.yaml's superellipsoid minus a box written as AX code) over the active
   voxels of the read-back topology. A second table prints our voxelise time per active voxel
   (voxelise() alone, and with the VDB build) vs AX's time per active voxel, and the ratio.
   Both sides use the 2 cores (Numba kernels and AX's TBB threads); AX's time excludes its
   JIT compilation of the snippet is inside the timed call (included; the last column times the
   same snippet on an empty grid, i.e. the compilation alone).
   The 512^3 rows (default sizes) are the demo at 512^3 vs the dense NumPy evaluation.
3. Scaling 128^3 .. 1024^3 for a sphere: work should grow ~4x per doubling (surface area),
   not 8x (volume). Peak memory of each run is measured in a fresh subprocess.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.io.vdbgrids import frep_to_vdb, vdb  # noqa: E402
from pipeline.io.vdbio import write_vdb  # noqa: E402
from pipeline.oracles import REGISTRY  # noqa: E402
from pipeline.voxel.voxelise import block_for, voxelise  # noqa: E402

MODELS = {
    # name: (node factory, AX expression of the same field)
    "sphere": (lambda: REGISTRY["sphere"](REGISTRY["sphere"].Params(radius=0.6)),
               "@frep = 0.6 - length(getvoxelpws());"),
    "torus": (lambda: REGISTRY["torus"](REGISTRY["torus"].Params(major=0.6, minor=0.2)),
              "vec3f p = getvoxelpws(); float q = sqrt(p.x*p.x + p.y*p.y) - 0.6;"
              " @frep = 0.2 - sqrt(q*q + p.z*p.z);"),
    "box": (lambda: REGISTRY["box"](REGISTRY["box"].Params(min=(-0.6, -0.45, -0.3), max=(0.6, 0.45, 0.3))),
            "vec3f p = getvoxelpws();"
            " float qx = abs(p.x) - 0.6; float qy = abs(p.y) - 0.45; float qz = abs(p.z) - 0.3;"
            " float ox = max(qx, 0.0); float oy = max(qy, 0.0); float oz = max(qz, 0.0);"
            " @frep = -(sqrt(ox*ox + oy*oy + oz*oz) + min(max(qx, max(qy, qz)), 0.0));"),
}


def _demo():
    """configs/demo.yaml's model: superellipsoid minus a thin box (r0)."""
    from pipeline.job.config import _Ctx, build_node

    raw = {"difference": [{"superellipsoid": {"radii": [1, 1, 1], "exponents": [0.3, 0.3]}},
                          {"box": {"min": [-1.3, -0.02, -1.3], "max": [1.3, 0.02, 1.3]}}], "rfunc": "r0"}
    return build_node(raw, ("model",), _Ctx("bench", raw, ROOT))


MODELS["demo"] = (_demo, """
vec3f p = getvoxelpws();
float e = 2.0 / 0.3;
float F = pow(abs(p.x), e) + pow(abs(p.y), e) + pow(abs(p.z), e);
float f1 = 1.0 - pow(F, 0.15);
float qx = abs(p.x) - 1.3; float qy = abs(p.y) - 0.02; float qz = abs(p.z) - 1.3;
float ox = max(qx, 0.0); float oy = max(qy, 0.0); float oz = max(qz, 0.0);
float f2 = sqrt(ox*ox + oy*oy + oz*oz) + min(max(qx, max(qy, qz)), 0.0);
float s = f1 + f2;
float rho = sqrt(f1*f1 + f2*f2);
if (s > 0.0) { @frep = 2.0*f1*f2 / (s + rho); } else { @frep = s - rho; }
""")
HALF = {"demo": 1.2}  # domain half-extent per model (default 1)


def domain(n: int, model: str = "sphere"):
    half = HALF.get(model, 1.0)
    h = 2.0 * half / n
    return np.array([-n // 2] * 3), np.array([n // 2] * 3), h


def run_sparse(model_name: str, n: int) -> dict:
    model = MODELS[model_name][0]()
    imin, imax, h = domain(n, model_name)
    # warm-up at 32^3: loads the cached Numba kernels once per process (~0.5 s), a fixed cost
    # that a batch pays once and that the dense NumPy reference does not have
    wlo, whi, wh = domain(32, model_name)
    block = block_for(model)  # the stage's default (block: auto)
    frep_to_vdb(*_pair(voxelise(model, wlo, whi, wh, 3.0, block)), "frep")
    t0 = time.perf_counter()
    res = voxelise(model, imin, imax, h, 3.0, block)
    t1 = time.perf_counter()
    grid = frep_to_vdb(res.blocks, res.inside_boxes, "frep")
    t2 = time.perf_counter()
    return {"model": model_name, "n": n, "block": block, "enumerate_eval_s": t1 - t0, "vdb_s": t2 - t1, "total_s": t2 - t0,
            "voxels_evaluated": res.stats["voxels_evaluated"], "active": res.stats["active_voxels"],
            "cells_visited": res.stats["cells_visited"], "grid_active": int(grid.activeVoxelCount()),
            "evaluate_s": res.stats["evaluate_seconds"], "enumerate_s": res.stats["enumerate_seconds"],
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _pair(res):
    return res.blocks, res.inside_boxes


def run_dense(model_name: str, n: int) -> dict:
    """Every voxel of the domain evaluated with the same NumPy field code, slab by slab."""
    model = MODELS[model_name][0]()
    imin, imax, h = domain(n, model_name)
    ax = np.arange(imin[0], imax[0] + 1) * h
    t0 = time.perf_counter()
    total = 0
    Y, Z = np.meshgrid(ax, ax, indexing="ij")
    yz = np.stack([Y.ravel(), Z.ravel()], 1)
    for x in ax:  # one x-slab at a time keeps memory bounded
        pts = np.column_stack([np.full(len(yz), x), yz])
        model.evaluate(pts)
        total += len(pts)
    return {"model": model_name, "n": n, "dense_s": time.perf_counter() - t0, "voxels_evaluated": total}


def written_grid(res):
    """Our frep grid written to a .vdb (as the export stage does) and read back."""
    grid = frep_to_vdb(res.blocks, res.inside_boxes, "frep")
    with tempfile.TemporaryDirectory(prefix="bench_voxelise_") as tmp:
        path = Path(tmp) / "frep.vdb"
        write_vdb(path, [grid])
        return vdb.read(str(path), "frep")


def run_ax(model_name: str, n: int) -> dict:
    """OpenVDB AX over the active voxels of our written (read-back) frep grid: C++ per-voxel
    throughput on the same topology."""
    model = MODELS[model_name][0]()
    imin, imax, h = domain(n, model_name)
    res = voxelise(model, imin, imax, h, 3.0, block_for(model))
    grid = written_grid(res)
    ref = {tuple(map(int, p)): v for p, v in zip(*res.blocks.active_voxels(), strict=True)}
    t0 = time.perf_counter()
    vdb.ax(MODELS[model_name][1], grid)
    dt = time.perf_counter() - t0
    empty = vdb.FloatGrid(-1.0)
    empty.name = "frep"
    t0 = time.perf_counter()
    vdb.ax(MODELS[model_name][1], empty)  # the same snippet on no voxels: AX's JIT compilation
    compile_s = time.perf_counter() - t0
    acc = grid.getConstAccessor()
    sample = list(ref.items())[:: max(1, len(ref) // 200)]
    err = max(abs(acc.getValue(k) - v) for k, v in sample)
    return {"model": model_name, "n": n, "ax_s": dt, "ax_voxels": int(grid.activeVoxelCount()), "ax_max_diff": err,
            "ax_compile_s": compile_s}


INLINE = False  # --quick: every run in this process (no start-up per run; peak RSS is cumulative)
RUNS = {"sparse": run_sparse, "dense": run_dense, "ax": run_ax}


def in_subprocess(fn: str, model: str, n: int) -> dict:
    if INLINE:
        return RUNS[fn](model, n)
    out = subprocess.run([sys.executable, __file__, "--one", fn, model, str(n)], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


KEY = {"sparse": "total_s", "dense": "dense_s", "ax": "ax_s"}


def alternated(model: str, n: int, repeat: int) -> tuple[dict, dict, dict, list[float]]:
    """sparse, dense and AX runs alternated ``repeat`` times (each in a fresh process; this VM's
    speed drifts within minutes), the run of median time of each, and the dense/sparse ratio of
    every round."""
    rounds = [{fn: in_subprocess(fn, model, n) for fn in ("sparse", "dense", "ax")} for _ in range(repeat)]
    med = [sorted((r[fn] for r in rounds), key=lambda x, fn=fn: x[KEY[fn]])[repeat // 2] for fn in KEY]
    return (*med, [r["dense"]["dense_s"] / r["sparse"]["total_s"] for r in rounds])


def print_per_active(pairs: list[tuple[dict, dict]]) -> None:
    """Our voxelise per active voxel vs OpenVDB AX per active voxel of the read-back grid."""
    print("\n## Per active voxel: our voxelise vs OpenVDB AX over the same active voxels"
          " (our frep grid written to .vdb and read back)\n")
    print("| model | n^3 | active (ours) | active (read back, AX) | voxelise() s | + VDB build s |"
          " ours ns / active | AX s | AX ns / active | ours / AX | evaluation + band + leaves s | its ns / evaluated voxel"
          " vs AX ns / active | AX max abs diff | AX compile s (empty grid) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s, a in pairs:
        ours = s["enumerate_eval_s"] / s["grid_active"] * 1e9
        ours_all = s["total_s"] / s["grid_active"] * 1e9
        ax = a["ax_s"] / a["ax_voxels"] * 1e9
        kern = s["evaluate_s"] / s["voxels_evaluated"] * 1e9  # tape kernel + band marking + leaf writes (one pass)
        print(f"| {s['model']} | {s['n']} | {s['grid_active']:,} | {a['ax_voxels']:,} | {s['enumerate_eval_s']:.3f} |"
              f" {s['total_s']:.3f} | {ours:.0f} ({ours_all:.0f} with build) | {a['ax_s']:.3f} | {ax:.0f} |"
              f" {ours / ax:.1f}x ({ours_all / ax:.1f}x) | {s['evaluate_s']:.3f} | {kern:.0f} vs {ax:.0f} |"
              f" {a['ax_max_diff']:.2e} | {a['ax_compile_s']:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="128^3 only, runs in this process (smoke run, < 60 s)")
    ap.add_argument("--one", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=3, help="alternated runs of each side; medians are printed")
    args = ap.parse_args()
    if args.one:
        fn, model, n = args.one
        print(json.dumps(RUNS[fn](model, int(n))))
        return
    global INLINE
    INLINE = args.quick
    sizes = [128] if args.quick else [256, 512]
    repeat = 1 if args.quick else max(1, args.repeat)
    print(f"## Sparse voxelise vs dense NumPy vs OpenVDB AX (band 3, the stage's block: auto; medians of {repeat} alternated runs)\n")
    print("| model | n^3 | block | sparse s | dense s | dense/sparse | per round | evaluated sparse | evaluated dense |"
          " evaluated/active | AX s (active voxels) | sparse eval per voxel vs AX |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    pairs = []
    for model in MODELS:
        for n in sizes:
            s, d, a, ratios = alternated(model, n, repeat)
            pairs.append((s, a))
            ns_sparse = s["enumerate_eval_s"] / s["voxels_evaluated"] * 1e9
            ns_ax = a["ax_s"] / a["ax_voxels"] * 1e9
            print(f"| {model} | {n} | {s['block']} | {s['total_s']:.2f} | {d['dense_s']:.2f} | {d['dense_s'] / s['total_s']:.1f}x |"
                  f" {' / '.join(f'{x:.1f}' for x in ratios)} | {s['voxels_evaluated']:,} | {d['voxels_evaluated']:,} | {s['voxels_evaluated'] / s['active']:.2f} |"
                  f" {a['ax_s']:.3f} ({a['ax_voxels']:,}) | {ns_sparse:.0f} ns vs {ns_ax:.0f} ns |")
    print_per_active(pairs)
    print("\n## Scaling (sphere r = 0.6, band 3): cost per doubling should be ~4x (area), not 8x (volume)\n")
    print("| n^3 | total s | x per doubling | voxels evaluated | x per doubling | active | cells visited | peak RSS MiB |")
    print("|---|---|---|---|---|---|---|---|")
    prev = None
    for n in ([64, 128] if args.quick else [128, 256, 512, 1024]):
        s = in_subprocess("sparse", "sphere", n)
        tr = f"{s['total_s'] / prev['total_s']:.1f}" if prev else "-"
        vr = f"{s['voxels_evaluated'] / prev['voxels_evaluated']:.2f}" if prev else "-"
        print(f"| {n} | {s['total_s']:.2f} | {tr} | {s['voxels_evaluated']:,} | {vr} | {s['active']:,} |"
              f" {s['cells_visited']:,} | {s['peak_rss_mb']:.0f} |")
        prev = s


if __name__ == "__main__":
    main()
