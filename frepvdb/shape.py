"""``Shape``: a model tree held as the YAML data a config would give, built into nodes by the
config loader itself (:func:`pipeline.job.config.build_model`, which calls ``build_node``).

One representation, two front ends: a shape made in Python and the same model written in YAML
are the same data, so they build the same node objects, the same compiled tape
(:func:`pipeline.model.tape.compile_model`) and the same grids; :meth:`Shape.to_yaml` prints that data.

Sign convention (SPEC): f > 0 inside, f = 0 on the surface, f < 0 outside (fogleman/sdf and
libfive use the opposite sign).
"""

from __future__ import annotations

import math
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from pipeline.job.config import ConfigError, Domain, build_model, validation_problems
from pipeline.model.expr import FormulaError, parse_formula
from pipeline.model.tape import compile_model, gradient_with
from pipeline.oracles import REGISTRY, Node

SOURCE = "<python>"  # how a shape made in code is named in messages (a config names its file)


class Shape:
    """An FRep model: ``{kind: params}`` with child shapes, as in a config's ``model:``.

    Combine with ``|`` (union), ``&`` (intersection), ``-`` (difference), ``~`` (complement);
    transform by chaining (``.translate([1, 0, 0]).rotate(30, "z")``). Every node type of the
    config is a function of :mod:`frepvdb` and, when it has one child ``of``, a method here.
    """

    __slots__ = ("kind", "params", "_nodes")

    def __init__(self, kind: str, params: dict[str, Any]):
        self.kind = kind
        self.params = params  # YAML-shaped values; child shapes stay Shape objects
        self._nodes: dict[tuple, Node] = {}

    # --- the one representation -------------------------------------------------------------
    def to_dict(self) -> dict:
        """The model as plain YAML data (``{"union": {"of": [...], "rfunc": "r0"}}``)."""
        return {self.kind: {k: _plain(v) for k, v in self.params.items()}}

    def to_yaml(self) -> str:
        """The model as YAML text: put it under ``model:`` in a config to get this model back."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=100)

    def node(self, domain: Domain | None = None, t: float = 0.0) -> Node:
        """The node tree, built by the config loader (cached per domain and time). ``domain``
        sets the magnitude control of r0/sardf set operations as a job's domain does."""
        key = (None if domain is None else (domain.bounds, domain.voxel_size), float(t))
        if key not in self._nodes:
            self._nodes[key] = build_model(self.to_dict(), domain, t, file=SOURCE)
        return self._nodes[key]

    # --- using it ---------------------------------------------------------------------------
    def evaluate(self, points: Any, t: float = 0.0) -> np.ndarray:
        """Field values at points: an (N, 3) array gives (N,), one point (3,) gives a float."""
        p = np.asarray(points, dtype=np.float64)
        vals = self.node(t=t).evaluate(p.reshape(-1, 3), t)
        return float(vals[0]) if p.ndim == 1 else vals.reshape(p.shape[:-1])

    __call__ = evaluate

    def bound(self, lo: Any, hi: Any, t: float = 0.0) -> tuple:
        """Rigorous (lower, upper) bounds of the field over the box lo..hi (revised affine
        arithmetic, pipeline.field.affine); (B, 3) corners give arrays, one box (3,) gives floats."""
        lo_a, hi_a = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        flo, fhi = self.node(t=t).bound(lo_a.reshape(-1, 3), hi_a.reshape(-1, 3), t)
        if lo_a.ndim == 1:
            return float(flo[0]), float(fhi[0])
        return flo, fhi

    def gradient(self, points: Any, t: float = 0.0) -> np.ndarray:
        """Exact gradients of the field at points, forward mode over the compiled tape
        (pipeline.model.tape.gradient_with; one-sided on creases): (N, 3) gives (N, 3), one point (3,)
        gives (3,). A model the tape cannot hold (grid, hfrep, component, r0/sardf or ADF meshes)
        raises TypeError."""
        p = np.asarray(points, dtype=np.float64)
        tape = compile_model(self.node(t=t), t)
        if tape is None:
            raise TypeError("this model has a node the compiled tape cannot hold (grid, hfrep, component, or a "
                            "mesh other than a min_max BSP-field): no exact gradient")
        g = gradient_with(tape, p.reshape(-1, 3))[1]
        return g[0] if p.ndim == 1 else g.reshape(p.shape)

    def children(self) -> list[Shape]:
        out: list[Shape] = []
        for v in self.params.values():
            out.extend(c for c in (v if isinstance(v, list) else [v]) if isinstance(c, Shape))
        return out

    # --- operators (fogleman/sdf style) -----------------------------------------------------
    def __or__(self, other: Shape) -> Shape:
        return make("union", (self, other), {})

    def __and__(self, other: Shape) -> Shape:
        return make("intersection", (self, other), {})

    def __sub__(self, other: Shape) -> Shape:
        return make("difference", (self, other), {})

    def __invert__(self) -> Shape:
        return make("complement", (self,), {})

    def __repr__(self) -> str:
        text = yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=True, width=10**9).strip()
        return f"Shape({text if len(text) <= 200 else text[:200] + ' ...'})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Shape) and self.to_dict() == other.to_dict()

    __hash__ = None  # mutable-looking value semantics: shapes compare by their data


def _plain(v: Any) -> Any:
    """YAML-safe data: shapes become their mappings, arrays and tuples lists, NumPy scalars floats."""
    if isinstance(v, Shape):
        return v.to_dict()
    if isinstance(v, PurePath):
        return str(v)
    if isinstance(v, np.ndarray):
        return [_plain(x) for x in v.tolist()]
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    return v


#: positional parameters of each node function, after any child shapes (the rest are keywords)
POSITIONAL: dict[str, tuple[str, ...]] = {
    "sphere": ("radius", "center"),
    "box": ("min", "max"),
    "cylinder": ("radius", "center"),
    "cone": ("radius", "height", "center"),
    "torus": ("major", "minor", "center"),
    "ellipsoid": ("radii", "center"),
    "superellipsoid": ("radii", "exponents", "center"),
    "halfspace": ("normal", "offset"),
    "blobby": ("blobs", "threshold"),
    "expr": ("formula",),
    "mesh": ("path",),
    "grid": ("path",),
    "translate": ("by",),
    "rotate": ("angle", "axis", "center"),
    "scale": ("by", "center"),
    "twist": ("rate", "axis", "center"),
    "taper": ("range", "scale"),
    "bend": ("rate", "plane"),
    "offset": ("distance",),
    "component": ("index",),
    "morph": ("t",),
    "shell": ("thickness", "side"),
    "tpms": ("type", "cell", "thickness"),
    "lattice": ("struts", "radius"),
}


def make(kind: str, args: tuple, kwargs: dict[str, Any]) -> Shape:
    """The shape of node ``kind`` from positional children and parameters, validated now with
    the config's messages (``<python> sphere.radius: must be > 0``)."""
    cls = REGISTRY[kind]
    fields = cls.Params.model_fields
    keys = {n: (f.alias or n) for n, f in fields.items()}
    kids = [a for a in args if isinstance(a, Shape)]
    rest = [a for a in args if not isinstance(a, Shape)]
    if any(isinstance(a, Shape) for a in args[len(kids):]):
        raise TypeError(f"{kind}(): child shapes come first, then the parameters")
    params: dict[str, Any] = {}
    _place_children(kind, cls, kids, params)
    names = POSITIONAL.get(kind, ())
    if len(rest) > len(names):
        raise TypeError(f"{kind}() takes {len(names)} positional parameter(s) ({', '.join(names) or 'none'}) "
                        f"after its child shapes, got {len(rest)}")
    params.update(zip(names, rest, strict=False))
    for k, v in kwargs.items():
        key = keys.get(k, keys.get(k.rstrip("_"), k))  # from_ -> from (a Python keyword)
        if key in params:
            raise TypeError(f"{kind}() got {key!r} twice")
        params[key] = v
    params = {k: v for k, v in params.items() if v is not None}  # None: the default
    _check(kind, cls, params)
    return Shape(kind, params)


def _place_children(kind: str, cls: type[Node], kids: list[Shape], params: dict) -> None:
    if not kids:
        return
    if cls.list_field:
        params[cls.list_field] = list(kids)
        return
    slots = [cls.Params.model_fields[n].alias or n for n in cls.child_fields]
    if len(kids) > len(slots):
        raise TypeError(f"{kind}() takes {len(slots)} child shape(s), got {len(kids)}")
    params.update(zip(slots, kids, strict=False))


def _check(kind: str, cls: type[Node], params: dict) -> None:
    """Validate the node's own parameters (children are built later, by the loader)."""
    body = {k: (v if isinstance(v, Shape) or (isinstance(v, list) and v and isinstance(v[0], Shape))
                else _plain(v)) for k, v in params.items()}
    try:
        p = cls.Params.model_validate(body)
    except ValidationError as e:
        raise ConfigError(validation_problems(e, SOURCE, {}, (kind,), cls.Params)) from None
    formula = getattr(p, "formula", None)
    if kind == "expr" and isinstance(formula, str):
        try:
            parse_formula(formula)
        except FormulaError as e:
            raise ConfigError.one(SOURCE, None, (kind, "formula"), f"bad formula: {e}") from None
    path = params.get("path")
    if isinstance(path, (str, Path)):  # input files are named as they were given, made absolute
        params["path"] = str(Path(path).expanduser().resolve())
    for k, v in params.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ConfigError.one(SOURCE, None, (kind, k), "must be a finite number")
