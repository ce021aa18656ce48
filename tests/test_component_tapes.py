"""Per-cell tapes in Algorithm 1's descent (components seed, section 4.1, on the compiled model):
a parent's tape shortened to its box gives the values of the whole tape there, to the bit; a
union of many parts is bounded and evaluated with a few parts per cell, and the octree's
count, volumes, labels and the written `component` grid are those of the descent over the
whole tape."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb
from pipeline.job.config import _Ctx, build_node
from pipeline.model.tape import TapePool, compile_model, evaluate_with
from pipeline.model.tape_affine import affine_bounds
from pipeline.topology import components as cc


def node(raw: dict):
    return build_node(raw, ("model",), _Ctx("test", raw, Path(".")))


def lattice(n: int, seed: int, r: tuple[float, float] = (0.03, 0.06)) -> dict:
    rng = np.random.default_rng(seed)
    c, rad = rng.uniform(-0.9, 0.9, (n, 3)), rng.uniform(*r, n)
    return {"union": [{"sphere": {"center": [float(v) for v in p], "radius": float(q)}} for p, q in zip(c, rad, strict=True)],
            "rfunc": "min_max"}


def mixed(seed: int) -> dict:
    """Unions, intersections and differences of spheres and boxes (min / max at every level)."""
    rng = np.random.default_rng(seed)

    def part(i):
        p = rng.uniform(-0.7, 0.7, 3)
        if i % 2:
            return {"sphere": {"center": p.tolist(), "radius": float(rng.uniform(0.1, 0.4))}}
        h = rng.uniform(0.05, 0.3, 3)
        return {"box": {"min": (p - h).tolist(), "max": (p + h).tolist()}}

    parts = [part(i) for i in range(int(rng.integers(3, 12)))]
    return {"difference": [{"union": parts[:-2]}, {"intersection": parts[-2:]}], "rfunc": "min_max"}


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), lattice_model=st.booleans(), width=st.floats(0.02, 0.8))
def test_shortened_tapes_give_the_whole_tapes_values_in_their_boxes(seed, lattice_model, width):
    """TapePool.specialised on boxes, then values at points of each closed box (corners
    included), by that box's tape: bit-identical to the whole tape; and the affine bounds of the
    shortened tapes over sub-boxes hold those values."""
    model = node(lattice(200, seed) if lattice_model else mixed(seed))
    tape = compile_model(model)
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-1, 1 - width, (40, 3))
    hi = lo + width
    short = TapePool.single(tape).specialised(np.zeros(len(lo), np.int64), lo, hi)
    u = rng.random((len(lo), 12, 3))
    u[:, :8] = cc._CORNERS  # the box's corners: a child's corner lies on its parent's boundary
    pts = (lo[:, None] + u * width).reshape(-1, 3)
    rows = np.repeat(np.arange(len(lo)), 12)
    got = short.evaluate(pts, rows)
    assert np.array_equal(got, evaluate_with(tape, pts), equal_nan=True)
    if lattice_model and width < 0.15:
        assert short.length.mean() < len(tape) / 4  # a lattice's small boxes hold a few of its spheres
    sub_lo = lo + 0.25 * width
    flo, fhi = affine_bounds(short, sub_lo, sub_lo + 0.5 * width, np.arange(len(lo)))
    inner = (sub_lo[:, None] + rng.random((len(lo), 6, 3)) * 0.5 * width)
    v = short.evaluate(inner.reshape(-1, 3), np.repeat(np.arange(len(lo)), 6)).reshape(len(lo), 6)
    assert np.all((flo[:, None] <= v) & (v <= fhi[:, None]))


def _untaped(monkeypatch):
    monkeypatch.setattr(cc.CellTapes, "start", classmethod(lambda cls, model, tape: None))


def test_lattice_descent_bounds_few_parts_per_cell_and_finds_the_same_components(monkeypatch):
    model = node(lattice(400, 7))
    lo, size, depth = np.full(3, -1.0), 2.0, 7
    found = cc.detect(model, lo, size, depth)
    levels = found.tree.stats["levels"]
    assert levels[0]["mean_tape"] == len(compile_model(model))
    assert levels[depth - 2]["mean_tape"] < len(compile_model(model)) / 50
    assert "mean_tape" not in levels[depth - 1]  # the finest cells' corners by their parents' tapes
    with monkeypatch.context() as mp:
        _untaped(mp)
        whole = cc.detect(model, lo, size, depth)
    assert "mean_tape" not in whole.tree.stats["levels"][0]
    assert found.count == whole.count > 50
    assert np.allclose(np.sort(found.volumes), np.sort(whole.volumes), rtol=1e-12)
    # fewer affine tests: the whole tree's affine union bounds reject no cell above the finest levels
    assert found.tree.stats["affine_tests"] < whole.tree.stats["affine_tests"]
    assert found.tree.stats["border_cells"] == whole.tree.stats["border_cells"]
    pts = np.random.default_rng(1).uniform(-1, 1, (20_000, 3))
    a, b = cc.point_labels(found, pts), cc.point_labels(whole, pts)
    assert np.array_equal(a > 0, b > 0)
    pairs = np.unique(np.stack([a[a > 0], b[a > 0]], 1), axis=0)  # one label to one label
    assert len(pairs) == len(np.unique(pairs[:, 0])) == len(np.unique(pairs[:, 1]))


def _run(tmp_path: Path, name: str) -> tuple[dict, dict]:
    raw = {"name": name, "domain": {"bounds": [[-1, -1, -1], [1, 1, 1]], "resolution": 96},
           "model": lattice(300, 3, (0.03, 0.08)),
           "stages": [{"voxelise": {"band": 3}}, {"components": {"separate": False}}, {"export": {"vdb": True}}]}
    tmp_path.mkdir()
    cfg = tmp_path / f"{name}.yaml"
    cfg.write_text(json.dumps(raw))
    assert main(["run", str(cfg), "--out", str(tmp_path / "out"), "--force"]) == 0
    comp = vdb.read(str(tmp_path / "out" / name / f"{name}.vdb"), "component")
    manifest = json.loads((tmp_path / "out" / name / "manifest.json").read_text())
    return _dense(comp), manifest["stages"][1]["stats"]


def _dense(grid) -> dict:
    """Every value of the active bounding box (inactive ones included), the active count and
    the background."""
    lo, hi = grid.evalActiveVoxelBoundingBox()
    arr = np.zeros(tuple(int(h - l + 1) for l, h in zip(lo, hi, strict=True)), np.float64)
    grid.copyToArray(arr, ijk=lo)
    return {"lo": tuple(lo), "values": arr, "active": int(grid.activeVoxelCount()), "background": grid.background}


def test_written_component_grid_of_a_lattice_equals_the_whole_tape_runs(tmp_path, monkeypatch):
    """What the user receives: the `component` grid read back from the .vdb, equal voxel for
    voxel (values, active count) to the one written by the descent over the whole tape."""
    got, st_got = _run(tmp_path / "a", "lat")
    with monkeypatch.context() as mp:
        _untaped(mp)
        ref, st_ref = _run(tmp_path / "b", "lat")
    assert st_got["count"] == st_ref["count"] > 10
    assert got["lo"] == ref["lo"] and got["active"] == ref["active"] and got["background"] == ref["background"]
    assert np.array_equal(got["values"], ref["values"])
    assert st_got["corner_evaluations"] < st_ref["corner_evaluations"]


@pytest.mark.parametrize("rfunc", ["r0", "sardf"])
def test_models_without_min_max_keep_the_whole_tape(rfunc):
    model = node({**lattice(5, 2), "rfunc": rfunc})
    assert not compile_model(model).shortens
    tree = cc.enumerate_octree(model, np.full(3, -1.0), 2.0, 5)
    assert all("mean_tape" not in lv for lv in tree.stats["levels"])


def test_short_tapes_are_not_shortened_further():
    """Below cc.SHORT_TAPE clauses deciding costs what it saves: a small CSG keeps its tape."""
    model = node({"union": [{"box": {"min": [-0.5, -0.5, -0.1], "max": [0.5, 0.5, 0.1]}},
                            {"sphere": {"center": [0.3, 0.3, 0.2], "radius": 0.3}}], "rfunc": "min_max"})
    tape = compile_model(model)
    assert tape.shortens and len(tape) < cc.SHORT_TAPE
    tree = cc.enumerate_octree(model, np.full(3, -1.0), 2.0, 6)
    assert all("mean_tape" not in lv for lv in tree.stats["levels"])


@pytest.mark.parametrize("rfunc", ["min_max", "r0"])
def test_mesh_cells_are_decided_by_the_surface(tmp_path, monkeypatch, rfunc):
    """A closed mesh's cells are decided by its surface (TapePool.surface_sides, as voxelise's
    descent does): a cell no triangle comes near takes the sign of one point. Every inside cell
    so kept is inside (the field positive on a 3^3 lattice of its box), the border
    cells, the count and the labels are those of the interval bounds alone, and fewer cells are
    visited (the bounds left cells well inside unproven down to the finest level)."""
    import trimesh

    torus = trimesh.creation.torus(major_radius=0.45, minor_radius=0.14, major_sections=48, minor_sections=24)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    ball.apply_translation([0.0, 0.0, 0.55])
    mesh = trimesh.util.concatenate([torus, ball])
    path = tmp_path / "parts.off"
    mesh.export(path)
    model = node({"mesh": {"path": str(path), "rfunc": rfunc}})
    origin, size, depth = np.array([-0.8, -0.8, -0.8]), 1.6, 7

    def cells(tree, kind):
        sel = tree.kind == kind
        return {(int(lv), *map(int, c)) for lv, c in zip(tree.level[sel], tree.coords[sel], strict=True)}

    found = cc.detect(model, origin, size, depth)
    with monkeypatch.context() as m:
        m.setattr(TapePool, "surface_sides", lambda self, lo, hi, tape_of=None: (np.zeros(len(lo), np.int8),
                                                                                   np.zeros(len(lo))))
        ref = cc.detect(model, origin, size, depth)
    st, st_ref = found.tree.stats, ref.tree.stats
    assert found.count == ref.count == 2
    assert st["surface_tests"] > 0 and st_ref["surface_tests"] == 0
    assert st["cells_visited"] < st_ref["cells_visited"]
    assert cells(found.tree, cc.BORDER) == cells(ref.tree, cc.BORDER)
    lo, hi = found.tree.boxes()
    inner = found.tree.kind == cc.INSIDE
    frac = np.stack(np.meshgrid(*[np.linspace(0.0, 1.0, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    probe = (lo[inner][:, None] + frac[None] * (hi - lo)[inner][:, None]).reshape(-1, 3)
    assert (model.evaluate(probe) > 0).all()  # the field's sign is containment (test_written_grids)
    pts = np.random.default_rng(0).uniform(-0.8, 0.8, (20000, 3))
    assert np.array_equal(cc.point_labels(found, pts), cc.point_labels(ref, pts))
    assert np.allclose(found.volumes, ref.volumes, rtol=1e-12)
