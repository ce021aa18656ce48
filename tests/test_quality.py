"""Field-quality kernels (pipeline.distance.quality) against direct NumPy computations on sparse grids
with block borders, missing neighbour blocks and inactive voxels."""

from __future__ import annotations

import numpy as np
from test_eikonal import band_grid, sphere, torus

from pipeline.distance.quality import central_gradient, extra_zero_crossings, gradient_stats
from pipeline.sparse.grid import BlockGrid


def _holes(grid: BlockGrid, seed: int) -> BlockGrid:
    rng = np.random.default_rng(seed)
    active = grid.active & (rng.random(grid.active.shape) > 0.05)
    keep = rng.random(len(grid.origins)) > 0.1  # missing blocks: neighbours absent
    return BlockGrid(grid.voxel_size, grid.background, grid.origins[keep], grid.values[keep], active[keep])


def test_histogram_statistics_match_the_per_voxel_gradients() -> None:
    frep, _ = band_grid(torus, 64)
    grid = _holes(frep, 1)
    fast = gradient_stats(grid)  # Numba histogram, constant memory
    _, g = central_gradient(grid)  # per-voxel gradients, NumPy statistics
    mag = np.linalg.norm(g, axis=1)
    assert fast["voxels"] == len(mag) > 1000
    assert abs(fast["mean"] - mag.mean()) < 1e-9
    assert abs(fast["p01"] - np.percentile(mag, 1)) < 2e-4 and abs(fast["p99"] - np.percentile(mag, 99)) < 2e-4
    assert abs(fast["share_below_0_5"] - np.mean(mag < 0.5)) < 1e-12
    assert abs(fast["share_within_1pct"] - np.mean(np.abs(mag - 1) <= 0.01)) < 2e-3  # bin edges


def _flips_numpy(field: BlockGrid, ref: BlockGrid) -> tuple[int, int]:
    """Edges between active voxels of both grids where field flips sign and ref does not."""
    fi, fv = field.active_voxels()
    ri, rv = ref.active_voxels()
    f = {tuple(p): v for p, v in zip(fi.tolist(), fv.tolist(), strict=True)}
    r = {tuple(p): v for p, v in zip(ri.tolist(), rv.tolist(), strict=True)}
    extra = edges = 0
    for p, v in f.items():
        if p not in r:
            continue
        for d in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
            q = (p[0] + d[0], p[1] + d[1], p[2] + d[2])
            if q in f and q in r:
                edges += 1
                extra += ((v > 0) != (f[q] > 0)) and (r[p] > 0) == (r[q] > 0)
    return extra, edges


def test_extra_zero_crossings_are_counted_exactly() -> None:
    frep, _ = band_grid(sphere, 32)
    ref = _holes(frep, 2)
    rng = np.random.default_rng(4)
    values = ref.values.copy()
    flip = ref.active & (rng.random(values.shape) < 0.01)
    values[flip] *= -1  # spurious sign changes
    field = BlockGrid(ref.voxel_size, ref.background, ref.origins, values, ref.active)
    out = extra_zero_crossings(field, ref)
    extra, edges = _flips_numpy(field, ref)
    assert extra > 50
    assert (out["extra_zero_crossings"], out["edges_compared"]) == (extra, edges)
    assert extra_zero_crossings(ref, ref)["extra_zero_crossings"] == 0


def test_histogram_counts_every_voxel_in_its_bin_whatever_inactive_voxels_hold() -> None:
    """The compiled histogram (its gradients computed for every voxel of a row before the
    activity test) equals NumPy's histogram of the per-voxel gradients, bin for bin; inactive
    voxels holding inf, nan or huge values change nothing; the inside negation too."""
    from pipeline.distance.quality import _NO_SIGN, HIST_BINS, HIST_MAX, _chunks, _gradient_hist
    from pipeline.sparse.access import block_neighbours

    frep, _ = band_grid(torus, 48)
    grid = _holes(frep, 3)
    nbr = block_neighbours(grid)
    _, g = central_gradient(grid)
    mag = np.linalg.norm(g, axis=1)
    want = np.bincount(np.minimum((mag * (HIST_BINS / HIST_MAX)).astype(np.int64), HIST_BINS - 1),
                       minlength=HIST_BINS)
    junk = grid.values.copy()
    rng = np.random.default_rng(7)
    junk[~grid.active] = rng.choice([np.inf, -np.inf, np.nan, 3e38], size=int((~grid.active).sum()))
    for values in (grid.values, junk):
        hist = np.zeros(HIST_BINS, np.int64)
        n, total = _gradient_hist(values, grid.active, nbr, float(grid.voxel_size), hist, _chunks(len(values)),
                                  _NO_SIGN)
        assert n == len(mag) > 1000 and np.array_equal(hist, want)
        assert abs(total - mag.sum()) < 1e-9 * n
    # |grad| of -f inside equals |grad f| wherever the stencil does not cross the inside's border
    inside = np.ones(grid.values.shape, bool)
    hist = np.zeros(HIST_BINS, np.int64)
    n, _ = _gradient_hist(grid.values, grid.active, nbr, float(grid.voxel_size), hist, _chunks(len(junk)), inside)
    assert n == len(mag) and np.array_equal(hist, want)
