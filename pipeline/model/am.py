"""Additive-manufacturing nodes: ``shell`` (a wall of given thickness along a surface), ``tpms``
(sheet gyroid / Schwarz P / diamond lattices with cell size and wall thickness that may vary in
space, graded by a formula of x, y, z and the field ``d`` of another node: hfrep seed section 7)
and ``lattice`` (a union of capsule struts, listed or in a cubic / BCC / octet pattern).

Every formula is written once with :mod:`pipeline.model.ops`, so values, affine bounds and the
compiled tape (pipeline.model.tape) all come from it (pipeline.model.base).
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from pipeline.model import ops
from pipeline.model.base import Node, Params, Real, Vec3, register
from pipeline.model.expr import FormulaError, parse_formula
from pipeline.model.operations import balanced
from pipeline.util.errors import InputError


@register("shell")
class Shell(Node):
    """A wall of ``thickness`` along the surface of ``of``: inside it (0 <= f <= T: min(f, T - f)),
    outside it (-T <= f <= 0: min(f + T, -f)) or centred on it (T/2 - |f|). A distance field in,
    a distance field out (the wall's two faces are offsets of the surface)."""

    class Params(Params):
        of: Any
        thickness: Real = Field(gt=0)
        side: Literal["inside", "outside", "both"] = "inside"

    child_fields = ("of",)

    def field(self, x, y, z, t):
        p = self.params
        f = p.of.field(x, y, z, t)
        if p.side == "inside":
            return ops.minimum(f, p.thickness - f)
        if p.side == "outside":
            return ops.minimum(f + p.thickness, -f)
        return 0.5 * p.thickness - ops.abs_(f)


def _formula_or_number(v: Any) -> Any:
    if isinstance(v, str):
        try:
            parse_formula(v, {"d": None})
        except FormulaError as e:
            raise ValueError(f"bad formula: {e}") from None
    elif not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
        raise ValueError("must be a number > 0 or a formula of x, y, z, t, d")
    return v


#: regularisation of |grad g| (in units of the wavenumber): keeps g / |grad g| finite at the
#: critical points of g, which lie off the zero set for these three surfaces
GRAD_EPS = 0.1


@register("tpms")
class TPMS(Node):
    """Sheet TPMS of ``type``: the wall dist <= thickness / 2 around the zero set of

    * gyroid:    g = sin X cos Y + sin Y cos Z + sin Z cos X
    * schwarz_p: g = cos X + cos Y + cos Z
    * diamond:   g = sin X sin Y sin Z + sin X cos Y cos Z + cos X sin Y cos Z + cos X cos Y sin Z

    with (X, Y, Z) = 2 pi (x, y, z) / cell = k (x, y, z) and dist = a(u) / k, u = |g| / |grad_X g|:
    u / k is the first-order (Newton) distance to the zero set and a(u) = u / (1 + 4u^2/3)^(1/4)
    corrects it along the normal as atan(u) would (exact for one sine wave), so the wall is
    ``thickness`` thick and the field is distance-like.
    ``cell`` and ``thickness`` are numbers or formulas of x, y, z, t and ``d``, the field of the
    node ``d_from`` (e.g. the part itself: the distance to its surface grades the lattice)."""

    class Params(Params):
        type: Literal["gyroid", "schwarz_p", "diamond"] = "gyroid"
        cell: Real | str = Field(description="cell size (period), a number or a formula")
        thickness: Real | str = Field(description="wall thickness, a number or a formula")
        d_from: Any = Field(default=None, description="node whose field is the formula variable d")

        @field_validator("cell", "thickness")
        @classmethod
        def _number_or_formula(cls, v):
            return _formula_or_number(v)

    child_fields = ("d_from",)

    def __init__(self, params, where: str = ""):
        super().__init__(params, where)
        self.env: dict[str, Any] = {"d": None}  # the formulas read d here; field() fills it
        self.cell = self._parse("cell", params.cell)
        self.thickness = self._parse("thickness", params.thickness)

    def children(self) -> list[Node]:
        return [] if self.params.d_from is None else [self.params.d_from]

    def _parse(self, key: str, v: Any) -> Any:
        if not isinstance(v, str):
            return float(v)
        try:
            return parse_formula(v, self.env if self.params.d_from is not None else None)
        except FormulaError as e:  # the only new error here: d without d_from
            raise InputError(f"{key}: bad formula: {e}; d is the field of the node given as d_from") from None

    def _value(self, v: Any, x, y, z, t):
        return v if isinstance(v, float) else v.field(x, y, z, t)

    def field(self, x, y, z, t):
        if self.params.d_from is not None:
            self.env["d"] = self.params.d_from.field(x, y, z, t)
        cell = self._value(self.cell, x, y, z, t)
        k = 2.0 * math.pi / cell if isinstance(cell, float) else ops.div(2.0 * math.pi, cell)
        g, gx, gy, gz = _TPMS[self.params.type](k * x, k * y, k * z)
        u = ops.div(ops.abs_(g), ops.sqrt(ops.sqr(gx) + ops.sqr(gy) + ops.sqr(gz) + GRAD_EPS * GRAD_EPS))
        dist = ops.div(u, k * ops.sqrt(ops.sqrt(1.0 + ATAN_C * ops.sqr(u))))
        thick = self._value(self.thickness, x, y, z, t)
        return 0.5 * thick - dist


def _gyroid(X, Y, Z):
    sx, cx, sy, cy, sz, cz = ops.sin(X), ops.cos(X), ops.sin(Y), ops.cos(Y), ops.sin(Z), ops.cos(Z)
    return sx * cy + sy * cz + sz * cx, cx * cy - sz * sx, cy * cz - sx * sy, cz * cx - sy * sz


def _schwarz_p(X, Y, Z):
    return ops.cos(X) + ops.cos(Y) + ops.cos(Z), -ops.sin(X), -ops.sin(Y), -ops.sin(Z)


def _diamond(X, Y, Z):
    sx, cx, sy, cy, sz, cz = ops.sin(X), ops.cos(X), ops.sin(Y), ops.cos(Y), ops.sin(Z), ops.cos(Z)
    g = sx * sy * sz + sx * cy * cz + cx * sy * cz + cx * cy * sz
    gx = cx * sy * sz + cx * cy * cz - sx * sy * cz - sx * cy * sz
    gy = sx * cy * sz - sx * sy * cz + cx * cy * cz - cx * sy * sz
    gz = sx * sy * cz - sx * cy * sz - cx * sy * sz + cx * cy * cz
    return g, gx, gy, gz


#: u / (1 + c u^2)^(1/4), c = 4/3, agrees with atan(u) to third order and is increasing and
#: unbounded: atan(k g / |grad g|) / k is the exact distance for one sine wave, so the wall keeps
#: its thickness where k T is not small (u alone overestimates the distance by tan(ks)/k - s)
ATAN_C = 4.0 / 3.0

_TPMS = {"gyroid": _gyroid, "schwarz_p": _schwarz_p, "diamond": _diamond}

#: struts of one lattice (each is a few tape clauses; a config's children are limited alike)
MAX_STRUTS = 50_000

# unit-cell struts of the patterns, as pairs of points in [0, 1]^3
_CORNERS = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
_EDGES = [(a, b) for a in _CORNERS for b in _CORNERS
          if a < b and sum(abs(p - q) for p, q in zip(a, b, strict=True)) == 1]
_FACE_CENTRES = [tuple(0.5 if i != ax else s for i in range(3)) for ax in range(3) for s in (0.0, 1.0)]
PATTERNS: dict[str, list] = {
    "cubic": _EDGES,
    "bcc": [((0.5, 0.5, 0.5), c) for c in _CORNERS],
    # octet truss: the face diagonals, and the octahedron joining adjacent face centres
    "octet": [(a, b) for a in _CORNERS for b in _CORNERS
              if a < b and sum(abs(p - q) for p, q in zip(a, b, strict=True)) == 2
              and sum(p == q for p, q in zip(a, b, strict=True)) == 1]
             + [(a, b) for a in _FACE_CENTRES for b in _FACE_CENTRES
                if a < b and math.isclose(sum((p - q) ** 2 for p, q in zip(a, b, strict=True)), 0.5)],
}


@register("lattice")
class Lattice(Node):
    """Union (max) of capsules: r - distance to each strut segment. ``struts`` lists segments
    [[x0, y0, z0], [x1, y1, z1]]; or ``pattern`` (cubic: cube edges, bcc: centre to corners,
    octet: face diagonals and the octahedron of face centres) repeated with period ``cell`` over
    ``bounds`` (whole cells from bounds[0]). Duplicate struts of neighbouring cells are merged."""

    class Params(Params):
        struts: list[tuple[Vec3, Vec3]] | None = None
        pattern: Literal["cubic", "bcc", "octet"] | None = None
        cell: Real | None = Field(default=None, gt=0)
        bounds: tuple[Vec3, Vec3] | None = None
        radius: Real = Field(gt=0)

        @model_validator(mode="after")
        def _one_source(self):
            if (self.struts is None) == (self.pattern is None):
                raise ValueError("give exactly one of struts (a list of segments) or pattern (with cell and bounds)")
            if self.pattern is not None and (self.cell is None or self.bounds is None):
                raise ValueError("pattern needs cell and bounds")
            if self.bounds is not None and any(a >= b for a, b in zip(*self.bounds, strict=True)):
                raise ValueError("bounds: the first corner must be below the second on every axis")
            if self.struts is not None and not self.struts:
                raise ValueError("struts must not be empty")
            return self

    def __init__(self, params, where: str = ""):
        super().__init__(params, where)
        self.segments = _segments(params)
        if len(self.segments) > MAX_STRUTS:
            raise InputError(f"{len(self.segments):,} struts (the limit is {MAX_STRUTS:,}); use a larger cell")

    def field(self, x, y, z, t):
        r = self.params.radius
        return balanced(ops.maximum, [r - _capsule_distance(a, b, x, y, z) for a, b in self.segments])


def _segments(p) -> list[tuple[np.ndarray, np.ndarray]]:
    if p.struts is not None:
        return [(np.asarray(a, float), np.asarray(b, float)) for a, b in p.struts]
    lo, hi = (np.asarray(v, float) for v in p.bounds)
    n = np.maximum(np.floor((hi - lo) / p.cell + 1e-9).astype(int), 1)
    if float(np.prod(n.astype(float))) * len(PATTERNS[p.pattern]) > 4 * MAX_STRUTS:
        raise InputError(f"{int(np.prod(n)):,} cells of {p.cell:g} in the bounds (more than {MAX_STRUTS:,} struts); "
                         "use a larger cell")
    unit = PATTERNS[p.pattern]
    seen: set[tuple] = set()
    for c in np.ndindex(*n):  # in cell units (integers and halves: exact), then to world
        for a, b in unit:
            ends = sorted([tuple(ci + ai for ci, ai in zip(c, a, strict=True)),
                           tuple(ci + bi for ci, bi in zip(c, b, strict=True))])
            seen.add(tuple(ends))
    return [(lo + np.asarray(a) * p.cell, lo + np.asarray(b) * p.cell) for a, b in sorted(seen)]


def _capsule_distance(a: np.ndarray, b: np.ndarray, x, y, z):
    """Distance to the segment a..b: |p - a - h (b - a)|, h the projection clamped to [0, 1]."""
    d = b - a
    dd = float(d @ d)
    px, py, pz = x - a[0], y - a[1], z - a[2]
    if dd == 0:
        return ops.length(px, py, pz)
    h = ops.minimum(ops.maximum((px * d[0] + py * d[1] + pz * d[2]) * (1.0 / dd), 0.0), 1.0)
    return ops.length(px - h * d[0], py - h * d[1], pz - h * d[2])
