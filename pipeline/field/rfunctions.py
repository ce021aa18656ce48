"""R-functions for set operations on FRep fields (f > 0 inside), on NumPy arrays.

Three families, chosen per operation with ``rfunc``:

* ``min_max`` - bsp-fields eq. 1: exact where one argument dominates, C1-discontinuous on f1 = f2.
* ``r0``      - bsp-fields eq. 2: f1 + f2 +- sqrt(f1^2 + f2^2); C1 except where f1 = f2 = 0.
* ``sardf``   - smooth approximation of min/max in the spirit of the SARDF operations
  [FPSM06] (Fayolle, Pasko, Schmitt, Mirenkov 2006). Outside an angular window around the
  diagonal f1 = f2 it *is* min/max (so it keeps the distance property of its arguments);
  inside the window |f1 - f2| < k * rho, rho = sqrt(f1^2 + f2^2), the |f1 - f2| in
  min = (f1 + f2 - |f1 - f2|)/2 is replaced by the C1 quadratic (u^2 + (k rho)^2) / (2 k rho).
  The result is homogeneous of degree 1 and C1 away from f1 = f2 = 0; for k < 1 its sign
  equals the sign of min/max everywhere (the window never meets the lines f1 = 0 or f2 = 0
  on the positive side), so it is an R-function and keeps the zero set exactly. This is our
  formulation of the FPSM06 idea; docs/rfunctions.md states how it differs from the paper.

**Magnitude control (issue 12).** Eq. 2 multiplies magnitudes at every level where both
arguments have one sign (R0 AND of two negatives is up to (2 + sqrt 2) times the larger one),
so a deep tree — a BSP-tree of depth 500, a union of 140 parts — reaches 1e38 and beyond far
from the surface and overflows. ``r0`` and ``sardf`` results therefore pass through
:func:`compress` with a length scale c (the model's size, set by the tree): the identity for
|f| <= c and c (1 + ln(|f| / c)) beyond. It is C1, increasing and odd, so the result is still an
R-function with the same sign and zero set, every value within c of zero is exactly eq. 2, and
no value can grow beyond a few c (the fixed point of c (1 + ln((2 + sqrt 2) f / c)) is
about 3.5 c). ``scale = inf`` (the default for direct calls) turns it off.

The formulas are written once, as compiled scalar functions in :mod:`pipeline.field.rkernels`
(which the tape's kernels and the BSP-field inline); the array functions here run them in
compiled loops over the broadcast arrays. Their enclosures over boxes (affine arithmetic) are in
:mod:`pipeline.model.ops`, which dispatches on the argument type; model nodes call the ``ops``
versions.
"""

from __future__ import annotations

import numpy as np

from pipeline.field import rkernels as rk
from pipeline.util.jit import njit

FAMILIES = ("min_max", "r0", "sardf")
SARDF_K = 0.5  # half-width of the smoothing window (|f1-f2| < k*rho); must be < 1 to stay an R-function


@njit(cache=True)
def _r0_loop(f1, f2, cc, out):
    for i in range(out.shape[0]):
        out[i] = rk.compress(rk.r0_and(f1[i], f2[i]), cc)


@njit(cache=True)
def _sardf_loop(f1, f2, k, cc, out):
    for i in range(out.shape[0]):
        out[i] = rk.compress(rk.sardf_and(f1[i], f2[i], k), cc)


@njit(cache=True)
def _compress_loop(f, cc, out):
    for i in range(out.shape[0]):
        out[i] = rk.compress(f[i], cc)


def _apply(loop, arrays: tuple, *params: float) -> np.ndarray:
    """``loop(*flat arrays, *params, out)`` over the float64 ``arrays`` broadcast together, as a
    ufunc would: compiled loops load from Numba's cache in milliseconds, where a ``vectorize``
    ufunc builds its wrapper again in every process (0.4 s for these three)."""
    arrays = tuple(np.asarray(a, np.float64) for a in arrays)
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    out = np.empty(shape)
    flat = [np.ascontiguousarray(a if a.shape == shape else np.broadcast_to(a, shape)).reshape(-1) for a in arrays]
    loop(*flat, *(float(p) for p in params), out.reshape(-1))
    return out


def compress(f: np.ndarray, scale: float) -> np.ndarray:
    """The identity for |f| <= scale, sign(f) scale (1 + ln(|f| / scale)) beyond (C1, increasing)."""
    if not np.isfinite(scale):
        return f
    return _apply(_compress_loop, (f,), scale)


def r_and(f1: np.ndarray, f2: np.ndarray, family: str = "r0", k: float = SARDF_K,
          scale: float = np.inf) -> np.ndarray:
    """R-conjunction (intersection) of two fields (float64); ``scale``: see :func:`compress`.
    r0 is written without cancellation (the conjugate form 2 f1 f2 / (f1 + f2 + rho) where
    f1 + f2 > 0: the naive form loses the sign when the arguments differ by many orders of
    magnitude, as deep BSP trees produce); sardf is min itself outside its window."""
    if family == "min_max":
        return np.minimum(f1, f2)
    if family == "r0":
        return _apply(_r0_loop, (f1, f2), scale)
    if family == "sardf":
        return _apply(_sardf_loop, (f1, f2), k, scale)
    raise ValueError(f"unknown R-function family {family!r}")


def r_or(f1: np.ndarray, f2: np.ndarray, family: str = "r0", k: float = SARDF_K,
         scale: float = np.inf) -> np.ndarray:
    """R-disjunction (union) of two fields: -(-f1 AND -f2), which is exact for all three families."""
    return -r_and(-f1, -f2, family, k, scale)


def r_not(f: np.ndarray) -> np.ndarray:
    """Complement."""
    return -f
