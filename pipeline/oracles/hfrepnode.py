"""``hfrep`` node: the HFRep field of a child node (hfrep seed, section 5.1, eq. 21) in a tree.

The child is voxelised on its own grid (:func:`pipeline.voxel.voxelise.voxelise`), the unsigned
distance to its zero set is solved by the block FIM (:func:`pipeline.distance.eikonal.solve_distance`,
eq. 22), smoothed by the interpolating C2 tricubic B-spline (eq. 20) and signed by a C1 step
of the child's value (eq. 21, 23)::

    F(p) = F_st(f_child(p)) * sqrt(s(p)^2 + eps^2)

(:class:`pipeline.distance.hfrep.HFRepField`). The field is C1 wherever the child is, has exactly the
child's zero set and sign, and is distance-like: ``offset`` of an ``hfrep`` node moves the
surface by the offset distance along the normals (a true offset, up to the solver's
distance error: under a quarter voxel on smooth parts, half a voxel in edge and corner
fans), and ``blend`` / ``morph`` see distances rather than arbitrary FRep values.

Rigorous bound over a box B (inclusion property, so affine culling in the voxeliser and the
components stage stays sound):

- sign part: the child's revised affine form over B gives [f_lo, f_hi]; the step is
  monotone, so ``F_st(B) ⊆ [F_st(f_lo), F_st(f_hi)]``;
- distance part: the uniform cubic B-spline weights are non-negative and sum to one, so
  ``s(p)`` lies in the convex hull of the 4^3 coefficients of its support; over B it lies
  within [min, max] of the coefficients whose support meets B (index range
  ``floor(lo/h) - 1 .. floor(hi/h) + 2`` per axis), plus the fallback value ``fill``
  where that range leaves the solved blocks; ``sqrt(s^2 + eps^2)`` is monotone in |s|;
- the two intervals are multiplied with interval arithmetic and widened outwards by a
  rounding allowance; the result is returned as an affine form without noise symbols.

The distance is solved once, when the node is first evaluated or bounded (not when it is built:
validating a config does not solve), for the child at the job's ``t``.
``bounds`` and the voxel size default to the job's domain (the config loader passes it:
``uses_domain``); beyond ``bounds`` (or beyond ``max_distance`` outside) the distance is the
clamp value, so keep offsets smaller than ``max_distance`` and the surface at least 4 voxels
inside ``bounds``.
"""

from __future__ import annotations

import functools
from typing import Any, ClassVar, Literal, NamedTuple

import numpy as np
from pydantic import Field, model_validator

from pipeline.distance.eikonal import solve_distance
from pipeline.distance.hfrep import HFRepField, hfrep_field, step_function
from pipeline.distance.spline import TricubicSpline
from pipeline.field.affine import AffineForm
from pipeline.model.base import Node, Params, Real, Vec3, register
from pipeline.util.errors import InputError
from pipeline.util.jit import njit
from pipeline.voxel.voxelise import voxelise

_ROUND = 1e-12  # relative allowance for the spline sum, step and products (>> float64 rounding)


class _Solve(NamedTuple):
    """What the node's solve gives: the eikonal result, the field, the per-block coefficient
    ranges of its spline (for the bounds) and the statistics."""

    result: Any
    hf: HFRepField
    block_min: np.ndarray
    block_max: np.ndarray
    stats: dict


@register("hfrep")
class HFRepNode(Node):
    """``hfrep: {of: node, resolution | voxel_size, bounds, band, step, slope, max_distance, order}``."""

    oracle = True

    class Params(Params):
        of: Any
        resolution: int | None = Field(default=None, gt=0, le=1024, description="voxels along the longest side")
        voxel_size: Real | None = Field(default=None, gt=0)
        bounds: tuple[Vec3, Vec3] | None = None
        band: Real = Field(default=3.0, gt=0, le=64, description="narrow band of the child, voxels")
        step: Literal["sigmoid", "tanh", "rational"] = "sigmoid"
        slope: Real = Field(default=0.01, gt=0)
        max_distance: Real | None = Field(default=None, gt=0, description="world units; default: all of bounds")
        order: Literal[1, 2] = Field(default=2, description="upwind scheme of the eikonal solver")

        @model_validator(mode="after")
        def _check(self):
            if self.resolution is not None and self.voxel_size is not None:
                raise ValueError("give at most one of resolution or voxel_size")
            if self.bounds is not None and any(a >= b for a, b in zip(*self.bounds, strict=True)):
                raise ValueError("bounds: the first corner must be below the second on every axis")
            return self

    child_fields = ("of",)
    uses_domain: ClassVar[bool] = True  # pipeline.job.config.build_node passes domain= and t=
    solves_on_first_use: ClassVar[bool] = True  # the loader does not evaluate it (Node)

    def __init__(self, params, where: str = "", domain: Any = None, t: float = 0.0):
        super().__init__(params, where)
        p = params
        bounds = p.bounds if p.bounds is not None else (domain.bounds if domain is not None else None)
        if bounds is None:
            raise InputError("bounds: needed when the node is built without a job domain")
        lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
        if p.voxel_size is not None:
            h = float(p.voxel_size)
        elif p.resolution is not None:
            h = float((hi - lo).max() / p.resolution)
        elif domain is not None:
            h = float(domain.voxel_size)
        else:
            raise InputError("give resolution or voxel_size (no job domain to take the voxel size from)")
        imin = np.ceil(lo / h - 1e-9).astype(np.int64)
        imax = np.floor(hi / h + 1e-9).astype(np.int64)
        if np.any(imax - imin + 1 > 2048):
            raise InputError(f"voxel_size {h:g} gives {(imax - imin + 1).tolist()} voxels: at most 2048 per axis")
        self.t = float(t)
        self.voxel_size = h
        self._index_box = (imin, imax)

    # --- the solve, on first use ------------------------------------------------------------
    # Not in __init__: building the model (``frepvdb validate``, the config loader) must not
    # voxelise and solve. Its problems are then found by the first stage that evaluates the
    # node, and located at the node (InputError ``node=``).
    @functools.cached_property
    def _solved(self) -> _Solve:
        p = self.params
        imin, imax = self._index_box
        vox = voxelise(p.of, imin, imax, self.voxel_size, p.band, 4, self.t)
        if vox.blocks.active_count == 0 or not _has_sign_change(vox.blocks):
            raise InputError("the child has no surface inside the hfrep bounds", node=self.where or None)
        result = solve_distance(vox.blocks, p.max_distance, (imin, imax), vox.inside_boxes, order=p.order)
        hf = HFRepField(lambda q: p.of.evaluate(q, self.t), _spline(result), p.step, p.slope)
        bmin, bmax = _block_ranges(hf.distance.coefficients)
        return _Solve(result, hf, bmin, bmax, {**vox.stats, **result.stats})

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state.pop("_solved", None)  # a worker solves its own copy (the field holds a closure)
        return state

    @property
    def result(self):
        """The eikonal solve of the child's distance (:func:`pipeline.distance.eikonal.solve_distance`)."""
        return self._solved.result

    @property
    def hf(self) -> HFRepField:
        return self._solved.hf

    @property
    def stats(self) -> dict:
        return self._solved.stats

    def field(self, x, y, z, t):
        if any(isinstance(v, AffineForm) for v in (x, y, z)):
            return self._bound_form(x, y, z, t)
        shape = np.broadcast(x, y, z).shape
        pts = np.stack([np.broadcast_to(np.asarray(v, dtype=np.float64), shape).ravel() for v in (x, y, z)], 1)
        f = np.broadcast_to(np.asarray(self.params.of.field(x, y, z, t), dtype=np.float64), shape).ravel()
        out = hfrep_field(f, self.hf.smoothed_distance(pts), self.params.step, self.params.slope)
        return out.reshape(shape)

    # --- rigorous bound -------------------------------------------------------------------
    def distance_range(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the regularised distance sqrt(s^2 + eps^2) over boxes lo..hi (B,3), world."""
        sp = self.hf.distance
        h = self.voxel_size
        lat_lo = sp.lattice_lo * 8
        lat_hi = (sp.lattice_lo + np.array(sp.lattice.shape)) * 8 - 1
        with np.errstate(invalid="ignore"):
            a = np.floor(lo / h) - 1
            b = np.floor(hi / h) + 2
        bad = ~(np.isfinite(a) & np.isfinite(b)).all(axis=1)
        a = np.where(np.isfinite(a), a, lat_lo - 1)
        b = np.where(np.isfinite(b), b, lat_hi + 1)
        ilo = np.clip(a, lat_lo - 1, lat_hi + 1).astype(np.int64)
        ihi = np.clip(b, lat_lo - 1, lat_hi + 1).astype(np.int64)
        n = len(lo)
        smin, smax, complete = np.empty(n), np.empty(n), np.empty(n, dtype=np.bool_)
        solve = self._solved
        _coef_range(sp.coefficients, solve.block_min, solve.block_max, sp.lattice, sp.lattice_lo, ilo, ihi, smin, smax,
                    complete)
        fill = sp.fill
        smin = np.where(complete & ~bad, smin, np.minimum(smin, fill))
        smax = np.where(complete & ~bad, smax, np.maximum(smax, fill))
        tol = _ROUND * np.maximum(np.abs(smin), np.abs(smax)) + 1e-300
        smin, smax = smin - tol, smax + tol
        eps2 = self.hf.eps**2
        amin = np.where((smin <= 0) & (smax >= 0), 0.0, np.minimum(np.abs(smin), np.abs(smax)))
        amax = np.maximum(np.abs(smin), np.abs(smax))
        rlo = np.sqrt(amin * amin + eps2) * (1 - _ROUND)
        rhi = np.sqrt(amax * amax + eps2) * (1 + _ROUND)
        rlo = np.where(bad, self.hf.eps * (1 - _ROUND), rlo)
        rhi = np.where(bad, np.inf, rhi)
        return rlo, rhi

    def _bound_form(self, x, y, z, t) -> AffineForm:
        n = next(len(v) for v in (x, y, z) if isinstance(v, AffineForm))
        lo = np.stack([_lo(v, n) for v in (x, y, z)], axis=1)
        hi = np.stack([_hi(v, n) for v in (x, y, z)], axis=1)
        fc = self.params.of.field(x, y, z, t)
        if isinstance(fc, AffineForm):
            flo, fhi = fc.interval()
            flo = np.where(np.isnan(flo), -np.inf, flo)
            fhi = np.where(np.isnan(fhi), np.inf, fhi)
        else:
            flo = fhi = np.broadcast_to(np.asarray(fc, dtype=np.float64), (n,))
        slo = _step_bound(flo, self.params.step, self.params.slope, -1)
        shi = _step_bound(fhi, self.params.step, self.params.slope, +1)
        rlo, rhi = self.distance_range(lo, hi)
        with np.errstate(invalid="ignore"):
            cands = np.stack([slo * rlo, slo * rhi, shi * rlo, shi * rhi])
        cands = np.where(np.isnan(cands), 0.0, cands)  # 0 * inf: the step factor is exactly 0
        plo, phi = cands.min(axis=0), cands.max(axis=0)
        plo = plo - _ROUND * np.abs(plo) - 1e-300
        phi = phi + _ROUND * np.abs(phi) + 1e-300
        return AffineForm.from_interval(plo, phi)


def _lo(v, n: int) -> np.ndarray:
    return v.lo if isinstance(v, AffineForm) else np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))


def _hi(v, n: int) -> np.ndarray:
    return v.hi if isinstance(v, AffineForm) else np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))


def _step_bound(f: np.ndarray, step: str, slope: float, side: int) -> np.ndarray:
    """F_st at interval ends (monotone), widened outwards by the rounding allowance; +-1 at +-inf."""
    with np.errstate(all="ignore"):
        s = step_function(np.clip(f, -1e300, 1e300), step, slope)
    s = np.where(f == np.inf, 1.0, np.where(f == -np.inf, -1.0, s))
    return np.clip(s + side * (_ROUND + 1e-300), -1.0, 1.0)


def _has_sign_change(blocks) -> bool:
    v = blocks.values[blocks.active]
    return bool((v > 0).any() and (v <= 0).any())


def _spline(result):
    return TricubicSpline(result.distance)


def _block_ranges(coef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-row min and max of the coefficients of each 8^3 block."""
    flat = coef.reshape(len(coef), -1)
    return flat.min(axis=1), flat.max(axis=1)


@njit(cache=True)
def _coef_range(coef, bmin, bmax, lattice, lat_lo, ilo, ihi, out_lo, out_hi, complete):
    """Min/max of the coefficients over the voxel index boxes ilo..ihi (inclusive).

    Whole blocks use their precomputed range, partly covered blocks are scanned; ``complete``
    is False where the box reaches a block that does not exist (its value is ``fill``).
    """
    nx, ny, nz = lattice.shape
    for p in range(ilo.shape[0]):
        lo = np.inf
        hi = -np.inf
        ok = True
        bl = np.empty(3, dtype=np.int64)
        bh = np.empty(3, dtype=np.int64)
        for a in range(3):
            bl[a] = (ilo[p, a] >> 3) - lat_lo[a]
            bh[a] = (ihi[p, a] >> 3) - lat_lo[a]
            if bl[a] < 0 or bh[a] >= lattice.shape[a]:
                ok = False
        for bi in range(max(bl[0], 0), min(bh[0], nx - 1) + 1):
            for bj in range(max(bl[1], 0), min(bh[1], ny - 1) + 1):
                for bk in range(max(bl[2], 0), min(bh[2], nz - 1) + 1):
                    row = lattice[bi, bj, bk]
                    if row < 0:
                        ok = False
                        continue
                    o0 = (bi + lat_lo[0]) * 8
                    o1 = (bj + lat_lo[1]) * 8
                    o2 = (bk + lat_lo[2]) * 8
                    i0, i1 = max(ilo[p, 0] - o0, 0), min(ihi[p, 0] - o0, 7)
                    j0, j1 = max(ilo[p, 1] - o1, 0), min(ihi[p, 1] - o1, 7)
                    k0, k1 = max(ilo[p, 2] - o2, 0), min(ihi[p, 2] - o2, 7)
                    if i0 == 0 and j0 == 0 and k0 == 0 and i1 == 7 and j1 == 7 and k1 == 7:
                        lo = min(lo, bmin[row])
                        hi = max(hi, bmax[row])
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            for k in range(k0, k1 + 1):
                                c = coef[row, i, j, k]
                                lo = min(lo, c)
                                hi = max(hi, c)
        out_lo[p] = lo
        out_hi[p] = hi
        complete[p] = ok
