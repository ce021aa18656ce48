"""Revised affine arithmetic over the compiled tape (pipeline.model.tape_affine) against the node-by-node
Python RAA (``model.bound``, pipeline.field.affine / pipeline.model.ops) and against the field's values:

- inclusion: the tape's values at random points of a box (and at its corners) lie within the
  compiled bound, for every opcode the tape can emit (the coverage is checked), random trees and
  a min_max mesh in CSG;
- tightness: the compiled bound is never wider than the Python one beyond rounding. Measured when
  this was written (every model here, boxes of edge 1 .. 0.005, and the random trees): no box
  wider than Python's width * (1 + 1e-9) + 1e-12 (1 + |bounds|); the largest excess, relative,
  ~1e-8 on blobby boxes whose width is ~1e-7 (1e-15 absolute: the rounding allowances this module
  adds where affine.py adds none: coordinates, forms made from intervals, the SARDF widening), and
  the final forms' coefficients agree to ~1e-12 relative (CSE, folded and immediate constants and
  the fused R0AND clause change only the rounding). So the test asserts it for every box;
- soundness of non-finite cases: no NaN ever, unbounded (-inf, inf) where a form overflows or a
  box is not finite.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.model import tape as pt
from pipeline.model.tape_affine import affine_bounds, clause_forms
from tests.test_tape import NODES, _ico, job_of
from tests.test_written_grids import tree

EXTRA = {
    # integer powers (odd across 0, even, negative, 0), real powers, reciprocals of powers
    "powers": 'expr: "x^3 + (abs(y) + 0.05)^-2 - (z + 1.25)^-1 + pow(abs(x), 1.5) + abs(y)^0.3 + (z - 0.2)^4 '
              '- x^5 + (0.5 + x^2)^-3 + (abs(z) + 0.01)^-0.5 + x^0 + (x - 1.3)^-3"',
    # division of two forms (denominators across 0 in large boxes), log, exp, sqrt
    "divlog": 'expr: "x / (y + 1.5) - log(x + 1.3) + log(abs(y) + 0.01) + exp(3 * z) - 1 / (x * y + 1.5) '
              '+ sqrt(abs(x * z)) + (x + 2) / (y - 1.3)"',
    "trig": 'expr: "sin(9 * x + y) * cos(7 * z) - sin(x * x * 20) + cos(0.1 * y)"',
    "minmax": 'expr: "min(x, y, z * z) - max(x * y, 0.2, -z) + min(-x, -y)"',
}
SIZES = (1.0, 0.3, 0.05, 0.005)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("models")
    texts = {k: v for k, v in NODES.items() if k != "lattice"} | EXTRA  # lattice: 964 clauses of the same ops
    texts["mesh"] = (f"difference: {{of: [{{rotate: {{axis: [1, 1, 0], angle: 20, of: {{mesh: {{path: {_ico(tmp)}, "
                     f"rfunc: min_max}}}}}}}}, {{sphere: {{center: [0.5, 0, 0], radius: 0.3}}}}], rfunc: r0}}")
    out = {}
    for name, text in texts.items():
        job = job_of(tmp, text)
        tp = pt.compile_model(job.model, job.t)
        assert tp is not None, name
        out[name] = (job, tp)
    return out


def boxes(rng, n: int, size: float, lo: float = -1.2, hi: float = 1.2):
    b = rng.uniform(lo, hi - size, (n, 3))
    return b, b + size


def check_inclusion(tp: pt.Tape, lo: np.ndarray, hi: np.ndarray, flo, fhi, rng, per: int = 24) -> None:
    """Values at ``per`` random points and the 8 corners of every box lie in [flo, fhi]."""
    assert not np.isnan(flo).any() and not np.isnan(fhi).any()
    assert np.all(flo <= fhi)
    u = np.concatenate([rng.uniform(0, 1, (len(lo), per, 3)),
                        np.broadcast_to(np.array(np.meshgrid(*[[0.0, 1.0]] * 3)).reshape(3, -1).T, (len(lo), 8, 3))],
                       axis=1)
    pts = lo[:, None, :] + u * (hi - lo)[:, None, :]
    v = pt.evaluate_with(tp, pts.reshape(-1, 3)).reshape(len(lo), -1)
    fin = np.isfinite(v)
    out = fin & ((v < flo[:, None]) | (v > fhi[:, None]))
    assert not out.any(), (np.argwhere(out)[:5], v[out][:5])


def check_tight(flo, fhi, plo, phi) -> None:
    """The compiled width is at most Python's width, to rounding (module docstring), on every box;
    where Python's bound is finite, so is the compiled one."""
    wc, wp = fhi - flo, phi - plo
    fin = np.isfinite(wp)
    assert np.all(np.isfinite(wc[fin])), np.flatnonzero(fin & ~np.isfinite(wc))[:5]
    tol = wp * (1 + 1e-9) + 1e-12 * (1 + np.abs(plo) + np.abs(phi))
    worse = fin & ~(wc <= tol)
    assert not worse.any(), (np.flatnonzero(worse)[:5], wc[worse][:5], wp[worse][:5])


def test_every_opcode_is_covered(models) -> None:
    seen = set()
    for _, tp in models.values():
        seen |= set(int(o) for o in tp.op)
    missing = set(range(len(pt.NAMES))) - seen
    assert not missing, [pt.NAMES[k] for k in sorted(missing)]


@pytest.mark.parametrize("name", sorted({k for k in NODES if k != "lattice"} | set(EXTRA) | {"mesh"}))
def test_bounds_enclose_and_are_as_tight_as_python(models, name) -> None:
    job, tp = models[name]
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    for size in SIZES:
        lo, hi = boxes(rng, 150, size)
        flo, fhi = affine_bounds(tp, lo, hi)
        check_inclusion(tp, lo, hi, flo, fhi, rng)
        check_tight(flo, fhi, *job.model.bound(lo, hi, job.t))


def test_final_form_is_python_form(models) -> None:
    """Clause by clause the same rules: the result's centre and slopes are the Python form's to
    rounding (where both are bounded), not merely an interval of similar width."""
    rng = np.random.default_rng(5)
    for name, (job, tp) in models.items():
        lo, hi = boxes(rng, 12, 0.2)
        ref = job.model.bound_form(lo, hi, job.t)
        for q in range(len(lo)):
            c, g0, g1, g2, e = clause_forms(tp, lo[q], hi[q])[tp.res]
            if not (np.isfinite(e) and np.isfinite(ref.e[q])):
                continue
            scale = abs(ref.c[q]) + np.abs(ref.g[:, q]).sum() + ref.e[q]
            assert abs(c - ref.c[q]) <= 1e-10 * scale, (name, q)
            np.testing.assert_allclose([g0, g1, g2], ref.g[:, q], rtol=0, atol=1e-10 * scale, err_msg=name)
            assert e <= ref.e[q] * (1 + 1e-9) + 1e-12 * scale, (name, q)


def test_demo_model(tmp_path) -> None:
    """configs/demo.yaml's model (a superellipsoid minus a thin box, r0): inclusion, tightness."""
    job = job_of(tmp_path, "difference: {of: [{superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}}, "
                           "{box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}}], rfunc: r0}")
    tp = pt.compile_model(job.model, job.t)
    rng = np.random.default_rng(0)
    for size in (2.4 / 8, 2.4 / 64, 2.4 / 512):
        lo, hi = boxes(rng, 400, size)
        flo, fhi = affine_bounds(tp, lo, hi)
        check_inclusion(tp, lo, hi, flo, fhi, rng, per=8)
        check_tight(flo, fhi, *job.model.bound(lo, hi, job.t))


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(model=tree(), seed=st.integers(0, 100), size=st.sampled_from(SIZES))
def test_random_trees(tmp_path_factory, model, seed, size) -> None:
    job = job_of(tmp_path_factory.mktemp("t"), model)
    tp = pt.compile_model(job.model, job.t)
    rng = np.random.default_rng(seed)
    lo, hi = boxes(rng, 60, size)
    flo, fhi = affine_bounds(tp, lo, hi)
    check_inclusion(tp, lo, hi, flo, fhi, rng, per=12)
    check_tight(flo, fhi, *job.model.bound(lo, hi, job.t))


@pytest.mark.parametrize("scale", [1e150, 1e300])
def test_huge_and_infinite_boxes_are_unbounded_not_nan(models, scale) -> None:
    """Forms that overflow, and boxes with infinite corners, give (-inf, inf) (or a bound that
    still holds), never NaN."""
    rng = np.random.default_rng(7)
    for name, (_, tp) in models.items():
        lo, hi = boxes(rng, 20, 0.5 * scale, -scale, scale)
        lo[:5, 0] = -np.inf
        hi[5:10, 2] = np.inf
        flo, fhi = affine_bounds(tp, lo, hi)
        assert not np.isnan(flo).any() and not np.isnan(fhi).any(), name
        assert np.all(flo <= fhi), name
        fin = np.all(np.isfinite(lo) & np.isfinite(hi), axis=1)
        check_inclusion(tp, lo[fin], hi[fin], flo[fin], fhi[fin], rng, per=4)


def test_log_and_division_across_zero_are_unbounded() -> None:
    """log over a box reaching x <= 0 and 1 / x across 0: the Python rules' (-inf, ...) ranges."""
    op = np.array([pt.X, pt.LOG, pt.RDIVC, pt.ADD], np.int64)
    tp = pt.Tape(op, np.array([-1, 0, 0, 1]), np.array([-1, -1, -1, 2]), np.array([0.0, 0.0, 1.0, 0.0]), 3)
    lo = np.array([[-1.0, 0, 0], [0.5, 0, 0], [0.0, 0, 0]])
    hi = np.array([[1.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
    flo, fhi = affine_bounds(tp, lo, hi)
    assert flo[0] == -np.inf and fhi[0] == np.inf and flo[2] == -np.inf
    assert np.isfinite(flo[1]) and np.isfinite(fhi[1])
    v = np.log(np.linspace(0.5, 2, 101)) + 1 / np.linspace(0.5, 2, 101)
    assert flo[1] <= v.min() and v.max() <= fhi[1]


def test_integer_power_beyond_int64_is_not_taken_for_a_real_power() -> None:
    """x ** 1e20 is defined for x < 0 (an even integer power); the real-power rule (x >= 0 only)
    would bound it by 0 over a box across 0. Numba's math.floor returns an int64 (1e20 overflows),
    so the kernel tests integrality with np.floor: this failed with math.floor."""
    for p in (1e20, 2.0**63):
        tp = pt.Tape(np.array([pt.X, pt.POWC]), np.array([-1, 0]), np.array([-1, -1]), np.array([0.0, p]), 1)
        flo, fhi = affine_bounds(tp, np.array([[-0.5, 0, 0], [0.2, 0, 0]]), np.array([[0.5, 0, 0], [0.9, 0, 0]]))
        assert flo[0] == -np.inf and fhi[0] == np.inf
        assert flo[1] <= 0.0 <= fhi[1] < 1e-200  # 0.9 ** 1e20 underflows to 0
