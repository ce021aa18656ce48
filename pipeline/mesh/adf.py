"""Approximate distance fields of triangle meshes (approximate-distance-fields.txt, sections 2-3).

Per triangle i (section 3.2.1), in coordinates normalised by the mesh size L
(x' = (x - centre) / L, so the constants a = 0.2, k = 2 of the paper keep their meaning):

* f  - signed distance to the carrier plane;
* p_j - signed distance to the plane through edge j orthogonal to the carrier plane, positive
  on the triangle's side;
* t = (p1 ^f p2) ^f p3 with the conditional R-conjunction of eq. 15,
  p1 ^f p2 = p1 + p2 - sqrt(p1^2 + p2^2 + a f^k)                            (eq. 15-16);
* h = sqrt(f^2 + (sqrt(t^2 + f^4) - t)^2 / 4)   (trimming, eq. 5; ``trim='eq4'`` uses |t| of eq. 4).

The triangle fields are joined into the unsigned field u by R-equivalence (eq. 6)
u = (sum h_i^-p)^(-1/p), or by the R-conjunction chain of eq. 7
u = (((h1 ^ h2) ^ h3) ...), h1 ^ h2 = h1 + h2 - (h1^p + h2^p)^(1/p). The FRep field is
F = L * s(x) * u, with s = +1 inside, -1 outside by mesh containment (generalised winding
number >= 1/2, Van Oosterom-Strackee solid angles).

Rigorous bounds: every step is monotone in its arguments - eq. 15 is nondecreasing in p1, p2
and nonincreasing in f^2, h of eq. 4/5 is nonincreasing in t and nondecreasing in f^2, and
eq. 6 and eq. 7 are nondecreasing in each h_i - so interval propagation from the exact
ranges of the affine f, p_j over a box encloses u. u vanishes on the surface, so a box with
lower bound u_lo > 0 does not meet the surface and has one containment sign, taken at its
centre; otherwise the enclosure is [-u_hi, u_hi].
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import prange

from pipeline.util.jit import njit

if TYPE_CHECKING:  # trimesh takes ~0.3 s to import; only the type is needed here
    import trimesh

TRIM_A = 0.2  # eq. 15 constants of section 3.2.1
TRIM_K = 2


@njit(cache=True)
def _cand(p1: float, p2: float, f2: float) -> float:
    """Conditional R-conjunction of eq. 15 with k = 2 (f2 = f^2)."""
    return p1 + p2 - np.sqrt(p1 * p1 + p2 * p2 + TRIM_A * f2)


@njit(cache=True)
def _trim(f2: float, t: float, smooth: bool) -> float:
    """Trimming of eq. 5 (smooth) or eq. 4, written with f2 = f^2."""
    g = np.sqrt(t * t + f2 * f2) - t if smooth else abs(t) - t
    return np.sqrt(f2 + 0.25 * g * g)


@njit(cache=True)
def _affine(planes, i, j, x) -> float:
    return planes[i, j, 0] * x[0] + planes[i, j, 1] * x[1] + planes[i, j, 2] * x[2] + planes[i, j, 3]


@njit(cache=True)
def _affine_range(planes, i, j, lo, hi):
    mid = planes[i, j, 3]
    rad = 0.0
    for c in range(3):
        mid += planes[i, j, c] * 0.5 * (lo[c] + hi[c])
        rad += abs(planes[i, j, c]) * 0.5 * (hi[c] - lo[c])
    return mid - rad, mid + rad


@njit(cache=True)
def _tri_field(planes, i, x, smooth) -> float:
    f = _affine(planes, i, 0, x)
    f2 = f * f
    t = _cand(_cand(_affine(planes, i, 1, x), _affine(planes, i, 2, x), f2), _affine(planes, i, 3, x), f2)
    return _trim(f2, t, smooth)


@njit(cache=True)
def _tri_range(planes, i, lo, hi, smooth):
    """Enclosure of the triangle field h_i over a box (monotone propagation)."""
    flo, fhi = _affine_range(planes, i, 0, lo, hi)
    f2lo = 0.0 if flo <= 0.0 <= fhi else min(flo * flo, fhi * fhi)
    f2hi = max(flo * flo, fhi * fhi)
    a1, b1 = _affine_range(planes, i, 1, lo, hi)
    a2, b2 = _affine_range(planes, i, 2, lo, hi)
    a3, b3 = _affine_range(planes, i, 3, lo, hi)
    tlo = _cand(_cand(a1, a2, f2hi), a3, f2hi)
    thi = _cand(_cand(b1, b2, f2lo), b3, f2lo)
    return _trim(f2lo, thi, smooth), _trim(f2hi, tlo, smooth)


@njit(cache=True)
def _join(h, join: int, p: float) -> float:
    """Eq. 6 (join 0) or the eq. 7 chain (join 1) of the triangle fields h."""
    if join == 0:
        acc = 0.0
        for i in range(h.shape[0]):
            if h[i] <= 0.0:
                return 0.0
            acc += h[i] ** (-p)
        return acc ** (-1.0 / p)
    u = h[0]
    for i in range(1, h.shape[0]):
        u = u + h[i] - (u**p + h[i] ** p) ** (1.0 / p)
    return u


@njit(cache=True)
def _winding(x, tris) -> float:
    """Generalised winding number of the closed triangle set around x (Van Oosterom-Strackee)."""
    total = 0.0
    for i in range(tris.shape[0]):
        a = tris[i, 0] - x
        b = tris[i, 1] - x
        c = tris[i, 2] - x
        la, lb, lc = np.sqrt(a @ a), np.sqrt(b @ b), np.sqrt(c @ c)
        det = a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) \
            + a[2] * (b[0] * c[1] - b[1] * c[0])
        den = la * lb * lc + (a @ b) * lc + (b @ c) * la + (c @ a) * lb
        total += 2.0 * np.arctan2(det, den)
    return total / (4.0 * np.pi)


@njit(parallel=True, cache=True)
def _eval_adf(points, planes, tris, join, p, smooth):
    n = points.shape[0]
    out = np.empty(n)
    for k in prange(n):
        h = np.empty(planes.shape[0])
        for i in range(planes.shape[0]):
            h[i] = _tri_field(planes, i, points[k], smooth)
        u = _join(h, join, p)
        out[k] = u if _winding(points[k], tris) >= 0.5 else -u
    return out


@njit(parallel=True, cache=True)
def _bound_adf(lo, hi, planes, tris, join, p, smooth, pad):
    nb = lo.shape[0]
    flo = np.empty(nb)
    fhi = np.empty(nb)
    for k in prange(nb):
        hl = np.empty(planes.shape[0])
        hh = np.empty(planes.shape[0])
        for i in range(planes.shape[0]):
            hl[i], hh[i] = _tri_range(planes, i, lo[k], hi[k], smooth)
        ulo = max(_join(hl, join, p) - pad, 0.0)
        uhi = _join(hh, join, p) + pad
        if ulo > 0.0:
            inside = _winding(0.5 * (lo[k] + hi[k]), tris) >= 0.5
            flo[k], fhi[k] = (ulo, uhi) if inside else (-uhi, -ulo)
        else:
            flo[k], fhi[k] = -uhi, uhi
    return flo, fhi


def triangle_planes(tris: np.ndarray) -> np.ndarray:
    """(F, 4, 4) plane rows [n, c] per triangle: carrier plane f, then the three edge planes p_j.

    Edge plane j passes through edge (v_j, v_j+1), is orthogonal to the carrier plane and is
    positive on the side of the opposite vertex; all normals are unit (normal functions).
    """
    e = [tris[:, (j + 1) % 3] - tris[:, j] for j in range(3)]
    nrm = np.cross(e[0], -e[2])
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    out = np.empty((len(tris), 4, 4))
    out[:, 0, :3] = nrm
    out[:, 0, 3] = -np.einsum("ij,ij->i", nrm, tris[:, 0])
    for j in range(3):
        m = np.cross(nrm, e[j])  # in-plane, orthogonal to the edge, towards the interior (CCW)
        m /= np.linalg.norm(m, axis=1)[:, None]
        out[:, j + 1, :3] = m
        out[:, j + 1, 3] = -np.einsum("ij,ij->i", m, tris[:, j])
    return out


class ADFField:
    """Signed approximate distance field of a triangle mesh by trimming and joining."""

    def __init__(self, tris: np.ndarray, join: str, p: float, trim: str):
        if join not in ("requiv", "rconj"):
            raise ValueError(f"join must be 'requiv' or 'rconj', got {join!r}")
        if trim not in ("eq4", "eq5"):
            raise ValueError(f"trim must be 'eq4' or 'eq5', got {trim!r}")
        if p < 1:
            raise ValueError(f"p must be >= 1, got {p}")
        pts = tris.reshape(-1, 3)
        self.centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        self.size = float(np.linalg.norm(np.ptp(pts, axis=0))) or 1.0
        self.tris = np.ascontiguousarray((tris - self.centre) / self.size)
        self.planes = np.ascontiguousarray(triangle_planes(self.tris))
        self.join, self.p, self.trim = join, float(p), trim

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, join: str = "requiv", p: float = 2,
                  trim: str = "eq5") -> ADFField:
        """Build from a triangle mesh (degenerate triangles are dropped)."""
        tris = np.asarray(mesh.triangles, dtype=np.float64)
        tris = tris[mesh.area_faces > 1e-14 * max(mesh.scale, 1e-300) ** 2]
        if len(tris) == 0:
            raise ValueError("mesh has no non-degenerate triangles")
        return cls(tris, join, p, trim)

    def _args(self):
        return self.planes, self.tris, 0 if self.join == "requiv" else 1, self.p, self.trim == "eq5"

    def _local(self, x: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray((np.asarray(x, dtype=np.float64).reshape(-1, 3) - self.centre)
                                    / self.size)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Signed field (N,) at points (N, 3): positive inside, zero on the triangles."""
        return self.size * _eval_adf(self._local(points), *self._args())

    def bound(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rigorous enclosure (flo, fhi) of the field over each box [lo_i, hi_i] (B, 3)."""
        a, b = _bound_adf(self._local(lo), self._local(hi), *self._args(), 1e-12)
        return self.size * a, self.size * b
