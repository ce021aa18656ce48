"""The eikonal solve continued across bricks (pipeline.distance.eikonal_bricks): inline, on the local
process pool and on a real Dask LocalCluster, against the unsplit solve."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_eikonal import SHAPES, band_grid

from pipeline.distance.eikonal import solve_distance
from pipeline.distance.eikonal_bricks import brick_of_blocks
from pipeline.io.vdbgrids import vdb
from pipeline.job.batch import DaskExecutor, Executor, LocalExecutor, run_batch
from pipeline.job.config import load_jobs

N = 64
H = 2.0 / N


def compare(a, b, limit_vox: float | None) -> float:
    """Max difference (voxels) between two solves on the same block set; the solved sets may
    differ only on voxels at the max_distance limit (accepted or not within the tolerance)."""
    assert np.array_equal(a.distance.origins, b.distance.origins)
    assert np.array_equal(a.inside, b.inside)
    differ = a.distance.active ^ b.distance.active
    if differ.any():
        assert limit_vox is not None
        at = np.where(a.distance.active, a.distance.values, b.distance.values)[differ] / H
        # a voxel whose value lands within the solver's error of the cut-off may be accepted
        # by one visiting order and not by the other
        assert np.all(np.abs(at - limit_vox) < 0.05), at
        assert differ.sum() <= 1e-4 * a.distance.active.sum() + 2
    both = a.distance.active & b.distance.active
    return float(np.abs(a.distance.values - b.distance.values)[both].max() / H)


_BOX_FANS = pytest.mark.xfail(strict=True, reason="not met since session 16: on the box, bricks of 16 differ from the "
                              "unsplit second-order solve by 0.0013 voxel (max_distance 3 voxels) and 0.007 voxel "
                              "(whole domain, 20 voxels out in an edge's fan; 0.00025 before): the voxels diagonal "
                              "to convex edges and corners are now frozen next to the kink (max error 0.96 -> 0.43 "
                              "voxel, scikit-fmm 0.73), and the non-monotone second-order scheme settles in those "
                              "fans in an order-dependent way")


@pytest.mark.parametrize("name, order", [(n, o) if (n, o) != ("box", 2) else pytest.param(n, o, marks=_BOX_FANS)
                                         for o in (1, 2) for n in sorted(SHAPES)])
def test_bricked_solve_equals_the_unsplit_one(name: str, order: int) -> None:
    frep, dom = band_grid(SHAPES[name], N)
    for limit in (3.0, None):
        whole = solve_distance(frep, None if limit is None else limit * H, dom, order=order)
        for brick in (16, 24, 40):  # 24 and 40 do not divide the domain or the 8^3 leaves' lattice evenly
            split = solve_distance(frep, None if limit is None else limit * H, dom, order=order, brick=brick)
            assert split.stats["bricks"] > 1
            assert split.stats["rounds"] >= 2  # information did cross brick faces
            assert split.stats["converged"] and split.stats["scheme"] == whole.stats["scheme"]
            # the same fixed point up to the stopping tolerance (1e-6 voxel per update, met along
            # fronts tens of voxels long in a different order) and float32 storage; the
            # second-order pass is not monotone and settles within 1e-3 voxel
            assert compare(whole, split, limit) < (1e-4 if order == 1 else 1e-3), (name, limit, brick)


@settings(max_examples=6, deadline=None)
@given(st.lists(st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.12, 0.35)),
                min_size=1, max_size=4),
       st.sampled_from([8, 16, 32]))
def test_bricked_solve_on_random_sphere_unions(spheres, brick) -> None:
    """First order: the bricked rounds reach the unsplit fixed point (monotone scheme, unique
    fixed point: Jeong & Whitaker's argument). Second order: see the strict xfail below."""
    c = np.array([s[:3] for s in spheres])
    r = np.array([s[3] for s in spheres])

    def fn(p):
        return (r - np.linalg.norm(p[..., None, :] - c, axis=-1)).max(axis=-1)

    frep, dom = band_grid(fn, 48)
    h = 2.0 / 48
    whole = solve_distance(frep, 4 * h, dom, order=1)
    split = solve_distance(frep, 4 * h, dom, brick=brick, order=1)
    both = whole.distance.active & split.distance.active
    assert np.abs(whole.distance.values - split.distance.values)[both].max() < 1e-4 * h


def test_bricks_follow_the_brick_lattice() -> None:
    origins = np.array([[0, 0, 0], [8, 0, 0], [16, 0, 0], [-8, 0, 0], [8, 24, 8]])
    b = brick_of_blocks(origins, 16)
    assert b[0] == b[1] and len({b[0], b[2], b[3], b[4]}) == 4


def test_bricked_solve_on_the_process_pool() -> None:
    frep, dom = band_grid(SHAPES["torus"], N)
    whole = solve_distance(frep, 3 * H, dom)
    pool = LocalExecutor(2)
    try:
        split = solve_distance(frep, 3 * H, dom, brick=32, map_fn=pool.map)
    finally:
        pool.close()
    assert compare(whole, split, 3.0) < 1e-3


JOB = """name: {name}
domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 64}}
{bricks}
model:
  union:
    - torus: {{major: 0.55, minor: 0.22}}
    - box: {{min: [-0.25, -0.25, -0.5], max: [0.25, 0.25, 0.5]}}
stages:
  - voxelise: {{band: 3}}
  - hfrep: {{max_distance: 0.2, attributes: [{{name: depth, formula: d}}]}}
  - export: {{vdb: true}}
"""


def dense(path, name):
    g = vdb.read(str(path), name)
    lo, hi = g.evalActiveVoxelBoundingBox()
    a = np.zeros(tuple(np.array(hi) - np.array(lo) + 1), np.float32)
    g.copyToArray(a, lo)
    return int(g.activeVoxelCount()), a, tuple(lo)


@pytest.fixture(scope="module")
def cluster():
    ex = DaskExecutor(workers=2)
    yield ex
    ex.close()


def test_hfrep_on_bricks_on_dask_matches_the_unsplit_run(tmp_path, cluster) -> None:
    (tmp_path / "whole.yaml").write_text(JOB.format(name="whole", bricks=""))
    (tmp_path / "split.yaml").write_text(JOB.format(name="split", bricks="bricks: {size: 32}"))
    (rw,) = run_batch(load_jobs(tmp_path / "whole.yaml"), tmp_path, Executor())
    (rs,) = run_batch(load_jobs(tmp_path / "split.yaml"), tmp_path, cluster)
    assert rw["status"] == rs["status"] == "ok", (rw, rs)
    ms = json.loads((tmp_path / "split" / "manifest.json").read_text())
    hstats = next(s["stats"] for s in ms["stages"] if s["name"] == "hfrep")
    assert hstats["bricks"] >= 8 and hstats["rounds"] >= 2 and hstats["converged"]
    h = 2.0 / 64
    for grid in ("surface", "hfrep", "depth"):
        nw, aw, low = dense(tmp_path / "whole" / "whole.vdb", grid)
        ns, as_, los = dense(tmp_path / "split" / "split.vdb", grid)
        # as compare() allows: a few voxels whose value lands at the max_distance cut-off within
        # the solver's tolerance may be accepted by one visiting order and not by the other
        assert abs(nw - ns) <= 1e-4 * nw + 2 and low == los, (grid, nw, ns)
        # within the solver's tolerance; in the last voxel before the max_distance cut-off (0.2)
        # the non-monotone second-order update may settle up to 0.05 voxel apart (docs/eikonal.md)
        near_cut = np.abs(np.abs(aw) - 0.2) < h if grid != "depth" else np.zeros(aw.shape, bool)
        np.testing.assert_allclose(as_[~near_cut], aw[~near_cut], atol=1e-3 * h, err_msg=grid)
        np.testing.assert_allclose(as_[near_cut], aw[near_cut], atol=0.05 * h, err_msg=grid)


@pytest.mark.parametrize("centre, radius, brick", [
    ((0.0, 0.0, 0.4375), 0.25, 8),
    # 0.0025 voxel apart until session 16 (then a strict xfail); within the bound since the
    # voxels next to kinks of the sampled surface are frozen
    ((0.0, 0.06299828609015157, -0.14924104884936357), 0.13713543362049535, 16)])
def test_bricked_second_order_solve_near_brick_faces(centre, radius, brick) -> None:
    c = np.array([centre])
    r = np.array([radius])

    def fn(p):
        return (r - np.linalg.norm(p[..., None, :] - c, axis=-1)).max(axis=-1)

    frep, dom = band_grid(fn, 48)
    h = 2.0 / 48
    whole = solve_distance(frep, 4 * h, dom)
    split = solve_distance(frep, 4 * h, dom, brick=brick)
    both = whole.distance.active & split.distance.active
    assert np.abs(whole.distance.values[both] - split.distance.values[both]).max() < 1e-3 * h
