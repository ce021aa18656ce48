"""Distance from a voxel to the zero set of the piecewise-linear interpolant of sampled values.

Each cube of 2x2x2 samples is split into the six Kuhn (Freudenthal) tetrahedra that share the
cube's main diagonal; on a tetrahedron the linear interpolant's zero set is a triangle or a
planar quadrilateral through the edge crossings (marching tetrahedra). The distance from a
sample to that surface is exact for a planar zero set and, unlike the distance to the tangent
plane or to the axis crossings, stays close to the true one next to edges and corners of the
surface, where f has a kink (a voxel diagonal to a box's convex corner has no axis neighbour
across the surface at all).

Used by :func:`pipeline.distance.fim.init_interface` for the voxels next to a kink.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.util.jit import njit

# the Kuhn tetrahedra of the unit cube: from corner 0 to corner (1,1,1) one axis at a time,
# in each of the six orders
KUHN_PATHS = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]], np.int64)


@njit(cache=True, inline="always")
def origin_triangle_distance(ax, ay, az, bx, by, bz, cx, cy, cz):
    """Distance from the origin to triangle abc (Ericson 2005, "Real-Time Collision Detection",
    5.1.5: the Voronoi regions of the vertices, the edges, then the face). A degenerate
    (collinear) triangle, two crossings at one point where f is 0 at a sample: the nearest of
    its edges."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    ab2, ac2 = abx * abx + aby * aby + abz * abz, acx * acx + acy * acy + acz * acz
    if not nx * nx + ny * ny + nz * nz > 1e-20 * ab2 * ac2:  # degenerate: the nearest of its edges
        return min(_origin_segment_distance(ax, ay, az, bx, by, bz),
                   min(_origin_segment_distance(bx, by, bz, cx, cy, cz),
                       _origin_segment_distance(cx, cy, cz, ax, ay, az)))
    d1 = -(abx * ax + aby * ay + abz * az)  # ab . (p - a) with p = 0
    d2 = -(acx * ax + acy * ay + acz * az)
    if d1 <= 0.0 and d2 <= 0.0:
        return math.sqrt(ax * ax + ay * ay + az * az)
    d3 = -(abx * bx + aby * by + abz * bz)
    d4 = -(acx * bx + acy * by + acz * bz)
    if d3 >= 0.0 and d4 <= d3:
        return math.sqrt(bx * bx + by * by + bz * bz)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)  # d1 - d3 = |ab|^2 > 0: not degenerate
        return _norm(ax + v * abx, ay + v * aby, az + v * abz)
    d5 = -(abx * cx + aby * cy + abz * cz)
    d6 = -(acx * cx + acy * cy + acz * cz)
    if d6 >= 0.0 and d5 <= d6:
        return math.sqrt(cx * cx + cy * cy + cz * cz)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)  # |ac|^2
        return _norm(ax + w * acx, ay + w * acy, az + w * acz)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))  # |bc|^2
        return _norm(bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz))
    s = va + vb + vc  # |ab x ac|^2 > 0
    v, w = vb / s, vc / s
    return _norm(ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w)


@njit(cache=True, inline="always")
def _origin_segment_distance(ax, ay, az, bx, by, bz):
    ux, uy, uz = bx - ax, by - ay, bz - az
    uu = ux * ux + uy * uy + uz * uz
    t = 0.0 if uu == 0.0 else min(1.0, max(0.0, -(ax * ux + ay * uy + az * uz) / uu))
    return _norm(ax + t * ux, ay + t * uy, az + t * uz)


@njit(cache=True, inline="always")
def _norm(x, y, z):
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True, inline="always")
def _crossing(p, f, a, b, q, n):
    """The point where f's linear interpolant vanishes on edge (a, b) into q[n]."""
    t = f[a] / (f[a] - f[b])
    for d in range(3):
        q[n, d] = p[a, d] + t * (p[b, d] - p[a, d])


@njit(cache=True)
def tetra_zero_distance(p, f, q):
    """Distance from the origin to the zero set of the linear interpolant of ``f`` (4,) on the
    tetrahedron ``p`` (4, 3); inf without a sign change. ``q``: a (4, 3) work array."""
    npos = 0
    for v in range(4):
        npos += f[v] > 0.0
    if npos == 0 or npos == 4:
        return np.inf
    if npos == 2:  # a quadrilateral through the four edges between the two pairs
        p0 = p1 = n0 = n1 = -1
        for v in range(4):
            if f[v] > 0.0:
                if p0 < 0:
                    p0 = v
                else:
                    p1 = v
            elif n0 < 0:
                n0 = v
            else:
                n1 = v
        _crossing(p, f, p0, n0, q, 0)
        _crossing(p, f, p0, n1, q, 1)
        _crossing(p, f, p1, n1, q, 2)
        _crossing(p, f, p1, n0, q, 3)
        d = origin_triangle_distance(q[0, 0], q[0, 1], q[0, 2], q[1, 0], q[1, 1], q[1, 2], q[2, 0], q[2, 1], q[2, 2])
        return min(d, origin_triangle_distance(q[0, 0], q[0, 1], q[0, 2], q[2, 0], q[2, 1], q[2, 2],
                                               q[3, 0], q[3, 1], q[3, 2]))
    lone = -1  # one vertex on its own side: a triangle through its three edges
    for v in range(4):
        if (f[v] > 0.0) == (npos == 1):
            lone = v
    n = 0
    for v in range(4):
        if v != lone:
            _crossing(p, f, lone, v, q, n)
            n += 1
    return origin_triangle_distance(q[0, 0], q[0, 1], q[0, 2], q[1, 0], q[1, 1], q[1, 2], q[2, 0], q[2, 1], q[2, 2])


@njit(cache=True)
def zero_set_distance(fb, known, i, j, k):
    """Distance (voxels) from voxel (i, j, k) of the buffer ``fb`` to the zero set of the
    piecewise-linear interpolant on the Kuhn tetrahedra of the eight cubes that have the voxel
    as a corner; inf when none of them has a sign change. A cube with an unknown sample
    (``known`` False) is left out. The voxel is the first vertex of every tetrahedron of its
    cubes (the paths start there), so each distance is measured from the origin."""
    best = np.inf
    p = np.empty((4, 3))
    f = np.empty(4)
    q = np.empty((4, 3))
    for c in range(8):
        si, sj, sk = 2 * (c & 1) - 1, 2 * ((c >> 1) & 1) - 1, 2 * ((c >> 2) & 1) - 1
        npos = 0
        whole = True
        for e in range(8):
            a, b, g = i + si * (e & 1), j + sj * ((e >> 1) & 1), k + sk * ((e >> 2) & 1)
            whole = whole and known[a, b, g]
            npos += fb[a, b, g] > 0.0
        if not whole or npos == 0 or npos == 8:
            continue
        for t in range(6):
            x0 = x1 = x2 = 0
            for v in range(4):
                if v > 0:
                    axis = KUHN_PATHS[t, v - 1]
                    x0, x1, x2 = x0 | (axis == 0), x1 | (axis == 1), x2 | (axis == 2)
                p[v, 0], p[v, 1], p[v, 2] = si * x0, sj * x1, sk * x2
                f[v] = fb[i + si * x0, j + sj * x1, k + sk * x2]
            best = min(best, tetra_zero_distance(p, f, q))
    return best
