"""Command line: ``frepvdb run | validate | info | collide``. Exit 0 ok, 2 bad config or input, 1 failure."""

from __future__ import annotations

import argparse
import signal
import sys
import traceback
from pathlib import Path

import yaml

from pipeline.errors import ConfigError, interrupted, on_interrupt

EXIT_OK, EXIT_FAIL, EXIT_INPUT = 0, 1, 2


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    previous = _terminate_on_sigterm()
    try:
        return args.func(args)
    except ConfigError as e:
        for line in e.lines():
            print(f"error: {line}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_FAIL
    except Exception as e:  # noqa: BLE001 - one line for the user; --debug shows the traceback
        if interrupted():  # an interrupt that surfaced as an error of compiled code
            print("interrupted", file=sys.stderr)
            return EXIT_FAIL
        if getattr(args, "debug", False):
            traceback.print_exc()
        print(f"error: {_one_line(e)}", file=sys.stderr)
        return EXIT_FAIL
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGINT, signal.default_int_handler)


def _one_line(e: BaseException, limit: int = 300) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    if isinstance(e, OSError) and e.filename:
        text = f"{e.filename}: {e.strerror or text}"
    return text if len(text) <= limit else text[:limit] + "..."


def _terminate_on_sigterm():
    """SIGTERM ends a run like Ctrl-C: staging folders are removed, locks released, exit 1
    (both go through pipeline.errors.on_interrupt, so an interrupt inside compiled code is
    still reported as one)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    signal.signal(signal.SIGINT, on_interrupt)
    return signal.signal(signal.SIGTERM, on_interrupt)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="frepvdb", description="FRep models and meshes to sparse OpenVDB grids.")
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run one or more configs")
    r.add_argument("configs", nargs="+", type=Path)
    r.add_argument("--out", default="outputs", help="output root (default: outputs)")
    r.add_argument("--executor", choices=["local", "dask"], default=None, help="default: the config's, else local")
    r.add_argument("--workers", type=int, default=None)
    r.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    r.add_argument("--force", action="store_true", help="rerun jobs whose outputs are up to date")
    r.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    r.set_defaults(func=cmd_run)
    v = sub.add_parser("validate", help="parse and check a config; print it normalised")
    v.add_argument("config", type=Path)
    v.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    v.set_defaults(func=cmd_validate)
    i = sub.add_parser("info", help="describe the grids in a .vdb file")
    i.add_argument("file", type=Path)
    i.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    i.set_defaults(func=cmd_info)
    c = sub.add_parser("collide", help="do two models intersect? (component count of A AND B)")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--tolerance", type=float, default=None, help="finest cell (default: the smaller voxel size)")
    c.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    c.set_defaults(func=cmd_collide)
    return ap


def cmd_validate(args) -> int:
    from pipeline.config import load_jobs

    jobs = load_jobs(args.config)
    # libyaml's emitter when present: a frames sweep prints thousands of documents
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    print(yaml.dump_all([j.normalised for j in jobs], Dumper=dumper, sort_keys=False), end="")
    return EXIT_OK


def cmd_info(args) -> int:
    from pipeline.vdbinfo import describe_vdb_isolated

    try:
        print(describe_vdb_isolated(args.file), end="")
    except (OSError, ValueError) as e:
        print(f"error: {_one_line(e)}", file=sys.stderr)
        return EXIT_INPUT
    return EXIT_OK


#: finest collision octree: ``--tolerance`` at most this many halvings of the common box
COLLIDE_MAX_DEPTH = 20


def cmd_collide(args) -> int:
    """components seed, section 5: collision iff the intersection has a component."""
    import math

    import numpy as np

    from pipeline.components import collide, depth_for
    from pipeline.config import load_job

    if args.tolerance is not None and not (math.isfinite(args.tolerance) and args.tolerance > 0):
        print(f"error: --tolerance must be a finite number > 0, got {args.tolerance:g}", file=sys.stderr)
        return EXIT_INPUT
    a, b = load_job(args.a), load_job(args.b)
    tol = args.tolerance if args.tolerance is not None else min(a.domain.voxel_size, b.domain.voxel_size)
    lo = np.maximum(np.asarray(a.domain.bounds[0]), np.asarray(b.domain.bounds[0]))
    hi = np.minimum(np.asarray(a.domain.bounds[1]), np.asarray(b.domain.bounds[1]))
    size = float((hi - lo).max())
    if size > 0 and depth_for(size, tol) > COLLIDE_MAX_DEPTH:
        print(f"error: --tolerance {tol:g} is finer than the limit ({size / 2**COLLIDE_MAX_DEPTH:.3g}: the common "
              f"box of {size:g} halved {COLLIDE_MAX_DEPTH} times)", file=sys.stderr)
        return EXIT_INPUT
    res = collide(a.model, b.model, (lo, hi), tol, a.t, b.t)
    print(f"collision: {'yes' if res.collide else 'no'}")
    print(f"tolerance: {res.tolerance:g} (octree depth {res.depth}, {res.count} component(s) in the intersection)")
    return EXIT_OK


def cmd_run(args) -> int:
    from pipeline.batch import make_executor, run_batch
    from pipeline.config import load_jobs
    from pipeline.progress import BatchProgress

    status = EXIT_OK
    jobs = []
    for cfg in args.configs:
        try:
            jobs.extend(load_jobs(cfg))
        except ConfigError as e:
            _print_problems(e)
            status = EXIT_INPUT
    if not jobs:
        return status
    from pipeline.batch import check_unique_names
    from pipeline.outputs import prepare_out_root

    try:
        check_unique_names(jobs)
        out = prepare_out_root(args.out)
    except ConfigError as e:
        _print_problems(e)
        return EXIT_INPUT
    conf = next((j.executor for j in jobs if j.executor is not None), None)
    kind = args.executor or (conf.kind if conf else "local")
    workers = args.workers or (conf.workers if conf else None)
    scheduler = args.scheduler or (conf.scheduler if conf else None)
    bricked = any(j.bricks for j in jobs)
    executor = make_executor(kind, workers, scheduler, jobs=len(jobs) + (2 if bricked else 0))
    try:
        with BatchProgress(jobs) as progress:
            rows = run_batch(jobs, out, executor, force=args.force, on_done=progress.job_done,
                             progress=progress.stage)
    except KeyboardInterrupt:
        executor.close(interrupted=True)
        raise
    executor.close()
    for row in rows:
        if row["status"] == "input-error":
            print("\n".join(f"error: {line}" for line in row["message"].splitlines()), file=sys.stderr)
            status = EXIT_INPUT
        elif row["status"] == "failed":
            print(f"error: {row['config']}: job {row['name']!r} failed: {row['message']}", file=sys.stderr)
            if args.debug and row.get("traceback"):
                print(row["traceback"], file=sys.stderr)
            status = status if status == EXIT_INPUT else EXIT_FAIL
    _summary(rows, out, executor.describe())
    return status


def _print_problems(e: ConfigError) -> None:
    for line in e.lines():
        print(f"error: {line}", file=sys.stderr)


def _summary(rows: list[dict], out: Path, where: str) -> None:
    """One line per job: status, time, active voxels, components, where the files are."""
    if len(rows) == 1 and rows[0]["status"] == "ok":
        r = rows[0]
        print(f"{r['name']}: {r.get('outputs', 0)} files in {out / r['name']} ({r['seconds']:.2f} s)")
        return
    print(f"{'job':<28} {'status':<12} {'seconds':>8} {'active voxels':>14} {'components':>10}  ({where})")
    for r in rows:
        av = r.get("active_voxels")
        comp = r.get("components")
        print(f"{r['name']:<28} {r['status']:<12} {r.get('seconds', 0):>8.2f} "
              f"{'' if av is None else av:>14} {'' if comp is None else comp:>10}")
    bad = sum(r["status"] in ("failed", "input-error") for r in rows)
    print(f"{len(rows)} jobs: {len(rows) - bad} ok or up to date, {bad} failed; outputs in {out}")

if __name__ == "__main__":
    sys.exit(main())
