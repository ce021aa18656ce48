"""HFRep attributes parameterised by distance (hfrep seed, definition 4.2, sections 5.2 and 7).

An attribute component is ``F_A(F_HFRep(p), p)``: a function of the point and of the
distance to the boundary (section 5.2 step 2). Here each attribute is a formula (or three,
for an RGB colour) in ``x, y, z, t`` and ``d``, parsed by :func:`pipeline.model.expr.parse_formula`
with the extra variable ``d`` — never Python's ``eval``.

``d`` is the smoothed unsigned distance ``F_smDF`` (eq. 20) in world units, ``d >= 0``:
the interpolating tricubic spline of the eikonal distance, which at voxel centres equals the
solved samples (``pipeline.distance.spline``), so on the grid ``d`` is the solved distance of the
voxel. Inside the object ``d = F_HFRep`` up to the step of eq. 21, which is 1 there.

Outside the object (``outside:``):

- ``inactive`` (default): attribute grids are active only on the solved voxels inside
  (frep > 0); outside they hold the background (0 or (0, 0, 0));
- ``surface``: the voxels of the hfrep grid outside the object, up to the stage's band,
  are active too and take the formula with ``d = 0`` — the surface value continued
  outwards, so a renderer that interpolates the attribute at the zero set (Houdini,
  Blender) sees no dark fringe from the background.

Microstructures (section 7.1) are attributes too: eq. 24 slabs ``S(p) = sin(nu p + phi) + l``
written as a formula, e.g. material 1 where ``sin(40 x) + 0.3 > 0`` and a solid skin where
``d`` is small (``configs/hfrep_microstructure.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import prange

from pipeline.model.base import Node
from pipeline.model.expr import FormulaError, Param, Var, parse_formula
from pipeline.model.tape import Tape, TapePool, compile_model
from pipeline.sparse.grid import BlockGrid
from pipeline.util.jit import njit

VARIABLES = ("d",)


class AttributeFormula:
    """A parsed attribute formula ``F_A(d, x, y, z, t)``; raises FormulaError on bad input."""

    def __init__(self, src: str) -> None:
        self.src = src
        self._env: dict[str, object] = {name: 0.0 for name in VARIABLES}
        self.tree: Node = parse_formula(src, self._env)

    def __call__(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, d: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Values at points (coordinate arrays of one shape) with distances ``d`` (same shape)."""
        self._env["d"] = np.asarray(d, dtype=np.float64)
        try:
            with np.errstate(all="ignore"):
                out = self.tree.field(x, y, z, float(t))
        finally:
            self._env["d"] = 0.0
        return np.broadcast_to(np.asarray(out, dtype=np.float64), np.shape(x)).copy()

    def lowered(self, t: float = 0.0) -> tuple[Tape, np.ndarray] | None:
        """The formula as a tape of three inputs and what feeds each (:data:`SLOT_SOURCES`
        rows: 0/1/2 the voxel's x/y/z, 3 its distance d, -1 nothing), or None when it reads all
        four of x, y, z and d (a tape has three inputs) or does not trace. A coordinate keeps its
        own input; d takes one the formula leaves free."""
        used = _names(self.tree)
        if {"x", "y", "z", "d"} <= used:
            return None
        src = np.array([a if "xyz"[a] in used else -1 for a in range(3)], np.int64)
        if "d" in used:
            src[int(np.flatnonzero(src < 0)[0])] = 3
        tape = compile_model(_Lowered(self, src), t)
        return None if tape is None else (tape, src)


class _Lowered:
    """An attribute formula as a model of three inputs for the tracer (pipeline.model.tape):
    input a feeds the formula's x, y, z or d as ``src[a]`` says."""

    def __init__(self, formula: AttributeFormula, src: np.ndarray):
        self.formula, self.src = formula, src

    def field(self, x, y, z, t):
        inputs = (x, y, z)
        feed = {int(v): inputs[a] for a, v in enumerate(self.src) if v >= 0}
        self.formula._env["d"] = feed.get(3, 0.0)
        try:
            return self.formula.tree.field(feed.get(0, 0.0), feed.get(1, 0.0), feed.get(2, 0.0), t)
        finally:
            self.formula._env["d"] = 0.0


def _names(tree: Node) -> set[str]:
    """The variables (x y z t and the extra ones) a parsed formula reads."""
    out, stack = set(), [tree]
    while stack:
        item = stack.pop()
        if isinstance(item, (Var, Param)):
            out.add(item.args[0])
        elif isinstance(item, Node):
            stack.extend(getattr(item, "args", ()))
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
    return out


def check_formula(src: str) -> str:
    """Pydantic validator: the formula parses with the attribute variables (x y z t d)."""
    try:
        AttributeFormula(src)
    except FormulaError as e:  # pydantic reports the ValueError with its YAML path
        raise ValueError(f"bad formula: {e}") from None
    return src


@dataclass
class AttributeVoxels:
    """Where attributes are evaluated: voxel centres, their distance ``d``, and the blocks."""

    origins: np.ndarray  # (L,3) block origins of the eikonal result
    active: np.ndarray  # (L,8,8,8) voxels that carry the attribute
    d: np.ndarray  # (L,8,8,8) float32 distance used in the formula (0 where not active)
    voxel_size: float

    def coordinates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, y, z of every voxel centre, each (L,8,8,8)."""
        r = np.arange(8)
        loc = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1)
        ijk = self.origins[:, None, None, None, :] + loc[None]
        w = ijk * self.voxel_size
        return w[..., 0], w[..., 1], w[..., 2]


def attribute_voxels(result, hfrep: BlockGrid, outside: str = "inactive", band: float = 3.0) -> AttributeVoxels:
    """The voxels attributes cover (see the module docstring), from an EikonalResult.

    ``hfrep``: the stage's hfrep blocks (same origins as ``result.distance``); ``band``: for
    ``outside: surface``, how far outside (voxels) the surface value is continued.
    """
    if outside not in ("inactive", "surface"):
        raise ValueError(f"outside must be 'inactive' or 'surface', not {outside!r}")
    dist = result.distance
    active = np.empty(dist.active.shape, np.bool_)
    d = np.empty(dist.values.shape, np.float32)
    _covered(result.inside, dist.active, dist.values, hfrep.active, outside == "surface",
             np.float32(band * dist.voxel_size), active, d)
    return AttributeVoxels(dist.origins, active, d, float(dist.voxel_size))


@njit(cache=True, parallel=True)
def _covered(inside, solved, dist, hf_active, surface, reach, active, d):
    """active = solved inside voxels, and with ``surface`` the solved outside voxels within
    ``reach`` (world units) that hfrep keeps; d = the distance inside (float32 as solved: exact
    in a formula's float64), 0 elsewhere. One pass over the blocks: the NumPy masks and
    ``where`` made five full-size temporaries (3.5 s per attribute at 1024^3)."""
    for b in prange(dist.shape[0]):
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    s = solved[b, i, j, k]
                    if inside[b, i, j, k]:
                        active[b, i, j, k] = s
                        d[b, i, j, k] = dist[b, i, j, k] if s else np.float32(0.0)
                    else:
                        active[b, i, j, k] = surface and s and dist[b, i, j, k] <= reach and hf_active[b, i, j, k]
                        d[b, i, j, k] = np.float32(0.0)


def evaluate_attribute(formulas: list[AttributeFormula], vox: AttributeVoxels, t: float = 0.0) -> np.ndarray:
    """(L,8,8,8) float32 for one formula, (L,8,8,8,3) for three (RGB); zero where not active.

    A formula that lowers to a tape (:meth:`AttributeFormula.lowered`) runs on the compiled
    evaluator over the active voxels, a chunk of blocks at a time; one that reads all of x, y,
    z and d runs node by node in NumPy. The same float64 values either way, rounded to float32
    (the grids' type). Raises NonFiniteAttribute naming the component and the first voxel (in
    block order) where a formula is not finite."""
    m = vox.active
    out = np.zeros(m.shape + ((len(formulas),) if len(formulas) > 1 else ()), np.float32)
    for c, f in enumerate(formulas):
        dst = out[..., c] if len(formulas) > 1 else out
        low = f.lowered(t)
        if low is None:
            _evaluate_numpy(c, f, vox, t, dst)
        else:
            _evaluate_tape(c, low, vox, dst)
    return out


ATTRIBUTE_CHUNK = 8192  # blocks per compiled evaluation (4M voxels at most: 100 MB of points)


def _evaluate_tape(c: int, low: tuple[Tape, np.ndarray], vox: AttributeVoxels, dst: np.ndarray) -> None:
    tape, src = low
    pool = TapePool.single(tape)
    m = vox.active
    room = np.empty((0, 3))  # one buffer for every chunk: its pages are faulted in once
    for a in range(0, len(m), ATTRIBUTE_CHUNK):
        b = min(a + ATTRIBUTE_CHUNK, len(m))
        counts = m[a:b].reshape(b - a, -1).sum(axis=1)
        offs = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        if len(room) < offs[-1]:
            room = np.empty((int(offs[-1]), 3))
        pts = room[:int(offs[-1])]
        _slot_points(vox.origins[a:b], m[a:b], vox.d[a:b], vox.voxel_size, src, offs, pts)
        vals = pool.evaluate(pts)
        bad = ~np.isfinite(vals)
        if bad.any():
            _raise_first(c, vox, a, b, bad)
        _scatter(m[a:b], offs, vals, dst[a:b])


def _raise_first(c: int, vox: AttributeVoxels, a: int, b: int, bad: np.ndarray) -> None:
    """NonFiniteAttribute at the first active voxel of blocks a..b-1 whose value is bad (``bad``:
    per active voxel of those blocks, in block and C order)."""
    bb, i, j, k = np.nonzero(vox.active[a:b])
    n = int(np.flatnonzero(bad)[0])
    blk, ii, jj, kk = a + bb[n], i[n], j[n], k[n]
    p = (vox.origins[blk] + (ii, jj, kk)) * vox.voxel_size
    raise NonFiniteAttribute(c, tuple(p), vox.d[blk, ii, jj, kk])


def _evaluate_numpy(c: int, f: AttributeFormula, vox: AttributeVoxels, t: float, dst: np.ndarray) -> None:
    x, y, z = vox.coordinates()
    m = vox.active
    vals = f(x[m], y[m], z[m], vox.d[m], t)  # the active voxels in block and C order
    bad = ~np.isfinite(vals)
    if bad.any():
        _raise_first(c, vox, 0, len(m), bad)
    dst[m] = vals


SLOT_SOURCES = ("x", "y", "z", "d")  # what a lowered formula's input reads, by index


@njit(cache=True, parallel=True)
def _slot_points(origins, active, d, h, src, offs, pts):
    """The tape's inputs at the active voxels of each block, in block and C order from
    ``offs[b]``: input a is the voxel centre's coordinate src[a] (0..2), its distance (3) or 0."""
    for b in prange(origins.shape[0]):
        n = offs[b]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if not active[b, i, j, k]:
                        continue
                    for a in range(3):
                        s = src[a]
                        if s == 0:
                            pts[n, a] = (origins[b, 0] + i) * h
                        elif s == 1:
                            pts[n, a] = (origins[b, 1] + j) * h
                        elif s == 2:
                            pts[n, a] = (origins[b, 2] + k) * h
                        elif s == 3:
                            pts[n, a] = np.float64(d[b, i, j, k])
                        else:
                            pts[n, a] = 0.0
                    n += 1


@njit(cache=True, parallel=True)
def _scatter(active, offs, vals, dst):
    """dst's active voxels (block and C order, from offs[b]) = float32(vals)."""
    for b in prange(active.shape[0]):
        n = offs[b]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if active[b, i, j, k]:
                        dst[b, i, j, k] = np.float32(vals[n])
                        n += 1


class NonFiniteAttribute(ValueError):
    """An attribute formula that is NaN or infinite at a voxel (division by zero, log of 0...)."""

    def __init__(self, component: int, point: tuple, d: float):
        self.component = component
        px, py, pz = (float(v) for v in point)
        super().__init__(f"the formula is not a finite number at ({px:g}, {py:g}, {pz:g}), d = {float(d):g} "
                         "(division by zero, log or sqrt of a negative number?)")


