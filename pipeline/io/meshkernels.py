"""Compiled kernels for surface meshes and bulk grid reads (export stage): merging coincident
vertices with a hash table instead of a sort, triangle and vertex normals in one pass, and
grouping points by the grid chunk they fall in with a counting sort.

Each kernel does what the NumPy code it replaced did, value for value: the same float64
arithmetic for normals and the degenerate-triangle test, the same accumulation order for vertex
normals, exact bit equality of float32 coordinates for merging (as ``np.unique`` on the raw
bytes did: -0.0 and 0.0 stay distinct). Only the order of the merged vertices differs: first
occurrence instead of byte order.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from pipeline.util.jit import njit

_EMPTY = -1


@njit(cache=True)
def _hash3(a: np.uint64, b: np.uint64, c: np.uint64) -> np.uint64:
    h = a * np.uint64(0x9E3779B97F4A7C15)
    h ^= b * np.uint64(0xC2B2AE3D27D4EB4F)
    h ^= c * np.uint64(0x165667B19E3779F9)
    return h ^ (h >> np.uint64(29))


_SHARD_BITS = 6  # unique_rows_first: 64 hash tables of a few MB each (cache-sized at 10M points)


@njit(cache=True, parallel=True)
def unique_rows_first(bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rep, first) for rows of ``bits`` (N,3) uint32: ``rep[i]`` is the rank of row i's first
    occurrence among the distinct rows, ``first`` the index of each distinct row's first occurrence.

    The rows are split by the top bits of their hash into shards, each with its own open-addressing
    table (slots hold the row index of a first occurrence), filled in parallel in increasing row
    order, so every row finds its first occurrence; the ranks then follow in one ordered pass.
    Equal rows have equal hashes, so they always meet in one shard."""
    n = bits.shape[0]
    hashes = np.empty(n, np.uint64)
    for i in prange(n):
        hashes[i] = _hash3(np.uint64(bits[i, 0]), np.uint64(bits[i, 1]), np.uint64(bits[i, 2]))
    nshard = 1 << _SHARD_BITS
    shift = np.uint64(64 - _SHARD_BITS)
    starts = np.zeros(nshard + 1, np.int64)
    for i in range(n):
        starts[np.int64(hashes[i] >> shift) + 1] += 1
    for sh in range(nshard):
        starts[sh + 1] += starts[sh]
    pos = starts[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):  # increasing i within each shard
        sh = np.int64(hashes[i] >> shift)
        order[pos[sh]] = i
        pos[sh] += 1
    firstidx = np.empty(n, np.int64)
    for sh in prange(nshard):
        lo, hi = starts[sh], starts[sh + 1]
        size = 1
        while size < 2 * (hi - lo) + 2:
            size *= 2
        mask = np.uint64(size - 1)
        table = np.full(size, _EMPTY, np.int64)
        for q in range(lo, hi):
            i = order[q]
            slot = hashes[i] & mask
            while True:
                e = table[slot]
                if e == _EMPTY:
                    table[slot] = i
                    firstidx[i] = i
                    break
                if hashes[e] == hashes[i] and bits[e, 0] == bits[i, 0] and bits[e, 1] == bits[i, 1] \
                        and bits[e, 2] == bits[i, 2]:
                    firstidx[i] = e
                    break
                slot = (slot + np.uint64(1)) & mask
    rep = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    count = 0
    for i in range(n):  # a first occurrence precedes its repeats: their rank is known by then
        f = firstidx[i]
        if f == i:
            rep[i] = count
            first[count] = i
            count += 1
        else:
            rep[i] = rep[f]
    return rep, first[:count].copy()


@njit(cache=True)
def _nonzero_area(p: np.ndarray, a: int, b: int, c: int) -> bool:
    """(p[b] - p[a]) x (p[c] - p[a]) in float64 has a non-zero component."""
    ax, ay, az = np.float64(p[a, 0]), np.float64(p[a, 1]), np.float64(p[a, 2])
    ux, uy, uz = np.float64(p[b, 0]) - ax, np.float64(p[b, 1]) - ay, np.float64(p[b, 2]) - az
    vx, vy, vz = np.float64(p[c, 0]) - ax, np.float64(p[c, 1]) - ay, np.float64(p[c, 2]) - az
    return (uy * vz - uz * vy) != 0.0 or (uz * vx - ux * vz) != 0.0 or (ux * vy - uy * vx) != 0.0


@njit(cache=True)
def _compact(used: np.ndarray) -> tuple[np.ndarray, int]:
    """(new index of every used row in order, -1 for the others; how many are used)."""
    remap = np.full(len(used), -1, np.int64)
    count = 0
    for u in range(len(used)):
        if used[u]:
            remap[u] = count
            count += 1
    return remap, count


# Compiled functions here never call a parallel compiled function (unique_rows_first): they
# take its result from Python. A cached caller compiled in a process that loaded its parallel
# callee from the cache crashes when it is loaded later (numba issues #8578, #4807: the
# gufunc's native name differs between the processes); merge_kernel did, in `frepvdb convert
# x.vdb x.stl` after any run had written a .vtp (tests/test_numba_cache.py).


def weld_kernel(points: np.ndarray, bits: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical float32 points (``bits``: the points viewed as uint32), drop zero-area
    triangles (float64 cross product of the merged points, exactly zero), drop unused points.
    Returns (points, triangles). The per-triangle tests and the outputs are parallel passes; the
    used points and the output rows are counted in order, so the result does not depend on the
    threads."""
    rep, first = unique_rows_first(bits)
    return _weld_triangles(points, triangles, rep, first)


@njit(cache=True, parallel=True)
def _weld_triangles(points: np.ndarray, triangles: np.ndarray, rep: np.ndarray,
                    first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`weld_kernel` after the merge of the points."""
    m = triangles.shape[0]
    keep = np.zeros(m, np.bool_)
    for t in prange(m):
        a, b, c = rep[triangles[t, 0]], rep[triangles[t, 1]], rep[triangles[t, 2]]
        keep[t] = _nonzero_area(points, first[a], first[b], first[c])
    used = np.zeros(len(first), np.bool_)
    row_of = np.empty(m, np.int64)
    kept = 0
    for t in range(m):
        row_of[t] = kept
        if keep[t]:
            used[rep[triangles[t, 0]]] = True
            used[rep[triangles[t, 1]]] = True
            used[rep[triangles[t, 2]]] = True
            kept += 1
    remap, count = _compact(used)
    out_pts = np.empty((count, 3), np.float32)
    for u in prange(len(first)):
        if used[u]:
            out_pts[remap[u]] = points[first[u]]
    out_tris = np.empty((kept, 3), triangles.dtype)  # the index type of the input
    for t in prange(m):
        if keep[t]:
            for v in range(3):
                out_tris[row_of[t], v] = remap[rep[triangles[t, v]]]
    return out_pts, out_tris


@njit(cache=True)
def face_normals_kernel(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unnormalised float64 triangle normals (p1 - p0) x (p2 - p0)."""
    m = triangles.shape[0]
    out = np.empty((m, 3), np.float64)
    for t in range(m):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay, az = np.float64(points[a, 0]), np.float64(points[a, 1]), np.float64(points[a, 2])
        ux = np.float64(points[b, 0]) - ax
        uy = np.float64(points[b, 1]) - ay
        uz = np.float64(points[b, 2]) - az
        vx = np.float64(points[c, 0]) - ax
        vy = np.float64(points[c, 1]) - ay
        vz = np.float64(points[c, 2]) - az
        out[t, 0] = uy * vz - uz * vy
        out[t, 1] = uz * vx - ux * vz
        out[t, 2] = ux * vy - uy * vx
    return out


@njit(cache=True)
def vertex_normal_sums(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Sum of the unnormalised normals of the triangles at each vertex (float64, in triangle
    order: the order ``np.bincount`` over the flattened corners adds them in)."""
    acc = np.zeros((points.shape[0], 3), np.float64)
    face = face_normals_kernel(points, triangles)
    for t in range(triangles.shape[0]):
        for v in range(3):
            p = triangles[t, v]
            acc[p, 0] += face[t, 0]
            acc[p, 1] += face[t, 1]
            acc[p, 2] += face[t, 2]
    return acc


@njit(cache=True)
def group_by_id(ids: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Counting sort: (order, starts) with ``order[starts[g]:starts[g + 1]]`` the rows whose id is g,
    in their original order."""
    starts = np.zeros(n_groups + 1, np.int64)
    for i in range(ids.shape[0]):
        starts[ids[i] + 1] += 1
    for g in range(n_groups):
        starts[g + 1] += starts[g]
    pos = starts[:-1].copy()
    order = np.empty(ids.shape[0], np.int64)
    for i in range(ids.shape[0]):
        g = ids[i]
        order[pos[g]] = i
        pos[g] += 1
    return order, starts


@njit(cache=True)
def gather_chunk(out: np.ndarray, buf: np.ndarray, ijk: np.ndarray, rows: np.ndarray,
                 ox: int, oy: int, oz: int) -> None:
    """``out[r] = buf[ijk[r] - origin]`` for the rows ``rows`` (all inside ``buf``)."""
    for n in range(rows.shape[0]):
        r = rows[n]
        out[r] = buf[ijk[r, 0] - ox, ijk[r, 1] - oy, ijk[r, 2] - oz]


@njit(cache=True)
def centroid_voxels(points: np.ndarray, triangles: np.ndarray, voxel_size: float) -> np.ndarray:
    """The voxel nearest each triangle's centroid: rint(((p0 + p1 + p2) / 3) / voxel_size), the
    sum in float64 and in that order (as ``points[triangles].astype(float64).mean(axis=1)``)."""
    m = triangles.shape[0]
    out = np.empty((m, 3), np.int64)
    for t in range(m):
        for c in range(3):
            s = np.float64(points[triangles[t, 0], c]) + np.float64(points[triangles[t, 1], c])
            s += np.float64(points[triangles[t, 2], c])
            out[t, c] = np.int64(np.rint(s / 3.0 / voxel_size))
    return out


def split_polygons(tris: np.ndarray, quads: np.ndarray, flip: bool, out: np.ndarray | None = None) -> np.ndarray:
    """volumeToMesh's triangles, then each quad (a, b, c, d) as (a, b, c) and, after all of those,
    (a, c, d); every row reversed when ``flip``. Into ``out`` (T + 2Q, 3) of any integer type
    (int32 halves the mesh's largest array); int64 when None."""
    if out is None:
        out = np.empty((tris.shape[0] + 2 * quads.shape[0], 3), np.int64)
    _split_into(tris, quads, flip, out)
    return out


@njit(cache=True, parallel=True)
def _split_into(tris, quads, flip, out):
    nt, nq = tris.shape[0], quads.shape[0]
    first, last = (2, 0) if flip else (0, 2)
    for t in prange(nt):
        out[t, first], out[t, 1], out[t, last] = tris[t, 0], tris[t, 1], tris[t, 2]
    for q in prange(nq):
        a, b, c, d = quads[q, 0], quads[q, 1], quads[q, 2], quads[q, 3]
        out[nt + q, first], out[nt + q, 1], out[nt + q, last] = a, b, c
        out[nt + nq + q, first], out[nt + nq + q, 1], out[nt + nq + q, last] = a, c, d


@njit(cache=True)
def view_bounds(points: np.ndarray, right: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((3,) lo, hi) of the points and ((2,) lo, hi) of their projections on ``right`` and ``up``
    (as :func:`raster_surface` projects them), in one pass: NumPy's axis-0 reductions of a
    (5.6M, 3) array took 0.3 s each at 1024^3."""
    lo = np.full(5, np.inf)
    hi = np.full(5, -np.inf)
    for n in range(points.shape[0]):
        x, y, z = np.float64(points[n, 0]), np.float64(points[n, 1]), np.float64(points[n, 2])
        v = (x, y, z, x * right[0] + y * right[1] + z * right[2], x * up[0] + y * up[1] + z * up[2])
        for a in range(5):
            lo[a] = min(lo[a], v[a])
            hi[a] = max(hi[a], v[a])
    return lo, hi


@njit(cache=True)
def raster_surface(points: np.ndarray, triangles: np.ndarray, labels: np.ndarray, palette: np.ndarray,
                   right: np.ndarray, up: np.ndarray, eye: np.ndarray, light: np.ndarray,
                   x0: float, y0: float, scale: float, width: int, height: int) -> np.ndarray:
    """Orthographic z-buffer rendering of the front faces: RGBA (height, width, 4) float32, row 0
    at the bottom, alpha 0 where no face covers a pixel centre.

    A pixel at column i, row j samples the view-plane point (x0 + (i + 0.5) / scale,
    y0 + (j + 0.5) / scale); a face covers it when the point lies in the projected triangle
    (edge functions >= 0) and is nearer the eye than any face drawn there. Face colour:
    ``palette[(max(label, 1) - 1) % len(palette)]`` (``palette[0]`` without labels) times
    0.25 + 0.75 clip(n . light, 0, 1) for the unit face normal n (flat shading)."""
    img = np.zeros((height, width, 4), np.float32)
    zbuf = np.full((height, width), -np.inf)
    k = palette.shape[0]
    for t in range(triangles.shape[0]):
        ia, ib, ic = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay, az = np.float64(points[ia, 0]), np.float64(points[ia, 1]), np.float64(points[ia, 2])
        bx, by, bz = np.float64(points[ib, 0]), np.float64(points[ib, 1]), np.float64(points[ib, 2])
        cx, cy, cz = np.float64(points[ic, 0]), np.float64(points[ic, 1]), np.float64(points[ic, 2])
        ux, uy, uz = bx - ax, by - ay, bz - az
        vx, vy, vz = cx - ax, cy - ay, cz - az
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0.0 or nx * eye[0] + ny * eye[1] + nz * eye[2] <= 0.0:
            continue  # degenerate or facing away
        lit = (nx * light[0] + ny * light[1] + nz * light[2]) / length
        shade = 0.25 + 0.75 * min(max(lit, 0.0), 1.0)
        row = 0 if labels.shape[0] == 0 else (max(labels[t], 1) - 1) % k
        # screen positions (pixels) and depths of the corners
        pa_x = ((ax * right[0] + ay * right[1] + az * right[2]) - x0) * scale
        pa_y = ((ax * up[0] + ay * up[1] + az * up[2]) - y0) * scale
        pb_x = ((bx * right[0] + by * right[1] + bz * right[2]) - x0) * scale
        pb_y = ((bx * up[0] + by * up[1] + bz * up[2]) - y0) * scale
        pc_x = ((cx * right[0] + cy * right[1] + cz * right[2]) - x0) * scale
        pc_y = ((cx * up[0] + cy * up[1] + cz * up[2]) - y0) * scale
        za = ax * eye[0] + ay * eye[1] + az * eye[2]
        zb = bx * eye[0] + by * eye[1] + bz * eye[2]
        zc = cx * eye[0] + cy * eye[1] + cz * eye[2]
        area = (pb_x - pa_x) * (pc_y - pa_y) - (pb_y - pa_y) * (pc_x - pa_x)
        if area == 0.0:
            continue
        i0 = max(int(np.ceil(min(pa_x, pb_x, pc_x) - 0.5)), 0)
        i1 = min(int(np.floor(max(pa_x, pb_x, pc_x) - 0.5)), width - 1)
        j0 = max(int(np.ceil(min(pa_y, pb_y, pc_y) - 0.5)), 0)
        j1 = min(int(np.floor(max(pa_y, pb_y, pc_y) - 0.5)), height - 1)
        for j in range(j0, j1 + 1):
            py = j + 0.5
            for i in range(i0, i1 + 1):
                px = i + 0.5
                w0 = ((pc_x - pb_x) * (py - pb_y) - (pc_y - pb_y) * (px - pb_x)) / area
                w1 = ((pa_x - pc_x) * (py - pc_y) - (pa_y - pc_y) * (px - pc_x)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = w0 * za + w1 * zb + w2 * zc
                if z > zbuf[j, i]:
                    zbuf[j, i] = z
                    img[j, i, 0] = palette[row, 0] * shade
                    img[j, i, 1] = palette[row, 1] * shade
                    img[j, i, 2] = palette[row, 2] * shade
                    img[j, i, 3] = 1.0
    return img


@njit(cache=True)
def group_boxes(ijk: np.ndarray, order: np.ndarray, starts: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """(G, 2, 3) inclusive bounding box of the points of each group in ``groups`` (rows
    ``order[starts[g]:starts[g + 1]]``)."""
    out = np.empty((groups.shape[0], 2, 3), np.int64)
    for n in range(groups.shape[0]):
        g = groups[n]
        first = order[starts[g]]
        for a in range(3):
            out[n, 0, a] = ijk[first, a]
            out[n, 1, a] = ijk[first, a]
        for m in range(starts[g] + 1, starts[g + 1]):
            r = order[m]
            for a in range(3):
                v = ijk[r, a]
                if v < out[n, 0, a]:
                    out[n, 0, a] = v
                elif v > out[n, 1, a]:
                    out[n, 1, a] = v
    return out


@njit(cache=True)
def chunk_ids(ijk: np.ndarray, log2: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids, cmin, dims): the chunk ``ijk >> log2`` of every point as a row-major index into the
    chunks' bounding box, which starts at chunk ``cmin`` and spans ``dims`` chunks."""
    n = ijk.shape[0]
    cmin = np.empty(3, np.int64)
    cmax = np.empty(3, np.int64)
    for a in range(3):
        cmin[a] = ijk[0, a] >> log2
        cmax[a] = cmin[a]
    for r in range(1, n):
        for a in range(3):
            c = ijk[r, a] >> log2
            if c < cmin[a]:
                cmin[a] = c
            elif c > cmax[a]:
                cmax[a] = c
    dims = cmax - cmin + 1
    ids = np.empty(n, np.int64)
    for r in range(n):
        ids[r] = (((ijk[r, 0] >> log2) - cmin[0]) * dims[1] + ((ijk[r, 1] >> log2) - cmin[1])) * dims[2] + (
            (ijk[r, 2] >> log2) - cmin[2])
    return ids, cmin, dims


@njit(cache=True)
def unit_rows(acc: np.ndarray) -> np.ndarray:
    """float32 rows of ``acc`` divided by their length sqrt(x*x + y*y + z*z) (float64, summed in
    that order as ``np.linalg.norm(acc, axis=1)``); zero rows stay zero."""
    out = np.empty(acc.shape, np.float32)
    for r in range(acc.shape[0]):
        x, y, z = acc[r, 0], acc[r, 1], acc[r, 2]
        length = np.sqrt(x * x + y * y + z * z)
        if length <= 0.0:
            length = 1.0
        out[r, 0] = np.float32(x / length)
        out[r, 1] = np.float32(y / length)
        out[r, 2] = np.float32(z / length)
    return out


def merge_kernel(bits: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical rows of ``bits`` (points as uint32), drop triangles with a repeated
    vertex (zero-area ones with three distinct vertices stay) and unused points. Returns (the
    index of each kept point's first occurrence, triangles over the kept points)."""
    rep, first = unique_rows_first(bits)
    return _merge_triangles(triangles, rep, first)


@njit(cache=True)
def _merge_triangles(triangles: np.ndarray, rep: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_kernel` after the merge of the points."""
    m = triangles.shape[0]
    keep = np.zeros(m, np.bool_)
    used = np.zeros(len(first), np.bool_)
    kept = 0
    for t in range(m):
        a, b, c = rep[triangles[t, 0]], rep[triangles[t, 1]], rep[triangles[t, 2]]
        if a != b and b != c and a != c:
            keep[t] = True
            used[a] = True
            used[b] = True
            used[c] = True
            kept += 1
    remap, count = _compact(used)
    source = np.empty(count, np.int64)
    for u in range(len(first)):
        if used[u]:
            source[remap[u]] = first[u]
    out = np.empty((kept, 3), np.int64)
    row = 0
    for t in range(m):
        if keep[t]:
            for v in range(3):
                out[row, v] = remap[rep[triangles[t, v]]]
            row += 1
    return source, out
