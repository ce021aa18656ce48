"""Tricubic B-spline (pipeline.distance.spline) and the continuous HFRep field (pipeline.distance.hfrep)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_eikonal import band_grid, sphere, torus

from pipeline.distance.eikonal import solve_distance
from pipeline.distance.hfrep import HFRepField, hfrep_field, step_function
from pipeline.distance.spline import TricubicSpline

N = 64
H = 2.0 / N


@pytest.fixture(scope="module")
def torus_result():
    frep, dom = band_grid(torus, N)
    return solve_distance(frep, 3 * H, dom)


@pytest.fixture(scope="module")
def sphere_result():
    frep, dom = band_grid(sphere, N)
    return solve_distance(frep, 3 * H, dom)


def test_spline_interpolates_the_samples(torus_result) -> None:
    spline = TricubicSpline(torus_result.distance)
    ijk, v = torus_result.distance.active_voxels()
    pts = ijk * H
    ok = spline.supported(pts)
    assert ok.mean() > 0.95
    assert np.max(np.abs(spline(pts[ok]) - v[ok])) < 1e-5 * H
    between = pts[ok] + 0.5 * H  # not a sample: the spline differs from trilinear there
    assert np.max(np.abs(spline(between) - spline.trilinear(between))) > 1e-4 * H


def test_missing_support_falls_back_to_fill(torus_result) -> None:
    spline = TricubicSpline(torus_result.distance)
    far = np.array([[0.0, 0.0, 0.99], [5.0, 5.0, 5.0]])
    val, grad = spline.evaluate(far, with_gradient=True)
    assert not spline.supported(far).any()
    assert np.all(val == torus_result.distance.background)
    assert np.all(grad == 0.0)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(-0.7, 0.7), min_size=3, max_size=3))
def test_spline_gradient_matches_finite_differences(p) -> None:
    frep, dom = band_grid(sphere, 32)
    res = solve_distance(frep, None, dom)
    spline = TricubicSpline(res.distance)
    x = np.array([p])
    g = spline.gradient(x)[0]
    eps = 1e-6
    fd = [(spline(x + eps * e) - spline(x - eps * e))[0] / (2 * eps) for e in np.eye(3)]
    assert np.allclose(g, fd, atol=1e-5)


def _knot_points(n: int, seed: int) -> np.ndarray:
    """Points whose x index is an integer (a knot plane of both interpolants), y, z random."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.45, 0.45, size=(n, 3))
    p[:, 0] = np.round(p[:, 0] / H) * H
    return p


def _slope_jumps(fn, points: np.ndarray, axis: int = 0) -> np.ndarray:
    """|right minus left one-sided difference slope| across the knot plane at ``points``."""
    delta = 1e-4 * H
    e = np.zeros(3)
    e[axis] = delta
    f0, fp, fm = fn(points), fn(points + e), fn(points - e)
    return np.abs((fp - f0) / delta - (f0 - fm) / delta)


def _away_from_kinks(points: np.ndarray) -> np.ndarray:
    """Inside the sphere, 3 voxels from its surface and its centre (no kinks in the data)."""
    r = np.linalg.norm(points - np.array([0.013, -0.021, 0.007]), axis=1)
    return (r > 3 * H) & (r < 0.6 - 3 * H)


def test_hfrep_is_c1_across_voxel_boundaries_and_trilinear_is_not(sphere_result) -> None:
    field = HFRepField.from_result(sphere, sphere_result, step="sigmoid", slope=0.01)
    pts = _knot_points(4000, 3)
    pts = pts[_away_from_kinks(pts)]
    assert len(pts) > 1000
    spline_jump = _slope_jumps(field.evaluate, pts)
    trilinear_field = lambda q: hfrep_field(sphere(q), field.distance.trilinear(q))  # noqa: E731
    tri_jump = _slope_jumps(trilinear_field, pts)
    assert spline_jump.max() < 1e-3
    assert np.median(tri_jump) > 1e-2  # trilinear's kinks are detected by the same measure
    assert tri_jump.max() > 10 * spline_jump.max()


@pytest.mark.parametrize("axis", [1, 2])
def test_spline_c1_along_other_axes(sphere_result, axis: int) -> None:
    spline = TricubicSpline(sphere_result.distance)
    pts = _knot_points(3000, 11 + axis)
    pts[:, [0, axis]] = pts[:, [axis, 0]]
    pts = pts[_away_from_kinks(pts)]
    assert _slope_jumps(spline, pts, axis).max() < 1e-3
    assert np.median(_slope_jumps(spline.trilinear, pts, axis)) > 1e-2


def test_step_functions() -> None:
    x = np.linspace(-1, 1, 2001)
    sig = step_function(x, "sigmoid", 0.05)
    assert np.allclose(sig, np.tanh(x / 0.05), atol=1e-12)  # eq. 23 with r = 2 is tanh(x/sl)
    assert np.allclose(step_function(x, "tanh", 0.05), sig)
    rat = step_function(x, "rational", 0.05)
    for s in (sig, rat):
        assert np.all(np.abs(s) <= 1) and np.all(np.diff(s) >= 0)
        assert np.all(np.diff(s[np.abs(x) < 0.3]) > 0)  # strictly increasing near the surface
        assert np.array_equal(np.sign(s), np.sign(x))
    assert step_function(np.array([0.0]), "sigmoid", 0.01)[0] == 0.0
    with pytest.raises(ValueError):
        step_function(x, "heaviside", 0.1)
    with pytest.raises(ValueError):
        step_function(x, "tanh", 0.0)
    assert np.allclose(hfrep_field(np.array([1.0, -1.0]), np.array([0.3, 0.2]), "tanh", 1e-3), [0.3, -0.2])
