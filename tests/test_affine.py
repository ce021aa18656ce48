"""Inclusion property of revised affine arithmetic (components seed, section 3.1).

For every operation and every node type: the values at points sampled in a box lie inside
the bound of that box. Boxes and parameters come from hypothesis.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.field import affine as aa
from pipeline.field.affine import AffineForm
from pipeline.model import ops
from pipeline.oracles import REGISTRY

SLACK = 1e-12  # float rounding between the two evaluation orders, relative to the magnitude

coord = st.floats(-3, 3, allow_nan=False)
width = st.floats(1e-6, 2.5, allow_nan=False)


def boxes_and_points(seed: int, lo: np.ndarray, w: np.ndarray, n: int = 300):
    rng = np.random.default_rng(seed)
    hi = lo + w
    pts = lo + rng.random((n, 3)) * w
    pts = np.vstack([pts, lo, hi, [[lo[0], hi[1], lo[2]]]])  # corners too
    return lo[None, :], hi[None, :], pts


def assert_encloses(lo, hi, values):
    finite = np.isfinite(values)
    v = values[finite]
    scale = 1.0 + np.abs(v)
    assert np.all(v >= lo[0] - SLACK * scale), (lo, v.min())
    assert np.all(v <= hi[0] + SLACK * scale), (hi, v.max())


UNARY = {
    "sqrt": (lambda x: ops.sqrt(ops.abs_(x) + 0.0), lambda x: np.sqrt(np.abs(x))),
    "exp": (ops.exp, np.exp),
    "log": (lambda x: ops.log(ops.sqr(x) + 0.1), lambda x: np.log(x * x + 0.1)),
    "sin": (ops.sin, np.sin),
    "cos": (ops.cos, np.cos),
    "abs": (ops.abs_, np.abs),
    "sqr": (ops.sqr, np.square),
    "cube": (lambda x: ops.pow_(x, 3), lambda x: x**3),
    "pow4": (lambda x: ops.pow_(x, 4), lambda x: x**4),
    "pow-2": (lambda x: ops.pow_(ops.sqr(x) + 0.2, -2), lambda x: (x * x + 0.2) ** -2),
    "pow2.7": (lambda x: ops.pow_(ops.abs_(x), 2.7), lambda x: np.abs(x) ** 2.7),
    "pow0.3": (lambda x: ops.pow_(ops.abs_(x), 0.3), lambda x: np.abs(x) ** 0.3),
    "recip": (lambda x: ops.div(1.0, ops.sqr(x) + 0.5), lambda x: 1.0 / (x * x + 0.5)),
}


@pytest.mark.parametrize("name", sorted(UNARY))
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(x0=coord, w=width, k=st.floats(-4, 4), seed=st.integers(0, 2**16))
def test_unary_inclusion(name, x0, w, k, seed):
    f_form, f_np = UNARY[name]
    lo, hi, pts = boxes_and_points(seed, np.array([x0, -1.0, 0.5]), np.array([w, 0.7, w]))
    X, Y, Z = AffineForm.coordinates(lo, hi)
    arg_form = X * k + Y * 0.3 - Z  # correlated arguments exercise the noise symbols
    arg = pts[:, 0] * k + pts[:, 1] * 0.3 - pts[:, 2]
    blo, bhi = f_form(arg_form).interval()
    assert_encloses(blo, bhi, f_np(arg))


BINARY = {
    "mul": (lambda a, b: a * b, lambda a, b: a * b),
    "div": (lambda a, b: ops.div(a, ops.sqr(b) + 0.3), lambda a, b: a / (b * b + 0.3)),
    "min": (ops.minimum, np.minimum),
    "max": (ops.maximum, np.maximum),
    "r0_and": (lambda a, b: ops.r_and(a, b, "r0"), lambda a, b: ops.r_and(a, b, "r0")),
    "r0_or": (lambda a, b: ops.r_or(a, b, "r0"), lambda a, b: ops.r_or(a, b, "r0")),
    "sardf_and": (lambda a, b: ops.r_and(a, b, "sardf"), lambda a, b: ops.r_and(a, b, "sardf")),
    "sardf_or": (lambda a, b: ops.r_or(a, b, "sardf"), lambda a, b: ops.r_or(a, b, "sardf")),
    "minmax_and": (lambda a, b: ops.r_and(a, b, "min_max"), lambda a, b: ops.r_and(a, b, "min_max")),
}


@pytest.mark.parametrize("name", sorted(BINARY))
@settings(max_examples=60, deadline=None)
@given(x0=coord, y0=coord, w=width, seed=st.integers(0, 2**16))
def test_binary_inclusion(name, x0, y0, w, seed):
    f_form, f_np = BINARY[name]
    lo, hi, pts = boxes_and_points(seed, np.array([x0, y0, -0.2]), np.array([w, w, 0.4]))
    X, Y, Z = AffineForm.coordinates(lo, hi)
    a_form, b_form = X - 0.5 * Z, Y * Y - X
    a, b = pts[:, 0] - 0.5 * pts[:, 2], pts[:, 1] ** 2 - pts[:, 0]
    blo, bhi = f_form(a_form, b_form).interval()
    assert_encloses(blo, bhi, f_np(a, b))


def test_affine_ops_are_exact():
    """x - x is exactly 0 and rotations keep correlation: affine forms, not intervals."""
    lo, hi = np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 2.0, 3.0]])
    X, Y, Z = AffineForm.coordinates(lo, hi)
    d = (X + Y) - (Y + X)
    assert abs(d.lo[0]) < 1e-12 and abs(d.hi[0]) < 1e-12  # interval arithmetic would give [-3, 3]
    s = X * 2.0 + 1.0
    assert s.lo[0] == pytest.approx(1.0) and s.hi[0] == pytest.approx(3.0)


def test_sqr_tighter_than_interval_product():
    """Revised rule: x^2 over [-1, 1] is [0, 1], not the interval product [-1, 1]."""
    X, _, _ = AffineForm.coordinates(np.array([[-1.0, 0, 0]]), np.array([[1.0, 0, 0]]))
    lo, hi = aa.sqr(X).interval()
    assert lo[0] >= -1e-12 and hi[0] <= 1.0 + 1e-12


def test_many_boxes_in_one_call():
    """One call bounds thousands of boxes, each independently."""
    rng = np.random.default_rng(0)
    lo = rng.uniform(-2, 2, (5000, 3))
    hi = lo + rng.uniform(0.01, 0.5, (5000, 3))
    sphere = REGISTRY["sphere"](REGISTRY["sphere"].Params(radius=1.0))
    flo, fhi = sphere.bound(lo, hi)
    assert flo.shape == (5000,)
    pts = lo + rng.random((5000, 3)) * (hi - lo)
    v = sphere.evaluate(pts)
    assert np.all(v >= flo - 1e-12) and np.all(v <= fhi + 1e-12)


def test_from_range_with_infinite_ends_is_unbounded_not_nan() -> None:
    """affine.from_range of [-inf, inf], [-inf, 1] and [2, inf] (1/x or log across 0): the
    unbounded form (interval [-inf, inf], never NaN, which a test like ``lo > 0`` would read as
    'not proven' but arithmetic would spread); finite ranges keep their exact interval."""
    x = AffineForm.coordinates(np.full((4, 3), -1.0), np.full((4, 3), 1.0))[0]
    rlo = np.array([-np.inf, -np.inf, 2.0, -3.0])
    rhi = np.array([np.inf, 1.0, np.inf, 5.0])
    lo, hi = aa.from_range(x, rlo, rhi).interval()
    assert not np.isnan(lo).any() and not np.isnan(hi).any()
    assert (lo[:3] == -np.inf).all() and (hi[:3] == np.inf).all()
    assert lo[3] <= -3.0 and hi[3] >= 5.0 and hi[3] - lo[3] < 8.0 + 1e-9
