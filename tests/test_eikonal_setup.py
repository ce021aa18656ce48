"""The eikonal solve's set-up. The ``signed_values`` shortcut (the hfrep stage's default
after voxelise): the sign of every voxel of voxelise's leaves read from its value gives the
same distances, sides and statistics as the flood fill of the band's signs it replaces, for
models inside, crossing and filling the domain, hollow ones, and domains whose bounds cut the
leaves. The merge of sorted origin lists equals a stable sort of their concatenation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.distance.eikonal import solve_distance
from pipeline.job.config import _Ctx, build_node
from pipeline.sparse.grid import merge_sorted, pack_keys
from pipeline.voxel.voxelise import voxelise


def node(raw: dict):
    return build_node(raw, ("model",), _Ctx("test", raw, Path(".")))


def sphere(c, r) -> dict:
    return {"sphere": {"center": list(c), "radius": r}}


def _same(model: dict, lo: np.ndarray, hi: np.ndarray, n: int, limit: float | None, inside: float | None) -> None:
    h = 2.0 / n
    vox = voxelise(node(model), lo, hi, h, 3.0)
    runs = [solve_distance(vox.blocks, None if limit is None else limit * h, (lo, hi), vox.inside_boxes,
                           inside_distance=None if inside is None else inside * h, signed_values=s)
            for s in (False, True)]
    a, b = runs
    assert np.array_equal(a.distance.origins, b.distance.origins)
    assert np.array_equal(a.distance.active, b.distance.active)
    assert np.array_equal(a.distance.values, b.distance.values)  # bit for bit
    assert np.array_equal(a.inside, b.inside)
    assert {k: v for k, v in a.stats.items() if "seconds" not in k} == \
        {k: v for k, v in b.stats.items() if "seconds" not in k}
    assert a.distance.active.sum() > 1000  # a solve that did something


MODELS = {
    "union": {"union": [sphere((-0.3, 0, 0), 0.4), sphere((0.35, 0.1, 0), 0.3)]},
    "hollow": {"difference": [sphere((0, 0, 0), 0.8), sphere((0.05, 0, 0), 0.45)]},
    "crossing": sphere((0.6, 0, 0), 0.7),  # cut by the domain: inside voxels outside the bounds
    "demo": {"difference": [{"superellipsoid": {"radii": [1, 1, 1], "exponents": [0.3, 0.3]}},
                            {"box": {"min": [-1.3, -0.02, -1.3], "max": [1.3, 0.02, 1.3]}}]},
}


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from(sorted(MODELS)), n=st.sampled_from([40, 64]),
       shift=st.tuples(*[st.integers(-5, 5)] * 3), cut=st.integers(0, 7),
       limit=st.sampled_from([None, 4.0]), inside=st.sampled_from([None, 5.0]))
def test_signs_from_values_equal_the_flood_fill(name, n, shift, cut, limit, inside) -> None:
    # a domain box shifted off the leaf lattice and cut short on its upper faces
    lo = np.array([-n // 2] * 3) + np.array(shift)
    hi = np.array([n // 2] * 3) + np.array(shift) - cut
    _same(MODELS[name], lo, hi, n, limit, inside)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), na=st.integers(0, 300), nb=st.integers(0, 300), span=st.integers(1, 6))
def test_merge_sorted_equals_a_stable_sort(seed, na, nb, span) -> None:
    rng = np.random.default_rng(seed)

    def sorted_origins(n):
        o = (rng.integers(-span, span, size=(n, 3)) * 8).astype(np.int64)
        return o[np.argsort(pack_keys(o), kind="stable")]

    a, b = sorted_origins(na), sorted_origins(nb)
    both = np.concatenate([a, b])
    order = np.argsort(pack_keys(both), kind="stable")
    merged, pos = merge_sorted(a, b)
    assert np.array_equal(merged, both[order])
    tag = np.zeros(len(both), int)  # b's rows land where the stable sort puts them
    tag[pos] = np.arange(1, nb + 1)
    assert np.array_equal(tag, np.where(order >= na, order - na + 1, 0))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 300), st.sampled_from(["C", "F", "strided", "int32"]))
def test_pack_keys_is_the_key_layout_on_any_integer_rows(seed: int, n: int, layout: str) -> None:
    """grid.pack_keys (a compiled pass) gives grid.key_of of the offset coordinates, the one
    definition of the layout, for any (N,3) integer rows in [-2^20, 2^20): C or Fortran order,
    a strided view, int32; and its order sorts by x, then y, then z."""
    from pipeline.sparse.grid import KEY_OFFSET, key_of

    rng = np.random.default_rng(seed)
    a = rng.integers(-(2**20), 2**20, size=(2 * n, 3))
    a[: n // 2] = a[n // 2: 2 * (n // 2)]  # some equal rows
    want = key_of(*(a + KEY_OFFSET).T)
    if layout == "F":
        a = np.asfortranarray(a)
    elif layout == "strided":
        a, want = a[::2], want[::2]
    elif layout == "int32":
        a = a.astype(np.int32)
    got = pack_keys(a)
    assert got.dtype == np.int64 and np.array_equal(got, want)
    order = np.argsort(got, kind="stable")
    assert np.array_equal(order, np.lexsort((a[:, 2], a[:, 1], a[:, 0])))
