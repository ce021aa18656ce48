"""Revised affine arithmetic over the compiled tape (issue 13): affine bounds of boxes in Numba.

The components stage bounds boxes with revised affine arithmetic (RAA), components seed
(../shared/seeds/component-detection-and-separation.txt), section 3.1 eq. 2:

    x^ = x0 + x1 e1 + x2 e2 + x3 e3 + ex [-1, 1],   ex >= 0,   ei in [-1, 1],

one noise symbol per coordinate and one accumulated error term. :mod:`pipeline.field.affine` does it
in NumPy, node by node through each node's formula (``model.bound``); this module runs the same
rules over the model's tape (:func:`pipeline.model.tape.compile_model`), one clause loop per box:
:func:`affine_bounds` is ``model.bound`` for a traced model.

Every clause is a form (c, g0, g1, g2, e), computed op by op as pipeline/field/affine.py does:
affine operations exact (ADD, SUB, NEG, the immediates ADDC, MULC, RSUBC, DIVC = a * (1/c),
RDIVC = c * (1/a)); the revised product with the diagonal terms e_i^2 in [0, 1] folded in
(MUL, SQR); Chebyshev approximations for the convex / concave ones (SQRT, EXP, LOG, the
reciprocal of DIV / RDIVC, real powers); integer powers (sqr, repeated Chebyshev or the
monotone range across 0, reciprocals of them); |x| (exact one-sided, Chebyshev across 0);
min / max as (a + b -/+ |a - b|) / 2; sin / cos the narrower of the first-order Taylor form and
the exact range. The R-functions as pipeline/model/ops.py bounds them: R0AND is
a + b - sqrt(sqr(a) + sqr(b)) cut to the monotone hull [r0(a_lo, b_lo), r0(a_hi, b_hi)] where
that is narrower (ops._monotone_hull); SARDFAND is min(a, b) widened down by k rho / 4
(ops._sardf_and_bound); COMPRESS is the form where its range lies within +-scale, else the
interval of the compressed ends (ops.compress_form). A mesh clause (BSP) is the interval of its
BSP-tree over the box of its coordinate forms (as tape._bound_bsp, from the clause's own start
node), as a form with no correlation (AffineForm.from_interval).

Rounding: every operation adds affine._ROUND times the result's magnitude to its error term,
as affine.py does; beyond affine.py, the coordinate forms, the forms made from intervals and the
SARDF widening get that allowance too, and the final interval is rounded outwards, so the
inclusion property survives floating point. Non-finite values: a form whose centre or slopes are
not finite, or whose error is NaN, becomes the unbounded form (0, 0, 0, 0, inf), never a NaN that
would hide a bound; an unbounded operand makes every non-constant result unbounded.

Numba cache: the kernels call bsp_minmax.box_bound and rkernels.r0_and and rkernels.compress (all in
pipeline.KERNEL_PROVIDERS) and nothing compiled of pipeline.model.tape. The opcodes are this module's
own constants, checked against pipeline.model.tape's at import: a renumbering there fails loudly
instead of leaving stale machine code in the cache.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from pipeline.field.rkernels import compress, r0_and
from pipeline.mesh.bsp_minmax import box_bound
from pipeline.model import tape as _tp
from pipeline.util.jit import njit

# --- opcodes (pipeline.model.tape's; checked below) --------------------------------------------------------
X, Y, Z, CONST, ADD, SUB, MUL, DIV, NEG, SQRT, SQR, ABS, EXP, LOG, SIN, COS, POWC, MIN, MAX, R0AND, \
    SARDFAND, COMPRESS, BSPXY, BSP, ADDC, MULC, RSUBC, DIVC, RDIVC = range(29)
_MINE = dict(zip(_tp.NAMES, range(29), strict=True))
if len(_tp.NAMES) != 29 or any(getattr(_tp, name.upper()) != code for name, code in _MINE.items()):
    raise ImportError("pipeline.model.tape's opcodes changed: update pipeline/model/tape_affine.py to match")

_EPS = 2.220446049250313e-16
_ROUND = 8.0 * _EPS  # affine._ROUND: relative rounding allowance per operation
_TINY = 1e-300  # affine._TINY
_INF = math.inf
_HALF_PI = 0.5 * math.pi
_TWO_PI = 2.0 * math.pi

# Chebyshev kinds
_K_SQRT, _K_EXP, _K_LOG, _K_RECIP, _K_RPOW, _K_IPOW = range(6)

# IEEE division (x / 0 is inf or NaN, never an exception): every result is checked by _sound
_jit = njit  # pipeline.util.jit: NumPy's error model is the default


# --- form helpers (a form is the tuple (c, g0, g1, g2, e)) ---------------------------------------------


@_jit()
def _unbounded():
    return 0.0, 0.0, 0.0, 0.0, _INF


@_jit()
def _gsum(g0, g1, g2):
    return (abs(g0) + abs(g1)) + abs(g2)


@_jit()
def _radius(g0, g1, g2, e):
    return _gsum(g0, g1, g2) + e


@_jit()
def _new(c, g0, g1, g2, e):
    """affine.AffineForm._new: the rounding allowance of one operation added to the error."""
    mag = (abs(c) + _gsum(g0, g1, g2)) + e
    return c, g0, g1, g2, e + _ROUND * mag


@_jit()
def _smul(a, b):
    """Product of non-negative magnitudes with 0 * inf = 0 (affine._smul)."""
    return 0.0 if a == 0.0 or b == 0.0 else a * b


@_jit()
def _sound(c, g0, g1, g2, e):
    """The form itself, or the unbounded form where a centre or slope is not finite or e is NaN."""
    if math.isfinite(c) and math.isfinite(g0) and math.isfinite(g1) and math.isfinite(g2) and e == e:
        return c, g0, g1, g2, e
    return _unbounded()


@_jit()
def _from_interval(lo, hi):
    """AffineForm.from_interval, plus the rounding of the centre and radius."""
    c = 0.5 * (lo + hi)
    e = 0.5 * (hi - lo)
    if not math.isfinite(c) or not math.isfinite(e):
        return _unbounded()
    return c, 0.0, 0.0, 0.0, e + _ROUND * (abs(c) + e)


@_jit()
def _add(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4):
    return _new(a0 + b0, a1 + b1, a2 + b2, a3 + b3, a4 + b4)


@_jit()
def _sub(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4):
    """a + (-b), as AffineForm.__sub__."""
    return _new(a0 + (-b0), a1 + (-b1), a2 + (-b2), a3 + (-b3), a4 + b4)


@_jit()
def _scale(a0, a1, a2, a3, a4, k):
    """form * scalar (AffineForm.__mul__ with a number)."""
    return _new(a0 * k, a1 * k, a2 * k, a3 * k, _smul(a4, abs(k)))


@_jit()
def _mul(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4):
    """affine.mul: the revised product, diagonal terms g_ai g_bi e_i^2 half to the centre."""
    d1, d2, d3 = a1 * b1, a2 * b2, a3 * b3
    ra = _radius(a1, a2, a3, a4)
    rb = _radius(b1, b2, b3, b4)
    c = a0 * b0 + 0.5 * ((d1 + d2) + d3)
    e = _smul(abs(a0), b4) + _smul(abs(b0), a4) + _smul(ra, rb) - 0.5 * _gsum(d1, d2, d3)
    return _new(c, a0 * b1 + b0 * a1, a0 * b2 + b0 * a2, a0 * b3 + b0 * a3, max(e, 0.0))


@_jit()
def _sqr(a0, a1, a2, a3, a4):
    """affine.sqr."""
    s = (a1 * a1 + a2 * a2) + a3 * a3
    r = _radius(a1, a2, a3, a4)
    c = a0 * a0 + 0.5 * s
    e = _smul(2.0 * abs(a0), a4) + _smul(r, r) - 0.5 * s
    return _new(c, 2.0 * a0 * a1, 2.0 * a0 * a2, 2.0 * a0 * a3, max(e, 0.0))


@_jit()
def _linear(a0, a1, a2, a3, a4, alpha, zeta, delta):
    """affine._linear: alpha * a + zeta +- delta (unbounded where any of them is not finite)."""
    if not (math.isfinite(alpha) and math.isfinite(zeta) and math.isfinite(delta)):
        return _unbounded()
    c = alpha * a0 + zeta
    e = _smul(abs(alpha), a4) + abs(delta)
    return _new(c, alpha * a1, alpha * a2, alpha * a3, e)


@_jit()
def _from_range(rlo, rhi):
    """affine.from_range: the range of f over the form's interval, no correlation."""
    return _linear(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5 * (rlo + rhi), 0.5 * (rhi - rlo))


@_jit()
def _pw(x, p):
    """x ** p for x >= 0 with 0 ** (p < 0) = inf (np.power's result)."""
    if x == 0.0 and p < 0.0:
        return _INF
    return x ** p


@_jit()
def _f(kind, x, p):
    if kind == _K_SQRT:
        return math.sqrt(x) if x >= 0.0 else math.nan
    if kind == _K_EXP:
        return math.exp(x) if x < 709.7 else _INF
    if kind == _K_LOG:
        return math.log(x) if x > 0.0 else (-_INF if x == 0.0 else math.nan)
    if kind == _K_RECIP:
        return 1.0 / x
    if kind == _K_RPOW:
        return _pw(x, p) if x >= 0.0 else math.nan
    return x ** p  # _K_IPOW: p an integer >= 3


@_jit()
def _finv(kind, al, p, lo, hi):
    """The point u with f'(u) = al (the Chebyshev tangent point, before clipping)."""
    if kind == _K_SQRT:
        return 0.25 / (al * al)
    if kind == _K_EXP:
        return math.log(max(al, _TINY))
    if kind == _K_LOG:
        return 1.0 / al
    if kind == _K_RECIP:
        s = -1.0 / al
        r = math.sqrt(s) if s >= 0.0 else math.nan
        return -r if hi < 0.0 else r
    if kind == _K_RPOW:
        return _pw(max(al / p, _TINY), 1.0 / (p - 1.0))
    root = _pw(abs(al) / p, 1.0 / (p - 1.0))
    if hi <= 0.0:
        return -root
    if lo >= 0.0:
        return root
    return root if al > 0.0 else (-root if al < 0.0 else 0.0)


@_jit()
def _chebyshev(a0, a1, a2, a3, a4, lo, hi, kind, p):
    """affine.chebyshev: the secant slope and the tangent point's deviation, for a function
    convex or concave on [lo, hi]."""
    width = hi - lo
    flo = _f(kind, lo, p)
    fhi = _f(kind, hi, p)
    alpha = (fhi - flo) / width if width > 0.0 else 0.0
    u = lo
    if width > 0.0:
        u = _finv(kind, alpha, p, lo, hi)
        if u == u:
            u = min(max(u, lo), hi)
    d1 = flo - alpha * lo
    d2 = _f(kind, u, p) - alpha * u
    zeta = 0.5 * (d1 + d2)
    delta = 0.5 * abs(d1 - d2) + _ROUND * (abs(d1) + abs(d2))
    return _linear(a0, a1, a2, a3, a4, alpha, zeta, delta)


@_jit()
def _interval(a0, a1, a2, a3, a4):
    r = _radius(a1, a2, a3, a4)
    return a0 - r, a0 + r


@_jit()
def _sqrt(a0, a1, a2, a3, a4):
    lo, hi = _interval(a0, a1, a2, a3, a4)
    lo = max(lo, 0.0)
    hi = max(hi, lo)
    return _chebyshev(a0, a1, a2, a3, a4, lo, hi, _K_SQRT, 0.0)


@_jit()
def _exp(a0, a1, a2, a3, a4):
    lo, hi = _interval(a0, a1, a2, a3, a4)
    return _chebyshev(a0, a1, a2, a3, a4, lo, hi, _K_EXP, 0.0)


@_jit()
def _log(a0, a1, a2, a3, a4):
    lo, hi = _interval(a0, a1, a2, a3, a4)
    if not lo > 0.0:  # unbounded below (affine.log's range (-inf, log hi])
        return _unbounded()
    return _chebyshev(a0, a1, a2, a3, a4, lo, hi, _K_LOG, 0.0)


@_jit()
def _recip(a0, a1, a2, a3, a4):
    lo, hi = _interval(a0, a1, a2, a3, a4)
    if not (lo > 0.0 or hi < 0.0):
        return _unbounded()
    return _chebyshev(a0, a1, a2, a3, a4, lo, hi, _K_RECIP, 0.0)


@_jit()
def _int_power(a0, a1, a2, a3, a4, n):
    """affine._int_power, n >= 3."""
    lo, hi = _interval(a0, a1, a2, a3, a4)
    if lo >= 0.0 or (hi <= 0.0 and n % 2 == 1) or n % 2 == 0:
        return _chebyshev(a0, a1, a2, a3, a4, lo, hi, _K_IPOW, float(n))
    return _from_range(lo ** float(n), hi ** float(n))  # odd n across 0: monotone


@_jit()
def _power(a0, a1, a2, a3, a4, p):
    """affine.power: integer p by the exact rules, real p for x >= 0 (Chebyshev)."""
    if p == np.floor(p) and abs(p) < 2.0 ** 62:
        n = int(p)
        m = abs(n)
        if m == 0:
            return 1.0, 0.0, 0.0, 0.0, 0.0
        if m == 1:
            f = (a0, a1, a2, a3, a4)
        elif m == 2:
            f = _sqr(a0, a1, a2, a3, a4)
        else:
            f = _int_power(a0, a1, a2, a3, a4, m)
        f = _sound(*f)
        if n < 0:
            return _recip(*f)
        return f
    lo, hi = _interval(a0, a1, a2, a3, a4)
    if not math.isfinite(p) or (p == np.floor(p) and lo < 0.0):  # an integer beyond int64: x < 0 is defined
        return _unbounded()
    lo = max(lo, 0.0)
    hi = max(hi, lo)
    return _chebyshev(a0, a1, a2, a3, a4, lo, hi, _K_RPOW, p)


@_jit()
def _absolute(a0, a1, a2, a3, a4):
    """affine.absolute: exact one-sided, Chebyshev (kink at 0) across 0."""
    lo, hi = _interval(a0, a1, a2, a3, a4)
    if lo >= 0.0:
        return a0, a1, a2, a3, a4
    if hi <= 0.0:
        return -a0, -a1, -a2, -a3, a4
    width = hi - lo if hi > lo else 1.0
    alpha = (hi + lo) / width
    d1 = -lo - alpha * lo
    return _linear(a0, a1, a2, a3, a4, alpha, 0.5 * d1, 0.5 * abs(d1))


@_jit()
def _minmax(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4, sign):
    """affine.minimum (sign -1) / maximum (+1): 0.5 * (a + b -/+ |a - b|)."""
    s = _add(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4)
    d = _sub(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4)
    ab = _sound(*_absolute(*_sound(*d)))
    s = _sound(*s)
    t = _sub(*s, *ab) if sign < 0 else _add(*s, *ab)
    return _scale(*_sound(*t), 0.5)


@_jit()
def _trig_range(lo, hi, cosine):
    """affine._trig_range: the exact range of sin (peak phase pi/2) or cos (0) over [lo, hi]."""
    if cosine:
        flo, fhi, peak = math.cos(lo), math.cos(hi), 0.0
    else:
        flo, fhi, peak = math.sin(lo), math.sin(hi), _HALF_PI
    rlo, rhi = min(flo, fhi), max(flo, fhi)
    wide = (hi - lo) >= _TWO_PI or not (math.isfinite(lo) and math.isfinite(hi))
    kmax = np.ceil((lo - peak) / _TWO_PI)
    kmin = np.ceil((lo - peak - math.pi) / _TWO_PI)
    if wide or peak + _TWO_PI * kmax <= hi:
        rhi = 1.0
    if wide or peak + math.pi + _TWO_PI * kmin <= hi:
        rlo = -1.0
    return rlo, rhi


@_jit()
def _trig(a0, a1, a2, a3, a4, cosine):
    """affine._trig: the first-order Taylor form (remainder r^2 / 2) or the exact range,
    whichever has the smaller radius."""
    r = _radius(a1, a2, a3, a4)
    if cosine:
        fc, alpha = math.cos(a0), -math.sin(a0)
    else:
        fc, alpha = math.sin(a0), math.cos(a0)
    t = _sound(*_linear(a0, a1, a2, a3, a4, alpha, fc - alpha * a0, 0.5 * r * r))
    rlo, rhi = _trig_range(a0 - r, a0 + r, cosine)
    g = _sound(*_from_range(rlo, rhi))
    if _radius(g[1], g[2], g[3], g[4]) < _radius(t[1], t[2], t[3], t[4]):
        return g
    return t


@_jit()
def _r0and(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4):
    """ops.r_and's r0 form: a + b - sqrt(sqr(a) + sqr(b)), then ops._monotone_hull."""
    s = _sound(*_add(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4))
    q = _sound(*_add(*_sound(*_sqr(a0, a1, a2, a3, a4)), *_sound(*_sqr(b0, b1, b2, b3, b4))))
    r = _sound(*_sub(*s, *_sound(*_sqrt(*q))))
    alo, ahi = _interval(a0, a1, a2, a3, a4)
    blo, bhi = _interval(b0, b1, b2, b3, b4)
    lo = r0_and(alo, blo)
    hi = r0_and(ahi, bhi)
    if lo != lo:
        lo = -_INF
    if hi != hi:
        hi = _INF
    pad = _ROUND * (((abs(alo) + abs(blo)) + abs(ahi)) + abs(bhi))
    rlo, rhi = _interval(*r)
    lo, hi = max(lo - pad, rlo), min(hi + pad, rhi)
    if (hi - lo) < (rhi - rlo):
        return _from_interval(min(lo, hi), hi)
    return r


@_jit()
def _sardf(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4, k):
    """ops._sardf_and_bound: min(a, b) widened down by k rho / 4, rho <= |a| + |b|."""
    m0, m1, m2, m3, m4 = _sound(*_minmax(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4, -1))
    alo, ahi = _interval(a0, a1, a2, a3, a4)
    blo, bhi = _interval(b0, b1, b2, b3, b4)
    rho_hi = max(abs(alo), abs(ahi)) + max(abs(blo), abs(bhi))
    drop = 0.25 * k * rho_hi
    return _new(m0 - 0.5 * drop, m1, m2, m3, m4 + 0.5 * drop)


@_jit()
def _compress_form(r0, r1, r2, r3, r4, scale):
    """ops.compress_form: the form where its range lies within +-scale, else the interval of
    the compressed ends (compress is increasing), widened by 1e-12 for rounding."""
    if not math.isfinite(scale):
        return r0, r1, r2, r3, r4
    lo, hi = _interval(r0, r1, r2, r3, r4)
    if not (lo < -scale or hi > scale):
        return r0, r1, r2, r3, r4
    clo = compress(lo, scale) * (1.0 + math.copysign(1e-12, -lo))
    chi = compress(hi, scale) * (1.0 + math.copysign(1e-12, hi))
    if clo != clo:
        clo = -_INF
    if chi != chi:
        chi = _INF
    return _from_interval(clo, chi)


@_jit()
def _down(v):
    return v - abs(v) * (4.0 * _EPS) - _TINY if v == v else -_INF


@_jit()
def _up(v):
    return v + abs(v) * (4.0 * _EPS) + _TINY if v == v else _INF


@_jit()
def _bsp(F, k, a, b, c, orc, sj, sv):
    """Mesh clause k: the interval of its BSP-tree (from the clause's start node) over the box of
    its coordinate forms' intervals (tape._bound_bsp), as a form with no correlation."""
    ia, ib = a[k], b[k]
    xa, ya = a[ia], b[ia]
    lo0, hi0 = _interval(F[xa, 0], F[xa, 1], F[xa, 2], F[xa, 3], F[xa, 4])
    lo1, hi1 = _interval(F[ya, 0], F[ya, 1], F[ya, 2], F[ya, 3], F[ya, 4])
    lo2, hi2 = _interval(F[ib, 0], F[ib, 1], F[ib, 2], F[ib, 3], F[ib, 4])
    if not (math.isfinite(lo0) and math.isfinite(hi0) and math.isfinite(lo1) and math.isfinite(hi1)
            and math.isfinite(lo2) and math.isfinite(hi2)):
        return _unbounded()
    pad = 1e-14 * (1.0 + max(max(abs(lo0), abs(hi0)), max(max(abs(lo1), abs(hi1)), max(abs(lo2), abs(hi2)))))
    flo, fhi, _ = box_bound(lo0, lo1, lo2, hi0, hi1, hi2, np.int64(c[k]), orc[0], orc[1], orc[2], orc[3], orc[4],
                            pad, sj, sv)
    return _from_interval(_down(flo), _up(fhi))


# inlined (as _form_box): a call per clause and box passed the arrays and the 5-tuple through memory;
# inlined, the affine pass of the demo takes 0.21 s instead of 0.36 s on 400k boxes (the same bits)
@_jit(inline="always")
def _clause(o, F, k, a, b, c):
    """The form of (non-leaf, non-mesh) clause k from its operands' forms in F."""
    ia, ib, ck = a[k], b[k], c[k]
    a0, a1, a2, a3, a4 = F[ia, 0], F[ia, 1], F[ia, 2], F[ia, 3], F[ia, 4]
    if ib >= 0:
        b0, b1, b2, b3, b4 = F[ib, 0], F[ib, 1], F[ib, 2], F[ib, 3], F[ib, 4]
    else:
        b0 = b1 = b2 = b3 = b4 = 0.0
    if o == ADD:
        return _add(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4)
    if o == SUB:
        return _sub(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4)
    if o == MUL:
        return _mul(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4)
    if o == DIV:
        return _mul(a0, a1, a2, a3, a4, *_sound(*_recip(b0, b1, b2, b3, b4)))
    if o == ADDC:
        return _new(a0 + ck, a1, a2, a3, a4)
    if o == MULC:
        return _scale(a0, a1, a2, a3, a4, ck)
    if o == RSUBC:
        return _new(-a0 + ck, -a1, -a2, -a3, a4)
    if o == DIVC:
        if ck == 0.0:
            return _unbounded()
        return _scale(a0, a1, a2, a3, a4, 1.0 / ck)
    if o == RDIVC:
        return _scale(*_sound(*_recip(a0, a1, a2, a3, a4)), ck)
    if o == NEG:
        return -a0, -a1, -a2, -a3, a4
    if o == SQRT:
        return _sqrt(a0, a1, a2, a3, a4)
    if o == SQR:
        return _sqr(a0, a1, a2, a3, a4)
    if o == ABS:
        return _absolute(a0, a1, a2, a3, a4)
    if o == EXP:
        return _exp(a0, a1, a2, a3, a4)
    if o == LOG:
        return _log(a0, a1, a2, a3, a4)
    if o == SIN:
        return _trig(a0, a1, a2, a3, a4, False)
    if o == COS:
        return _trig(a0, a1, a2, a3, a4, True)
    if o == POWC:
        return _power(a0, a1, a2, a3, a4, ck)
    if o == MIN:
        return _minmax(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4, -1)
    if o == MAX:
        return _minmax(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4, 1)
    if o == R0AND:
        return _r0and(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4)
    if o == SARDFAND:
        return _sardf(a0, a1, a2, a3, a4, b0, b1, b2, b3, b4, ck)
    if o == COMPRESS:
        return _compress_form(a0, a1, a2, a3, a4, ck)
    return _unbounded()  # an opcode this module does not know: no bound


@_jit(inline="always")
def _form_box(lo, hi, op, a, b, c, F, orc, sj, sv):
    """Every clause's form over the box lo..hi (3,) into F (len(op), 5)."""
    for k in range(op.shape[0]):
        o = op[k]
        if o <= Z:  # X, Y, Z
            d = 0 if o == X else (1 if o == Y else 2)
            mid = 0.5 * (lo[d] + hi[d])
            half = 0.5 * (hi[d] - lo[d])
            # AffineForm.coordinates, plus the rounding of mid and half
            f = _sound(mid, half if d == 0 else 0.0, half if d == 1 else 0.0, half if d == 2 else 0.0,
                       2.0 * _EPS * (abs(mid) + half))
        elif o == CONST:
            f = _sound(c[k], 0.0, 0.0, 0.0, 0.0)
        elif o == BSPXY:  # carries the mesh clause's operands only
            f = (0.0, 0.0, 0.0, 0.0, 0.0)
        elif o == BSP:
            f = _sound(*_bsp(F, k, a, b, c, orc, sj, sv))
        else:
            f = _sound(*_clause(o, F, k, a, b, c))
        F[k, 0], F[k, 1], F[k, 2], F[k, 3], F[k, 4] = f


@_jit(parallel=True)
def _affine_pass(lo, hi, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen):
    """(flo, fhi) of box q's tape (tape_of[q], into start/length/res) over lo[q]..hi[q]; boxes
    in chunks of 64 per task (one per task when there are few: the top levels of a descent,
    whose tapes are long), the (maxlen, 5) forms and the mesh walk's stacks allocated once per
    chunk."""
    n = lo.shape[0]
    flo = np.empty(n)
    fhi = np.empty(n)
    per = 64 if n >= 1024 else 1
    for ch in prange((n + per - 1) // per):
        F = np.empty((max(maxlen, 1), 5))
        sj = np.empty((3, odepth + 2), np.int64)
        sv = np.empty((4, odepth + 2))
        for q in range(ch * per, min(n, (ch + 1) * per)):
            tp = tape_of[q]
            s, e, r = start[tp], start[tp] + length[tp], res[tp]
            _form_box(lo[q], hi[q], op[s:e], a[s:e], b[s:e], c[s:e], F, orc, sj, sv)
            rad = _radius(F[r, 1], F[r, 2], F[r, 3], F[r, 4])
            flo[q] = _down(F[r, 0] - rad)
            fhi[q] = _up(F[r, 0] + rad)
    return flo, fhi


@_jit()
def _forms_one(lo, hi, op, a, b, c, orc, odepth):
    """Every clause's form over one box (debugging and tests)."""
    F = np.empty((max(op.shape[0], 1), 5))
    sj = np.empty((3, odepth + 2), np.int64)
    sv = np.empty((4, odepth + 2))
    _form_box(lo, hi, op, a, b, c, F, orc, sj, sv)
    return F


def affine_bounds(tape: _tp.Tape | _tp.TapePool, lo: np.ndarray, hi: np.ndarray,
                  tape_of: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rigorous (flo, fhi) of the field over each box lo..hi (B, 3) by revised affine
    arithmetic: ``model.bound(lo, hi, t)`` for ``tape = compile_model(model, t)``; or, for a
    pool of tapes (a descent's cells, :class:`pipeline.model.tape.TapePool`), of box q's tape
    ``tape_of[q]`` (None: tape 0).

    Memory: the two (B,) results and the forms of one chunk of 64 boxes per thread (the longest
    tape x 5 floats), whatever B is."""
    lo = np.ascontiguousarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.ascontiguousarray(hi, dtype=np.float64).reshape(-1, 3)
    if lo.shape != hi.shape:
        raise ValueError(f"lo {lo.shape} and hi {hi.shape} differ")
    pool = tape if isinstance(tape, _tp.TapePool) else _tp.TapePool.single(tape)
    tape_of = np.zeros(len(lo), np.int64) if tape_of is None else np.ascontiguousarray(tape_of, dtype=np.int64)
    orc, depth = pool.oracle.arrays()
    return _affine_pass(lo, hi, tape_of, *pool.arrays(), orc, depth, max(pool.max_length, 1))


def clause_forms(tape: _tp.Tape, lo, hi) -> np.ndarray:
    """(len(tape), 5) forms (c, g0, g1, g2, e) of every clause over one box (for tests)."""
    lo = np.ascontiguousarray(lo, dtype=np.float64).reshape(3)
    hi = np.ascontiguousarray(hi, dtype=np.float64).reshape(3)
    orc, depth = tape.oracle.arrays()
    return _forms_one(lo, hi, tape.op, tape.a, tape.b, tape.c, orc, depth)
