"""Primitive solids. Where it is cheap the field is the exact signed distance (positive
inside); otherwise a distance-like normalisation is documented on the class."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.model import ops
from pipeline.model.base import Node, Params, Real, Vec3, local_uvw, register

Axis = Literal["x", "y", "z"]
Positive = Field(gt=0)


@register("sphere")
class Sphere(Node):
    """Exact signed distance: r - |p - c|."""

    class Params(Params):
        center: Vec3 = (0.0, 0.0, 0.0)
        radius: Real = Positive

    def field(self, x, y, z, t):
        c = self.params.center
        return self.params.radius - ops.length(x - c[0], y - c[1], z - c[2])


def _box_sdf(qx, qy, qz):
    """Exact signed distance of a box from q = |p - centre| - half (positive inside)."""
    outside = ops.length(ops.maximum(qx, 0.0), ops.maximum(qy, 0.0), ops.maximum(qz, 0.0))
    inside = ops.minimum(ops.maximum(qx, ops.maximum(qy, qz)), 0.0)
    return -(outside + inside)


@register("box")
class Box(Node):
    """Exact signed distance of the axis-aligned box min..max."""

    class Params(Params):
        min: Vec3
        max: Vec3

        @model_validator(mode="after")
        def _ordered(self):
            if any(a >= b for a, b in zip(self.min, self.max, strict=True)):
                raise ValueError("min must be below max on every axis")
            return self

    def field(self, x, y, z, t):
        lo, hi = self.params.min, self.params.max
        q = [ops.abs_(v - 0.5 * (a + b)) - 0.5 * (b - a) for v, a, b in zip((x, y, z), lo, hi, strict=True)]
        return _box_sdf(*q)


@register("cylinder")
class Cylinder(Node):
    """Exact signed distance; infinite along ``axis`` unless ``height`` is given (centred)."""

    class Params(Params):
        center: Vec3 = (0.0, 0.0, 0.0)
        radius: Real = Positive
        axis: Axis = "z"
        height: Real | None = Field(default=None, gt=0)

    def field(self, x, y, z, t):
        p = self.params
        u, v, w = local_uvw(x, y, z, p.center, p.axis)
        radial = ops.length(u, v) - p.radius
        if p.height is None:
            return -radial
        axial = ops.abs_(w) - 0.5 * p.height
        outside = ops.length(ops.maximum(radial, 0.0), ops.maximum(axial, 0.0))
        return -(outside + ops.minimum(ops.maximum(radial, axial), 0.0))


@register("cone")
class Cone(Node):
    """Finite cone: base disc of ``radius`` at ``center``, apex at ``height`` along ``axis``.

    Intersection (min) of the slab 0 <= w <= height and the infinite cone; the side term is
    the exact distance to the side surface, ((height - w) r/height - rho) cos(alpha).
    """

    class Params(Params):
        center: Vec3 = (0.0, 0.0, 0.0)
        radius: Real = Positive
        height: Real = Positive
        axis: Axis = "z"

    def field(self, x, y, z, t):
        p = self.params
        u, v, w = local_uvw(x, y, z, p.center, p.axis)
        cos_a = p.height / (p.height**2 + p.radius**2) ** 0.5
        side = ((p.height - w) * (p.radius / p.height) - ops.length(u, v)) * cos_a
        slab = ops.minimum(w, p.height - w)
        return ops.minimum(side, slab)


@register("torus")
class Torus(Node):
    """Exact signed distance: minor - |(|p_uv| - major, p_w)|."""

    class Params(Params):
        center: Vec3 = (0.0, 0.0, 0.0)
        major: Real = Positive
        minor: Real = Positive
        axis: Axis = "z"

    def field(self, x, y, z, t):
        p = self.params
        u, v, w = local_uvw(x, y, z, p.center, p.axis)
        return p.minor - ops.length(ops.length(u, v) - p.major, w)


@register("ellipsoid")
class Ellipsoid(Node):
    """min(radii) * (1 - |(p - c)/radii|): exact on the boundary, distance-like near it."""

    class Params(Params):
        center: Vec3 = (0.0, 0.0, 0.0)
        radii: Vec3

        @model_validator(mode="after")
        def _positive(self):
            if min(self.radii) <= 0:
                raise ValueError("radii must be > 0")
            return self

    def field(self, x, y, z, t):
        c, r = self.params.center, self.params.radii
        rho = ops.length((x - c[0]) / r[0], (y - c[1]) / r[1], (z - c[2]) / r[2])
        return min(r) * (1.0 - rho)


@register("superellipsoid")
class Superellipsoid(Node):
    """Barr's superellipsoid, inside-outside function
    F = ((|x/a|^(2/e2) + |y/b|^(2/e2))^(e2/e1) + |z/c|^(2/e1)); field min(radii)(1 - F^(e1/2)).

    F^(e1/2) is homogeneous of degree 1 along rays from the centre, so the field is
    distance-like near the boundary and its zero set is Barr's surface.
    """

    class Params(Params):
        center: Vec3 = (0.0, 0.0, 0.0)
        radii: Vec3 = (1.0, 1.0, 1.0)
        exponents: tuple[Real, Real] = (1.0, 1.0)

        @model_validator(mode="after")
        def _positive(self):
            if min(self.radii) <= 0:
                raise ValueError("radii must be > 0")
            if min(self.exponents) <= 0:
                raise ValueError("exponents must be > 0")
            return self

    def field(self, x, y, z, t):
        p = self.params
        e1, e2 = p.exponents
        ax = ops.pow_(ops.abs_((x - p.center[0]) / p.radii[0]), 2.0 / e2)
        ay = ops.pow_(ops.abs_((y - p.center[1]) / p.radii[1]), 2.0 / e2)
        az = ops.pow_(ops.abs_((z - p.center[2]) / p.radii[2]), 2.0 / e1)
        F = ops.pow_(ax + ay, e2 / e1) + az
        return min(p.radii) * (1.0 - ops.pow_(F, e1 / 2.0))


@register("halfspace")
class Halfspace(Node):
    """Exact signed distance to the plane n.p = offset; inside is n.p <= offset (n points out)."""

    class Params(Params):
        normal: Vec3
        offset: Real = 0.0

        @model_validator(mode="after")
        def _nonzero(self):
            if sum(c * c for c in self.normal) == 0:
                raise ValueError("normal must not be zero")
            return self

    def field(self, x, y, z, t):
        n = self.params.normal
        norm = sum(c * c for c in n) ** 0.5
        return self.params.offset - (n[0] * x + n[1] * y + n[2] * z) / norm


class Blob(Params):
    """One skeletal element: a point ``center`` or a line ``segment``, with its own falloff."""

    center: Vec3 | None = None
    segment: tuple[Vec3, Vec3] | None = None
    radius: Real = Positive
    strength: Real = 1.0

    @model_validator(mode="after")
    def _one_skeleton(self):
        if (self.center is None) == (self.segment is None):
            raise ValueError("give exactly one of center or segment")
        return self


@register("blobby")
class Blobby(Node):
    """Skeletal implicit surface (Blinn's blobby model): sum_i s_i exp(-(d_i/R_i)^2) - threshold,
    d_i the distance to skeleton i (a point or a segment)."""

    class Params(Params):
        blobs: list[Blob] = Field(min_length=1)
        threshold: Real = Field(default=0.5, gt=0)

    def field(self, x, y, z, t):
        total = None
        for b in self.params.blobs:
            d2 = _skeleton_dist2(b, x, y, z)
            term = b.strength * ops.exp(-1.0 / (b.radius * b.radius) * d2)
            total = term if total is None else total + term
        return total - self.params.threshold


def _skeleton_dist2(b: Blob, x, y, z):
    """Squared distance to a point or to a segment (projection clamped to [0, 1])."""
    if b.center is not None:
        c = b.center
        return ops.sqr(x - c[0]) + ops.sqr(y - c[1]) + ops.sqr(z - c[2])
    a, e = b.segment
    d = [e[i] - a[i] for i in range(3)]
    dd = sum(c * c for c in d)
    px, py, pz = x - a[0], y - a[1], z - a[2]
    if dd == 0:
        return ops.sqr(px) + ops.sqr(py) + ops.sqr(pz)
    h = ops.minimum(ops.maximum((px * d[0] + py * d[1] + pz * d[2]) * (1.0 / dd), 0.0), 1.0)
    return ops.sqr(px - h * d[0]) + ops.sqr(py - h * d[1]) + ops.sqr(pz - h * d[2])
