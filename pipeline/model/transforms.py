"""Space mappings: the child is evaluated at the inverse-mapped point.

Rigid and affine maps are exact on affine forms (linear combinations of the noise symbols);
twist and bend go through sin/cos, taper through a division, all bounded rigorously by
:mod:`pipeline.field.affine`.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from pipeline.model import ops
from pipeline.model.base import Node, Params, Real, Vec3, local_uvw, register, unpermute

Axis = Literal["x", "y", "z"]


@register("translate")
class Translate(Node):
    class Params(Params):
        by: Vec3
        of: Any

    child_fields = ("of",)
    sign_from_children = True

    def field(self, x, y, z, t):
        b = self.params.by
        return self.params.of.field(x - b[0], y - b[1], z - b[2], t)


@register("rotate")
class Rotate(Node):
    """Rotation by ``angle`` degrees about ``axis`` (x, y, z or a vector) through ``center``."""

    class Params(Params):
        angle: Real
        axis: Axis | Vec3 = "z"
        center: Vec3 = (0.0, 0.0, 0.0)
        of: Any

        @field_validator("axis")
        @classmethod
        def _nonzero(cls, v):
            if not isinstance(v, str) and sum(c * c for c in v) == 0:
                raise ValueError("axis vector must not be zero")
            return v

    child_fields = ("of",)
    sign_from_children = True

    def __init__(self, params, where=""):
        super().__init__(params, where)
        a = params.axis
        n = np.eye(3)["xyz".index(a)] if isinstance(a, str) else np.asarray(a, float) / np.linalg.norm(a)
        th = math.radians(params.angle)
        K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
        R = np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)  # Rodrigues
        self._inv = R.T  # inverse rotation maps world points back into the child's frame

    def field(self, x, y, z, t):
        c = self.params.center
        px, py, pz = x - c[0], y - c[1], z - c[2]
        m = self._inv
        q = [m[i, 0] * px + m[i, 1] * py + m[i, 2] * pz + c[i] for i in range(3)]
        return self.params.of.field(q[0], q[1], q[2], t)


@register("scale")
class Scale(Node):
    """Scaling about ``center``; the value is multiplied by the smallest factor so that a
    distance field stays a distance (exactly for uniform scaling)."""

    class Params(Params):
        by: Real | Vec3
        center: Vec3 = (0.0, 0.0, 0.0)
        of: Any

        @field_validator("by")
        @classmethod
        def _positive(cls, v):
            vals = (v,) if isinstance(v, (int, float)) else v
            if min(vals) <= 0:
                raise ValueError("scale factors must be > 0")
            return v

    child_fields = ("of",)
    sign_from_children = True

    def field(self, x, y, z, t):
        p = self.params
        s = (p.by,) * 3 if isinstance(p.by, (int, float)) else p.by
        c = p.center
        q = [(v - c[i]) * (1.0 / s[i]) + c[i] for i, v in enumerate((x, y, z))]
        return min(s) * p.of.field(q[0], q[1], q[2], t)


@register("twist")
class Twist(Node):
    """Twist about ``axis`` through ``center``: the cross-section at height w is turned by
    ``rate`` * w degrees (rate in degrees per unit length)."""

    class Params(Params):
        rate: Real
        axis: Axis = "z"
        center: Vec3 = (0.0, 0.0, 0.0)
        of: Any

    child_fields = ("of",)
    sign_from_children = True

    def field(self, x, y, z, t):
        p = self.params
        c = p.center
        u, v, w = local_uvw(x, y, z, c, p.axis)
        th = (-math.radians(p.rate)) * w
        cs, sn = ops.cos(th), ops.sin(th)
        q = unpermute(cs * u - sn * v, sn * u + cs * v, w, p.axis)
        return p.of.field(q[0] + c[0], q[1] + c[1], q[2] + c[2], t)


@register("taper")
class Taper(Node):
    """Taper along ``axis``: the cross-section is scaled by s(w), linear from ``scale[0]`` at
    ``range[0]`` to ``scale[1]`` at ``range[1]`` and constant beyond."""

    class Params(Params):
        axis: Axis = "z"
        range: tuple[Real, Real]
        scale: tuple[Real, Real]
        center: Vec3 = (0.0, 0.0, 0.0)
        of: Any

        @model_validator(mode="after")
        def _check(self):
            if self.range[0] >= self.range[1]:
                raise ValueError("range must be increasing")
            if min(self.scale) <= 0:
                raise ValueError("scale factors must be > 0")
            return self

    child_fields = ("of",)
    sign_from_children = True

    def field(self, x, y, z, t):
        p = self.params
        c = p.center
        u, v, w = local_uvw(x, y, z, c, p.axis)
        (w0, w1), (s0, s1) = p.range, p.scale
        ww = ops.minimum(ops.maximum(w + c["xyz".index(p.axis)], w0), w1)  # world height, clamped
        s = s0 + ((s1 - s0) / (w1 - w0)) * (ww - w0)
        inv = ops.div(1.0, s)
        q = unpermute(u * inv, v * inv, w, p.axis)
        return min(s0, s1) * p.of.field(q[0] + c[0], q[1] + c[1], q[2] + c[2], t)


@register("bend")
class Bend(Node):
    """Bend: the ``along`` axis is curved towards the next axis of the ``plane`` with ``rate``
    radians per unit length (the rotation angle grows linearly along ``along``)."""

    class Params(Params):
        rate: Real
        plane: Literal["xy", "yz", "zx"] = "xy"
        center: Vec3 = (0.0, 0.0, 0.0)
        of: Any = Field()

    child_fields = ("of",)
    sign_from_children = True

    def field(self, x, y, z, t):
        p = self.params
        c = p.center
        q = [x - c[0], y - c[1], z - c[2]]
        i, j = ("xyz".index(p.plane[0]), "xyz".index(p.plane[1]))
        a, b = q[i], q[j]
        th = p.rate * a
        cs, sn = ops.cos(th), ops.sin(th)
        q[i], q[j] = cs * a - sn * b, sn * a + cs * b
        return p.of.field(q[0] + c[0], q[1] + c[1], q[2] + c[2], t)
