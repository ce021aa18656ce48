"""C2 tricubic B-spline interpolation of a sparse block grid (HFRep step 3, eq. 20).

HFRep smooths the discrete unsigned distance with an at least C1 interpolation
``F_smDF = F_I o F_DF`` (hfrep seed, section 5.1 step 3 and section 6.2: "B-splines or
bicubic/tricubic splines"). We use the uniform cubic B-spline, which is C2, with
coefficients obtained by the exact prefilter of Unser, Aldroubi & Eden (1991): the
B-spline sampled at the integers is the filter (1, 4, 1)/6, whose inverse is a causal plus
anticausal recursive filter with pole z = sqrt(3) - 2, so the spline *interpolates* the
samples (a quasi-interpolant would not: it would move the zero-distance layer).

Sparse blocks: the separable prefilter runs along every maximal run of consecutive
blocks on each axis (mirror boundary at the run ends). Inside the block set it is the
exact global prefilter (the recursive filter's truncation is below 1e-12); within about
4 voxels of a run end (the border of the solved region, far from the surface when the
band is wider than that) the mirror condition makes interpolation approximate.

Evaluation at (N,3) world points is a Numba kernel on a dense block lattice (O(1) block
lookup, 64 coefficients per point). Fallback: a point whose 4^3 coefficient support
touches a block that does not exist gets ``fill`` (the grid background, e.g. the clamp
distance) and zero gradient; :meth:`TricubicSpline.supported` reports which points those
are.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.sparse.access import block_lattice, block_neighbours, lattice_row
from pipeline.sparse.grid import BlockGrid
from pipeline.util.jit import njit

POLE = math.sqrt(3.0) - 2.0


@njit(cache=True)
def _prefilter_line(s, out, tol):
    """Cubic B-spline coefficients of the 1-D samples ``s`` (mirror boundaries, Unser 1991)."""
    n = s.shape[0]
    z = POLE
    horizon = min(n, int(math.ceil(math.log(tol) / math.log(abs(z)))))
    zk = 1.0
    c0 = 0.0
    for k in range(horizon):
        c0 += zk * s[k]
        zk *= z
    out[0] = c0
    for k in range(1, n):
        out[k] = s[k] + z * out[k - 1]
    out[n - 1] = (z / (z * z - 1.0)) * (out[n - 1] + z * out[n - 2])
    for k in range(n - 2, -1, -1):
        out[k] = z * (out[k + 1] - out[k])
    for k in range(n):
        out[k] *= 6.0


@njit(cache=True)
def _prefilter_axis(c, nbr, axis, tol):
    """Prefilter ``c`` in place along ``axis`` over every maximal run of consecutive blocks."""
    nb = c.shape[0]
    chain = np.empty(nb, dtype=np.int64)
    line = np.empty(8 * nb)
    out = np.empty(8 * nb)
    for start in range(nb):
        if nbr[start, 2 * axis] >= 0:
            continue
        m = 0
        b = start
        while b >= 0:
            chain[m] = b
            m += 1
            b = nbr[b, 2 * axis + 1]
        for u in range(8):
            for v in range(8):
                for q in range(m):
                    for t in range(8):
                        line[8 * q + t] = _at(c, chain[q], axis, t, u, v)
                _prefilter_line(line[: 8 * m], out[: 8 * m], tol)
                for q in range(m):
                    for t in range(8):
                        _set(c, chain[q], axis, t, u, v, out[8 * q + t])


@njit(cache=True, inline="always")
def _at(c, b, axis, t, u, v):
    if axis == 0:
        return c[b, t, u, v]
    if axis == 1:
        return c[b, u, t, v]
    return c[b, u, v, t]


@njit(cache=True, inline="always")
def _set(c, b, axis, t, u, v, x):
    if axis == 0:
        c[b, t, u, v] = x
    elif axis == 1:
        c[b, u, t, v] = x
    else:
        c[b, u, v, t] = x


@njit(cache=True, inline="always")
def _bspline_weights(t, w, dw):
    """Cubic B-spline weights (and derivatives) of the 4 samples i-1..i+2 at i + t."""
    s = 1.0 - t
    w[0] = s * s * s / 6.0
    w[1] = (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0
    w[2] = (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0
    w[3] = t * t * t / 6.0
    dw[0] = -0.5 * s * s
    dw[1] = 1.5 * t * t - 2.0 * t
    dw[2] = -1.5 * t * t + t + 0.5
    dw[3] = 0.5 * t * t


@njit(cache=True)
def _eval_tricubic(coef, lattice, lat_lo, x, fill, val, grad, ok):
    """Tensor-product cubic B-spline value and index-space gradient at points ``x`` (N,3)."""
    wx = np.empty(4)
    wy = np.empty(4)
    wz = np.empty(4)
    dx = np.empty(4)
    dy = np.empty(4)
    dz = np.empty(4)
    for p in range(x.shape[0]):
        fi = math.floor(x[p, 0])
        fj = math.floor(x[p, 1])
        fk = math.floor(x[p, 2])
        _bspline_weights(x[p, 0] - fi, wx, dx)
        _bspline_weights(x[p, 1] - fj, wy, dy)
        _bspline_weights(x[p, 2] - fk, wz, dz)
        i0, j0, k0 = int(fi) - 1, int(fj) - 1, int(fk) - 1
        v = 0.0
        gx = 0.0
        gy = 0.0
        gz = 0.0
        good = True
        for a in range(4):
            for b in range(4):
                for c in range(4):
                    i, j, k = i0 + a, j0 + b, k0 + c
                    row = lattice_row(lattice, lat_lo, i, j, k)
                    if row < 0:
                        good = False
                        break
                    cf = coef[row, i & 7, j & 7, k & 7]
                    v += wx[a] * wy[b] * wz[c] * cf
                    gx += dx[a] * wy[b] * wz[c] * cf
                    gy += wx[a] * dy[b] * wz[c] * cf
                    gz += wx[a] * wy[b] * dz[c] * cf
                if not good:
                    break
            if not good:
                break
        ok[p] = good
        val[p] = v if good else fill
        grad[p, 0] = gx if good else 0.0
        grad[p, 1] = gy if good else 0.0
        grad[p, 2] = gz if good else 0.0


@njit(cache=True)
def _eval_trilinear(vals, lattice, lat_lo, x, fill, out):
    """Trilinear interpolation of the samples (C0 only: the comparison for the C1 tests)."""
    for p in range(x.shape[0]):
        fi = math.floor(x[p, 0])
        fj = math.floor(x[p, 1])
        fk = math.floor(x[p, 2])
        tx, ty, tz = x[p, 0] - fi, x[p, 1] - fj, x[p, 2] - fk
        v = 0.0
        good = True
        for a in range(2):
            for b in range(2):
                for c in range(2):
                    i, j, k = int(fi) + a, int(fj) + b, int(fk) + c
                    row = lattice_row(lattice, lat_lo, i, j, k)
                    if row < 0:
                        good = False
                        continue
                    w = (tx if a else 1 - tx) * (ty if b else 1 - ty) * (tz if c else 1 - tz)
                    v += w * vals[row, i & 7, j & 7, k & 7]
        out[p] = v if good else fill


class TricubicSpline:
    """Interpolating C2 tricubic B-spline over the blocks of a :class:`BlockGrid`.

    Inactive voxels take the grid's background before prefiltering (for an eikonal
    distance grid: the clamp distance beyond ``max_distance``). ``fill`` is returned for
    points whose support leaves the block set (default: the background).
    """

    def __init__(self, grid: BlockGrid, fill: float | None = None, tol: float = 1e-12) -> None:
        self.voxel_size = float(grid.voxel_size)
        self.fill = float(grid.background if fill is None else fill)
        samples = np.where(grid.active, grid.values, grid.background).astype(np.float64)
        self.samples = np.ascontiguousarray(samples)
        coef = self.samples.copy()
        nbr = block_neighbours(grid)
        for axis in range(3):
            _prefilter_axis(coef, nbr, axis, tol)
        self.coefficients = coef
        self.lattice, self.lattice_lo = block_lattice(grid.origins)

    def _index(self, points: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3) / self.voxel_size)

    def evaluate(self, points: np.ndarray, with_gradient: bool = False):
        """Values at (N,3) world points; with ``with_gradient`` also (N,3) world gradients."""
        x = self._index(points)
        val = np.empty(len(x))
        grad = np.empty((len(x), 3))
        ok = np.empty(len(x), dtype=bool)
        _eval_tricubic(self.coefficients, self.lattice, self.lattice_lo, x, self.fill, val, grad, ok)
        return (val, grad / self.voxel_size) if with_gradient else val

    __call__ = evaluate

    def gradient(self, points: np.ndarray) -> np.ndarray:
        """Analytic gradient (world units) of the spline at (N,3) world points."""
        return self.evaluate(points, with_gradient=True)[1]

    def supported(self, points: np.ndarray) -> np.ndarray:
        """True where the whole 4^3 support exists (the value is the spline, not ``fill``)."""
        x = self._index(points)
        val, grad, ok = np.empty(len(x)), np.empty((len(x), 3)), np.empty(len(x), dtype=bool)
        _eval_tricubic(self.coefficients, self.lattice, self.lattice_lo, x, self.fill, val, grad, ok)
        return ok

    def trilinear(self, points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of the same samples (C0; for comparisons and tests)."""
        x = self._index(points)
        out = np.empty(len(x))
        _eval_trilinear(self.samples, self.lattice, self.lattice_lo, x, self.fill, out)
        return out

