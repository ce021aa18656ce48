"""BSP-fields (pipeline.mesh.bsp) and approximate distance fields (pipeline.mesh.adf) on small shapes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.path import Path as MplPath

from pipeline.field import rfunctions as rf
from pipeline.field import rkernels as rk
from pipeline.mesh.adf import ADFField
from pipeline.mesh.bsp import FAMILY_CODE, SPECIAL_B, SPECIAL_C, BSPField, merge_coplanar

FAMILIES = ("min_max", "r0", "sardf")


# --------------------------------------------------------------------------- shapes


def voxel_solid(cells: list[tuple[int, int, int]]) -> trimesh.Trimesh:
    """Closed mesh of a union of unit cubes (faces shared by two cubes removed)."""
    boxes = [trimesh.creation.box((1, 1, 1)).apply_translation(np.add(c, 0.5)) for c in cells]
    mesh = trimesh.util.concatenate(boxes)
    tri = mesh.triangles
    edges = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], axis=1)
    j = np.argmax(np.linalg.norm(edges, axis=2), axis=1)  # the diagonal of the unit square
    mid = 0.5 * (tri[np.arange(len(tri)), j] + tri[np.arange(len(tri)), (j + 1) % 3])
    key = np.round(mid * 4).astype(np.int64)  # both triangles of a square share it
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    keep = cnt[inv.ravel()] == 2  # a square of one cube only; shared squares count 4
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=True)
    assert out.is_watertight and out.volume > 0
    return out


L_SHAPE = [(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 0), (0, 2, 0)]
U_SHAPE = [(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 0), (0, 2, 0), (2, 1, 0), (2, 2, 0)]
RING = [(x, y, 0) for x in range(3) for y in range(3) if (x, y) != (1, 1)]
STEPS = [(x, y, z) for x in range(3) for y in range(3) for z in range(3) if x + y + z <= 2]
SHAPES = {"L": L_SHAPE, "U": U_SHAPE, "ring": RING, "steps": STEPS}

NOTCH = np.array([[0, 0], [4, 0], [4, 3], [3, 3], [2, 1], [1, 3], [0, 3]], float)
SQUARE_HOLE = [np.array([[0, 0], [4, 0], [4, 4], [0, 4]], float),
               np.array([[1, 1], [1, 3], [3, 3], [3, 1]], float)]  # hole: clockwise


def _random_points(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    lo, hi = mesh.bounds
    ext = hi - lo
    return np.random.default_rng(seed).uniform(lo - 0.2 * ext, hi + 0.2 * ext, (n, 3))


def _far_from_surface(mesh: trimesh.Trimesh, p: np.ndarray, dist: float) -> np.ndarray:
    _, d, _ = trimesh.proximity.closest_point(mesh, p)
    return d > dist


def _inside_2d(loops: list[np.ndarray], p: np.ndarray) -> np.ndarray:
    count = np.zeros(len(p), dtype=int)
    for loop in loops:
        count += MplPath(loop).contains_points(p)
    return count % 2 == 1


def _dist_to_segments_2d(loops: list[np.ndarray], p: np.ndarray) -> np.ndarray:
    best = np.full(len(p), np.inf)
    for loop in loops:
        for a, b in zip(loop, np.roll(loop, -1, axis=0), strict=True):
            t = np.clip(((p - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
            best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1))
    return best


# --------------------------------------------------------------------------- R-functions


finite = st.floats(-1e3, 1e3, allow_nan=False)


def _reference_and(f1: float, f2: float, family: str, scale: float) -> float:
    """The conjunctions as the papers write them (bsp-fields eq. 1 and 2; the SARDF window of
    pipeline.field.rfunctions), in plain Python, then the magnitude control."""
    if family == "min_max":
        return min(f1, f2)
    rho = math.hypot(f1, f2)
    if family == "r0":
        r = f1 + f2 - rho
    else:
        w = rf.SARDF_K * rho
        u = f1 - f2
        r = min(f1, f2) if abs(u) >= w else 0.5 * (f1 + f2 - (u * u + w * w) / (2 * w))
    if abs(r) <= scale:
        return r
    return math.copysign(scale * (1 + math.log(abs(r) / scale)), r)


@settings(max_examples=300, deadline=None)
@given(finite, finite, st.sampled_from(FAMILIES), st.sampled_from([np.inf, 1.0, 50.0]))
def test_rfunctions_match_the_papers_formulas(f1: float, f2: float, family: str, scale: float) -> None:
    """The compiled scalars (rkernels, which the tape and the BSP-field inline) and the array
    functions that run them in compiled loops (rfunctions) equal the formulas as written (r0
    computed naively here: its cancellation costs up to (|f1| + |f2|) float64 units)."""
    code = FAMILY_CODE[family]
    tol = 1e-12 * (abs(f1) + abs(f2)) + 1e-300
    want_and = _reference_and(f1, f2, family, scale)
    want_or = -_reference_and(-f1, -f2, family, scale)
    assert rk.r_and(f1, f2, code, rf.SARDF_K, scale) == pytest.approx(want_and, abs=tol, rel=1e-12)
    assert rk.r_or(f1, f2, code, rf.SARDF_K, scale) == pytest.approx(want_or, abs=tol, rel=1e-12)
    assert float(rf.r_and(np.array(f1), np.array(f2), family, scale=scale)) == rk.r_and(f1, f2, code, rf.SARDF_K, scale)
    assert float(rf.r_or(np.array(f1), np.array(f2), family, scale=scale)) == rk.r_or(f1, f2, code, rf.SARDF_K, scale)


magnitude = st.one_of(finite, st.sampled_from([0.0, -0.0, 1e-160, -1e-160, 3e-300, 1e200, -1e200, 1e300]))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(magnitude, magnitude), min_size=1, max_size=300), st.sampled_from(FAMILIES),
       st.sampled_from([np.inf, 1.0, 50.0]), st.sampled_from([1.0, -1.0]), st.sampled_from([1.0, -1.0]),
       st.sampled_from([1.0, -1.0]))
def test_and_rows_is_r_and_on_every_lane(pairs, family: str, scale: float, sa: float, sb: float,
                                         so: float) -> None:
    """The vectorised row form (sqrt instead of hypot, the magnitude control in a second pass)
    equals the scalar r_and on every lane, with its sign, for magnitudes whose squares
    overflow or underflow too (they go through the scalar pass)."""
    a = np.array([p[0] for p in pairs])
    b = np.array([p[1] for p in pairs])
    out = np.full(len(a) + 3, np.nan)
    rk.and_rows(a, sa, b, sb, so, out, len(a), FAMILY_CODE[family], rf.SARDF_K, scale)
    want = np.array([so * rk.r_and(sa * x, sb * y, FAMILY_CODE[family], rf.SARDF_K, scale) for x, y in pairs])
    np.testing.assert_allclose(out[:len(a)], want, rtol=4e-16, atol=0)
    assert np.array_equal(np.sign(out[:len(a)]), np.sign(want))
    assert np.isnan(out[len(a):]).all()  # nothing written past n


@pytest.mark.parametrize("family", FAMILIES)
def test_rfunctions_are_nondecreasing(family: str) -> None:
    """Dense check that every family is monotone in each argument (basis of bound())."""
    g = np.linspace(-3, 3, 1201)
    f1, f2 = np.meshgrid(g, g, indexing="ij")
    for op in (rf.r_and, rf.r_or):
        v = op(f1, f2, family)
        assert np.all(np.diff(v, axis=0) >= -1e-12)
        assert np.all(np.diff(v, axis=1) >= -1e-12)


def test_sardf_partial_derivative_bounded_by_one() -> None:
    """d/df1 of the SARDF window term is at most 1 (so AND is nondecreasing), on the unit circle."""
    th = np.linspace(0, 2 * np.pi, 200001)
    f1, f2, h = np.cos(th), np.sin(th), 1e-7
    d = (rf.r_and(f1 + h, f2, "sardf") - rf.r_and(f1 - h, f2, "sardf")) / (2 * h)
    assert d.min() >= -1e-6 and d.max() <= 1 + 1e-6


# --------------------------------------------------------------------------- merge and tree stats


def test_box_has_six_planes_and_no_splits() -> None:
    field = BSPField.from_mesh(trimesh.creation.box((2, 3, 4)), planes="naive", seed=3)
    s = field.stats
    assert (s["faces"], s["planes"], s["polygons"], s["splits"]) == (12, 6, 6, 0)
    assert s["nodes"] == 6 and s["set_operations"] == 5


def test_merge_counts_on_voxel_shapes() -> None:
    ring = voxel_solid(RING)
    polys = merge_coplanar(ring.vertices, ring.faces)
    # outer 4 sides, inner 4 sides, top and bottom (each an annulus made of many triangles)
    assert polys.count == 10 and len(np.unique(polys.plane_id)) == 10
    steps = voxel_solid(STEPS)
    n_planes = len(np.unique(merge_coplanar(steps.vertices, steps.faces).plane_id))
    assert n_planes == 3 + 3 * 3  # three outer faces at 0 plus three step levels per axis


def test_icosphere_polygons_are_triangles() -> None:
    sphere = trimesh.creation.icosphere(2)
    assert BSPField.from_mesh(sphere).stats["planes"] == len(sphere.faces)


@pytest.mark.parametrize("name", ["L", "U", "ring", "steps"])
def test_optimised_splits_no_more_than_naive(name: str) -> None:
    mesh = voxel_solid(SHAPES[name])
    opt = BSPField.from_mesh(mesh, planes="optimised").stats["splits"]
    naive = [BSPField.from_mesh(mesh, planes="naive", seed=s).stats["splits"] for s in range(5)]
    assert opt <= min(naive)
    assert opt == 0


# --------------------------------------------------------------------------- 3D fields


def _reference_eval(field: BSPField, p: np.ndarray) -> np.ndarray:
    """Section 3.3.2 formula evaluated recursively with pipeline.field.rfunctions (NumPy)."""
    t, fam = field.tree, field.rfunc

    def node(j: int) -> np.ndarray:
        fa = p @ t.normals[j] + t.offsets[j]
        fb = node(t.pos[j]) if t.pos[j] >= 0 else None
        fc = node(t.neg[j]) if t.neg[j] >= 0 else None
        c = field.magnitude_scale
        a, o = (lambda x, y: rf.r_and(x, y, fam, scale=c)), (lambda x, y: rf.r_or(x, y, fam, scale=c))
        if fb is None and fc is None:
            return fa
        if fc is None:
            return a(fa, fb)
        if fb is None:
            return o(fa, fc)
        if t.mode[j] == SPECIAL_B:
            return a(o(fa, fc), fb)
        if t.mode[j] == SPECIAL_C:
            return a(o(-fa, fb), fc)
        return o(a(o(fa, fc), fb), a(-fa, fc))

    return node(len(t.mode) - 1)


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("planes", ["naive", "optimised"])
def test_compiled_matches_reference_formula(family: str, planes: str) -> None:
    mesh = voxel_solid(STEPS)
    field = BSPField.from_mesh(mesh, rfunc=family, planes=planes, seed=1)
    p = _random_points(mesh, 2000, 0)
    np.testing.assert_allclose(field.evaluate(p), _reference_eval(field, p), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("family", ["r0", "sardf"])
def test_block_kernel_matches_reference_on_a_deep_tree(family: str) -> None:
    """A bumpy icosphere's tree (about 2,000 nodes, values beyond the magnitude control far out):
    the block kernel (256 points per block, one register row per live node) equals the recursive
    formula at a point count that is not a multiple of the block, near the surface and far out,
    and its bounds hold the values."""
    sphere = trimesh.creation.icosphere(3)
    rng = np.random.default_rng(7)
    sphere.vertices *= 1 + 0.15 * rng.random((len(sphere.vertices), 1))
    field = BSPField.from_mesh(sphere, rfunc=family)
    assert field.stats["nodes"] > 1000 and field.stats["depth"] > 10, field.stats
    p = np.concatenate([rng.uniform(-1.3, 1.3, (700, 3)), rng.uniform(-20, 20, (301, 3))])
    v = field.evaluate(p)
    ref = _reference_eval(field, p)
    assert np.abs(ref).max() > field.magnitude_scale  # the second (compress) pass ran
    np.testing.assert_allclose(v, ref, rtol=1e-12, atol=1e-12)
    assert np.array_equal(np.sign(v), np.sign(ref))
    lo = p - rng.uniform(0, 0.05, p.shape)
    hi = p + rng.uniform(0, 0.05, p.shape)
    flo, fhi = field.bound(lo, hi)
    assert np.all(flo <= v) and np.all(v <= fhi)


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("planes", ["naive", "optimised"])
@pytest.mark.parametrize("name", ["L", "U", "ring", "steps"])
def test_sign_equals_containment(name: str, planes: str, family: str) -> None:
    mesh = voxel_solid(SHAPES[name])
    field = BSPField.from_mesh(mesh, rfunc=family, planes=planes, seed=7)
    p = _random_points(mesh, 3000, 1)
    p = p[_far_from_surface(mesh, p, 1e-6)]
    v = field.evaluate(p)
    assert np.all((v > 0) == mesh.contains(p))
    assert np.all(v != 0)


@pytest.mark.parametrize("family", FAMILIES)
def test_sign_on_icosphere_and_torus(family: str) -> None:
    for mesh in (trimesh.creation.icosphere(2), trimesh.creation.torus(1.0, 0.4, 24, 12)):
        field = BSPField.from_mesh(mesh, rfunc=family)
        p = _random_points(mesh, 3000, 2)
        p = p[_far_from_surface(mesh, p, 1e-6)]
        assert np.all((field.evaluate(p) > 0) == mesh.contains(p))


@pytest.mark.parametrize("family", FAMILIES)
def test_zero_on_faces(family: str) -> None:
    for mesh in (voxel_solid(RING), trimesh.creation.torus(1.0, 0.4, 24, 12)):
        for planes in ("naive", "optimised"):
            field = BSPField.from_mesh(mesh, rfunc=family, planes=planes)
            s, _ = trimesh.sample.sample_surface(mesh, 2000, seed=3)
            assert np.abs(field.evaluate(s)).max() < 1e-12 * mesh.scale


def test_special_cases_keep_the_set() -> None:
    mesh = voxel_solid(STEPS)
    a = BSPField.from_mesh(mesh, planes="naive", seed=2, special_cases=True)
    b = BSPField.from_mesh(mesh, planes="naive", seed=2, special_cases=False)
    assert a.stats["special_cases"] > 0 and b.stats["special_cases"] == 0
    assert a.stats["set_operations"] < b.stats["set_operations"]
    p = _random_points(mesh, 5000, 4)
    assert np.array_equal(a.evaluate(p) > 0, b.evaluate(p) > 0)


def test_inverted_mesh_is_flipped() -> None:
    box = trimesh.creation.box((1, 1, 1))
    inv = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    assert BSPField.from_mesh(inv).evaluate(np.zeros((1, 3)))[0] > 0


# --------------------------------------------------------------------------- bounds


_U_FIELDS = {fam: BSPField.from_mesh(voxel_solid(U_SHAPE), rfunc=fam, planes="naive", seed=5)
             for fam in FAMILIES}
coord = st.floats(-1.0, 4.0, allow_nan=False)
size = st.floats(0.0, 2.0, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(st.tuples(coord, coord, coord), st.tuples(size, size, size), st.sampled_from(FAMILIES),
       st.integers(0, 2**31))
def test_bound_contains_samples_3d(lo, ext, family, seed) -> None:
    field = _U_FIELDS[family]
    lo = np.array(lo)
    hi = lo + np.array(ext)
    flo, fhi = field.bound(lo[None], hi[None])
    rng = np.random.default_rng(seed)
    corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    p = np.concatenate([lo + rng.random((300, 3)) * (hi - lo), lo + corners * (hi - lo)])
    v = field.evaluate(p)
    assert flo[0] <= v.min() and v.max() <= fhi[0]


def test_bound_is_tight_for_points_and_vectorised() -> None:
    field = _U_FIELDS["r0"]
    p = _random_points(voxel_solid(U_SHAPE), 500, 5)
    flo, fhi = field.bound(p, p)
    v = field.evaluate(p)
    assert np.all(flo <= v) and np.all(v <= fhi)
    assert np.abs(fhi - flo).max() < 1e-9


# --------------------------------------------------------------------------- 2D


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("planes", ["naive", "optimised"])
def test_2d_sign_and_zero_set(family: str, planes: str) -> None:
    for loops in ([NOTCH], SQUARE_HOLE):
        field = BSPField.from_polygon2d(loops, rfunc=family, planes=planes, seed=4)
        assert field.dim == 2
        p = np.random.default_rng(6).uniform(-1, 5, (5000, 2))
        p = p[_dist_to_segments_2d(loops, p) > 1e-6]
        assert np.all((field.evaluate(p) > 0) == _inside_2d(loops, p))
        t = np.random.default_rng(7).random(200)[:, None]
        on = np.concatenate([a + t * (b - a) for lp in loops for a, b in zip(lp, np.roll(lp, -1, 0), strict=True)])
        assert np.abs(field.evaluate(on)).max() < 1e-12


def test_2d_tree_counts_and_bound() -> None:
    hole = BSPField.from_polygon2d(SQUARE_HOLE, planes="optimised", rfunc="sardf")
    assert hole.stats["planes"] == 8 and hole.stats["splits"] == 0
    # collinear consecutive edges merge into one polygon
    merged = BSPField.from_polygon2d([np.array([[0, 0], [1, 0], [2, 0], [2, 2], [0, 2]], float)])
    assert merged.stats["faces"] == 5 and merged.stats["planes"] == 4
    rng = np.random.default_rng(8)
    lo = rng.uniform(-1, 5, (300, 2))
    hi = lo + rng.uniform(0, 1.5, (300, 2))
    assert_bound_encloses(hole, lo, hi, rng, 60)


# --------------------------------------------------------------------------- C1 continuity


def _max_gradient_jump(field: BSPField, a: np.ndarray, b: np.ndarray, n: int) -> float:
    """Largest change of the central-difference gradient between neighbouring samples on a segment."""
    t = np.linspace(0, 1, n)[:, None]
    p = a + t * (b - a)
    h = 1e-6
    grads = np.stack([(field.evaluate(p + h * e) - field.evaluate(p - h * e)) / (2 * h)
                      for e in np.eye(3)], axis=1)
    return float(np.linalg.norm(np.diff(grads, axis=0), axis=1).max())


@pytest.mark.parametrize("name", ["cube", "L"])
def test_c1_away_from_surface(name: str) -> None:
    """r0 and sardf have continuous gradients off the surface; min/max jumps on f1 = f2."""
    mesh = trimesh.creation.box((2, 2, 2)) if name == "cube" else voxel_solid(L_SHAPE)
    seg = {"cube": ([-0.6, -0.2, 0.1], [0.6, 0.35, -0.2]), "L": ([0.3, 0.2, 0.5], [0.7, 2.6, 0.45])}
    a, b = (np.array(v, float) for v in seg[name])
    assert _far_from_surface(mesh, a + np.linspace(0, 1, 50)[:, None] * (b - a), 0.05).all()
    for family in FAMILIES:
        field = BSPField.from_mesh(mesh, rfunc=family)
        coarse = _max_gradient_jump(field, a, b, 400)
        fine = _max_gradient_jump(field, a, b, 800)
        if family == "min_max":
            assert coarse > 0.5 and fine > 0.5  # a jump that does not shrink with the step
        else:
            assert coarse < 0.05 and fine < 0.6 * coarse  # shrinks with the step: continuous


# --------------------------------------------------------------------------- ADF


@pytest.mark.parametrize("join", ["requiv", "rconj"])
def test_adf_sign_zero_and_bounds(join: str) -> None:
    mesh = voxel_solid(L_SHAPE)
    field = ADFField.from_mesh(mesh, join=join, p=2)
    p = _random_points(mesh, 1500, 9)
    p = p[_far_from_surface(mesh, p, 1e-6)]
    v = field.evaluate(p)
    assert np.all((v > 0) == mesh.contains(p))
    s, _ = trimesh.sample.sample_surface(mesh, 300, seed=10)
    assert np.abs(field.evaluate(s)).max() < 1e-12 * mesh.scale
    rng = np.random.default_rng(11)
    lo = rng.uniform(-0.5, 3.0, (80, 3))
    hi = lo + rng.uniform(0, 1.0, (80, 3))
    assert_bound_encloses(field, lo, hi, rng, 40)


def test_adf_requiv_is_normalised_near_a_face() -> None:
    """Eq. 6 keeps first-order normalisation: |F| ~ distance close to a face centre."""
    mesh = voxel_solid(L_SHAPE)
    field = ADFField.from_mesh(mesh, join="requiv", p=2)
    bottom = np.nonzero(mesh.face_normals[:, 2] < -0.99)[0][0]
    centre = mesh.triangles_center[bottom]  # away from the triangle's edges, where joins act
    d = np.array([1e-4, 1e-3])
    p = centre - d[:, None] * np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(-field.evaluate(p), d, rtol=1e-3)



def test_adf_rejects_bad_parameters() -> None:
    mesh = trimesh.creation.box((1, 1, 1))
    with pytest.raises(ValueError, match="join"):
        ADFField.from_mesh(mesh, join="union")
    with pytest.raises(ValueError, match="p must"):
        ADFField.from_mesh(mesh, p=0.5)


def assert_bound_encloses(field, lo, hi, rng, samples: int) -> None:
    """Values at random points of every box lie inside the field's bound of that box."""
    flo, fhi = field.bound(lo, hi)
    for i in range(len(lo)):
        v = field.evaluate(lo[i] + rng.random((samples, lo.shape[1])) * (hi[i] - lo[i]))
        assert flo[i] <= v.min() and v.max() <= fhi[i]


def _highs_margin(a: np.ndarray, b: np.ndarray) -> float:
    """max t s.t. a x + t <= b (rows), t <= 1, x free: the margin by scipy's HiGHS."""
    from scipy.optimize import linprog

    d = a.shape[1]
    r = linprog(np.r_[np.zeros(d), -1.0], A_ub=np.c_[a, np.ones(len(a))], b_ub=b,
                bounds=[(None, None)] * d + [(None, 1.0)], method="highs")
    assert r.status == 0
    return -r.fun


def _margin_cases(rng) -> list:
    """Halfspace sets a x <= b of the interior LPs: random ones, unit boxes with a halfspace
    touching or cutting a face (margin 0 or not), repeated planes (degenerate), axis normals
    (sparse rows)."""
    cases = []
    for _ in range(300):
        m = int(rng.integers(4, 41))
        n = rng.normal(size=(m, 3))
        n /= np.linalg.norm(n, axis=1)[:, None]
        cases.append((n, rng.uniform(-0.5, 1.0, m)))  # a x <= b with a = n: often bounded, sometimes empty
    box = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    for _ in range(50):  # a unit box and a halfspace touching one of its faces or cutting it
        k = int(rng.integers(6))
        cut = rng.choice([0.0, 0.3, -0.2])
        cases.append((np.r_[box, -box[k:k + 1]], np.r_[np.full(6, 0.5), [-0.5 + cut]]))
        cases.append((np.r_[box, box, box[k:k + 1]], np.r_[np.full(12, 0.5), [0.5]]))  # repeated planes
    return cases


def test_direct_highs_is_linprogs() -> None:
    """pipeline.mesh.bsp._highs_margin (the special cases' near-threshold LPs through scipy's HiGHS
    module directly, without linprog's ~1 ms of Python a call) returns linprog's optimum to the
    bit, so the special-case decisions, hence the trees and their values, are unchanged."""
    from pipeline.mesh.bsp import _highs_margin as direct

    for a, b in _margin_cases(np.random.default_rng(11)):
        a1 = np.ascontiguousarray(np.c_[a, np.ones(len(a))])
        assert direct(a1, b.copy()) == _highs_margin(a, b)


def test_compiled_margin_agrees_with_highs() -> None:
    """pipeline.field.small_lp.max_margin (the special cases' interior LPs, section 3.2): the optimum
    equals HiGHS's to 1e-7 on random halfspace sets of 4-40 planes, on boxes touching a
    halfspace (margin 0) and on repeated planes (degenerate); so its decision (margin > tol) is
    HiGHS's wherever the margin is not within HiGHS's own tolerance of the threshold."""
    from pipeline.field.small_lp import max_margin

    for a, b in _margin_cases(np.random.default_rng(7)):
        t = max_margin(np.ascontiguousarray(a), np.ascontiguousarray(b))
        assert np.isfinite(t)
        assert abs(t - _highs_margin(a, b)) < 1e-7, (t, _highs_margin(a, b))
