"""The compiled leaf builder (pipeline/io/leafbuild.cpp) against pyopenvdb's copyFromArray:
write_batched must make the same grid either way - every value, its activity, the tiles and the
leaf count - for any blocks, scales, batches and special values (the background, NaN, constant
blocks), written into empty grids and over grids that already hold leaves and tiles."""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.io import vdbgrids as vg
from pipeline.sparse.blockwrite import LeafSource
from pipeline.sparse.grid import LEAF

vdb = vg.vdb
HEADERS = Path("/usr/include/openvdb/openvdb.h").exists()


def test_the_leaf_builder_is_built_where_openvdb_headers_are():
    """.ci/setup.sh installs the headers on Debian, so the build must have made the module: a
    silent fall-back to copyFromArray would cost ~3 s per 1024^3 job unnoticed."""
    if not HEADERS:
        pytest.skip("no OpenVDB headers: the package is built without the leaf builder")
    if os.environ.get("FREPVDB_COPY_FROM_ARRAY") == "1":
        pytest.skip("FREPVDB_COPY_FROM_ARRAY=1 asks for the old path")
    assert vg._leafbuild is not None, "pipeline.io._leafbuild was not built: run `make setup` and read its output"


@contextlib.contextmanager
def _path(compiled: bool):
    """The compiled module (as built) or the pyopenvdb paths, for the calls inside."""
    saved = vg._leafbuild
    vg._leafbuild = saved if compiled else None
    try:
        yield
    finally:
        vg._leafbuild = saved


def _items(grid) -> list[tuple]:
    """Every stored value (leaf voxels, tiles, active or not) with its box, NaN as a token."""
    out = []
    for it in grid.citerAllValues():
        v = it.value
        out.append((tuple(it.min), tuple(it.max), "nan" if isinstance(v, float) and math.isnan(v) else v, it.active))
    return out


@st.composite
def _blocks(draw):
    n = draw(st.integers(1, 40))
    cells = draw(st.lists(st.tuples(*[st.integers(-6, 6)] * 3), min_size=n, max_size=n, unique=True))
    origins = np.array(sorted(cells), np.int64) * LEAF
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(n, LEAF, LEAF, LEAF)).astype(np.float32)
    active = rng.random((n, LEAF, LEAF, LEAF)) < draw(st.sampled_from([0.0, 0.3, 0.9, 1.0]))
    bg = draw(st.sampled_from([0.0, 0.25, -3.0]))
    scale = draw(st.sampled_from([1.0, -1.0, 2.5]))
    for b in range(n):  # some blocks of each kind a writer can meet
        kind = rng.integers(0, 6)
        if kind == 0:
            active[b] = False
        elif kind == 1:  # constant and active: an active tile
            active[b], values[b] = True, np.float32(rng.normal())
        elif kind == 2:  # the background after scaling: inactive
            values[b, 0, 0, :4] = np.float32(bg / scale)
            active[b, 0, 0, :4] = True
        elif kind == 3:
            values[b, 1, 2, 3] = np.nan
            active[b, 1, 2, 3] = True
        elif kind == 4:  # constant at the background: nothing
            active[b], values[b] = True, np.float32(bg / scale)
    dtype = draw(st.sampled_from([np.float32, np.float64]))
    return origins, values.astype(dtype), active, bg, scale, draw(st.sampled_from([None, 1, 7])), draw(st.booleans())


def _write(origins, values, active, bg, scale, batch, prior, compiled: bool, fill: bool):
    grid = vdb.FloatGrid(bg)
    if prior:  # leaves and a tile there already, where some blocks go and where none does
        grid.fill((-8, -8, -8), (23, 7, 7), 1.5, True)
        grid.copyFromArray(np.full((8, 8, 8), 0.75, np.float32), (0, 8, 0))
        grid.copyFromArray(np.arange(512, dtype=np.float32).reshape(8, 8, 8), (64, 64, 64))
    with _path(compiled):
        if fill:
            def fill_rows(lo, hi, v, a):
                v[:] = values[lo:hi]
                a[:] = active[lo:hi]
            vg.write_leaves(grid, LeafSource(1.0, bg, origins, fill=fill_rows), scale=scale, batch=batch)
        else:
            vg.write_batched(grid, origins, None, scale, batch, source=(values, active))
    return grid


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_blocks())
def test_leaf_builder_makes_copy_from_arrays_grid(case):
    origins, values, active, bg, scale, batch, prior = case
    fill = values.dtype == np.float32 and batch == 7  # the LeafSource path takes float32 leaves
    old = _write(origins, values, active, bg, scale, batch, prior, compiled=False, fill=fill)
    new = _write(origins, values, active, bg, scale, batch, prior, compiled=True, fill=fill)
    assert new.activeVoxelCount() == old.activeVoxelCount()
    assert new.leafCount() == old.leafCount()
    assert _items(new) == _items(old)


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_blocks())
def test_vec3_attribute_grid_is_that_of_copy_from_array(case):
    """attribute_grid's Vec3S grid from the compiled builder (add_vec3_blocks) is the one the
    per-block copyFromArray under a sentinel background makes: every value and box, active or
    not, the same; active voxels at (0, 0, 0), constant all-active blocks (tiles), empty blocks."""
    origins, values, active, *_ = case
    rng = np.random.default_rng(len(origins))
    rgb = np.stack([values, rng.normal(size=values.shape), np.abs(values)], -1).astype(np.float32)
    rgb = np.nan_to_num(rgb)  # attributes are finite (evaluate_attribute refuses the others)
    rgb[0, :2] = 0.0  # active voxels at the background keep their activity
    rgb[-1] = rgb[-1, 0, 0, 0]  # one constant block: a tile where it is all active
    rgb[~active] = 0.0
    with _path(False):
        old = vg.attribute_grid("color", rgb, origins, active, 0.5)
    with _path(True):
        new = vg.attribute_grid("color", rgb, origins, active, 0.5)
    assert new.activeVoxelCount() == old.activeVoxelCount() == int(active.sum())
    assert _items(new) == _items(old)
    assert new.background == old.background and new.name == old.name == "color"


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
def test_leaf_builder_refuses_bad_arrays():
    grid = vdb.FloatGrid(0.0)
    values = np.zeros((1, 8, 8, 8), np.float32)
    active = np.ones((1, 8, 8, 8), bool)
    with pytest.raises(ValueError, match="multiples of 8"):
        vg._leafbuild.add_blocks(grid, np.array([[1, 0, 0]], np.int64), values, active, 1.0)
    with pytest.raises(ValueError, match="element type"):
        vg._leafbuild.add_blocks(grid, np.zeros((1, 3), np.int64), values.astype(np.float64), active, 1.0)
    with pytest.raises(ValueError, match="expected"):
        vg._leafbuild.add_blocks(grid, np.zeros((2, 3), np.int64), values, active, 1.0)
    with pytest.raises(TypeError):  # not a FloatGrid
        vg._leafbuild.add_blocks(vdb.Vec3SGrid(), np.zeros((1, 3), np.int64), values, active, 1.0)
    assert grid.activeVoxelCount() == 0


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(*[st.integers(-5, 5)] * 3), min_size=1, max_size=60, unique=True),
       st.sampled_from([8, 128]), st.integers(0, 2**31 - 1), st.booleans(), st.sampled_from([None, 1.0]))
def test_tiles_are_those_of_grid_fill(cells, cell, seed, prior, merge):
    """fill_tiles through add_tiles makes the tiles grid.fill made, over leaves and tiles already
    there too; values repeat (runs along z of one value were one fill call)."""
    rng = np.random.default_rng(seed)
    origins = np.array(cells, np.int64) * cell
    values = rng.choice(np.array([1.0, 0.5, -2.0], np.float32), size=len(origins))
    grids = []
    for compiled in (False, True):
        grid = vdb.FloatGrid(0.0)
        if prior:
            grid.fill((-16, -16, -16), (15, 15, 15), 3.0, True)
            grid.copyFromArray(np.arange(512, dtype=np.float32).reshape(8, 8, 8), (0, 0, 8 * 3))
        with _path(compiled):
            vg.fill_tiles(grid, origins, values, cell=cell, merge_value=merge)
        grids.append(grid)
    old, new = grids
    assert new.activeVoxelCount() == old.activeVoxelCount()
    assert _items(new) == _items(old)


def _mixed_grid(seed: int, bg: float):
    """A grid with partial leaves, a tile, an active constant block and the background around."""
    rng = np.random.default_rng(seed)
    grid = vdb.FloatGrid(bg)
    grid.fill((-32, -32, 0), (-17, -1, 15), -0.5, True)  # leaf-sized tiles
    for _ in range(12):
        o = rng.integers(-4, 4, 3) * LEAF
        block = rng.normal(size=(8, 8, 8)).astype(np.float32)
        block[rng.random((8, 8, 8)) < 0.4] = bg
        grid.copyFromArray(block, tuple(int(c) for c in o))
    return grid


def _old_path(fn, *args):
    with _path(compiled=False):
        return fn(*args)


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 3.0]), st.integers(0, 3000))
def test_sample_reads_what_the_chunked_reads_read(seed, bg, n):
    """sample_values through the compiled sampler: leaf values, tiles and background, at
    points inside and far outside the grid, repeated points and none."""
    from pipeline.io.vtkio import sample_values

    grid = _mixed_grid(seed, bg)
    rng = np.random.default_rng(seed + 1)
    ijk = np.concatenate([rng.integers(-40, 40, (n, 3)), rng.integers(-10**6, 10**6, (n // 10, 3))])
    ijk = np.concatenate([ijk, ijk[: n // 5]])
    new = sample_values(grid, ijk)
    old = _old_path(sample_values, grid, ijk)
    assert new.dtype == old.dtype == np.float32
    assert np.array_equal(new, old)


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.tuples(*[st.integers(-45, 10)] * 3), st.tuples(*[st.integers(1, 60)] * 3),
       st.integers(1, 7))
def test_strided_box_reads_what_the_plane_reads_read(seed, lo, shape, stride):
    """The .vti's strided box (VTK point order, x fastest) through the compiled reader."""
    from pipeline.io.vtkio import _strided_box

    grid = _mixed_grid(seed, 1.0)
    new = _strided_box(grid, np.array(lo), np.array(shape), stride)
    old = _old_path(_strided_box, grid, np.array(lo), np.array(shape), stride)
    assert new.shape == old.shape
    assert np.array_equal(new, old)


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
def test_readers_refuse_bad_arrays():
    grid = vdb.FloatGrid(0.0)
    with pytest.raises(ValueError, match="writable float32"):
        vg._leafbuild.sample(grid, np.zeros((2, 3), np.int64), np.zeros(2, np.float64))
    with pytest.raises(ValueError, match="expected"):
        vg._leafbuild.sample(grid, np.zeros((2, 3), np.int64), np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="out must hold"):
        vg._leafbuild.strided_box(grid, (0, 0, 0), (2, 2, 2), 1, np.zeros(7, np.float32))


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_blocks(), st.sampled_from([0.0, 0.3, 2.0]))
def test_frep_signs_are_those_of_flood_fill_ax_and_background(case, bg):
    """frep_to_vdb's FRep signs through frep_signs (flood fill, every value negated, the
    background too, in C++) equal pyopenvdb's signedFloodFill + AX negation + background change:
    every value, tile and activity, for blocks of any sign with NaN, zeros, constant (tile)
    blocks and values at the background."""
    origins, values, active, _, _, _, _ = case
    blocks = vg.BlockGrid(1.0, bg, origins, values.astype(np.float32), active)
    grids = []
    for compiled in (False, True):
        with _path(compiled):
            grids.append(vg.frep_to_vdb(blocks, np.zeros((0, 2, 3), np.int64)))
    old, new = grids
    assert new.background == old.background
    assert new.leafCount() == old.leafCount()
    assert _items(new) == _items(old)


@pytest.mark.skipif(vg._leafbuild is None, reason="the leaf builder is not built here")
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 3.0, -1.0]), st.booleans())
def test_min_max_is_eval_min_max(seed, bg, tiles_only):
    """The compiled min_max equals pyopenvdb's evalMinMax over leaves, active tiles and values
    beyond any leaf's; (0, 0) for a grid with nothing active, as evalMinMax gives."""
    grid = vdb.FloatGrid(bg)
    if tiles_only:
        grid.fill((0, 0, 0), (127, 127, 127), 7.5, True)  # a node-sized tile, no leaf
    else:
        grid = _mixed_grid(seed, bg)
        grid.fill((64, 64, 64), (71, 71, 71), float(seed % 97) - 50.0, True)
    assert vg.min_max(grid) == grid.evalMinMax()
    empty = vdb.FloatGrid(bg)
    empty.fill((0, 0, 0), (7, 7, 7), 2.0, False)  # inactive values do not count
    assert vg.min_max(empty) == empty.evalMinMax() == (0.0, 0.0)
