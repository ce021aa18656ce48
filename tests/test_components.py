"""Components seed: detection (Algorithm 1 + section 4.2), Algorithm 2, separation (section 4.3),
collision (section 5), the components stage and the collide command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from pipeline.cli import main
from pipeline.field import rfunctions as rf
from pipeline.io.vdbgrids import vdb
from pipeline.job.config import _Ctx, build_node
from pipeline.topology import components as cc

FAST = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
DEMO = {"difference": [{"superellipsoid": {"radii": [1, 1, 1], "exponents": [0.3, 0.3]}},
                       {"box": {"min": [-1.3, -0.02, -1.3], "max": [1.3, 0.02, 1.3]}}]}
NOISE = ("81 - 100*x^2 - 100*y^2 - 100*z^2 + (3.8*sin(15*x) + 1.6*sin(11.1*x + 1.1*sin(15*x)))"
         " * (3.8*sin(15*y) + 1.3*sin(11.1*x + 1.1*sin(15*x)))"
         " * (3.8*sin(15*z) + 2.6*sin(11.1*x + 1.1*sin(15*x)))")


def node(raw: dict):
    return build_node(raw, ("model",), _Ctx("test", raw, Path(".")))


def sphere(c, r) -> dict:
    return {"sphere": {"center": list(c), "radius": r}}


def cube(lo: float = -1.0, size: float = 2.0) -> tuple[np.ndarray, float]:
    return np.full(3, lo), size


# --- detection --------------------------------------------------------------------------------------


@FAST
@given(n=st.integers(1, 5), r=st.floats(0.08, 0.15), shift=st.floats(0.0, 0.05))
def test_n_disjoint_spheres_give_n(n, r, shift):
    centres = [(-0.8 + shift + 0.38 * i, 0.1 * i - 0.2, 0.0) for i in range(n)]
    model = node({"union": [sphere(c, r) for c in centres]})
    found = cc.detect(model, *cube(), 7)  # cell 0.0156; gaps >= 0.08 > 2 cells
    assert found.count == n
    lab = cc.point_labels(found, np.array(centres))
    assert sorted(lab.tolist()) == list(range(1, n + 1))  # scan order = order along x
    assert np.allclose(found.volumes, 4 / 3 * np.pi * r**3, rtol=0.05)
    assert np.all(found.volume_bounds[:, 0] <= found.volumes) and np.all(found.volumes <= found.volume_bounds[:, 1])


@FAST
@given(offset=st.floats(-0.03, 0.03), depth=st.integers(6, 7))
def test_gap_larger_than_two_cells_gives_two_touching_gives_one(offset, depth):
    lo, size = cube()
    cell = size / 2**depth
    r = 0.3
    gap = 2.5 * cell
    apart = node({"union": [sphere((offset - r - gap / 2, 0, 0), r), sphere((offset + r + gap / 2, 0, 0), r)]})
    assert cc.detect(apart, lo, size, depth).count == 2
    touching = node({"union": [sphere((offset - r, 0.01, 0), r), sphere((offset + r, 0.01, 0), r)]})
    assert cc.detect(touching, lo, size, depth).count == 1


def test_torus_gives_one_and_its_hole_is_not_filled():
    model = node({"torus": {"center": [0, 0, 0], "major": 0.6, "minor": 0.15}})
    found = cc.detect(model, *cube(), 7)
    assert found.count == 1
    assert cc.point_labels(found, np.array([[0.6, 0, 0], [-0.6, 0, 0]])).tolist() == [1, 1]
    assert found.tree.locate(np.array([[0.0, 0.0, 0.0]]))[0] == -1  # the hole holds no kept cell
    assert found.volumes[0] == pytest.approx(2 * np.pi**2 * 0.6 * 0.15**2, rel=0.03)


def test_demo_model_gives_two():
    found = cc.detect(node(DEMO), np.full(3, -1.25), 2.5, 7)
    assert found.count == 2
    lab = cc.point_labels(found, np.array([[0, -0.5, 0], [0, 0.5, 0]]))
    assert lab.tolist() == [1, 2]
    assert found.volumes[0] == pytest.approx(found.volumes[1], rel=1e-9)


def test_continuation_off_is_plain_affine_subdivision_and_agrees():
    model = node({"union": [sphere((-0.4, 0, 0), 0.3), sphere((0.4, 0, 0), 0.3)]})
    on = cc.enumerate_octree(model, *cube(), 7)
    off = cc.enumerate_octree(model, *cube(), 7, continuation=False)
    assert on.stats["affine_skipped"] > 0 and off.stats["affine_skipped"] == 0
    assert off.stats["affine_tests"] > on.stats["affine_tests"]
    assert cc.label_cells(on).count == cc.label_cells(off).count == 2
    assert on.stats["border_cells"] <= off.stats["border_cells"]  # corners never overestimate


def test_continuation_recovers_cells_the_descent_did_not_reach():
    model = node(sphere((0, 0, 0), 0.5))
    signs = cc._sign_bits(np.array([[1.0, -1, -1, -1, -1, -1, -1, -1]]) > 0)  # only corner 0's edges change sign
    assert signs.tolist() == [1]
    have = np.sort(cc.pack(np.array([[5, 5, 5]])))
    nb = cc._unique_rows(cc._missing_edge_neighbours(have, signs, have, 64))
    assert {tuple(r) for r in nb} == {(4, 4, 5), (4, 5, 4), (4, 5, 5), (5, 4, 4), (5, 4, 5), (5, 5, 4)}
    # an unclipped descent reaches every cell across a sign-changing edge itself
    full = cc.enumerate_octree(model, *cube(), 6)
    assert full.stats["continuation_cells"] == 0 and full.stats["border_cells"] > 0


@FAST
@given(seed=st.integers(0, 10_000), n=st.integers(1, 3000), extra=st.integers(0, 3000))
def test_missing_edge_neighbours_equal_a_set_reference(seed, n, extra):
    """The continuation's search (cells in key order, a forward pointer per neighbour offset)
    finds the same missing cells, with the same repeats, as a set lookup of every neighbour
    across every sign-changing edge."""
    rng = np.random.default_rng(seed)
    lim = 24
    cells = cc._unique_rows(rng.integers(0, lim, (n, 3)))
    keys = cc.pack(cells)  # sorted by _unique_rows
    signs = rng.integers(0, 256, len(cells)).astype(np.uint8)
    have = np.unique(np.concatenate([keys, cc.pack(rng.integers(0, lim, (extra, 3)))]))
    got = cc._missing_edge_neighbours(keys, signs, have, lim)
    present = set(have.tolist())
    want = []
    for (x, y, z), b in zip(cells.tolist(), signs.tolist(), strict=True):
        for a in range(8):
            for axis in range(3):
                bit = 4 >> axis
                if a & bit or ((b >> a) & 1) == ((b >> (a | bit)) & 1):
                    continue
                u, v = (axis + 1) % 3, (axis + 2) % 3
                for du, dv in ((1, 0), (0, 1), (1, 1)):
                    q = [x, y, z]
                    q[u] += du * (1 if a & (4 >> u) else -1)
                    q[v] += dv * (1 if a & (4 >> v) else -1)
                    if min(q) >= 0 and max(q) < lim and int(cc.pack(np.array([q]))[0]) not in present:
                        want.append(q)
    want = np.array(want, np.int64).reshape(-1, 3)
    assert np.array_equal(got[np.lexsort(got.T[::-1])], want[np.lexsort(want.T[::-1])])


@FAST
@given(seed=st.integers(0, 10_000), density=st.floats(0.2, 0.45))
def test_marking_with_propagation_matches_scipy_on_mixed_depths(seed, density):
    """Section 4.2 on a random octree: finest cells from a random mask, with every full 2x2x2
    block replaced by its parent (Figure 1: same level, finer and coarser neighbours)."""
    rng = np.random.default_rng(seed)
    mask = rng.random((16, 16, 16)) < density
    mask[4:12, 4:12, 4:12] |= rng.random() < 0.5  # sometimes a solid block that coarsens
    ref, nref = ndimage.label(mask)
    blocks = mask.reshape(8, 2, 8, 2, 8, 2).all(axis=(1, 3, 5))
    fine = mask & ~np.repeat(np.repeat(np.repeat(blocks, 2, 0), 2, 1), 2, 2)
    coords = np.concatenate([np.argwhere(fine), np.argwhere(blocks)])
    level = np.concatenate([np.full(fine.sum(), 4), np.full(blocks.sum(), 3)])
    n = len(level)
    tree = cc.Octree(np.zeros(3), 1.0, 4, level, coords, np.full(n, cc.BORDER, np.int8), np.full(n, 0.5))
    comp = cc.label_cells(tree)
    assert comp.count == nref
    centres = (coords + 0.5) / 2.0**level[:, None]
    dense = ref[tuple(np.floor(centres * 16).astype(int).T)]
    pairs = set(zip(comp.labels.tolist(), dense.tolist(), strict=True))
    assert len(pairs) == nref  # the two labellings are the same partition


def test_algorithm2_coarsest_level_keeps_the_count():
    model = node({"union": [sphere((-0.5, 0, 0), 0.3), sphere((0.5, 0, 0), 0.3)]})
    found = cc.detect(model, *cube(), 8)
    coarse, mapping = cc.coarsest_same_count(found)
    assert coarse.count == found.count == 2
    assert coarse.tree.depth < found.tree.depth
    assert cc.label_cells(cc.truncate(found.tree, coarse.tree.depth - 1)).count != 2
    assert sorted(mapping.values()) == [1, 2]
    assert len(coarse.tree) < len(found.tree)
    # every cell's row in a truncated tree is the cell holding its centre (itself or its ancestor)
    for lv in range(found.tree.depth + 1):
        tree, rows = cc._truncate(found.tree, lv)
        lo, hi = found.tree.boxes()
        np.testing.assert_array_equal(rows, tree.locate(0.5 * (lo + hi)))
    # truncating the previous truncation (as coarsest_same_count does) is truncating the original
    chained, rows = found.tree, np.arange(len(found.tree))
    for lv in range(found.tree.depth - 1, -1, -1):
        chained, step = cc._truncate(chained, lv)
        rows = step[rows]
        direct, direct_rows = cc._truncate(found.tree, lv)
        for f in ("level", "coords", "kind", "pos_frac"):
            np.testing.assert_array_equal(getattr(chained, f), getattr(direct, f))
        np.testing.assert_array_equal(rows, direct_rows)
    # the label map of two labellings: scatter when it is a function, every pair when not
    assert cc._label_map(np.array([1, 2, 2, 0]), np.array([5, 7, 7, 0])) == {0: 0, 1: 5, 2: 7}
    assert cc._label_map(np.array([1, 1]), np.array([3, 4])) == {1: 4}


@pytest.mark.parametrize("coarse_level", [0, 5, 7])
def test_find_and_locate_equal_a_reference_search(coarse_level, monkeypatch):
    """Octree.find / locate (compiled binary searches per level finer than the dense table's
    level, one lookup in that table for the coarser ones): the same rows as a reference that
    looks the point's cell up at every level in a dict of the kept cells, for points inside,
    outside and between kept cells and for queries at every level."""
    monkeypatch.setattr(cc, "COARSE_LEVEL", coarse_level)
    # a box beside a sphere: large inside cells next to subdivided ones, levels 4 to 7
    model = node({"union": [sphere((-0.45, 0.1, 0), 0.35),
                            {"box": {"min": [0.05, -0.6, -0.5], "max": [0.8, 0.55, 0.45]}}]})
    found = cc.detect(model, *cube(), 7)
    tree = found.tree
    assert np.ptp(tree.level) >= 3
    kept = {(int(lv), *map(int, c)): r for r, (lv, c) in enumerate(zip(tree.level, tree.coords, strict=True))}

    def reference(points: np.ndarray, level: int) -> np.ndarray:
        """The kept cell holding each point at ``level`` or above, -1 when none."""
        out = np.full(len(points), -1)
        ijk = np.floor((points - tree.origin) / tree.finest).astype(np.int64)
        for n, c in enumerate(ijk):
            hits = [kept[key] for lv in range(level + 1) if (key := (lv, *(c >> (tree.depth - lv)))) in kept]
            assert len(hits) <= 1  # kept cells never overlap
            out[n] = hits[0] if hits else -1
        return out

    lo, hi = tree.boxes()
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1, 1, (4000, 3))
    want = reference(pts, tree.depth)
    np.testing.assert_array_equal(tree.locate(pts), want)
    assert (want < 0).sum() > 1000 and (want >= 0).sum() > 300
    # a point anywhere in a kept cell, near its corners too, finds that cell from the finest level
    for corner in (0.01, 0.5, 0.99):
        np.testing.assert_array_equal(tree.locate(lo + corner * (hi - lo)), np.arange(len(tree)))
    for level in range(tree.depth + 1):  # queries at coarser levels: the cell or a kept ancestor
        ijk = np.floor((pts - tree.origin) / tree.cell_size(level)).astype(np.int64)
        np.testing.assert_array_equal(tree.find(level, ijk), reference(pts, level))


@pytest.mark.parametrize("coarse_level", [0, 4, 6])
def test_merged_neighbours_equal_the_search_of_every_face(coarse_level, monkeypatch):
    """The marking's same-level neighbours by merging a level's sorted keys (cc._level_neighbours,
    any chunk bounds) are the rows the per-cell search finds across each face, coarser and
    missing neighbours included; the union of them gives the same clusters."""
    monkeypatch.setattr(cc, "COARSE_LEVEL", coarse_level)
    model = node({"union": [sphere((-0.45, 0.1, 0), 0.35), sphere((0.5, 0.1, 0), 0.3),
                            {"box": {"min": [0.05, -0.6, -0.5], "max": [0.8, 0.0, 0.45]}}]})
    tree = cc.enumerate_octree(model, *cube(), 7)
    keys, rows, off, levels, coarse, c = flat = tree.flat_tables()
    assert c == coarse_level and np.ptp(tree.level) >= 3
    same = coarser = missing = 0
    for lv in range(c + 1, tree.depth + 1):
        s, e = off[lv], off[lv + 1]
        want = cc._face_neighbours(levels, tree.coords, *flat, rows[s:e])
        cut = s + (e - s) // 3
        got = np.concatenate([cc._level_neighbours(*flat, lv, s, cut), cc._level_neighbours(*flat, lv, cut, e)])
        np.testing.assert_array_equal(got, want)
        found = want[want >= 0]
        same, coarser = same + (levels[found] == lv).sum(), coarser + (levels[found] < lv).sum()
        missing += (want < 0).sum()
    assert same > 1000 and coarser > 100 and missing > 1000
    ids, count = cc._face_union(levels, tree.coords, *flat)
    monkeypatch.setattr(cc, "UNION_CHUNK", 97)
    assert count == 2 and np.array_equal(cc._face_union(levels, tree.coords, *flat)[0], ids)


def test_solid_noise_matches_dense_label_at_the_same_tolerance():
    """Appendix A. Reference 1: the field sampled densely on the lattice of cell corners, a cell
    kept when one of its corners is positive (the finest-level rule of Algorithm 1), labelled by
    scipy.ndimage.label with face connectivity: the counts must be equal. Reference 2: a 1.5x
    finer centre-sampled labelling; each of its large pieces must fall in one component, and
    pieces that share a component must be linked by gaps below the two-cell resolution
    (section 4.2)."""
    model = node({"expr": NOISE})
    lo, hi = cc.enclosing_box(model)
    assert np.all(lo > -1.8) and np.all(hi < 1.8)
    origin, size, depth = np.full(3, -1.8), 3.6, 7
    found = cc.detect(model, origin, size, depth)
    n = 2**depth
    ax = origin[0] + np.arange(n + 1) * size / n
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    pos = (model.evaluate(grid) > 0).reshape(n + 1, n + 1, n + 1)
    cells = np.zeros((n, n, n), bool)
    for c in cc._CORNERS:
        cells |= pos[c[0]:c[0] + n, c[1]:c[1] + n, c[2]:c[2] + n]
    _, nref = ndimage.label(cells)
    assert found.count == nref > 50
    m = 3 * n // 2
    fine_ax = origin[0] + (np.arange(m) + 0.5) * size / m
    fine = np.stack(np.meshgrid(fine_ax, fine_ax, fine_ax, indexing="ij"), -1).reshape(-1, 3)
    ref, _ = ndimage.label((model.evaluate(fine) > 0).reshape(m, m, m))
    ref = ref.reshape(-1)
    order = np.argsort(ref, kind="stable")
    bounds = np.searchsorted(ref[order], np.arange(ref.max() + 2))
    pieces = [fine[order[bounds[k]:bounds[k + 1]]] for k in range(1, ref.max() + 1)]
    big = [p for p in pieces if len(p) > 100]
    labels = [set(cc.point_labels(found, p).tolist()) for p in big]
    assert all(len(s) == 1 for s in labels)
    reach = 2 * np.sqrt(3) * size / n + np.sqrt(3) * size / m
    _assert_linked_groups(big, [next(iter(s)) for s in labels], reach)


def _assert_linked_groups(pieces: list, labels: list, reach: float) -> None:
    """Pieces with the same label form a connected graph when pieces closer than ``reach``
    are linked: merging happens only below the resolution."""
    from scipy.spatial import cKDTree

    for lab in set(labels):
        group = [p for p, q in zip(pieces, labels, strict=True) if q == lab]
        trees = [cKDTree(p) for p in group]
        linked, todo = {0}, [0]
        while todo:
            i = todo.pop()
            for j in range(len(group)):
                if j not in linked and trees[i].sparse_distance_matrix(trees[j], reach).nnz:
                    linked.add(j)
                    todo.append(j)
        assert len(linked) == len(group)


# --- separation -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo_pieces():
    box = [[-1.05, -1.05, -1.05], [1.05, 1.05, 1.05]]
    pieces = {method: [node({"component": {"of": DEMO, "index": k, "method": method, "depth": 7,
                                           "adaptive": False, "bounds": box}}) for k in (1, 2)]
              for method in ("surface", "cells")}
    for method in ("surface", "cells"):  # Fig. 3f: the second piece turned and moved
        pieces[f"moved {method}"] = node({"translate": {"by": [0.3, 0, 0], "of": {"rotate": {
            "angle": 30, "axis": "z", "of": {"component": {"of": DEMO, "index": 2, "method": method, "depth": 7,
                                                           "bounds": box}}}}}})
    return pieces


@pytest.mark.parametrize("method", ["surface", "cells"])
def test_separated_fields_are_positive_only_inside_their_piece(demo_pieces, method):
    f = node(DEMO)
    pts = np.random.default_rng(1).uniform(-1.2, 1.2, (20000, 3))
    fv = f.evaluate(pts)
    fk = [p.evaluate(pts) for p in demo_pieces[method]]
    side = np.where(pts[:, 1] < 0, 1, 2)
    for k in (1, 2):
        assert np.all(fv[fk[k - 1] > 0] > 0)
        assert np.all(side[fk[k - 1] > 0] == k)
        assert np.all(fk[k - 1][(fv > 1e-3) & (side == k)] > 0)
    union = rf.r_or(fk[0], fk[1], "r0")
    strict = np.abs(fv) > 1e-9
    assert np.array_equal(union[strict] > 0, fv[strict] > 0)  # the pieces together are the object


@pytest.mark.parametrize("method", ["surface", "cells"])
def test_separated_field_is_zero_on_its_boundary(demo_pieces, method):
    f = node(DEMO)
    rng = np.random.default_rng(2)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    d[:, 1] = -np.abs(d[:, 1]) - 0.2  # rays from inside piece 1 to its outer surface
    d /= np.linalg.norm(d, axis=1)[:, None]
    start = np.array([0.0, -0.5, 0.0])
    a, b = np.zeros(len(d)), np.full(len(d), 2.0)
    for _ in range(60):  # bisection for the zero of f along each ray
        mid = 0.5 * (a + b)
        inside = f.evaluate(start + mid[:, None] * d) > 0
        a, b = np.where(inside, mid, a), np.where(inside, b, mid)
    surf = start + a[:, None] * d
    assert np.all(np.abs(f.evaluate(surf)) < 1e-9)
    assert np.all(np.abs(demo_pieces[method][0].evaluate(surf)) < 1e-8)


@pytest.mark.parametrize("method", ["surface", "cells"])
def test_no_internal_zeros_on_shared_cell_faces(demo_pieces, method):
    piece = demo_pieces[method][0]
    cf = piece.cluster(0.0)
    tree = cf.comp.tree
    c = tree.finest
    # lines along x on cell edges (y, z on the cell lattice) through piece 1, sampled on the
    # cell faces x = origin + i c and between them
    ys = tree.origin[1] + c * np.arange(8, 56, 5)
    zs = tree.origin[2] + c * np.arange(20, 110, 9)
    xs = np.sort(np.concatenate([tree.origin[0] + c * np.arange(2**tree.depth + 1),
                                 np.linspace(-1.1, 1.1, 3001)]))
    yy, zz, xx = np.meshgrid(ys[ys < -0.05], zs[np.abs(zs) < 0.9], xs, indexing="ij")
    pts = np.stack([xx, yy, zz], -1).reshape(-1, 3)
    fv = node(DEMO).evaluate(pts)
    inner = fv > 1e-4
    assert inner.sum() > 10000
    assert np.all(piece.evaluate(pts[inner]) > 0)
    assert np.all(cf.value(pts[inner]) > 0)


@FAST
@given(x=st.floats(-1.0, 0.9), y=st.floats(-1.0, 0.9), z=st.floats(-1.0, 0.9), w=st.floats(1e-3, 0.3))
def test_component_bound_encloses_values_under_a_transform(demo_pieces, x, y, z, w):
    """Fig. 3f: a separated piece is an ordinary node: transformed, its bound still encloses it."""
    lo, hi = np.array([[x, y, z]]), np.array([[x + w, y + w, z + w]])
    pts = np.random.default_rng(3).uniform(lo, hi, (64, 3))
    for method in ("surface", "cells"):
        piece = demo_pieces[method][1]
        for n in (piece, demo_pieces[f"moved {method}"]):
            blo, bhi = n.bound(lo, hi)
            v = n.evaluate(pts)
            assert np.all(v >= blo[0] - 1e-12) and np.all(v <= bhi[0] + 1e-12)
        glo, ghi = piece.cluster(0.0).bound(lo, hi)
        g = piece.cluster(0.0).value(pts)
        assert np.all(g >= glo[0] - 1e-12) and np.all(g <= ghi[0] + 1e-12)


def test_recombined_pieces_voxelise(tmp_path):
    """Fig. 3f: the second piece moved away and united with the first; four-thousandths apart
    before, they now are two well separated components."""
    cfg = tmp_path / "fig3f.yaml"
    cfg.write_text("""name: fig3f
domain: {bounds: [[-1.2, -1.2, -1.2], [1.2, 1.6, 1.2]], resolution: 48}
model:
  union:
    - component: {of: &demo {difference: [{superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}},
                                          {box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}}]},
                  index: 1, depth: 7, bounds: &box [[-1.05, -1.05, -1.05], [1.05, 1.05, 1.05]]}
    - translate: {by: [0, 0.4, 0], of: {component: {of: *demo, index: 2, depth: 7, bounds: *box}}}
stages:
  - voxelise: {band: 2}
  - components: {}
""")
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    m = json.loads((tmp_path / "out" / "fig3f" / "manifest.json").read_text())
    assert m["components"]["count"] == 2


def test_bad_component_index_is_a_config_error(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("""name: bad
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 32}
model:
  component: {of: {sphere: {radius: 0.5}}, index: 2, depth: 5}
stages:
  - voxelise: {}
""")
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml:4" in err and "component index 2" in err


# --- collision (section 5, Fig. 6) --------------------------------------------------------------------


def _microstructure() -> dict:
    struts = []
    for a, axis in enumerate("xyz"):
        for u in (-0.4, 0.0, 0.4):
            for v in (-0.4, 0.0, 0.4):
                c = [0.0, 0.0, 0.0]
                others = [i for i in range(3) if i != a]
                c[others[0]], c[others[1]] = u, v
                struts.append({"cylinder": {"center": c, "radius": 0.08, "axis": axis, "height": 1.8}})
    return {"intersection": [{"union": struts}, sphere((0, 0, 0), 0.85)]}


def _needle(y: float) -> dict:
    """A vertical needle between the struts, |y - 0.105| from the x-struts at y = 0."""
    return {"cylinder": {"center": [0.2, y, 0.2], "radius": 0.025, "axis": "z", "height": 1.2}}


@pytest.mark.parametrize(("y", "expect"), [(0.2, False), (0.105 + 0.016, False), (0.105 - 0.024, True)])
def test_needle_and_microstructure(y, expect):
    box = (np.full(3, -1.0), np.full(3, 1.0))
    res = cc.collide(node(_microstructure()), node(_needle(y)), box, 0.008)
    assert res.tolerance <= 0.008
    assert res.collide is expect
    assert (res.count > 0) is expect


def test_collide_command(tmp_path, capsys):
    import yaml

    def cfg(name: str, model: dict) -> Path:
        p = tmp_path / f"{name}.yaml"
        p.write_text(yaml.safe_dump({"name": name, "domain": {"bounds": [[-1, -1, -1], [1, 1, 1]], "voxel_size": 0.008},
                                     "model": model, "stages": [{"voxelise": {}}]}))
        return p

    micro = cfg("micro", _microstructure())
    assert main(["collide", str(micro), str(cfg("out", _needle(0.105 + 0.016)))]) == 0
    assert capsys.readouterr().out.splitlines()[0] == "collision: no"
    assert main(["collide", str(micro), str(cfg("in", _needle(0.105 - 0.024)))]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "collision: yes" and out[1].startswith("tolerance: ")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    assert main(["collide", str(micro), str(bad)]) == 2


# --- the stage -------------------------------------------------------------------------------------


TWO = """name: two
domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 64}}
model:
  union:
    - sphere: {{center: [-0.5, 0, 0], radius: 0.35}}
    - sphere: {{center: [0.5, 0, 0], radius: {r2}}}
stages:
  - voxelise: {{band: 3}}
  - components: {params}
  - export: {{vdb: true}}
"""


def _run(tmp_path: Path, r2: float, params: str) -> tuple[dict, Path]:
    cfg = tmp_path / "two.yaml"
    cfg.write_text(TWO.format(r2=r2, params=params))
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    out = tmp_path / "out" / "two"
    return json.loads((out / "manifest.json").read_text()), out


def _grid_values(path: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    g = vdb.read(str(path), name)
    lo, hi = g.evalActiveVoxelBoundingBox()
    arr = np.zeros([h - l + 1 for l, h in zip(lo, hi, strict=True)], np.float32)
    g.copyToArray(arr, ijk=lo)
    return arr, np.asarray(lo)


def test_run_two_spheres_labels_every_active_voxel(tmp_path):
    m, out = _run(tmp_path, 0.35, "{}")
    assert m["components"]["count"] == 2
    assert m["components"]["volumes"] == pytest.approx([4 / 3 * np.pi * 0.35**3] * 2, rel=0.05)
    assert m["grids"]["component"]["active_voxels"] == m["grids"]["frep"]["active_voxels"]
    comp = vdb.read(str(out / "two.vdb"), "component")
    assert comp.metadata["component_count"] == 2
    arr, lo = _grid_values(out / "two.vdb", "component")
    assert set(np.unique(arr).tolist()) == {0.0, 1.0, 2.0}
    h = 2.0 / 64
    xs = (np.nonzero(arr)[0] + lo[0]) * h
    assert np.all(arr[np.nonzero(arr)] == np.where(xs < 0, 1.0, 2.0))


def test_keep_largest_removes_the_small_piece_and_separate_writes_pieces(tmp_path):
    m, out = _run(tmp_path, 0.2, "{keep: largest, separate: true}")
    c = m["components"]
    assert c["count"] == 2 and c["kept"] == [1] and c["files"] == ["two_component_1.vdb"]
    frep, lo = _grid_values(out / "two.vdb", "frep")
    h = 2.0 / 64
    active_x = (np.nonzero(np.abs(frep) < 0.08)[0] + lo[0]) * h
    assert active_x.max() < 0.0  # nothing of the small sphere at x = 0.5 is left
    g = vdb.read(str(out / "two.vdb"), "frep")
    acc = g.getConstAccessor()
    assert acc.getValue((16, 0, 0)) < 0  # the small sphere's centre is outside now
    assert acc.getValue((-16, 0, 0)) > 0
    piece = vdb.read(str(out / "two_component_1.vdb"), "frep").getConstAccessor()
    assert piece.getValue((-16, 0, 0)) > 0 and piece.getValue((16, 0, 0)) < 0
    assert {o["path"] for o in m["outputs"]} >= {"two.vdb", "two_component_1.vdb"}


def test_keep_min_volume_and_bad_params(tmp_path, capsys):
    m, _ = _run(tmp_path, 0.2, "{keep: {min_volume: 0.05}}")  # volumes 0.18 and 0.034
    assert m["components"]["kept"] == [1]
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(TWO.format(r2=0.2, params="{tolerance: 0.01, depth: 5}"))
    assert main(["validate", str(cfg)]) == 2
    assert "tolerance or depth" in capsys.readouterr().err


# --- meshes (BSP-field node) ----------------------------------------------------------------------


KNOT = Path(__file__).resolve().parents[2] / "shared" / "meshes" / "knot2.off"


@pytest.mark.realdata
@pytest.mark.skipif(not KNOT.exists(), reason="../shared/meshes is absent")
def test_two_component_knot_mesh():
    model = node({"mesh": {"path": str(KNOT)}})
    v = np.loadtxt(KNOT, skiprows=3, max_rows=5760)  # OFF, counts, an empty line, the vertices
    lo, hi = v.min(axis=0), v.max(axis=0)
    size = 1.1 * float((hi - lo).max())
    pad = 0.05 * size
    found = cc.detect(model, 0.5 * (lo + hi) - size / 2, size, 5, region=(lo - pad, hi + pad))
    assert found.count == 2


def _two_sphere_blocks(gap: float, cut: bool = False):
    """Two spheres ``gap`` apart (``cut``: the second one a box that the domain cuts, so the
    pieces have coarse cells on the domain's faces) voxelised densely into 8^3 blocks (band 3
    voxels) and their components on the voxel-aligned octree: (model, found, blocks, index_min,
    depth)."""
    from types import SimpleNamespace

    from pipeline.sparse.grid import BlockGrid
    from stages.components import octree_frame

    h, r = 1.0 / 40, 0.3
    second = {"box": {"min": [gap / 2, -0.9, -0.9], "max": [1.5, 0.9, 0.9]}} if cut else sphere((r + gap / 2, 0, 0.01), r)
    model = node({"union": [sphere((-r - gap / 2, 0.03, 0), r), second]})
    imin, imax = np.array([-40, -20, -20]), np.array([39, 19, 19])
    dom = SimpleNamespace(voxel_size=h, dims=imax - imin + 1, index_min=imin, index_max=imax)
    origin, size, depth, region = octree_frame(dom, None, None)
    found = cc.detect(model, origin, size, depth, 0.0, region)
    assert found.count == 2
    o = np.stack(np.meshgrid(*[np.arange(lo, hi + 1, 8) for lo, hi in zip((imin // 8) * 8, imax, strict=True)],
                             indexing="ij"), -1).reshape(-1, 3)
    loc = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(8), indexing="ij"), -1)
    ijk = o[:, None, None, None, :] + loc[None]
    f = model.evaluate(ijk.reshape(-1, 3) * h).reshape(len(o), 8, 8, 8)
    inside_dom = np.all((ijk >= imin) & (ijk <= imax), axis=-1)
    active = (np.abs(f) < 3 * h) & inside_dom
    keep = active.any(axis=(1, 2, 3))
    blocks = BlockGrid(h, 3 * h, o[keep], f[keep].astype(np.float32), active[keep])
    return model, found, blocks, imin, depth


@pytest.mark.parametrize("gap", [0.03, 0.12])
def test_block_labels_equal_point_labels_on_every_active_voxel(gap):
    """The stage's painted labels (cc.block_labels) are the labels point_labels gives at the voxel
    centres, including band voxels outside every kept cell (nearest finest cell), for pieces far
    apart and for pieces closer than the band."""
    model, found, blocks, imin, depth = _two_sphere_blocks(gap)
    h = blocks.voxel_size
    got = cc.block_labels(found, blocks, imin)
    b, i, j, k = np.nonzero(blocks.active)
    pts = (blocks.origins[b] + np.stack([i, j, k], axis=1)) * h
    want = cc.point_labels(found, pts)
    assert np.all(want > 0)
    assert (found.tree.locate(pts) < 0).sum() > 1000  # the nearest-cell search is exercised
    assert np.array_equal(got[b, i, j, k], want)
    assert not got[~blocks.active].any()


@pytest.mark.parametrize("hole", ["inactive", "no_block"])
def test_block_labels_where_finest_cells_are_not_active_voxels(hole, monkeypatch):
    """Finest cells at voxels the band left inactive, or on no block at all (a knot's mesh at
    512^3 has 176 of the latter): block_labels still equals point_labels on every active voxel
    (the nearest finest cell is any finest cell), and the local search still runs: only voxels
    within its reach of a finest cell on no block take the exact path. (The search read the
    labels of inactive voxels as 0 and wrote 0 into active ones; a finest cell on no block sent
    every voxel outside the kept cells to point_labels.)"""
    from pipeline.sparse.grid import BlockGrid

    model, found, blocks, imin, depth = _two_sphere_blocks(0.03)
    h = blocks.voxel_size
    tree = found.tree
    assert int(cc.block_labels(found, blocks, imin).astype(bool).sum()) == int(blocks.active.sum())
    fine = imin + tree.coords[tree.level == tree.depth]
    rng = np.random.default_rng(3)
    if hole == "inactive":  # half of the finest cells' voxels out of the band
        pick = fine[rng.random(len(fine)) < 0.5]
        o = (pick >> 3) << 3
        row = blocks.block_index(o)
        i, j, k = (pick - o).T
        active = blocks.active.copy()
        active[row, i, j, k] = False
        blocks = BlockGrid(h, blocks.background, blocks.origins, blocks.values, active)
    else:  # a few blocks holding finest cells dropped
        rows = np.unique(blocks.block_index((fine >> 3) << 3))
        drop = rng.choice(rows, 6, replace=False)
        keep = np.setdiff1d(np.arange(len(blocks.origins)), drop)
        blocks = BlockGrid(h, blocks.background, blocks.origins[keep], blocks.values[keep], blocks.active[keep])
    exact = []
    real = cc.point_labels
    monkeypatch.setattr(cc, "point_labels", lambda comp, pts: exact.append(len(pts)) or real(comp, pts))
    got = cc.block_labels(found, blocks, imin)
    b, i, j, k = np.nonzero(blocks.active)
    pts = (blocks.origins[b] + np.stack([i, j, k], axis=1)) * h
    want = real(found, pts)
    outside = int((tree.locate(pts) < 0).sum())
    assert np.all(want > 0) and outside > 1000
    assert np.array_equal(got[b, i, j, k], want)
    assert not got[~blocks.active].any()
    # the voxels beyond the search's reach of every finest cell, and (no_block) those near the
    # dropped blocks, went to point_labels; not the thousands outside the kept cells
    assert sum(exact) < outside / 4


@pytest.mark.parametrize("gap, cut", [(0.03, False), (0.12, False), (0.12, True)])
def test_piece_blocks_equal_the_separation_field_at_every_voxel(gap, cut):
    """The stage's compiled piece (ClusterField.piece_blocks: membership painted by cells, the
    distance block by block) is r_and(f, value(voxel centre), "r0") bit for bit on every active
    voxel of the piece, on the coarsest same-count tree (coarser than the voxels for the wider
    gaps; boundary faces of several sizes where the domain cuts a piece)."""
    model, found, blocks, imin, depth = _two_sphere_blocks(gap, cut)
    labels = cc.block_labels(found, blocks, imin)
    sep, mapping = cc.coarsest_same_count(found)
    assert (sep.tree.depth < depth) == (gap > 0.1)
    for k in (1, 2):
        field = cc.ClusterField(sep, mapping[k], "surface")
        assert (len(field.index) > 1) == (cut and k == 2)  # boxes of several size classes
        rows, vals, act = field.piece_blocks(blocks, labels, k, depth, imin)
        mine = blocks.active & (labels == k)
        assert np.array_equal(rows, np.flatnonzero(mine.any(axis=(1, 2, 3))))
        assert np.array_equal(act, mine[rows])
        b, i, j, kk = np.nonzero(act)
        pts = (blocks.origins[rows][b] + np.stack([i, j, kk], axis=1)) * blocks.voxel_size
        g = field.value(pts)
        assert (g > 0).any() and (g < 0).any() and (np.abs(g) < field.clamp).any()
        want = rf.r_and(blocks.values[rows][b, i, j, kk].astype(np.float64), g, "r0").astype(np.float32)
        assert np.array_equal(vals[b, i, j, kk].view(np.int32), want.view(np.int32))
        assert np.all(vals[~act] == np.float32(blocks.background))


# --- the compiled key helpers against their NumPy definitions ------------------------------------------


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 60_000), st.integers(1, 2_000), st.integers(0, 5), st.booleans(), st.integers(0, 2**31))
def test_pack_rows_and_unique_keys_equal_numpy(n, span, shift, sorted_runs, seed) -> None:
    """pack_rows(coords, rows, shift) == pack(coords[rows] >> shift) and unique_keys == np.unique
    (values and inverse), on random cells and on cells that come in sorted runs (as the octree's do);
    sizes on both sides of pack's small-array path."""
    rng = np.random.default_rng(seed)
    coords = rng.integers(0, span, (n, 3), dtype=np.int64)
    if sorted_runs and n:
        coords = cc.unpack(np.sort(cc.pack(coords)))
    rows = rng.permutation(n)[: n // 2]
    shifts = rng.integers(0, shift + 1, len(rows))
    ref = (coords[rows] >> shifts[:, None])
    ref = (ref[:, 0] << 42) | (ref[:, 1] << 21) | ref[:, 2]
    assert np.array_equal(cc.pack_rows(coords, rows, shifts), ref)
    assert np.array_equal(cc.pack(coords), cc.pack_rows(coords))
    assert np.array_equal(cc.pack_rows(coords, np.zeros(0, np.int64)), np.zeros(0, np.int64))  # no rows: none
    u, inv = cc.unique_keys(ref)
    ru, rinv = np.unique(ref, return_inverse=True)
    assert np.array_equal(u, ru) and np.array_equal(inv, rinv.reshape(-1))
    assert np.array_equal(cc.unique_keys(ref, inverse=False)[0], ru)


def test_finest_kinds_split_by_the_control_range() -> None:
    """Inside: all 8 corners positive (255); border: mixed, with the fraction of positive corners;
    outside (0) dropped; in the cells' order."""
    rng = np.random.default_rng(3)
    cells = rng.integers(0, 100, (5000, 3))
    signs = rng.choice(np.array([0, 255, 1, 7, 128, 254], np.uint8), 5000)
    kinds = cc._finest_kinds(cells, signs)
    npos = np.array([bin(int(s)).count("1") for s in signs])
    assert np.array_equal(kinds[cc.INSIDE][0], cells[npos == 8]) and (kinds[cc.INSIDE][1] == 1).all()
    mixed = (npos > 0) & (npos < 8)
    assert np.array_equal(kinds[cc.BORDER][0], cells[mixed]) and np.allclose(kinds[cc.BORDER][1], npos[mixed] / 8)


KEEP_THEN_HFREP = """name: keep
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 96}
model:
  union:
    - sphere: {center: [-0.3, 0, 0], radius: 0.5}
    - sphere: {center: [0.41, 0.03, 0.01], radius: 0.17}
stages:
  - voxelise: {band: 1}
  - components: {keep: largest}
  - hfrep: {}
  - export: {vdb: true}
"""


def test_keep_then_hfrep_every_written_voxel_on_the_kept_side(tmp_path):
    """After ``keep`` removed a piece two voxels from the kept one (leaves shared: 158 of the
    removed piece's inside voxels stay inactive, with positive values, in the kept leaves), every
    grid read back from the .vdb puts each voxel of the domain, active, inactive or tile, farther
    than 1.5 voxels from the kept sphere on its side (hfrep then floods the band's signs:
    voxelise's values no longer all carry them)."""
    cfg = tmp_path / "keep.yaml"
    cfg.write_text(KEEP_THEN_HFREP)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    n, h = 97, 2.0 / 96
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3) - 48
    kept = 0.5 - np.linalg.norm(ijk * h - np.array([-0.3, 0, 0]), axis=1)
    m = json.loads((tmp_path / "out" / "keep" / "manifest.json").read_text())
    assert m["components"]["count"] == 2 and m["components"]["kept"] == [1]
    removed = 0.17 - np.linalg.norm(ijk * h - np.array([0.41, 0.03, 0.01]), axis=1)
    assert (removed > 1.5 * h).sum() > 500  # the removed piece's voxels are checked too
    for name, positive_inside, margin in (("frep", True, 1.5), ("hfrep", True, 1.5), ("surface", False, 1.5),
                                          ("density", True, 4.0)):
        g = vdb.read(str(tmp_path / "out" / "keep" / "keep.vdb"), name)
        arr = np.zeros((n, n, n), np.float32)
        g.copyToArray(arr, ijk=(-48, -48, -48))
        v = arr.reshape(-1)
        written_inside = (v > 0.5) if name == "density" else ((v > 0) if positive_inside else (v < 0))
        far = np.abs(kept) > margin * h
        assert np.array_equal(written_inside[far], kept[far] > 0), name


def test_order_keeping_passes_give_the_one_range_result() -> None:
    """_split_into and _truncated split their input into ranges run in parallel; any number of
    ranges gives the arrays of one range (a serial pass): same cells, same order."""
    from pipeline.topology import components as cc

    rng = np.random.default_rng(7)
    m, n0 = 50_000, 7_000
    signs = rng.choice(np.array([0, 255, 3, 17, 128], np.uint8), m)
    cells = rng.integers(0, 1024, (m, 3))
    coarse = (rng.integers(0, 10, n0), rng.integers(0, 1024, (n0, 3)), rng.integers(0, 3, n0).astype(np.int8),
              rng.random(n0))
    one = cc._split_into(*coarse, cells, signs, 10, 1)
    assert len(one[0]) == n0 + int((signs != 0).sum()) and (one[2][n0:][:int((signs == 255).sum())] == cc.INSIDE).all()
    for chunks in (2, 7, 64):
        assert all(np.array_equal(a, b) for a, b in zip(one, cc._split_into(*coarse, cells, signs, 10, chunks),
                                                          strict=True))
    level = rng.integers(0, 8, m)
    deep = level > 4
    inv = rng.integers(0, 300, int(deep.sum()))
    anc = np.sort(rng.choice(1 << 30, 300, replace=False)).astype(np.int64)
    kind, frac = signs.astype(np.int8), rng.random(m)
    one = cc._truncated(level, cells, kind, frac, 4, anc, inv, 1)
    assert (one[4][deep] == int((~deep).sum()) + inv).all()  # deep cells: their ancestor's row
    for chunks in (2, 7, 64):
        got = cc._truncated(level, cells, kind, frac, 4, anc, inv, chunks)
        assert all(np.array_equal(a, b) for a, b in zip(one, got, strict=True))


@FAST
@given(seed=st.integers(0, 2**31), n=st.integers(1, 3000), span=st.sampled_from([4, 16, 128]),
       chunk=st.sampled_from([7, 1 << 16]))
def test_shared_lattice_points_evaluated_once_give_the_same_child_signs(seed, n, span, chunk) -> None:
    """Algorithm 1's child corner signs with each shared lattice point evaluated once (by its
    first parent in key order) equal those with every parent evaluating its 19 points: parents
    on the domain's low faces (coordinate 0), dense and scattered sets, several chunks; and the
    model is evaluated exactly once per distinct new lattice point."""
    rng = np.random.default_rng(seed)
    c = rng.integers(0, span, (n, 3))
    keys = np.unique(cc.key_of(c[:, 0], c[:, 1], c[:, 2]))
    parents = cc.unpack(keys)
    psigns = rng.integers(0, 256, len(parents)).astype(np.uint8)
    cache = cc._CornerCache(node({"sphere": {"center": [0.3, 0.2, 0.25], "radius": 0.3}}), np.zeros(3),
                            0.6 / (4 * span), 0.0)  # the sphere fills the lattice: both signs
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cc, "CHILD_CHUNK", chunk)
        once = cc._child_corner_signs(cache, parents, psigns, 2)
        evaluated = cache.evaluations
        assert np.array_equal(once, cc._child_corner_signs_each(cache, parents, psigns, 2))
    new = (2 * parents[:, None, :] + cc._NEW19[None]).reshape(-1, 3)
    assert evaluated == len(np.unique(cc.key_of(new[:, 0], new[:, 1], new[:, 2])))
    unsorted = cc._child_corner_signs(cache, parents[::-1].copy(), psigns[::-1].copy(), 2)  # not in key order
    assert np.array_equal(unsorted.reshape(-1, 8)[::-1].reshape(-1), once)


def test_components_of_an_r0_mesh_run_on_its_sign_proxy(tmp_path):
    """Components depend on the sign alone: detect enumerates the model's sign proxy (the meshes'
    min_max twins, pruned per cell) and finds the same count, volumes and labels as enumerating
    the r0 model itself, whose every cell walks the whole BSP-tree (the octrees differ where the
    r0 union's affine forms and the min_max tape's intervals refine differently)."""
    import trimesh

    from pipeline.oracles import REGISTRY

    def node(kind, **params):
        cls = REGISTRY[kind]
        return cls(cls.Params.model_validate(params))

    m = trimesh.creation.icosphere(3)
    v = m.vertices * (0.35 + 0.03 * np.sin(5 * m.vertices[:, :1]) * np.sin(7 * m.vertices[:, 1:2]))
    path = tmp_path / "blob.off"
    trimesh.Trimesh(v, m.faces, process=False).export(str(path))
    model = node("union", rfunc="r0", of=[node("translate", by=[-0.45, 0, 0], of=node("mesh", path=str(path))),
                                          node("translate", by=[0.45, 0.1, 0], of=node("mesh", path=str(path)))])
    assert model.sign_proxy() is not model
    origin, size, depth = np.array([-1.0, -1.0, -1.0]), 2.0, 6
    got = cc.detect(model, origin, size, depth)
    want = cc.label_cells(cc.enumerate_octree(model, origin, size, depth))
    assert got.count == want.count == 2
    np.testing.assert_array_equal(got.volumes, want.volumes)
    np.testing.assert_array_equal(got.volume_bounds, want.volume_bounds)
    p = np.random.default_rng(2).uniform(-0.9, 0.9, (20000, 3))
    lg, lw = cc.point_labels(got, p), cc.point_labels(want, p)
    assert set(np.unique(lw)) == {1, 2}
    np.testing.assert_array_equal(lg, lw)  # labels in scan order of the lowest cell: the same numbers


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 3000), st.integers(0, 2**31 - 1), st.floats(0.0, 3.0))
def test_cluster_ids_in_place_number_clusters_by_first_appearance(n, seed, density):
    """_cluster_ids (written over the union-find forest) equals looking up every cell's root and
    numbering the roots in order of first appearance; and it agrees with scipy's components of
    the same edges."""
    rng = np.random.default_rng(seed)
    m = int(density * n)
    rows, nbr = rng.integers(0, n, m), rng.integers(-1, n, (m, 6))
    parent = np.arange(n)
    cc._union_rows(parent, rows, nbr)
    roots = np.array([cc._root(parent.copy(), r) for r in range(n)])
    _, first = np.unique(roots, return_index=True)
    rank = {int(roots[f]): i for i, f in enumerate(sorted(first))}
    want = np.array([rank[int(a)] for a in roots])
    got, count = cc._cluster_ids(parent.copy())
    assert count == len(first)
    assert np.array_equal(got, want)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    src, dst = np.repeat(rows, 6), nbr.reshape(-1)
    keep = dst >= 0
    graph = coo_matrix((np.ones(int(keep.sum())), (src[keep], dst[keep])), shape=(n, n))
    k, lab = connected_components(graph, directed=False)
    assert k == count
    assert len(np.unique(np.stack([lab, got], axis=1), axis=0)) == count  # the same partition


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 300), st.integers(1, 40), st.integers(0, 2**31 - 1), st.booleans())
def test_rows_by_label_equal_a_scan_per_piece(nb, count, seed, uniform_blocks) -> None:
    """Every piece's block rows from one pass (separating 242 pieces scanned every block 242
    times) equal a scan of the blocks for that piece; labels <= 0 and inactive voxels ignored."""
    rng = np.random.default_rng(seed)
    active = rng.random((nb, 8, 8, 8)) < rng.random()
    labels = rng.integers(-1, count + 1, (nb, 8, 8, 8))
    if uniform_blocks:
        labels = np.repeat(rng.integers(0, count + 1, nb), 512).reshape(nb, 8, 8, 8)
    start, rows = cc.rows_by_label(active, labels, count)
    for k in range(1, count + 1):
        assert np.array_equal(rows[start[k]:start[k + 1]], np.flatnonzero((active & (labels == k)).any(axis=(1, 2, 3))))


def test_separation_makes_the_octrees_ancestor_sets_once() -> None:
    model = node({"union": [sphere((-0.6 + 0.3 * i, 0, 0), 0.08) for i in range(5)]})
    found = cc.detect(model, *cube(), 6)
    assert found.count == 5 and found.tree._ancestors is None
    faces = [cc.boundary_faces(found, k) for k in range(1, 6)]
    kept = found.tree._ancestors
    assert kept is not None and cc._ancestor_sets(found.tree) is kept
    assert all(len(lo) > 0 for lo, _ in faces)


@pytest.mark.parametrize("depth", [5, 7])
def test_ancestor_sets_are_the_cells_with_kept_descendants(depth) -> None:
    """_ancestor_sets, made bottom up (each level the parents of the next one's kept cells and
    ancestors), equals its definition: per level, every cell some deeper kept cell lies in."""
    model = node({"union": [sphere((-0.6 + 0.3 * i, 0.05 * i, 0), 0.08 + 0.02 * i) for i in range(5)]})
    tree = cc.detect(model, *cube(), depth).tree
    got = cc._ancestor_sets(tree)
    assert len(got) == depth + 1 and len(got[depth]) == 0
    for lv in range(depth + 1):
        deeper = tree.level > lv
        want = np.unique(cc.pack(tree.coords[deeper] >> (tree.level[deeper] - lv)[:, None])) if deeper.any() \
            else np.zeros(0, np.int64)
        assert np.array_equal(got[lv], want), lv
    found = cc.detect(model, *cube(), depth)  # the faces from a cluster's rows, as the stage gives them
    for k in range(1, found.count + 1):
        a = cc.boundary_faces(found, k)
        b = cc.boundary_faces(found, k, np.flatnonzero(found.labels == k))
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def _faces_by_levels(comp, label):
    """boundary_faces by its definition, level by level in NumPy (the walk it had before it was
    compiled): per direction, a face against another label or no cell, the four children on the
    face against finer cells."""
    tree = comp.tree
    anc = cc._ancestor_sets(tree)
    rows = np.flatnonzero(comp.labels == label)
    out = []
    for d in cc._FACES:
        axis = int(np.nonzero(d)[0][0])
        lv, cs = tree.level[rows], tree.coords[rows]
        while len(lv):
            nxt_l, nxt_c = [], []
            for level in np.unique(lv):
                c = cs[lv == level]
                found = tree.find(int(level), c + d)
                same = (found >= 0) & (comp.labels[np.maximum(found, 0)] == label)
                deeper = (found < 0) & cc._has_descendants(anc, int(level), c + d)
                face = ~same & ~deeper
                if face.any():
                    out.append(np.concatenate(cc._face_box(tree, int(level), c[face], d, axis), axis=1))
                if deeper.any():
                    kids = cc._face_children(c[deeper], d, axis)
                    nxt_l.append(np.full(len(kids), level + 1)), nxt_c.append(kids)
            lv = np.concatenate(nxt_l) if nxt_l else np.zeros(0, np.int64)
            cs = np.concatenate(nxt_c) if nxt_c else np.zeros((0, 3), np.int64)
    faces = np.concatenate(out) if out else np.zeros((0, 6))
    return faces[np.lexsort(faces.T[::-1])]


@pytest.mark.parametrize("case", ["spheres5", "spheres7", "cut"])
def test_compiled_boundary_faces_are_the_octree_surface(case) -> None:
    """The compiled walk gives every cluster the faces of the level-by-level definition (the
    same boxes, in another order), on the detected tree and the coarsest same-count one; with
    a piece the domain cuts, faces of several sizes (cells of several levels on its surface)."""
    if case == "cut":
        _, found, *_ = _two_sphere_blocks(0.12, True)
    else:
        model = node({"union": [sphere((-0.6 + 0.3 * i, 0.05 * i, 0), 0.08 + 0.02 * i) for i in range(5)]})
        found = cc.detect(model, *cube(), int(case[-1]))
    sep, _ = cc.coarsest_same_count(found)
    sizes = 0
    for comp in (found, sep):
        for k in range(1, comp.count + 1):
            lo, hi = cc.boundary_faces(comp, k)
            got = np.concatenate([lo, hi], axis=1)
            got = got[np.lexsort(got.T[::-1])]
            assert len(got) > 0 and np.array_equal(got, _faces_by_levels(comp, k))
            sizes = max(sizes, len(np.unique(np.round((hi - lo).max(axis=1), 12))))
    assert sizes > 1 or case != "cut"
