"""Hierarchical FIM (pipeline.distance.hfim) on a small sphere and box in the domain [-1, 1]^3:
coarse nodes vs the analytic distance and vs the flat whole-domain solve, the written grid
(tiles for far space, read back from a .vdb file) and its storage growth with resolution."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.distance.eikonal import solve_distance
from pipeline.distance.hfim import hierarchical_distance, hierarchical_tiles
from pipeline.io.vdbgrids import fill_tiles, stored_values, tiled_grid, vdb
from pipeline.sparse.grid import LEAF
from tests.test_eikonal import band_grid, box_of, sphere_of

HALF = np.array([0.2, 0.15, 0.18])
sphere = sphere_of(0.25)
box = box_of(HALF)


SHAPES = {"sphere": sphere, "box": box}
_CACHE: dict = {}


def hfim(name: str, n: int, **kw):
    key = (name, n, tuple(sorted(kw.items())))
    if key not in _CACHE:
        frep, dom = band_grid(SHAPES[name], n)
        _CACHE[key] = (frep, dom, hierarchical_distance(frep, dom, **kw))
    return _CACHE[key]


def flat(name: str, n: int):
    key = ("flat", name, n)
    if key not in _CACHE:
        frep, dom = band_grid(SHAPES[name], n)
        _CACHE[key] = solve_distance(frep, None, dom)
    return _CACHE[key]


def coarse_errors(name: str, n: int, level: int = 0, **kw) -> tuple[float, float, int]:
    """(max, mean) error in world units of the nodes solved on the level (not frozen), count."""
    _, _, res = hfim(name, n, **kw)
    lv = res.levels[level]
    h = 2.0 / n
    m = lv.solved & ~lv.frozen
    err = np.abs(lv.values[m] * h + SHAPES[name](lv.node_index()[m] * h))
    return float(err.max()), float(err.mean()), int(m.sum())


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_coarse_nodes_match_the_analytic_distance(name: str) -> None:
    rows = [(n, *coarse_errors(name, n)) for n in (64, 128)]
    for n, emax, emean, count in rows:
        s = LEAF * 2.0 / n  # coarse spacing, world units
        assert count > 50
        assert emax <= 0.5 * s and emean <= 0.15 * s, (n, emax / s, emean / s)
    assert rows[1][1] < rows[0][1] and rows[1][2] < rows[0][2]  # finer voxels, finer coarse cells


def test_second_level_continues_the_first() -> None:
    """Level 2 (cells of 32 voxels here, to fit a small domain) is frozen from level 1 where
    level 1 reached and solves the rest; its error stays within one of its cells."""
    kw = {"levels": (8, 32), "coarse_distance_vox": 40.0}
    _, _, res = hfim("sphere", 128, **kw)
    l1, l2 = res.levels
    assert np.isfinite(l1.values).sum() < l1.values.size  # level 1 stopped at its reach
    assert l2.frozen.any() and (l2.solved & ~l2.frozen).any()
    assert l2.solved.all()
    emax, emean, _ = coarse_errors("sphere", 128, level=1, **kw)
    assert emax <= 32 * 2.0 / 128 and emean <= 0.3 * 32 * 2.0 / 128


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_coarse_field_agrees_with_the_flat_solve(name: str) -> None:
    n = 64
    h = 2.0 / n
    _, _, res = hfim(name, n)
    ref = flat(name, n).distance
    lv = res.levels[0]
    m = lv.solved & ~lv.frozen
    origins = (lv.lat_lo + np.argwhere(m)) * LEAF
    rows = ref.block_index(origins)
    assert (rows >= 0).all() and ref.active[rows].all()
    at_node = ref.values[rows][:, 3:5, 3:5, 3:5].reshape(len(rows), -1).mean(axis=1)  # trilinear at centre
    diff = np.abs(lv.values[m] * h - at_node)
    assert diff.max() <= LEAF * h and diff.mean() <= 0.3 * LEAF * h, (diff.max() / h, diff.mean() / h)


def test_written_grid_has_tiles_for_far_space(tmp_path) -> None:
    n = 128
    h = 2.0 / n
    _, dom, res = hfim("sphere", n)
    grid = tiled_grid(*hierarchical_tiles(res), "distance", level_set=True)
    path = tmp_path / "hfim.vdb"
    vdb.write(str(path), grids=[grid])
    back = vdb.read(str(path), "distance")
    leaves_flat = (n // LEAF) ** 3  # the flat whole-domain solve keeps every leaf of the domain
    assert back.leafCount() == res.stats["written"]["leaves"] < leaves_flat / 4
    domain_voxels = n**3
    assert back.activeVoxelCount() >= domain_voxels  # every voxel of the domain has a value
    assert back.activeVoxelCount() - back.activeLeafVoxelCount() > domain_voxels / 2  # mostly tiles
    # far points: the tile value (the distance at the cell centre) within a half cell diagonal
    # plus one coarse spacing of the analytic distance
    rng = np.random.default_rng(1)
    ijk = rng.integers(dom[0], dom[1] + 1, size=(4000, 3))
    exact = -sphere(ijk * h)
    far = ijk[exact > 24 * h][:300]
    acc = back.getConstAccessor()
    got = np.array([acc.getValue(tuple(int(x) for x in p)) for p in far])
    err = np.abs(got + sphere(far * h))
    s = LEAF * h
    assert len(far) == 300 and err.max() <= (np.sqrt(3) / 2 + 1) * s and err.mean() <= 0.5 * s
    # near and inside: the fine solve (signed, negative inside)
    near = ijk[np.abs(sphere(ijk * h)) < 10 * h][:100]
    got = np.array([acc.getValue(tuple(int(x) for x in p)) for p in near])
    assert np.abs(got + sphere(near * h)).max() < 0.1 * h * 10


def test_tiles_are_tiles_not_leaves() -> None:
    _, _, res = hfim("sphere", 64)
    grid = tiled_grid(*hierarchical_tiles(res), "distance", level_set=True)
    st = stored_values(grid, count_tiles=True)
    assert st["tiles_by_voxels"] == {LEAF**3: res.stats["written"]["leaf_tiles"]}
    assert st["stored_values"] == res.stats["written"]["stored_values"]
    kw = {"levels": (8, 32), "coarse_distance_vox": 40.0}
    _, _, res2 = hfim("sphere", 128, **kw)
    g2 = tiled_grid(*hierarchical_tiles(res2), "distance", level_set=True)
    assert res2.stats["written"]["big_tiles"] > 0
    # a 32^3 cell is 64 leaf-sized tiles: no leaf is made for it
    assert g2.leafCount() == res2.stats["written"]["leaves"]


def test_storage_grows_like_area() -> None:
    """Stored values (leaves * 512 + tiles) per resolution doubling: the flat whole-domain
    solve grows like the volume (x8), the hierarchical grid like the area (the fine leaves of
    the shell of constant width in voxels; the sphere's interior is small here)."""
    stored, flat_stored = [], []
    for n in (64, 128):
        _, _, res = hfim("sphere", n)
        hierarchical_tiles(res)
        stored.append(res.stats["written"]["stored_values"])
        flat_stored.append(len(flat("sphere", n).distance.origins) * LEAF**3)
    assert stored[1] / stored[0] < 5
    assert flat_stored[1] / flat_stored[0] > 7
    assert stored[1] < flat_stored[1] / 4


STAGE_CONFIG = """\
name: small
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 64}
model:
  sphere: {center: [0.013, -0.021, 0.007], radius: 0.25}
stages:
  - voxelise: {band: 3}
  - hfrep: {solver: hfim, quality: false, density: false}
  - export: {vdb: true}
"""


def test_hfrep_stage_with_hfim(tmp_path) -> None:
    """``solver: hfim``: the ``surface`` grid covers the domain box, far space as tiles."""
    from pipeline.cli import main

    cfg = tmp_path / "small.yaml"
    cfg.write_text(STAGE_CONFIG)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    grids, _ = vdb.readAll(str(tmp_path / "out" / "small" / "small.vdb"))
    surface = {g.name: g for g in grids}["surface"]
    h = 2.0 / 64
    assert surface.leafCount() < 0.8 * 9**3  # the domain [-32, 32]^3 voxels meets 9^3 leaves
    assert surface.activeVoxelCount() - surface.activeLeafVoxelCount() > 0  # far space as tiles
    assert surface.activeVoxelCount() >= 65**3
    acc = surface.getConstAccessor()
    for ijk in [(-30, -30, -30), (30, 28, -29), (0, 0, 0), (20, 0, 0)]:
        exact = -sphere(np.array(ijk) * h)
        assert abs(acc.getValue(ijk) - exact) <= (np.sqrt(3) / 2 + 1) * LEAF * h
    band = 3.0
    assert surface.background == pytest.approx(band * h)  # SPEC: surface background = band * voxel size
    assert surface.gridClass == vdb.GridClass.LEVEL_SET


def test_fine_solve_on_bricks_gives_the_same_levels() -> None:
    """With ``brick`` the fine FIM runs per brick (pipeline.distance.eikonal_bricks); the fine field and
    the coarse levels built on it match the unsplit run within the solver's tolerance."""
    frep, dom, whole = hfim("sphere", 64)
    split = hierarchical_distance(frep, dom, brick=16)
    assert split.fine.stats["bricks"] > 8 and split.fine.stats["rounds"] >= 2
    a, b = whole.fine.distance, split.fine.distance
    both = a.active & b.active
    h = a.voxel_size
    assert np.abs(a.values - b.values)[both].max() < 1e-3 * h
    for lw, ls in zip(whole.levels, split.levels, strict=True):
        assert np.array_equal(np.isfinite(lw.values), np.isfinite(ls.values))
        fin = np.isfinite(lw.values)
        assert np.abs(lw.values[fin] - ls.values[fin]).max() < 1e-2  # voxel units


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("holes", [False, True])
def test_lattice_fim_solves_what_node_fim_solves(seed: int, holes: bool) -> None:
    """The coarse interior's node FIM on blocks of nodes (both cores) against the node-by-node
    FIM, inside a sphere whose shell of nodes holds the exact distance, on a lattice of
    40 x 37 x 29 nodes (not whole blocks): the same nodes solved; first order to the solver
    tolerance (one fixed point), also with 3 % of the nodes excluded (holes, read as unknown;
    junk values in them must not leak); second order (from the same first-order start, no
    holes: around holes the non-monotone scheme's result depends on the visiting order, and
    both solvers overshoot there) to 1e-3 voxels, and closer to the exact distance than first
    order. Frozen and excluded nodes are never written. (The second-order case found that the
    block FIM dropped an axis whose second neighbour lay in an absent block, read as outside:
    21 voxels off at the lattice's edge; fixed in fim._axis_term.)"""
    from pipeline.distance.fim import EXCLUDED, FREE, FROZEN
    from pipeline.distance.hfim import lattice_fim, node_fim

    rng = np.random.default_rng(seed)
    state, r = _sphere_lattice()
    shape = state.shape
    if holes:
        state[rng.random(shape) < 0.03] = EXCLUDED
    exact = (16.0 + rng.random() - r) * 8.0  # voxel units: the distance inside a sphere, nodes 8 apart
    d = np.where(state == FROZEN, exact, np.inf)
    d[state == EXCLUDED] = rng.random(int((state == EXCLUDED).sum()))  # junk that must not leak
    inside = np.ones(shape, bool)
    a, b = d.copy(), d.copy()
    node_fim(a, state, inside, 8.0, np.inf, 8e-6, False, 1 << 62)
    lattice_fim(b, state, inside, 8.0, 8e-6, False, 1 << 40)
    free = state == FREE
    assert np.array_equal(np.isfinite(a[free]), np.isfinite(b[free])) and np.isfinite(a[free]).mean() > 0.9
    ok = np.isfinite(a) & free
    assert np.abs(a[ok] - b[ok]).max() < 1e-3
    assert np.array_equal(a[~free], d[~free]) and np.array_equal(b[~free], d[~free])
    if holes:
        return
    b2 = a.copy()
    node_fim(a, state, inside, 8.0, np.inf, 8e-6, True, 1 << 40)
    lattice_fim(b2, state, inside, 8.0, 8e-6, True, 50)
    assert np.abs(a[ok] - b2[ok]).max() < 1e-3 and np.array_equal(b2[~free], d[~free])
    assert np.abs(b2[ok] - exact[ok]).mean() < 0.5 * np.abs(b[ok] - exact[ok]).mean()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), size=st.integers(1, 2000), extent=st.integers(1, 12),
       merge=st.sampled_from([None, 1.0, 0.5]))
def test_fill_tiles_equals_one_fill_per_tile(seed, size, extent, merge) -> None:
    """Runs along z and merged boxes of ``merge_value`` write exactly the tiles given, values
    and active states, in any input order (read back voxel by voxel over the whole box)."""
    rng = np.random.default_rng(seed)
    lat = np.unique(rng.integers(0, extent, size=(size, 3)), axis=0)
    origins = lat * 8 - 40
    values = np.where(rng.random(len(lat)) < 0.6, 1.0, rng.integers(0, 3, len(lat)) * 0.5).astype(np.float32)
    ref, got = vdb.FloatGrid(-7.0), vdb.FloatGrid(-7.0)
    for a, x in zip(origins.tolist(), values.tolist(), strict=True):
        ref.fill(a, [c + 7 for c in a], x, True)
    perm = rng.permutation(len(lat))
    fill_tiles(got, origins[perm], values[perm], merge_value=merge)
    n = 8 * extent + 16
    a, b = np.zeros((n, n, n), np.float32), np.zeros((n, n, n), np.float32)
    ref.copyToArray(a, ijk=(-48, -48, -48))
    got.copyToArray(b, ijk=(-48, -48, -48))
    assert np.array_equal(a, b)
    assert got.activeVoxelCount() == ref.activeVoxelCount() == 512 * len(lat)


def _sphere_lattice(shape=(40, 37, 29)):
    """(state, r) of a lattice of nodes inside a sphere: free nodes (r < 14 nodes from the
    centre), a frozen shell (14 <= r < 15.5), the rest excluded."""
    from pipeline.distance.fim import EXCLUDED, FREE, FROZEN

    g = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    r = np.linalg.norm(g - np.array(shape) / 2, axis=-1)
    state = np.full(shape, EXCLUDED, np.int8)
    state[r < 14] = FREE
    state[(r >= 14) & (r < 15.5)] = FROZEN
    return state, r


def test_interior_solve_second_order_straight_from_the_frozen_nodes() -> None:
    """The coarse interior's node FIM runs the second-order scheme straight from the frozen
    nodes (hfim._interior_solve), as the fine solve does: the same nodes solved as first order
    then second order, within 2e-3 voxels of it, with fewer updates, frozen nodes untouched.
    When the second-order pass stops at its visit bound, the free nodes are reset and the
    robust path runs: exactly what first order, then second order give from the start."""
    from pipeline.distance import eikonal, hfim
    from pipeline.distance.fim import FREE, FROZEN

    state, r = _sphere_lattice()
    d = np.where(state == FROZEN, (16.0 - r) * 8.0, np.inf)  # the exact distance, voxel units
    inside = np.ones(state.shape, bool)
    ref = d.copy()
    up_ref = hfim.lattice_fim(ref, state, inside, 8.0, 8e-6, False, 1 << 40)[0]
    up_ref += hfim.lattice_fim(ref, state, inside, 8.0, 8e-6, True, eikonal.SECOND_ORDER_VISITS)[0]
    got = d.copy()
    up = hfim._interior_solve(got, state, inside, 8.0, 8e-6, 2)
    free = state == FREE
    assert np.array_equal(np.isfinite(got), np.isfinite(ref)) and np.isfinite(got[free]).all()
    assert np.abs(got[free] - ref[free]).max() < 2e-3 and up < up_ref
    assert np.array_equal(got[~free], d[~free])

    bound = 1  # one visit per block: the straight pass cannot converge
    saved = eikonal.SECOND_ORDER_VISITS  # the bound of eikonal.run_passes, which chooses the passes
    eikonal.SECOND_ORDER_VISITS = bound
    try:
        fallback = d.copy()
        hfim._interior_solve(fallback, state, inside, 8.0, 8e-6, 2)
    finally:
        eikonal.SECOND_ORDER_VISITS = saved
    robust = d.copy()
    hfim.lattice_fim(robust, state, inside, 8.0, 8e-6, False, 1 << 40)
    assert not hfim.lattice_fim(robust, state, inside, 8.0, 8e-6, True, bound)[2]
    assert np.array_equal(fallback, robust)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.booleans())
def test_leaf_nodes_are_numpys_mean_of_the_centre_voxels(seed: int, centre: bool) -> None:
    """hfim._fine_nodes (one compiled pass) against its NumPy formulation, bit for bit: node =
    float32 mean of a leaf's 8 centre voxels / h, frozen where the leaf (``centre``: its 8
    centre voxels) is solved, inside where more than half of those 8 are; leaves off the
    lattice are skipped."""
    from types import SimpleNamespace

    from pipeline.distance.hfim import _fine_nodes
    from pipeline.sparse.grid import BlockGrid, pack_keys

    rng = np.random.default_rng(seed)
    shape = (5, 4, 6)
    lat_lo = np.array([-2, 1, -3])
    cells = rng.permutation(np.argwhere(np.ones((7, 6, 8), bool)))[:60] + lat_lo - 1  # some off the lattice
    origins = cells[np.argsort(pack_keys(cells))] * LEAF  # in BlockGrid's order: inside is aligned with it
    values = (rng.random((60, LEAF, LEAF, LEAF)) * 40).astype(np.float32)
    active = rng.random(values.shape) < 0.995
    active[rng.random(60) < 0.5] = True
    inside = rng.random(values.shape) < 0.5
    h = 0.0123
    fine = SimpleNamespace(distance=BlockGrid(h, 1.0, origins, values, active), inside=inside)
    assert np.array_equal(fine.distance.origins, origins)
    vals, frozen, ins = _fine_nodes(fine, lat_lo, shape, centre)

    want_v, want_f, want_i = np.full(shape, np.inf), np.zeros(shape, bool), np.zeros(shape, bool)
    p = (origins >> 3) - lat_lo
    ok = np.all((p >= 0) & (p < np.array(shape)), axis=1)
    solved = active[:, 3:5, 3:5, 3:5] if centre else active
    full = solved.reshape(60, -1).all(axis=1) & ok
    mean = values[:, 3:5, 3:5, 3:5].reshape(60, -1).mean(axis=1) / h
    want_v[tuple(p[full].T)] = mean[full]
    want_f[tuple(p[full].T)] = True
    want_i[tuple(p[ok].T)] = inside[:, 3:5, 3:5, 3:5][ok].reshape(int(ok.sum()), -1).mean(axis=1) > 0.5
    assert full.any() and (~ok).any()
    assert np.array_equal(vals, want_v) and np.array_equal(frozen, want_f) and np.array_equal(ins, want_i)


def _blocks_by_numpy(res, signed: bool):
    """hierarchical_blocks as NumPy array expressions (its definition before it was compiled)."""
    from pipeline.distance.hfim import sample_distance

    dist = res.fine.distance
    h = res.voxel_size
    values = dist.values.astype(np.float64) / h
    todo = ~dist.active
    if todo.any():
        b, i, j, k = np.nonzero(todo)
        values[b, i, j, k] = sample_distance(res, dist.origins[b] + np.stack([i, j, k], 1))
    lo, hi = res.domain
    ijk = dist.origins[:, :, None] + np.arange(LEAF)[None, None, :]
    inb = (ijk >= lo[None, :, None]) & (ijk <= hi[None, :, None])
    active = inb[:, 0, :, None, None] & inb[:, 1, None, :, None] & inb[:, 2, None, None, :] & np.isfinite(values)
    values = values * h
    if signed:
        values = np.where(res.fine.inside, -values, values)
    bg = float(np.nanmax(np.where(active, np.abs(values), 0.0), initial=0.0))
    return np.where(active, values, bg).astype(np.float32), active, bg


@pytest.mark.parametrize(("name", "n", "kw"), [("sphere", 48, {}), ("box", 64, {"fine_distance_vox": 4.0}),
                                               ("sphere", 40, {"fine_distance_vox": 2.0})])
@pytest.mark.parametrize("signed", [True, False])
def test_hierarchical_blocks_compiled_is_the_numpy_definition(name: str, n: int, kw: dict, signed: bool) -> None:
    """The written fine leaves (one compiled pass) are the NumPy expressions' to the bit: values,
    active voxels (in the domain box, finite), background; with voxels left to the coarse levels."""
    from pipeline.distance.hfim import hierarchical_blocks

    _, _, res = hfim(name, n, **kw)
    assert (~res.fine.distance.active).any()  # some voxels take the coarse levels' samples
    got = hierarchical_blocks(res, signed)
    values, active, bg = _blocks_by_numpy(res, signed)
    assert got.background == bg and np.array_equal(got.active, active)
    assert np.array_equal(got.values.view(np.uint32), values.view(np.uint32))
