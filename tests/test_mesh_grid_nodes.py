"""The ``mesh`` and ``grid`` nodes inside model trees: values, signs and rigorous bounds."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb
from pipeline.oracles import REGISTRY


def node(kind, **params):
    cls = REGISTRY[kind]
    return cls(cls.Params.model_validate(params))


@pytest.fixture(scope="module")
def box_mesh(tmp_path_factory):
    path = tmp_path_factory.mktemp("m") / "box.off"
    trimesh.creation.box(extents=(1.0, 0.6, 0.4)).export(path)
    return path


@pytest.fixture(scope="module")
def sphere_vdb(tmp_path_factory):
    path = tmp_path_factory.mktemp("g") / "ls.vdb"
    g = vdb.createLevelSetSphere(radius=0.5, center=(0.1, 0, 0), voxelSize=0.02, halfWidth=3.0)
    g.name = "surface"
    vdb.write(str(path), grids=[g])
    return path


def test_mesh_node_sign_matches_containment(box_mesh):
    m = node("mesh", path=str(box_mesh), rfunc="r0")
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.8, 0.8, (3000, 3))
    inside = np.all(np.abs(pts) < [0.5, 0.3, 0.2], axis=1)
    v = m.evaluate(pts)
    assert np.all((v > 0) == inside)
    assert m.report.watertight and m.stats["planes"] == 6


@settings(max_examples=40, deadline=None)
@given(c=st.tuples(*[st.floats(-0.8, 0.6)] * 3), w=st.floats(0.01, 0.8), angle=st.floats(-180, 180))
def test_mesh_node_bound_encloses_under_rotation(box_mesh, c, w, angle):
    m = node("rotate", angle=angle, axis=(1, 1, 0), of=node("mesh", path=str(box_mesh), rfunc="sardf"))
    lo = np.array(c)
    hi = lo + w
    pts = lo + np.random.default_rng(1).random((300, 3)) * w
    flo, fhi = m.bound(lo[None], hi[None])
    v = m.evaluate(pts)
    assert v.min() >= flo[0] - 1e-12 and v.max() <= fhi[0] + 1e-12


def test_grid_node_reads_level_set_as_frep(sphere_vdb):
    g = node("grid", path=str(sphere_vdb))
    pts = np.array([[0.1, 0, 0], [0.1 + 0.45, 0, 0], [0.1 + 0.55, 0, 0], [2, 2, 2]])
    v = g.evaluate(pts)
    assert v[0] > 0 and v[1] == pytest.approx(0.05, abs=0.01) and v[2] == pytest.approx(-0.05, abs=0.01) and v[3] < 0


@settings(max_examples=40, deadline=None)
@given(c=st.tuples(*[st.floats(-0.7, 0.7)] * 3), w=st.floats(0.005, 0.6))
def test_grid_node_bound_encloses(sphere_vdb, c, w):
    g = node("grid", path=str(sphere_vdb))
    lo = np.array(c)
    pts = lo + np.random.default_rng(2).random((300, 3)) * w
    flo, fhi = g.bound(lo[None], (lo + w)[None])
    v = g.evaluate(pts)
    assert v.min() >= flo[0] - 1e-12 and v.max() <= fhi[0] + 1e-12


def test_grid_and_mesh_in_one_run(tmp_path, box_mesh, sphere_vdb, capsys):
    cfg = tmp_path / "mix.yaml"
    cfg.write_text(f"""name: mix
domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 64}}
model:
  union:
    - mesh: {{path: {box_mesh}}}
    - grid: {{path: {sphere_vdb}}}
stages:
  - voxelise: {{band: 3}}
  - export: {{vdb: true}}
""")
    assert main(["run", str(cfg), "--out", str(tmp_path / "o")]) == 0
    g = vdb.read(str(tmp_path / "o" / "mix" / "mix.vdb"), "frep")
    acc = g.getConstAccessor()
    h = g.transform.voxelSize()[0]
    assert acc.getValue((round(0.45 / h), 0, 0)) > 0  # inside the box
    assert acc.getValue((round(-0.9 / h), 0, 0)) < 0


@pytest.mark.parametrize("content, message", [
    (None, "mesh file not found"), ("OFF\n0 0 0\n", "no faces"), ("garbage", ""),
])
def test_bad_mesh_is_exit_2_with_line(tmp_path, capsys, content, message):
    mesh = tmp_path / "m.off"
    if content is not None:
        mesh.write_text(content)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"name: c\ndomain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 16}}\nmodel:\n"
                   f"  mesh: {{path: {mesh.name}}}\nstages:\n  - voxelise: {{}}\n")
    assert main(["run", str(cfg), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "c.yaml:4 model.mesh:" in err and "m.off" in err and message in err
    assert "Traceback" not in err and not (tmp_path / "o" / "c").exists()


def test_open_mesh_is_exit_2_unless_allowed(tmp_path, capsys):
    """SPEC: a mesh that is not closed is bad input; allow_open converts it with a warning."""
    m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    m.update_faces(np.arange(len(m.faces)) != 0)  # drop one triangle: a hole
    m.export(tmp_path / "open.off")
    text = ("name: o\ndomain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 24}\nmodel:\n"
            "  mesh: {path: open.off%s}\nstages:\n  - voxelise: {}\n")
    cfg = tmp_path / "o.yaml"
    cfg.write_text(text % "")
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "o.yaml:4 model.mesh:" in err and "open.off: mesh is not closed" in err and "allow_open" in err
    cfg.write_text(text % ", allow_open: true")
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    import json

    man = json.loads((tmp_path / "out" / "o" / "manifest.json").read_text())
    assert any("not closed" in w for w in man["warnings"]) and man["meshes"][0]["watertight"] is False


def test_slow_rfunc_on_a_large_mesh_is_warned_before_the_run(tmp_path, capsys) -> None:
    """r0 / sardf evaluate every BSP node at every voxel: a tree above SLOW_TREE nodes gets a
    warning on stderr before the run starts and in the manifest; min_max gets none."""
    import json

    import trimesh

    from pipeline.cli import main

    path = tmp_path / "ico.off"
    trimesh.creation.icosphere(4, 0.8).export(str(path))  # 5,120 faces: ~10k nodes
    for rfunc, warned in (("r0", True), ("min_max", False)):
        cfg = tmp_path / f"{rfunc}.yaml"
        cfg.write_text(f"name: {rfunc}\ndomain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 8}}\n"
                       f"model: {{mesh: {{path: {path}, rfunc: {rfunc}}}}}\nstages:\n  - voxelise: {{band: 3}}\n"
                       "  - export: {vdb: true}\n")
        assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
        err = capsys.readouterr().err
        manifest = json.loads((tmp_path / "out" / rfunc / "manifest.json").read_text())
        said = [w for w in manifest["warnings"] if "evaluates all" in w]
        assert bool(said) == warned and (f"rfunc {rfunc} evaluates all" in err) == warned, (err, said)


def test_loading_a_config_does_not_evaluate_the_mesh_for_nan(tmp_path, box_mesh, monkeypatch) -> None:
    """The NaN check of a config skips what cannot be NaN: a mesh's field (its whole BSP-tree
    per point: 11 s for a 1.3M-face mesh) and set operations of finite children. A formula
    beside the mesh is still evaluated, and a bad one is still named."""
    from pipeline.job.config import load_jobs
    from pipeline.oracles.mesh import Mesh

    def never(*args, **kwargs):
        raise AssertionError("the mesh was evaluated")

    monkeypatch.setattr(Mesh, "evaluate", never)
    monkeypatch.setattr(Mesh, "field", never)
    text = ("name: m\ndomain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 24}}\nmodel:\n  union:\n"
            "    - mesh: {{path: {mesh}, rfunc: min_max}}\n    - {other}\nstages:\n  - voxelise: {{}}\n")
    cfg = tmp_path / "m.yaml"
    cfg.write_text(text.format(mesh=box_mesh, other="sphere: {radius: 0.3}"))
    (job,) = load_jobs(cfg)
    assert job.model.kind == "union"
    cfg.write_text(text.format(mesh=box_mesh, other='expr: "log(x - 2)"'))
    with pytest.raises(Exception) as bad:
        load_jobs(cfg)
    assert "model.union[1].expr: the field is not a finite number" in str(bad.value)


def test_set_operations_are_finite_from_children_only_under_the_magnitude_control() -> None:
    """r0 of finite values overflows without the domain's magnitude control (a tree built in
    code): the NaN check then evaluates the set operation; min_max is always finite."""
    from pipeline.model.operations import Union

    s = node("sphere", radius=1.0)
    assert not Union(Union.Params.model_validate({"of": [s, s], "rfunc": "r0"})).finite_from_children
    assert Union(Union.Params.model_validate({"of": [s, s], "rfunc": "min_max"})).finite_from_children
    domain = type("D", (), {"bounds": ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))})()
    assert Union(Union.Params.model_validate({"of": [s, s], "rfunc": "r0"}), domain=domain).finite_from_children
