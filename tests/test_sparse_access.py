"""pipeline.sparse.access.load_ghosts and pipeline.field.stencils against a dense copy of the grid:
a loaded buffer holds exactly the dense array's window around the block (the missing value where
no block is), and the stencils equal NumPy's differences on the dense array."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit, prange

from pipeline.field.stencils import central_gradient_at, half_difference
from pipeline.sparse.access import (
    ALL27,
    FACE_ROWS27,
    FACES6,
    FACES27,
    OFFSETS27,
    block_neighbours,
    block_neighbours27,
    load_ghosts,
)

MISSING = -7.5


def _grid(seed: int, keep: float):
    """Random blocks of a 4x4x4-block lattice (some absent), their values and active flags, and
    the dense (32+16)^3 copies padded by 8 voxels of MISSING / False."""
    rng = np.random.default_rng(seed)
    lattice = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    origins = 8 * lattice[rng.random(len(lattice)) < keep] - 8  # negative origins too
    if len(origins) == 0:
        origins = np.zeros((1, 3), np.int64)
    vals = rng.normal(size=(len(origins), 8, 8, 8)).astype(np.float32)
    act = rng.random((len(origins), 8, 8, 8)) < 0.7
    dense = np.full((48, 48, 48), MISSING, np.float32)
    dact = np.zeros((48, 48, 48), bool)
    for (x, y, z), v, a in zip(origins + 16, vals, act, strict=True):  # origin -8 at dense 8
        dense[x:x + 8, y:y + 8, z:z + 8] = v
        dact[x:x + 8, y:y + 8, z:z + 8] = a
    return origins.astype(np.int64), vals, act, dense, dact


def _window(dense, origin, w):
    x, y, z = origin + 16
    return dense[x - w:x + 8 + w, y - w:y + 8 + w, z - w:z + 8 + w]


def _loaded_offsets(cols) -> np.ndarray:
    """(n,n,n) mask of the buffer cells load_ghosts writes for a column map (centre always)."""
    return np.array([cols[o] >= 0 or o == 13 for o in range(27)])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), keep=st.sampled_from([0.3, 0.7, 1.0]), w=st.integers(1, 3),
       which=st.sampled_from(["faces6", "faces27", "all27"]), permute=st.booleans())
def test_load_ghosts_copies_the_dense_window(seed: int, keep: float, w: int, which: str, permute: bool) -> None:
    origins, vals, act, dense, dact = _grid(seed, keep)
    nbr = block_neighbours(origins) if which == "faces6" else block_neighbours27(origins)
    cols = {"faces6": FACES6, "faces27": FACES27, "all27": ALL27}[which]
    rows = np.zeros(0, np.int64)
    src_vals, src_act = vals, act
    if permute:  # the values live in another array's rows (load_padded_rows' case)
        perm = np.random.default_rng(seed).permutation(len(origins))
        src_vals, src_act = vals[perm], act[perm]
        rows = np.argsort(perm)
    n = 8 + 2 * w
    loaded = _loaded_offsets(cols)
    for b in range(len(origins)):
        buf = np.full((n, n, n), 123.0)
        abuf = np.zeros((n, n, n), bool)
        load_ghosts(src_vals, src_act, rows, nbr, cols, b, w, MISSING, buf, abuf)
        want, want_a = _window(dense, origins[b], w), _window(dact, origins[b], w)
        # which offset region each buffer cell is in
        part = np.concatenate([[0] * w, [1] * 8, [2] * w])
        region = part[:, None, None] * 9 + part[None, :, None] * 3 + part[None, None, :]
        written = loaded[region]
        assert np.array_equal(buf[written], want[written].astype(np.float64))
        assert np.array_equal(abuf[written], want_a[written])
        assert np.all(buf[~written] == 123.0), "cells of offsets not asked for are left alone"


def test_face_columns_are_the_faces() -> None:
    assert np.array_equal(OFFSETS27[FACE_ROWS27], [[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1],
                                                    [0, 0, 1]])
    assert sorted(np.flatnonzero(FACES6 >= 0)) == sorted(FACE_ROWS27) and sorted(FACES6[FACES6 >= 0]) == list(range(6))


@njit(cache=True)
def _stencils(buf, known):
    n = buf.shape[0]
    ax = np.zeros((n, n, n, 3))
    cg = np.zeros((n, n, n, 3))
    ok = np.zeros((n, n, n), np.bool_)
    for i in range(1, n - 1):
        for j in range(1, n - 1):
            for k in range(1, n - 1):
                for a in range(3):
                    di, dj, dk = int(a == 0), int(a == 1), int(a == 2)
                    ax[i, j, k, a] = half_difference(buf[i - di, j - dj, k - dk], known[i - di, j - dj, k - dk],
                                                     buf[i, j, k], buf[i + di, j + dj, k + dk],
                                                     known[i + di, j + dj, k + dk])
                cg[i, j, k, 0], cg[i, j, k, 1], cg[i, j, k, 2], ok[i, j, k] = central_gradient_at(buf, known, i, j, k)
    return ax, cg, ok


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), p_known=st.sampled_from([0.5, 0.9, 1.0]))
def test_stencils_equal_numpy_differences(seed: int, p_known: float) -> None:
    rng = np.random.default_rng(seed)
    buf = rng.normal(size=(10, 10, 10))
    known = rng.random((10, 10, 10)) < p_known
    ax, cg, ok = _stencils(buf, known)
    inner = (slice(1, 9),) * 3
    for a in range(3):
        lo, hi = np.roll(buf, 1, a), np.roll(buf, -1, a)
        klo, khi = np.roll(known, 1, a), np.roll(known, -1, a)
        want = np.where(klo & khi, 0.5 * (hi - lo), np.where(khi, hi - buf, np.where(klo, buf - lo, 0.0)))
        assert np.array_equal(ax[..., a][inner], want[inner])
        both = known & klo & khi
        assert np.array_equal(cg[..., a][inner][ok[inner]], (0.5 * (hi - lo))[inner][ok[inner]])
        if a == 0:
            all_ok = both.copy()
        else:
            all_ok &= both
    assert np.array_equal(ok[inner], all_ok[inner])


def test_half_difference_cases() -> None:
    f = half_difference
    assert f(1.0, True, 2.0, 5.0, True) == 2.0  # central
    assert f(1.0, False, 2.0, 5.0, True) == 3.0  # forward
    assert f(1.0, True, 2.0, 5.0, False) == 1.0  # backward
    assert f(1.0, False, 2.0, 5.0, False) == 0.0  # nothing known: flat


@njit(parallel=True)
def _centre_values(vals, act, nbr):
    out = np.zeros(vals.shape[0])
    for b in prange(vals.shape[0]):  # the prange index itself, unsigned in Numba's parfors
        buf = np.empty((10, 10, 10))
        abuf = np.empty((10, 10, 10), np.bool_)
        load_ghosts(vals, act, np.zeros(0, np.int64), nbr, ALL27, b, 1, -1.0, buf, abuf)
        out[b] = buf[1, 1, 1]
    return out


def test_load_ghosts_takes_a_prange_index() -> None:
    """Numba unifies an unsigned prange index with int64 block rows to float64, which cannot
    index an array: load_ghosts must type its centre row itself (this failed to compile)."""
    origins, vals, act, _, _ = _grid(7, 1.0)
    got = _centre_values(vals.astype(np.float64), act, block_neighbours27(origins))
    assert np.array_equal(got, vals[:, 0, 0, 0].astype(np.float64))
