"""Command line: ``frepvdb run | validate | info``. Exit 0 ok, 2 bad config or input, 1 failure."""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

import yaml

from pipeline.errors import ConfigError

EXIT_OK, EXIT_FAIL, EXIT_INPUT = 0, 1, 2


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return args.func(args)
    except ConfigError as e:
        for line in e.lines():
            print(f"error: {line}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_FAIL


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="frepvdb", description="FRep models and meshes to sparse OpenVDB grids.")
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run one or more configs")
    r.add_argument("configs", nargs="+", type=Path)
    r.add_argument("--out", type=Path, default=Path("outputs"), help="output root (default: outputs)")
    r.add_argument("--executor", choices=["local", "dask"], default="local")
    r.add_argument("--workers", type=int, default=None)
    r.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    r.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    r.set_defaults(func=cmd_run)
    v = sub.add_parser("validate", help="parse and check a config; print it normalised")
    v.add_argument("config", type=Path)
    v.set_defaults(func=cmd_validate)
    i = sub.add_parser("info", help="describe the grids in a .vdb file")
    i.add_argument("file", type=Path)
    i.set_defaults(func=cmd_info)
    return ap


def cmd_validate(args) -> int:
    from pipeline.config import load_job

    job = load_job(args.config)
    print(yaml.safe_dump(job.normalised, sort_keys=False), end="")
    return EXIT_OK


def cmd_info(args) -> int:
    from pipeline.vdbinfo import describe_vdb

    try:
        print(describe_vdb(args.file))
    except (OSError, ValueError) as e:
        print(f"error: {args.file}: {e}", file=sys.stderr)
        return EXIT_INPUT
    return EXIT_OK


def cmd_run(args) -> int:
    from pipeline.config import load_job
    from pipeline.progress import StageProgress
    from pipeline.runner import run_job

    status = EXIT_OK
    jobs = []
    for cfg in args.configs:
        try:
            jobs.append(load_job(cfg))
        except ConfigError as e:
            for line in e.lines():
                print(f"error: {line}", file=sys.stderr)
            status = EXIT_INPUT
    for job in jobs:
        with StageProgress(job.name, len(job.stages)) as progress:
            try:
                manifest = run_job(job, args.out, progress=progress)
            except ConfigError as e:
                for line in e.lines():
                    print(f"error: {line}", file=sys.stderr)
                status = EXIT_INPUT
                continue
            except Exception as e:  # a failure while running: report, go on with the others
                if args.debug:
                    traceback.print_exc()
                print(f"error: {job.config_path}: job {job.name!r} failed: {type(e).__name__}: {e}", file=sys.stderr)
                status = max(status, EXIT_FAIL) if status != EXIT_INPUT else status
                continue
        secs = sum(s["seconds"] for s in manifest["stages"])
        print(f"{job.name}: {len(manifest['outputs'])} files in {Path(args.out) / job.name} ({secs:.2f} s)")
    return status


if __name__ == "__main__":
    sys.exit(main())
