"""The fine solve's inside limit (``solve_distance(..., inside_distance=...)``, the hfrep
stage's ``interior: coarse``) and the coarse values beyond it (``pipeline.distance.hfim.interior_tiles``
and ``fill_deep``): inside the limit the values are the unlimited solve's, beyond it every
voxel (leaf tiles and the deep voxels of solved blocks) is within the stated bound of the
exact distance, and the written grids read back with those values."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.distance.eikonal import INSIDE_MARGIN, solve_distance
from pipeline.distance.hfim import fill_deep, interior_tiles
from pipeline.distance.hfrep import density_leaves, hfrep_blocks
from pipeline.io.vdbgrids import fill_tiles, fog_grid, frep_to_vdb
from tests.test_eikonal import band_grid, box_of, sphere_of

N = 96
H = 2.0 / N
SHAPES = {"sphere": sphere_of(0.7), "box": box_of(np.array([0.7, 0.5, 0.6]))}
LIMIT = 6.0  # voxels: the reach (inside_distance)
SOLVED = LIMIT + INSIDE_MARGIN  # how far inside the fine FIM accepts values
BOUND = 4 * np.sqrt(3) + 1  # voxels: half a leaf's diagonal plus the node solve's error


def _pair(name: str):
    frep, dom = band_grid(SHAPES[name], N)
    full = solve_distance(frep, 3 * H, dom)
    lim = solve_distance(frep, 3 * H, dom, inside_distance=LIMIT * H)
    return frep, dom, full, lim


@pytest.fixture(scope="module", params=sorted(SHAPES))
def pair(request):
    return (request.param, *_pair(request.param))


def test_values_inside_the_limit_are_the_unlimited_solve(pair) -> None:
    name, frep, dom, full, lim = pair
    st = lim.stats
    assert st["unsolved_blocks_dropped"] > 0 and st["deep_voxels_in_fine_blocks"] > 0
    assert st["solved_voxels"] < full.stats["solved_voxels"]
    rows = full.distance.block_index(lim.distance.origins)
    assert (rows >= 0).all()
    fv, fa = full.distance.values[rows] / H, full.distance.active[rows]
    lv, la = lim.distance.values / H, lim.distance.active
    assert np.array_equal(lim.inside, full.inside[rows])
    assert (fa | ~la).all()
    # the same fixed point wherever the unlimited value is within the reach; a voxel next to the
    # cut-off (one voxel deeper) may end up a little off (the second-order scheme is not
    # monotone: without its neighbours beyond the cut-off its updates come in another order)
    within = la & (fv <= LIMIT)
    assert within.sum() > 10_000 and np.abs(lv[within] - fv[within]).max() <= 1e-4
    # past the reach (the INSIDE_MARGIN shell, written as fine voxels of the deep interior) a
    # voxel next to the cut-off can move (measured 0.15 voxel): far inside the deep bound
    assert np.abs(lv[la] - fv[la]).max() <= 0.25
    ins = lim.inside & la
    assert SOLVED - 0.5 < lv[ins].max() <= SOLVED
    # nothing shallower than the limit is lost, the deep voxels are deeper than it
    shallow = lim.inside & fa & (fv <= SOLVED - 1e-3)
    assert la[shallow].all()
    deep = np.zeros_like(la)
    deep[lim.deep_rows] = lim.deep_mask
    assert (fv[deep] > SOLVED - 1e-3).all()
    # every inside voxel of the full solve is solved, deep, or in a coarse block
    keys = set(map(tuple, lim.distance.origins.tolist())) | set(map(tuple, lim.coarse_inside.tolist()))
    missing = [o for o, a in zip(full.distance.origins.tolist(), (full.inside & full.distance.active)
                                 .reshape(len(full.inside), -1).any(axis=1), strict=True) if a and tuple(o) not in keys]
    assert not missing


def test_deep_voxels_and_tiles_read_back_within_the_bound(pair) -> None:
    name, frep, dom, full, lim = pair
    fn = SHAPES[name]
    origins, values, fill, st = interior_tiles(lim, dom)
    assert st["unreached"] == 0 and st["deep_blocks"] == len(lim.deep_rows) > 0 and len(origins) > 0
    hf = hfrep_blocks(frep, lim)
    fill_deep(hf, lim, fill)
    grid = frep_to_vdb(hf, np.zeros((0, 2, 3), np.int64), "hfrep")
    fill_tiles(grid, origins, values)
    dens = fog_grid(*density_leaves(lim, 3 * H), "density")
    fill_tiles(dens, origins, np.ones(len(origins)))
    lo, hi = (np.asarray(b) for b in dom)
    shape = tuple(int(x) for x in hi - lo + 1)
    arr, darr = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    grid.copyToArray(arr, tuple(int(x) for x in lo))
    dens.copyToArray(darr, tuple(int(x) for x in lo))
    act = np.zeros(shape, bool)
    for item in grid.citerOnValues():
        a, b = item["min"], item["max"]
        act[a[0] - lo[0]:b[0] - lo[0] + 1, a[1] - lo[1]:b[1] - lo[1] + 1, a[2] - lo[2]:b[2] - lo[2] + 1] = True
    ijk = np.stack(np.meshgrid(*[np.arange(lo[a], hi[a] + 1) for a in range(3)], indexing="ij"), -1)
    exact = fn(ijk * H) / H  # positive inside
    inside = exact > 0.5
    assert act[inside].all()  # every voxel inside is active: nothing of the interior is missing
    d = arr / H
    beyond = inside & (exact > LIMIT + 1)
    assert beyond.sum() > 10_000
    assert np.abs(d[beyond] - exact[beyond]).max() <= BOUND
    assert (d[beyond] >= LIMIT - 1e-3).all()
    near = inside & (exact < LIMIT - 1)
    assert np.abs(d[near] - exact[near]).max() <= 1.0  # the fine solve (first order, under a voxel)
    assert np.array_equal(darr[beyond], np.ones(int(beyond.sum()), np.float32))
    # the voxels the fill covered inside solved blocks, on their own
    deep_ijk = []
    for r, m in zip(lim.deep_rows, lim.deep_mask, strict=True):
        deep_ijk.append(lim.distance.origins[r] + np.argwhere(m))
    deep_ijk = np.concatenate(deep_ijk) - lo
    dd, de = d[tuple(deep_ijk.T)], exact[tuple(deep_ijk.T)]
    assert np.abs(dd - de).max() <= BOUND and dd.min() >= LIMIT - 1e-3


def test_blocks_left_out_before_the_solve_change_nothing(monkeypatch) -> None:
    """The lower bound that leaves blocks out before the FIM (eikonal._far_blocks) only drops
    blocks the FIM would not have solved: the same result as without it (margin so large that
    nothing is left out)."""
    import pipeline.distance.eikonal as eik

    frep, dom = band_grid(SHAPES["box"], N)
    a = solve_distance(frep, 3 * H, dom, inside_distance=LIMIT * H)
    monkeypatch.setattr(eik, "SURFACE_MARGIN", 1e9)
    b = solve_distance(frep, 3 * H, dom, inside_distance=LIMIT * H)
    assert a.stats["far_blocks_left_out"] > 100 and b.stats["far_blocks_left_out"] == 0
    assert a.stats["unsolved_blocks_dropped"] < b.stats["unsolved_blocks_dropped"]
    assert np.array_equal(a.distance.origins, b.distance.origins)
    assert np.array_equal(a.distance.values, b.distance.values)
    assert np.array_equal(a.distance.active, b.distance.active)
    assert np.array_equal(a.coarse_inside, b.coarse_inside)
    assert np.array_equal(a.deep_rows, b.deep_rows) and np.array_equal(a.deep_mask, b.deep_mask)
    for k in ("block_visits", "voxel_updates", "solved_voxels"):
        assert a.stats[k] == b.stats[k]
