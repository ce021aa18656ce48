"""Grid building: the compiled leaf builder (pipeline/io/leafbuild.cpp) against pyopenvdb's
copyFromArray, the anchor, on the demo's grids at each resolution, in the same run.

For each resolution the demo (configs/demo.yaml) is voxelised and its hfrep stage's distance is
solved once; then the ``frep`` grid (voxelise's leaves) and the ``surface`` distance leaves
(every solved voxel: the hfrep stage's largest grid) are written with each path, ``--repeat``
times, alternating. Each row gives the median seconds, the cost per active voxel and the ratio
copyFromArray / leaf builder, and checks that both grids are the same (active voxel count, leaf
count and the values at 200,000 random voxels of the active bounding box, tiles and background
included).

Usage: ``.venv/bin/python bench/leaves.py [--res 256 512 1024] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.scale import conditions  # noqa: E402
from pipeline.distance.eikonal import solve_distance  # noqa: E402
from pipeline.io import vdbgrids as vg  # noqa: E402
from pipeline.io.vtkio import sample_values  # noqa: E402
from pipeline.job.config import load_jobs  # noqa: E402
from pipeline.job.context import JobContext  # noqa: E402
from pipeline.job.runner import _run_stage  # noqa: E402
from pipeline.sparse.grid import BlockGrid  # noqa: E402
from stages.base import FrepBand  # noqa: E402
from stages.hfrep import _inside_distance  # noqa: E402


def demo_leaves(n: int) -> dict[str, BlockGrid]:
    """The demo's frep leaves and its distance leaves (every solved voxel) at ``n``^3."""
    job = load_jobs(str(ROOT / "configs" / "demo.yaml"), overrides=[f"domain.resolution={n}"])[0]
    ctx = JobContext(job, Path(tempfile.mkdtemp(prefix="frepvdb-leaves-")))
    stages = dict(job.stages)
    _run_stage(ctx, "voxelise", stages["voxelise"])
    fb, dom = ctx.get(FrepBand), job.domain
    h = dom.voxel_size
    res = solve_distance(fb.blocks, 10 * h, (dom.index_min, dom.index_max), fb.inside_boxes,
                         inside_distance=_inside_distance(stages["hfrep"], 10 * h, fb.band * h),
                         signed_values=fb.signed)
    d = res.distance
    return {"frep": fb.blocks, "distance": BlockGrid(h, d.background, d.origins, d.values, d.active)}


def build(blocks: BlockGrid, compiled: bool) -> tuple[float, object]:
    saved = vg._leafbuild
    vg._leafbuild = saved if compiled else None
    try:
        grid = vg.vdb.FloatGrid(float(blocks.background))
        t = time.perf_counter()
        vg.write_leaves(grid, blocks)
        return time.perf_counter() - t, grid
    finally:
        vg._leafbuild = saved


def same(a, b, rng: np.random.Generator) -> bool:
    if a.activeVoxelCount() != b.activeVoxelCount() or a.leafCount() != b.leafCount():
        return False
    lo, hi = (np.asarray(c, np.int64) for c in a.evalActiveVoxelBoundingBox())
    ijk = rng.integers(lo, hi + 1, size=(200_000, 3))
    return bool(np.array_equal(sample_values(a, ijk), sample_values(b, ijk), equal_nan=True))


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    if vg._leafbuild is None:
        sys.exit("bench/leaves.py: pipeline.io._leafbuild is not built (run `make setup`)")
    print(f"# grid building, leaf builder vs copyFromArray ({conditions()})")
    print("| n^3 | grid | active voxels | leaves | copyFromArray s | leaf builder s | ns/voxel (old, new) | ratio | same grid |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    rng = np.random.default_rng(0)
    for n in args.res:
        for name, blocks in demo_leaves(n).items():
            times: dict[bool, list[float]] = {False: [], True: []}
            grids = {}
            for _ in range(args.repeat):
                for compiled in (False, True):
                    t, grids[compiled] = build(blocks, compiled)
                    times[compiled].append(t)
            old, new = statistics.median(times[False]), statistics.median(times[True])
            nvox = grids[True].activeVoxelCount()
            row = {"n": n, "grid": name, "voxels": nvox, "leaves": grids[True].leafCount(), "old_s": old,
                   "new_s": new, "ratio": old / new, "same": same(grids[False], grids[True], rng)}
            rows.append(row)
            print(f"| {n} | {name} | {nvox:,} | {row['leaves']:,} | {old:.3f} | {new:.3f} |"
                  f" {old / nvox * 1e9:.1f}, {new / nvox * 1e9:.1f} | {row['ratio']:.1f}x |"
                  f" {'yes' if row['same'] else 'NO'} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
