"""The distance to the zero set of the piecewise-linear interpolant (pipeline.field.zeroset)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.field.zeroset import origin_triangle_distance, zero_set_distance

OFFSETS = np.indices((3, 3, 3)).transpose(1, 2, 3, 0) - 1  # the 3^3 samples around a voxel


def _known():
    return np.ones((3, 3, 3), bool)


@settings(max_examples=200, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(-0.95, 0.95))
def test_plane_gives_the_exact_distance(nx: float, ny: float, nz: float, c: float) -> None:
    """A linear f is its own interpolant: the distance to the plane, wherever the plane crosses
    the voxel's cubes."""
    n = np.array([nx, ny, nz])
    if np.linalg.norm(n) < 1e-3:
        return
    n /= np.linalg.norm(n)
    d = zero_set_distance(OFFSETS @ n - c, _known(), 1, 1, 1)
    assert abs(d - abs(c)) <= 1e-9


def test_no_sign_change_is_inf_and_unknown_cubes_are_left_out() -> None:
    f = OFFSETS @ np.array([1.0, 0.0, 0.0]) + 5.0
    assert zero_set_distance(f, _known(), 1, 1, 1) == np.inf
    f = OFFSETS @ np.array([1.0, 0.0, 0.0]) - 0.5  # crosses between x = 0 and x = 1 only
    known = _known()
    known[2] = False  # every cube on the +x side has an unknown sample
    assert zero_set_distance(f, known, 1, 1, 1) == np.inf
    assert abs(zero_set_distance(f, _known(), 1, 1, 1) - 0.5) < 1e-12


def test_convex_corner_is_found_diagonally() -> None:
    """A voxel diagonal to a box's corner (no axis neighbour inside): a finite distance, at
    least the true one (the interpolant cuts the corner) and within 0.3 voxel of it."""
    off = np.array([0.38, 0.19, 0.06])
    q = OFFSETS + off  # the corner at the origin, the box in the negative octant
    f = -(np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0))  # exact, > 0 inside
    assert all(f[1 + a, 1 + b, 1 + c] < 0 for a, b, c in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0),
                                                         (0, 0, 1), (0, 0, -1)))
    d = zero_set_distance(f, _known(), 1, 1, 1)
    assert np.linalg.norm(off) <= d <= np.linalg.norm(off) + 0.3


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-2, 2), min_size=9, max_size=9))
def test_triangle_distance_is_the_least_over_the_triangle(v: list[float]) -> None:
    a, b, c = np.array(v).reshape(3, 3)
    d = origin_triangle_distance(*a, *b, *c)
    w = np.random.default_rng(0).dirichlet(np.ones(3), 4000)
    pts = np.concatenate([w @ np.stack([a, b, c]), np.stack([a, b, c])])
    assert d <= np.linalg.norm(pts, axis=1).min() + 1e-9
    assert d >= np.linalg.norm(pts, axis=1).min() - 0.05 * (1 + np.ptp(pts, axis=0).max())
