"""Compiled BSP-tree build (pipeline.mesh.bsp_build, bsp-fields.txt section 3.3): exact fields on
generated meshes of 5k-20k faces, about n log n scaling, deep trees, the NumPy reference."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh

from pipeline.mesh.bsp import BSPField, build_tree, merge_coplanar

FAMILIES = ("min_max", "r0", "sardf")


def bumpy_sphere(subdivisions: int) -> trimesh.Trimesh:
    """Icosphere displaced radially by a smooth noise, so that it is not convex (20 * 4^s faces)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = m.vertices
    r = 1.0 + 0.05 * np.sin(5 * v[:, 0]) * np.sin(7 * v[:, 1]) * np.sin(6 * v[:, 2])
    return trimesh.Trimesh(v * r[:, None], m.faces, process=False)


@pytest.fixture(scope="module", params=[4, 5], ids=["5k", "20k"])
def generated(request):
    mesh = bumpy_sphere(request.param)
    return mesh, BSPField.from_mesh(mesh, rfunc="r0")


def test_sign_equals_containment_generated(generated) -> None:
    mesh, field = generated
    p = np.random.default_rng(0).uniform(-1.2, 1.2, (3000, 3))
    _, dist, _ = trimesh.proximity.closest_point(mesh, p)
    p = p[dist > 1e-6]
    inside = mesh.contains(p)
    for fam in FAMILIES:
        v = field.with_rfunc(fam).evaluate(p)
        assert np.array_equal(v > 0, inside), fam
        assert np.all(v != 0)


def test_zero_on_faces_generated(generated) -> None:
    mesh, field = generated
    s, _ = trimesh.sample.sample_surface(mesh, 1000, seed=1)
    for fam in FAMILIES:
        assert np.abs(field.with_rfunc(fam).evaluate(s)).max() < 1e-9 * mesh.scale, fam


def test_optimised_fewer_splits_than_naive_generated(generated) -> None:
    mesh, field = generated
    if len(mesh.faces) > 6000:
        pytest.skip("one size is enough")
    naive = BSPField.from_mesh(mesh, planes="naive", special_cases=False)
    assert field.stats["splits"] < 0.5 * naive.stats["splits"]


def _build_seconds(polys) -> float:
    t = time.perf_counter()
    build_tree(polys, sample=1024, work=32)  # one search effort for both sizes
    return time.perf_counter() - t


def test_build_scales_about_n_log_n() -> None:
    """4x the faces may take at most 10x the time (n log n gives ~4.5x; n^2 would give 16x)."""
    small, large = (merge_coplanar(m.vertices, m.faces) for m in (bumpy_sphere(5), bumpy_sphere(6)))
    _build_seconds(merge_coplanar(*(lambda m: (m.vertices, m.faces))(bumpy_sphere(2))))  # compile
    ts = min(_build_seconds(small) for _ in range(2))
    tl = _build_seconds(large)
    assert tl < 10 * ts + 0.5, f"20k faces {ts:.2f} s, 80k faces {tl:.2f} s"


def test_deep_tree_evaluates_and_bounds() -> None:
    """Without the median cuts a near-convex surface gives long chains (depth in the thousands):
    evaluation and bounds are loops over the post-order arrays and the special-case pass is
    bounded, so nothing recurses."""
    mesh = bumpy_sphere(5)
    polys = merge_coplanar(mesh.vertices, mesh.faces)
    field = BSPField(build_tree(polys, kd_leaf=None), "r0", {}, float(mesh.scale))
    assert field.tree.depth > 1000
    p = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    v = field.evaluate(p)
    assert v[0] > 0 > v[1]
    lo, hi = field.bound(p - 0.01, p + 0.01)
    assert np.all(lo <= v) and np.all(v <= hi)


def test_median_cuts_make_large_trees_shallow() -> None:
    """Above KD_MIN triangles the optimised build first halves the list by median cuts: the
    20k-face bumpy sphere's tree is tens of nodes deep instead of thousands, with no more splits
    than the chain (and far fewer than naive), and its field is exact (sign and zero set above)."""
    from pipeline.mesh.bsp import KD_LEAF, KD_MIN

    mesh = bumpy_sphere(5)
    polys = merge_coplanar(mesh.vertices, mesh.faces)
    assert len(polys.pieces) > KD_MIN
    kd, chain = build_tree(polys), build_tree(polys, kd_leaf=None)
    assert kd.depth < 3 * (np.log2(len(polys.pieces) / KD_LEAF) + KD_LEAF) and chain.depth > 20 * kd.depth
    assert kd.splits <= 1.2 * chain.splits
    small = merge_coplanar(*(lambda m: (m.vertices, m.faces))(bumpy_sphere(3)))  # 1280 faces: unchanged
    a, b = build_tree(small), build_tree(small, kd_leaf=None)
    assert np.array_equal(a.normals, b.normals) and np.array_equal(a.pos, b.pos)


@pytest.mark.parametrize("planes", ["naive", "optimised"])
def test_compiled_and_python_engines_agree_on_the_set(planes: str) -> None:
    mesh = trimesh.creation.torus(1.0, 0.4, 24, 12)
    polys = merge_coplanar(mesh.vertices, mesh.faces)
    trees = [build_tree(polys, planes, seed=3, engine=e) for e in ("compiled", "python")]
    fields = [BSPField(t, "r0", {}, float(mesh.scale)) for t in trees]
    p = np.random.default_rng(5).uniform(-1.6, 1.6, (3000, 3))
    _, dist, _ = trimesh.proximity.closest_point(mesh, p)
    p = p[dist > 1e-6]
    inside = mesh.contains(p)
    for f in fields:
        assert np.array_equal(f.evaluate(p) > 0, inside)


def test_special_cases_are_counted_and_bounded() -> None:
    mesh = bumpy_sphere(4)
    a = BSPField.from_mesh(mesh, special_cases=True)
    b = BSPField.from_mesh(mesh, special_cases=False)
    assert a.stats["special_cases"] >= 0 and b.stats["special_cases"] == 0
    p = np.random.default_rng(6).uniform(-1.2, 1.2, (2000, 3))
    assert np.array_equal(a.evaluate(p) > 0, b.evaluate(p) > 0)


def test_vectorised_triangle_split_equals_clip_simplex() -> None:
    """bsp._split_triangles (median cuts split ~ one triangle per face) gives the parts of the
    per-piece Split_Polygon (_clip_simplex), in the same order, to the bit; cut planes through
    vertices (axis planes at 0 through an icosphere) included."""
    from pipeline.mesh import bsp

    polys = merge_coplanar(*(lambda m: (m.vertices, m.faces))(bumpy_sphere(3)))
    rng = np.random.default_rng(0)
    for trial in range(12):
        n = rng.normal(size=3)
        n, c = n / np.linalg.norm(n), float(rng.uniform(-0.5, 0.5))
        if trial % 3 == 0:
            n, c = np.eye(3)[trial % 9 // 3], 0.0
        s, cls = bsp._classify(polys, n, c, 1e-9)
        idx = np.nonzero((cls == 3)[polys.owner])[0]
        assert len(idx) > 0
        got = bsp._split_triangles(polys, s, idx, 1e-9)
        ref: list[list] = [[], [], [], []]
        for i in idx:
            si = np.where(np.abs(s[i]) <= 1e-9, 0.0, s[i])
            v = polys.pieces[i]
            one = si.min() >= 0 or si.max() <= 0
            parts = (([v], []) if si.max() > 0 else ([], [v])) if one else bsp._clip_simplex(v, si)
            for k, part in enumerate(parts):
                ref[2 * k] += part
                ref[2 * k + 1] += [polys.owner[i]] * len(part)
        for a, b in zip(got, ref, strict=True):
            assert np.array_equal(a, np.asarray(b).reshape(a.shape)), trial
