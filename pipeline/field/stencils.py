"""Finite-difference stencils on a block of field values held in a buffer, with a flag per cell
that says whether its value is known (in the spirit of OpenVDB's math/Stencils.h).

The one place a first derivative of a sampled field is written: the band test of the voxeliser
(approximate-distance-fields 1.2: |f| / |grad f| within the band), the eikonal solver's
initialisation next to the zero set (|f| / |grad f|, the distance to the tangent plane) and the
|grad| statistics of the field-quality report. Each caller fills its buffer its own way (a
block alone, or with ghost layers of its neighbours: :func:`pipeline.sparse.access.load_ghosts`);
the stencils only read it. Values are in the field's units per voxel (divide by the voxel size
for world units).

In a module of its own so that the Numba cache is keyed by it (pipeline.KERNEL_PROVIDERS): the
kernels that inline these keep their machine code only while this file is unchanged.
"""

from __future__ import annotations

from pipeline.util.jit import njit


@njit(cache=True, inline="always")
def half_difference(lo, lo_known, c, hi, hi_known):
    """Derivative along one axis (per voxel) at a voxel of value ``c`` between neighbours ``lo``
    and ``hi``: central, (hi - lo) / 2, where both are known; one-sided where one is; 0 where
    neither is (no information: the caller treats the axis as flat)."""
    if lo_known and hi_known:
        return 0.5 * (hi - lo)
    if hi_known:
        return hi - c
    if lo_known:
        return c - lo
    return 0.0


@njit(cache=True, inline="always")
def central_gradient_at(buf, known, i, j, k):
    """(gx, gy, gz, ok): the central-difference gradient (per voxel) at buffer cell (i, j, k);
    ok only when the cell and its six face neighbours are known (no one-sided fallback: the
    statistics of |grad| should not mix in first-order differences)."""
    ok = (known[i, j, k] and known[i - 1, j, k] and known[i + 1, j, k] and known[i, j - 1, k]
          and known[i, j + 1, k] and known[i, j, k - 1] and known[i, j, k + 1])
    if not ok:
        return 0.0, 0.0, 0.0, False
    return (0.5 * (buf[i + 1, j, k] - buf[i - 1, j, k]), 0.5 * (buf[i, j + 1, k] - buf[i, j - 1, k]),
            0.5 * (buf[i, j, k + 1] - buf[i, j, k - 1]), True)
