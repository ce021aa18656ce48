"""Attribute formulas of the hfrep stage (hfrep seed, section 5.2 and 7) on the compiled evaluator:
a formula in x y z t d lowers to a tape of three inputs (d takes an input the formula leaves
free) and gives, rounded to float32, what the node-by-node NumPy evaluation gives, on every
active voxel; a formula that reads all four variables keeps the NumPy path; the first voxel
where a formula is not finite is reported the same way on both."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from pipeline.distance import attributes as attr


def voxels(seed: int, n: int = 300) -> attr.AttributeVoxels:
    """Random blocks with a random active mask and float32 distances (0 where not active)."""
    rng = np.random.default_rng(seed)
    origins = np.unique(rng.integers(-40, 40, (n, 3)) * 8, axis=0)
    active = rng.random((len(origins), 8, 8, 8)) < 0.6
    d = np.where(active, rng.uniform(0, 0.3, active.shape), 0).astype(np.float32)
    return attr.AttributeVoxels(origins, active, d, 1.0 / 128)


def numpy_values(formulas: list[str], vox: attr.AttributeVoxels, t: float, monkeypatch) -> np.ndarray:
    with monkeypatch.context() as m:
        m.setattr(attr.AttributeFormula, "lowered", lambda self, t=0.0: None)
        return attr.evaluate_attribute([attr.AttributeFormula(f) for f in formulas], vox, t)


@pytest.mark.parametrize("src, inputs", [
    ("d / 0.1", ("d", None, None)),
    ("0.5 + 0.5*cos(2*pi*(d/0.1 - 1/3))", ("d", None, None)),
    ("max(min(1, max(0, 50*(0.06 - d))), min(1, max(0, 20*max(sin(20*x + pi/2) - 0.5, sin(20*z + pi/2) - 0.5))))",
     ("x", "d", "z")),
    ("y * exp(-d) + z^2 + t", ("d", "y", "z")),
    ("x + y - z", ("x", "y", "z")),
    ("3.5", (None, None, None)),
])
def test_lowered_formulas_read_their_variables_from_the_right_inputs(src, inputs, monkeypatch):
    f = attr.AttributeFormula(src)
    tape, where = f.lowered(0.25)
    assert tuple(attr.SLOT_SOURCES[s] if s >= 0 else None for s in where) == inputs
    vox = voxels(1)
    got = attr.evaluate_attribute([f], vox, 0.25)
    want = numpy_values([src], vox, 0.25, monkeypatch)
    assert got.dtype == np.float32 and np.array_equal(got, want)
    assert not got[~vox.active].any()
    assert got[vox.active].std() > 0 or src == "3.5"


def test_a_formula_of_x_y_z_and_d_keeps_the_numpy_path(monkeypatch):
    f = attr.AttributeFormula("x*y*z + d")
    assert f.lowered() is None
    vox = voxels(2)
    got = attr.evaluate_attribute([f], vox)
    b, i, j, k = np.nonzero(vox.active)
    p = (vox.origins[b] + np.stack([i, j, k], 1)) * vox.voxel_size
    want = (p[:, 0] * p[:, 1] * p[:, 2] + vox.d[b, i, j, k].astype(np.float64)).astype(np.float32)
    assert np.array_equal(got[b, i, j, k], want)


NAMES = st.sampled_from(["x", "y", "z", "d", "t", "pi", "0.5", "2", "1e-3"])


@st.composite
def formulas(draw, depth: int = 3) -> str:
    if depth == 0 or draw(st.booleans()):
        return draw(NAMES)
    kind = draw(st.sampled_from(["bin", "fn", "minmax", "pow"]))
    a = draw(formulas(depth - 1))
    if kind == "fn":
        return f"{draw(st.sampled_from(['sin', 'cos', 'abs', 'exp']))}({a})"
    b = draw(formulas(depth - 1))
    if kind == "minmax":
        return f"{draw(st.sampled_from(['min', 'max']))}({a}, {b})"
    if kind == "pow":
        return f"({a})^{draw(st.sampled_from(['2', '3']))}"
    return f"({a}) {draw(st.sampled_from(['+', '-', '*']))} ({b})"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rgb=st.lists(formulas(), min_size=1, max_size=3).filter(lambda v: len(v) != 2), t=st.floats(-2, 2))
def test_compiled_attributes_equal_the_numpy_evaluation(rgb, t, monkeypatch):
    """Random formulas (one, or three for RGB): the compiled values are the NumPy ones rounded to
    float32 (one float32 unit where a libm function rounds differently)."""
    vox = voxels(3, 60)
    try:  # a constant part that overflows (exp(exp(pi^2))) is a config error, not a formula to run
        [attr.AttributeFormula(f) for f in rgb]
    except attr.FormulaError:
        assume(False)
    try:
        want = numpy_values(rgb, vox, t, monkeypatch)
    except attr.NonFiniteAttribute as e:  # exp(exp(exp(2))): both report the same voxel
        with pytest.raises(attr.NonFiniteAttribute) as got_err:
            attr.evaluate_attribute([attr.AttributeFormula(f) for f in rgb], vox, t)
        assert str(got_err.value) == str(e)
        return
    got = attr.evaluate_attribute([attr.AttributeFormula(f) for f in rgb], vox, t)
    assert got.shape == want.shape
    assert np.allclose(got, want, rtol=2.0**-22, atol=0.0)


@pytest.mark.parametrize("src", ["sqrt(0.15 - d)", "log(x)", "exp(d) * log(d - 0.1)"])
def test_the_first_voxel_not_finite_is_reported_as_by_numpy(src, monkeypatch):
    vox = voxels(4)
    with pytest.raises(attr.NonFiniteAttribute) as got:
        attr.evaluate_attribute([attr.AttributeFormula("d"), attr.AttributeFormula(src)], vox)
    with pytest.raises(attr.NonFiniteAttribute) as want:
        numpy_values(["d", src], vox, 0.0, monkeypatch)
    assert got.value.component == want.value.component == 1
    assert str(got.value) == str(want.value)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 6), st.booleans(), st.floats(0.0, 1.0), st.floats(1e-3, 1e6), st.integers(0, 2**31))
def test_attribute_grid_sentinel_exceeds_every_active_value(blocks, vector, share, scale, seed) -> None:
    """attribute_grid writes under a sentinel background that no active value takes: the
    compiled max over the active voxels gives the definition's even integer above them all
    (scalar and Vec3S blocks, any share of active voxels, none at all)."""
    import math

    from pipeline.io.vdbgrids import _sentinel

    rng = np.random.default_rng(seed)
    shape = (blocks, 8, 8, 8, 3) if vector else (blocks, 8, 8, 8)
    values = (rng.standard_normal(shape) * scale).astype(np.float32)
    active = rng.random(shape[:4]) < share
    flags = active[..., None] if vector else active
    want = float(np.float32(2.0 * math.floor(np.abs(values[np.broadcast_to(flags, shape)]).max(initial=0.0)) + 2.0))
    got = _sentinel(values, active)
    assert got == want
    assert not np.any(np.where(np.broadcast_to(flags, shape), values, 0.0) == got)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 5), st.sampled_from(["inactive", "surface"]), st.floats(0.5, 4.0), st.integers(0, 2**31))
def test_attribute_voxels_are_the_definitions(blocks, outside, band, seed) -> None:
    """The compiled pass of attribute_voxels covers the solved inside voxels, and with
    ``outside: surface`` the solved outside ones within the band that hfrep keeps; d is the
    distance inside and 0 elsewhere (the NumPy masks it replaces)."""
    from types import SimpleNamespace

    from pipeline.sparse.grid import BlockGrid

    rng = np.random.default_rng(seed)
    h = 0.01
    shape = (blocks, 8, 8, 8)
    origins = rng.integers(-4, 4, (blocks, 3)) * 8
    dist = BlockGrid(h, 3 * h, origins, (rng.random(shape) * 8 * h).astype(np.float32), rng.random(shape) < 0.8)
    hf = BlockGrid(h, 3 * h, origins, np.zeros(shape, np.float32), rng.random(shape) < 0.7)
    result = SimpleNamespace(distance=dist, inside=rng.random(shape) < 0.5)
    vox = attr.attribute_voxels(result, hf, outside, band)
    inside = result.inside & dist.active
    want = inside.copy()
    if outside == "surface":
        want |= (~result.inside) & dist.active & (dist.values <= band * h) & hf.active
    assert np.array_equal(vox.active, want)
    assert vox.d.dtype == np.float32 and np.array_equal(vox.d, np.where(inside, dist.values, np.float32(0)))
    assert vox.origins is dist.origins and vox.voxel_size == h
