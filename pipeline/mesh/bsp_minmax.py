"""Exact short-circuit kernels of min_max BSP-fields (bsp-fields.txt, section 3.3.2 with eq. 1).

Node modes of a compiled BSP-tree (post-order arrays, root last; pipeline.mesh.bsp builds them) and
the section 3.3.2 formula with min/max R-functions::

    LEAF_NODE   f = fa
    POS_ONLY    f = min(fa, fb)
    NEG_ONLY    f = max(fa, fc)
    GENERAL     f = max(min(max(fa, fc), fb), min(-fa, fc))        (eq. 4)
    SPECIAL_B   f = min(max(fa, fc), fb)                           (section 3.2)
    SPECIAL_C   f = min(max(-fa, fb), fc)

**Short circuit.** At a point on the positive side of a GENERAL node's plane (fa >= 0), if
-fa <= fb <= fa then f = fb whatever fc is: max(fa, fc) >= fa >= fb, and min(-fa, fc) <= -fa <= fb.
Symmetrically on the negative side, |fc| <= -fa gives f = fc. SPECIAL_B with fa >= 0 and
fb <= fa is fb; SPECIAL_C with fa <= 0 and fc <= -fa is fc. So the subtree on the point's side
is evaluated first and the other one only when the rule fails. Near the surface (|f| small) a
point then visits about its root path instead of the whole tree (elephant, 10,426 nodes: ~100
visits), and the value is the same to the bit: a min/max composition returns one of its
operands, computed by the same arithmetic.

**Boxes.** The same rules hold on intervals (if they hold for the bounds they hold at every
point of the box), so a box is bounded visiting only the subtrees its rules cannot exclude. A
box also yields its **start node**: the deepest node reached from the start through nodes each
decided by one subtree over the whole box (for POS_ONLY, min(fa, fb), when fa >= fb on the
box; NEG_ONLY likewise). At every point of the box (and of any box inside
it) the field equals that node's field, so a cell's children and voxels start there: this is
the per-cell specialisation of a mesh clause of the tape (pipeline.model.tape).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from pipeline.util.jit import njit

# node modes of the compiled tree; MIN2 / MAX2 (no plane: min / max of the two subtrees) occur
# only in the evaluation tree of :func:`regroup_chains`
LEAF_NODE, POS_ONLY, NEG_ONLY, GENERAL, SPECIAL_B, SPECIAL_C, MIN2, MAX2 = range(8)
CHAIN_MIN = 8  # chains shorter than this stay as they are


@njit(cache=True, inline="always")
def _node(m, fa, fb, fc):
    """One node of the formula above (min/max R-functions)."""
    if m == POS_ONLY:
        return min(fa, fb)
    if m == NEG_ONLY:
        return max(fa, fc)
    if m == GENERAL:
        return max(min(max(fa, fc), fb), min(-fa, fc))
    if m == SPECIAL_B:
        return min(max(fa, fc), fb)
    if m == SPECIAL_C:
        return min(max(-fa, fb), fc)
    if m == MIN2:
        return min(fb, fc)
    if m == MAX2:
        return max(fb, fc)
    return fa


@njit(cache=True, inline="always")
def _node_box(m, alo, ahi, blo, bhi, clo, chi):
    """Interval of one node: min and max are nondecreasing, -fa is handled with swapped ends."""
    if m == POS_ONLY:
        return min(alo, blo), min(ahi, bhi)
    if m == NEG_ONLY:
        return max(alo, clo), max(ahi, chi)
    if m == GENERAL:
        return (max(min(max(alo, clo), blo), min(-ahi, clo)), max(min(max(ahi, chi), bhi), min(-alo, chi)))
    if m == SPECIAL_B:
        return min(max(alo, clo), blo), min(max(ahi, chi), bhi)
    if m == SPECIAL_C:
        return min(max(-ahi, blo), clo), min(max(-alo, bhi), chi)
    if m == MIN2:
        return min(blo, clo), min(bhi, chi)
    if m == MAX2:
        return max(blo, clo), max(bhi, chi)
    return alo, ahi


@njit(cache=True, inline="always")
def _first_is_pos(m, fa):
    """Which subtree to visit first: the one on the point's side of the plane."""
    return m == POS_ONLY or m == SPECIAL_B or m >= MIN2 or (m == GENERAL and fa >= 0.0)  # noqa: SIM109


@njit(cache=True, inline="always")
def _decided(m, s, alo, ahi, rlo, rhi):
    """Is the node's value its first subtree's ([rlo, rhi]) over the whole range [alo, ahi] of fa?
    ``s``: 1 when the positive subtree came first, 2 the negative."""
    if m == GENERAL:
        if s == 1:
            return alo >= 0.0 and -alo <= rlo and rhi <= alo
        return ahi <= 0.0 and ahi <= rlo and rhi <= -ahi
    if m == SPECIAL_B:
        return alo >= 0.0 and rhi <= alo
    if m == SPECIAL_C:
        return ahi <= 0.0 and rhi <= -ahi
    return False


@njit(cache=True, inline="always")
def _push(sj, top, state, child):
    """Record the state the frame at ``top`` resumes in and open a frame for ``child``."""
    sj[1, top] = state
    sj[0, top + 1] = child
    sj[1, top + 1] = 0
    return top + 1


@njit(cache=True)
def point_value(px, py, pz, start, normals, offsets, pos, neg, mode, sj, sv):
    """Field of the subtree rooted at ``start`` at (px, py, pz). ``sj`` (2, D) int64 and ``sv``
    (2, D) float64 are stack scratch, D >= the tree's depth + 1."""
    top = 0
    sj[0, 0] = start
    sj[1, 0] = 0
    ret = 0.0
    while top >= 0:
        j = sj[0, top]
        s = sj[1, top]
        m = mode[j]
        if s == 0:  # MIN2 / MAX2 have a zero plane: fa = 0, positive subtree first
            fa = offsets[j] + normals[j, 0] * px + normals[j, 1] * py + normals[j, 2] * pz
            if m == LEAF_NODE:
                ret = fa
                top -= 1
                continue
            sv[0, top] = fa
            first_pos = _first_is_pos(m, fa)
            top = _push(sj, top, 1 if first_pos else 2, pos[j] if first_pos else neg[j])
            continue
        fa = sv[0, top]
        if s <= 2:  # ret: the first subtree's value
            if m == POS_ONLY:
                ret = min(fa, ret)
            elif m == NEG_ONLY:
                ret = max(fa, ret)
            elif m >= MIN2 or not _decided(m, s, fa, fa, ret, ret):
                sv[1, top] = ret
                top = _push(sj, top, s + 2, neg[j] if s == 1 else pos[j])
                continue
            top -= 1
            continue
        fb = sv[1, top] if s == 3 else ret
        fc = ret if s == 3 else sv[1, top]
        ret = _node(m, fa, fb, fc)
        top -= 1
    return ret


@njit(cache=True)
def point_plane(px, py, pz, start, normals, offsets, pos, neg, mode, sj, sv):
    """:func:`point_value` that also says where the value comes from: (value, node, sign), the
    value being sign * (the plane of ``node`` at the point), exactly (min/max return one of their
    operands). The field's gradient there is sign * normals[node] (one-sided on a crease, where
    two planes give the same value). ``sj`` (4, D) int64, ``sv`` (2, D) float64: stack scratch."""
    top = 0
    sj[0, 0] = start
    sj[1, 0] = 0
    ret = 0.0
    rj, rs = start, 1
    while top >= 0:
        j = sj[0, top]
        s = sj[1, top]
        m = mode[j]
        if s == 0:
            fa = offsets[j] + normals[j, 0] * px + normals[j, 1] * py + normals[j, 2] * pz
            if m == LEAF_NODE:
                ret, rj, rs = fa, j, 1
                top -= 1
                continue
            sv[0, top] = fa
            first_pos = _first_is_pos(m, fa)
            top = _push(sj, top, 1 if first_pos else 2, pos[j] if first_pos else neg[j])
            continue
        fa = sv[0, top]
        if s <= 2:
            if m == POS_ONLY:
                if fa < ret:
                    ret, rj, rs = fa, j, 1
            elif m == NEG_ONLY:
                if fa > ret:
                    ret, rj, rs = fa, j, 1
            elif m >= MIN2 or not _decided(m, s, fa, fa, ret, ret):
                sv[1, top] = ret
                sj[2, top] = rj
                sj[3, top] = rs
                top = _push(sj, top, s + 2, neg[j] if s == 1 else pos[j])
                continue
            top -= 1
            continue
        if s == 3:
            fb, bj, bs, fc, cj, cs = sv[1, top], sj[2, top], sj[3, top], ret, rj, rs
        else:
            fb, bj, bs, fc, cj, cs = ret, rj, rs, sv[1, top], sj[2, top], sj[3, top]
        ret = _node(m, fa, fb, fc)
        if ret == fb:
            rj, rs = bj, bs
        elif ret == fc:
            rj, rs = cj, cs
        elif ret == fa:
            rj, rs = j, 1
        else:
            rj, rs = j, -1
        top -= 1
    return ret, rj, rs


@njit(cache=True)
def box_bound(lo0, lo1, lo2, hi0, hi1, hi2, start, normals, offsets, pos, neg, mode, pad, sj, sv):
    """(flo, fhi, start') over the box: the interval of the subtree at ``start`` (every interval
    widened by ``pad`` for rounding) and the box's start node (see the module docstring).
    ``sj`` (3, D) int64, ``sv`` (4, D) float64: stack scratch."""
    c0, c1, c2 = 0.5 * (lo0 + hi0), 0.5 * (lo1 + hi1), 0.5 * (lo2 + hi2)
    r0, r1, r2 = 0.5 * (hi0 - lo0), 0.5 * (hi1 - lo1), 0.5 * (hi2 - lo2)
    top = 0
    sj[0, 0] = start
    sj[1, 0] = 0
    rlo = rhi = 0.0
    rstart = start
    while top >= 0:
        j = sj[0, top]
        s = sj[1, top]
        m = mode[j]
        if s == 0:
            centre = offsets[j] + normals[j, 0] * c0 + normals[j, 1] * c1 + normals[j, 2] * c2
            rad = abs(normals[j, 0]) * r0 + abs(normals[j, 1]) * r1 + abs(normals[j, 2]) * r2
            alo = centre - rad - pad
            ahi = centre + rad + pad
            if m == LEAF_NODE:
                rlo, rhi, rstart = alo - pad, ahi + pad, j
                top -= 1
                continue
            sv[0, top] = alo
            sv[1, top] = ahi
            first_pos = _first_is_pos(m, alo)
            top = _push(sj, top, 1 if first_pos else 2, pos[j] if first_pos else neg[j])
            continue
        alo = sv[0, top]
        ahi = sv[1, top]
        if s <= 2:
            if m == POS_ONLY and not alo >= rhi:  # alo >= rhi: min(fa, fb) is fb on the box
                rlo, rhi, rstart = min(alo, rlo), min(ahi, rhi), j
            elif m == NEG_ONLY and not ahi <= rlo:  # max(fa, fc) is fc
                rlo, rhi, rstart = max(alo, rlo), max(ahi, rhi), j
            elif m >= MIN2 or (m != POS_ONLY and m != NEG_ONLY and not _decided(m, s, alo, ahi, rlo, rhi)):
                sv[2, top] = rlo
                sv[3, top] = rhi
                sj[2, top] = rstart
                top = _push(sj, top, s + 2, neg[j] if s == 1 else pos[j])
                continue
            # decided: the value (and the start node) is the first subtree's
            rlo -= pad
            rhi += pad
            top -= 1
            continue
        if s == 3:
            blo, bhi, clo, chi = sv[2, top], sv[3, top], rlo, rhi
        else:
            blo, bhi, clo, chi = rlo, rhi, sv[2, top], sv[3, top]
        if m >= MIN2:  # one subtree dominating over the box is the node there (start with it)
            low_first = (bhi <= clo) if m == MIN2 else (blo >= chi)
            low_second = (chi <= blo) if m == MIN2 else (clo >= bhi)
            if low_first:
                rlo, rhi, rstart = blo - pad, bhi + pad, sj[2, top]
                top -= 1
                continue
            if low_second:
                rlo, rhi = clo - pad, chi + pad  # rstart: the second subtree's, as returned
                top -= 1
                continue
        a, b = _node_box(m, alo, ahi, blo, bhi, clo, chi)
        rlo, rhi, rstart = a - pad, b + pad, j
        top -= 1
    return rlo, rhi, rstart


@njit(cache=True, inline="always")
def _emit(j, p, q, m, normals, offsets, cn, co, cp, cq, cm, k):
    """Copy node ``j``'s plane into slot ``k`` of a specialised tree, with children p, q and mode m."""
    cn[k, 0] = normals[j, 0]
    cn[k, 1] = normals[j, 1]
    cn[k, 2] = normals[j, 2]
    co[k] = offsets[j]
    cp[k] = p
    cq[k] = q
    cm[k] = m
    return k + 1


@njit(cache=True)
def specialise_box(lo0, lo1, lo2, hi0, hi1, hi2, start, normals, offsets, pos, neg, mode, pad, sj, sv,
                   cn, co, cp, cq, cm):
    """The subtree at ``start`` specialised to a box: the nodes the box cannot bypass, written in
    post-order into (cn, co, cp, cq, cm) (the layout of the tree's own arrays); returns the root.

    Same rules as :func:`box_bound`, applied to every node below the start instead of only on
    the way to it: a node whose value over the box is its first subtree's (``_decided``, or a
    POS_ONLY / NEG_ONLY whose plane never wins) is replaced by that subtree; a POS_ONLY /
    NEG_ONLY whose plane always wins (min(fa, fb) with fa <= fb on the box) becomes a leaf of
    its plane. Every replacement returns, at every point of the box, the operand the node would
    return, computed by the same arithmetic: the specialised tree gives the same values to the
    bit there. On a near-convex mesh (a chain of thousands of GENERAL nodes, every one decided
    away from its plane) a voxel block's tree keeps the few nodes whose planes pass near it.
    ``sj`` (3, D) int64, ``sv`` (4, D) float64: stack scratch, as box_bound's."""
    c0, c1, c2 = 0.5 * (lo0 + hi0), 0.5 * (lo1 + hi1), 0.5 * (lo2 + hi2)
    r0, r1, r2 = 0.5 * (hi0 - lo0), 0.5 * (hi1 - lo1), 0.5 * (hi2 - lo2)
    top = 0
    sj[0, 0] = start
    sj[1, 0] = 0
    rlo = rhi = 0.0
    ridx = -1
    k = 0
    while top >= 0:
        j = sj[0, top]
        s = sj[1, top]
        m = mode[j]
        if s == 0:
            centre = offsets[j] + normals[j, 0] * c0 + normals[j, 1] * c1 + normals[j, 2] * c2
            rad = abs(normals[j, 0]) * r0 + abs(normals[j, 1]) * r1 + abs(normals[j, 2]) * r2
            alo = centre - rad - pad
            ahi = centre + rad + pad
            if m == LEAF_NODE:
                rlo, rhi, ridx = alo - pad, ahi + pad, k
                k = _emit(j, -1, -1, LEAF_NODE, normals, offsets, cn, co, cp, cq, cm, k)
                top -= 1
                continue
            sv[0, top] = alo
            sv[1, top] = ahi
            first_pos = _first_is_pos(m, alo)
            top = _push(sj, top, 1 if first_pos else 2, pos[j] if first_pos else neg[j])
            continue
        alo = sv[0, top]
        ahi = sv[1, top]
        if s <= 2:
            if m == POS_ONLY or m == NEG_ONLY:  # noqa: SIM109 (plain compares in the kernel)
                own = alo >= rhi if m == POS_ONLY else ahi <= rlo  # the subtree always wins
                plane = ahi <= rlo if m == POS_ONLY else alo >= rhi  # the plane always wins
                if plane:
                    rlo, rhi, ridx = alo, ahi, k
                    k = _emit(j, -1, -1, LEAF_NODE, normals, offsets, cn, co, cp, cq, cm, k)
                elif not own:
                    if m == POS_ONLY:
                        rlo, rhi = min(alo, rlo), min(ahi, rhi)
                        k = _emit(j, ridx, -1, m, normals, offsets, cn, co, cp, cq, cm, k)
                    else:
                        rlo, rhi = max(alo, rlo), max(ahi, rhi)
                        k = _emit(j, -1, ridx, m, normals, offsets, cn, co, cp, cq, cm, k)
                    ridx = k - 1
            elif m >= MIN2 or not _decided(m, s, alo, ahi, rlo, rhi):
                sv[2, top] = rlo
                sv[3, top] = rhi
                sj[2, top] = ridx
                top = _push(sj, top, s + 2, neg[j] if s == 1 else pos[j])
                continue
            rlo -= pad
            rhi += pad
            top -= 1
            continue
        if s == 3:
            blo, bhi, clo, chi, bi, ci = sv[2, top], sv[3, top], rlo, rhi, sj[2, top], ridx
        else:
            blo, bhi, clo, chi, bi, ci = rlo, rhi, sv[2, top], sv[3, top], ridx, sj[2, top]
        if m >= MIN2:  # one subtree dominating over the box is the node there
            if (bhi <= clo) if m == MIN2 else (blo >= chi):
                rlo, rhi, ridx = blo - pad, bhi + pad, bi
                top -= 1
                continue
            if (chi <= blo) if m == MIN2 else (clo >= bhi):
                rlo, rhi, ridx = clo - pad, chi + pad, ci
                top -= 1
                continue
        a, b = _node_box(m, alo, ahi, blo, bhi, clo, chi)
        rlo, rhi, ridx = a - pad, b + pad, k
        k = _emit(j, bi, ci, m, normals, offsets, cn, co, cp, cq, cm, k)
        top -= 1
    return ridx


BLOCK_TREE_MAX = 4096  # nodes of a specialised tree evaluated tree-major (64 values a node: 2 MiB, in L2)


@njit(cache=True)
def block_values(px, py, pz, npt, root, normals, offsets, pos, neg, mode, reg, fa, out):
    """The field of a specialised tree (:func:`specialise_box`'s post-order output, root
    ``root``) at the points (px, py, pz)[:npt], tree-major: every node for all points at once,
    into ``out[:npt]``. ``reg`` (>= root + 1, >= npt) and ``fa`` (>= npt): scratch.

    A voxel block's tree keeps the planes near the block; on a smooth surface that is hundreds
    of nearly tied planes, and the point walk (:func:`point_value`) visits about half of them
    per voxel through its stack. Here each node is a plain loop over the points (the plane, then
    the node's min/max formula: vectorised), children before parents, so the values are the
    same operations on the same operands: equal to the point walk's to the bit (the short
    circuit only skips operands the formula would not return). Nodes that the specialisation
    left behind unused are evaluated too, at no risk: nothing reads them."""
    for k in range(root + 1):
        m = mode[k]
        n0, n1, n2, o = normals[k, 0], normals[k, 1], normals[k, 2], offsets[k]
        if m == LEAF_NODE:
            for v in range(npt):
                reg[k, v] = o + n0 * px[v] + n1 * py[v] + n2 * pz[v]
            continue
        ib, ic = pos[k], neg[k]
        if m == MIN2:
            for v in range(npt):
                reg[k, v] = min(reg[ib, v], reg[ic, v])
            continue
        if m == MAX2:
            for v in range(npt):
                reg[k, v] = max(reg[ib, v], reg[ic, v])
            continue
        for v in range(npt):
            fa[v] = o + n0 * px[v] + n1 * py[v] + n2 * pz[v]
        if m == POS_ONLY:
            for v in range(npt):
                reg[k, v] = min(fa[v], reg[ib, v])
        elif m == NEG_ONLY:
            for v in range(npt):
                reg[k, v] = max(fa[v], reg[ic, v])
        elif m == GENERAL:
            for v in range(npt):
                reg[k, v] = max(min(max(fa[v], reg[ic, v]), reg[ib, v]), min(-fa[v], reg[ic, v]))
        elif m == SPECIAL_B:
            for v in range(npt):
                reg[k, v] = min(max(fa[v], reg[ic, v]), reg[ib, v])
        else:  # SPECIAL_C
            for v in range(npt):
                reg[k, v] = min(max(-fa[v], reg[ib, v]), reg[ic, v])
    for v in range(npt):
        out[v] = reg[root, v]


@njit(parallel=True, cache=True)
def eval_points(points, normals, offsets, pos, neg, mode, depth):
    """Values (N,) of the whole tree at points (N, 3)."""
    n = points.shape[0]
    out = np.empty(n)
    root = normals.shape[0] - 1
    chunk = 1024
    for ch in prange((n + chunk - 1) // chunk):
        sj = np.empty((2, depth + 2), np.int64)
        sv = np.empty((2, depth + 2))
        for i in range(ch * chunk, min(n, (ch + 1) * chunk)):
            out[i] = point_value(points[i, 0], points[i, 1], points[i, 2], root, normals, offsets, pos, neg, mode,
                                 sj, sv)
    return out


@njit(parallel=True, cache=True)
def bound_boxes(lo, hi, normals, offsets, pos, neg, mode, pad, depth):
    """(flo, fhi) of the whole tree over boxes [lo_i, hi_i] (B, 3)."""
    nb = lo.shape[0]
    flo = np.empty(nb)
    fhi = np.empty(nb)
    root = normals.shape[0] - 1
    chunk = 64
    for ch in prange((nb + chunk - 1) // chunk):
        sj = np.empty((3, depth + 2), np.int64)
        sv = np.empty((4, depth + 2))
        for i in range(ch * chunk, min(nb, (ch + 1) * chunk)):
            flo[i], fhi[i], _ = box_bound(lo[i, 0], lo[i, 1], lo[i, 2], hi[i, 0], hi[i, 1], hi[i, 2], root, normals,
                                          offsets, pos, neg, mode, pad, sj, sv)
    return flo, fhi


@njit(cache=True)
def tree_depth(pos: np.ndarray, neg: np.ndarray) -> int:
    """Nodes on the longest root-to-leaf path of a post-order tree (the kernels' stack room)."""
    n = len(pos)
    dep = np.zeros(n, np.int64)
    for j in range(n):
        dmax = 0
        if pos[j] >= 0:
            dmax = dep[pos[j]]
        if neg[j] >= 0:
            dmax = max(dmax, dep[neg[j]])
        dep[j] = dmax + 1
    return int(dep.max()) if n else 0


def regroup_chains(normals, offsets, pos, neg, mode):
    """The evaluation tree of a min_max BSP-field: every chain of CHAIN_MIN or more POS_ONLY nodes
    (min(fa1, min(fa2, ... min(fak, f_tail)))) becomes a balanced tree of MIN2 nodes over the
    planes as leaves and the tail, the planes ordered by their normals (a Morton order of the
    normal's direction), so that the faces near a cell form a few subtrees the cell's bounds
    single out; NEG_ONLY chains likewise with MAX2. min and max are associative and commutative
    and return one of their operands, so the field is the same to the bit. A convex mesh's tree
    is one such chain (a displaced icosphere's nearly so): each voxel then takes the min over
    the few planes near it instead of over all of them.

    Returns (normals, offsets, pos, neg, mode) in post-order, root last."""
    n = len(mode)
    if n == 0:
        return normals, offsets, pos, neg, mode
    plane, p, q, m, cnt = _regroup(pos.astype(np.int64), neg.astype(np.int64), mode.astype(np.int64),
                                   _normal_keys(normals))
    plane, p, q, m = plane[:cnt], p[:cnt], q[:cnt], m[:cnt]
    has = plane >= 0
    nn = np.zeros((cnt, normals.shape[1]))
    oo = np.zeros(cnt)
    nn[has] = normals[plane[has]]
    oo[has] = offsets[plane[has]]
    return np.ascontiguousarray(nn), oo, p, q, m


@njit(cache=True)
def _regroup(pos, neg, mode, key):
    """:func:`regroup_chains` on the post-order arrays, children first: a node that continues a
    chain of CHAIN_MIN or more (its parent has its mode and it is the parent's min / max operand)
    is skipped, and the chain's top emits the balanced tree of the chain's planes and its tail.
    Returns per new node (plane node or -1, pos, neg, mode) and the node count."""
    n = len(mode)
    link = np.zeros(n, np.bool_)  # j continues its parent's chain
    for j in range(n):
        if mode[j] == POS_ONLY and pos[j] >= 0 and mode[pos[j]] == POS_ONLY:
            link[pos[j]] = True
        if mode[j] == NEG_ONLY and neg[j] >= 0 and mode[neg[j]] == NEG_ONLY:
            link[neg[j]] = True
    skip = np.zeros(n, np.bool_)
    chain_len = np.zeros(n, np.int64)
    for j in range(n):
        m = mode[j]
        if link[j] or (m != POS_ONLY and m != NEG_ONLY):
            continue
        length, k = 1, pos[j] if m == POS_ONLY else neg[j]
        while mode[k] == m:
            length += 1
            k = pos[k] if m == POS_ONLY else neg[k]
        chain_len[j] = length
        if length >= CHAIN_MIN:
            k = pos[j] if m == POS_ONLY else neg[j]
            while mode[k] == m:
                skip[k] = True
                k = pos[k] if m == POS_ONLY else neg[k]
    cap = 2 * n + 1
    plane = np.empty(cap, np.int64)
    op = np.empty(cap, np.int64)
    oq = np.empty(cap, np.int64)
    om = np.empty(cap, np.int64)
    res = np.full(n, -1, np.int64)
    items = np.empty(n + 1, np.int64)
    cnt = 0
    for j in range(n):
        if skip[j]:
            continue
        m = mode[j]
        if chain_len[j] >= CHAIN_MIN:
            members = np.empty(chain_len[j], np.int64)
            k, t = j, 0
            while mode[k] == m and t < chain_len[j]:
                members[t] = k
                t += 1
                k = pos[k] if m == POS_ONLY else neg[k]
            order = np.argsort(key[members], kind="mergesort")
            for t in range(len(members)):  # the planes as leaves, in normal order, then the tail
                plane[cnt], op[cnt], oq[cnt], om[cnt] = members[order[t]], -1, -1, LEAF_NODE
                items[t] = cnt
                cnt += 1
            items[len(members)] = res[k]
            size = len(members) + 1
            while size > 1:  # pair neighbours level by level
                half = 0
                for t in range(0, size, 2):
                    if t + 1 < size:
                        plane[cnt], op[cnt], oq[cnt] = -1, items[t], items[t + 1]
                        om[cnt] = MIN2 if m == POS_ONLY else MAX2
                        items[half] = cnt
                        cnt += 1
                    else:
                        items[half] = items[t]
                    half += 1
                size = half
            res[j] = items[0]
            continue
        plane[cnt] = j
        op[cnt] = res[pos[j]] if pos[j] >= 0 else -1
        oq[cnt] = res[neg[j]] if neg[j] >= 0 else -1
        om[cnt] = m
        res[j] = cnt
        cnt += 1
    return plane, op, oq, om, cnt


def _normal_keys(normals: np.ndarray) -> np.ndarray:
    """Morton code of each unit normal's (x, y, z) quantised to 10 bits: nearby directions,
    nearby keys."""
    q = np.clip(((normals + 1.0) * 0.5 * 1023).astype(np.int64), 0, 1023)
    key = np.zeros(len(normals), np.int64)
    for bit in range(10):
        for axis in range(normals.shape[1]):
            key |= ((q[:, axis] >> bit) & 1) << (bit * normals.shape[1] + axis)
    return key


# --- the surface: which boxes the zero set can meet ------------------------------------------------
#
# The zero set of the BSP-field of a closed mesh is its surface (bsp-fields.txt section 3.3.2: on a
# node's plane outside its polygons both sides have the same sign, so f != 0 there), to the build's
# tolerances (1e-9 x the mesh size: coplanar merges, splits). So a box that no triangle comes near
# holds no zero of the field and has one sign, the sign of any of its points: the voxeliser culls
# such boxes from a triangle BVH query and one point value instead of an interval walk of the tree
# over the box (pipeline.model.tape.bound_cull_decide), which on a smooth 50k-face mesh visits hundreds of
# nearly tied planes per box.

BVH_LEAF = 4  # triangles per BVH leaf
BVH_STACK = 128  # stack room of a query (the tree is balanced: depth ~ log2(triangles / BVH_LEAF))


@njit(cache=True)
def surface_bvh(tris):
    """A bounding-volume hierarchy of triangles (T, 3, 3): (tris in leaf order (T, 9), node boxes
    (N, 6) lo/hi, node children (N, 2) (-1: a leaf), node triangle spans (N, 2) first/count).
    Triangles are sorted by the Morton code of their centroids and split at the middle of each
    range (in whole leaves), so the tree is balanced; node 0 is the root, children come after their parent."""
    t = tris.shape[0]
    cen = np.empty((t, 3))
    for i in range(t):
        for d in range(3):
            cen[i, d] = (tris[i, 0, d] + tris[i, 1, d] + tris[i, 2, d]) / 3.0
    key = np.zeros(t, np.int64)
    if t:
        lo = np.empty(3)
        ext = np.empty(3)
        for d in range(3):
            lo[d] = cen[:, d].min()
            ext[d] = max(cen[:, d].max() - lo[d], 1e-300)
        for i in range(t):
            k = 0
            for bit in range(9, -1, -1):
                for d in range(3):
                    q = min(1023, max(0, int((cen[i, d] - lo[d]) / ext[d] * 1023.0)))
                    k = (k << 1) | ((q >> bit) & 1)
            key[i] = k
    order = np.argsort(key, kind="mergesort")
    flat = np.empty((t, 9))
    for i in range(t):
        for v in range(3):
            for d in range(3):
                flat[i, 3 * v + d] = tris[order[i], v, d]
    cap = 2 * ((t + BVH_LEAF - 1) // BVH_LEAF) + 1
    box = np.empty((cap, 6))
    kid = np.full((cap, 2), -1, np.int64)
    span = np.zeros((cap, 2), np.int64)
    stack = np.empty((cap, 3), np.int64)
    stack[0, 0], stack[0, 1], stack[0, 2] = 0, 0, t
    top, n = 1, 1
    while top > 0:
        top -= 1
        j, i0, i1 = stack[top, 0], stack[top, 1], stack[top, 2]
        span[j, 0], span[j, 1] = i0, i1 - i0
        if i1 - i0 <= BVH_LEAF:
            continue
        mid = i0 + BVH_LEAF * ((i1 - i0 + 2 * BVH_LEAF - 1) // (2 * BVH_LEAF))  # full leaves: <= cap nodes
        kid[j, 0], kid[j, 1] = n, n + 1
        stack[top, 0], stack[top, 1], stack[top, 2] = n, i0, mid
        stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2] = n + 1, mid, i1
        top += 2
        n += 2
    for j in range(n - 1, -1, -1):  # children after parents: boxes bottom-up
        if kid[j, 0] < 0:
            for d in range(3):
                box[j, d], box[j, 3 + d] = np.inf, -np.inf
            for i in range(span[j, 0], span[j, 0] + span[j, 1]):
                for v in range(3):
                    for d in range(3):
                        box[j, d] = min(box[j, d], flat[i, 3 * v + d])
                        box[j, 3 + d] = max(box[j, 3 + d], flat[i, 3 * v + d])
        else:
            a, b = kid[j, 0], kid[j, 1]
            for d in range(3):
                box[j, d] = min(box[a, d], box[b, d])
                box[j, 3 + d] = max(box[a, 3 + d], box[b, 3 + d])
    return flat, box[:n].copy(), kid[:n].copy(), span[:n].copy()


@njit(cache=True, inline="always")
def _axis_apart(p0, p1, p2, r):
    """The projections p0..p2 of a triangle onto an axis miss the box's [-r, r]."""
    return min(p0, min(p1, p2)) > r or max(p0, max(p1, p2)) < -r


@njit(cache=True)
def triangle_meets_box(tri, i, c0, c1, c2, e0, e1, e2):
    """Does triangle i of ``tri`` (rows of 9) meet the box of centre c and half-sizes e
    (separating-axis test of Akenine-Moeller: the box's 3 axes, the triangle's normal, the 9 cross
    products of edges and axes)? Degenerate triangles pass the tests they cannot fail."""
    v00, v01, v02 = tri[i, 0] - c0, tri[i, 1] - c1, tri[i, 2] - c2
    v10, v11, v12 = tri[i, 3] - c0, tri[i, 4] - c1, tri[i, 5] - c2
    v20, v21, v22 = tri[i, 6] - c0, tri[i, 7] - c1, tri[i, 8] - c2
    if _axis_apart(v00, v10, v20, e0) or _axis_apart(v01, v11, v21, e1) or _axis_apart(v02, v12, v22, e2):
        return False
    f00, f01, f02 = v10 - v00, v11 - v01, v12 - v02
    f10, f11, f12 = v20 - v10, v21 - v11, v22 - v12
    f20, f21, f22 = v00 - v20, v01 - v21, v02 - v22
    n0, n1, n2 = f01 * f12 - f02 * f11, f02 * f10 - f00 * f12, f00 * f11 - f01 * f10
    if abs(n0 * v00 + n1 * v01 + n2 * v02) > e0 * abs(n0) + e1 * abs(n1) + e2 * abs(n2):
        return False
    for k in range(3):
        g0, g1, g2 = (f00, f01, f02) if k == 0 else ((f10, f11, f12) if k == 1 else (f20, f21, f22))
        # axis x cross g = (0, -g2, g1)
        if _axis_apart(-g2 * v01 + g1 * v02, -g2 * v11 + g1 * v12, -g2 * v21 + g1 * v22, e1 * abs(g2) + e2 * abs(g1)):
            return False
        # axis y cross g = (g2, 0, -g0)
        if _axis_apart(g2 * v00 - g0 * v02, g2 * v10 - g0 * v12, g2 * v20 - g0 * v22, e0 * abs(g2) + e2 * abs(g0)):
            return False
        # axis z cross g = (-g1, g0, 0)
        if _axis_apart(-g1 * v00 + g0 * v01, -g1 * v10 + g0 * v11, -g1 * v20 + g0 * v21, e0 * abs(g1) + e1 * abs(g0)):
            return False
    return True


@njit(cache=True)
def box_near_surface(lo0, lo1, lo2, hi0, hi1, hi2, margin, root, tri, box, kid, span, stack):
    """Does a triangle of the BVH at ``root`` come within ``margin`` of the box (in each axis: the
    box grown by ``margin`` meets it)? False proves that no triangle meets the grown box.
    ``stack``: int64 scratch of BVH_STACK."""
    a0, a1, a2 = lo0 - margin, lo1 - margin, lo2 - margin
    b0, b1, b2 = hi0 + margin, hi1 + margin, hi2 + margin
    c0, c1, c2 = 0.5 * (a0 + b0), 0.5 * (a1 + b1), 0.5 * (a2 + b2)
    e0, e1, e2 = 0.5 * (b0 - a0) + margin, 0.5 * (b1 - a1) + margin, 0.5 * (b2 - a2) + margin
    top = 0
    stack[0] = root
    while top >= 0:
        j = stack[top]
        top -= 1
        if (box[j, 0] > b0 or box[j, 3] < a0 or box[j, 1] > b1 or box[j, 4] < a1 or box[j, 2] > b2
                or box[j, 5] < a2):
            continue
        if kid[j, 0] >= 0:
            stack[top + 1] = kid[j, 0]
            stack[top + 2] = kid[j, 1]
            top += 2
            continue
        for i in range(span[j, 0], span[j, 0] + span[j, 1]):
            if triangle_meets_box(tri, i, c0, c1, c2, e0, e1, e2):
                return True
    return False
