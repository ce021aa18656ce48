"""The R-functions and the compression, written once, as compiled scalar functions (Numba):
the formulas of pipeline.field.rfunctions (which documents them and applies them to arrays as
compiled loops over arrays).

Used by the tape's clause arithmetic (pipeline.model.tape, tape_affine), the BSP-field of a mesh
(pipeline.mesh.bsp), the separated pieces of the components stage and, through rfunctions, every
NumPy caller. In a module of its own so that the Numba cache is keyed by it
(pipeline.KERNEL_PROVIDERS): a kernel that inlines one of these keeps its machine code only
while this file is unchanged.
"""

from __future__ import annotations

import math

from pipeline.util.jit import njit


@njit(cache=True, inline="always")
def r0_and(f1, f2):
    """f1 + f2 - sqrt(f1^2 + f2^2) (R0 conjunction, eq. 2), in the conjugate form
    2 f1 f2 / (f1 + f2 + rho) where f1 + f2 > 0 (no cancellation), evaluated as
    2 f1 (f2 / (f1 + f2 + rho)) so that the product of two tiny values does not underflow to 0
    (which would put two inside points on the surface)."""
    s = f1 + f2
    rho = math.hypot(f1, f2)
    return 2.0 * f1 * (f2 / (s + rho)) if s > 0 else s - rho


@njit(cache=True, inline="always")
def sardf_and(f1, f2, k):
    """SARDF conjunction: min(f1, f2) outside the blending window |f1 - f2| < k rho, the
    smoothed form inside it, as rfunctions.r_and(..., "sardf")."""
    rho = math.hypot(f1, f2)
    u = f1 - f2
    w = k * rho
    if abs(u) >= w:
        return min(f1, f2)
    return 0.5 * (f1 + f2 - (u * u + w * w) / (2.0 * w))


@njit(cache=True, inline="always")
def compress(f, cc):
    """The scalar form of rfunctions.compress: f for |f| <= cc, sign(f) cc (1 + ln(|f| / cc)) beyond."""
    a = abs(f)
    if not a > cc:
        return f
    r = cc * (1.0 + math.log(a / cc))
    return r if f > 0 else -r


MIN_MAX, R0, SARDF = 0, 1, 2  # family codes, in the order of rfunctions.FAMILIES


@njit(cache=True, inline="always")
def r_and(f1, f2, fam, k, cc):
    """R-conjunction of family ``fam`` (MIN_MAX, R0, SARDF) with the magnitude control ``cc``
    of r0 and sardf (inf: none); min_max is min itself."""
    if fam == MIN_MAX:
        return min(f1, f2)
    if fam == R0:
        return compress(r0_and(f1, f2), cc)
    return compress(sardf_and(f1, f2, k), cc)


@njit(cache=True, inline="always")
def r_or(f1, f2, fam, k, cc):
    """R-disjunction -(-f1 AND -f2)."""
    return -r_and(-f1, -f2, fam, k, cc)
