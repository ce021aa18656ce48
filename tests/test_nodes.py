"""Model-tree nodes: analytic values, and the inclusion property of every node type."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.model.expr import FormulaError, parse_formula
from pipeline.oracles import REGISTRY


def node(kind: str, **params):
    cls = REGISTRY[kind]
    return cls(cls.Params.model_validate(params))


SPHERE = dict(center=(0.1, -0.2, 0.3), radius=0.7)


def sph(**kw):
    return node("sphere", **{**SPHERE, **kw})


# --- analytic values ------------------------------------------------------------------------

def test_sphere_is_exact_distance():
    rng = np.random.default_rng(1)
    p = rng.uniform(-2, 2, (500, 3))
    d = np.linalg.norm(p - SPHERE["center"], axis=1)
    np.testing.assert_allclose(sph().evaluate(p), 0.7 - d, atol=1e-12)


def test_box_is_exact_distance():
    b = node("box", min=(-1, -0.5, -0.25), max=(1, 0.5, 0.25))
    pts = np.array([[0, 0, 0], [2, 0, 0], [2, 1.5, 0], [0.9, 0, 0], [1, 0.5, 0.25], [2, 1.5, 1.25]])
    want = [0.25, -1.0, -math.hypot(1, 1), 0.1, 0.0, -math.sqrt(3)]
    np.testing.assert_allclose(b.evaluate(pts), want, atol=1e-12)


def test_cylinder_infinite_and_capped():
    c = node("cylinder", center=(0, 0, 0), radius=0.5, axis="x")
    np.testing.assert_allclose(c.evaluate(np.array([[7, 0, 0], [0, 1, 0], [3, 0.3, 0.4]])), [0.5, -0.5, 0.0], atol=1e-12)
    cap = node("cylinder", center=(0, 0, 0), radius=0.5, axis="z", height=2)
    np.testing.assert_allclose(cap.evaluate(np.array([[0, 0, 0], [0, 0, 1.5], [0, 0.9, 1.3]])), [0.5, -0.5, -0.5], atol=1e-12)


def test_torus_cone_halfspace_ellipsoid():
    tor = node("torus", center=(0, 0, 0), major=1.0, minor=0.25, axis="y")
    np.testing.assert_allclose(tor.evaluate(np.array([[1, 0, 0], [0, 0, 1.25], [0, 0, 0]])), [0.25, 0.0, -0.75], atol=1e-12)
    cone = node("cone", center=(0, 0, 0), radius=1.0, height=1.0, axis="z")
    v = cone.evaluate(np.array([[0, 0, 0.5], [0.5, 0, 0.5], [0, 0, 2], [0, 0, 0.1]]))
    assert v[0] > 0 and abs(v[1]) < 1e-12 and v[2] < 0 and v[3] == pytest.approx(0.1)
    hs = node("halfspace", normal=(0, 0, 2), offset=1.0)
    np.testing.assert_allclose(hs.evaluate(np.array([[0, 0, 0], [5, 5, 1], [0, 0, 3]])), [1, 0, -2], atol=1e-12)
    el = node("ellipsoid", center=(0, 0, 0), radii=(2, 1, 0.5))
    np.testing.assert_allclose(el.evaluate(np.array([[2, 0, 0], [0, 1, 0], [0, 0, 0.5], [0, 0, 0]])), [0, 0, 0, 0.5], atol=1e-12)


def test_superellipsoid_zero_set_and_sign():
    se = node("superellipsoid", radii=(1, 2, 1), exponents=(1, 1))  # exponents 1: an ellipsoid
    np.testing.assert_allclose(se.evaluate(np.array([[1, 0, 0], [0, 2, 0], [0, 0, 1]])), 0, atol=1e-12)
    assert se.evaluate(np.array([[0, 0, 0]]))[0] == pytest.approx(1.0)
    boxy = node("superellipsoid", radii=(1, 1, 1), exponents=(0.3, 0.3))
    assert boxy.evaluate(np.array([[0.8, 0.8, 0.8]]))[0] > 0  # nearly a cube: corners are inside


def test_blobby_point_and_segment():
    b = node("blobby", threshold=0.5, blobs=[{"center": (0, 0, 0), "radius": 1.0, "strength": 1.0}])
    r = math.sqrt(math.log(2))  # exp(-r^2) = 0.5
    np.testing.assert_allclose(b.evaluate(np.array([[r, 0, 0], [0, 0, 0]])), [0, 0.5], atol=1e-12)
    s = node("blobby", threshold=0.5, blobs=[{"segment": ((0, 0, 0), (2, 0, 0)), "radius": 1.0}])
    np.testing.assert_allclose(s.evaluate(np.array([[1, r, 0], [2 + r, 0, 0]])), [0, 0], atol=1e-12)


def test_set_operations_signs():
    a = node("sphere", center=(-0.4, 0, 0), radius=0.6)
    b = node("sphere", center=(0.4, 0, 0), radius=0.6)
    pts = np.array([[0, 0, 0], [-0.8, 0, 0], [0.8, 0, 0], [2, 0, 0]])
    for fam in ("min_max", "r0", "sardf"):
        u = node("union", of=[a, b], rfunc=fam).evaluate(pts)
        i = node("intersection", of=[a, b], rfunc=fam).evaluate(pts)
        d = node("difference", of=[a, b], rfunc=fam).evaluate(pts)
        assert list(np.sign(u)) == [1, 1, 1, -1]
        assert list(np.sign(i)) == [1, -1, -1, -1]
        assert list(np.sign(d)) == [-1, 1, -1, -1]
    # min_max union of two distance fields far from the join is the exact distance
    np.testing.assert_allclose(node("union", of=[a, b], rfunc="min_max").evaluate(np.array([[2, 0, 0]])), [-1.0])


def test_sardf_equals_minmax_away_from_diagonal_and_is_smooth():
    from pipeline.field import rfunctions as rf

    f1 = np.array([1.0, -2.0, 0.3])
    f2 = np.array([-0.5, 3.0, -0.9])
    np.testing.assert_allclose(rf.r_and(f1, f2, "sardf"), np.minimum(f1, f2))
    # across the diagonal f1 = f2 the gradient is continuous (min/max jumps)
    e = 1e-6
    g_sardf = (rf.r_and(np.array([1 + e]), np.array([1.0]), "sardf") - rf.r_and(np.array([1 - e]), np.array([1.0]), "sardf")) / (2 * e)
    assert 0.3 < g_sardf[0] < 0.7


def test_transforms():
    s = sph(center=(0, 0, 0), radius=0.5)
    t = node("translate", by=(1, 2, 3), of=s)
    assert t.evaluate(np.array([[1, 2, 3]]))[0] == pytest.approx(0.5)
    box = node("box", min=(-1, -0.1, -0.1), max=(1, 0.1, 0.1))
    r = node("rotate", angle=90, axis="z", of=box)
    assert r.evaluate(np.array([[0, 0.95, 0]]))[0] > 0 and r.evaluate(np.array([[0.95, 0, 0]]))[0] < 0
    sc = node("scale", by=2.0, of=s)
    assert sc.evaluate(np.array([[1.0, 0, 0], [0, 0, 0]])) == pytest.approx([0.0, 1.0])
    bar = node("box", min=(-1, -0.1, -2), max=(1, 0.1, 2))
    tw = node("twist", rate=90, axis="z", of=bar)  # at z = 1 the bar is turned by 90 degrees
    assert tw.evaluate(np.array([[0, 0.9, 1.0]]))[0] > 0 and tw.evaluate(np.array([[0.9, 0, 1.0]]))[0] < 0
    tp = node("taper", axis="z", range=(0, 1), scale=(1, 0.5), of=node("cylinder", radius=1.0))
    assert tp.evaluate(np.array([[0.6, 0, 1.0]]))[0] < 0 < tp.evaluate(np.array([[0.6, 0, 0.0]]))[0]
    bend = node("bend", rate=0.5, plane="xy", of=box)
    assert bend.evaluate(np.array([[0, 0, 0]]))[0] == pytest.approx(0.1)


def test_offset_blend_morph_complement():
    s = sph(center=(0, 0, 0), radius=0.5)
    assert node("offset", distance=0.2, of=s).evaluate(np.array([[0.7, 0, 0]]))[0] == pytest.approx(0.0)
    assert node("complement", of=s).evaluate(np.array([[0, 0, 0]]))[0] == pytest.approx(-0.5)
    b = node("box", min=(-1, -1, -1), max=(1, 1, 1))
    m = node("morph", **{"from": s, "to": b, "t": 0.25})
    p = np.array([[0.3, 0.2, 0.1]])
    assert m.evaluate(p)[0] == pytest.approx(0.75 * s.evaluate(p)[0] + 0.25 * b.evaluate(p)[0])
    mt = node("morph", **{"from": s, "to": b})
    assert mt.evaluate(p, t=1.0)[0] == pytest.approx(b.evaluate(p)[0])
    a, c = node("sphere", center=(-0.5, 0, 0), radius=0.45), node("sphere", center=(0.5, 0, 0), radius=0.45)
    plain = node("union", of=[a, c]).evaluate(np.array([[0, 0, 0]]))[0]
    blended = node("blend", of=[a, c], op="union", a0=0.3, a1=0.2, a2=0.2).evaluate(np.array([[0, 0, 0]]))[0]
    assert plain < 0 < blended  # the blend adds material that bridges the gap


def test_expr_matches_sphere_and_parses_precedence():
    f = parse_formula("0.49 - x^2 - y^2 - z^2")
    p = np.array([[0.7, 0, 0], [0, 0, 0]])
    np.testing.assert_allclose(f.evaluate(p), [0, 0.49], atol=1e-12)
    assert parse_formula("-2^2").evaluate(p)[0] == -4  # ^ binds tighter than unary minus
    assert parse_formula("2^3^2").evaluate(p)[0] == 512  # right-associative
    assert parse_formula("min(x, 1, -3) + max(2, y)").evaluate(p)[0] == -1
    assert parse_formula("t * 2").evaluate(p, t=0.25)[0] == 0.5
    assert parse_formula("pow(2, 3) + abs(-1) + exp(0) + log(e) + cos(0) + sin(0) + sqrt(4)").evaluate(p)[0] == 14


@pytest.mark.parametrize("bad, col", [("1 +", 4), ("x * (y", 7), ("foo(x)", 1), ("1/0", 2), ("sqrt(x, y)", 1),
                                      ("x $ y", 3), ("", 1), ("log(0)", 1)])
def test_expr_errors_have_columns(bad, col):
    with pytest.raises(FormulaError) as e:
        parse_formula(bad)
    assert e.value.column == col


# --- inclusion property for every node type --------------------------------------------------

def random_node(kind: str, rng: np.random.Generator):
    """A node of ``kind`` with random valid parameters (children are random spheres/boxes)."""
    def v3(scale=1.0):
        return tuple(rng.uniform(-scale, scale, 3))

    def leaf():
        if rng.random() < 0.5:
            return node("sphere", center=v3(0.5), radius=rng.uniform(0.2, 1.0))
        lo = np.array(v3(0.8))
        return node("box", min=tuple(lo), max=tuple(lo + rng.uniform(0.1, 1.0, 3)))

    axis = str(rng.choice(["x", "y", "z"]))
    fam = str(rng.choice(["min_max", "r0", "sardf"]))
    radii = tuple(rng.uniform(0.3, 1.2, 3))
    lo3 = np.array(v3(0.8))
    params = {
        "sphere": dict(center=v3(0.5), radius=rng.uniform(0.1, 1.5)),
        "box": dict(min=tuple(lo3), max=tuple(lo3 + rng.uniform(0.1, 1.5, 3))),
        "cylinder": dict(center=v3(0.5), radius=rng.uniform(0.1, 1), axis=axis,
                         height=None if rng.random() < 0.5 else rng.uniform(0.2, 2)),
        "cone": dict(center=v3(0.5), radius=rng.uniform(0.1, 1), height=rng.uniform(0.2, 2), axis=axis),
        "torus": dict(center=v3(0.5), major=rng.uniform(0.4, 1), minor=rng.uniform(0.05, 0.35), axis=axis),
        "ellipsoid": dict(center=v3(0.5), radii=radii),
        "superellipsoid": dict(center=v3(0.3), radii=radii, exponents=tuple(rng.uniform(0.2, 2.5, 2))),
        "halfspace": dict(normal=v3(), offset=rng.uniform(-1, 1)),
        "blobby": dict(threshold=rng.uniform(0.2, 0.8), blobs=[
            {"center": v3(0.7), "radius": rng.uniform(0.2, 0.8), "strength": rng.uniform(0.5, 1.5)},
            {"segment": (v3(0.7), v3(0.7)), "radius": rng.uniform(0.1, 0.5)}]),
        "expr": dict(formula=str(rng.choice([
            "cos(3*x) + cos(3*y) + cos(3*z) - 0.3", "1 - x^2 - y^2*2 - z^4", "x*y*z - 0.1 + sin(x*y)",
            "min(1 - abs(x), 1 - abs(y)) / (1 + z^2)", "exp(-x^2 - y^2) - 0.5 + log(1 + z^2)",
            "sqrt(x^2 + y^2 + 0.01) - 0.5", "pow(abs(x), 2.5) + pow(abs(y), 2.5) - 0.3 + t"]))),
        "union": dict(of=[leaf(), leaf(), leaf()], rfunc=fam),
        "intersection": dict(of=[leaf(), leaf()], rfunc=fam),
        "difference": dict(of=[leaf(), leaf()], rfunc=fam),
        "complement": dict(of=leaf()),
        "blend": dict(of=[leaf(), leaf()], op=str(rng.choice(["union", "intersection", "difference"])),
                      a0=rng.uniform(-0.3, 0.5), a1=rng.uniform(0.05, 1), a2=rng.uniform(0.05, 1), rfunc=fam),
        "offset": dict(of=leaf(), distance=rng.uniform(-0.3, 0.3)),
        "morph": {"from": leaf(), "to": leaf(), "t": None if rng.random() < 0.5 else rng.uniform(0, 1)},
        "translate": dict(by=v3(), of=leaf()),
        "rotate": dict(angle=rng.uniform(-180, 180), axis=axis if rng.random() < 0.5 else v3(), of=leaf()),
        "scale": dict(by=rng.uniform(0.3, 2) if rng.random() < 0.5 else tuple(rng.uniform(0.3, 2, 3)), of=leaf()),
        "twist": dict(rate=rng.uniform(-120, 120), axis=axis, of=leaf()),
        "taper": dict(axis=axis, range=(-1.0, 1.0), scale=tuple(rng.uniform(0.3, 1.5, 2)), of=leaf()),
        "bend": dict(rate=rng.uniform(-1, 1), plane=str(rng.choice(["xy", "yz", "zx"])), of=leaf()),
        "shell": dict(of=leaf(), thickness=rng.uniform(0.05, 0.4), side=str(rng.choice(["inside", "outside", "both"]))),
        "tpms": dict(type=str(rng.choice(["gyroid", "schwarz_p", "diamond"])), cell=rng.uniform(0.3, 1.0),
                     thickness="0.05 + 0.1 * abs(d)", d_from=leaf()) if rng.random() < 0.5 else
                dict(type=str(rng.choice(["gyroid", "schwarz_p", "diamond"])), cell="0.5 + 0.2 * x",
                     thickness=rng.uniform(0.02, 0.2)),
        "lattice": dict(struts=[(v3(), v3()), (v3(), v3())], radius=rng.uniform(0.05, 0.3)) if rng.random() < 0.5
                   else dict(pattern=str(rng.choice(["cubic", "bcc", "octet"])), cell=rng.uniform(0.4, 1.0),
                             bounds=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), radius=rng.uniform(0.02, 0.2)),
    }
    return node(kind, **params[kind])


CORE_KINDS = sorted(k for k in REGISTRY if k not in ("mesh", "grid", "component", "hfrep"))


@pytest.mark.parametrize("kind", CORE_KINDS)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), corner=st.tuples(*[st.floats(-1.5, 1.0)] * 3),
       size=st.floats(0.005, 1.5), t=st.floats(0, 1))
def test_bound_encloses_samples(kind, seed, corner, size, t):
    rng = np.random.default_rng(seed)
    n = random_node(kind, rng)
    lo = np.array(corner)
    hi = lo + size * rng.uniform(0.3, 1.0, 3)
    pts = lo + rng.random((400, 3)) * (hi - lo)
    flo, fhi = n.bound(lo[None], hi[None], t)
    vals = n.evaluate(pts, t)
    vals = vals[np.isfinite(vals)]
    scale = 1 + np.abs(vals)
    assert np.all(vals >= flo[0] - 1e-12 * scale), f"{kind}: {vals.min()} < {flo[0]}"
    assert np.all(vals <= fhi[0] + 1e-12 * scale), f"{kind}: {vals.max()} > {fhi[0]}"


def test_every_registered_core_node_is_covered():
    """Adding a node type without an inclusion test fails here."""
    rng = np.random.default_rng(0)
    for kind in CORE_KINDS:
        assert random_node(kind, rng).kind == kind


def test_bound_tightens_as_boxes_shrink():
    """Affine bounds converge: the overestimate of a small box is second order in its size."""
    s = node("torus", center=(0, 0, 0), major=1.0, minor=0.3, axis="z")
    c = np.array([0.8, 0.5, 0.1])
    widths = []
    for h in (0.2, 0.1, 0.05):
        flo, fhi = s.bound((c - h)[None], (c + h)[None])
        widths.append(fhi[0] - flo[0])
    assert widths[1] < 0.6 * widths[0] and widths[2] < 0.6 * widths[1]
