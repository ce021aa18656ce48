"""Command line: ``frepvdb run | validate | info | collide | convert``. Exit 0 ok, 2 bad config or input, 1 failure.

Each command imports what it needs inside its function: deferred for start-up time (``info``
needs neither Numba nor the node registry, and VTK, matplotlib and trimesh load only for runs that
write VTK files or previews or read meshes: tests/test_config_cli.py). This
module is the top layer, so these imports all point down (tests/test_layers.py)."""

from __future__ import annotations

import argparse
import signal
import sys
import traceback
from pathlib import Path

import yaml

from pipeline.util.errors import ConfigError, interrupted, on_interrupt

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
    (both go through pipeline.util.errors.on_interrupt, so an interrupt inside compiled code is
    still reported as one)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    signal.signal(signal.SIGINT, on_interrupt)
    return signal.signal(signal.SIGTERM, on_interrupt)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="frepvdb", description="FRep models and meshes to sparse OpenVDB grids.",
        epilog="examples:\n  frepvdb run configs/demo.yaml --out outputs\n"
               "  frepvdb run part.yaml --set domain.resolution=512 --set 'stages[0].voxelise.band=4'\n"
               "  frepvdb convert part.stl part.vdb --voxel-size 0.01 --surface\n"
               "  frepvdb convert part.vdb part_out.stl\n"
               "Python: import frepvdb (docs/python-api.md)", formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run one or more configs")
    r.add_argument("configs", nargs="+", type=Path)
    r.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", dest="overrides",
                   help="override a config value, e.g. domain.resolution=512 or stages[0].voxelise.band=4 "
                        "(YAML value; repeatable; checked like the config)")
    r.add_argument("--out", default="outputs", help="output root (default: outputs)")
    r.add_argument("--executor", choices=["local", "dask"], default=None, help="default: the config's, else local")
    r.add_argument("--workers", type=int, default=None)
    r.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    r.add_argument("--force", action="store_true", help="rerun jobs whose outputs are up to date")
    r.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    r.set_defaults(func=cmd_run)
    v = sub.add_parser("validate", help="parse and check a config; print it normalised")
    v.add_argument("config", type=Path)
    v.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", dest="overrides",
                   help="override a config value (as for run)")
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
    _convert_parser(sub)
    return ap


def _convert_parser(sub) -> None:
    v = sub.add_parser(
        "convert", help="mesh -> .vdb (frep, and --surface level set) or .vdb level set -> mesh",
        description="One-step conversions, like vdb_tool -read part.stl -mesh2ls -write part.vdb. A mesh "
                    "(.off .obj .stl .ply) becomes a .vdb with the 'frep' grid (BSP-field or ADF), and the "
                    "'surface' level set with --surface; the domain is the mesh's bounds padded by 10% and the "
                    "band. A .vdb becomes a closed triangle mesh (.stl .3mf .ply .obj) of its 'surface' grid "
                    "(else a level set, else 'frep').")
    v.add_argument("input", type=Path, help="mesh (.off .obj .stl .ply) or .vdb")
    v.add_argument("output", type=Path, help=".vdb for a mesh input; .stl .3mf .ply .obj for a .vdb input")
    size = v.add_mutually_exclusive_group()
    size.add_argument("--voxel-size", type=float, default=None, help="voxel edge, world units")
    size.add_argument("--resolution", type=int, default=None,
                      help="voxels along the mesh's longest side (default 256)")
    v.add_argument("--band", type=float, default=3.0, help="narrow-band half-width in voxels (default 3)")
    v.add_argument("--rfunc", choices=["min_max", "r0", "sardf"], default="min_max",
                   help="R-functions of the BSP-field (default min_max: compiled per-cell tapes; r0, sardf: C1)")
    v.add_argument("--method", choices=["bsp", "adf"], default="bsp", help="exact BSP-field or approximate ADF")
    v.add_argument("--surface", action="store_true", help="also the 'surface' level set (eikonal distance)")
    v.add_argument("--allow-open", action="store_true",
                   help="convert a mesh that is not closed (with a warning; its field is then not exact)")
    v.add_argument("--grid", default=None, help="grid of a .vdb input to mesh (default: surface, a level set, frep)")
    v.add_argument("--debug", action="store_true", help="print tracebacks of failures")
    v.set_defaults(func=cmd_convert)


def cmd_validate(args) -> int:
    from pipeline.job.config import load_jobs

    jobs = load_jobs(args.config, overrides=args.overrides)
    # libyaml's emitter when present: a frames sweep prints thousands of documents
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    print(yaml.dump_all([j.normalised for j in jobs], Dumper=dumper, sort_keys=False), end="")
    return EXIT_OK


def cmd_info(args) -> int:
    from pipeline.io.vdbinfo import describe_vdb_isolated

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

    from pipeline.job.config import load_job
    from pipeline.topology.components import collide, depth_for

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


def _say_first_run() -> None:
    """On a terminal, before any model is built (that compiles already): the first run of these
    sources compiles the kernels for minutes."""
    from pipeline import first_run_notice

    notice = first_run_notice()
    if notice and sys.stderr.isatty():
        print(notice, file=sys.stderr)


def cmd_run(args) -> int:
    from pipeline.job.batch import make_executor, run_batch
    from pipeline.job.config import load_jobs
    from pipeline.job.display import BatchProgress
    from pipeline.job.runner import model_warnings

    _say_first_run()
    status = EXIT_OK
    jobs = []
    for cfg in args.configs:
        try:
            jobs.extend(load_jobs(cfg, overrides=args.overrides))
        except ConfigError as e:
            _print_problems(e)
            status = EXIT_INPUT
    if not jobs:
        return status
    from pipeline.job.batch import check_unique_names
    from pipeline.job.outputs import prepare_out_root

    try:
        check_unique_names(jobs)
        out = prepare_out_root(args.out)
        if args.overrides:  # workers and bricks load their job by file: run the overridden config's file
            jobs = _overridden_jobs(args.configs, args.overrides, out)
    except ConfigError as e:
        _print_problems(e)
        return EXIT_INPUT
    for j in jobs:  # the model's warnings before the run (a slow rfunc is worth knowing before it starts)
        for w in model_warnings(j):
            print(f"warning: {j.name}: {w}", file=sys.stderr)
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


def _overridden_jobs(configs: list[Path], overrides: list[str], out: Path) -> list:
    """The jobs of each config with ``--set`` applied, from its effective config written under
    ``<out>/.frepvdb-configs/`` (pipeline.job.config.write_config)."""
    from pipeline.job.config import apply_overrides, load_jobs, load_yaml, write_config

    jobs = []
    for cfg in configs:
        root = load_yaml(cfg)
        apply_overrides(root, overrides, str(cfg))
        jobs.extend(load_jobs(write_config(root, cfg.resolve().parent, out, cfg.stem)))
    return jobs


#: default voxels along the mesh's longest side for ``convert``
CONVERT_RESOLUTION = 256
#: ``convert`` pads the mesh's bounds by this fraction of its longest side, plus the band
CONVERT_PAD = 0.1


def cmd_convert(args) -> int:
    """mesh -> .vdb through a job (the runner, its checks and safe outputs), or .vdb -> mesh."""
    from pipeline.mesh.meshio import SUFFIXES

    src, dst = args.input.suffix.lower(), args.output.suffix.lower()
    if src in SUFFIXES:
        if dst != ".vdb":
            return _usage(f"{args.output}: a mesh converts to a .vdb file (got {dst or 'no suffix'!r})")
        return _mesh_to_vdb(args)
    if src == ".vdb":
        from pipeline.io.meshout import MESH_KINDS

        if dst.lstrip(".") not in MESH_KINDS:
            return _usage(f"{args.output}: a .vdb converts to a mesh file: .{', .'.join(MESH_KINDS)} "
                          f"(got {dst or 'no suffix'!r})")
        return _vdb_to_mesh(args)
    return _usage(f"{args.input}: cannot convert {src or 'a file without suffix'!r} (use a mesh: "
                  f"{' '.join(SUFFIXES)}, or a .vdb)")


def _usage(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return EXIT_INPUT


def _finite_positive(name: str, value: float | None) -> str | None:
    import math

    if value is not None and not (math.isfinite(value) and value > 0):
        return f"{name} must be a finite number > 0, got {value:g}"
    return None


def convert_config(args, bounds) -> dict:
    """The config ``convert`` runs for a mesh whose bounds are ``bounds`` (lo, hi)."""
    import numpy as np

    lo, hi = (np.asarray(b, float) for b in bounds)
    extent = float((hi - lo).max())
    h = args.voxel_size if args.voxel_size is not None else extent / (args.resolution or CONVERT_RESOLUTION)
    pad = CONVERT_PAD * extent + (args.band + 1) * h
    stages: list[dict] = [{"voxelise": {"band": float(args.band)}}]
    grids = ["frep"]
    if args.surface:
        stages.append({"hfrep": {"density": False, "quality": False}})
        grids.append("surface")
    stages.append({"export": {"vdb": True, "grids": grids, "report": False}})
    return {"name": "convert",
            "domain": {"bounds": [(lo - pad).tolist(), (hi + pad).tolist()], "voxel_size": float(h)},
            "model": {"mesh": {"path": str(args.input.resolve()), "method": args.method, "rfunc": args.rfunc,
                               **({"allow_open": True} if getattr(args, "allow_open", False) else {})}},
            "stages": stages}


def _mesh_to_vdb(args) -> int:
    import os
    import shutil
    import tempfile

    from pipeline.job.batch import make_executor, run_batch
    from pipeline.job.config import load_jobs, write_config
    from pipeline.mesh.meshio import MeshError, holding, load_mesh

    problem = (_finite_positive("--voxel-size", args.voxel_size) or _finite_positive("--band", args.band)
               or (f"--resolution must be > 0, got {args.resolution}" if args.resolution is not None
                   and args.resolution <= 0 else None))
    if problem:
        return _usage(problem)
    _say_first_run()
    try:
        loaded = load_mesh(args.input)
    except MeshError as e:
        return _usage(str(e))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".frepvdb-convert-", dir=args.output.parent))
    try:
        cfg = write_config(convert_config(args, loaded[0].bounds), Path.cwd(), work, "convert")
        try:
            with holding(args.input, loaded):  # the node takes the mesh read above
                jobs = load_jobs(cfg)
        except ConfigError as e:  # the mesh's own problem (not closed, ...): the config is ours, not the user's
            return _usage("; ".join(msg for *_, msg in e.problems))
        executor = make_executor("local", None, None, jobs=1)
        (row,) = run_batch(jobs, work, executor, force=True)
        if row["status"] != "ok":
            return _usage(row["message"]) if row["status"] == "input-error" else _fail(row["message"])
        os.replace(work / "convert" / "convert.vdb", args.output)  # verified by the runner; one rename
    finally:
        shutil.rmtree(work, ignore_errors=True)
    for w in row.get("warnings", []):  # the manifest that held them is not kept
        print(f"warning: {w}", file=sys.stderr)
    print(f"{args.output}: {', '.join(jobs[0].stages[-1][1].grids)} (voxel size {jobs[0].domain.voxel_size:g}, "
          f"{row.get('active_voxels')} active voxels, {row['seconds']:.2f} s)")
    return EXIT_OK


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return EXIT_FAIL


def _vdb_to_mesh(args) -> int:
    from pipeline.io.meshout import WRITERS, zero_set
    from pipeline.io.vdbio import read_grids

    if not args.input.is_file():
        return _usage(f"{args.input}: file not found")
    try:
        grids = read_grids(args.input)
    except Exception as e:  # noqa: BLE001 - OpenVDB raises plain RuntimeErrors here
        return _usage(f"{args.input}: does not open as a .vdb ({_one_line(e, 120)})")
    name = args.grid or next((n for n in ("surface", *(n for n, g in grids.items() if str(g.gridClass) ==
                                                     "level set"), "frep") if n in grids), None)
    if name is None or name not in grids:
        return _usage(f"{args.input}: no grid {'named ' + repr(name) if name else 'to mesh'} "
                      f"(grids: {', '.join(grids) or 'none'}; pick one with --grid)")
    if not hasattr(grids[name], "convertToPolygons") or grids[name].valueTypeName != "float":
        return _usage(f"{args.input}: grid {name!r} is {grids[name].valueTypeName}, not a float field")
    mesh = zero_set(grids[name])
    if len(mesh.triangles) == 0:
        return _usage(f"{args.input}: grid {name!r} has no zero crossing to mesh")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    entry = WRITERS[args.output.suffix.lower().lstrip(".")](args.output, mesh)
    closed = "closed" if entry["open_edges"] == 0 else f"NOT closed: {entry['open_edges']} open edges"
    print(f"{args.output}: {entry['triangles']} triangles from grid {name!r}, {closed}, volume {entry['volume']:.6g}")
    return EXIT_OK


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

def run() -> None:
    """The console entry point (``frepvdb``, ``python -m pipeline.cli``): :func:`main`, then exit.

    After an interrupt the run has said "interrupted" and cleaned up; objects finalised at exit
    may then be half made (an interrupt during a Numba compilation leaves llvmlite objects whose
    ``__del__`` raises), and Python would print their errors as tracebacks. Those are not shown."""
    code = main()
    if interrupted():
        sys.unraisablehook = lambda unraisable: None
    sys.exit(code)


if __name__ == "__main__":
    run()
