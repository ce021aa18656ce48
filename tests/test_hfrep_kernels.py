"""hfrep_blocks (one compiled pass) and field_report (the signed distance read from the unsigned
one, not copied) against the NumPy expressions they replaced, on a small sphere: equal bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.distance.eikonal import signed_distance_blocks
from pipeline.distance.hfrep import hfrep_blocks, step_function
from pipeline.distance.quality import deviation_on_blocks, extra_zero_crossings, field_report, gradient_stats
from tests.test_eikonal import band_grid, solved, sphere


@pytest.fixture(scope="module")
def sph():
    frep, _, res = solved(sphere, 32, max_vox=3.0)
    return frep, res


@pytest.mark.parametrize("step", ["sigmoid", "tanh", "rational"])
def test_hfrep_blocks_equal_the_numpy_expression(sph, step: str) -> None:
    frep, res = sph
    dist = res.distance
    values = np.where(res.inside, np.float32(1.0), np.float32(-1.0))
    rows = frep.block_index(dist.origins)
    hb = np.flatnonzero(rows >= 0)
    sub, fa = values[hb], frep.active[rows[hb]]
    sub[fa] = step_function(frep.values[rows[hb]][fa], step, 0.05)
    values[hb] = sub
    values *= dist.values
    values[~dist.active] = -dist.background
    got = hfrep_blocks(frep, res, step, 0.05)
    assert np.array_equal(got.values, values) and np.array_equal(got.active, dist.active)
    assert np.abs(sub[fa]).min() < 0.5  # the step matters: voxels next to the surface are far from +-1


def test_field_report_equals_the_report_of_the_signed_copy(sph) -> None:
    frep, res = sph
    hf = hfrep_blocks(frep, res)
    sd = signed_distance_blocks(res)
    band = 3 * frep.voxel_size
    want = {"frep": {"gradient": gradient_stats(frep), "deviation": deviation_on_blocks(frep, sd, band, -1.0)},
            "surface": {"gradient": gradient_stats(sd)},
            "hfrep": {"gradient": gradient_stats(hf),
                      "deviation": deviation_on_blocks(hf, sd, band, -1.0, near=frep.origins),
                      **extra_zero_crossings(hf, frep)}}
    assert field_report(frep, res, hf) == want
    assert want["surface"]["gradient"]["voxels"] > 5000 and want["frep"]["deviation"]["voxels"] > 1000


def test_fim_dirty_faces_give_the_full_sweeps_result() -> None:
    """A revisited block starts its sweeps from the voxels next to the faces whose ghost layers
    changed (fim.relax_block's ``dirty``): the same distances, bit for bit, as starting every
    visit from every voxel (the serial waves driven here with dirty = all faces)."""
    from pipeline.distance import eikonal as ek
    from pipeline.distance import fim as fm

    frep, dom = band_grid(sphere, 48)
    saved = {}
    real = ek._flat_pass

    def spy(d, state, inside, nbr27, colour, limit, tol, max_sweeps, limit_in=np.inf):
        saved.update(d=d.copy(), state=state.copy(), inside=inside, nbr27=nbr27, colour=colour, limit=limit)
        return real(d, state, inside, nbr27, colour, limit, tol, max_sweeps, limit_in)

    ek._flat_pass = spy
    try:
        res = ek.solve_distance(frep, 12 * frep.voxel_size, dom, order=2)
    finally:
        ek._flat_pass = real
    got = saved["d"].copy()
    seeds = np.nonzero((saved["state"] == fm.FROZEN).reshape(len(got), -1).any(axis=1))[0]
    ref = saved["d"].copy()
    lists, counts, on_list, dirty, key = fm._seed_lists(saved["colour"], seeds, len(ref))
    buf, sbuf, mask = np.empty((12, 12, 12)), np.zeros((12, 12, 12), bool), np.empty((12, 12), np.int64)
    c = 0 if counts[0] >= counts[1] else 1
    visits = 0
    while counts[0] + counts[1] > 0:
        work = fm._take_wave(lists, counts, on_list, c, key, fm._window_end(lists, counts, key, fm.WINDOW))
        if len(work):
            out = np.zeros((len(work), 3), np.int64)
            for t, b in enumerate(work):
                out[t] = fm.relax_block(ref, saved["state"], saved["inside"], saved["nbr27"], b, saved["limit"], 1e-6,
                                       64, True, buf, sbuf, mask, np.inf, 63)
            bmin = np.array([ref[b].min() for b in work])
            fm._finish_wave(work, out, saved["nbr27"], saved["colour"], lists, counts, on_list, dirty, key, bmin)
            visits += len(work)
        c = 1 - c
    fm._fim_serial(got, saved["state"], saved["inside"], saved["nbr27"], saved["colour"], seeds, saved["limit"], 1e-6,
                  64, True, 1 << 40, np.inf, fm.WINDOW)
    assert visits > 1.5 * len(ref)  # blocks are revisited
    assert np.array_equal(got, ref) and res.stats["converged"]


def test_batched_writer_builds_the_same_grid() -> None:
    """vdbgrids.write_leaves, in one batch and in batches of 37 (runs packed by a compiled pass, split where
    a batch ends) give the grid of a plain reference, one copyFromArray per block of
    where(active, -value, background): same values, active voxels and leaves."""
    from pipeline.io.vdbgrids import vdb, write_leaves

    frep, (lo, hi) = band_grid(sphere, 48)
    shape = tuple(int(x) for x in hi - lo + 9)
    bg = np.float32(frep.background)

    def reference(g):
        for o, v, m in zip(frep.origins, frep.values, frep.active, strict=True):
            g.copyFromArray(np.where(m, -v, bg).astype(np.float32), tuple(int(x) for x in o))

    grids = []
    for write in (reference, lambda g: write_leaves(g, frep, -1.0), lambda g: write_leaves(g, frep, -1.0, batch=37)):
        g = vdb.FloatGrid(float(frep.background))
        g.name = "g"
        write(g)
        a = np.zeros(shape, np.float32)
        g.copyToArray(a, tuple(int(x) for x in lo - 8))
        vdb.ax("@g = 12345.0;", g)
        m = np.zeros(shape, np.float32)
        g.copyToArray(m, tuple(int(x) for x in lo - 8))
        grids.append((a, m == 12345.0, g.leafCount(), g.activeVoxelCount()))
    (a0, m0, n0, v0) = grids[0]
    assert (n0, v0) == (len(frep.origins), frep.active_count) and m0.sum() == v0 and (a0[m0] != 0).any()
    for a1, m1, n1, v1 in grids[1:]:
        assert np.array_equal(a0, a1) and np.array_equal(m0, m1) and (n0, v0) == (n1, v1)


def test_release_rows_frees_whole_pages_of_the_given_rows_only() -> None:
    from pipeline.sparse.blockwrite import mapped_empty, release_rows

    a = mapped_empty((100, 8, 8, 8), np.float32)  # 2 KiB rows: two to a 4 KiB page
    a[:] = 1.0
    release_rows(a, 50, 3)  # rows 3..49: the page holding rows 2-3 stays
    assert (a[4:50] == 0).all() and (a[:4] == 1).all() and (a[50:] == 1).all()
    b = np.ones((10, 8, 8, 8), np.float32)
    release_rows(b, 10)  # not a mapping: left alone
    assert (b == 1).all()


def test_surface_grid_consuming_the_solve_writes_the_same_grid(sph, monkeypatch) -> None:
    from pipeline.distance.eikonal import EikonalResult, surface_leaves
    from pipeline.io import vdbgrids
    from pipeline.io.vdbgrids import level_set_grid
    from pipeline.sparse.blockwrite import mapped_empty
    from pipeline.sparse.grid import BlockGrid

    _, res = sph
    monkeypatch.setattr(vdbgrids, "BATCH", 7)  # many batches, each releasing the blocks before the next
    grids = []
    for consume in (False, True):
        d = res.distance
        copy = [mapped_empty(x.shape, x.dtype) for x in (d.values, d.active, res.inside)]
        for c, x in zip(copy, (d.values, d.active, res.inside), strict=True):
            c[:] = x
        r = EikonalResult(BlockGrid(d.voxel_size, d.background, d.origins, copy[0], copy[1]), copy[2], res.max_distance)
        g = level_set_grid(surface_leaves(r, 3.0, consume=consume), "surface")
        grids.append((g.activeVoxelCount(), g.leafCount(), g.evalMinMax(), copy))
    assert grids[0][:3] == grids[1][:3] and grids[0][0] > 5000
    assert (grids[0][3][0] == res.distance.values).all() and not (grids[1][3][0] == res.distance.values).all()


@pytest.mark.parametrize("keep, far", [(1.0, 0), (0.3, 0), (0.3, 100_000)])
def test_neighbour_tables_equal_the_searches(keep: float, far: int) -> None:
    """sparse.access.block_neighbours / block_neighbours27 (a dense lattice of rows where it is
    small, binary searches where it is not) against grid.block_index at every offset; also from
    bare origins in any order (rows then index that order)."""
    from pipeline.sparse.access import FACE_DIRS, OFFSETS27, block_neighbours, block_neighbours27
    from pipeline.sparse.grid import BlockGrid

    rng = np.random.default_rng(3)
    p = np.stack(np.meshgrid(*[np.arange(-6, 7)] * 3, indexing="ij"), -1).reshape(-1, 3)
    p = p[rng.random(len(p)) < keep]
    p[:, 2] += far * (p[:, 0] > 0)  # far: a lattice too large to hold densely (the searches)
    grid = BlockGrid(1.0, 1.0, p * 8, np.zeros((len(p), 8, 8, 8), np.float32), np.zeros((len(p), 8, 8, 8), bool))
    for table, offs in ((block_neighbours(grid), FACE_DIRS), (block_neighbours27(grid), OFFSETS27)):
        want = np.stack([grid.block_index(grid.origins + 8 * o) for o in offs], axis=1)
        assert np.array_equal(table, want) and (want >= 0).any()
    shuffle = rng.permutation(len(grid.origins))
    rank = np.argsort(shuffle)  # row in the shuffled list of each sorted row
    for fn in (block_neighbours, block_neighbours27):
        got = fn(grid.origins[shuffle])
        want = fn(grid)[shuffle]
        assert np.array_equal(got, np.where(want >= 0, rank[np.maximum(want, 0)], -1))
