"""Block FIM eikonal solver (pipeline.distance.eikonal) on analytic sphere, box and torus bands.

The frep input is built here as the voxeliser builds it: the field evaluated on every 8^3
leaf that touches the band, active where |f| < band * h.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.distance.eikonal import signed_distance_blocks, solve_distance, surface_blocks, surface_leaves
from pipeline.distance.hfrep import HFRepField, hfrep_blocks
from pipeline.distance.quality import central_gradient, extra_zero_crossings, gradient_stats
from pipeline.io.vdbgrids import level_set_grid, vdb
from pipeline.sparse.grid import LEAF, BlockGrid

C = np.array([0.013, -0.021, 0.007])  # off-grid centre: no voxel-aligned symmetry
HALF = np.array([0.5, 0.35, 0.45])


def sphere_of(radius: float):
    """FRep sphere (exact distance, positive inside) of ``radius`` centred at C."""
    def fn(p: np.ndarray) -> np.ndarray:
        return radius - np.linalg.norm(p - C, axis=-1)
    return fn


def box_of(half: np.ndarray):
    """FRep box (exact signed distance, positive inside) of half-extents ``half`` centred at C."""
    def fn(p: np.ndarray) -> np.ndarray:
        q = np.abs(p - C) - half
        return -(np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0))
    return fn


sphere = sphere_of(0.6)
box = box_of(HALF)


def torus(p: np.ndarray) -> np.ndarray:
    q = p - C
    return 0.22 - np.hypot(np.hypot(q[..., 0], q[..., 1]) - 0.55, q[..., 2])


def medial_distance(name: str, p: np.ndarray) -> np.ndarray:
    """Distance-like measure from the medial axis (interior and exterior) of each shape."""
    q = p - C
    if name == "sphere":
        return np.linalg.norm(q, axis=-1)
    if name == "torus":
        rho = np.hypot(q[..., 0], q[..., 1])
        return np.minimum(np.hypot(rho - 0.55, q[..., 2]), rho)
    gaps = np.sort(np.abs(np.abs(q) - HALF), axis=-1)  # box: two faces nearly equidistant
    return np.minimum(gaps[..., 1] - gaps[..., 0], np.linalg.norm(q, axis=-1))


SHAPES = {"sphere": sphere, "box": box, "torus": torus}


def band_grid(fn, n: int, band: float = 3.0) -> tuple[BlockGrid, tuple[np.ndarray, np.ndarray]]:
    """frep BlockGrid of ``fn`` on the domain [-1, 1]^3 with n voxels per side."""
    h = 2.0 / n
    lo = np.full(3, -(n // 2), dtype=np.int64)
    nb = -(-n // LEAF) + 1
    axes = [np.arange(nb)] * 3
    origins = (np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) + (lo >> 3)) << 3
    r = np.arange(LEAF)
    local = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1)
    ijk = origins[:, None, None, None, :] + local[None]
    f = fn(ijk * h)
    in_domain = np.all((ijk >= lo) & (ijk < lo + n), axis=-1)
    active = (np.abs(f) < band * h) & in_domain
    keep = active.reshape(len(origins), -1).any(axis=1)
    grid = BlockGrid(h, band * h, origins[keep], f[keep].astype(np.float32), active[keep])
    return grid, (lo, lo + n - 1)


def solved(fn, n: int, max_vox: float | None = 3.0, order: int = 2):
    frep, dom = band_grid(fn, n)
    h = 2.0 / n
    res = solve_distance(frep, None if max_vox is None else max_vox * h, dom, order=order)
    return frep, dom, res


def _errors(fn, n: int, order: int = 2) -> tuple[float, float]:
    _, _, res = solved(fn, n, order=order)
    ijk, v = signed_distance_blocks(res).active_voxels()
    err = np.abs(v + fn(ijk * (2.0 / n)))
    return float(err.max()), float(err.mean())


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_error_shrinks_with_voxel_size(name: str) -> None:
    fn = SHAPES[name]
    rows = [(n, *_errors(fn, n)) for n in (32, 64, 128)]
    print(f"\n{name}: n, max error, mean error (world units, domain [-1,1]^3)")
    for n, emax, emean in rows:
        print(f"  {n:4d}  {emax:.5f}  {emean:.6f}  max/h={emax * n / 2:.2f}")
    for (_, m0, a0), (_, m1, a1) in zip(rows[:-1], rows[1:], strict=True):
        # the max sits at the medial axis and at convex corners (point sources): first order;
        # the mean converges faster than first order
        assert math.log2(m0 / m1) >= 0.8, rows
        assert math.log2(a0 / a1) >= 1.2, rows
    assert rows[-1][1] < 1.0 * 2.0 / 128  # max error below one voxel at 128^3


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_second_order_beats_first_order(name: str) -> None:
    e1 = _errors(SHAPES[name], 96, order=1)
    e2 = _errors(SHAPES[name], 96, order=2)
    assert e2[1] < 0.5 * e1[1], (e1, e2)
    assert e2[0] < e1[0], (e1, e2)


def _vs_scikit_fmm(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(our error, scikit-fmm order-2 error, exact signed distance) on the dense 96^3 domain."""
    skfmm = pytest.importorskip("skfmm")
    n = 96
    h = 2.0 / n
    fn = SHAPES[name]
    frep, dom = band_grid(fn, n)
    axes = [np.arange(dom[0][a], dom[1][a] + 1) for a in range(3)]
    ijk = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    exact = -fn(ijk * h)
    theirs = np.abs(skfmm.distance(-fn(ijk * h), dx=h, order=2) - exact)
    sd = signed_distance_blocks(solve_distance(frep, None, dom))
    ours = np.abs(sd.sample_voxels(ijk.reshape(-1, 3)).reshape(exact.shape) - exact)
    for label, sel in (("<= 10 voxels", np.abs(exact) <= 10 * h), ("whole domain", np.ones_like(exact, bool))):
        print(f"\n{name} {label}: ours max {ours[sel].max() / h:.3f} mean {ours[sel].mean() / h:.4f} | "
              f"skfmm max {theirs[sel].max() / h:.3f} mean {theirs[sel].mean() / h:.4f} (voxels)")
    return ours, theirs, exact


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_no_less_accurate_than_scikit_fmm_order_2(name: str) -> None:
    """The issue's bar: no less accurate than dense fast marching (scikit-fmm, order 2), on the
    region the stage solves by default (10 voxels out) and the shell inside."""
    ours, theirs, exact = _vs_scikit_fmm(name)
    near = np.abs(exact) <= 10 * 2.0 / 96
    assert ours[near].mean() <= theirs[near].mean()
    # the box's convex corners included: the voxels diagonal to a corner are frozen next to
    # the kink (max 0.94 voxel before, in the corner fans; skfmm 0.73)
    assert ours[near].max() <= theirs[near].max()


def test_box_corner_fans_within_half_a_voxel() -> None:
    """Outside a box's convex corners the distance is a point-source fan; the voxels diagonal to
    the corner have no axis neighbour inside and were left to the FIM, 0.88 voxel too far in
    the first shell and 0.96 beyond (session 16). Frozen next to the kink, the whole region
    the stage solves (10 voxels out, the inside shell) stays within 0.45 voxel."""
    ours, _, exact = _vs_scikit_fmm("box")
    h = 2.0 / 96
    near = np.abs(exact) <= 10 * h
    assert ours[near].max() <= 0.45 * h
    first = (exact > 0) & (exact < h)  # outside, within a voxel of the surface (0.19 voxel; was 0.88)
    assert ours[first].max() <= 0.25 * h


def _grad_magnitudes(name: str, n: int = 128, order: int = 2) -> np.ndarray:
    _, _, res = solved(SHAPES[name], n, order=order)
    ijk, g = central_gradient(signed_distance_blocks(res))
    h = 2.0 / n
    far = medial_distance(name, ijk * h) > 8 * h
    return np.linalg.norm(g[far], axis=1)


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_gradient_norm_within_one_percent(name: str) -> None:
    """Issue bar: |grad| within 1% of 1 on at least 99% of the voxels away from the medial axis."""
    mag = _grad_magnitudes(name)
    assert len(mag) > 10000
    assert np.mean(np.abs(mag - 1) <= 0.01) >= 0.99
    assert np.all(mag > 0.5)


def test_first_order_scheme_stays_within_five_percent() -> None:
    mag = _grad_magnitudes("sphere", order=1)
    assert np.mean(np.abs(mag - 1) <= 0.05) >= 0.99
    assert np.mean(np.abs(mag - 1) <= 0.01) < 0.9  # what the second-order pass improves on


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_interior_fully_covered_and_outward_growth_stops(name: str) -> None:
    fn = SHAPES[name]
    n, max_vox = 64, 4.0
    h = 2.0 / n
    _, dom, res = solved(fn, n, max_vox)
    dist = res.distance
    r = np.arange(LEAF)
    ijk = (dist.origins[:, None, None, None, :] + np.stack(np.meshgrid(r, r, r, indexing="ij"), -1)[None])
    in_dom = np.all((ijk >= dom[0]) & (ijk <= dom[1]), axis=-1)
    f = fn(ijk * h)
    assert np.all(dist.active[(f > 0) & in_dom])  # every inside voxel that exists is solved
    assert np.array_equal(res.inside[in_dom & (np.abs(f) > h)], f[in_dom & (np.abs(f) > h)] > 0)
    # every inside voxel of the domain exists in the block set
    n_inside = int((fn(_domain_points(dom, h)) > 0).sum())
    assert int((dist.active & (f > 0) & in_dom).sum()) == n_inside
    out = dist.active & (f < 0)
    assert dist.values[out].max() <= max_vox * h + 1e-6
    assert np.all(dist.active[in_dom & (f < 0) & (-f < (max_vox - 1.5) * h)])
    assert not np.any(dist.active & in_dom & (-f > (max_vox + 1.5) * h))


def _domain_points(dom, h: float) -> np.ndarray:
    axes = [np.arange(dom[0][a], dom[1][a] + 1) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) * h


def test_sparse_block_set_grows_with_surface_not_volume() -> None:
    _, _, sparse = solved(sphere, 128, 3.0)
    _, _, dense = solved(sphere, 128, None)
    assert dense.distance.active.all()
    assert sparse.stats["blocks"] < 0.5 * dense.stats["blocks"]
    both = dense.distance.block_index(sparse.distance.origins)
    a = sparse.distance
    same = a.active
    diff = np.abs(a.values[same] - dense.distance.values[both][same]) / a.voxel_size
    inner = a.values[same] / a.voxel_size < 2.0  # more than a voxel inside the 3-voxel cut-off
    # within the last voxel before the cut-off, a tangential neighbour beyond it is missing in
    # the sparse run: the second-order update there may differ by a few thousandths of a voxel
    assert np.mean(diff[inner] <= 1e-4) >= 0.9999 and diff[inner].max() < 1e-3
    assert diff.max() < 1e-2


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_hfrep_has_the_sign_of_frep(name: str) -> None:
    fn = SHAPES[name]
    n = 64
    frep, _, res = solved(fn, n, 4.0)
    field = HFRepField.from_result(fn, res, step="sigmoid", slope=0.01)
    rng = np.random.default_rng(7)
    pts = rng.uniform(-0.95, 0.95, size=(200000, 3))
    ok = field.distance.supported(pts)
    v = field.evaluate(pts[ok])
    f = fn(pts[ok])
    assert ok.sum() > 20000
    assert np.array_equal(np.sign(v), np.sign(f))
    grid = hfrep_blocks(frep, res)
    assert extra_zero_crossings(grid, frep)["extra_zero_crossings"] == 0
    ijk, vals = grid.active_voxels()
    fv = fn(ijk * grid.voxel_size)
    assert np.all(np.sign(vals[np.abs(fv) > 1e-6]) == np.sign(fv[np.abs(fv) > 1e-6]))


def test_hollow_shell_cavity_is_outside_and_clipped_object_is_inside() -> None:
    def shell(p):
        r = np.linalg.norm(p - C, axis=-1)
        return np.minimum(0.8 - r, r - 0.4)

    n = 64
    h = 2.0 / n
    frep, dom, res = solved(shell, n, 3.0)
    ijk, v = signed_distance_blocks(res).active_voxels()
    f = shell(ijk * h)
    assert np.all(np.sign(-v[np.abs(f) > h]) == np.sign(f[np.abs(f) > h]))
    cavity_centre = np.array([0, 0, 0])
    assert res.distance.sample_voxels(cavity_centre[None])[0] == res.distance.background  # unsolved

    def big(p):  # sphere clipped by the domain: the interior touches the domain faces
        return 1.1 - np.linalg.norm(p, axis=-1)

    _, dom, res = solved(big, n, 3.0)
    corner_inside = np.array([[dom[0][0], 0, 0]])
    assert res.distance.sample_voxels(corner_inside)[0] > 0
    row = res.distance.block_index(corner_inside >> 3 << 3)[0]
    assert res.inside[row].any()


@settings(max_examples=8, deadline=None)
@given(
    cx=st.floats(-0.05, 0.05), cy=st.floats(-0.05, 0.05), cz=st.floats(-0.05, 0.05),
    radius=st.floats(0.3, 0.7), squared=st.booleans(),
)
def test_sphere_any_position_non_distance_frep(cx, cy, cz, radius, squared) -> None:
    c = np.array([cx, cy, cz])
    exact = lambda p: radius - np.linalg.norm(p - c, axis=-1)  # noqa: E731
    fn = (lambda p: radius**2 - np.sum((p - c) ** 2, axis=-1)) if squared else exact  # noqa: E731
    n = 48
    h = 2.0 / n
    frep, dom = band_grid(fn, n, band=3.0 if not squared else 6.0)
    res = solve_distance(frep, 3 * h, dom)
    ijk, v = signed_distance_blocks(res).active_voxels()
    err = np.abs(v + exact(ijk * h))
    assert err.max() < 1.2 * h
    near = np.abs(exact(ijk * h)) < 1.5 * h
    assert err[near].max() < 0.15 * h  # sub-voxel initialisation, not 0 / infinity


def test_surface_level_set_grid() -> None:
    n, band = 64, 3.0
    h = 2.0 / n
    fn = lambda p: 0.6 - np.linalg.norm(p, axis=-1)  # noqa: E731  (the contract check's sphere)
    frep, dom = band_grid(fn, n)
    res = solve_distance(frep, band * h, dom)
    blocks = surface_blocks(res, band, full=True)
    assert blocks.background == pytest.approx(band * h)
    assert np.all(np.abs(blocks.values[~blocks.active]) == pytest.approx(band * h))
    grid = level_set_grid(surface_leaves(res, band, full=True), "surface")  # the whole solved region; the default is a narrow band
    assert grid.gridClass == vdb.GridClass.LEVEL_SET
    assert grid.name == "surface"
    acc = grid.getConstAccessor()
    ijk = grid.transform.worldToIndexCellCentered((0.5, 0.0, 0.0))
    assert abs(acc.getValue(tuple(int(c) for c in ijk)) - (-0.1)) < 0.5 * h
    assert acc.getValue((0, 0, 0)) == pytest.approx(-0.6, abs=1.5 * h)  # interior solved
    assert acc.getValue((1000, 0, 0)) == pytest.approx(band * h)
    stats = gradient_stats(signed_distance_blocks(res), lambda p: np.linalg.norm(p, axis=1) > 8 * h)
    assert 0.97 < stats["mean"] < 1.03 and stats["share_below_0_5"] == 0.0


def test_second_order_fallback_path_gives_the_same_field(monkeypatch) -> None:
    """If the second-order pass from the initial layer does not converge within its bound, the
    free voxels are reset and first order then second order run: the same field."""
    import pipeline.distance.eikonal as eik

    frep, dom = band_grid(torus, 64)
    h = 2.0 / 64
    direct = solve_distance(frep, 3 * h, dom)
    assert direct.stats["scheme"] == "second order" and direct.stats["converged"]
    real = eik._flat_pass

    def flaky(*args):
        run = real(*args)
        calls = []

        def first_fails(seeds, order2, visits):
            calls.append(order2)
            out = run(seeds, order2, 0 if len(calls) == 1 else visits)  # a zero budget: abandoned at once
            return out
        return first_fails

    monkeypatch.setattr(eik, "_flat_pass", flaky)
    robust = solve_distance(frep, 3 * h, dom)
    assert robust.stats["scheme"].startswith("second order did not converge")
    assert not robust.stats["abandoned"]["converged"] and robust.stats["converged"]
    both = direct.distance.active & robust.distance.active
    assert np.abs(direct.distance.values - robust.distance.values)[both].max() < 1e-3 * h
    differ = direct.distance.active ^ robust.distance.active  # accepted or not at the cut-off
    at = np.where(direct.distance.active, direct.distance.values, robust.distance.values)[differ] / h
    print(f"\n{differ.sum()} voxels differ, at {at.min():.4f}..{at.max():.4f} voxels (cut-off 3)")
    assert differ.sum() <= 1e-3 * both.sum() and np.all(np.abs(at - 3.0) < 0.05)


def test_red_black_waves_give_the_same_field_on_any_thread_count(monkeypatch) -> None:
    """The FIM relaxes one colour of blocks at a time, in parallel: the serial kernel, the
    parallel one on 1 and on 2 threads give bit-identical distances."""
    import numba

    import pipeline.distance.fim as fim

    frep, dom = band_grid(torus, 96)
    h = 2.0 / 96
    fields = []
    monkeypatch.setattr(fim, "PARALLEL_BLOCKS", 1 << 62)  # serial kernel
    fields.append(solve_distance(frep, None, dom).distance.values)
    monkeypatch.setattr(fim, "PARALLEL_BLOCKS", 0)  # parallel kernel
    before = numba.get_num_threads()
    try:
        for threads in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)}):
            numba.set_num_threads(threads)
            fields.append(solve_distance(frep, None, dom).distance.values)
    finally:
        numba.set_num_threads(before)
    assert all(np.array_equal(fields[0], f) for f in fields[1:])
    assert np.isfinite(fields[0]).all() and fields[0].max() > 20 * h


@pytest.mark.parametrize(("name", "n", "gain"), [("sphere", 256, 0.7), ("torus", 128, None)])
def test_waves_in_distance_order_same_field_fewer_updates(monkeypatch, name: str, n: int, gain) -> None:
    """The FIM takes its list in order of distance (fim.WINDOW): against the plain FIM (every
    listed block in every wave) the same distances within the second-order scheme's settling
    (a hundredth of a voxel), as accurate against the exact distance, and on a deep interior
    far fewer voxel updates (the sphere at 256^3: 7.1 -> 4.4 per voxel; the torus's interior,
    14 voxels deep, gains nothing)."""
    from functools import partial

    import pipeline.distance.eikonal as eik
    import pipeline.distance.fim as fim

    fn = SHAPES[name]
    frep, dom = band_grid(fn, n)
    h = 2.0 / n
    ordered = solve_distance(frep, 3 * h, dom)
    monkeypatch.setattr(eik, "fim", partial(fim.fim, window=np.inf))
    plain = solve_distance(frep, 3 * h, dom)
    assert ordered.stats["converged"] and plain.stats["converged"]
    a, b = ordered.distance, plain.distance
    assert np.array_equal(a.origins, b.origins)
    both = a.active & b.active
    assert (a.active ^ b.active).sum() <= 1e-4 * both.sum()  # accepted or not at the cut-off
    assert np.abs(a.values - b.values)[both].max() < 0.01 * h
    errs = []
    for res in (ordered, plain):
        ijk, v = signed_distance_blocks(res).active_voxels()
        err = np.abs(v + fn(ijk * h)) / h
        errs.append((err.max(), err.mean()))
    assert errs[0][0] <= errs[1][0] + 0.01 and errs[0][1] <= errs[1][1] * 1.05
    per_voxel = [r.stats["voxel_updates"] / r.stats["solved_voxels"] for r in (ordered, plain)]
    print(f"\n{name}: updates per voxel {per_voxel[0]:.2f} ordered, {per_voxel[1]:.2f} plain; errors {errs}")
    if gain:
        assert per_voxel[0] < gain * per_voxel[1]
