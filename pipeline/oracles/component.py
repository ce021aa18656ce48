"""``component``: one connected component of a model, separated as a proper FRep field.

components seed, section 4.3: the model is enumerated (Algorithm 1), its clusters labelled
(section 4.2), and the chosen cluster turned into a scalar field g_k - the signed distance to
the cluster's octree surface (``method: surface``, section 4.3.1) or the union of merged cells
(``method: cells``, eq. 4-5 with the merging rules of Fig. 2, section 4.3.2). The component is
the R-conjunction f AND g_k, positive only inside the k-th piece, zero on its boundary.

The node evaluates and bounds like any other (g_k has a rigorous interval extension), so a
separated piece can be transformed and recombined (Fig. 3f). Components are numbered 1..N in
scan order of their lowest cell (x, then y, then z). With ``adaptive: true`` the separating
octree is the coarsest one with the same count (Algorithm 2), which is cheaper to evaluate.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from pipeline.field.affine import AffineForm
from pipeline.model import ops
from pipeline.model.base import Node, Params, Real, Vec3, register
from pipeline.topology import components as comp
from pipeline.util.errors import InputError


@register("component")
class Component(Node):
    """The ``index``-th connected component of ``of`` at the given tolerance."""

    oracle = True

    class Params(Params):
        of: Any
        index: int = Field(default=1, ge=1)
        method: Literal["surface", "cells"] = "surface"
        tolerance: Real | None = Field(default=None, gt=0, description="finest cell edge, world units")
        depth: int | None = Field(default=None, ge=1, le=14, description="octree depth (instead of tolerance)")
        bounds: tuple[Vec3, Vec3] | None = Field(default=None, description="box holding the model")
        adaptive: bool = Field(default=True, description="separate on the coarsest octree with the same count")
        rfunc: Literal["min_max", "r0", "sardf"] = "r0"

        @model_validator(mode="after")
        def _one_precision(self):
            if self.tolerance is not None and self.depth is not None:
                raise ValueError("give tolerance or depth, not both")
            if self.bounds is not None and any(a >= b for a, b in zip(*self.bounds, strict=True)):
                raise ValueError("bounds: the first corner must be below the second on every axis")
            return self

    child_fields = ("of",)
    DEFAULT_DEPTH = 7

    def __init__(self, params: Params, where: str = ""):
        super().__init__(params, where)
        self._fields: dict[float, comp.ClusterField] = {}
        self.cluster(0.0)  # validate the index now, so that a bad index is a config error

    def cluster(self, t: float) -> comp.ClusterField:
        """The separating field of the chosen cluster at time t (built once per t)."""
        if t not in self._fields:
            self._fields[t] = self._build(t)
        return self._fields[t]

    def _build(self, t: float) -> comp.ClusterField:
        p = self.params
        try:
            lo, hi = (np.asarray(b, float) for b in p.bounds) if p.bounds else comp.enclosing_box(p.of, t)
        except ValueError as e:
            raise InputError(str(e)) from None
        size = float((hi - lo).max())
        pad = 0.02 * size  # keep the surface off the root cube's faces
        lo, size = lo - pad, size + 2 * pad
        depth = p.depth if p.depth is not None else (
            comp.depth_for(size, p.tolerance) if p.tolerance is not None else self.DEFAULT_DEPTH)
        found = comp.detect(p.of, lo, size, depth, t)
        if p.index > found.count:
            raise InputError(f"component index {p.index} but the model has {found.count} component(s) "
                             f"at tolerance {size / 2**depth:g}")
        label = p.index
        if p.adaptive:
            found, mapping = comp.coarsest_same_count(found)
            label = mapping[p.index]
        return comp.ClusterField(found, label, p.method)

    def field(self, x, y, z, t):
        f = self.params.of.field(x, y, z, t)
        cf = self.cluster(float(t))
        if ops.is_form(x, y, z):
            lo, hi = _boxes(x, y, z)
            glo, ghi = cf.bound(lo, hi)
            g = AffineForm.from_interval(glo, ghi)
        else:
            pts = np.stack(np.broadcast_arrays(x, y, z), axis=-1).reshape(-1, 3)
            g = cf.value(pts).reshape(np.shape(np.broadcast_arrays(x, y, z)[0]))
        return ops.r_and(f, g, self.params.rfunc)


def _boxes(x, y, z) -> tuple[np.ndarray, np.ndarray]:
    """World boxes (lo, hi) (B,3) enclosing the affine forms (or constants) of x, y, z."""
    forms = [v for v in (x, y, z) if isinstance(v, AffineForm)]
    n = len(forms[0])
    lo, hi = np.empty((n, 3)), np.empty((n, 3))
    for a, v in enumerate((x, y, z)):
        if isinstance(v, AffineForm):
            lo[:, a], hi[:, a] = v.interval()
        else:
            lo[:, a] = hi[:, a] = np.broadcast_to(np.asarray(v, float), (n,))
    return lo, hi
