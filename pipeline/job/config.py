"""Config loading: YAML with line numbers -> validated job description with a model tree.

Every problem becomes a :class:`~pipeline.util.errors.ConfigError` that names the file, the line
and the YAML path (``configs/x.yaml:14 model.union[1].sphere.radius: must be > 0``).
Unknown keys are errors with a "did you mean" hint.
"""

from __future__ import annotations

import difflib
import functools
import hashlib
import json
import math
import textwrap
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from yaml.composer import Composer
from yaml.constructor import SafeConstructor
from yaml.parser import Parser
from yaml.reader import Reader
from yaml.resolver import Resolver
from yaml.scanner import Scanner

try:
    from yaml._yaml import CParser
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    CParser = None
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipeline.job.outputs import job_name_problem
from pipeline.model.base import Real, Vec3
from pipeline.model.expr import FormulaError
from pipeline.oracles import REGISTRY, Node
from pipeline.util.atomic import atomic_path
from pipeline.util.errors import ConfigError, InputError, format_path
from stages import REGISTRY as STAGES
from stages.base import FrepBand

MAX_INDEX = 2**30  # OpenVDB index coordinates are 32-bit; keep a safety margin


# --- limits (docs/user-guide.md, "Limits") ----------------------------------------------------

#: a config larger than this is refused before it is parsed (real configs are a few KB; YAML
#: parsing costs about 10 us per value in Python)
MAX_CONFIG_BYTES = 2 * 2**20
#: nesting of YAML collections (mappings and lists); a model tree of depth n nests about 2n
MAX_YAML_DEPTH = 100
#: alias uses (``*name``) in one config
MAX_YAML_ALIASES = 1000
#: collections and scalars of the config once every alias is expanded (the "billion laughs")
MAX_YAML_NODES = 250_000
#: entries of ``frames: {count: ...}``; validate builds and checks every frame
MAX_FRAMES = 10_000
#: children of one node (``union: [...]``); a union of 10^4 parts is an ordinary model (each child
#: is at least three YAML values, so MAX_YAML_NODES allows about 80,000)
MAX_CHILDREN = 50_000


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


class _LimitedComposer(Composer):
    """PyYAML's composer with limits checked before anything is built: nesting depth (the
    composer and our constructors recurse per level), alias uses and the expanded size."""

    def __init__(self) -> None:
        super().__init__()
        self._depth = 0
        self._aliases = 0
        self._total = 0  # values so far, aliases expanded: checked as they come, not per collection

    def compose_node(self, parent: Any, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            return self._compose_alias(parent, index)
        mark = self.peek_event().start_mark
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            raise _limit(f"collections nested deeper than {MAX_YAML_DEPTH} levels", mark)
        self._count(1, mark)
        try:
            node = Composer.compose_node(self, parent, index)
        finally:
            self._depth -= 1
        node.weight = 1 + sum(_weight(c) for c in _node_children(node))  # its size with aliases expanded
        return node

    def _count(self, n: int, mark: Any) -> None:
        self._total += n
        if self._total > MAX_YAML_NODES:
            raise _limit(f"more than {MAX_YAML_NODES:,} values once aliases are expanded", mark)

    def _compose_alias(self, parent: Any, index: Any) -> yaml.Node:
        mark = self.peek_event().start_mark
        self._aliases += 1
        if self._aliases > MAX_YAML_ALIASES:
            raise _limit(f"more than {MAX_YAML_ALIASES} aliases (*name)", mark)
        node = Composer.compose_node(self, parent, index)
        if getattr(node, "weight", None) is None:  # the anchor is still being composed
            raise yaml.composer.ComposerError(None, None, "an alias inside its own anchor (a recursive structure)",
                                              mark)
        self._count(node.weight, mark)
        return node


if CParser is not None:

    class _Loader(CParser, _LimitedComposer, SafeConstructor, Resolver):
        """libyaml's scanner and parser (C, ~4x faster) with our composer and constructors."""

        def __init__(self, stream: str):
            CParser.__init__(self, stream)
            _LimitedComposer.__init__(self)
            SafeConstructor.__init__(self)
            Resolver.__init__(self)

        # CParser composes in C by default: use the Python composer (and so the limits)
        get_single_node = Composer.get_single_node
        compose_document = Composer.compose_document
        check_node = Composer.check_node
        get_node = Composer.get_node
        compose_node = _LimitedComposer.compose_node

else:  # pragma: no cover - PyYAML without libyaml

    class _Loader(Reader, Scanner, Parser, _LimitedComposer, SafeConstructor, Resolver):
        def __init__(self, stream: str):
            Reader.__init__(self, stream)
            Scanner.__init__(self)
            Parser.__init__(self)
            _LimitedComposer.__init__(self)
            SafeConstructor.__init__(self)
            Resolver.__init__(self)


class _LimitError(yaml.composer.ComposerError):
    """A limit of the loader exceeded (well-formed YAML, refused for its size)."""


def _limit(what: str, mark: Any) -> yaml.YAMLError:
    return _LimitError(None, None, f"config too large or too deep: {what} (the limit)", mark)


def _node_children(node: yaml.Node) -> list:
    if isinstance(node, yaml.SequenceNode):
        return node.value
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def _weight(node: yaml.Node) -> int:
    w = getattr(node, "weight", None)
    if w is None:
        raise yaml.composer.ComposerError(None, None, "an alias inside its own anchor (a recursive structure)",
                                          node.start_mark)
    return w


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> LineDict:
    loader.flatten_mapping(node)
    d = LineDict()
    d.line = node.start_mark.line + 1
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if isinstance(key, (list, dict, set)):
            raise yaml.constructor.ConstructorError(
                None, None, f"a key must be a name or a number, found {type_word(key)}", key_node.start_mark)
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


def type_word(value: Any) -> str:
    """How a YAML value is named in messages (never an internal class name such as LineList)."""
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "text"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, (list, tuple)):
        return "a list"
    if value is None:
        return "nothing (null)"
    return "a value of an unsupported type"


def load_yaml(path: Path) -> Any:
    """Parse YAML keeping line numbers; malformed YAML is a ConfigError with its line."""
    text = _config_text(path)
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - our SafeLoader subclass
    except yaml.reader.ReaderError as e:  # a control character: no problem_mark, a character position
        line = text.count("\n", 0, e.position) + 1
        code = ord(e.character) if isinstance(e.character, str) else int(e.character)
        raise ConfigError.one(str(path), line, (), f"malformed YAML: control character U+{code:04X} "
                                                   "is not allowed") from None
    except _LimitError as e:
        raise ConfigError.one(str(path), e.problem_mark.line + 1, (), e.problem) from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(e, "problem", None) or str(e)
        raise ConfigError.one(str(path), line, (), f"malformed YAML: {clip(problem)}") from None
    except RecursionError:  # a safety net below our depth limit (a deep stack in the caller)
        raise ConfigError.one(str(path), None, (), "config too deep to parse") from None


def _config_text(path: Path) -> str:
    """The config's text: a regular file of at most MAX_CONFIG_BYTES, in UTF-8."""
    try:
        if path.is_dir():
            raise ConfigError.one(str(path), None, (), "is a folder, not a config file")
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError.one(str(path), None, (), f"config file too large ({size:,} bytes; the limit is "
                                                       f"{MAX_CONFIG_BYTES:,})")
        data = path.read_bytes()
    except OSError as e:
        raise ConfigError.one(str(path), None, (), f"cannot read config: {e.strerror or e}") from None
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise ConfigError.one(str(path), 1, (), "config is UTF-16 text; save it as UTF-8")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        col = e.start - (data.rfind(b"\n", 0, e.start) + 1) + 1
        raise ConfigError.one(str(path), line, (), f"config is not UTF-8 text: byte 0x{data[e.start]:02x} at "
                                                   f"column {col} (byte offset {e.start}); save it as UTF-8") from None


def clip(text: str, limit: int = 200) -> str:
    """One line of at most ``limit`` characters (a message quoting a 50 MB input stays short)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit] + f"... ({len(text):,} characters)"


def stage_path(job: Job, params: Any) -> tuple:
    """YAML path of a stage's parameters: ``stages[i].<name>``, or ``jobs[k].stages[i].<name>``
    when the job's own entry under ``jobs:`` lists the stages."""
    i, name = next((n, s) for n, (s, q) in enumerate(job.stages) if q is params)
    raw = job.raw if isinstance(job.raw, dict) else {}
    entry = raw["jobs"][job.index[0]] if raw.get("jobs") and job.index else None
    base = ("jobs", job.index[0], "stages") if isinstance(entry, dict) and "stages" in entry else ("stages",)
    return base + (i, name)


def input_error_path(job: Job, params: Any, e: InputError) -> tuple:
    """YAML path of an InputError raised while a stage ran: relative to the model node that
    raised it (a node that solves lazily, e.g. ``hfrep``), else to the stage's parameters."""
    return (tuple(_parse_path(e.node)) if e.node else stage_path(job, params)) + e.path


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
        return f"unknown key {clip(key, 60)!r}{alts}"
    if kind == "too_long" and ctx.get("field_type") == "Tuple":
        return _items_message(ctx["max_length"], ctx["actual_length"])
    if kind == "too_long":
        return f"must have at most {ctx['max_length']} items, got {ctx['actual_length']}"
    if kind == "int_parsing_size":
        return "must be a smaller number (an integer of at most 19 digits)"
    ops = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if isinstance(err.get("input"), bool) and (kind in ops or kind.startswith(("int_", "float_"))):
        return "must be a number, not true/false"  # pydantic read it as 1 or 0 and then refused it
    if kind in ops:
        bound = next(iter(ctx.values()))
        return f"must be {ops[kind]} {bound}"
    msg = err["msg"]
    msg = msg.removeprefix("Value error, ").removeprefix("Assertion failed, ")
    return clip(msg.replace("Input should be", "must be"), 300)


def _items_message(want: int, got: int) -> str:
    if want == 3:
        return f"must be three numbers [x, y, z], got {got}"
    return f"must be a list of {want} items, got {got}"


def _short_tuples(errors: list[dict]) -> dict[tuple, tuple[int, int]]:
    """Fixed-length lists given too few items: pydantic reports each missing index as a
    missing key (``max[2]: missing required key``); map the list's location to (want, got)."""
    out: dict[tuple, tuple[int, int]] = {}
    for err in errors:
        loc = err["loc"]
        if err["type"] == "missing" and loc and isinstance(loc[-1], int) and isinstance(err.get("input"), list):
            want = max(loc[-1] + 1, out.get(loc[:-1], (0, 0))[0])
            out[loc[:-1]] = (want, len(err["input"]))
    return out


def _clean_loc(loc: tuple) -> tuple:
    """Drop pydantic's union-member tags (e.g. 'tuple[float, float, float]') from a location."""
    return tuple(p for p in loc if isinstance(p, int) or ("[" not in p and p not in _TYPE_TAGS))


_TYPE_TAGS = {"float", "int", "str", "bool", "function-after", "literal", "list", "dict"}


def validation_problems(exc: ValidationError, file: str, root: Any, base: tuple, model: type[BaseModel],
                        strip: str | None = None) -> list:
    allowed = sorted({(f.alias or n) for n, f in model.model_fields.items()})
    seen, problems = set(), []
    errors = exc.errors()
    short = _short_tuples(errors)
    for err in errors:
        raw_loc = err["loc"][:-1] if err["loc"] and err["loc"][:-1] in short else err["loc"]
        loc = _clean_loc(raw_loc)
        if strip and loc and loc[0] == strip:
            loc = loc[1:]
        path = base + loc
        msg = _items_message(*short[raw_loc]) if raw_loc in short else _message(err, allowed)
        if (path, msg) in seen or any(p[2] == path for p in problems):
            continue  # one message per path (unions produce one error per member)
        seen.add((path, msg))
        problems.append((file, line_of(root, path), path, msg))
    return problems


def coerced_booleans(raw: Any, value: Any, path: tuple = ()) -> list[tuple]:
    """Paths where YAML ``true``/``false`` was accepted as a number (pydantic's lax mode reads
    true as 1 and 1.0): a boolean is not a number anywhere in a config. ``raw`` is the YAML
    value, ``value`` what validation made of it."""
    if isinstance(raw, bool):
        return [] if isinstance(value, bool) or value is raw else [path]
    if isinstance(raw, dict) and isinstance(value, BaseModel):
        keys = {(f.alias or n): n for n, f in type(value).model_fields.items()}
        return [p for k, v in raw.items() if k in keys
                for p in coerced_booleans(v, getattr(value, keys[k]), path + (k,))]
    if isinstance(raw, dict) and isinstance(value, dict):
        return [p for k, v in raw.items() if k in value for p in coerced_booleans(v, value[k], path + (k,))]
    if isinstance(raw, list) and isinstance(value, (list, tuple)) and len(raw) == len(value):
        return [p for i, (r, v) in enumerate(zip(raw, value, strict=True)) for p in coerced_booleans(r, v, path + (i,))]
    return []


def boolean_problems(raw: Any, value: Any, file: str, root: Any, base: tuple) -> ConfigError | None:
    paths = coerced_booleans(raw, value)
    if not paths:
        return None
    return ConfigError([(file, line_of(root, base + p), base + p, "must be a number, not true/false") for p in paths])


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


def _listing(names: list[str]) -> str:
    """Names for a message, on indented lines of their own below the problem's line: an error
    line stays short (file, line, YAML path and the problem) however many node types there are."""
    return "\n" + textwrap.fill(", ".join(names), 96, initial_indent="  ", subsequent_indent="  ")


def build_node(raw: Any, path: tuple, ctx: _Ctx) -> Node:
    """Build a node from ``{type: params}`` (plus optional ``rfunc``) at YAML ``path``."""
    kinds = sorted(REGISTRY)
    if not isinstance(raw, dict) or not raw:
        raise ctx.fail(path, f"a node is a mapping with one key, its type, one of:{_listing(kinds)}")
    type_keys = [k for k in raw if k not in NODE_SIBLINGS]
    if len(type_keys) != 1:
        raise ctx.fail(path, f"a node has exactly one type key, found {len(type_keys)}: {type_keys}")
    kind = type_keys[0]
    if kind not in REGISTRY:
        hint = difflib.get_close_matches(str(kind), kinds, n=1)
        alts = f" (did you mean {hint[0]!r}?)" if hint else f"; the node types are:{_listing(kinds)}"
        raise ctx.fail(path + (kind,), f"unknown node type {kind!r}{alts}")
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
    bad = None if strip else boolean_problems(body, params, ctx.file, ctx.root, here)
    if bad:
        raise bad
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
        raise ctx.fail(path, f"parameters of {cls.kind} must be a mapping, got {type_word(body)}")
    out = dict(body)
    if "path" in out and isinstance(out["path"], str):  # file inputs are relative to the config
        p = Path(out["path"]).expanduser()
        out["path"] = str(p if p.is_absolute() else (ctx.base_dir / p))
    return out, None


def _build_children(value: Any, path: tuple, ctx: _Ctx):
    if isinstance(value, list):
        if len(value) > MAX_CHILDREN:
            raise ctx.fail(path, f"more than {MAX_CHILDREN:,} children in one node (the limit); "
                                 "split the list into nested unions")
        return [build_node(item, path + (i,), ctx) for i, item in enumerate(value)]
    return build_node(value, path, ctx)


# --- top level ---------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DomainConfig(_Strict):
    bounds: tuple[Vec3, Vec3]
    voxel_size: Real | None = Field(default=None, gt=0)
    #: voxels along the longest side; OpenVDB's index coordinates are 32-bit
    resolution: int | None = Field(default=None, gt=0, le=MAX_INDEX)

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

    count: int = Field(ge=1)
    t: tuple[Real, Real] = (0.0, 1.0)

    @field_validator("count")
    @classmethod
    def _at_most(cls, v: int) -> int:
        if v > MAX_FRAMES:
            raise ValueError(f"at most {MAX_FRAMES:,} frames per config (the limit), got {v:,}; "
                             "split the sweep over several configs")
        return v


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
    memory_estimate: dict = field(default_factory=dict)  # stage -> estimated peak bytes (_check_memory)


def _check_top_keys(root: dict, file: str) -> None:
    """Unknown top-level keys are refused before any validation: a mistyped key over a huge
    value costs nothing then."""
    allowed = sorted({(f.alias or n) for n, f in TopConfig.model_fields.items()})
    unknown = [k for k in root if k not in allowed]
    if unknown:
        key = unknown[0]
        msg = _message({"type": "extra_forbidden", "loc": (str(key),)}, allowed)
        raise ConfigError.one(file, line_of(root, (key,)), (clip(str(key), 60),), msg)


def load_jobs(path: str | Path, select: str | None = None, overrides: list[str] | tuple = ()) -> list[Job]:
    """Load and validate a config file into its jobs (one, a ``jobs:`` list, times ``frames``).

    ``select`` builds only the job of that name (how a worker finds its job again);
    ``overrides``: ``KEY.PATH=VALUE`` strings (``frepvdb run --set``) applied before validation,
    problems they cause named by the option (:func:`apply_overrides`)."""
    path = Path(path)
    root = load_yaml(path)
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    if not overrides:
        return jobs_from_root(root, str(path), path.resolve().parent, sha, path.stem, select)
    applied = apply_overrides(root, overrides, str(path))
    sha = hashlib.sha256((sha + json.dumps(list(overrides))).encode()).hexdigest()
    try:
        return jobs_from_root(root, str(path), path.resolve().parent, sha, path.stem, select)
    except ConfigError as e:
        raise ConfigError([_blame_override(p, applied) for p in e.problems]) from None


def jobs_from_root(root: Any, file: str, base_dir: Path, sha: str, stem: str, select: str | None = None) -> list[Job]:
    """The jobs of a parsed config (a YAML file's or a Python dict's): ``file`` names it in
    messages, ``base_dir`` anchors relative input paths, ``stem`` names a job without ``name:``."""
    if not isinstance(root, dict):
        raise ConfigError.one(file, getattr(root, "line", 1), (), "a config is a mapping (name, domain, model, stages)")
    _check_top_keys(root, file)
    try:
        top = TopConfig.model_validate(root)
    except ValidationError as e:
        raise ConfigError(validation_problems(e, file, root, (), TopConfig)) from None
    bad = boolean_problems(root, top, file, root, ())
    if bad:
        raise bad
    ctx = _Ctx(file, root, base_dir)
    if top.jobs is None and not top.name and job_name_problem(stem):
        raise ConfigError.one(file, None, (), f"the job is named after the file ({Path(file).name!r}), which is not "
                              f"a valid job name: {job_name_problem(stem)}; add a `name:` key")
    entries = [(None, top.name or stem, None, top.model, None, None)] if top.jobs is None else [
        (i, e.name, e.domain, e.model, e.stages, e.t) for i, e in enumerate(top.jobs)]
    jobs = []
    for i, name, dom, model_raw, stages_raw, t in entries:
        base = () if i is None else ("jobs", i)
        jobs.extend(_entry_jobs(ctx, top, sha, base, i or 0, name, dom, model_raw, stages_raw, t, select))
    dup = sorted(n for n, k in Counter(j.name for j in jobs).items() if k > 1)
    if dup:
        raise ctx.fail(("jobs",), f"job names must be unique (outputs go to <out>/<name>/): {dup}")
    return jobs


def load_job(path: str | Path) -> Job:
    """The single job of a config file (a ``jobs:`` or ``frames:`` config is an error here)."""
    jobs = load_jobs(path)
    if len(jobs) != 1:
        raise ConfigError.one(str(path), None, (), f"expected one job, the config makes {len(jobs)}")
    return jobs[0]


# --- factories for the Python API and command-line overrides ----------------------------------


def build_model(raw: Any, domain: Domain | None = None, t: float = 0.0, file: str = "<python>",
                base_dir: Path | None = None) -> Node:
    """The node tree of a model given as YAML-shaped data (``{"sphere": {"radius": 1}}``), built by
    the loader's own :func:`build_node`: the Python API (package ``frepvdb``) and configs make the
    same nodes. ``domain`` sets the magnitude control of r0/sardf set operations as a job's does."""
    ctx = _Ctx(file, {"model": raw}, Path.cwd() if base_dir is None else base_dir, domain, float(t))
    return build_node(raw, ("model",), ctx)


def make_domain(bounds: Any, voxel_size: float | None = None, resolution: int | None = None,
                file: str = "<python>") -> Domain:
    """A validated :class:`Domain` (the ``domain:`` section's rules and messages)."""
    raw = {"bounds": bounds, "voxel_size": voxel_size, "resolution": resolution}
    raw = {k: v for k, v in raw.items() if v is not None}
    try:
        d = DomainConfig.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(validation_problems(e, file, raw, ("domain",), DomainConfig)) from None
    return _domain(d, _Ctx(file, {"domain": raw}, Path.cwd()))


#: keys of ``domain`` that exclude each other: overriding one drops the other
_EXCLUSIVE = {"resolution": "voxel_size", "voxel_size": "resolution"}


def parse_override(text: str) -> tuple[tuple, Any]:
    """``stages[0].voxelise.band=4`` -> (('stages', 0, 'voxelise', 'band'), 4); the value is YAML."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise ValueError("expected KEY.PATH=VALUE")
    parts: list = []
    for piece in key.strip().replace("[", ".[").split("."):
        if piece.startswith("["):
            if not piece.endswith("]") or not piece[1:-1].isdigit():
                raise ValueError(f"bad index {piece!r} (an index is [0], [1], ...)")
            parts.append(int(piece[1:-1]))
        elif piece:
            parts.append(piece)
        else:
            raise ValueError("empty key in the path")
    try:
        val = yaml.safe_load(value) if value.strip() else None
    except yaml.YAMLError as e:
        raise ValueError(f"value is not valid YAML: {clip(getattr(e, 'problem', e), 80)}") from None
    return tuple(parts), val


def apply_overrides(root: Any, overrides: list[str] | tuple, file: str) -> list[tuple[tuple, str]]:
    """Set each ``KEY.PATH=VALUE`` in the parsed config (missing mappings on the way are made);
    returns (path, option text) per override for :func:`_blame_override`."""
    applied = []
    for text in overrides:
        where = f"--set {clip(text, 80)}"
        try:
            path, value = parse_override(text)
            _set_at(root, path, value)
        except ValueError as e:
            raise ConfigError.one(where, None, (), str(e)) from None
        applied.append((path, where))
    return applied


def _set_at(root: Any, path: tuple, value: Any) -> None:
    node = root
    for i, part in enumerate(path):
        last = i == len(path) - 1
        shown = format_path(path[:i + 1])
        if isinstance(part, int):
            if not isinstance(node, list):
                raise ValueError(f"{format_path(path[:i]) or 'the config'} is not a list")
            if part >= len(node):
                raise ValueError(f"{shown}: index out of range (the list has {len(node)} items)")
        elif not isinstance(node, dict):
            raise ValueError(f"{format_path(path[:i]) or 'the config'} is {type_word(node)}, not a mapping")
        if last:
            if isinstance(node, dict) and path[:-1] == ("domain",) and _EXCLUSIVE.get(part) in node:
                del node[_EXCLUSIVE[part]]  # resolution replaces voxel_size and vice versa
            node[part] = value
            return
        child = node[part] if (isinstance(part, int) or part in node) else None
        if child is None:  # ``voxelise:`` with no body, or a key not there yet
            child = {}
            node[part] = child
        node = child


def write_config(root: Any, base_dir: Path, out_root: Path, stem: str) -> Path:
    """The effective config (a dict from Python, or a file with ``--set`` overrides applied) as a
    YAML file under ``<out>/.frepvdb-configs/`` that runs like the original: input paths made
    absolute (they were relative to ``base_dir``) and the job keeps its name. Workers and bricks
    find their job again by config file (pipeline.job.refs.JobRef), so the run goes through it."""
    data = _to_plain(root)
    if data.get("jobs") is None and not data.get("name"):
        data["name"] = stem
    for model in [data.get("model")] + [j.get("model") for j in data.get("jobs") or [] if isinstance(j, dict)]:
        _absolute_paths(model, base_dir)
    text = yaml.safe_dump(data, sort_keys=False)
    folder = Path(out_root) / ".frepvdb-configs"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{stem}-{hashlib.sha256(text.encode()).hexdigest()[:12]}.yaml"
    if not path.exists():
        with atomic_path(path) as tmp:
            tmp.write_text(text)
    return path


def _absolute_paths(node: Any, base_dir: Path) -> None:
    """Every ``path:`` of a model's nodes relative to ``base_dir`` made absolute, in place."""
    if isinstance(node, list):
        for item in node:
            _absolute_paths(item, base_dir)
    elif isinstance(node, dict):
        for key, value in node.items():
            if key == "path" and isinstance(value, str):
                p = Path(value).expanduser()
                node[key] = str(p if p.is_absolute() else (base_dir / p).resolve())
            else:
                _absolute_paths(value, base_dir)


def _blame_override(problem: tuple, applied: list[tuple[tuple, str]]) -> tuple:
    """A problem at (or above, or below) an overridden path is reported as the option's."""
    file, line, path, msg = problem
    for opt_path, where in reversed(applied):
        n = min(len(path), len(opt_path))
        if tuple(path[:n]) == tuple(opt_path[:n]) and n > 0:
            deeper = len(path) > len(opt_path)
            return (where, None, (), f"{format_path(path)}: {msg}" if deeper else msg)
    return problem


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
    # in floating point, before any conversion to integers (a huge quotient would wrap around)
    reach = max(abs(c) for c in (*lo, *hi)) / h if h > 0 else math.inf
    if not reach < MAX_INDEX:
        key = "voxel_size" if d.voxel_size is not None else "resolution"
        raise ctx.fail(base + ("domain", key), f"index coordinates exceed OpenVDB's 32-bit range (voxel size {h:g}, "
                                               f"bounds reach {reach:.3g} voxels from the origin; the limit is "
                                               f"{MAX_INDEX:,})")
    return Domain((tuple(lo), tuple(hi)), float(h))


def _stages(raw: list, ctx: _Ctx, base: tuple = ("stages",)) -> list[tuple[str, Any]]:
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
        bad = boolean_problems(body or {}, params, ctx.file, ctx.root, path + (name,))
        if bad:
            raise bad
        out.append((name, params))
    made: set[type] = set()
    for i, (n, _) in enumerate(out):
        missing = [r for r in getattr(STAGES[n], "REQUIRES", ()) if r not in made]
        if missing:
            raise ctx.fail(base + (i, n), f"needs the {', '.join(_producers(missing))} stage before it")
        made.update(getattr(STAGES[n], "PRODUCES", ()))
    _check_grid_names(out, ctx, base)
    return out


def _producers(kinds: list[type]) -> list[str]:
    """The stages that make results of these types without needing them first (voxelise)."""
    return [n for n, st in STAGES.items() for k in kinds
            if k in getattr(st, "PRODUCES", ()) and k not in getattr(st, "REQUIRES", ())]


def _check_grid_names(stages: list[tuple[str, Any]], ctx: _Ctx, base: tuple) -> None:
    """Grid names that export refers to must be made by a stage before it (else the run would
    fail after the expensive stages, or silently write less)."""
    made: list[str] = []
    for i, (name, params) in enumerate(stages):
        if name == "export":
            written = made if params.grids is None else [g for g in made if g in params.grids]
            for key, names, known in (("grids", params.grids, made), ("half_float", params.half_float, written)):
                if not isinstance(names, list):
                    continue
                for j, g in enumerate(names):
                    if g not in known:
                        why = (f"no stage before export makes a grid named {clip(g, 60)!r}" if g not in made
                               else f"grid {g!r} is not in export.grids, so it is not written")
                        raise ctx.fail(base + (i, name, key, j), f"{why} (grids here: {', '.join(known) or 'none'})")
        made.extend(STAGES[name].grids(params))


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
    names the deepest node where it first appears (e.g. a formula dividing by zero). Not for a
    tree with a node that solves on first use (``hfrep``): validating must not run its solve;
    the stages find such values as they evaluate (NonFiniteField, located the same way)."""
    if any(node.solves_on_first_use for node in job.model.walk()):
        return
    err = locate_nonfinite(job, _check_points(job.domain.bounds))
    if err is not None:
        raise err


@functools.lru_cache(maxsize=16)
def _check_points(bounds: tuple) -> np.ndarray:
    """17^3 lattice points of the domain (cached: every frame of a sweep shares its domain)."""
    lo, hi = (np.asarray(b, float) for b in bounds)
    axes = [np.linspace(lo[i], hi[i], 17) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    pts.flags.writeable = False
    return pts


def locate_nonfinite(job: Job, pts: np.ndarray) -> ConfigError | None:
    """ConfigError naming the deepest model node that is NaN or infinite at one of ``pts``."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    finite: dict[int, bool] = {}

    def is_finite(node) -> bool:
        # nodes finite by construction or from finite children are not evaluated: a mesh's
        # BSP-field takes its whole tree per point (11 s for 17^3 points, 1.3M faces)
        if id(node) not in finite:
            inferred = node.finite_by_construction or (
                node.finite_from_children and all(is_finite(c) for c in node.children()))
            finite[id(node)] = inferred or bool(np.all(np.isfinite(node.evaluate(pts, job.t))))
        return finite[id(node)]

    # the last in walk order: the deepest offender is the most useful one
    bad_node = next((n for n in reversed(list(job.model.walk())) if getattr(n, "where", "") and not is_finite(n)),
                    None)
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


def _check_memory(job: Job, ctx: _Ctx, base: tuple = ()) -> None:
    """Refuse a domain whose grids would not fit in this machine's memory (estimates): the
    stage that makes the narrow band estimates it (after the memory of the estimate itself),
    then every stage estimates its own peak from it (``estimate_bytes``, stages.base; kept in
    ``job.memory_estimate``, which the runner writes into the manifest); the largest must fit."""
    maker = next(((n, p) for n, p in job.stages if n in _producers([FrepBand])), None)
    if maker is None or job.domain.dims.max() < 512:
        return  # small domains always fit: 512^3 voxels of band would be ~3 GiB
    avail = _available_memory()
    stage, params = STAGES[maker[0]], maker[1]
    need, what = stage.enumeration_bytes(job, params)
    if need > avail:
        _refuse_memory(job, ctx, base, need, what, avail)
    band = stage.estimate_band(job, params)
    est: dict[str, tuple[float, str]] = {}
    for name, p in job.stages:  # every stage holds the band grids, some more (stages.base)
        need = STAGES[name].estimate_bytes(job, p, band)
        est[name] = max(est.get(name, need), need, key=lambda x: x[0])
    job.memory_estimate = {n: int(v) for n, (v, _) in est.items()}
    top = max(est, key=lambda n: est[n][0])
    if est[top][0] > avail:
        _refuse_memory(job, ctx, base, est[top][0], est[top][1], avail)


def _refuse_memory(job: Job, ctx: _Ctx, base: tuple, need: float, what: str, avail: float) -> None:
    local = _at(job.raw, base + ("domain",))
    raw_dom = local or job.raw.get("domain", {})
    key = "voxel_size" if "voxel_size" in raw_dom else "resolution"
    where = (base if local else ()) + ("domain", key)
    raise ctx.fail(where, f"this domain needs an estimated {need / 2**30:.3g} GiB for {what}; "
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
    """Free memory, or the process's address-space limit (ulimit -v) when that is smaller."""
    import resource

    try:
        import psutil

        avail = int(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover
        with open("/proc/meminfo") as f:
            info = dict(line.split(":", 1) for line in f)
        avail = int(info["MemAvailable"].split()[0]) * 1024
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return avail if soft == resource.RLIM_INFINITY else min(avail, soft)

