"""Largest margin of a few halfspaces: a compiled two-phase simplex for the BSP special cases.

pipeline.mesh.bsp decides the section 3.2 special cases with thousands of tiny linear programs

    maximise t  subject to  s_i (n_i . x + c_i) >= t  (i = 1..m),  t <= 1,  x free,

whose optimum is the largest margin of a point inside every halfspace (unit normals n_i): the
intersection has an interior point when it is positive. scipy's ``linprog`` spends ~1 ms of
Python per call on them; this solves the dual, which has a feasible start,

    minimise  b . y + z  subject to  sum_i y_i a_i = 0,  sum_i y_i + z = 1,  y, z >= 0

(a_i = -s_i n_i, b_i = s_i c_i; its optimum equals the primal's by LP duality, and the primal
is always feasible and bounded by 1), with a dense tableau, Bland's rule against cycling (the
three zero right-hand sides make it very degenerate) and a phase 1 through artificials. About
ten microseconds per problem.
"""

from __future__ import annotations

import numpy as np

from pipeline.util.jit import njit

EPS = 1e-12
MAX_PIVOTS = 10_000


@njit(cache=True)
def _pivot(t, r, c):
    t[r, :] /= t[r, c]
    for i in range(t.shape[0]):
        if i != r and t[i, c] != 0.0:
            t[i, :] -= t[i, c] * t[r, :]


@njit(cache=True)
def _run(t, basis, ncols, obj):
    """Bland's-rule simplex on tableau t (constraint rows 0..k-1, objective row ``obj``, right
    hand side in the last column) over columns < ncols. Returns False if it did not finish."""
    k = basis.shape[0]
    rhs = t.shape[1] - 1
    for _ in range(MAX_PIVOTS):
        enter = -1
        for c in range(ncols):  # Bland: the first column with a negative reduced cost
            if t[obj, c] < -EPS:
                enter = c
                break
        if enter < 0:
            return True
        leave = -1
        best = np.inf
        for i in range(k):
            if t[i, enter] > EPS:
                q = t[i, rhs] / t[i, enter]
                if q < best - EPS or (abs(q - best) <= EPS and basis[i] < basis[leave]):
                    best, leave = q, i
        if leave < 0:
            return False  # unbounded: cannot happen for this dual (its optimum exists)
        _pivot(t, leave, enter)
        basis[leave] = enter
    return False


@njit(cache=True)
def max_margin(a, b):
    """Optimum of the primal above for rows a (m, d) = -s_i n_i and b (m,) = s_i c_i; NaN if the
    simplex did not finish (the caller then asks a general solver)."""
    m, d = a.shape
    k = d + 1  # rows: d equalities sum y_i a_i = 0, and sum y + z = 1
    nreal = m + 1  # columns y_0..y_{m-1}, z
    t = np.zeros((k + 2, nreal + k + 1))  # + artificials, rhs; rows: constraints, phase-2 obj, phase-1 obj
    rhs = nreal + k
    for i in range(m):
        for j in range(d):
            t[j, i] = a[i, j]
        t[d, i] = 1.0
    t[d, m] = 1.0
    t[d, rhs] = 1.0
    basis = np.empty(k, np.int64)
    for j in range(k):
        t[j, nreal + j] = 1.0
        basis[j] = nreal + j
    p2, p1 = k, k + 1
    for i in range(m):
        t[p2, i] = b[i]
    t[p2, m] = 1.0
    for c in range(rhs + 1):  # phase 1 objective: sum of artificials, in terms of the non-basics
        s = 0.0
        for j in range(k):
            s += t[j, c]
        t[p1, c] = -s if c < nreal or c == rhs else 0.0
    if not _run(t, basis, nreal, p1) or t[p1, rhs] < -1e-9:
        return np.nan
    for j in range(k):  # drive artificials out of the basis (they are at zero)
        if basis[j] >= nreal:
            for c in range(nreal):
                if abs(t[j, c]) > 1e-9:
                    _pivot(t, j, c)
                    basis[j] = c
                    break
    for j in range(k):  # a redundant row keeps its artificial at zero: blank its row's coupling
        if basis[j] >= nreal:
            t[j, :nreal] = 0.0
    if not _run(t, basis, nreal, p2):
        return np.nan
    return -t[p2, rhs]
