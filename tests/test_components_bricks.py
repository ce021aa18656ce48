"""Components on bricks (components seed, Algorithm 1 + section 4.2 split over bricks): the
bricked detection equals the whole-domain one (same cell set, same labels in scan order, same
volumes), for components crossing brick faces, edges and corners, brick sizes that do not divide
the octree, continuation walks that leave their brick, and end to end on a Dask LocalCluster."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.io.vdbgrids import vdb
from pipeline.job.batch import DaskExecutor, Executor, LocalExecutor, run_batch
from pipeline.job.config import _Ctx, build_node, load_jobs
from pipeline.model.base import Node
from pipeline.topology import component_bricks as cb
from pipeline.topology import components as cc

ORIGIN, SIZE = np.full(3, -1.0), 2.0
DIAGONAL = {"intersection": [{"expr": "0.004 - (x^2 + y^2 + z^2 - (x + y + z)^2 / 3)"},
                             {"sphere": {"radius": 0.95}}]}  # thin rod along x = y = z


def node(raw: dict) -> Node:
    return build_node(raw, ("model",), _Ctx("test", raw, Path(".")))


def sphere(c, r) -> dict:
    return {"sphere": {"center": list(c), "radius": r}}


def cell_table(comp: cc.Components) -> tuple[np.ndarray, np.ndarray]:
    """Rows (level, lowest-corner key, kind) sorted, and the labels in that order."""
    tree = comp.tree
    key = cc.pack(tree.coords << (tree.depth - tree.level)[:, None])
    rows = np.stack([tree.level, key, tree.kind.astype(np.int64)], axis=1)
    order = np.lexsort(rows.T[::-1])
    return rows[order], comp.labels[order]


def assert_same(got: cc.Components, ref: cc.Components) -> None:
    assert got.count == ref.count
    gr, gl = cell_table(got)
    rr, rl = cell_table(ref)
    assert np.array_equal(gr, rr)  # the union of the bricks' cells is the whole-domain cell set
    assert np.array_equal(gl, rl)  # identical labels after the scan-order renumbering
    np.testing.assert_allclose(got.volumes, ref.volumes, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.volume_bounds, ref.volume_bounds, rtol=0, atol=1e-12)
    if got.tree.stats["continuation_cells"] == 0:  # then even the row order is the same
        for a in ("level", "coords", "kind", "pos_frac"):
            assert np.array_equal(getattr(got.tree, a), getattr(ref.tree, a)), a
        assert np.array_equal(got.labels, ref.labels)


MODELS = {
    "spheres": {"union": [sphere((-0.55, -0.3, 0.1), 0.25), sphere((0.05, 0.45, -0.2), 0.2),
                          sphere((0.5, -0.4, 0.45), 0.3), sphere((0.5, 0.5, 0.5), 0.12)]},
    "torus": {"torus": {"major": 0.6, "minor": 0.15}},
    "diagonal_rod": DIAGONAL,
    # centred on the corner shared by 8 bricks of 16 cells (index 32 -> world 0) and of 12 cells (-0.25)
    "corner_spheres": {"union": [sphere((0, 0, 0), 0.2), sphere((-0.25, -0.25, -0.25), 0.04),
                                 sphere((-0.625, 0.5, -0.625), 0.1)]},
}


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("brick", [16, 12])  # 12 does not divide the 64 finest cells
def test_bricked_detection_equals_the_whole_domain(name, brick):
    model = node(MODELS[name])
    ref = cc.detect(model, ORIGIN, SIZE, 6)
    got = cb.detect_bricked(model, ORIGIN, SIZE, 6, brick)
    assert_same(got, ref)
    info = got.tree.stats["bricked"]
    assert info["bricks"] == (64 // brick + (64 % brick > 0)) ** 3
    assert info["cross_face_unions"] == info["local_clusters"] - ref.count  # one union per merged pair
    if name != "spheres":
        assert info["cross_face_unions"] > 0  # these components do cross brick faces


def test_region_and_phase_like_the_stage():
    """A region smaller than the root (the job's domain box), planes offset by a phase, the layer
    of cells that only touch the region's high face: still the same cells and labels."""
    model = node({"union": [MODELS["torus"], sphere((0.3, 0.3, 0.55), 0.2)]})
    region = (np.full(3, -1.0), np.full(3, 0.7))
    ref = cc.detect(model, ORIGIN, SIZE, 6, 0.0, region)
    got = cb.detect_bricked(model, ORIGIN, SIZE, 6, 10, 0.0, region, phase=(3, 7, 0))
    assert_same(got, ref)
    assert got.tree.stats["bricked"]["ghost_links"] > 0  # coarse inside cells reach across planes


class LooseBound(Node):
    """A model whose affine bound wrongly says "outside" right of x = -0.3: the subdivision
    rejects surface cells there and only Algorithm 1's continuation (sign changes on cell edges)
    finds them, walking across brick planes into bricks that never enumerated them."""

    kind = "loose_bound"

    def __init__(self, inner: Node):
        super().__init__(None)
        self.inner = inner

    def field(self, x, y, z, t):
        return self.inner.field(x, y, z, t)

    def bound(self, lo, hi, t=0.0):
        flo, fhi = self.inner.bound(lo, hi, t)
        wrong = lo[:, 0] > -0.3
        return np.where(wrong, -1.0, flo), np.where(wrong, -1.0, fhi)


@pytest.mark.parametrize("brick", [8, 11])
def test_continuation_that_leaves_its_brick(brick):
    model = LooseBound(node({"union": [{"torus": {"major": 0.55, "minor": 0.2}}, sphere((0.6, 0.6, 0), 0.2)]}))
    ref = cc.detect(model, ORIGIN, SIZE, 6)
    assert ref.tree.stats["continuation_cells"] > 100
    got = cb.detect_bricked(model, ORIGIN, SIZE, 6, brick)
    assert got.tree.stats["bricked"]["driver_cells"] > 0  # escaped walks finished by the driver
    assert_same(got, ref)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spheres=st.lists(st.tuples(st.floats(-0.7, 0.7), st.floats(-0.7, 0.7), st.floats(-0.7, 0.7),
                                  st.floats(0.06, 0.3)), min_size=1, max_size=5),
       brick=st.integers(5, 13), phase=st.integers(0, 12))
def test_random_spheres(spheres, brick, phase):
    model = node({"union": [sphere(s[:3], s[3]) for s in spheres]})
    ref = cc.detect(model, ORIGIN, SIZE, 5)
    assert_same(cb.detect_bricked(model, ORIGIN, SIZE, 5, brick, phase=phase), ref)


def test_split_planes_follow_voxel_bricks():
    # 64 voxels from index -32: bricks of 24 voxels start at index -48, -24, 0, 24 -> cells 8, 32, 56
    cells, phase = cb.voxel_bricks(24, np.array([-32, -32, -32]), 1 / 32, 2.0, 6)
    assert cells == 24 and phase.tolist() == [8, 8, 8]
    cuts = cb.planes(ORIGIN, SIZE, 6, cells, phase)
    assert [c.tolist() for c in cuts] == [[8, 32, 56]] * 3
    assert len(cb.bricks_of(6, cuts)) == 64
    cells, phase = cb.voxel_bricks(32, np.array([-32, -32, -32]), 1 / 32, 2.0, 5)  # finest cell = 2 voxels
    assert cells == 16 and phase.tolist() == [0, 0, 0]


# --- end to end: the components stage on bricks, on a Dask LocalCluster -------------------------------

JOB = """name: {name}
domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 64}}
{bricks}
model:
  union:
    - {{intersection: [{{expr: "0.004 - (x^2 + y^2 + z^2 - (x + y + z)^2 / 3)"}}, {{sphere: {{radius: 0.95}}}}]}}
    - {{torus: {{major: 0.55, minor: 0.12, center: [0, 0, -0.55]}}}}
    - {{sphere: {{center: [0.25, -0.5, 0.25], radius: 0.2}}}}
    - {{sphere: {{center: [-0.6, 0.6, 0.1], radius: 0.15}}}}
stages:
  - voxelise: {{band: 2}}
  - components: {{}}
  - export: {{vdb: true}}
"""


@pytest.fixture(scope="module")
def cluster():
    ex = DaskExecutor(workers=2)
    yield ex
    ex.close()


def component_labels(path: Path) -> tuple[np.ndarray, np.ndarray]:
    g = vdb.read(str(path), "component")
    lo, hi = g.evalActiveVoxelBoundingBox()
    a = np.zeros(tuple(np.array(hi) - np.array(lo) + 3), np.float32)
    g.copyToArray(a, tuple(c - 1 for c in lo))
    return np.array(lo), a


def run_pair(tmp_path: Path, executor, brick: int) -> tuple[dict, dict, np.ndarray, np.ndarray]:
    whole = tmp_path / "whole.yaml"
    whole.write_text(JOB.format(name="whole", bricks=""))
    split = tmp_path / "split.yaml"
    split.write_text(JOB.format(name="split", bricks=f"bricks: {{size: {brick}}}"))
    (rw,) = run_batch(load_jobs(whole), tmp_path, Executor())
    (rs,) = run_batch(load_jobs(split), tmp_path, executor)
    assert rw["status"] == rs["status"] == "ok", (rw, rs)
    mw = json.loads((tmp_path / "whole" / "manifest.json").read_text())
    ms = json.loads((tmp_path / "split" / "manifest.json").read_text())
    low, A = component_labels(tmp_path / "whole" / "whole.vdb")
    los, B = component_labels(tmp_path / "split" / "split.vdb")
    assert np.array_equal(low, los) and A.shape == B.shape
    return mw, ms, A, B


def test_components_on_bricks_on_dask_match_the_unsplit_run(tmp_path, cluster):
    assert cluster.workers == 2
    mw, ms, A, B = run_pair(tmp_path, cluster, 24)  # 24 voxels: planes at cells 8, 32, 56 of 65
    cw, cs = mw["components"], ms["components"]
    assert cs["count"] == cw["count"] == 3  # the rod runs through the torus tube
    assert cw["labelling"] == {"bricked": False}
    lab = cs["labelling"]
    assert lab["bricked"] and lab["bricks"] == 64 and lab["cross_face_unions"] > 0
    comp_stats = next(s for s in ms["stages"] if s["name"] == "components")["stats"]
    assert comp_stats["bricked"]["bricks"] == 64
    np.testing.assert_allclose(cs["volumes"], cw["volumes"], rtol=0, atol=1e-12)
    active = (A != 0) | (B != 0)
    assert np.array_equal(A != 0, B != 0)  # same active voxels
    pairs = set(zip(A[active].tolist(), B[active].tolist(), strict=True))
    assert len(pairs) == cw["count"] == len({a for a, _ in pairs}) == len({b for _, b in pairs})
    assert np.array_equal(A, B)  # and in fact the same numbers: scan order on both sides


def test_components_on_bricks_on_the_process_pool(tmp_path):
    ex = LocalExecutor(2)
    try:
        mw, ms, A, B = run_pair(tmp_path, ex, 32)
    finally:
        ex.close()
    assert ms["components"]["labelling"]["bricks"] == 27  # 65 voxels a side: planes at cells 32, 64
    assert ms["components"]["count"] == mw["components"]["count"] and np.array_equal(A, B)
