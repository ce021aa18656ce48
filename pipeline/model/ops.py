"""Field arithmetic that works on both NumPy arrays (evaluation) and affine forms (bounds).

Model nodes write their defining function once, with these functions and the ordinary
operators; called with arrays of coordinates it evaluates the field at points, called with
:class:`~pipeline.field.affine.AffineForm` coordinates it bounds the field over boxes. One formula,
two interpretations: the bound cannot drift away from what is evaluated.
"""

from __future__ import annotations

import numpy as np

from pipeline.field import affine as aa
from pipeline.field import rfunctions as rf
from pipeline.field.affine import AffineForm
from pipeline.model import tape as tp
from pipeline.model.tape import Sym

Value = np.ndarray | AffineForm | float


def is_form(*xs) -> bool:
    return any(isinstance(x, AffineForm) for x in xs)


def _lift(x, like: AffineForm) -> AffineForm:
    if isinstance(x, AffineForm):
        return x
    c = np.broadcast_to(np.asarray(x, dtype=np.float64), like.c.shape).copy()
    return AffineForm(c, np.zeros_like(like.g), np.zeros_like(like.e))


def _unary(np_fn, aa_fn, code: int):
    """One function, three interpretations: arrays (values), AffineForms (bounds), Syms (tape)."""
    def fn(x):
        if isinstance(x, Sym):
            return x.unary(code)
        return aa_fn(x) if isinstance(x, AffineForm) else np_fn(x)

    fn.__name__ = np_fn.__name__ if hasattr(np_fn, "__name__") else aa_fn.__name__
    return fn


sqrt = _unary(np.sqrt, aa.sqrt, tp.SQRT)
exp = _unary(np.exp, aa.exp, tp.EXP)
log = _unary(np.log, aa.log, tp.LOG)
sin = _unary(np.sin, aa.sin, tp.SIN)
cos = _unary(np.cos, aa.cos, tp.COS)
abs_ = _unary(np.abs, aa.absolute, tp.ABS)
sqr = _unary(np.square, aa.sqr, tp.SQR)


def is_sym(*xs) -> bool:
    return any(isinstance(x, Sym) for x in xs)


def pow_(x, p: float):
    """x**p for a constant exponent; real exponents need x >= 0 (use pow_(abs_(x), p))."""
    if isinstance(x, Sym):
        return x.unary(tp.POWC, float(p))
    if isinstance(x, AffineForm):
        return aa.power(x, p)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.power(x, p)


def _binary(a, b, code: int, on_forms, on_arrays):
    """One binary operation on tape symbols (a clause), affine forms (the other operand lifted
    to a form) or arrays."""
    if is_sym(a, b):
        return tp.binary(code, a, b)
    if is_form(a, b):
        like = a if isinstance(a, AffineForm) else b
        return on_forms(_lift(a, like), _lift(b, like))
    return on_arrays(a, b)


def _divide(a, b):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.true_divide(a, b)


def minimum(a, b):
    return _binary(a, b, tp.MIN, aa.minimum, np.minimum)


def maximum(a, b):
    return _binary(a, b, tp.MAX, aa.maximum, np.maximum)


def div(a, b):
    return _binary(a, b, tp.DIV, lambda p, q: p / q, _divide)


def length(*xs):
    """Euclidean norm of the components."""
    s = sqr(xs[0])
    for x in xs[1:]:
        s = s + sqr(x)
    return sqrt(s)


# --- R-functions --------------------------------------------------------------------------


def r_and(a, b, family: str = "r0", k: float = rf.SARDF_K, scale: float = np.inf):
    """R-conjunction: intersection of two FRep fields (families of pipeline.field.rfunctions);
    ``scale``: the magnitude control of :func:`pipeline.field.rfunctions.compress`."""
    if is_sym(a, b):
        return _r_and_sym(a, b, family, k, scale)
    if not is_form(a, b):
        return rf.r_and(a, b, family, k, scale)
    like = a if isinstance(a, AffineForm) else b
    a, b = _lift(a, like), _lift(b, like)
    if family == "min_max":
        return aa.minimum(a, b)
    if family == "r0":
        return compress_form(_monotone_hull(a + b - aa.sqrt(aa.sqr(a) + aa.sqr(b)), a, b), scale)
    if family == "sardf":
        return compress_form(_sardf_and_bound(a, b, k), scale)
    raise ValueError(f"unknown R-function family {family!r}")


def _r_and_sym(a, b, family: str, k: float, scale: float):
    """The tape clauses of an R-conjunction (min for min_max; r0/sardf then the compression)."""
    if family == "min_max":
        return tp.binary(tp.MIN, a, b)
    if family not in ("r0", "sardf"):
        raise ValueError(f"unknown R-function family {family!r}")
    if family == "r0":
        r = tp.binary(tp.R0AND, a, b)
    else:
        s = a if isinstance(a, Sym) else b
        r = s.tb.emit(tp.SARDFAND, s._lift(a).pos, s._lift(b).pos, float(k))
    return r.unary(tp.COMPRESS, float(scale)) if np.isfinite(scale) else r


def compress_form(r: AffineForm, scale: float) -> AffineForm:
    """Bound of compress(r): the form itself where its range lies within +-scale (compress is the
    identity there), else the interval [compress(lo), compress(hi)] (compress is increasing)."""
    if not np.isfinite(scale):
        return r
    lo, hi = r.interval()
    far = (lo < -scale) | (hi > scale)
    if not far.any():
        return r
    with np.errstate(invalid="ignore"):
        clo = rf.compress(lo, scale) * (1.0 + np.copysign(1e-12, -lo))  # outward by rounding
        chi = rf.compress(hi, scale) * (1.0 + np.copysign(1e-12, hi))
    box = AffineForm.from_interval(np.nan_to_num(clo, nan=-np.inf), np.nan_to_num(chi, nan=np.inf))
    return aa.select(far, box, r)


def _monotone_hull(r: AffineForm, a: AffineForm, b: AffineForm) -> AffineForm:
    """r0 is increasing in both arguments, so [r0(a_lo, b_lo), r0(a_hi, b_hi)] encloses it over
    a box; where that interval is narrower than the affine form (wide operands, e.g. unions of
    many nodes folded left, where sqr/sqrt widen the form at every step), use it instead."""
    alo, ahi = a.interval()
    blo, bhi = b.interval()
    with np.errstate(invalid="ignore", over="ignore"):
        lo = np.nan_to_num(rf.r_and(alo, blo, "r0"), nan=-np.inf)
        hi = np.nan_to_num(rf.r_and(ahi, bhi, "r0"), nan=np.inf)
        pad = 8.0 * np.finfo(np.float64).eps * (np.abs(alo) + np.abs(blo) + np.abs(ahi) + np.abs(bhi))
    rlo, rhi = r.interval()
    lo, hi = np.maximum(lo - pad, rlo), np.minimum(hi + pad, rhi)
    tighter = (hi - lo) < (rhi - rlo)
    return aa.select(tighter, AffineForm.from_interval(np.minimum(lo, hi), hi), r)


def r_or(a, b, family: str = "r0", k: float = rf.SARDF_K, scale: float = np.inf):
    """R-disjunction: union, -(-a AND -b)."""
    return -r_and(-a, -b, family, k, scale)


def _sardf_and_bound(a: AffineForm, b: AffineForm, k: float) -> AffineForm:
    """Bound of the SARDF conjunction: it lies in [min - k rho / 4, min] (rfunctions module doc).

    The smoothed |u| exceeds |u| by at most k rho / 2 (at u = 0), so the conjunction
    (f1 + f2 - smooth|u|)/2 is below min(f1, f2) by at most k rho / 4, rho <= |f1| + |f2|.
    """
    m = aa.minimum(a, b)
    alo, ahi = a.interval()
    blo, bhi = b.interval()
    rho_hi = np.maximum(np.abs(alo), np.abs(ahi)) + np.maximum(np.abs(blo), np.abs(bhi))
    drop = 0.25 * k * rho_hi
    return AffineForm(m.c - 0.5 * drop, m.g, m.e + 0.5 * drop)
