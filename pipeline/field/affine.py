"""Revised affine arithmetic over arrays of boxes.

components seed, section 3.1 eq. 2: a revised affine form keeps a fixed number of noise
symbols - one per coordinate - plus one accumulated error term:

    x^ = x0 + x1 e1 + x2 e2 + x3 e3 + ex [-1, 1],   ex >= 0,   ei in [-1, 1].

`AffineForm` holds these coefficients as NumPy arrays over B boxes, so one call bounds
thousands of boxes. Affine operations (+, -, scalar *) are exact. Non-affine operations use
Chebyshev (for convex or concave functions) or min-range approximations with a rigorous
error term (de Figueiredo & Stolfi 2004, the components seed's [15, 16]); the product uses
the revised rule with the diagonal terms e_i^2 in [0, 1] folded in. Every operation adds a
rounding allowance to the error term so the inclusion property survives floating point.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

_ROUND = 8.0 * np.finfo(np.float64).eps  # relative rounding allowance per operation
_TINY = 1e-300


class AffineForm:
    """x0 + sum_i g_i e_i + e [-1, 1] for B boxes: ``c`` (B,), ``g`` (3,B), ``e`` (B,) >= 0."""

    __slots__ = ("c", "g", "e")
    __array_ufunc__ = None  # ndarray (op) AffineForm defers to our reflected operators

    def __init__(self, c: np.ndarray, g: np.ndarray, e: np.ndarray):
        self.c = c
        self.g = g
        self.e = e

    # --- construction ---------------------------------------------------------------------
    @classmethod
    def coordinates(cls, lo: np.ndarray, hi: np.ndarray) -> tuple[AffineForm, AffineForm, AffineForm]:
        """Affine forms of x, y, z over boxes lo..hi (B,3): x^ = mid + half * e1 (section 3.2)."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        mid = 0.5 * (lo + hi)
        half = 0.5 * (hi - lo)
        B = lo.shape[0]
        forms = []
        for axis in range(3):
            g = np.zeros((3, B))
            g[axis] = half[:, axis]
            forms.append(cls(mid[:, axis].copy(), g, np.zeros(B)))
        return forms[0], forms[1], forms[2]

    @classmethod
    def from_interval(cls, lo: np.ndarray, hi: np.ndarray) -> AffineForm:
        """Form with no correlation: centre of the interval plus its radius as error."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        c = 0.5 * (lo + hi)
        e = 0.5 * (hi - lo)
        bad = ~np.isfinite(c)
        c = np.where(bad, 0.0, c)
        e = np.where(bad | ~np.isfinite(e), np.inf, e)
        return cls(c, np.zeros((3,) + c.shape), e)

    @classmethod
    def constant(cls, value: float, like: AffineForm) -> AffineForm:
        B = like.c.shape[0]
        return cls(np.full(B, float(value)), np.zeros((3, B)), np.zeros(B))

    # --- range ----------------------------------------------------------------------------
    @property
    def radius(self) -> np.ndarray:
        return np.abs(self.g).sum(axis=0) + self.e

    @property
    def lo(self) -> np.ndarray:
        return self.c - self.radius

    @property
    def hi(self) -> np.ndarray:
        return self.c + self.radius

    def interval(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.radius
        return self.c - r, self.c + r

    def __len__(self) -> int:
        return self.c.shape[0]

    def __repr__(self) -> str:  # pragma: no cover - debugging aid
        return f"AffineForm(B={len(self)}, lo={self.lo[:3]}, hi={self.hi[:3]})"

    # --- affine (exact) operations ---------------------------------------------------------
    def _new(self, c: np.ndarray, g: np.ndarray, e: np.ndarray) -> AffineForm:
        mag = np.abs(c) + np.abs(g).sum(axis=0) + e
        return AffineForm(c, g, e + _ROUND * mag)

    def __neg__(self) -> AffineForm:
        return AffineForm(-self.c, -self.g, self.e)

    def __pos__(self) -> AffineForm:
        return self

    def __add__(self, other) -> AffineForm:
        if isinstance(other, AffineForm):
            return self._new(self.c + other.c, self.g + other.g, self.e + other.e)
        return self._new(self.c + other, self.g, self.e)

    __radd__ = __add__

    def __sub__(self, other) -> AffineForm:
        return self + (-other)

    def __rsub__(self, other) -> AffineForm:
        return (-self) + other

    def __mul__(self, other) -> AffineForm:
        if isinstance(other, AffineForm):
            return mul(self, other)
        k = np.asarray(other, dtype=np.float64)
        return self._new(self.c * k, self.g * k, _smul(self.e, np.abs(k)))

    __rmul__ = __mul__

    def __truediv__(self, other) -> AffineForm:
        if isinstance(other, AffineForm):
            return mul(self, reciprocal(other))
        return self * (1.0 / np.asarray(other, dtype=np.float64))

    def __rtruediv__(self, other) -> AffineForm:
        return reciprocal(self) * other

    def __pow__(self, p) -> AffineForm:
        return power(self, p)


# --- non-affine operations ----------------------------------------------------------------


def _smul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product of non-negative magnitudes with 0 * inf = 0 (an exact zero times an unbounded
    term contributes nothing; without this the error term would become NaN)."""
    with np.errstate(invalid="ignore"):
        return np.where((a == 0) | (b == 0), 0.0, a * b)


def mul(a: AffineForm, b: AffineForm) -> AffineForm:
    """Revised AA product: diagonal terms g_ai g_bi e_i^2, e_i^2 in [0,1], go half to the centre."""
    diag = a.g * b.g
    ra, rb = a.radius, b.radius
    c = a.c * b.c + 0.5 * diag.sum(axis=0)
    g = a.c * b.g + b.c * a.g
    e = _smul(np.abs(a.c), b.e) + _smul(np.abs(b.c), a.e) + _smul(ra, rb) - 0.5 * np.abs(diag).sum(axis=0)
    return a._new(c, g, np.maximum(e, 0.0))


def sqr(a: AffineForm) -> AffineForm:
    """x^2 with the diagonal terms folded in (tighter than mul(a, a) by the revised rule)."""
    g2 = a.g * a.g
    r = a.radius
    c = a.c * a.c + 0.5 * g2.sum(axis=0)
    e = _smul(2.0 * np.abs(a.c), a.e) + _smul(r, r) - 0.5 * g2.sum(axis=0)
    return a._new(c, 2.0 * a.c * a.g, np.maximum(e, 0.0))


def _linear(a: AffineForm, alpha: np.ndarray, zeta: np.ndarray, delta: np.ndarray) -> AffineForm:
    """alpha * a + zeta +- delta (the result of every univariate approximation)."""
    alpha = np.where(np.isfinite(alpha), alpha, 0.0)
    bad = ~(np.isfinite(zeta) & np.isfinite(delta))
    c = alpha * a.c + np.where(bad, 0.0, zeta)
    e = _smul(np.abs(alpha), a.e) + np.where(bad, np.inf, np.abs(delta))
    return a._new(c, alpha * a.g, e)


def chebyshev(
    a: AffineForm,
    lo: np.ndarray,
    hi: np.ndarray,
    f: Callable[[np.ndarray], np.ndarray],
    fprime_inv: Callable[[np.ndarray], np.ndarray],
) -> AffineForm:
    """Chebyshev approximation of a function that is convex or concave on [lo, hi].

    alpha is the slope of the secant; the largest deviation of f from the secant is at u with
    f'(u) = alpha, so f(x) - alpha x lies between f(lo) - alpha lo and f(u) - alpha u.
    """
    width = hi - lo
    flo, fhi = f(lo), f(hi)
    with np.errstate(all="ignore"):
        alpha = np.where(width > 0, (fhi - flo) / np.where(width > 0, width, 1.0), 0.0)
        u = np.clip(fprime_inv(alpha), lo, hi)
        u = np.where(width > 0, u, lo)
        d1 = flo - alpha * lo
        d2 = f(u) - alpha * u
    zeta = 0.5 * (d1 + d2)
    delta = 0.5 * np.abs(d1 - d2) + _ROUND * (np.abs(d1) + np.abs(d2))
    return _linear(a, alpha, zeta, delta)


def from_range(a: AffineForm, rlo: np.ndarray, rhi: np.ndarray) -> AffineForm:
    """Interval fallback: the exact range [rlo, rhi] of f over the form's interval, no correlation.
    An infinite end gives the unbounded form (``_linear``: centre 0, error inf); the centre of
    [-inf, inf] is NaN on the way there, which is not an error."""
    zero = np.zeros_like(a.c)
    with np.errstate(invalid="ignore"):
        return _linear(a, zero, 0.5 * (rlo + rhi), 0.5 * (rhi - rlo))


def sqrt(a: AffineForm) -> AffineForm:
    """sqrt, concave. The form may dip below 0 by overestimation, but the true arguments are
    >= 0, so the Chebyshev line on [max(lo, 0), hi] still encloses sqrt at every true value."""
    lo, hi = a.interval()
    lo = np.maximum(lo, 0.0)
    hi = np.maximum(hi, lo)
    with np.errstate(all="ignore"):
        return chebyshev(a, lo, hi, np.sqrt, lambda al: 0.25 / (al * al))


def exp(a: AffineForm) -> AffineForm:
    lo, hi = a.interval()
    return chebyshev(a, lo, hi, np.exp, lambda al: np.log(np.maximum(al, _TINY)))


def log(a: AffineForm) -> AffineForm:
    """log, concave; unbounded below where the interval reaches 0."""
    lo, hi = a.interval()
    ok = lo > 0
    safe_lo = np.where(ok, lo, 1.0)
    safe_hi = np.where(ok, hi, 1.0)
    with np.errstate(all="ignore"):
        res = chebyshev(a, safe_lo, safe_hi, np.log, lambda al: 1.0 / al)
    if not ok.all():
        upper = np.log(np.maximum(hi, _TINY))
        res = select(~ok, from_range(a, np.full_like(upper, -np.inf), upper), res)
    return res


def reciprocal(a: AffineForm) -> AffineForm:
    """1/x: convex on x > 0, concave on x < 0, unbounded where the interval contains 0."""
    lo, hi = a.interval()
    pos, neg = lo > 0, hi < 0
    ok = pos | neg
    slo = np.where(ok, lo, 1.0)
    shi = np.where(ok, hi, 2.0)
    sign = np.where(neg, -1.0, 1.0)
    with np.errstate(all="ignore"):
        res = chebyshev(a, slo, shi, lambda x: 1.0 / x, lambda al: sign * np.sqrt(-1.0 / al))
    if not ok.all():
        inf = np.full_like(lo, np.inf)
        res = select(~ok, from_range(a, -inf, inf), res)
    return res


def power(a: AffineForm, p) -> AffineForm:
    """x^p. Integer p: exact rules (sqr, repeated products); real p: x >= 0 only (convex/concave)."""
    p = float(p)
    if p == int(p):
        n = int(p)
        if n == 0:
            return AffineForm.constant(1.0, a)
        if n < 0:
            return reciprocal(power(a, -n))
        if n == 1:
            return a
        if n == 2:
            return sqr(a)
        return _int_power(a, n)
    # real exponent: defined for x >= 0 (callers pass |x| or x >= 0); same argument as sqrt
    lo, hi = a.interval()
    lo = np.maximum(lo, 0.0)
    hi = np.maximum(hi, lo)
    def fp(x: np.ndarray) -> np.ndarray:
        return np.power(x, p)

    def inv(al: np.ndarray) -> np.ndarray:  # f'(u) = p u^(p-1) = alpha
        return np.power(np.maximum(al / p, _TINY), 1.0 / (p - 1.0))

    with np.errstate(all="ignore"):
        res = chebyshev(a, lo, hi, fp, inv)
    return res


def _int_power(a: AffineForm, n: int) -> AffineForm:
    """x^n, n >= 3: Chebyshev where x^n is convex/concave on the interval, range otherwise."""
    lo, hi = a.interval()
    one_sided = (lo >= 0) | ((hi <= 0) & (n % 2 == 1)) | (n % 2 == 0)
    with np.errstate(all="ignore"):
        def inv(al: np.ndarray) -> np.ndarray:
            root = np.power(np.abs(al) / n, 1.0 / (n - 1))
            # on the negative side the tangent point has x < 0
            return np.where(hi <= 0, -root, np.where(lo >= 0, root, np.sign(al) * root))
        res = chebyshev(a, lo, hi, lambda x: np.power(x, n), inv)
    if not one_sided.all():  # odd n across 0: inflection, use the exact monotone range
        res = select(~one_sided, from_range(a, np.power(lo, n), np.power(hi, n)), res)
    return res


def absolute(a: AffineForm) -> AffineForm:
    """|x|: exact where the interval is one-sided, Chebyshev (convex, kink at 0) otherwise."""
    lo, hi = a.interval()
    width = np.where(hi > lo, hi - lo, 1.0)
    alpha = (hi + lo) / width  # secant slope (|hi| - |lo|)/(hi - lo) when lo < 0 < hi
    d1 = -lo - alpha * lo  # |lo| - alpha lo; the tangent point is u = 0 with deviation 0
    mixed = _linear(a, alpha, 0.5 * d1, 0.5 * np.abs(d1))
    res = select(lo >= 0, a, select(hi <= 0, -a, mixed))
    return res


def minimum(a: AffineForm, b: AffineForm) -> AffineForm:
    """min(a, b) = (a + b - |a - b|)/2: keeps the correlation of both arguments."""
    return 0.5 * (a + b - absolute(a - b))


def maximum(a: AffineForm, b: AffineForm) -> AffineForm:
    return 0.5 * (a + b + absolute(a - b))


def sin(a: AffineForm) -> AffineForm:
    """sin: first-order Taylor form with remainder r^2/2 (|sin''| <= 1), or the exact range,
    whichever is narrower per box."""
    return _trig(a, np.sin, np.cos, 0.5 * np.pi)


def cos(a: AffineForm) -> AffineForm:
    return _trig(a, np.cos, lambda x: -np.sin(x), 0.0)


def _trig(a: AffineForm, f, fprime, peak_phase: float) -> AffineForm:
    r = a.radius
    alpha = fprime(a.c)
    taylor = _linear(a, alpha, f(a.c) - alpha * a.c, 0.5 * r * r)
    rlo, rhi = _trig_range(a.c - r, a.c + r, f, peak_phase)
    rng = from_range(a, rlo, rhi)
    return select(rng.radius < taylor.radius, rng, taylor)


def _trig_range(lo: np.ndarray, hi: np.ndarray, f, peak_phase: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact range of sin (peak_phase pi/2) or cos (peak_phase 0) over [lo, hi]."""
    flo, fhi = f(lo), f(hi)
    rlo, rhi = np.minimum(flo, fhi), np.maximum(flo, fhi)
    two_pi = 2.0 * np.pi
    # a maximum at peak_phase + 2 pi k, a minimum at peak_phase + pi + 2 pi k inside [lo, hi]?
    kmax = np.ceil((lo - peak_phase) / two_pi)
    has_max = peak_phase + two_pi * kmax <= hi
    kmin = np.ceil((lo - peak_phase - np.pi) / two_pi)
    has_min = peak_phase + np.pi + two_pi * kmin <= hi
    wide = (hi - lo) >= two_pi
    rhi = np.where(has_max | wide, 1.0, rhi)
    rlo = np.where(has_min | wide, -1.0, rlo)
    return rlo, rhi


def select(mask: np.ndarray, a: AffineForm, b: AffineForm) -> AffineForm:
    """Per box: a where mask, b elsewhere (both must be valid bounds for their boxes)."""
    return AffineForm(np.where(mask, a.c, b.c), np.where(mask, a.g, b.g), np.where(mask, a.e, b.e))


def hull(a: AffineForm, b: AffineForm) -> AffineForm:
    """A form containing both a and b for every box (for values that may come from either)."""
    alo, ahi = a.interval()
    blo, bhi = b.interval()
    return AffineForm.from_interval(np.minimum(alo, blo), np.maximum(ahi, bhi))
