"""Benchmark: batch throughput, the cost of bricking, and the demo end to end per stage.

    .venv/bin/python bench/scale.py [--quick] [--batch] [--bricks] [--e2e] [--e2e-repeat K] [--stage-limit S]

Prints Markdown tables (no section switch given: all three sections).

1. Batch throughput: N jobs of different primitives at the same resolution (voxelise +
   components + hfrep + export vdb) inline, on the local process pool and on a Dask
   LocalCluster with 1 and 2 workers: jobs/second and speed-up over 1 worker. Each executor
   is started and warmed up (a batch of tiny jobs: imports, Numba caches) before the timing.
2. Cost of bricking: the demo model (voxelise + components + hfrep + export vdb) unsplit vs
   ``bricks: {size: B}`` inline and on a 2-worker process pool: seconds per bricked stage, and
   checks against the unsplit run: the ``frep`` grids are identical (active voxel count, leaf
   count, max |difference| of values over the active bounding box, inactive values
   included), the component count, and the max |difference| of the ``surface`` grids.
3. End to end: configs/demo.yaml (components + hfrep + export) at several resolutions over
   [-1.2, 1.2]^3, each in a fresh subprocess. The child reports stage starts (the runner's
   ``progress`` callback) on stdout; this process samples the memory of the child (RSS) and of
   its own children (the forked .vdb writers: the pages private to them, USS, since they share
   the job's pages copy-on-write) with psutil every 20 ms, in a thread of its own (outside the child, so a long Numba kernel holding the
   child's GIL cannot starve the sampler) and gives each sample to the stage that is running.
   A stage that runs longer than ``--stage-limit`` seconds, or a child whose RSS passes
   ``--max-rss-gib`` (default 90 % of RAM), is stopped and reported, and so is a child killed
   by the kernel (out of memory).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from pipeline.job.batch import DaskExecutor, Executor, LocalExecutor, execute, run_batch  # noqa: E402
from pipeline.job.config import load_jobs  # noqa: E402

Row = dict[str, Any]

# --- configs ------------------------------------------------------------------------------------

BATCH_MODELS = [
    ("ball", "sphere: {radius: 0.6}"),
    ("ring", "torus: {major: 0.55, minor: 0.2}"),
    ("cube", "box: {min: [-0.5, -0.5, -0.5], max: [0.5, 0.5, 0.5]}"),
    ("can", "cylinder: {radius: 0.45, height: 1.2}"),
    ("cone", "cone: {center: [0, 0, -0.6], radius: 0.6, height: 1.2}"),
    ("egg", "ellipsoid: {radii: [0.75, 0.55, 0.45]}"),
    ("pair", "union: [{sphere: {center: [-0.45, 0, 0], radius: 0.35}}, {sphere: {center: [0.45, 0, 0], radius: 0.35}}]"),
    ("blob", "blobby: {blobs: [{center: [0, 0, 0], radius: 0.5}, {center: [0.4, 0, 0], radius: 0.4}]}"),
]

BATCH_STAGES = """stages:
  - voxelise: {band: 3}
  - components: {}
  - hfrep: {}
  - export: {vdb: true}
"""

DEMO_MODEL = """model:
  difference:
    - superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}
    - box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}
  rfunc: r0
"""

DEMO_BOUNDS = "[[-1.2, -1.2, -1.2], [1.2, 1.2, 1.2]]"


def batch_config(folder: Path, name: str, n: int, count: int) -> Path:
    """A ``jobs:`` config of ``count`` primitives (cycling through BATCH_MODELS) at resolution n."""
    lines = [f"name: {name}", f"domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: {n}}}", BATCH_STAGES.rstrip(),
             "jobs:"]
    for i in range(count):
        label, model = BATCH_MODELS[i % len(BATCH_MODELS)]
        lines.append(f"  - {{name: {name}_{i}_{label}, model: {{{model}}}}}")
    path = folder / f"{name}.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


def demo_model_config(folder: Path, name: str, n: int, brick: int | None, stages: str) -> Path:
    """The demo model over [-1.2, 1.2]^3 at resolution n (voxel size 2.4/n), optionally bricked."""
    text = f"name: {name}\ndomain: {{bounds: {DEMO_BOUNDS}, resolution: {n}}}\n"
    if brick:
        text += f"bricks: {{size: {brick}}}\n"
    path = folder / f"{name}.yaml"
    path.write_text(text + DEMO_MODEL + stages)
    return path


def demo_config(folder: Path, n: int) -> Path:
    """configs/demo.yaml with the voxel size 2.4/n instead of 0.01 (and its own name)."""
    src = (ROOT / "configs" / "demo.yaml").read_text()
    if "voxel_size: 0.01" not in src:
        raise RuntimeError("configs/demo.yaml changed: expected 'voxel_size: 0.01'")
    text = src.replace("voxel_size: 0.01", f"resolution: {n}").replace("name: demo", f"name: demo_{n}")
    path = folder / f"demo_{n}.yaml"
    path.write_text(text)
    return path


# --- 1. batch throughput ------------------------------------------------------------------------


def make(kind: str, workers: int) -> Executor:
    if kind == "inline":
        return Executor()
    if kind == "local":
        return LocalExecutor(workers)
    return DaskExecutor(workers=workers)


def batch_throughput(folder: Path, n: int = 128, count: int = 8,
                     setups: tuple[tuple[str, int], ...] = (("inline", 1), ("local", 1), ("local", 2),
                                                            ("dask", 1), ("dask", 2)),
                     warmup: int = 4) -> list[Row]:
    """Rows: executor, workers, jobs, seconds, jobs/s, speed-up over the same executor with 1 worker.

    ``warmup`` tiny jobs run on each executor before the timed batch (0: none)."""
    cfg = batch_config(folder, "batch", n, count)
    warm = batch_config(folder, "warm", 16, warmup) if warmup else None
    rows: list[Row] = []
    for kind, workers in setups:
        t0 = time.perf_counter()
        ex = make(kind, workers)
        start = time.perf_counter() - t0
        try:
            if warm is not None:
                run_batch(load_jobs(warm), folder / "out_warm", ex, force=True)
            jobs = load_jobs(cfg)
            t0 = time.perf_counter()
            results = run_batch(jobs, folder / f"out_{kind}_{workers}", ex, force=True)
            seconds = time.perf_counter() - t0
        finally:
            ex.close()
        bad = [r for r in results if r["status"] != "ok"]
        if bad:
            raise RuntimeError(f"batch on {kind}/{workers}: {bad[0]['name']} {bad[0]['status']}: {bad[0]['message']}")
        rows.append({"executor": kind, "workers": workers, "jobs": len(jobs), "n": n, "start_s": start,
                     "seconds": seconds, "jobs_per_s": len(jobs) / seconds,
                     "job_s_mean": float(np.mean([r["seconds"] for r in results]))})
    for r in rows:
        one = next((o for o in rows if o["executor"] == r["executor"] and o["workers"] == 1), None)
        r["speedup"] = one["seconds"] / r["seconds"] if one else None
    return rows


def batch_table(rows: list[Row]) -> str:
    out = ["| executor | workers | jobs (n^3) | start s | batch s | jobs/s | mean s per job | speed-up vs 1 worker |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sp = f"{r['speedup']:.2f}x" if r["speedup"] is not None else "-"
        out.append(f"| {r['executor']} | {r['workers']} | {r['jobs']} ({r['n']}^3) | {r['start_s']:.1f} |"
                   f" {r['seconds']:.1f} | {r['jobs_per_s']:.3f} | {r['job_s_mean']:.1f} | {sp} |")
    return "\n".join(out)


# --- 2. cost of bricking ------------------------------------------------------------------------


def read_frep(path: Path, name: str = "frep") -> Any:
    from pipeline.io.vdbgrids import vdb

    return vdb.read(str(path), name)


def compare_grids(a: Any, b: Any) -> dict:
    """Active voxel and leaf counts of both, and max |a - b| over the union of the active
    bounding boxes (one voxel of margin): over all values (inactive +-background included) and
    over the voxels holding band values (|value| below the background)."""
    out = {"active_a": int(a.activeVoxelCount()), "active_b": int(b.activeVoxelCount()),
           "leaves_a": int(a.leafCount()), "leaves_b": int(b.leafCount())}
    (la, ha), (lb, hb) = a.evalActiveVoxelBoundingBox(), b.evalActiveVoxelBoundingBox()
    lo = np.minimum(la, lb) - 1
    hi = np.maximum(ha, hb) + 1
    shape = tuple(int(x) for x in hi - lo + 1)
    bg = min(abs(float(a.background)), abs(float(b.background)))
    diff = band = 0.0
    step = max(1, int(2**26 // (shape[1] * shape[2])))  # slabs of <= 256 MiB per grid
    for x0 in range(0, shape[0], step):
        s = (min(step, shape[0] - x0), shape[1], shape[2])
        origin = (int(lo[0]) + x0, int(lo[1]), int(lo[2]))
        A, B = np.zeros(s, np.float32), np.zeros(s, np.float32)
        a.copyToArray(A, origin)
        b.copyToArray(B, origin)
        d = np.abs(A - B)
        diff = max(diff, float(d.max()))
        near = (np.abs(A) < bg * 0.999) | (np.abs(B) < bg * 0.999)  # not +-background: band values
        band = max(band, float(d[near].max(initial=0.0)))
    out["max_abs_diff"] = diff
    out["max_abs_diff_band"] = band
    out["background_diff"] = abs(float(a.background) - float(b.background))
    out["identical"] = out["active_a"] == out["active_b"] and out["leaves_a"] == out["leaves_b"] and diff == 0.0
    return out


def brick_cost(folder: Path, sizes: tuple[int, ...] = (256, 512), bricks: tuple[int, ...] = (64, 128, 256),
               workers: int = 2) -> list[Row]:
    """Rows: n, bricks (None = unsplit), executor, brick count, seconds per stage, total s, checks."""
    stages = ("stages:\n  - voxelise: {band: 3}\n  - components: {}\n"
              "  - hfrep: {quality: false, density: false}\n  - export: {vdb: true, report: false}\n")
    pool = LocalExecutor(workers)
    rows: list[Row] = []
    try:
        warm = demo_model_config(folder, "brickwarm", 32, 16, stages)
        execute(load_jobs(warm)[0], folder / "out_bricks", True, pool)  # start the workers' imports
        for n in sizes:
            ref = ref_surface = None
            runs: list[tuple[int | None, str, Executor]] = [(None, "inline", Executor())]
            runs += [(b, name, ex) for b in bricks if b < n
                     for name, ex in (("inline", Executor()), (f"local pool, {workers} workers", pool))]
            for b, ex_name, ex in runs:
                name = f"demo{n}_{'whole' if b is None else f'b{b}'}_{'pool' if ex is pool else 'inline'}"
                job = load_jobs(demo_model_config(folder, name, n, b, stages))[0]
                t0 = time.perf_counter()
                res = execute(job, folder / "out_bricks", True, ex)
                total = time.perf_counter() - t0
                if res["status"] != "ok":
                    raise RuntimeError(f"{name}: {res['status']}: {res['message']}")
                manifest = json.loads((folder / "out_bricks" / name / "manifest.json").read_text())
                secs = {f"{s['name']}_s": s["seconds"] for s in manifest["stages"]}
                vox = next(s for s in manifest["stages"] if s["name"] == "voxelise")
                hf = next(s for s in manifest["stages"] if s["name"] == "hfrep")
                grid = read_frep(folder / "out_bricks" / name / f"{name}.vdb")
                surface = read_frep(folder / "out_bricks" / name / f"{name}.vdb", "surface")
                if ref is None:
                    ref, ref_surface = grid, surface
                check = compare_grids(ref, grid)
                surf = compare_grids(ref_surface, surface)
                rows.append({"n": n, "brick": b, "executor": ex_name, "bricks": vox["stats"].get("bricks", 1),
                             **secs, "total_s": total, **check, "components": manifest["components"]["count"],
                             "hfrep_rounds": hf["stats"].get("rounds", 0),
                             "surface_active_equal": surf["active_a"] == surf["active_b"],
                             "surface_max_diff_vox": surf["max_abs_diff_band"] / job.domain.voxel_size})
    finally:
        pool.close()
    for r in rows:
        base = next(o for o in rows if o["n"] == r["n"] and o["brick"] is None)
        for stage in ("voxelise", "components", "hfrep"):
            r[f"{stage}_ratio"] = r[f"{stage}_s"] / base[f"{stage}_s"]
    return rows


def brick_table(rows: list[Row]) -> str:
    out = ["| n^3 | brick | executor | bricks | voxelise s (vs unsplit) | components s (vs unsplit) |"
           " hfrep s (vs unsplit, rounds) | total s | frep active voxels | frep identical |"
           " components | surface: same active voxels, max diff (voxels) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = "unsplit" if r["brick"] is None else str(r["brick"])
        out.append(f"| {r['n']} | {b} | {r['executor']} | {r['bricks']} |"
                   f" {r['voxelise_s']:.2f} ({r['voxelise_ratio']:.2f}x) |"
                   f" {r['components_s']:.2f} ({r['components_ratio']:.2f}x) |"
                   f" {r['hfrep_s']:.2f} ({r['hfrep_ratio']:.2f}x, {r['hfrep_rounds']}) | {r['total_s']:.2f} |"
                   f" {r['active_b']:,} | {'yes' if r['identical'] else 'NO'} | {r['components']} |"
                   f" {'yes' if r['surface_active_equal'] else 'NO'}, {r['surface_max_diff_vox']:.2g} |")
    return "\n".join(out)


# --- 3. end to end ------------------------------------------------------------------------------


def child_e2e(config: str, out: str) -> None:
    """Run one job here, reporting stage starts and the result as JSON lines on stdout."""
    import resource

    def emit(obj: dict) -> None:
        sys.stdout.write(json.dumps(obj) + "\n")
        sys.stdout.flush()

    emit({"event": "start", "t": time.time()})
    try:
        job = load_jobs(config)[0]
    except Exception as e:  # noqa: BLE001 - reported to the parent, e.g. the memory pre-check
        emit({"event": "error", "stage": "load", "message": f"{type(e).__name__}: {e}"})
        return
    names = {n for n, _ in job.stages}
    from pipeline.job.runner import run_job

    def progress(msg: str) -> None:
        if msg in names:
            emit({"event": "stage", "stage": msg, "t": time.time()})

    try:
        m = run_job(job, out, progress=progress)
    except Exception as e:  # noqa: BLE001
        emit({"event": "error", "stage": None, "message": f"{type(e).__name__}: {e}"})
        return
    emit({"event": "done", "t": time.time(), "stages": {s["name"]: s["seconds"] for s in m["stages"]},
          "grids": {k: v.get("active_voxels") for k, v in m["grids"].items()},
          "dims": m["domain"]["dims"], "voxel_size": m["domain"]["voxel_size"],
          "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024})


def _memory(proc: psutil.Process) -> int:
    """The job's memory: its RSS plus the pages private to its children (USS; Linux, RSS
    elsewhere). A forked .vdb writer shares the job's grids copy-on-write: summing RSS counted
    them twice (6.3 GiB instead of 3.9 at 1024^3). Reading USS walks a process's whole page
    table: sampled every 20 ms for the job it slowed the job by 40 %, and for a writer child at
    2048^3 (~13 GiB mapped) the walks took most of a core from the job (components 84 s in the
    benchmark against 57 s in-process), so a child's USS is read at most every
    CHILD_USS_INTERVAL seconds and its last value is used in between."""
    now = time.monotonic()
    total = proc.memory_info().rss
    for c in proc.children(recursive=True):
        try:
            seen = _CHILD_USS.get(c.pid)
            if seen is None or now - seen[0] >= CHILD_USS_INTERVAL:
                seen = (now, int(c.memory_full_info().uss))
                _CHILD_USS[c.pid] = seen
            total += seen[1]
        except (AttributeError, psutil.AccessDenied):
            total += int(c.memory_info().rss)
        except psutil.NoSuchProcess:
            pass
    return total


CHILD_USS_INTERVAL = 0.5  # seconds between two USS reads of one child (they grow as they write)
_CHILD_USS: dict[int, tuple[float, int]] = {}


def run_e2e(folder: Path, n: int, stage_limit: float = 900.0, interval: float = 0.02,
            max_rss_gib: float | None = None) -> Row:
    """One resolution of the demo in a fresh subprocess; per-stage wall time and peak memory (RSS
    of the process plus its children's private pages: :func:`_memory`).

    The child is stopped when a stage runs longer than ``stage_limit`` seconds or its RSS
    passes ``max_rss_gib`` (default: 90 % of this machine's memory, so a run that cannot fit
    stops before the kernel's OOM killer picks a process on a shared machine)."""
    limit_rss = (max_rss_gib * 2**30) if max_rss_gib else 0.9 * psutil.virtual_memory().total
    _CHILD_USS.clear()
    cfg = demo_config(folder, n)
    proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--child-e2e", str(cfg),
                             str(folder / "out_e2e")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    state: dict[str, Any] = {"stage": "load", "since": time.time(), "order": ["load"], "starts": {"load": time.time()},
                             "done": None, "error": None}
    lock = threading.Lock()

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            with lock:
                if ev["event"] == "stage":
                    state["stage"], state["since"] = ev["stage"], ev["t"]
                    state["order"].append(ev["stage"])
                    state["starts"][ev["stage"]] = ev["t"]
                elif ev["event"] == "done":
                    state["done"] = ev
                elif ev["event"] == "error":
                    state["error"] = ev

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    ps = psutil.Process(proc.pid)
    peaks: dict[str, int] = {}
    failure = None
    while proc.poll() is None:
        try:
            rss = _memory(ps)
        except psutil.Error:
            rss = 0
        with lock:
            stage, since = state["stage"], state["since"]
        peaks[stage] = max(peaks.get(stage, 0), rss)
        if rss > limit_rss:
            failure = (f"stopped: RSS {rss / 2**30:.1f} GiB passed the limit of {limit_rss / 2**30:.1f} GiB"
                       f" in stage '{stage}'")
            proc.kill()
            break
        if time.time() - since > stage_limit:
            failure = f"stopped: stage '{stage}' ran longer than {stage_limit:g} s"
            proc.kill()
            break
        time.sleep(interval)
    proc.wait()
    th.join(timeout=5)
    end = time.time()
    stderr = proc.stderr.read() if proc.stderr else ""
    if failure is None and state["error"]:
        failure = f"failed in '{state['error']['stage'] or state['stage']}': {state['error']['message']}"
    if failure is None and state["done"] is None:
        rc = proc.returncode
        how = f"killed by signal {-rc}" + (" (SIGKILL: out of memory?)" if rc == -9 else "") if rc < 0 else f"exit {rc}"
        tail = stderr.strip().splitlines()[-1] if stderr.strip() else ""
        failure = f"child {how} during '{state['stage']}' {tail}".strip()
    order, starts = state["order"], state["starts"]
    stages = []
    for i, s in enumerate(order):
        stop = starts[order[i + 1]] if i + 1 < len(order) else end
        secs = state["done"]["stages"].get(s) if state["done"] and s in state["done"]["stages"] else stop - starts[s]
        stages.append({"stage": s, "seconds": secs, "peak_rss_mib": peaks.get(s, 0) / 2**20,
                       "finished": state["done"] is not None or i + 1 < len(order)})
    return {"n": n, "voxel_size": 2.4 / n, "stages": stages, "failure": failure, "wall_s": end - starts["load"],
            "done": state["done"], "peak_rss_mib": max(peaks.values(), default=0) / 2**20,
            "load": os.getloadavg()}


def e2e_table(rows: list[Row]) -> str:
    out = ["| n^3 (voxel size) | stage | seconds | peak memory MiB | note |", "|---|---|---|---|---|"]
    for r in rows:
        for s in r["stages"]:
            note = "" if s["finished"] else (r["failure"] or "unfinished")
            out.append(f"| {r['n']} ({r['voxel_size']:.5f}) | {s['stage']} | {s['seconds']:.2f} |"
                       f" {s['peak_rss_mib']:,.0f} | {note} |")
        grids = ""
        if r["done"]:
            g = r["done"]["grids"]
            grids = f"frep {g.get('frep', 0):,} / surface {g.get('surface', 0):,} active voxels"
        elif r["failure"]:
            grids = r["failure"]
        load = ", ".join(f"{x:.2f}" for x in r.get("load", ()))
        out.append(f"| {r['n']} | **whole job** | {r['wall_s']:.2f} | {r['peak_rss_mib']:,.0f} | {grids};"
                   f" load average at the end {load} |")
    return "\n".join(out)


def median_row(runs: list[Row]) -> Row:
    """One row of several runs at the same size: each stage's median seconds and peak RSS (and
    the whole job's), with ``spread`` = (min, max) seconds per stage. The runs that finished
    count; none finished: the last run. On this VM one size's stage times move by 10-20 %
    from run to run, enough to swing a doubling ratio by +-0.4 (docs/performance.md)."""
    ok = [r for r in runs if r["done"]]
    if not ok:
        return runs[-1]
    names = [s["stage"] for s in ok[0]["stages"]]
    per = {n: [next(s for s in r["stages"] if s["stage"] == n) for r in ok if any(s["stage"] == n for s in r["stages"])]
           for n in names}
    stages = [{"stage": n, "seconds": float(np.median([s["seconds"] for s in per[n]])),
               "peak_rss_mib": float(np.median([s["peak_rss_mib"] for s in per[n]])), "finished": True}
              for n in names]
    return {**ok[-1], "stages": stages, "runs": len(ok), "wall_s": float(np.median([r["wall_s"] for r in ok])),
            "peak_rss_mib": float(np.median([r["peak_rss_mib"] for r in ok])),
            "spread": {n: (min(s["seconds"] for s in per[n]), max(s["seconds"] for s in per[n])) for n in names}}


def spread_table(rows: list[Row]) -> str:
    """Median and range of each stage's seconds over the runs of each size (:func:`median_row`)."""
    out = ["| n^3 | stage | runs | median s | min s | max s |", "|---|---|---|---|---|---|"]
    for r in rows:
        for s in r["stages"]:
            lo, hi = r.get("spread", {}).get(s["stage"], (s["seconds"], s["seconds"]))
            out.append(f"| {r['n']} | {s['stage']} | {r.get('runs', 1)} | {s['seconds']:.2f} | {lo:.2f} | {hi:.2f} |")
    return "\n".join(out)


def growth_table(rows: list[Row], bound: float = 4.5) -> str:
    """Per doubling of the resolution: each stage's time and peak RSS ratio, and whether both
    stay within ``bound`` (x4 is the surface, x8 the volume) and the stage within 3x voxelise."""
    out = ["| n -> 2n | stage | time ratio | peak memory ratio | within x4.5 | stage / voxelise time (2n) |",
           "|---|---|---|---|---|---|"]
    by_n = {r["n"]: r for r in rows if r["done"]}
    for n in sorted(by_n):
        if 2 * n not in by_n:
            continue
        a = {s["stage"]: s for s in by_n[n]["stages"]}
        b = {s["stage"]: s for s in by_n[2 * n]["stages"]}
        vox = b.get("voxelise", {}).get("seconds") or float("nan")
        for st in b:
            if st not in a or st == "load":
                continue
            t = b[st]["seconds"] / max(a[st]["seconds"], 1e-9)
            m = b[st]["peak_rss_mib"] / max(a[st]["peak_rss_mib"], 1e-9)
            ok = "yes" if t <= bound and m <= bound else "**no**"
            out.append(f"| {n} -> {2 * n} | {st} | {t:.2f} | {m:.2f} | {ok} | {b[st]['seconds'] / vox:.2f} |")
    return "\n".join(out)


# --- main ---------------------------------------------------------------------------------------


def conditions() -> str:
    vm = psutil.virtual_memory()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"{datetime.now().strftime('%Y-%m-%d %H:%M')}, {platform.machine()}, {os.cpu_count()} cores,"
            f" {vm.total / 2**30:.1f} GiB RAM ({vm.available / 2**30:.1f} GiB available), load average {load}")


def sections(args: argparse.Namespace, folder: Path, emit: Callable[[str], None]) -> dict[str, list[Row]]:
    """Run the selected sections, printing each table as soon as it is measured."""
    every = not (args.batch or args.bricks or args.e2e)
    q = args.quick
    results: dict[str, list[Row]] = {}
    emit(f"Measured {conditions()}.\n")
    if every or args.batch:
        n, count = (24, 4) if q else (args.batch_n, 8)
        emit(f"## Batch throughput: {count} jobs at {n}^3 (voxelise + components + hfrep + export vdb)\n")
        results["batch"] = batch_throughput(folder, n, count)
        emit(batch_table(results["batch"]) + "\n")
    if every or args.bricks:
        sizes, bricks = ((64,), (16, 32)) if q else (tuple(args.brick_n), (64, 128, 256))
        emit("## Cost of bricking: demo model, voxelise (band 3) + components + hfrep + export vdb\n")
        results["bricks"] = brick_cost(folder, sizes, bricks)
        emit(brick_table(results["bricks"]) + "\n")
    if every or args.e2e:
        sizes = (32, 64) if q else tuple(args.e2e_n)
        emit("## End to end: configs/demo.yaml (voxelise, components, hfrep, export), fresh process per size\n")
        every_run, rows = [], []
        for n in sizes:
            runs = [run_e2e(folder, n, args.stage_limit, max_rss_gib=args.max_rss_gib)
                    for _ in range(max(1, args.e2e_repeat))]
            every_run += runs
            rows.append(median_row(runs) if len(runs) > 1 else runs[0])
            emit(f"<!-- {n}^3 done: {', '.join(r['failure'] or 'ok' for r in runs)} -->")
        results["e2e"] = rows
        emit(e2e_table(every_run) + "\n")
        if args.e2e_repeat > 1:
            emit(f"Median of {args.e2e_repeat} runs per size (the growth table below uses these):\n")
            emit(spread_table(rows) + "\n")
        emit(growth_table(rows) + "\n")
    emit(f"Finished {conditions()}.")
    return results


def main(argv: list[str] | None = None) -> dict[str, list[Row]]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a smoke run, well under a minute)")
    ap.add_argument("--batch", action="store_true", help="run the batch throughput section")
    ap.add_argument("--bricks", action="store_true", help="run the cost of bricking section")
    ap.add_argument("--e2e", action="store_true", help="run the end-to-end section")
    ap.add_argument("--batch-n", type=int, default=128, help="resolution of the batch jobs")
    ap.add_argument("--brick-n", type=int, nargs="+", default=[256, 512], help="resolutions for bricking")
    ap.add_argument("--e2e-n", type=int, nargs="+", default=[256, 512, 1024], help="resolutions end to end")
    ap.add_argument("--e2e-repeat", type=int, default=1,
                    help="runs per size; the growth table then uses each stage's median")
    ap.add_argument("--stage-limit", type=float, default=900.0, help="seconds one e2e stage may run")
    ap.add_argument("--max-rss-gib", type=float, help="stop an e2e child above this RSS (default: 90%% of RAM)")
    ap.add_argument("--workdir", type=Path, help="where configs and outputs go (default: a temporary folder)")
    ap.add_argument("--child-e2e", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_e2e:
        child_e2e(*args.child_e2e)
        return {}

    def emit(text: str) -> None:
        print(text, flush=True)

    if args.workdir:
        args.workdir.mkdir(parents=True, exist_ok=True)
        return sections(args, args.workdir, emit)
    with tempfile.TemporaryDirectory(prefix="frepvdb-scale-") as tmp:
        return sections(args, Path(tmp), emit)


if __name__ == "__main__":
    main()
