"""Set-theoretic operations with R-functions, blending, offset and metamorphosis."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from pydantic import Field

from pipeline.model import ops
from pipeline.model.base import Node, Params, Real, register

RFunc = Literal["min_max", "r0", "sardf"]


class _SetParams(Params):
    of: list[Any] = Field(min_length=1)
    rfunc: RFunc = "r0"


R0_SCALE = 2.0  # magnitude control of r0/sardf results, in domain diagonals (rfunctions.compress)


def magnitude_scale(domain: Any) -> float:
    """c of :func:`pipeline.field.rfunctions.compress` for a job's set operations: twice the domain's
    diagonal, so every value within the domain's own distance scale is eq. 2 itself and no value
    overflows however deep the tree (no domain, as for nodes built in code: no control)."""
    if domain is None:
        return np.inf
    lo, hi = (np.asarray(b, dtype=np.float64) for b in domain.bounds)
    return R0_SCALE * float(np.linalg.norm(hi - lo)) or np.inf


def balanced(op: Callable[[Any, Any], Any], items: list) -> Any:
    """op folded over items as a balanced binary tree (depth log2 n, not n - 1): every R-function
    family is commutative and associative in sign, and r0's magnitude changes with the depth."""
    while len(items) > 1:
        pairs = [op(items[i], items[i + 1]) for i in range(0, len(items) - 1, 2)]
        items = pairs + ([items[-1]] if len(items) % 2 else [])
    return items[0]


class _SetOp(Node):
    Params = _SetParams
    child_fields = ("of",)
    sign_from_children = True
    list_field = "of"
    uses_domain = True  # the job's domain sets the magnitude control of r0 / sardf

    def __init__(self, params, where: str = "", domain: Any = None, t: float = 0.0):
        super().__init__(params, where)
        self.scale = magnitude_scale(domain)

    def _fields(self, x, y, z, t):
        return [c.field(x, y, z, t) for c in self.params.of]

    @property
    def finite_from_children(self) -> bool:  # type: ignore[override]
        """min / max of finite values; r0 / sardf under the magnitude control (a node built
        without a domain has none: sqrt(x^2 + y^2) of finite values can overflow there)."""
        return self.params.rfunc == "min_max" or bool(np.isfinite(self.scale))


@register("union")
class Union(_SetOp):
    """Union by R-disjunction (bsp-fields eq. 1 / eq. 2 / SARDF), as a balanced tree over the list."""

    def field(self, x, y, z, t):
        fam, c = self.params.rfunc, self.scale
        return balanced(lambda a, b: ops.r_or(a, b, fam, scale=c), self._fields(x, y, z, t))


@register("intersection")
class Intersection(_SetOp):
    """Intersection by R-conjunction, as a balanced tree over the list."""

    def field(self, x, y, z, t):
        fam, c = self.params.rfunc, self.scale
        return balanced(lambda a, b: ops.r_and(a, b, fam, scale=c), self._fields(x, y, z, t))


@register("difference")
class Difference(_SetOp):
    """First operand minus all others: f1 AND NOT (f2 OR f3 OR ...), the union balanced."""

    def field(self, x, y, z, t):
        fam, c = self.params.rfunc, self.scale
        first, *rest = self._fields(x, y, z, t)
        if not rest:
            return first
        return ops.r_and(first, -balanced(lambda a, b: ops.r_or(a, b, fam, scale=c), rest), fam, scale=c)


@register("complement")
class Complement(Node):
    """Complement: -f."""

    class Params(Params):
        of: Any

    child_fields = ("of",)
    sign_from_children = True
    finite_from_children = True

    def field(self, x, y, z, t):
        return -self.params.of.field(x, y, z, t)


@register("blend")
class Blend(Node):
    """Blending set operation (Pasko et al. 1995): R(f1, f2) + a0 / (1 + (f1/a1)^2 + (f2/a2)^2).

    a0 > 0 adds material around the junction, a0 < 0 removes it; a1, a2 set how far along
    each operand the blend reaches.
    """

    class Params(Params):
        of: list[Any] = Field(min_length=2, max_length=2)
        op: Literal["union", "intersection", "difference"] = "union"
        a0: Real = 0.1
        a1: Real = Field(default=0.1, gt=0)
        a2: Real = Field(default=0.1, gt=0)
        rfunc: RFunc = "r0"

    child_fields = ("of",)
    list_field = "of"  # blend: [a, b] like union: [a, b]
    uses_domain = True

    def __init__(self, params, where: str = "", domain: Any = None, t: float = 0.0):
        super().__init__(params, where)
        self.scale = magnitude_scale(domain)

    def field(self, x, y, z, t):
        p = self.params
        f1 = p.of[0].field(x, y, z, t)
        f2 = p.of[1].field(x, y, z, t)
        if p.op == "difference":
            f2 = -f2
        c = self.scale
        base = ops.r_or(f1, f2, p.rfunc, scale=c) if p.op == "union" else ops.r_and(f1, f2, p.rfunc, scale=c)
        disp = p.a0 * ops.div(1.0, 1.0 + ops.sqr(f1 * (1.0 / p.a1)) + ops.sqr(f2 * (1.0 / p.a2)))
        return base + disp


@register("offset")
class Offset(Node):
    """f + distance: grows the solid by ``distance`` (shrinks when negative) where f is a distance."""

    class Params(Params):
        of: Any
        distance: Real

    child_fields = ("of",)

    def field(self, x, y, z, t):
        return self.params.of.field(x, y, z, t) + self.params.distance


@register("morph")
class Morph(Node):
    """Metamorphosis: (1 - s) f_from + s f_to, s = ``t`` if given, else the frame time t."""

    class Params(Params):
        from_: Any = Field(alias="from")
        to: Any
        t: Real | None = Field(default=None, ge=0, le=1)

    child_fields = ("from_", "to")

    def field(self, x, y, z, t):
        s = self.params.t if self.params.t is not None else t
        f1 = self.params.from_.field(x, y, z, t)
        f2 = self.params.to.field(x, y, z, t)
        return (1.0 - s) * f1 + s * f2
