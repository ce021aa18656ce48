"""Set-theoretic operations with R-functions, blending, offset and metamorphosis."""

from __future__ import annotations

from functools import reduce
from typing import Any, Literal

from pydantic import Field

from pipeline import ops
from pipeline.nodes.base import Node, Params, Real, register

RFunc = Literal["min_max", "r0", "sardf"]


class _SetParams(Params):
    of: list[Any] = Field(min_length=1)
    rfunc: RFunc = "r0"


class _SetOp(Node):
    Params = _SetParams
    child_fields = ("of",)
    list_field = "of"

    def _fields(self, x, y, z, t):
        return [c.field(x, y, z, t) for c in self.params.of]


@register("union")
class Union(_SetOp):
    """Union by R-disjunction (bsp-fields eq. 1 / eq. 2 / SARDF), folded left over the list."""

    def field(self, x, y, z, t):
        fam = self.params.rfunc
        return reduce(lambda a, b: ops.r_or(a, b, fam), self._fields(x, y, z, t))


@register("intersection")
class Intersection(_SetOp):
    """Intersection by R-conjunction."""

    def field(self, x, y, z, t):
        fam = self.params.rfunc
        return reduce(lambda a, b: ops.r_and(a, b, fam), self._fields(x, y, z, t))


@register("difference")
class Difference(_SetOp):
    """First operand minus all others: f1 AND (NOT f2) AND (NOT f3) ..."""

    def field(self, x, y, z, t):
        fam = self.params.rfunc
        first, *rest = self._fields(x, y, z, t)
        return reduce(lambda a, b: ops.r_and(a, -b, fam), rest, first)


@register("complement")
class Complement(Node):
    """Complement: -f."""

    class Params(Params):
        of: Any

    child_fields = ("of",)

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

    def field(self, x, y, z, t):
        p = self.params
        f1 = p.of[0].field(x, y, z, t)
        f2 = p.of[1].field(x, y, z, t)
        if p.op == "difference":
            f2 = -f2
        base = ops.r_or(f1, f2, p.rfunc) if p.op == "union" else ops.r_and(f1, f2, p.rfunc)
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
