"""Compiled, per-cell specialised tapes vs the node-by-node evaluator, same run (issue 13).

For each model and resolution, voxelise (band 3, the stage's block: auto) twice in one process — once with the
tape (pipeline.model.tape: interval bounds, exact min/max pruning per cell, clause-major evaluation)
and once with the node-by-node affine bounds and NumPy evaluation — after a warm-up of the
compiled kernels, and print: seconds (the tape: median of ``--repeat`` runs), voxels evaluated, active voxels, microseconds per active
voxel, the speed-up, the mean tape length of the blocks, and the cost per active voxel relative
to one sphere's in the same run.

Usage: ``.venv/bin/python bench/tape.py [--quick] [--res 128 256] [--parts 10 100 1000 10000]``
(the node evaluator is skipped where it would take longer than ``--node-limit`` seconds, as
estimated from the previous part count; such rows print "skipped").
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pipeline.voxel.voxelise as vox  # noqa: E402
from pipeline.job.config import load_job  # noqa: E402


def job_for(model: str, res: int, tmp: Path):
    cfg = tmp / "m.yaml"
    cfg.write_text(f"name: m\ndomain: {{bounds: [[-1.2, -1.2, -1.2], [1.2, 1.2, 1.2]], resolution: {res}}}\n"
                   f"model:\n{model}\nstages: [{{voxelise: {{band: 3}}}}]\n")
    return load_job(cfg)


def spheres(n: int, seed: int = 0) -> str:
    rng = np.random.default_rng(seed)
    c, r = rng.uniform(-1, 1, (n, 3)), rng.uniform(0.03, 0.05, n)
    rows = "\n".join(f"      - sphere: {{center: [{x:.4f}, {y:.4f}, {z:.4f}], radius: {q:.4f}}}"
                     for (x, y, z), q in zip(c, r, strict=True))
    return f"  union:\n    rfunc: min_max\n    of:\n{rows}"


def run(job, tape: bool, repeat: int = 1) -> tuple[float, dict]:
    """Median seconds of ``repeat`` voxelise calls (a sphere at 256^3 takes ~0.05 s: one call
    is too short to time; its ratio to the union moved 2.9x-5.0x between single runs)."""
    vox.USE_TAPE = tape
    d = job.domain
    block = vox.block_for(job.model)  # the stage's default (block: auto): 8, 4 with an oracle or node by node
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = vox.voxelise(job.model, d.index_min, d.index_max, d.voxel_size, 3.0, block, job.t)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), r.stats


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--res", nargs="+", type=int, default=[128, 256])
    ap.add_argument("--parts", nargs="+", type=int, default=[10, 100, 1000, 10000])
    ap.add_argument("--node-limit", type=float, default=120.0)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeat", type=int, default=5, help="tape runs per row (the median is printed)")
    args = ap.parse_args()
    if args.quick:
        args.res, args.parts = [64], [10, 100]
    demo = (ROOT / "configs" / "demo.yaml").read_text().split("model:\n")[1].split("stages:")[0]
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print("| model | n^3 | tape s | nodes s | speed-up | evaluated (tape / nodes) | active | us/active tape"
          " | vs sphere | mean block tape |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        warm = job_for("  sphere: {radius: 0.8}", 32, Path(tmp))
        run(warm, True)
        run(warm, False)
        for res in args.res:
            sphere_cost = None
            last = (0.0, 1)  # (node-by-node seconds, parts) of the last model run that way
            models = [("sphere", "  sphere: {radius: 0.8}", 1), ("demo", demo, 1)]
            models += [(f"union of {n} spheres", spheres(n), n) for n in args.parts]
            for name, model, parts in models:
                job = job_for(model, res, Path(tmp))
                ts, st = run(job, True, args.repeat)
                per = 1e6 * ts / max(1, st["active_voxels"])
                sphere_cost = per if name == "sphere" else sphere_cost
                # the node-by-node anchor costs about its part count times the last one's
                if last[0] * parts / last[1] <= args.node_limit:
                    tn, sn = run(job, False)
                    last = (tn, parts)
                    nodes, ev_n, speed = f"{tn:.2f}", str(sn["voxels_evaluated"]), f"{tn / ts:.1f}x"
                else:
                    nodes, ev_n, speed = "skipped", "-", "-"
                mean = st["levels"][-1].get("mean_tape", "-")
                print(f"| {name} | {res} | {ts:.2f} | {nodes} | {speed} | {st['voxels_evaluated']} / {ev_n} | "
                      f"{st['active_voxels']} | {per:.3f} | {per / sphere_cost:.1f}x | {mean} |", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
