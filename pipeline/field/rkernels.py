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
    """f1 + f2 - sqrt(f1^2 + f2^2) (R0 conjunction, eq. 2): :func:`r0_and_rho` with rho =
    hypot(f1, f2), which neither overflows nor underflows."""
    return r0_and_rho(f1, f2, math.hypot(f1, f2))


@njit(cache=True, inline="always")
def r0_and_rho(f1, f2, rho):
    """Eq. 2 given rho = sqrt(f1^2 + f2^2), in the conjugate form 2 f1 f2 / (f1 + f2 + rho) where
    f1 + f2 > 0 (no cancellation), evaluated as 2 f1 (f2 / (f1 + f2 + rho)) so that the product of
    two tiny values does not underflow to 0 (which would put two inside points on the surface)."""
    s = f1 + f2
    return 2.0 * f1 * (f2 / (s + rho)) if s > 0 else s - rho


@njit(cache=True, inline="always")
def sardf_and(f1, f2, k):
    """SARDF conjunction: min(f1, f2) outside the blending window |f1 - f2| < k rho, the
    smoothed form inside it, as rfunctions.r_and(..., "sardf")."""
    return sardf_and_rho(f1, f2, k, math.hypot(f1, f2))


@njit(cache=True, inline="always")
def sardf_and_rho(f1, f2, k, rho):
    """:func:`sardf_and` given rho = sqrt(f1^2 + f2^2)."""
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


SAFE_SQ_LO, SAFE_SQ_HI = 1e-290, 1e290  # f1^2 + f2^2 in this range: sqrt of it is hypot to rounding


@njit(cache=True)
def and_rows(a, sa, b, sb, so, out, n, fam, k, cc):
    """out[:n] = so * r_and(sa * a, sb * b) for signs sa, sb, so = +-1 (so r_or(x, y) is
    ``and_rows(x, -1, y, -1, -1, ...)``): the row form of :func:`r_and` that LLVM vectorises.

    rho is sqrt(f1^2 + f2^2), which vectorises where math.hypot (a library call) does not; a
    row with a sum of squares outside [SAFE_SQ_LO, SAFE_SQ_HI] (overflow or lost digits) or
    with a result beyond the magnitude control ``cc`` is finished by a scalar pass (hypot, then
    :func:`compress`), so the values are r_and's to rounding for every input. The flags are
    integer ORs: a float max-reduction would keep the loop scalar."""
    if fam == MIN_MAX:
        for i in range(n):
            out[i] = so * min(sa * a[i], sb * b[i])
        return
    flag = 0
    if fam == R0:
        for i in range(n):
            f1 = sa * a[i]
            f2 = sb * b[i]
            q = f1 * f1 + f2 * f2
            v = r0_and_rho(f1, f2, math.sqrt(q))
            out[i] = so * v
            flag |= (q > SAFE_SQ_HI) | (q < SAFE_SQ_LO) | (abs(v) > cc)
    else:
        for i in range(n):
            f1 = sa * a[i]
            f2 = sb * b[i]
            q = f1 * f1 + f2 * f2
            v = sardf_and_rho(f1, f2, k, math.sqrt(q))
            out[i] = so * v
            flag |= (q > SAFE_SQ_HI) | (q < SAFE_SQ_LO) | (abs(v) > cc)
    if flag:  # rare lanes: sums of squares out of range (hypot), magnitudes beyond cc (compress)
        for i in range(n):
            f1 = sa * a[i]
            f2 = sb * b[i]
            q = f1 * f1 + f2 * f2
            if q > SAFE_SQ_HI or q < SAFE_SQ_LO:
                out[i] = so * (r0_and(f1, f2) if fam == R0 else sardf_and(f1, f2, k))
            out[i] = compress(out[i], cc)
