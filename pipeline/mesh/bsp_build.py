"""Compiled Build_Tree of bsp-fields.txt section 3.3.1 with the plane selection of section 3.3.3.

The recursion runs on flat arrays in one Numba function with an explicit stack, so deep trees
(a near-convex surface gives long chains) need no Python recursion:

* triangles are a growing (T, 3, 3) vertex array with an owner polygon per triangle; a node's
  list is a range of triangle ids in one index buffer used as a stack (children overwrite
  their parent's range, the positive child on top, so every pending range stays intact);
* a polygon of a node is the set of the node's triangles of one owner, so a split polygon
  keeps its id on both sides (as ``Split_Polygon`` does);
* Select_Polygon scores at most ``max_candidates`` distinct planes of the node (all of them if
  there are fewer) against at most ``sample`` of its triangles, so the work per node is
  bounded by a constant times the node's size and the total is about n log n for a balanced
  tree. Nodes with at most ``sample`` triangles are scored exactly, per polygon.
"""

from __future__ import annotations

import numpy as np

from pipeline.util.jit import njit

HALF_PI = 0.5 * np.pi
BIG_NODE = 4096  # triangles from which a node is kept in a bounding-volume hierarchy
BIG_CANDIDATES = 24  # a large node's cuts take small caps off, so their number grows like n:
BIG_SAMPLE = 128  # its selection costs a constant BIG_CANDIDATES * BIG_SAMPLE plane tests
WORK0 = 2048  # plane tests any node may spend, so small nodes are searched (almost) exhaustively


@njit(cache=True)
def plane_ids(key: np.ndarray, order: np.ndarray, tol: float) -> np.ndarray:
    """Label keys (normal, offset/scale) that agree to ``tol`` with one of the last 64 labels in
    lexicographic order (same rule as the former Python loop, compiled)."""
    q = key.shape[0]
    ids = np.empty(q, dtype=np.int64)
    reps = np.empty_like(key)
    nrep = 0
    for i in order:
        found = -1
        for r in range(max(0, nrep - 64), nrep):
            close = True
            for d in range(key.shape[1]):
                if abs(reps[r, d] - key[i, d]) >= tol:
                    close = False
                    break
            if close:
                found = r
                break
        if found < 0:
            reps[nrep] = key[i]
            found = nrep
            nrep += 1
        ids[i] = found
    return ids


@njit(cache=True)
def subtree_sizes(pos: np.ndarray, neg: np.ndarray) -> np.ndarray:
    """Nodes per subtree of a tree in post-order (children before parents)."""
    size = np.ones(pos.shape[0], dtype=np.int64)
    for j in range(pos.shape[0]):
        if pos[j] >= 0:
            size[j] += size[pos[j]]
        if neg[j] >= 0:
            size[j] += size[neg[j]]
    return size


@njit(cache=True)
def _grow_tri(tri: np.ndarray, own: np.ndarray, need: int):
    if need <= tri.shape[0]:
        return tri, own
    cap = max(need, 2 * tri.shape[0])
    t2 = np.empty((cap, 3, 3))
    t2[:tri.shape[0]] = tri
    o2 = np.empty(cap, dtype=np.int64)
    o2[:own.shape[0]] = own
    return t2, o2


@njit(cache=True)
def _grow_int(a: np.ndarray, need: int) -> np.ndarray:
    if need <= a.shape[0]:
        return a
    b = np.empty(max(need, 2 * a.shape[0]), dtype=np.int64)
    b[:a.shape[0]] = a
    return b


@njit(cache=True)
def _dist(tri: np.ndarray, t: int, k: int, n: np.ndarray, c: float) -> float:
    return n[0] * tri[t, k, 0] + n[1] * tri[t, k, 1] + n[2] * tri[t, k, 2] + c


@njit(cache=True)
def _poly_ranges(tri, own, items, n_items, polys, npoly, n, c, pmin, pmax):
    """Signed-distance range to the plane (n, c) of every polygon of the node, over its
    triangles items[:n_items] (how section 3.3.1 classifies a whole polygon)."""
    for i in range(npoly):
        pmin[polys[i]] = np.inf
        pmax[polys[i]] = -np.inf
    _extend_ranges(tri, own, items, n_items, n, c, pmin, pmax)


@njit(cache=True)
def _extend_ranges(tri, own, items, n_items, n, c, pmin, pmax):
    for i in range(n_items):
        t = items[i]
        o = own[t]
        for v in range(3):
            s = _dist(tri, t, v, n, c)
            pmin[o] = min(pmin[o], s)
            pmax[o] = max(pmax[o], s)


@njit(cache=True)
def _score(tri, own, items, m, polys, npoly, exact, pn, q, eps, pmin, pmax):
    """Section 3.3.3 criteria of the plane of polygon q over triangles items[:m]:
    (Ksplit, Kdist, Kangle, Ktree). Exact mode classifies whole polygons (their triangles in the
    node); sampled mode classifies the sampled triangles and scales the counts."""
    n = pn[q]
    c = pn[q, 3]
    kdist = np.inf
    if exact:
        for i in range(npoly):
            pmin[polys[i]] = np.inf
            pmax[polys[i]] = -np.inf
    nsplit = 0
    nf = 0
    nb = 0
    nopp = 0
    ang = -1.0  # largest |cos| of a tilted face so far
    for i in range(m):
        t = items[i]
        lo = np.inf
        hi = -np.inf
        for k in range(3):
            s = _dist(tri, t, k, n, c)
            lo = min(lo, s)
            hi = max(hi, s)
            if abs(s) > eps:
                kdist = min(kdist, abs(s))
        if exact:
            o = own[t]
            pmin[o] = min(pmin[o], lo)
            pmax[o] = max(pmax[o], hi)
        else:
            nsplit, nf, nb, ang, nopp = _tally(lo, hi, eps, pn, own[t], n, nsplit, nf, nb, ang, nopp)
    if exact:
        for i in range(npoly):
            p = polys[i]
            nsplit, nf, nb, ang, nopp = _tally(pmin[p], pmax[p], eps, pn, p, n, nsplit, nf, nb,
                                              ang, nopp)
    ktree = 1.0 if max(nf, nb) == 0 else min(nf, nb) / max(nf, nb)
    scale = 1.0 if exact else npoly / m  # sampled: splits estimated per polygon of the node
    # chain side: 1 all on the positive side, 2 all negative, 0 not a one-sided split-free plane
    side = 0
    if nsplit == 0 and nopp == 0 and nf + nb > 0 and min(nf, nb) == 0:
        side = 1 if nb == 0 else 2
    return (nsplit * scale, kdist if np.isfinite(kdist) else 0.0,
            np.arccos(min(ang, 1.0)) if ang >= 0 else HALF_PI, ktree, side)


@njit(cache=True)
def _tally(lo, hi, eps, pn, p, n, nsplit, nf, nb, ang, nopp):
    """Count one polygon (or sampled triangle) as on / front / back / spanning; Kangle over
    faces not parallel to the plane (parallel ones are never split)."""
    on = lo >= -eps and hi <= eps
    cosd = pn[p, 0] * n[0] + pn[p, 1] * n[1] + pn[p, 2] * n[2]
    if on:
        return nsplit, nf, nb, ang, nopp + (1 if cosd <= 0 else 0)
    if lo >= -eps:
        nf += 1
    elif hi <= eps:
        nb += 1
    else:
        nsplit += 1
    cosang = abs(cosd)
    if cosang < 1.0 - 1e-12:  # the smallest angle is the largest |cos|: arccos once, at the end
        ang = max(ang, cosang)
    return nsplit, nf, nb, ang, nopp


@njit(cache=True)
def _node_polys(own, items, n_items, pid, pstamp, lstamp, stamp, polys, cands):
    """Distinct polygons of the node and one representative polygon per distinct plane."""
    npoly = 0
    ncand = 0
    for i in range(n_items):
        o = own[items[i]]
        if pstamp[o] != stamp:
            pstamp[o] = stamp
            polys[npoly] = o
            npoly += 1
            if lstamp[pid[o]] != stamp:
                lstamp[pid[o]] = stamp
                cands[ncand] = o
                ncand += 1
    return npoly, ncand


@njit(cache=True)
def _k(kd: float, ka: float, kt: float, ks: float, rule: int) -> float:
    """Ranking among planes that split: 0 the paper's K = Kdist * Kangle * Ktree; others trade
    balance against the number of splits (experiments)."""
    if rule == 1:
        return kd * ka * kt / (1.0 + ks)
    if rule == 2:
        return kt / (1.0 + ks)
    if rule == 3:
        return (kd * ka) ** 0.25 * kt / (1.0 + ks)
    if rule == 4:
        return kt / (1.0 + ks) ** 2
    if rule == 5:
        return (kd * ka) ** 0.25 * kt / (1.0 + ks) ** 2
    if rule == 6:
        return ka * kt / (1.0 + ks) ** 2
    return kd * ka * kt


@njit(cache=True)
def _better(a, b) -> bool:
    """Section 3.3.3 order: a plane with Ksplit = 0 first (largest K, then balance), else the
    largest K, then fewer splits, then better balance. a, b = (Ksplit, K, Ktree)."""
    za = a[0] == 0
    zb = b[0] == 0
    if za != zb:
        return za
    if a[1] != b[1]:
        return a[1] > b[1]
    if not za and a[0] != b[0]:
        return a[0] < b[0]
    return a[2] > b[2]


@njit(cache=True)
def _select(tri, own, items, n_items, polys, npoly, cands, ncand, pn, eps, maxc, sample, work,
            rule, pmin, pmax, samp, chain, cside):
    """Select_Polygon (optimised): best candidate of a bounded sample of the node's planes.

    At most ``sample`` triangles are scored, and at most work * n_items + WORK0
    triangle-plane tests are spent (so the cost is proportional to the node's size). When the
    best plane is split-free and one-sided (nothing to balance, section 3.3.3 takes it for
    Ksplit = 0), every other such candidate is returned too in ``chain``: they stay
    one-sided and split-free in every sub-list, so they can be chained without rescoring.
    Returns (best, chain length)."""
    exact = n_items <= sample
    m = n_items if exact else sample
    nc = min(ncand, maxc, max(8, (work * n_items + WORK0) // m))
    if ncand > nc:  # partial Fisher-Yates: a uniform sample of nc planes
        for i in range(nc):
            j = i + np.random.randint(ncand - i)
            cands[i], cands[j] = cands[j], cands[i]
    use = items
    if not exact:
        for i in range(sample):
            samp[i] = items[np.random.randint(n_items)]
        use = samp
    best = cands[0]
    bkey = (np.inf, -1.0, -1.0)
    bside = 0
    nchain = 0
    for i in range(nc):
        ks, kd, ka, kt, side = _score(tri, own, use, m, polys, npoly, exact, pn, cands[i], eps,
                                      pmin, pmax)
        if side > 0:
            chain[nchain] = cands[i]
            cside[nchain] = side
            nchain += 1
        # a one-sided plane of a sampled (large) node makes no progress; only exact nodes may
        # take it (as a chain), so there its Ksplit = 0 preference is dropped
        k = _k(kd, ka, kt, ks, rule)
        key = (ks if exact or kt > 0 else max(ks, 0.5), k, kt)
        if i == 0 or _better(key, bkey):
            best = cands[i]
            bkey = key
            bside = side
    if bside == 0:
        return best, 0
    for i in range(nchain):  # best first (so that a sampled best that fails costs one scan)
        if chain[i] == best:
            chain[i], chain[0] = chain[0], chain[i]
            cside[i], cside[0] = cside[0], cside[i]
    if not exact:  # sampled one-sided planes are kept only if exactly one-sided and split-free
        nchain = _verify_chain(tri, own, items, n_items, polys, npoly, pn, eps, pmin, pmax,
                               chain, cside, nchain, best)
    return best, nchain


@njit(cache=True)
def _verify_chain(tri, own, items, n_items, polys, npoly, pn, eps, pmin, pmax, chain, cside,
                  nchain, best):
    """Exact rescoring of chain candidates found on a sample; 0 if ``best`` fails."""
    k = 0
    for i in range(nchain):
        side = _score(tri, own, items, n_items, polys, npoly, True, pn, chain[i], eps, pmin,
                      pmax)[4]
        if side > 0:
            chain[k] = chain[i]
            cside[k] = side
            k += 1
        elif chain[i] == best:
            return 0
    return k


@njit(cache=True)
def _clip(tri, own, t, s, n_tri, pos_out, npos, neg_out, nneg):
    """Split_Polygon for one spanning triangle: fans of the parts s >= 0 and s <= 0 (vertex
    order kept, so the pieces keep the outward orientation)."""
    pl = np.empty((4, 3))
    nl = np.empty((4, 3))
    a = 0
    b = 0
    v = tri[t].copy()
    for i in range(3):
        j = (i + 1) % 3
        if s[i] >= 0:
            pl[a] = v[i]
            a += 1
        if s[i] <= 0:
            nl[b] = v[i]
            b += 1
        if s[i] * s[j] < 0:
            p = v[i] + (s[i] / (s[i] - s[j])) * (v[j] - v[i])
            pl[a] = p
            nl[b] = p
            a += 1
            b += 1
    tri, own = _grow_tri(tri, own, n_tri + 4)
    for k in range(1, a - 1):
        tri[n_tri, 0] = pl[0]
        tri[n_tri, 1] = pl[k]
        tri[n_tri, 2] = pl[k + 1]
        own[n_tri] = own[t]
        pos_out[npos] = n_tri
        npos += 1
        n_tri += 1
    for k in range(1, b - 1):
        tri[n_tri, 0] = nl[0]
        tri[n_tri, 1] = nl[k]
        tri[n_tri, 2] = nl[k + 1]
        own[n_tri] = own[t]
        neg_out[nneg] = n_tri
        nneg += 1
        n_tri += 1
    return tri, own, n_tri, npos, nneg


@njit(cache=True)
def _partition(tri, own, items, n_items, polys, npoly, pn, q, eps, n_tri, pmin, pmax,
               pos_out, neg_out):
    """Classify the node's polygons against the plane of q (section 3.3.1) and split the spanning
    ones; polygons on the plane with q's orientation stay in the node."""
    n = pn[q]
    c = pn[q, 3]
    _poly_ranges(tri, own, items, n_items, polys, npoly, n, c, pmin, pmax)
    nsplit = 0
    for i in range(npoly):
        p = polys[i]
        if not (pmin[p] >= -eps or pmax[p] <= eps):
            nsplit += 1
    npos = 0
    nneg = 0
    s3 = np.empty(3)
    for i in range(n_items):
        t = items[i]
        o = own[t]
        lo = pmin[o]
        hi = pmax[o]
        if lo >= -eps and hi <= eps:  # on the plane: same orientation stays, opposite is negative
            if pn[o, 0] * n[0] + pn[o, 1] * n[1] + pn[o, 2] * n[2] <= 0:
                neg_out[nneg] = t
                nneg += 1
        elif lo >= -eps:
            pos_out[npos] = t
            npos += 1
        elif hi <= eps:
            neg_out[nneg] = t
            nneg += 1
        else:
            for k in range(3):
                sk = _dist(tri, t, k, n, c)
                s3[k] = 0.0 if abs(sk) <= eps else sk
            if s3.min() >= 0 or s3.max() <= 0:
                if s3.max() > 0:
                    pos_out[npos] = t
                    npos += 1
                else:
                    neg_out[nneg] = t
                    nneg += 1
            else:
                tri, own, n_tri, npos, nneg = _clip(tri, own, t, s3, n_tri, pos_out, npos,
                                                    neg_out, nneg)
    return tri, own, n_tri, npos, nneg, nsplit


@njit(cache=True)
def _add_node(node_q, node_pos, node_neg, node_dep, q, parent, side, dep) -> int:
    node = len(node_q)
    node_q.append(q)
    node_pos.append(-1)
    node_neg.append(-1)
    node_dep.append(dep)
    if parent >= 0:
        if side == 0:
            node_pos[parent] = node
        else:
            node_neg[parent] = node
    return node


@njit(cache=True)
def _chain_rest(tri, own, items, n_items, polys, npoly, pn, chain, k, eps, pmin, pmax, gone,
                stamp, out):
    """Triangles left after a chain of k one-sided split-free planes: a polygon on a chain plane
    with its orientation is stored in that node (section 3.3.1), every other polygon goes on."""
    for j in range(k):
        n = pn[chain[j]]
        c = pn[chain[j], 3]
        _poly_ranges(tri, own, items, n_items, polys, npoly, n, c, pmin, pmax)
        for i in range(npoly):
            p = polys[i]
            if pmin[p] >= -eps and pmax[p] <= eps and pn[p, 0] * n[0] + pn[p, 1] * n[1] + pn[p, 2] * n[2] > 0:
                gone[p] = stamp
    nrest = 0
    for i in range(n_items):
        if gone[own[items[i]]] != stamp:
            out[nrest] = items[i]
            nrest += 1
    return nrest


@njit(cache=True)
def _median_cut(tri, items, n_items):
    """(axis, position) of the cut through the median centroid of the items along their widest
    extent, or (-1, 0) when every centroid is the same point. The median moves to the middle of
    the range when it is an end of it, so both sides hold a centroid."""
    cen = np.empty((n_items, 3))
    for i in range(n_items):
        for d in range(3):
            cen[i, d] = (tri[items[i], 0, d] + tri[items[i], 1, d] + tri[items[i], 2, d]) / 3.0
    axis = 0
    wide = -1.0
    for d in range(3):
        w = cen[:, d].max() - cen[:, d].min()
        if w > wide:
            axis, wide = d, w
    if wide <= 0.0:
        return -1, 0.0
    lo, hi = cen[:, axis].min(), cen[:, axis].max()
    m = np.median(cen[:, axis])
    if not (lo < m < hi):
        m = 0.5 * (lo + hi)
    return axis, m


@njit(cache=True)
def build(tri0, own0, pn, pid, naive, seed, eps, maxc, sample, work, rule, big, nq, kd_leaf):
    """Build_Tree (section 3.3.1), iterative. pn (Q + spare, 4): polygon normal and offset in its
    first ``nq`` rows; pid (nq,): oriented plane label. Returns per preorder node: plane row of
    pn, positive child, negative child, depth; the number of polygon splits; and pn (grown when
    the cut planes needed more rows).

    ``kd_leaf`` > 0 (optimised only): a node of more than kd_leaf triangles is cut by the plane
    through its median centroid along the widest axis (a new row of pn, from nq on) instead of
    a face plane; see pipeline.mesh.bsp._build_tree_compiled for why."""
    kd_next = nq
    np.random.seed(seed)
    t0 = tri0.shape[0]
    q = nq
    tri = tri0.copy()
    own = own0.copy()
    tri, own = _grow_tri(tri, own, 2 * t0 + 16)
    n_tri = t0
    buf = np.arange(2 * t0 + 16, dtype=np.int64)
    pstamp = np.full(q, -1, dtype=np.int64)
    lstamp = np.full(pid.max() + 1, -1, dtype=np.int64)
    pmin = np.empty(q)
    pmax = np.empty(q)
    polys = np.empty(t0 + 16, dtype=np.int64)
    cands = np.empty(t0 + 16, dtype=np.int64)
    samp = np.empty(sample, dtype=np.int64)
    chain = np.empty(maxc, dtype=np.int64)
    cside = np.empty(maxc, dtype=np.int64)
    gone = np.full(q, -1, dtype=np.int64)
    pos_out = np.empty(t0 + 16, dtype=np.int64)
    neg_out = np.empty(t0 + 16, dtype=np.int64)
    node_q, node_pos, node_neg, node_dep = [0], [0], [0], [0]
    node_q.clear()
    node_pos.clear()
    node_neg.clear()
    node_dep.clear()
    stack = [(0, t0, -1, 0, 0)]  # (start, end, parent, side 0 pos / 1 neg, depth)
    splits = 0
    ctr = np.zeros(1, dtype=np.int64)
    scr = (pmin, pmax, pstamp, lstamp, np.zeros(q, dtype=np.int64), np.zeros(q, dtype=np.int64),
           np.full(q, -1, dtype=np.int64))
    while len(stack) > 0:
        s, e, parent, side, dep = stack.pop()
        nit = e - s
        items = buf[s:e].copy()
        if not naive and kd_leaf > 0 and nit > kd_leaf:
            axis, m = _median_cut(tri, items, nit)
            if axis >= 0:
                if kd_next == pn.shape[0]:  # room for more cut planes
                    pn2 = np.zeros((2 * pn.shape[0], 4))
                    pn2[:pn.shape[0]] = pn
                    pn = pn2
                polys = _grow_int(polys, nit)
                cands = _grow_int(cands, nit)
                ctr[0] += 1
                npoly, _ = _node_polys(own, items, nit, pid, pstamp, lstamp, ctr[0], polys, cands)
                pn[kd_next, :] = 0.0
                pn[kd_next, axis] = 1.0
                pn[kd_next, 3] = -m
                pos_out = _grow_int(pos_out, 3 * nit)
                neg_out = _grow_int(neg_out, 3 * nit)
                tri, own, n_tri2, npos, nneg, ns = _partition(tri, own, items, nit, polys, npoly, pn, kd_next,
                                                              eps, n_tri, pmin, pmax, pos_out, neg_out)
                # both sides non-empty (a cut plane's node takes the general formula) and each at
                # most 3/4 of the node (else thin triangles spanning the cut would only be split
                # again and again): otherwise a face plane decides this node
                if npos > 0 and nneg > 0 and 4 * max(npos, nneg) <= 3 * nit:
                    n_tri = n_tri2
                    node = _add_node(node_q, node_pos, node_neg, node_dep, kd_next, parent, side, dep)
                    kd_next += 1
                    splits += ns
                    buf = _grow_int(buf, s + npos + nneg)
                    buf[s:s + nneg] = neg_out[:nneg]
                    buf[s + nneg:s + nneg + npos] = pos_out[:npos]
                    stack.append((s, s + nneg, node, 1, dep + 1))
                    stack.append((s + nneg, s + nneg + npos, node, 0, dep + 1))
                    continue
        if not naive and nit >= big:
            tri, own, n_tri, buf, ns = _big_node(tri, own, n_tri, items, pn, pid, eps, maxc, sample,
                                                 work, rule, big, parent, side, dep, node_q, node_pos,
                                                 node_neg, node_dep, stack, buf, s, scr, ctr)
            splits += ns
            continue
        polys = _grow_int(polys, nit)
        cands = _grow_int(cands, nit)
        ctr[0] += 1
        stamp = ctr[0]
        npoly, ncand = _node_polys(own, items, nit, pid, pstamp, lstamp, stamp, polys, cands)
        nchain = 0
        if naive:
            best = polys[np.random.randint(npoly)]
        else:
            best, nchain = _select(tri, own, items, nit, polys, npoly, cands, ncand, pn, eps, maxc,
                                   sample, work, rule, pmin, pmax, samp, chain, cside)
        if nchain >= 2:
            pos_out = _grow_int(pos_out, nit)
            nrest = _chain_rest(tri, own, items, nit, polys, npoly, pn, chain, nchain, eps, pmin,
                                pmax, gone, stamp, pos_out)
            for j in range(nchain):
                parent = _add_node(node_q, node_pos, node_neg, node_dep, chain[j], parent, side, dep)
                side = 0 if cside[j] == 1 else 1
                dep += 1
            if nrest > 0:
                buf[s:s + nrest] = pos_out[:nrest]
                stack.append((s, s + nrest, parent, side, dep))
            continue
        node = _add_node(node_q, node_pos, node_neg, node_dep, best, parent, side, dep)
        pos_out = _grow_int(pos_out, 3 * nit)
        neg_out = _grow_int(neg_out, 3 * nit)
        tri, own, n_tri, npos, nneg, ns = _partition(tri, own, items, nit, polys, npoly, pn, best,
                                                     eps, n_tri, pmin, pmax, pos_out, neg_out)
        splits += ns
        buf = _grow_int(buf, s + npos + nneg)
        buf[s:s + nneg] = neg_out[:nneg]
        buf[s + nneg:s + nneg + npos] = pos_out[:npos]
        if nneg > 0:
            stack.append((s, s + nneg, node, 1, dep + 1))
        if npos > 0:
            stack.append((s + nneg, s + nneg + npos, node, 0, dep + 1))
    return (np.array(node_q), np.array(node_pos), np.array(node_neg), np.array(node_dep),
            splits, pn)


# --------------------------------------------------------------------------- large nodes
# A near-convex surface has no balanced face plane: each cut only takes a small cap off a large
# node, so a scan of the whole list per node would make the build quadratic. Large nodes are
# therefore kept in a bounding-volume hierarchy (Morton-ordered, 8 triangles per leaf): the
# triangles that are not strictly on the positive side of a plane are found by a query whose cost
# follows the cap, not the node; removed triangles are flagged, split parts kept in a side list.

BVH_LEAF = 8


@njit(cache=True)
def _lbvh(tri, items):
    """Morton order of items and the implicit complete-tree boxes (lo, hi) over leaves of BVH_LEAF."""
    m = items.shape[0]
    cen = np.empty((m, 3))
    for i in range(m):
        for d in range(3):
            cen[i, d] = (tri[items[i], 0, d] + tri[items[i], 1, d] + tri[items[i], 2, d]) / 3.0
    lo0 = np.empty(3)
    ext = np.empty(3)
    for d in range(3):
        lo0[d] = cen[:, d].min()
        ext[d] = max(cen[:, d].max() - lo0[d], 1e-300)
    code = np.empty(m, dtype=np.int64)
    for i in range(m):
        c = 0
        q = np.empty(3, dtype=np.int64)
        for d in range(3):
            q[d] = min(1023, int((cen[i, d] - lo0[d]) / ext[d] * 1024.0))
        for b in range(9, -1, -1):
            for d in range(3):
                c = (c << 1) | ((q[d] >> b) & 1)
        code[i] = c
    bi = items[np.argsort(code)]
    nleaf = (m + BVH_LEAF - 1) // BVH_LEAF
    size = 1
    while size < nleaf:
        size *= 2
    lo = np.full((2 * size, 3), np.inf)
    hi = np.full((2 * size, 3), -np.inf)
    for i in range(m):
        leaf = size + i // BVH_LEAF
        for k in range(3):
            for d in range(3):
                lo[leaf, d] = min(lo[leaf, d], tri[bi[i], k, d])
                hi[leaf, d] = max(hi[leaf, d], tri[bi[i], k, d])
    for j in range(size - 1, 0, -1):
        for d in range(3):
            lo[j, d] = min(lo[2 * j, d], lo[2 * j + 1, d])
            hi[j, d] = max(hi[2 * j, d], hi[2 * j + 1, d])
    return bi, lo, hi, size


@njit(cache=True)
def _query(tri, bi, alive, lo, hi, size, n, c, thr, out):
    """Positions in bi of alive triangles with a vertex at n.x + c <= thr; returns their count."""
    m = bi.shape[0]
    cnt = 0
    stack = np.empty(64, dtype=np.int64)
    top = 1
    stack[0] = 1
    while top > 0:
        top -= 1
        j = stack[top]
        if lo[j, 0] > hi[j, 0]:
            continue
        low = c  # the smallest n.x + c over the box
        for d in range(3):
            low += n[d] * (lo[j, d] if n[d] > 0 else hi[j, d])
        if low > thr:
            continue
        if j >= size:
            start = (j - size) * BVH_LEAF
            for i in range(start, min(m, start + BVH_LEAF)):
                if alive[i]:
                    t = bi[i]
                    if min(_dist(tri, t, 0, n, c), _dist(tri, t, 1, n, c), _dist(tri, t, 2, n, c)) <= thr:
                        out[cnt] = i
                        cnt += 1
        else:
            stack[top] = 2 * j
            stack[top + 1] = 2 * j + 1
            top += 2
    return cnt


@njit(cache=True)
def _draw(alive, m, ex, exalive, nex):
    """A uniformly random alive triangle of a large node (at least half of them are alive)."""
    while True:
        r = np.random.randint(m + nex)
        if r < m:
            if alive[r]:
                return r
        elif exalive[r - m]:
            return r


@njit(cache=True)
def _select_big(tri, own, bi, alive, m, ex, exalive, nex, nalive, pn, pid, lstamp, stamp, eps,
                maxc, sample, work, rule, pmin, pmax, samp, cands):
    """Select_Polygon for a large node: candidates and scores from random alive triangles."""
    for i in range(sample):
        r = _draw(alive, m, ex, exalive, nex)
        samp[i] = bi[r] if r < m else ex[r - m]
    nc = min(maxc, max(8, (work * nalive + WORK0) // sample))
    k = 0
    for _ in range(nc):
        r = _draw(alive, m, ex, exalive, nex)
        o = own[bi[r] if r < m else ex[r - m]]
        if lstamp[pid[o]] != stamp:
            lstamp[pid[o]] = stamp
            cands[k] = o
            k += 1
    best = cands[0]
    bkey = (np.inf, -1.0, -1.0)
    for i in range(k):
        ks, kd, ka, kt, _ = _score(tri, own, samp, sample, cands, nalive, False, pn, cands[i], eps,
                                   pmin, pmax)
        key = (max(ks, 0.5) if kt == 0 else ks, _k(kd, ka, kt, ks, rule), kt)
        if i == 0 or _better(key, bkey):
            best = cands[i]
            bkey = key
    return best


@njit(cache=True)
def _big_partition(tri, own, n_tri, bi, alive, lo, hi, size, ex, exalive, nex, perm, ofirst, ocnt,
                   ostamp, estamp, pn, q, eps, pmin, pmax, pstamp, stamp, flag, gt, gl, fo,
                   neg_out, pos_tmp):
    """Section 3.3.1 partition of a large node by the plane of q: only polygons with a triangle
    not strictly on the positive side are looked at; the others stay (positive). Removed
    triangles are flagged dead, positive split parts appended to the side list ``ex``.
    Returns (tri, own, n_tri, ex, exalive, nex, killed, nneg, nsplit)."""
    n = pn[q]
    c = pn[q, 3]
    nq = _query(tri, bi, alive, lo, hi, size, n, c, eps, flag)
    nfo = 0
    for i in range(nq):
        o = own[bi[flag[i]]]
        if pstamp[o] != stamp:
            pstamp[o] = stamp
            fo[nfo] = o
            nfo += 1
    for k in range(nex):
        t = ex[k]
        low = min(_dist(tri, t, 0, n, c), _dist(tri, t, 1, n, c), _dist(tri, t, 2, n, c))
        if exalive[k] and pstamp[own[t]] != stamp and low <= eps:
            pstamp[own[t]] = stamp
            fo[nfo] = own[t]
            nfo += 1
    ng = 0  # every alive triangle of the flagged polygons
    for i in range(nfo):
        o = fo[i]
        pmin[o] = np.inf
        pmax[o] = -np.inf
        if ostamp[o] == estamp:
            for r in range(ofirst[o], ofirst[o] + ocnt[o]):
                if alive[perm[r]]:
                    gt[ng] = bi[perm[r]]
                    gl[ng] = perm[r]
                    ng += 1
    for k in range(nex):
        if exalive[k] and pstamp[own[ex[k]]] == stamp:
            gt[ng] = ex[k]
            gl[ng] = -(k + 1)
            ng += 1
    _extend_ranges(tri, own, gt, ng, n, c, pmin, pmax)
    nsplit = 0
    for i in range(nfo):
        if not (pmin[fo[i]] >= -eps or pmax[fo[i]] <= eps):
            nsplit += 1
    nneg = 0
    npt = 0
    killed = 0
    s3 = np.empty(3)
    for i in range(ng):
        t = gt[i]
        o = own[t]
        a = pmin[o]
        b = pmax[o]
        dead = True
        if a >= -eps and b <= eps:
            if pn[o, 0] * n[0] + pn[o, 1] * n[1] + pn[o, 2] * n[2] <= 0:
                neg_out[nneg] = t
                nneg += 1
        elif a >= -eps:
            dead = False
        elif b <= eps:
            neg_out[nneg] = t
            nneg += 1
        else:
            for v in range(3):
                sv = _dist(tri, t, v, n, c)
                s3[v] = 0.0 if abs(sv) <= eps else sv
            if s3.min() >= 0 or s3.max() <= 0:
                if s3.max() > 0:
                    dead = False
                else:
                    neg_out[nneg] = t
                    nneg += 1
            else:
                tri, own, n_tri, npt, nneg = _clip(tri, own, t, s3, n_tri, pos_tmp, npt, neg_out, nneg)
        if dead:
            killed += 1
            if gl[i] >= 0:
                alive[gl[i]] = False
            else:
                exalive[-gl[i] - 1] = False
    if nex + npt > ex.shape[0]:
        ex = _grow_int(ex, nex + npt)
        e2 = np.zeros(ex.shape[0], dtype=np.bool_)
        e2[:nex] = exalive[:nex]
        exalive = e2
    for i in range(npt):
        ex[nex] = pos_tmp[i]
        exalive[nex] = True
        nex += 1
    return tri, own, n_tri, ex, exalive, nex, killed, nneg, nsplit


@njit(cache=True)
def _big_node(tri, own, n_tri, items, pn, pid, eps, maxc, sample, work, rule, big, parent, side,
              dep, node_q, node_pos, node_neg, node_dep, stack, buf, s, scr, ctr):
    """Run Build_Tree down the large side of a large node while it stays large; small sides go
    onto the stack as ordinary lists, and so does the rest when it shrinks (rebuilt if still
    large). Returns (tri, own, n_tri, buf, splits)."""
    pmin, pmax, pstamp, lstamp, ofirst, ocnt, ostamp = scr
    bi, lo, hi, size = _lbvh(tri, items)
    m = bi.shape[0]
    alive = np.ones(m, dtype=np.bool_)
    perm = np.argsort(own[bi])
    ctr[0] += 1
    estamp = ctr[0]
    for r in range(m):
        o = own[bi[perm[r]]]
        if ostamp[o] != estamp:
            ostamp[o] = estamp
            ofirst[o] = r
            ocnt[o] = 0
        ocnt[o] += 1
    ex = np.empty(m // 8 + 16, dtype=np.int64)
    exalive = np.zeros(m // 8 + 16, dtype=np.bool_)
    nex = 0
    nalive = m
    flag = np.empty(m, dtype=np.int64)
    samp = np.empty(sample, dtype=np.int64)
    cands = np.empty(maxc, dtype=np.int64)
    splits = 0
    top = s
    gt = np.empty(m + m // 8 + 16, dtype=np.int64)
    gl = np.empty_like(gt)
    fo = np.empty_like(gt)
    neg_out = np.empty(2 * gt.shape[0], dtype=np.int64)
    pos_tmp = np.empty_like(neg_out)
    while nalive > 0:
        if nalive < big // 2 or 2 * nalive < m + nex or 16 * nex > m:
            k = 0
            buf = _grow_int(buf, top + nalive)
            for i in range(m):
                if alive[i]:
                    buf[top + k] = bi[i]
                    k += 1
            for i in range(nex):
                if exalive[i]:
                    buf[top + k] = ex[i]
                    k += 1
            stack.append((top, top + k, parent, side, dep))
            break
        ctr[0] += 1
        best = _select_big(tri, own, bi, alive, m, ex, exalive, nex, nalive, pn, pid, lstamp,
                           ctr[0], eps, BIG_CANDIDATES, BIG_SAMPLE, work, rule, pmin, pmax, samp,
                           cands)
        node = _add_node(node_q, node_pos, node_neg, node_dep, best, parent, side, dep)
        ctr[0] += 1
        if m + nex > gt.shape[0]:  # scratch for one partition, allocated once (not per node)
            gt = _grow_int(gt, m + nex)
            gl = _grow_int(gl, m + nex)
            fo = _grow_int(fo, m + nex)
            neg_out = _grow_int(neg_out, 2 * (m + nex))
            pos_tmp = _grow_int(pos_tmp, 2 * (m + nex))
        tri, own, n_tri, ex, exalive, nex2, killed, nneg, ns = _big_partition(
            tri, own, n_tri, bi, alive, lo, hi, size, ex, exalive, nex, perm, ofirst, ocnt, ostamp,
            estamp, pn, best, eps, pmin, pmax, pstamp, ctr[0], flag, gt, gl, fo, neg_out, pos_tmp)
        nalive += nex2 - nex - killed
        nex = nex2
        splits += ns
        if nneg > 0:
            buf = _grow_int(buf, top + nneg)
            buf[top:top + nneg] = neg_out[:nneg]
            stack.append((top, top + nneg, node, 1, dep + 1))
            top += nneg
        parent = node
        side = 0
        dep += 1
    return tri, own, n_tri, buf, splits
