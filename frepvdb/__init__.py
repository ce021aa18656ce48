"""frepvdb's Python API: build FRep models in code, evaluate and bound them, voxelise them into
OpenVDB grids in memory, and run configs.

    import frepvdb as fv
    part = (fv.sphere(1.0) & fv.box([-0.8] * 3, [0.8] * 3)) - fv.cylinder(0.4, axis="x")
    part = part.twist(30).translate([0, 0, 0.5])
    grid = fv.voxelise(part, [[-1.5] * 3, [1.5] * 3], voxel_size=0.02)   # a pyopenvdb FloatGrid
    print(part.to_yaml())                                                # the same model as YAML

Every node type of the config (docs/user-guide.md) is a function here with the same parameter
names; nodes with one child ``of`` are also methods of :class:`Shape`. The shapes are the
config's own data and are built into nodes by the config loader (pipeline.job.config.build_model):
a model written in Python and the same model in YAML evaluate, bound and voxelise identically.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from frepvdb.shape import POSITIONAL, SOURCE, Shape, make
from pipeline.io.meshout import WRITERS, zero_set
from pipeline.io.vdbio import write_vdb
from pipeline.job.batch import make_executor, run_batch
from pipeline.job.config import (
    ConfigError,
    Domain,
    Job,
    apply_overrides,
    jobs_from_root,
    load_jobs,
    load_yaml,
    make_domain,
    validation_problems,
    write_config,
)
from pipeline.job.context import JobContext
from pipeline.job.outputs import prepare_out_root
from pipeline.oracles import REGISTRY
from stages import voxelise as voxelise_stage

__all__ = ["Shape", "ConfigError", "load", "voxelise", "save", "run", "config", "domain", *sorted(REGISTRY)]


def _node_function(kind: str) -> Callable[..., Shape]:
    cls = REGISTRY[kind]
    names = POSITIONAL.get(kind, ())

    def fn(*args: Any, **kwargs: Any) -> Shape:
        return make(kind, args, kwargs)

    fn.__name__ = fn.__qualname__ = kind
    params = ", ".join(f.alias or n for n, f in cls.Params.model_fields.items())
    kids = " (child shapes first)" if cls.child_fields else ""
    fn.__doc__ = (f"The ``{kind}`` node{kids}: parameters {params}; positional: {', '.join(names) or 'none'}."
                  f"\n\n{(cls.__doc__ or '').strip()}")
    return fn


def _method(kind: str) -> Callable[..., Shape]:
    def method(self: Shape, *args: Any, **kwargs: Any) -> Shape:
        return make(kind, (self, *args), kwargs)

    method.__name__ = method.__qualname__ = kind
    method.__doc__ = f"``{kind}`` of this shape: frepvdb.{kind}(self, ...)."
    return method


def _install() -> None:
    """One function per registered node type, one method per node with a single child (and
    union/intersection/difference/blend with other shapes: ``a.union(b, rfunc="min_max")``)."""
    for kind, cls in REGISTRY.items():
        globals()[kind] = _node_function(kind)
        single = cls.child_fields == ("of",) and not cls.list_field
        if single or cls.list_field:
            setattr(Shape, kind, _method(kind))


_install()


def load(model: str | dict) -> Shape:
    """A shape from a model's YAML text or data (``{"sphere": {"radius": 1}}``): the inverse of
    :meth:`Shape.to_yaml`. Built through the config loader, so bad input gets its messages."""
    import yaml

    data = yaml.safe_load(model) if isinstance(model, str) else copy.deepcopy(model)
    if not isinstance(data, dict) or len(data) != 1:
        raise ConfigError.one(SOURCE, None, (), "a model is a mapping with one key, its node type")
    return _shape_of(data)


def _shape_of(data: Any) -> Any:
    if isinstance(data, list):
        return [_shape_of(x) for x in data]
    if not (isinstance(data, dict) and len(data) == 1 and next(iter(data)) in REGISTRY):
        return data
    kind, body = next(iter(data.items()))
    cls = REGISTRY[kind]
    if isinstance(body, list) and cls.list_field:
        body = {cls.list_field: body}
    elif isinstance(body, str) and getattr(cls, "scalar_field", None):
        body = {cls.scalar_field: body}
    body = dict(body or {})
    for name in cls.child_fields:
        key = cls.Params.model_fields[name].alias or name
        if key in body:
            body[key] = _shape_of(body[key])
    return make(kind, (), body)


def domain(bounds: Any, voxel_size: float | None = None, resolution: int | None = None) -> Domain:
    """A voxel domain (exactly one of ``voxel_size`` or ``resolution``, voxels on the longest side)."""
    return make_domain(_plain_bounds(bounds), voxel_size, resolution, file=SOURCE)


def _plain_bounds(bounds: Any) -> list:
    return [[float(c) for c in corner] for corner in bounds]


def voxelise(shape: Shape, bounds: Any, voxel_size: float | None = None, resolution: int | None = None,
             band: float = 3.0, block: int | str = "auto", t: float = 0.0):
    """The ``frep`` grid of ``shape`` over ``bounds`` as a pyopenvdb FloatGrid, in memory.

    Runs the ``voxelise`` stage itself (stages/voxelise.py) on a job made from the shape, so the
    grid is the one ``frepvdb run`` writes for the same model, domain and band."""

    dom = domain(bounds, voxel_size, resolution)
    job = _job(shape, dom, t)
    params = _stage_params(voxelise_stage.Params, "voxelise", {"band": band, "block": block})
    ctx = JobContext(job, Path.cwd())
    voxelise_stage.run(ctx, params)
    return ctx.grids["frep"]


def save(shape: Shape, path: str | Path, bounds: Any, voxel_size: float | None = None,
         resolution: int | None = None, band: float = 3.0, t: float = 0.0) -> Path:
    """Voxelise ``shape`` over ``bounds`` and write ``path``: a .vdb (the ``frep`` grid), or a closed
    triangle mesh of its zero set (.stl binary, .3mf, .ply, .obj; pipeline.io.meshout). Also a
    method: ``shape.save("part.stl", bounds, voxel_size=0.01)``."""

    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind != "vdb" and kind not in WRITERS:
        raise ValueError(f"{path}: cannot write {path.suffix or 'a file without suffix'!r} (use .vdb, "
                         f".{', .'.join(WRITERS)})")
    grid = voxelise(shape, bounds, voxel_size, resolution, band=band, t=t)
    if kind == "vdb":
        write_vdb(path, [grid], {"creator": "frepvdb"})
    else:
        WRITERS[kind](path, zero_set(grid))
    return path


Shape.save = save


def _stage_params(model: type, name: str, raw: dict) -> Any:
    from pydantic import ValidationError

    try:
        return model.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(validation_problems(e, SOURCE, {}, (name,), model)) from None


def _job(shape: Shape, dom: Domain, t: float) -> Job:
    data = shape.to_dict()
    sha = hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()
    return Job("python", SOURCE, sha, dom, shape.node(dom, t), [], float(t), {"model": data})


def config(shape: Shape, bounds: Any, voxel_size: float | None = None, resolution: int | None = None,
           stages: list | None = None, name: str = "model") -> dict:
    """A config (as data) that runs ``shape``: ``frepvdb.run(config(...))`` or write it as YAML.
    ``stages`` defaults to voxelise and export."""
    dom: dict[str, Any] = {"bounds": _plain_bounds(bounds)}
    dom.update({k: v for k, v in (("voxel_size", voxel_size), ("resolution", resolution)) if v is not None})
    return {"name": name, "domain": dom, "model": shape.to_dict(),
            "stages": stages if stages is not None else [{"voxelise": {"band": 3}}, {"export": {"vdb": True}}]}


def run(config_or_path: str | Path | dict, out: str | Path = "outputs", force: bool = False,
        overrides: list[str] | tuple = ()) -> list[dict]:
    """Run a config file or a config given as data (as ``frepvdb run``); returns each job's manifest.

    ``overrides``: ``KEY.PATH=VALUE`` strings as ``--set`` takes them. A config given as data, or
    one with overrides, is written to ``<out>/.frepvdb-configs/`` and run from there (workers and
    bricks find their job by its file). Bad input raises :class:`ConfigError`; a failed job
    RuntimeError."""

    if isinstance(config_or_path, dict):
        root = copy.deepcopy(config_or_path)
        jobs = jobs_from_root(copy.deepcopy(root), SOURCE, Path.cwd(), "", str(root.get("name") or "model"))
        base, stem = Path.cwd(), str(root.get("name") or "model")
    else:
        path = Path(config_or_path)
        jobs = load_jobs(path, overrides=overrides)
        root, base, stem = None, path.resolve().parent, path.stem
    out_root = prepare_out_root(out)
    if root is not None or overrides:
        cfg = write_config(root if root is not None else _overridden(path, overrides), base, out_root, stem)
        jobs = load_jobs(cfg)
    executor = make_executor("local", None, None, jobs=len(jobs))
    try:
        rows = run_batch(jobs, out_root, executor, force=force)
    finally:
        executor.close()
    for row in rows:
        if row["status"] == "input-error":
            raise ConfigError.one(row["config"], None, (), row["message"])
        if row["status"] == "failed":
            raise RuntimeError(f"job {row['name']!r} failed: {row['message']}")
    return [json.loads((out_root / r["name"] / "manifest.json").read_text()) for r in rows]


def _overridden(path: Path, overrides: list[str] | tuple) -> dict:
    root = load_yaml(path)
    apply_overrides(root, overrides, str(path))
    return root
