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

from pipeline.model.base import Node
from pipeline.model.expr import FormulaError, parse_formula
from pipeline.sparse.grid import BlockGrid

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
    d: np.ndarray  # (L,8,8,8) distance used in the formula (0 where not active)
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
    dist = result.distance
    inside = result.inside & dist.active
    active = inside.copy()
    d = np.where(inside, dist.values.astype(np.float64), 0.0)
    if outside == "surface":
        near = (~result.inside) & dist.active & (dist.values <= band * dist.voxel_size) & hfrep.active
        active |= near
    elif outside != "inactive":
        raise ValueError(f"outside must be 'inactive' or 'surface', not {outside!r}")
    return AttributeVoxels(dist.origins, active, d, float(dist.voxel_size))


def evaluate_attribute(formulas: list[AttributeFormula], vox: AttributeVoxels, t: float = 0.0) -> np.ndarray:
    """(L,8,8,8) for one formula, (L,8,8,8,3) for three (RGB); zero where not active.

    Raises ValueError naming the component and a point where a formula is not finite.
    """
    x, y, z = vox.coordinates()
    m = vox.active
    comps = []
    for c, f in enumerate(formulas):
        vals = np.zeros(m.shape)
        vals[m] = f(x[m], y[m], z[m], vox.d[m], t)
        bad = m & ~np.isfinite(vals)
        if bad.any():
            b, i, j, k = np.argwhere(bad)[0]
            raise NonFiniteAttribute(c, (x[b, i, j, k], y[b, i, j, k], z[b, i, j, k]), vox.d[b, i, j, k])
        comps.append(vals)
    return comps[0] if len(comps) == 1 else np.stack(comps, axis=-1)


class NonFiniteAttribute(ValueError):
    """An attribute formula that is NaN or infinite at a voxel (division by zero, log of 0...)."""

    def __init__(self, component: int, point: tuple, d: float):
        self.component = component
        px, py, pz = (float(v) for v in point)
        super().__init__(f"the formula is not a finite number at ({px:g}, {py:g}, {pz:g}), d = {float(d):g} "
                         "(division by zero, log or sqrt of a negative number?)")


