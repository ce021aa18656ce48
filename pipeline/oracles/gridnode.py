"""``grid``: an existing .vdb float grid as a field (trilinear samples), e.g. a level set made
by Houdini or by an earlier run, combined with FRep nodes in one tree."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field
from scipy import ndimage

from pipeline.field.affine import AffineForm
from pipeline.io.vdbio import read_dense
from pipeline.model.base import Node, Params, register
from pipeline.model.tape import NotTraceable, Sym
from pipeline.util.jit import njit

MAX_DENSE = 512**3  # voxels of the active bounding box we are prepared to hold densely


@register("grid")
class GridNode(Node):
    """``grid: {path: part.vdb, name: surface, sign: auto}``.

    ``sign: auto`` negates level sets (OpenVDB: negative inside) so that f > 0 inside;
    ``frep`` keeps values, ``levelset`` always negates. Outside the grid's active bounding box
    the field is the (sign-adjusted) background. Bounds over a box are the min/max of the
    samples whose trilinear support meets it, which is rigorous for trilinear interpolation.
    """

    oracle = True

    class Params(Params):
        path: str
        name: str | None = None
        sign: Literal["auto", "frep", "levelset"] = "auto"
        scale: float = Field(default=1.0, gt=0, description="multiply values (units) by this")

    def __init__(self, params, where=""):
        super().__init__(params, where)
        dense = read_dense(Path(params.path), params.name, MAX_DENSE)
        flip = params.sign == "levelset" or (params.sign == "auto" and dense.level_set)
        s = (-1.0 if flip else 1.0) * params.scale
        self.background = s * dense.background
        self.values = (s * dense.values).astype(np.float64)
        self.lo = dense.lo
        self._o, self._Ainv = dense.origin, np.linalg.inv(dense.axes)

    def _to_index(self, pts: np.ndarray) -> np.ndarray:
        """World points (N,3) -> continuous coordinates in the dense array."""
        return (pts - self._o) @ self._Ainv.T - self.lo

    def field(self, x, y, z, t):
        if isinstance(x, AffineForm):
            return self._bound_form(x, y, z)
        if any(isinstance(v, Sym) for v in (x, y, z)):  # sampled by its own kernels, not the tape
            raise NotTraceable("grid nodes are evaluated by interpolation")
        shape = np.broadcast(x, y, z).shape
        pts = np.stack([np.broadcast_to(v, shape).ravel() for v in (x, y, z)], axis=1)
        u = self._to_index(pts)
        vals = ndimage.map_coordinates(self.values, u.T, order=1, mode="constant", cval=self.background)
        return vals.reshape(shape)

    def _bound_form(self, x, y, z) -> AffineForm:
        n = len(x)
        los = np.stack([v.lo if isinstance(v, AffineForm) else np.full(n, v) for v in (x, y, z)], 1)
        his = np.stack([v.hi if isinstance(v, AffineForm) else np.full(n, v) for v in (x, y, z)], 1)
        corners = np.stack([np.where(np.array(m)[None, :], his, los) for m in np.ndindex(2, 2, 2)], 1)
        idx = self._to_index(corners.reshape(-1, 3)).reshape(len(x), 8, 3)
        ilo = np.floor(idx.min(axis=1)).astype(np.int64)
        ihi = np.ceil(idx.max(axis=1)).astype(np.int64)
        flo, fhi = _range_over_boxes(self.values, ilo, ihi, self.background)
        return AffineForm.from_interval(flo, fhi)


@njit(cache=True)
def _range_over_boxes(v, ilo, ihi, bg):
    n = ilo.shape[0]
    flo = np.empty(n)
    fhi = np.empty(n)
    nx, ny, nz = v.shape
    for b in range(n):
        lo = np.inf
        hi = -np.inf
        outside = False
        a0, a1 = ilo[b, 0], ihi[b, 0]
        b0, b1 = ilo[b, 1], ihi[b, 1]
        c0, c1 = ilo[b, 2], ihi[b, 2]
        if a0 < 0 or b0 < 0 or c0 < 0 or a1 >= nx or b1 >= ny or c1 >= nz:
            outside = True
        for i in range(max(a0, 0), min(a1, nx - 1) + 1):
            for j in range(max(b0, 0), min(b1, ny - 1) + 1):
                for k in range(max(c0, 0), min(c1, nz - 1) + 1):
                    w = v[i, j, k]
                    lo = min(lo, w)
                    hi = max(hi, w)
        if outside:
            lo = min(lo, bg)
            hi = max(hi, bg)
        flo[b] = lo
        fhi[b] = hi
    return flo, fhi


