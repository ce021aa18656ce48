"""quality.deviation_on_blocks (the parallel kernel) against the same numbers computed directly
with NumPy on a sphere band whose values are perturbed by a known amount."""

from __future__ import annotations

import numpy as np

from pipeline.distance.quality import deviation_on_blocks
from pipeline.sparse.grid import BlockGrid
from tests.test_eikonal import band_grid, sphere_of


def test_deviation_on_blocks_matches_numpy() -> None:
    n = 64
    h = 2.0 / n
    ref, _ = band_grid(sphere_of(0.6), n, band=4.0)  # positive inside: the exact distance
    rng = np.random.default_rng(7)
    noise = rng.uniform(-0.3, 0.3, ref.values.shape).astype(np.float32) * np.float32(h)
    # the grid under test: level-set convention (negative inside), perturbed, a subset of the blocks
    keep = rng.permutation(len(ref.origins))[: len(ref.origins) * 3 // 4]
    grid = BlockGrid(h, 4 * h, ref.origins[keep], (-ref.values[keep] + noise[keep]), ref.active[keep].copy())
    grid.active[:, 0, 0, 0] = False
    band = 2.5 * h
    got = deviation_on_blocks(grid, ref, band, -1.0)
    at = {tuple(o): i for i, o in enumerate(ref.origins.tolist())}  # BlockGrid keeps its blocks sorted
    rows = np.array([at[tuple(o)] for o in grid.origins.tolist()])
    r = -ref.values[rows].astype(np.float64)
    use = grid.active & ref.active[rows] & (np.abs(r) < band)
    err = np.abs(grid.values.astype(np.float64) - r)[use]
    assert got["voxels"] == int(use.sum()) > 10_000
    assert got["max"] == err.max() and got["max"] <= 0.3 * h * 1.0001 and got["max"] > 0.29 * h
    assert np.isclose(got["mean"], err.mean(), rtol=1e-12) and np.isclose(got["rms"], np.sqrt((err**2).mean()),
                                                                          rtol=1e-12)
    near = grid.origins[: len(grid.origins) // 2]
    part = deviation_on_blocks(grid, ref, band, -1.0, near=near)
    assert part["voxels"] == int(use[: len(near)].sum())
    assert deviation_on_blocks(grid, ref, 0.0, -1.0) == {"voxels": 0}
