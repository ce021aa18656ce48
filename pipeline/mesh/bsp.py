"""BSP-fields: exact C1 scalar fields of polygonal objects (bsp-fields.txt, sections 3.2-3.3).

Pipeline:

1. :func:`merge_coplanar` joins edge-connected triangles (segments in 2D) that share one
   supporting plane into planar polygons. A polygon keeps its triangulation ("pieces") so
   that polygons with holes and non-convex polygons need no special code; Table 1 of the
   paper counts these unique supporting planes, not triangles.
2. :func:`build_tree` is ``Build_Tree`` of section 3.3.1: select a polygon, take its plane as
   the cut plane, classify every other polygon as positive / negative / spanning, split the
   spanning ones (``Split_Polygon``) and recurse. Polygons lying in the cut plane with the
   same orientation are stored in the node (they share its plane); coplanar polygons of the
   opposite orientation go to the negative list. Plane selection (section 3.3.3): ``naive``
   (random, seeded) or ``optimised`` (a plane with Ksplit = 0 if there is one, else the
   maximum of K = Kdist * Kangle * Ktree).
3. The tree is compiled to flat arrays in post-order and evaluated with Numba by the formula
   of section 3.3.2::

       f = fa                                     pos = 0, neg = 0
       f = fa AND fb                              pos != 0, neg = 0
       f = fa OR fc                               pos = 0, neg != 0
       f = ((fa OR fc) AND fb) OR (-fa AND fc)    otherwise  (eq. 4)

   with fa the signed distance to the node plane (positive on the inner side of its faces),
   fb / fc the fields of the positive / negative subtree. The two-operation special cases of
   section 3.2, ``(A OR C) AND B`` and ``(NOT A OR B) AND C``, are used where they are proven
   valid (see :func:`_special_case`).
4. ``bound(lo, hi)``: interval propagation through the same formula. Plane distances are
   affine, so their range over a box is exact; every R-function family of
   :mod:`pipeline.field.rfunctions` is nondecreasing in each argument, so propagating
   [F(lo1, lo2), F(hi1, hi2)] is rigorous (the result is widened by a few ulps of the scale
   to absorb rounding).

The code is dimension independent: a 2D polygon is given by its boundary segments and the
same functions build and evaluate its tree.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numba import prange
from scipy.optimize import linprog

from pipeline.field.rfunctions import FAMILIES, SARDF_K
from pipeline.field.rkernels import and_rows
from pipeline.field.small_lp import max_margin
from pipeline.mesh import bsp_minmax
from pipeline.mesh.bsp_build import BIG_NODE, plane_ids, subtree_sizes
from pipeline.mesh.bsp_build import build as _build_compiled
from pipeline.mesh.bsp_minmax import GENERAL, LEAF_NODE, NEG_ONLY, POS_ONLY, SPECIAL_B, SPECIAL_C
from pipeline.util.jit import njit

if TYPE_CHECKING:  # trimesh takes ~0.3 s to import; only the type is needed here
    import trimesh

FAMILY_CODE = {name: i for i, name in enumerate(FAMILIES)}  # min_max 0, r0 1, sardf 2
KD_MIN = 2048  # optimised trees of meshes above this many triangles start with median cuts ...
KD_LEAF = 64  # ... down to nodes of this many triangles (see _build_tree_compiled)
SMALL_MESH = 50000  # triangles up to which the compiled plane selection searches twice as much
R0_SCALE = 2.0  # magnitude control of r0/sardf, in mesh diagonals (see BSPField.magnitude_scale)

# node modes of the compiled tree: LEAF_NODE, POS_ONLY, NEG_ONLY, GENERAL, SPECIAL_B, SPECIAL_C (0..5)
MODE_OPS = np.array([0, 1, 1, 4, 2, 2])  # binary R-functions per node mode


# R-functions: pipeline.field.rkernels (r_and / r_or with the family codes of FAMILY_CODE)


LANES = 256  # points (or boxes) per block of the tree kernel: its rows stay in L1/L2


@njit(cache=True)
def tree_slots(pos: np.ndarray, neg: np.ndarray) -> tuple[np.ndarray, int]:
    """Row of each node's value in the tree kernel's block (a register allocation of the
    post-order tree): a node's row is taken before its children's rows are freed, so no node
    writes the row it reads (LLVM's alias check would fall back to scalar code). About the
    tree's depth rows in all (23 for elephant's 13,018 nodes)."""
    m = pos.shape[0]
    slot = np.empty(m, np.int64)
    free = np.empty(m + 2, np.int64)
    nfree = 0
    top = 0
    for j in range(m):
        if nfree > 0:
            nfree -= 1
            slot[j] = free[nfree]
        else:
            slot[j] = top
            top += 1
        for child in (pos[j], neg[j]):
            if child >= 0:
                free[nfree] = slot[child]
                nfree += 1
    return slot, top


@njit(cache=True)
def _node_rows(md, fa, nfa, fb, fc, out, t1, t2, n, fam, k, cc):
    """One node of the section 3.3.2 formula over a block's rows (modes 4, 5: the section 3.2
    special cases). ``nfa`` is the row that stands for -fa: -fa itself at points, the other end
    of fa's interval (negated) when the rows are a bound (every R-function is nondecreasing in
    each argument, so the lower bound takes -fa's lower end, -hi(fa))."""
    if md == 0:
        out[:n] = fa[:n]
    elif md == 1:  # fa AND fb
        and_rows(fa, 1.0, fb, 1.0, 1.0, out, n, fam, k, cc)
    elif md == 2:  # fa OR fc
        and_rows(fa, -1.0, fc, -1.0, -1.0, out, n, fam, k, cc)
    elif md == 3:  # ((fa OR fc) AND fb) OR (-fa AND fc), eq. 4
        and_rows(fa, -1.0, fc, -1.0, -1.0, t1, n, fam, k, cc)
        and_rows(t1, 1.0, fb, 1.0, 1.0, t2, n, fam, k, cc)
        and_rows(nfa, 1.0, fc, 1.0, 1.0, t1, n, fam, k, cc)
        and_rows(t2, -1.0, t1, -1.0, -1.0, out, n, fam, k, cc)
    elif md == 4:  # (fa OR fc) AND fb
        and_rows(fa, -1.0, fc, -1.0, -1.0, t1, n, fam, k, cc)
        and_rows(t1, 1.0, fb, 1.0, 1.0, out, n, fam, k, cc)
    else:  # (-fa OR fb) AND fc
        and_rows(nfa, -1.0, fb, -1.0, -1.0, t1, n, fam, k, cc)
        and_rows(t1, 1.0, fc, 1.0, 1.0, out, n, fam, k, cc)


@njit(cache=True)
def _plane_rows(j, normals, offsets, mid, half, n, side, pad, fa, nfa):
    """fa and the -fa row of node j's plane over a block: the signed distance at points
    (side 0), the lower (side -1) or upper (+1) end of its range over boxes (exact for an affine
    function: centre -+ radius), widened by ``pad``."""
    o = offsets[j]
    d = normals.shape[1]
    if d == 3:  # one pass over the block (the common case)
        w0, w1, w2 = normals[j, 0], normals[j, 1], normals[j, 2]
        for i in range(n):
            fa[i] = o + w0 * mid[0, i] + w1 * mid[1, i] + w2 * mid[2, i]
    else:
        for i in range(n):
            fa[i] = o
        for c in range(d):
            w = normals[j, c]
            for i in range(n):
                fa[i] += w * mid[c, i]
    if side == 0:
        for i in range(n):
            nfa[i] = -fa[i]
        return
    for i in range(n):
        nfa[i] = pad
    for c in range(d):
        w = abs(normals[j, c])
        for i in range(n):
            nfa[i] += w * half[c, i]  # the radius, widened
    for i in range(n):
        r = side * nfa[i]
        centre = fa[i]
        fa[i] = centre + r
        nfa[i] = r - centre


@njit(parallel=True, cache=True)
def _tree_lanes(mid, half, side, pad, normals, offsets, pos, neg, mode, slot, nslots, fam, k, cc):
    """The tree's field (side 0) at points ``mid`` (d, N), or the lower (side -1) / upper (+1)
    end of its interval over the boxes mid +- half, node by node over blocks of LANES points:
    each node is a few loops over a block's rows that LLVM vectorises (AVX), where a point-by-
    point walk of the tree spends ~15 ns per node and point (elephant, r0: 5x to 20x faster).
    Nodes are in post-order (children first, root last)."""
    d, n = mid.shape
    out = np.empty(n)
    m = normals.shape[0]
    for blk in prange((n + LANES - 1) // LANES):
        s0 = blk * LANES
        cnt = min(n, s0 + LANES) - s0
        regs = np.empty((nslots, LANES))
        fa = np.empty(LANES)
        nfa = np.empty(LANES)
        t1 = np.empty(LANES)
        t2 = np.empty(LANES)
        bm = np.ascontiguousarray(mid[:, s0:s0 + cnt])
        bh = np.ascontiguousarray(half[:, s0:s0 + cnt])
        for j in range(m):
            _plane_rows(j, normals, offsets, bm, bh, cnt, side, pad, fa, nfa)
            fb = regs[slot[pos[j]]] if pos[j] >= 0 else t2
            fc = regs[slot[neg[j]]] if neg[j] >= 0 else t2
            r = regs[slot[j]]
            _node_rows(mode[j], fa, nfa, fb, fc, r, t1, t2, cnt, fam, k, cc)
            if side != 0:  # rounding of every node (the widening of the old interval walk)
                for i in range(cnt):
                    r[i] += side * pad
        out[s0:s0 + cnt] = regs[slot[m - 1], :cnt]
    return out


def evaluate_tree(tree, points: np.ndarray, rfunc: str, cc: float = np.inf, slots=None) -> np.ndarray:
    """The field of ``tree`` at points (N, d), every node at every point (no short-circuit),
    with R-functions ``rfunc`` and the magnitude control ``cc``."""
    slot, nslots = tree_slots(tree.pos, tree.neg) if slots is None else slots
    mid = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, tree.normals.shape[1]).T)
    return _tree_lanes(mid, mid, 0, 0.0, tree.normals, tree.offsets, tree.pos, tree.neg, tree.mode, slot, nslots,
                       FAMILY_CODE[rfunc], SARDF_K, cc)


# --------------------------------------------------------------------------- planar polygons


@dataclass
class Polygons:
    """Planar polygons, each a set of simplex pieces (triangles in 3D, segments in 2D).

    ``pieces`` (P, d, d): piece vertices, grouped contiguously by polygon; ``owner`` (P,):
    polygon index of each piece; ``normal`` (Q, d) unit inward normals and ``offset`` (Q,), so
    that the plane field n.x + c is positive on the inner side; ``plane_id`` (Q,) labels
    polygons lying on one supporting plane with one orientation.
    """

    pieces: np.ndarray
    owner: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    plane_id: np.ndarray

    @property
    def count(self) -> int:
        return len(self.normal)


def simplex_planes(pieces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inward unit normals, offsets and measures (area / length) of oriented simplices.

    3D: outward normal (v1 - v0) x (v2 - v0) (counter-clockwise seen from outside).
    2D: segment a -> b of a counter-clockwise boundary, inner side on the left.
    """
    d = pieces.shape[1]
    if d == 3:
        raw = -np.cross(pieces[:, 1] - pieces[:, 0], pieces[:, 2] - pieces[:, 0])
        meas = 0.5 * np.linalg.norm(raw, axis=1)
    elif d == 2:
        e = pieces[:, 1] - pieces[:, 0]
        raw = np.stack([-e[:, 1], e[:, 0]], axis=1)
        meas = np.linalg.norm(raw, axis=1)
    else:
        raise ValueError(f"only 2D and 3D polygons are supported, got dimension {d}")
    norm = np.linalg.norm(raw, axis=1)
    n = raw / np.where(norm > 0, norm, 1.0)[:, None]
    c = -np.einsum("ij,ij->i", n, pieces[:, 0])
    return n, c, meas


def _adjacent_pairs(faces: np.ndarray) -> np.ndarray:
    """Pairs of simplices sharing a facet (an edge in 3D, a vertex in 2D)."""
    d = faces.shape[1]
    facets, who = [], []
    for skip in range(d):
        cols = [j for j in range(d) if j != skip]
        facets.append(np.sort(faces[:, cols], axis=1))
        who.append(np.arange(len(faces)))
    f = np.concatenate(facets)
    w = np.concatenate(who)
    nv = int(faces.max()) + 1 if faces.size else 1
    key = f[:, 0].astype(np.int64)
    for col in range(1, f.shape[1]):  # one integer per facet: a 1D sort instead of a row unique
        key = key * nv + f[:, col]
    order = np.argsort(key, kind="stable")
    inv_s, w_s = key[order], w[order]
    same = inv_s[1:] == inv_s[:-1]
    return np.stack([w_s[:-1][same], w_s[1:][same]], axis=1)


def _union_find(n: int, pairs: np.ndarray) -> np.ndarray:
    """Connected-component labels 0..k-1 of n items joined by pairs."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    g = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def merge_coplanar(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-9) -> Polygons:
    """Merge edge-connected coplanar simplices into planar polygons (Table 1 "planes").

    Two adjacent simplices merge when their unit normals differ by less than ``tol`` and each
    one's vertices lie within ``tol * scale`` of the other's plane (scale = bounding-box
    diagonal). A merged polygon gets the area-weighted plane of its pieces; if some vertex
    then lies farther than ``tol * scale`` from it (tolerance drift along a chain), the group
    is kept unmerged, so every polygon's plane contains its vertices to ``tol * scale``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    pieces = vertices[faces]
    scale = float(np.linalg.norm(np.ptp(vertices, axis=0))) or 1.0
    n, c, meas = simplex_planes(pieces)
    keep = meas > (tol * scale) ** (pieces.shape[1] - 1)
    pieces, n, c, meas, faces = pieces[keep], n[keep], c[keep], meas[keep], faces[keep]
    pairs = _adjacent_pairs(faces)
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        ok = np.linalg.norm(n[i] - n[j], axis=1) < tol
        di = np.abs(np.einsum("ikd,id->ik", pieces[j], n[i]) + c[i][:, None]).max(axis=1)
        dj = np.abs(np.einsum("ikd,id->ik", pieces[i], n[j]) + c[j][:, None]).max(axis=1)
        pairs = pairs[ok & (di < tol * scale) & (dj < tol * scale)]
    labels = _union_find(len(pieces), pairs) if len(pairs) else np.arange(len(pieces))
    labels = _refit_groups(pieces, n, meas, labels, tol * scale)
    return _polygons_from_labels(pieces, n, meas, labels, tol)


def _group_planes(pieces, n, meas, labels):
    q = labels.max() + 1
    nsum = np.zeros((q, n.shape[1]))
    np.add.at(nsum, labels, n * meas[:, None])
    nn = nsum / np.linalg.norm(nsum, axis=1)[:, None]
    proj = np.einsum("ikd,id->ik", pieces, nn[labels])
    csum = np.zeros(q)
    np.add.at(csum, labels, proj.sum(axis=1))
    cnt = np.bincount(labels, minlength=q) * pieces.shape[1]
    cc = -csum / cnt
    dev = np.abs(proj + cc[labels][:, None]).max(axis=1)
    return nn, cc, dev


def _refit_groups(pieces, n, meas, labels, dist_tol):
    """Split merged groups whose common plane misses a vertex by more than dist_tol."""
    _, labels = np.unique(labels, return_inverse=True)
    _, _, dev = _group_planes(pieces, n, meas, labels)
    gdev = np.zeros(labels.max() + 1)
    np.maximum.at(gdev, labels, dev)
    bad = gdev[labels] > dist_tol
    labels = labels.copy()
    labels[bad] = labels.max() + 1 + np.arange(np.count_nonzero(bad))
    return np.unique(labels, return_inverse=True)[1]


def _polygons_from_labels(pieces, n, meas, labels, tol) -> Polygons:
    order = np.argsort(labels, kind="stable")
    pieces, n, meas, labels = pieces[order], n[order], meas[order], labels[order]
    nn, cc, _ = _group_planes(pieces, n, meas, labels)
    scale = float(np.linalg.norm(np.ptp(pieces.reshape(-1, pieces.shape[2]), axis=0))) or 1.0
    return Polygons(pieces, labels, nn, cc, _plane_ids(nn, cc, scale, tol))


def _plane_ids(n: np.ndarray, c: np.ndarray, scale: float, tol: float) -> np.ndarray:
    """Label oriented planes that agree to ``tol`` (normal) and ``tol * scale`` (offset)."""
    key = np.ascontiguousarray(np.concatenate([n, (c / scale)[:, None]], axis=1))
    order = np.lexsort(key.T[::-1])
    return plane_ids(key, order, 10 * tol)


# --------------------------------------------------------------------------- Build_Tree


@dataclass
class Tree:
    """BSP-tree in post-order: node j has plane normals[j], offsets[j], children pos/neg (-1 none)."""

    normals: np.ndarray
    offsets: np.ndarray
    pos: np.ndarray
    neg: np.ndarray
    mode: np.ndarray
    splits: int
    depth: int
    surface: np.ndarray | None = None  # triangles (T, 3, 3) of a closed mesh: the field's zero set


def _per_polygon(values: np.ndarray, owner: np.ndarray, q: int) -> tuple[np.ndarray, np.ndarray]:
    """Min and max over each polygon's pieces of per-piece values (pieces grouped by owner)."""
    starts = np.searchsorted(owner, np.arange(q))
    return np.minimum.reduceat(values, starts), np.maximum.reduceat(values, starts)


def _compact(polys: Polygons) -> Polygons:
    """Renumber polygons 0..Q-1 in order of appearance (pieces stay grouped)."""
    uniq, first, inv = np.unique(polys.owner, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))
    owner = rank[inv]
    order = np.argsort(owner, kind="stable")
    sel = uniq[np.argsort(first)]
    return Polygons(polys.pieces[order], owner[order], polys.normal[sel], polys.offset[sel],
                    polys.plane_id[sel])


def _subset(polys: Polygons, piece_mask: np.ndarray) -> Polygons:
    return _compact(Polygons(polys.pieces[piece_mask], polys.owner[piece_mask], polys.normal,
                             polys.offset, polys.plane_id))


def _clip_simplex(v: np.ndarray, s: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Split_Polygon for one piece: the parts with s >= 0 and s <= 0, re-triangulated."""
    d = v.shape[0]
    if d == 2:
        t = s[0] / (s[0] - s[1])
        p = v[0] + t * (v[1] - v[0])
        a, b = np.array([v[0], p]), np.array([p, v[1]])
        return ([a], [b]) if s[0] > 0 else ([b], [a])
    pos_loop, neg_loop = [], []
    for i in range(3):
        j = (i + 1) % 3
        if s[i] >= 0:
            pos_loop.append(v[i])
        if s[i] <= 0:
            neg_loop.append(v[i])
        if s[i] * s[j] < 0:
            p = v[i] + (s[i] / (s[i] - s[j])) * (v[j] - v[i])
            pos_loop.append(p)
            neg_loop.append(p)
    return _fan(pos_loop), _fan(neg_loop)


def _fan(loop: list[np.ndarray]) -> list[np.ndarray]:
    return [np.array([loop[0], loop[i], loop[i + 1]]) for i in range(1, len(loop) - 1)]


def _split_polygons(polys: Polygons, s_piece: np.ndarray, spanning: np.ndarray,
                    eps: float) -> tuple[list, list, list, list]:
    """Split every spanning polygon's pieces; returns pieces and owners of both sides."""
    if polys.pieces.shape[1] == 3:
        return _split_triangles(polys, s_piece, np.nonzero(spanning[polys.owner])[0], eps)
    pp, po, nps, no = [], [], [], []
    for idx in np.nonzero(spanning[polys.owner])[0]:
        s = np.where(np.abs(s_piece[idx]) <= eps, 0.0, s_piece[idx])
        v, own = polys.pieces[idx], polys.owner[idx]
        one_side = s.min() >= 0 or s.max() <= 0
        parts = (([v], []) if s.max() > 0 else ([], [v])) if one_side else _clip_simplex(v, s)
        pp += parts[0]
        po += [own] * len(parts[0])
        nps += parts[1]
        no += [own] * len(parts[1])
    return pp, po, nps, no


def _split_triangles(polys: Polygons, s_piece: np.ndarray, idx: np.ndarray, eps: float) -> tuple:
    """:func:`_split_polygons` for triangles, vectorised (the same parts, in the same order and
    computed by the same arithmetic as :func:`_clip_simplex`): median cuts split about one
    triangle per face of a large mesh, too many for a Python loop."""
    v = polys.pieces[idx]
    s = np.where(np.abs(s_piece[idx]) <= eps, 0.0, s_piece[idx])
    own = polys.owner[idx]
    one_side = (s.min(axis=1) >= 0) | (s.max(axis=1) <= 0)
    whole_pos = one_side & (s.max(axis=1) > 0)
    sides = []
    for keep in (lambda x: x >= 0, lambda x: x <= 0):  # the positive loop, then the negative one
        loop = np.zeros((len(v), 4, 3))
        cnt = np.zeros(len(v), np.int64)
        rows = np.arange(len(v))
        for i in range(3):
            j = (i + 1) % 3
            m = keep(s[:, i])
            loop[rows[m], cnt[m]] = v[m, i]
            cnt += m
            x = s[:, i] * s[:, j] < 0
            with np.errstate(all="ignore"):  # rows without a crossing divide 0 by 0; unused
                t = s[:, i] / (s[:, i] - s[:, j])
                p = v[:, i] + t[:, None] * (v[:, j] - v[:, i])
            loop[rows[x], cnt[x]] = p[x]
            cnt += x
        # fan: (0, 1, 2) and, for a quadrilateral, (0, 2, 3)
        tri = [np.stack([loop[:, 0], loop[:, k], loop[:, k + 1]], axis=1) for k in (1, 2)]
        ok = [(cnt >= 3) & ~one_side, (cnt >= 4) & ~one_side]
        sides.append((tri, ok))
    out = []
    for side, whole in ((0, whole_pos), (1, one_side & ~whole_pos)):
        tri, ok = sides[side]
        parts = np.concatenate([v[whole], tri[0][ok[0]], tri[1][ok[1]]])
        pidx = np.concatenate([idx[whole], idx[ok[0]], idx[ok[1]]])  # piece of each part
        order = np.argsort(np.concatenate([np.zeros(whole.sum(), np.int64), np.zeros(ok[0].sum(), np.int64),
                                           np.ones(ok[1].sum(), np.int64)]) + 2 * np.searchsorted(idx, pidx),
                           kind="stable")
        owners = np.concatenate([own[whole], own[ok[0]], own[ok[1]]])
        out += [parts[order], owners[order]]
    return out[0], out[1], out[2], out[3]


def _classify(polys: Polygons, n: np.ndarray, c: float, eps: float):
    """Signed vertex distances per piece and the per-polygon class.

    Returns s (P, d), cls (Q,): 0 coplanar same orientation, 1 positive, 2 negative,
    3 spanning, 4 coplanar opposite orientation.
    """
    s = polys.pieces @ n + c
    smin = _per_polygon(s.min(axis=1), polys.owner, polys.count)[0]
    smax = _per_polygon(s.max(axis=1), polys.owner, polys.count)[1]
    cls = np.full(polys.count, 3)
    cls[smin >= -eps] = 1
    cls[smax <= eps] = 2
    on = (smin >= -eps) & (smax <= eps)
    same = polys.normal @ n > 0
    cls[on & same] = 0
    cls[on & ~same] = 4
    return s, cls


def _partition(polys: Polygons, n: np.ndarray, c: float, eps: float):
    """Classify against the cut plane and split; returns (pos list, neg list, splits)."""
    s, cls = _classify(polys, n, c, eps)
    spanning = cls == 3
    pcls = cls[polys.owner]
    pos = _subset(polys, pcls == 1)
    neg = _subset(polys, (pcls == 2) | (pcls == 4))
    if spanning.any():
        pp, po, nps, no = _split_polygons(polys, s, spanning, eps)
        pos = _append(pos, polys, pp, po)
        neg = _append(neg, polys, nps, no)
    return pos, neg, int(spanning.sum())


def _append(base: Polygons, src: Polygons, pieces: list, owners: list) -> Polygons:
    """Add split parts (pieces of polygons of ``src``) as new polygons of ``base``."""
    if len(pieces) == 0:
        return base
    owners_a = np.asarray(owners)
    uniq, inv = np.unique(owners_a, return_inverse=True)
    new_owner = base.count + inv
    return _compact(Polygons(
        np.concatenate([base.pieces, np.asarray(pieces)]),
        np.concatenate([base.owner, new_owner]),
        np.concatenate([base.normal, src.normal[uniq]]),
        np.concatenate([base.offset, src.offset[uniq]]),
        np.concatenate([base.plane_id, src.plane_id[uniq]]),
    ))


def _candidate_scores(polys: Polygons, cand: np.ndarray, eps: float, chunk: int = 64) -> np.ndarray:
    """Section 3.3.3 criteria for candidate polygons: columns Ksplit, Kdist, Kangle, Ktree.

    Kdist: smallest distance to the plane of a vertex not on it. Kangle: smallest angle
    between the plane and a face not parallel to it (faces parallel to the plane are never
    split, so they would only zero the product without telling anything about sliver
    risk), folded to [0, pi/2]; pi/2 when every face is parallel. Ktree = min(Nf, Nb) /
    max(Nf, Nb). Vectorised over candidates in chunks.
    """
    out = np.empty((len(cand), 4))
    q = polys.count
    verts = polys.pieces.reshape(-1, polys.pieces.shape[2])
    starts = np.searchsorted(polys.owner, np.arange(q))
    d = polys.pieces.shape[1]
    for c0 in range(0, len(cand), chunk):
        cc = cand[c0:c0 + chunk]
        n, c = polys.normal[cc], polys.offset[cc]
        s = (verts @ n.T + c).reshape(len(polys.pieces), d, len(cc))
        smin = np.minimum.reduceat(s.min(axis=1), starts, axis=0)
        smax = np.maximum.reduceat(s.max(axis=1), starts, axis=0)
        on = (smin >= -eps) & (smax <= eps)
        front = (smin >= -eps) & ~on
        back = (smax <= eps) & ~on
        split = ~(front | back | on)
        a = np.abs(s).reshape(-1, len(cc))
        kdist = np.where(a > eps, a, np.inf).min(axis=0)
        cosang = np.abs(polys.normal @ n.T)
        tilted = (cosang < 1.0 - 1e-12) & ~on
        ang = np.where(tilted, np.arccos(np.clip(cosang, 0.0, 1.0)), np.inf).min(axis=0)
        nf, nb = front.sum(axis=0), back.sum(axis=0)
        ktree = np.where(np.maximum(nf, nb) > 0, np.minimum(nf, nb) / np.maximum(np.maximum(nf, nb), 1), 1.0)
        out[c0:c0 + chunk, 0] = split.sum(axis=0)
        out[c0:c0 + chunk, 1] = np.where(np.isfinite(kdist), kdist, 0.0)
        out[c0:c0 + chunk, 2] = np.where(np.isfinite(ang), ang, np.pi / 2)
        out[c0:c0 + chunk, 3] = ktree
    return out


def select_polygon(polys: Polygons, planes: str, rng: np.random.Generator, eps: float,
                   max_candidates: int) -> int:
    """Select_Polygon of section 3.3.1 with the two strategies of section 3.3.3.

    ``naive``: a uniformly random polygon. ``optimised``: among candidate planes (one polygon
    per distinct plane), the one
    with Ksplit = 0 and the largest K = Kdist * Kangle * Ktree if any has Ksplit = 0, else the
    one with the largest K (ties: fewer splits, then better balance). Lists with more than
    ``max_candidates`` distinct planes are sampled: a random subset of that size is scanned in
    chunks, stopping at the first chunk that contains a Ksplit = 0 plane (a cost cap for large
    meshes; lists of up to ``max_candidates`` planes are searched exhaustively).
    """
    if planes == "naive":
        return int(rng.integers(polys.count))
    _, cand = np.unique(polys.plane_id, return_index=True)
    if len(cand) > max_candidates:
        cand = _scan_large(polys, rng.permutation(cand)[:max_candidates], eps)
    sc = _candidate_scores(polys, cand, eps)
    k = sc[:, 1] * sc[:, 2] * sc[:, 3]
    zero = sc[:, 0] == 0
    if zero.any():
        idx = np.nonzero(zero)[0]
        best = idx[np.lexsort((-sc[idx, 3], -k[idx]))[0]]
    else:
        best = np.lexsort((-sc[:, 3], sc[:, 0], -k))[0]
    return int(cand[best])


def _scan_large(polys: Polygons, cand: np.ndarray, eps: float, chunk: int = 16) -> np.ndarray:
    """Candidates of a large list, scanned in random chunks; stop at the first chunk that holds a
    Ksplit = 0 plane (that plane is taken anyway by section 3.3.3), else keep them all."""
    for c0 in range(0, len(cand), chunk):
        part = cand[c0:c0 + chunk]
        if np.any(_candidate_scores(polys, part, eps)[:, 0] == 0):
            return part
    return cand


def build_tree(polys: Polygons, planes: str = "optimised", seed: int = 0, eps: float | None = None,
               max_candidates: int = 128, sample: int | None = None, work: int | None = None,
               rule: int = 2, engine: str = "auto", kd_leaf: int | None = KD_LEAF) -> Tree:
    """Build_Tree of section 3.3.1. ``engine``: "compiled" (3D, :mod:`pipeline.mesh.bsp_build`: at most
    ``max_candidates`` planes scored on at most ``sample`` triangles per node, about n log n),
    "python" (the NumPy reference, any dimension) or "auto" (compiled in 3D). ``work``: plane
    tests per triangle of a node that the compiled plane selection may spend (defaults: 2048 and
    64 up to SMALL_MESH triangles, 512 and 16 above, where the build time matters more).
    ``rule``: ranking of planes that split (:func:`pipeline.mesh.bsp_build._k`): 0 the paper's
    K = Kdist * Kangle * Ktree, 2 (default) Ktree / (1 + Ksplit), which gives far fewer splits on
    the CGAL meshes (bench/bsp_table1.py); Ksplit = 0 planes come first either way."""
    if planes not in ("naive", "optimised"):
        raise ValueError(f"planes must be 'naive' or 'optimised', got {planes!r}")
    pts = polys.pieces.reshape(-1, polys.pieces.shape[2])
    scale = float(np.linalg.norm(np.ptp(pts, axis=0))) or 1.0
    eps = 1e-9 * scale if eps is None else eps
    d = polys.pieces.shape[2]
    small = len(polys.pieces) <= SMALL_MESH
    sample = sample or (2048 if small else 512)
    work = work or (64 if small else 16)
    if engine == "compiled" or (engine == "auto" and d == 3):
        kd = kd_leaf if planes == "optimised" and kd_leaf and len(polys.pieces) > max(KD_MIN, kd_leaf) else 0
        return _build_tree_compiled(polys, planes == "naive", seed, eps, max_candidates, sample, work,
                                    rule, kd)
    return _build_tree_python(polys, planes, seed, eps, max_candidates)


def _build_tree_compiled(polys: Polygons, naive: bool, seed: int, eps: float, max_candidates: int,
                         sample: int, work: int, rule: int, kd_leaf: int = 0) -> Tree:
    """Run the compiled build; node planes are the selected polygons' planes and, with
    ``kd_leaf``, the median cuts (rows of ``pn`` after the polygons').

    Balanced top, optimised bottom: while a node holds more than ``kd_leaf`` triangles it is
    cut by the axis-aligned plane through the median of its triangles' centroids along their
    widest extent (the builder's own partition: spanning polygons are split, counted in
    ``splits``); smaller nodes get the optimised plane selection of section 3.3.3.

    Why: on a smooth, nearly convex surface every face plane has all other faces on one side
    (Ksplit = 0 everywhere), so the optimised selection builds a chain as deep as the mesh is
    large, and a point near the surface walks it and visits the sibling of every face plane that
    passes near it (hundreds on a 20k-face sphere). Cut planes that halve the list make the root
    path logarithmic; a point then meets only the few cut planes near it and the face planes of
    its own small list. The cut planes hold no polygon and both of their sides hold some, so
    their nodes take the general formula of section 3.3.2, which is exact for any plane: at a
    point of the positive side, sign(f) = sign(f_pos), so the zero set and the sign are the
    mesh's whatever plane the node cuts with."""
    nq = polys.count
    spare = 4 * len(polys.pieces) // kd_leaf + 64 if kd_leaf else 0
    pn = np.zeros((nq + spare, 4))
    pn[:nq, :3], pn[:nq, 3] = polys.normal, polys.offset
    q, pos, neg, dep, splits, pn = _build_compiled(
        np.ascontiguousarray(polys.pieces, dtype=np.float64), polys.owner.astype(np.int64), pn,
        polys.plane_id.astype(np.int64), naive, seed, eps, max_candidates, sample, work, rule, BIG_NODE, nq,
        kd_leaf)
    return _postorder(pn[q, :3], pn[q, 3], pos, neg, int(splits), int(dep.max()) + 1)


def _build_tree_python(polys: Polygons, planes: str, seed: int, eps: float, max_candidates: int) -> Tree:
    """NumPy Build_Tree (iterative, so deep naive trees do not hit recursion limits)."""
    rng = np.random.default_rng(seed)
    normals, offsets, pos, neg, depth = [], [], [], [], []
    splits = 0
    stack = [(polys, -1, 0, 0)]  # (polygon list, parent node, side 0 pos / 1 neg, depth)
    while stack:
        pl, parent, side, dep = stack.pop()
        q = select_polygon(pl, planes, rng, eps, max_candidates)
        node = len(normals)
        normals.append(pl.normal[q])
        offsets.append(pl.offset[q])
        pos.append(-1)
        neg.append(-1)
        depth.append(dep)
        if parent >= 0:
            (pos if side == 0 else neg)[parent] = node
        pl_pos, pl_neg, ns = _partition(pl, pl.normal[q], pl.offset[q], eps)
        splits += ns
        if pl_neg.count:
            stack.append((pl_neg, node, 1, dep + 1))
        if pl_pos.count:
            stack.append((pl_pos, node, 0, dep + 1))
    return _postorder(np.array(normals), np.array(offsets), np.array(pos), np.array(neg), splits,
                      max(depth) + 1)


def _postorder(normals, offsets, pos, neg, splits, depth) -> Tree:
    """Reorder preorder-created nodes so that children precede parents (root last)."""
    m = len(normals)
    order = np.arange(m)[::-1]
    new = np.empty(m, dtype=np.int64)
    new[order] = np.arange(m)
    remap = np.where(pos >= 0, new[np.maximum(pos, 0)], -1)[order]
    remapn = np.where(neg >= 0, new[np.maximum(neg, 0)], -1)[order]
    mode = np.where(remap >= 0, np.where(remapn >= 0, GENERAL, POS_ONLY),
                    np.where(remapn >= 0, NEG_ONLY, LEAF_NODE))
    return Tree(np.ascontiguousarray(normals[order]), offsets[order].copy(), remap.astype(np.int64),
                remapn.astype(np.int64), mode.astype(np.int64), splits, depth)


# --------------------------------------------------------------------------- special cases (3.2)


def _regions(tree: Tree, j: int, cache: dict, cap: int):
    """In- and out-cells of subtree j as lists of halfspace constraints (sign * (n.x + c) >= 0).

    The sets are global: the subtree's formula, with its verified special cases, has exactly
    this in-set everywhere (section 3.3.2 semantics S = (A n B) u (not A n C)). None when a
    list would exceed ``cap`` cells.
    """
    if j in cache:
        return cache[j]
    if cache["size"][j] + 1 > 2 * cap:  # a subtree of s nodes has s + 1 cells: too many
        return None
    res = None
    sides = []
    for child, sign in ((tree.pos[j], 1.0), (tree.neg[j], -1.0)):
        if child < 0:
            cell = [(j, sign)]
            sides.append(([cell], []) if sign > 0 else ([], [cell]))
            continue
        sub = _regions(tree, child, cache, cap)
        if sub is None:
            break
        sides.append(tuple([[(j, sign)] + r for r in lst] for lst in sub))
    if len(sides) == 2:
        ins, outs = sides[0][0] + sides[1][0], sides[0][1] + sides[1][1]
        res = (ins, outs) if max(len(ins), len(outs)) <= cap else None
    cache[j] = res
    return res


def _has_interior(tree: Tree, cons: list[tuple[int, float]], tol: float) -> bool:
    """Does the intersection of the halfspaces have an interior point (Chebyshev-type LP)?

    In 3D :func:`pipeline.field.small_lp.max_margin` solves it; scipy's HiGHS is asked only when that
    did not finish or its optimum lies within 100 tol of the threshold (HiGHS's own tolerances
    then decide, as before)."""
    d = tree.normals.shape[1]
    idx = np.array([c[0] for c in cons])
    sg = np.array([c[1] for c in cons])
    a = -(sg[:, None] * tree.normals[idx])
    b_ub = sg * tree.offsets[idx]
    t = max_margin(np.ascontiguousarray(a), np.ascontiguousarray(b_ub)) if d == 3 else np.nan
    if abs(t - tol) > 100.0 * tol:  # decided (NaN compares False): the compiled simplex, ~15 us
        return bool(t > tol)
    a_ub = np.concatenate([a, np.ones((len(cons), 1))], axis=1)  # -sg(n.x+c) + t <= 0
    t = _highs_margin(a_ub, b_ub)
    return bool(t is not None and t > tol)


def _highs_margin(a_ub: np.ndarray, b_ub: np.ndarray) -> float | None:
    """max t s.t. a_ub @ (x, t) <= b_ub, t <= 1 (x free) by HiGHS, as ``linprog(method="highs")``
    solves it: None unless optimal. scipy's linprog spends ~1 ms of Python per call on these tiny
    problems (input checks, option validation, the result object); the same HiGHS model with the
    same options is built here directly (~0.2 ms), and its optimum is the one linprog returns,
    to the bit (checked in tests/test_bsp.py). linprog is the fallback when scipy's internal
    HiGHS module is not there."""
    hs = _highs_core()
    d1 = a_ub.shape[1]
    if hs is None:
        cost = np.zeros(d1)
        cost[-1] = -1.0
        r = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * (d1 - 1) + [(None, 1.0)], method="highs")
        return -float(r.fun) if r.status == 0 else None
    h, opts = hs
    m = a_ub.shape[0]
    nz = a_ub.T != 0  # CSC without explicit zeros (as linprog's csc_array of the dense matrix)
    lp = h.HighsLp()
    lp.num_col_ = d1
    lp.num_row_ = m
    lp.a_matrix_.num_col_ = d1
    lp.a_matrix_.num_row_ = m
    lp.a_matrix_.format_ = h.MatrixFormat.kColwise
    cost = np.zeros(d1)
    cost[-1] = -1.0
    lp.col_cost_ = cost
    lp.col_lower_ = np.full(d1, -h.kHighsInf)
    upper = np.full(d1, h.kHighsInf)
    upper[-1] = 1.0
    lp.col_upper_ = upper
    lp.row_lower_ = np.full(m, -h.kHighsInf)
    lp.row_upper_ = np.array(b_ub, dtype=np.float64)
    lp.a_matrix_.start_ = np.concatenate([[0], np.cumsum(nz.sum(axis=1))]).astype(np.int32)
    lp.a_matrix_.index_ = np.nonzero(nz)[1].astype(np.int32)
    lp.a_matrix_.value_ = a_ub.T[nz]
    solver = h._Highs()
    solver.passOptions(opts)
    solver.passModel(lp)
    solver.run()
    if solver.getModelStatus() != h.HighsModelStatus.kOptimal:
        return None
    # linprog's own check of the solution (scipy _check_result: violations beyond 10 sqrt(1e-9))
    sol = solver.getSolution()
    x = np.asarray(sol.col_value)
    slack = lp.row_upper_ - np.asarray(sol.row_value)
    fun = float(solver.getInfo().objective_function_value)
    chk = 10.0 * np.sqrt(1e-9)
    if np.isnan(fun) or np.isnan(x).any() or np.isnan(slack).any() or (slack < -chk).any() or x[-1] > 1.0 + chk:
        return None
    return -fun


_HIGHS: list = []


def _highs_core():
    """(scipy's HiGHS module, the options linprog(method="highs") passes), or None."""
    if not _HIGHS:
        try:
            from scipy.optimize._highspy import _core as h
            from scipy.optimize._highspy._core.simplex_constants import SimplexStrategy

            opts = h.HighsOptions()
            opts.presolve = "on"
            opts.highs_debug_level = h.HighsDebugLevel.kHighsDebugLevelNone
            opts.log_to_console = False
            opts.output_flag = False
            opts.simplex_strategy = SimplexStrategy.kSimplexStrategyDual
            _HIGHS.append((h, opts))
        except (ImportError, AttributeError):
            _HIGHS.append(None)
    return _HIGHS[0]


def _contained(tree, inner, outer_out, side, tol, budget) -> bool:
    """inner-cells n outer-out-cells n side-halfspace all without interior (inner within outer)."""
    for a in inner:
        for b in outer_out:
            if budget[0] <= 0:
                return False
            budget[0] -= 1
            if _has_interior(tree, a + b + side, tol):
                return False
    return True


def _special_case(tree: Tree, j: int, cache: dict, tol: float, budget: list, cap: int) -> int:
    """Mode for a node with both subtrees: SPECIAL_B, SPECIAL_C or GENERAL (section 3.2).

    (A u C) n B equals (A n B) u (not A n C) everywhere iff C lies within B on the negative side
    of the plane; (not A u B) n C iff B lies within C on the positive side. Both are checked
    exactly with linear programs over the convex in/out cells of the subtrees.
    """
    rb = _regions(tree, int(tree.pos[j]), cache, cap)
    rc = _regions(tree, int(tree.neg[j]), cache, cap)
    if rb is None or rc is None or len(rc[0]) * len(rb[1]) + len(rb[0]) * len(rc[1]) > budget[0]:
        return GENERAL
    if _contained(tree, rc[0], rb[1], [(j, -1.0)], tol, budget):
        return SPECIAL_B
    if _contained(tree, rb[0], rc[1], [(j, 1.0)], tol, budget):
        return SPECIAL_C
    return GENERAL


def apply_special_cases(tree: Tree, tol: float, budget: int | None = None, cap: int = 24) -> Tree:
    """Replace the 4-operation formula by a verified 2-operation special case where possible.

    Cells of a subtree are only enumerated up to ``cap`` per subtree (so only nodes whose two
    subtrees are small are checked, and the recursion depth stays below 2 * cap) and at most
    ``budget`` linear programs are solved and at most ``budget`` nodes examined per tree, so
    large meshes keep a bounded build time (a tree of median cuts has a small-subtree node per
    64 triangles: enumerating all their cells took 5.5 s of an 82k-face build); nodes not
    checked keep the general formula, which is always correct. Default budget: 4000 up to 2000
    nodes, 500 above (an LP takes about 15 us to a millisecond; the count applied is the
    ``special_cases`` entry of the stats).
    """
    if budget is None:
        budget = 4000 if len(tree.mode) <= 2000 else 500
    size = _subtree_sizes(tree.pos, tree.neg)
    cache: dict = {"size": size}
    left = [budget]
    mode = tree.mode.copy()
    small = np.zeros(len(mode) + 1, dtype=bool)
    small[:-1] = size + 1 <= 2 * cap
    general = np.nonzero((mode == GENERAL) & small[tree.pos] & small[tree.neg])[0][:budget]
    for j in general:  # post-order: children are final before their parent
        if left[0] <= 0:
            break
        mode[j] = _special_case(tree, int(j), cache, tol, left, cap)
    return Tree(tree.normals, tree.offsets, tree.pos, tree.neg, mode, tree.splits, tree.depth)


def _subtree_sizes(pos: np.ndarray, neg: np.ndarray) -> np.ndarray:
    """Nodes per subtree of a post-order tree."""
    return subtree_sizes(pos.astype(np.int64), neg.astype(np.int64))


# --------------------------------------------------------------------------- public field


class BSPField:
    """Exact field of a closed polygonal object from its BSP-tree (bsp-fields.txt section 3).

    f > 0 inside, f = 0 on the faces, f < 0 outside; ``rfunc`` is one of
    ``min_max``, ``r0``, ``sardf`` (:mod:`pipeline.field.rfunctions`).
    """

    def __init__(self, tree: Tree, rfunc: str, stats: dict, scale: float):
        if rfunc not in FAMILY_CODE:
            raise ValueError(f"rfunc must be one of {FAMILIES}, got {rfunc!r}")
        self.tree = tree
        self.rfunc = rfunc
        self.stats = stats
        self.scale = scale
        self.dim = tree.normals.shape[1]
        self.surface = None  # a closed mesh's triangles (T, 3, 3), set by from_mesh: the zero set

    @classmethod
    def from_polygons(cls, vertices: np.ndarray, faces: np.ndarray, rfunc: str = "r0",
                      planes: str = "optimised", seed: int = 0, special_cases: bool = True,
                      max_candidates: int = 128) -> BSPField:
        """Build from oriented simplices: triangles (outward CCW) in 3D, CCW segments in 2D."""
        polys = merge_coplanar(vertices, faces)
        scale = float(np.linalg.norm(np.ptp(np.asarray(vertices, float), axis=0))) or 1.0
        tree = build_tree(polys, planes, seed, max_candidates=max_candidates)
        if special_cases:
            tree = apply_special_cases(tree, 1e-9 * scale)
        stats = {
            "faces": int(len(faces)),
            "polygons": int(polys.count),
            "planes": int(len(np.unique(polys.plane_id))),
            "splits": int(tree.splits),
            "set_operations": int(MODE_OPS[tree.mode].sum()),
            "depth": int(tree.depth),
            "nodes": int(len(tree.mode)),
            "special_cases": int(np.count_nonzero(tree.mode >= SPECIAL_B)),
        }
        return cls(tree, rfunc, stats, scale)

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, rfunc: str = "r0", planes: str = "optimised",
                  seed: int = 0, special_cases: bool = True, max_candidates: int = 128) -> BSPField:
        """Build from a triangle mesh; inward-oriented closed meshes are flipped first."""
        faces = np.asarray(mesh.faces, dtype=np.int64)
        if mesh.is_watertight and mesh.volume < 0:
            faces = faces[:, ::-1]
        field = cls.from_polygons(mesh.vertices, faces, rfunc, planes, seed, special_cases, max_candidates)
        if mesh.is_watertight and mesh.is_winding_consistent:  # the zero set is this surface
            field.surface = np.asarray(mesh.vertices, dtype=np.float64)[faces]
        return field

    @classmethod
    def from_polygon2d(cls, loops: list[np.ndarray], **kw) -> BSPField:
        """2D polygon from closed vertex loops (outer loops CCW, holes CW)."""
        verts, edges, base = [], [], 0
        for loop in loops:
            m = len(loop)
            verts.append(np.asarray(loop, float))
            edges.append(np.stack([np.arange(m), (np.arange(m) + 1) % m], axis=1) + base)
            base += m
        return cls.from_polygons(np.concatenate(verts), np.concatenate(edges), **kw)

    def with_rfunc(self, rfunc: str) -> BSPField:
        """The same tree evaluated with another R-function family (no rebuild)."""
        other = BSPField(self.tree, rfunc, dict(self.stats), self.scale)
        other.surface = self.surface
        return other

    def _args(self):
        t = self.tree
        if getattr(self, "_slots", None) is None:
            self._slots = tree_slots(t.pos, t.neg)
        slot, nslots = self._slots
        return (t.normals, t.offsets, t.pos, t.neg, t.mode, slot, nslots, FAMILY_CODE[self.rfunc], SARDF_K,
                self.magnitude_scale)

    @property
    def magnitude_scale(self) -> float:
        """c of the r0/sardf magnitude control (pipeline.field.rfunctions.compress): twice the mesh's
        diagonal, so every value within a mesh diagonal of zero is eq. 2 itself."""
        return R0_SCALE * self.scale

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Field values (N,) at points (N, d)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, self.dim)
        if self._short_circuit:  # exact: the same values to the bit (pipeline.mesh.bsp_minmax)
            t = self.minmax_tree
            return bsp_minmax.eval_points(np.ascontiguousarray(p), t.normals, t.offsets, t.pos, t.neg, t.mode,
                                          t.depth)
        return evaluate_tree(self.tree, p, self.rfunc, self.magnitude_scale, self._args()[5:7])

    def bound(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rigorous (flo, fhi) over boxes [lo_i, hi_i] (B, d): the field on box i lies in it."""
        lo = np.asarray(lo, dtype=np.float64).reshape(-1, self.dim)
        hi = np.asarray(hi, dtype=np.float64).reshape(-1, self.dim)
        pad = 1e-14 * self.scale
        if self._short_circuit:
            t = self.minmax_tree
            return bsp_minmax.bound_boxes(np.ascontiguousarray(lo), np.ascontiguousarray(hi), t.normals, t.offsets,
                                          t.pos, t.neg, t.mode, pad, t.depth)
        mid = np.ascontiguousarray((0.5 * (lo + hi)).T)
        half = np.ascontiguousarray((0.5 * (hi - lo)).T)
        return _tree_lanes(mid, half, -1, pad, *self._args()), _tree_lanes(mid, half, 1, pad, *self._args())

    @property
    def _short_circuit(self) -> bool:
        """min_max in 3D has the exact short-circuit kernels; r0 and sardf depend on every node."""
        return self.rfunc == "min_max" and self.dim == 3

    @property
    def minmax_tree(self) -> Tree:
        """The evaluation tree of the min_max field (pipeline.mesh.bsp_minmax.regroup_chains: the
        same values, chains of min/max as balanced trees); ``depth``: its longest root path."""
        if getattr(self, "_minmax", None) is None:
            t = self.tree
            nn, oo, pp, qq, mm = bsp_minmax.regroup_chains(t.normals, t.offsets, t.pos, t.neg, t.mode)
            self._minmax = Tree(nn, oo, pp, qq, mm, t.splits, int(bsp_minmax.tree_depth(pp, qq)),
                                getattr(self, "surface", None))
        return self._minmax
