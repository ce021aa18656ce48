"""Config loading: YAML with line numbers -> validated job description with a model tree.

Every problem becomes a :class:`~pipeline.errors.ConfigError` that names the file, the line
and the YAML path (``configs/x.yaml:14 model.union[1].sphere.radius: must be > 0``).
Unknown keys are errors with a "did you mean" hint.
"""

from __future__ import annotations

import difflib
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from pipeline.errors import ConfigError, InputError, format_path
from pipeline.nodes import REGISTRY, Node
from pipeline.nodes.base import Vec3
from pipeline.nodes.expr import FormulaError
from pipeline.outputs import job_name_problem

MAX_INDEX = 2**30  # OpenVDB index coordinates are 32-bit; keep a safety margin


# --- YAML with line numbers -----------------------------------------------------------------


class LineDict(dict):
    """dict that remembers the line of each key (1-based)."""

    line: int = 0

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.lines: dict[Any, int] = {}


class LineList(list):
    line: int = 0

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.lines: list[int] = []


class _Loader(yaml.SafeLoader):
    pass


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> LineDict:
    loader.flatten_mapping(node)
    d = LineDict()
    d.line = node.start_mark.line + 1
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in d:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        d[key] = loader.construct_object(value_node, deep=True)
        d.lines[key] = key_node.start_mark.line + 1
    return d


def _construct_sequence(loader: _Loader, node: yaml.SequenceNode) -> LineList:
    seq = LineList(loader.construct_object(child, deep=True) for child in node.value)
    seq.line = node.start_mark.line + 1
    seq.lines = [child.start_mark.line + 1 for child in node.value]
    return seq


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)


def load_yaml(path: Path) -> Any:
    """Parse YAML keeping line numbers; malformed YAML is a ConfigError with its line."""
    try:
        text = path.read_text()
    except OSError as e:
        raise ConfigError.one(str(path), None, (), f"cannot read config: {e.strerror or e}") from None
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - our SafeLoader subclass
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(e, "problem", None) or str(e)
        raise ConfigError.one(str(path), line, (), f"malformed YAML: {problem}") from None


def line_of(root: Any, path: tuple) -> int | None:
    """Line of the deepest element of ``path`` that exists in the parsed YAML."""
    node, line = root, getattr(root, "line", None)
    for part in path:
        if isinstance(node, LineDict) and part in node:
            line, node = node.lines.get(part, line), node[part]
        elif isinstance(node, LineList) and isinstance(part, int) and 0 <= part < len(node):
            line, node = node.lines[part], node[part]
        else:
            break
    return line


# --- pydantic errors -> messages ---------------------------------------------------------------


def _message(err: dict, allowed: list[str]) -> str:
    kind, ctx = err["type"], err.get("ctx", {})
    if kind == "missing":
        return "missing required key"
    if kind == "extra_forbidden":
        key = str(err["loc"][-1])
        hint = difflib.get_close_matches(key, allowed, n=1)
        alts = f" (did you mean {hint[0]!r}?)" if hint else f" (allowed: {', '.join(allowed)})"
        return f"unknown key {key!r}{alts}"
    ops = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in ops:
        bound = next(iter(ctx.values()))
        return f"must be {ops[kind]} {bound}"
    msg = err["msg"]
    msg = msg.removeprefix("Value error, ").removeprefix("Assertion failed, ")
    return msg.replace("Input should be", "must be")


def _clean_loc(loc: tuple) -> tuple:
    """Drop pydantic's union-member tags (e.g. 'tuple[float, float, float]') from a location."""
    return tuple(p for p in loc if isinstance(p, int) or ("[" not in p and p not in _TYPE_TAGS))


_TYPE_TAGS = {"float", "int", "str", "bool", "function-after", "literal", "list", "dict"}


def validation_problems(exc: ValidationError, file: str, root: Any, base: tuple, model: type[BaseModel],
                        strip: str | None = None) -> list:
    allowed = sorted({(f.alias or n) for n, f in model.model_fields.items()})
    seen, problems = set(), []
    for err in exc.errors():
        loc = _clean_loc(err["loc"])
        if strip and loc and loc[0] == strip:
            loc = loc[1:]
        path = base + loc
        msg = _message(err, allowed)
        if (path, msg) in seen or any(p[2] == path for p in problems):
            continue  # one message per path (unions produce one error per member)
        seen.add((path, msg))
        problems.append((file, line_of(root, path), path, msg))
    return problems


# --- model tree --------------------------------------------------------------------------------

NODE_SIBLINGS = ("rfunc",)


@dataclass
class _Ctx:
    file: str
    root: Any
    base_dir: Path
    #: the job being built: node classes with ``uses_domain = True`` (e.g. ``hfrep``) get
    #: ``domain=`` and ``t=`` for defaults that depend on the job (bounds, voxel size)
    domain: Any = None
    t: float = 0.0

    def fail(self, path: tuple, message: str) -> ConfigError:
        return ConfigError.one(self.file, line_of(self.root, path), path, message)


def build_node(raw: Any, path: tuple, ctx: _Ctx) -> Node:
    """Build a node from ``{type: params}`` (plus optional ``rfunc``) at YAML ``path``."""
    kinds = sorted(REGISTRY)
    if not isinstance(raw, dict) or not raw:
        raise ctx.fail(path, f"a node is a mapping with one key, its type (one of: {', '.join(kinds)})")
    type_keys = [k for k in raw if k not in NODE_SIBLINGS]
    if len(type_keys) != 1:
        raise ctx.fail(path, f"a node has exactly one type key, found {len(type_keys)}: {type_keys}")
    kind = type_keys[0]
    if kind not in REGISTRY:
        hint = difflib.get_close_matches(str(kind), kinds, n=1)
        alts = f"did you mean {hint[0]!r}?" if hint else f"known: {', '.join(kinds)}"
        raise ctx.fail(path + (kind,), f"unknown node type {kind!r} ({alts})")
    cls = REGISTRY[kind]
    body, strip = _normalise_body(cls, raw[kind], path + (kind,), ctx)
    for sib in NODE_SIBLINGS:
        if sib in raw:
            if sib not in cls.Params.model_fields:
                raise ctx.fail(path + (sib,), f"{sib!r} does not apply to {kind}")
            body[sib] = raw[sib]
    here = path + (kind,)
    for name in cls.child_fields:
        key = cls.Params.model_fields[name].alias or name
        if key in body:
            body[key] = _build_children(body[key], here + (() if strip else (key,)), ctx)
    try:
        params = cls.Params.model_validate(body)
    except ValidationError as e:
        raise ConfigError(validation_problems(e, ctx.file, ctx.root, here, cls.Params, strip)) from None
    job_args = {"domain": ctx.domain, "t": ctx.t} if getattr(cls, "uses_domain", False) else {}
    try:
        return cls(params, where=format_path(here), **job_args)
    except FormulaError as e:
        raise ctx.fail(here + (() if strip else ("formula",)), f"bad formula: {e}") from None
    except InputError as e:
        raise ctx.fail(here, str(e)) from None
    except OSError as e:  # a file the node names cannot be opened (too long a name, permissions, ...)
        name = str(e.filename or "")
        shown = name if len(name) <= 80 else name[:60] + f"... ({len(name)} characters)"
        raise ctx.fail(here, f"cannot open {shown}: {e.strerror or e}") from None


def _normalise_body(cls: type[Node], body: Any, path: tuple, ctx: _Ctx) -> tuple[dict, str | None]:
    """Accept the shorthands ``union: [..]`` and ``expr: "formula"``; returns (body, stripped key)."""
    if isinstance(body, list) and cls.list_field:
        return {cls.list_field: body}, cls.list_field
    scalar = getattr(cls, "scalar_field", None)
    if isinstance(body, str) and scalar:
        return {scalar: body}, scalar
    if body is None:
        return {}, None
    if not isinstance(body, dict):
        raise ctx.fail(path, f"parameters of {cls.kind} must be a mapping, got {type(body).__name__}")
    out = dict(body)
    if "path" in out and isinstance(out["path"], str):  # file inputs are relative to the config
        p = Path(out["path"]).expanduser()
        out["path"] = str(p if p.is_absolute() else (ctx.base_dir / p))
    return out, None


def _build_children(value: Any, path: tuple, ctx: _Ctx):
    if isinstance(value, list):
        return [build_node(item, path + (i,), ctx) for i, item in enumerate(value)]
    return build_node(value, path, ctx)


# --- top level ---------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DomainConfig(_Strict):
    bounds: tuple[Vec3, Vec3]
    voxel_size: float | None = Field(default=None, gt=0)
    resolution: int | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _check(self):
        lo, hi = self.bounds
        if any(a >= b for a, b in zip(lo, hi, strict=True)):
            raise ValueError("bounds: the first corner must be below the second on every axis")
        if (self.voxel_size is None) == (self.resolution is None):
            raise ValueError("give exactly one of voxel_size or resolution")
        return self


class FramesConfig(_Strict):
    """A sweep of the model's time parameter: ``count`` frames from t[0] to t[1]."""

    count: int = Field(ge=1, le=100000)
    t: tuple[float, float] = (0.0, 1.0)


class ExecutorConfig(_Strict):
    kind: Literal["local", "dask"] = "local"
    workers: int | None = Field(default=None, ge=1)
    scheduler: str | None = Field(default=None, description="address of an existing Dask scheduler")


class BricksConfig(_Strict):
    size: int = Field(ge=8, description="voxels per brick side (a multiple of 8, the VDB leaf)")

    @model_validator(mode="after")
    def _leaf_multiple(self):
        if self.size % 8:
            raise ValueError("size must be a multiple of 8 (OpenVDB leaf nodes are 8^3)")
        return self


def _check_name(name: str) -> str:
    problem = job_name_problem(name) if name else None
    if problem:
        raise ValueError(problem)
    return name


JobName = Annotated[str, AfterValidator(_check_name)]


class JobEntry(_Strict):
    """One entry of ``jobs:``; missing keys come from the top level."""

    name: JobName = Field(min_length=1)
    domain: DomainConfig | None = None
    model: Any
    stages: list[Any] | None = Field(default=None, min_length=1)
    t: float | None = None


class TopConfig(_Strict):
    name: JobName = ""
    domain: DomainConfig | None = None
    model: Any = None
    stages: list[Any] | None = Field(default=None, min_length=1)
    t: float = Field(default=0.0, description="time parameter of the model (morph, expr)")
    jobs: list[JobEntry] | None = Field(default=None, min_length=1)
    frames: FramesConfig | None = None
    executor: ExecutorConfig | None = None
    bricks: BricksConfig | None = None

    @model_validator(mode="after")
    def _model_or_jobs(self):
        if (self.model is None) == (self.jobs is None):
            raise ValueError("give either model (one job) or jobs (a list of jobs)")
        return self


@dataclass(frozen=True)
class Domain:
    """World box and its voxelisation: voxel (i,j,k) centred at (i,j,k) * voxel_size."""

    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    voxel_size: float

    @property
    def index_min(self) -> np.ndarray:
        return np.ceil(np.asarray(self.bounds[0]) / self.voxel_size - 1e-9).astype(np.int64)

    @property
    def index_max(self) -> np.ndarray:
        return np.floor(np.asarray(self.bounds[1]) / self.voxel_size + 1e-9).astype(np.int64)

    @property
    def dims(self) -> np.ndarray:
        return self.index_max - self.index_min + 1

    def to_json(self) -> dict:
        return {"bounds": [list(self.bounds[0]), list(self.bounds[1])], "voxel_size": self.voxel_size,
                "dims": [int(d) for d in self.dims]}


@dataclass
class Job:
    name: str
    config_path: str
    config_sha256: str
    domain: Domain
    model: Node
    stages: list[tuple[str, Any]]
    t: float = 0.0
    raw: Any = None
    normalised: dict = field(default_factory=dict)
    index: tuple[int, int] = (0, 0)  # (entry in jobs:, frame): how a worker finds this job again
    frame: dict | None = None  # {"index", "count", "t", "series"} for frame sweeps
    bricks: int | None = None
    executor: ExecutorConfig | None = None
    job_sha256: str = ""  # hash of the normalised job and its input files: the key for resume
    name_line: int | None = None  # line of its ``name:`` key (None: the name is the file's stem)


def load_jobs(path: str | Path, select: str | None = None) -> list[Job]:
    """Load and validate a config file into its jobs (one, a ``jobs:`` list, times ``frames``).

    ``select`` builds only the job of that name (how a worker finds its job again)."""
    path = Path(path)
    file = str(path)
    root = load_yaml(path)
    if not isinstance(root, dict):
        raise ConfigError.one(file, getattr(root, "line", 1), (), "a config is a mapping (name, domain, model, stages)")
    try:
        top = TopConfig.model_validate(root)
    except ValidationError as e:
        raise ConfigError(validation_problems(e, file, root, (), TopConfig)) from None
    ctx = _Ctx(file, root, path.resolve().parent)
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    if top.jobs is None and not top.name and job_name_problem(path.stem):
        raise ConfigError.one(file, None, (), f"the job is named after the file ({path.name!r}), which is not a "
                              f"valid job name: {job_name_problem(path.stem)}; add a `name:` key")
    entries = [(None, top.name or path.stem, None, top.model, None, None)] if top.jobs is None else [
        (i, e.name, e.domain, e.model, e.stages, e.t) for i, e in enumerate(top.jobs)]
    jobs = []
    for i, name, dom, model_raw, stages_raw, t in entries:
        base = () if i is None else ("jobs", i)
        jobs.extend(_entry_jobs(ctx, top, sha, base, i or 0, name, dom, model_raw, stages_raw, t, select))
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ctx.fail(("jobs",), f"job names must be unique (outputs go to <out>/<name>/): {dup}")
    return jobs


def load_job(path: str | Path) -> Job:
    """The single job of a config file (a ``jobs:`` or ``frames:`` config is an error here)."""
    jobs = load_jobs(path)
    if len(jobs) != 1:
        raise ConfigError.one(str(path), None, (), f"expected one job, the config makes {len(jobs)}")
    return jobs[0]


def _entry_jobs(ctx: _Ctx, top: TopConfig, sha: str, base: tuple, index: int, name: str,
                dom: DomainConfig | None, model_raw: Any, stages_raw: list | None, t: float | None,
                select: str | None = None) -> list[Job]:
    if dom is None and top.domain is None:
        raise ctx.fail(base, "missing required key 'domain' (here or at the top level)")
    if stages_raw is None and top.stages is None:
        raise ctx.fail(base, "missing required key 'stages' (here or at the top level)")
    domain = _domain(dom or top.domain, ctx, base if dom is not None else ())
    stages = _stages(stages_raw or top.stages, ctx, base + ("stages",) if stages_raw is not None else ("stages",))
    frames = [(None, top.t if t is None else t)]
    if top.frames is not None:
        c, (t0, t1) = top.frames.count, top.frames.t
        frames = [(f, t0 + (t1 - t0) * f / max(c - 1, 1)) for f in range(c)]
    jobs = []
    for f, tf in frames:
        job_name = name if f is None else f"{name}_f{f:04d}"
        if select is not None and job_name != select:
            continue
        ctx.domain, ctx.t = domain, tf
        model = build_node(model_raw, base + ("model",), ctx)  # each job owns its tree
        job = Job(job_name, ctx.file, sha, domain, model, stages, tf, ctx.root, index=(index, f or 0),
                  bricks=top.bricks.size if top.bricks else None, executor=top.executor,
                  name_line=_name_line(ctx.root, base))
        if job_name_problem(job_name):  # a frame suffix can make a valid name too long
            raise ctx.fail(base + ("name",), job_name_problem(job_name))
        if f is not None:
            job.frame = {"index": f, "count": top.frames.count, "t": tf, "series": name}
        job.normalised = _normalised(job, model_raw)
        job.job_sha256 = _job_hash(job)
        _check_model_values(job, ctx)
        _check_memory(job, ctx, base)
        jobs.append(job)
    return jobs


def _name_line(root: Any, base: tuple) -> int | None:
    node = root
    for part in base:
        node = node[part]
    return node.lines.get("name") if isinstance(node, LineDict) and "name" in node else None


def _job_hash(job: Job) -> str:
    """Hash of what determines a job's outputs: its normalised config and its input files."""
    h = hashlib.sha256(json.dumps(job.normalised, sort_keys=True, default=str).encode())
    for node in job.model.walk():
        path = getattr(node.params, "path", None)
        if isinstance(path, str) and Path(path).is_file():
            h.update(hashlib.sha256(Path(path).read_bytes()).digest())
    return h.hexdigest()


def _domain(d: DomainConfig, ctx: _Ctx, base: tuple = ()) -> Domain:
    lo, hi = d.bounds
    extent = max(b - a for a, b in zip(lo, hi, strict=True))
    h = d.voxel_size if d.voxel_size is not None else extent / d.resolution
    dom = Domain((tuple(lo), tuple(hi)), float(h))
    if np.abs(np.concatenate([dom.index_min, dom.index_max])).max() >= MAX_INDEX:
        key = "voxel_size" if d.voxel_size is not None else "resolution"
        raise ctx.fail(base + ("domain", key), f"index coordinates exceed OpenVDB's 32-bit range (voxel size {h:g})")
    return dom


def _stages(raw: list, ctx: _Ctx, base: tuple = ("stages",)) -> list[tuple[str, Any]]:
    from stages import REGISTRY as STAGES

    out = []
    for i, item in enumerate(raw):
        path = base + (i,)
        if not isinstance(item, dict) or len(item) != 1:
            raise ctx.fail(path, f"a stage is a mapping with one key, its name (one of: {', '.join(STAGES)})")
        name, body = next(iter(item.items()))
        if name not in STAGES:
            hint = difflib.get_close_matches(str(name), list(STAGES), n=1)
            alts = f"did you mean {hint[0]!r}?" if hint else f"known: {', '.join(STAGES)}"
            raise ctx.fail(path + (name,), f"unknown stage {name!r} ({alts})")
        model = STAGES[name].Params
        try:
            params = model.model_validate(body or {})
        except ValidationError as e:
            raise ConfigError(validation_problems(e, ctx.file, ctx.root, path + (name,), model)) from None
        out.append((name, params))
    names = [n for n, _ in out]
    for i, n in enumerate(names):
        needs = getattr(STAGES[n], "REQUIRES", ())
        missing = [r for r in needs if r not in names[:i]]
        if missing:
            raise ctx.fail(base + (i, n), f"needs the {', '.join(missing)} stage before it")
    return out


def _normalised(job: Job, model_raw: Any) -> dict:
    return {
        "name": job.name,
        "domain": job.domain.to_json(),
        "t": job.t,
        "model": _to_plain(model_raw),
        "stages": [{n: p.model_dump(mode="json", by_alias=True)} for n, p in job.stages],
    }


def _to_plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _to_plain(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_to_plain(v) for v in x]
    return x


def _check_model_values(job: Job, ctx: _Ctx) -> None:
    """Evaluate the model on a coarse lattice of the domain; NaN or inf is a config error that
    names the deepest node where it first appears (e.g. a formula dividing by zero)."""
    lo, hi = (np.asarray(b, float) for b in job.domain.bounds)
    n = 17
    axes = [np.linspace(lo[i], hi[i], n) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    err = locate_nonfinite(job, pts)
    if err is not None:
        raise err


def locate_nonfinite(job: Job, pts: np.ndarray) -> ConfigError | None:
    """ConfigError naming the deepest model node that is NaN or infinite at one of ``pts``."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    bad_node = None
    for node in job.model.walk():
        if getattr(node, "where", ""):
            vals = node.evaluate(pts, job.t)
            if not np.all(np.isfinite(vals)):
                bad_node = node  # keep going: the deepest offender is the most useful one
    if bad_node is not None:
        vals = bad_node.evaluate(pts, job.t)
        p = pts[~np.isfinite(vals)][0]
        where = tuple(_parse_path(bad_node.where))
        msg = (f"the field is not a finite number at ({p[0]:g}, {p[1]:g}, {p[2]:g}) "
               "(division by zero, log or sqrt of a negative number?)")
        return ConfigError.one(job.config_path, line_of(job.raw, where), where, msg)
    return None


def _parse_path(s: str) -> list:
    out: list = []
    for part in s.replace("[", ".[").split("."):
        if part.startswith("["):
            out.append(int(part[1:-1]))
        elif part:
            out.append(part)
    return out


HFREP_BYTES_PER_VOXEL = 30  # measured peak of the hfrep stage per interior voxel (docs/performance.md)


def _check_memory(job: Job, ctx: _Ctx, base: tuple = ()) -> None:
    """Refuse a domain whose grids would not fit in this machine's memory (estimates): the
    narrow band of voxelise, and the interior that the hfrep stage solves completely."""
    from pipeline.voxelise import estimate_band_bytes, estimate_interior_voxels

    voxelise = next((p for n, p in job.stages if n == "voxelise"), None)
    if voxelise is None or job.domain.dims.max() < 1024:
        return  # small domains always fit
    need = estimate_band_bytes(job.model, job.domain, voxelise.band, job.t)
    what = "its narrow band"
    if any(n == "hfrep" for n, _ in job.stages):
        need += HFREP_BYTES_PER_VOXEL * estimate_interior_voxels(job.model, job.domain, voxelise.band, job.t)
        what = "its narrow band and the interior distance of the hfrep stage"
    avail = _available_memory()
    if need > avail:
        local = _at(job.raw, base + ("domain",))
        raw_dom = local or job.raw.get("domain", {})
        key = "voxel_size" if "voxel_size" in raw_dom else "resolution"
        where = (base if local else ()) + ("domain", key)
        raise ctx.fail(where, f"this domain needs an estimated {need / 2**30:.1f} GiB for {what}; "
                              f"this machine has {avail / 2**30:.1f} GiB available")


def _at(root: Any, path: tuple) -> Any:
    node = root
    for part in path:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            return None
    return node


def _available_memory() -> int:
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover
        with open("/proc/meminfo") as f:
            info = dict(line.split(":", 1) for line in f)
        return int(info["MemAvailable"].split()[0]) * 1024

