"""``frepvdb convert`` (mesh -> .vdb -> mesh, vdb_tool-style options) and ``run --set`` overrides."""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np
import pytest
import trimesh

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb


@pytest.fixture(scope="module")
def torus(tmp_path_factory):
    """A closed torus mesh: 64 x 40 sections = 5,120 faces."""
    path = tmp_path_factory.mktemp("mesh") / "torus.stl"
    m = trimesh.creation.torus(0.6, 0.25, major_sections=64, minor_sections=40)
    assert len(m.faces) == 5120 and m.is_watertight
    m.export(str(path))
    return path, float(m.volume)


def round_trip(tmp_path, mesh_path, *opts: str, grid_expect: tuple = ("frep",)) -> trimesh.Trimesh:
    out = tmp_path / "part.vdb"
    assert main(["convert", str(mesh_path), str(out), *opts]) == 0
    grids = {g.name: g for g in vdb.readAll(str(out))[0]}
    assert set(grids) == set(grid_expect)
    assert not list(tmp_path.glob(".frepvdb-convert-*"))  # the work folder is gone
    back = tmp_path / "back.stl"
    assert main(["convert", str(out), str(back)]) == 0
    m = trimesh.load(str(back))
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    return m


def test_mesh_to_vdb_to_mesh_keeps_the_volume(tmp_path, torus) -> None:
    """5k faces at 64 voxels across (the 256^3 check is the slow test below): the frep grid and the
    --surface level set both mesh back closed with the mesh's volume within 1%."""
    path, volume = torus
    m = round_trip(tmp_path, path, "--resolution", "64", "--band", "2", "--surface",
                   grid_expect=("frep", "surface"))
    assert m.volume == pytest.approx(volume, rel=0.01)  # meshed from 'surface' (the default)
    g = vdb.read(str(tmp_path / "part.vdb"), "frep")
    h = 1.7 / 64  # the torus is 1.7 wide
    assert g.transform.voxelSize()[0] == pytest.approx(h)
    lo, hi = g.evalActiveVoxelBoundingBox()
    # the padded domain holds the band: it reaches ceil(band) - 1 = 1 voxel beyond the sign change
    # (the torus's rim lies on a voxel centre, -32 h: the band's outermost voxel is -33 h)
    assert all(lo[i] * h < -0.85 - 0.5 * h for i in (0, 1))
    s = vdb.read(str(tmp_path / "part.vdb"), "surface")
    assert str(s.gridClass) == "level set"
    assert s.getConstAccessor().getValue((0, round(0.6 / h), 0)) < 0  # inside the tube: negative
    assert main(["convert", str(tmp_path / "part.vdb"), str(tmp_path / "frep.3mf"), "--grid", "frep"]) == 0
    with zipfile.ZipFile(tmp_path / "frep.3mf") as z:
        assert "3D/3dmodel.model" in z.namelist()
    assert main(["convert", str(tmp_path / "part.vdb"), str(tmp_path / "frep.ply"), "--grid", "frep"]) == 0
    f = trimesh.load(str(tmp_path / "frep.ply"))
    assert f.is_watertight and f.volume == pytest.approx(volume, rel=0.01)
    assert main(["convert", str(tmp_path / "part.vdb"), str(tmp_path / "x.stl"), "--grid", "nope"]) == 2


def test_convert_config_is_a_job_like_a_config_would_be(tmp_path) -> None:
    """The options land in the job: rfunc and method on the mesh node, band on voxelise, the
    domain padded by 10% of the longest side plus the band."""
    import argparse

    from pipeline.cli import convert_config

    args = argparse.Namespace(input=tmp_path / "a.stl", voxel_size=None, resolution=100, band=4.0, rfunc="r0",
                              method="adf", surface=True)
    cfg = convert_config(args, ([0, 0, 0], [2, 1, 1]))
    assert cfg["model"] == {"mesh": {"path": str((tmp_path / "a.stl").resolve()), "method": "adf", "rfunc": "r0"}}
    assert cfg["domain"]["voxel_size"] == pytest.approx(0.02)
    assert cfg["domain"]["bounds"][0] == pytest.approx([-0.3] * 3)  # 0.1 * 2 + (4 + 1) * 0.02
    assert [next(iter(st)) for st in cfg["stages"]] == ["voxelise", "hfrep", "export"]
    assert cfg["stages"][0]["voxelise"]["band"] == 4.0
    assert cfg["stages"][2]["export"]["grids"] == ["frep", "surface"]


@pytest.mark.skipif(not os.environ.get("FREPVDB_SLOW"), reason="256^3 round trip (~1-2 min): set FREPVDB_SLOW=1")
def test_round_trip_5k_faces_at_256(tmp_path, torus) -> None:
    path, volume = torus
    m = round_trip(tmp_path, path, "--resolution", "256", "--surface", grid_expect=("frep", "surface"))
    assert m.volume == pytest.approx(volume, rel=0.01)


@pytest.mark.parametrize("args, message", [
    (["missing.stl", "x.vdb"], "missing.stl: mesh file not found"),
    (["{mesh}", "x.stl"], "a mesh converts to a .vdb file"),
    (["{mesh}", "x.vdb", "--voxel-size", "-1"], "--voxel-size must be a finite number > 0"),
    (["{mesh}", "x.vdb", "--band", "nan"], "--band must be a finite number > 0"),
    (["{mesh}", "x.vdb", "--resolution", "0"], "--resolution must be > 0"),
    (["{open}", "x.vdb"], "mesh is not closed (not watertight), so its field has no inside; set allow_open: true "
                          "(frepvdb convert: --allow-open)"),
    (["{notvdb}", "x.stl"], "does not open as a .vdb"),
    (["x.txt", "x.vdb"], "cannot convert '.txt'"),
])
def test_bad_input_is_exit_2_with_one_line(tmp_path, torus, capsys, args, message) -> None:
    open_mesh = trimesh.creation.box()
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) > 0)
    open_mesh.export(str(tmp_path / "open.off"))
    (tmp_path / "bad.vdb").write_bytes(b"not a vdb")
    subs = {"{mesh}": str(torus[0]), "{open}": str(tmp_path / "open.off"), "{notvdb}": str(tmp_path / "bad.vdb")}
    argv = [subs.get(a, str(tmp_path / a) if a.startswith(("missing", "x.")) else a) for a in args]
    assert main(["convert", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_allow_open_converts_an_open_mesh_with_a_warning(tmp_path, capsys) -> None:
    """The flag the refusal names: the open box converts, with the mesh's warning in the output."""
    open_mesh = trimesh.creation.box()
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) > 0)
    open_mesh.export(str(tmp_path / "open.off"))
    assert main(["convert", str(tmp_path / "open.off"), str(tmp_path / "o.vdb"), "--resolution", "32",
                 "--allow-open"]) == 0
    out = capsys.readouterr()
    assert "not closed" in out.err, out
    g = vdb.read(str(tmp_path / "o.vdb"), "frep")
    assert g.activeVoxelCount() > 0


def test_vdb_without_a_field_is_refused(tmp_path, capsys) -> None:
    g = vdb.BoolGrid()
    g.name = "mask"
    vdb.write(str(tmp_path / "m.vdb"), grids=[g])
    assert main(["convert", str(tmp_path / "m.vdb"), str(tmp_path / "m.stl")]) == 2
    assert "no grid to mesh" in capsys.readouterr().err


CFG = """name: part
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], voxel_size: 0.1}
model: {sphere: {radius: 0.5}}
stages:
  - voxelise: {band: 3}
  - export: {vdb: true, report: false}
"""


def test_run_set_overrides(tmp_path, capsys) -> None:
    cfg = tmp_path / "part.yaml"
    cfg.write_text(CFG)
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out), "--set", "domain.resolution=40",
                 "--set", "stages[0].voxelise.band=1.5"]) == 0
    m = json.loads((out / "part" / "manifest.json").read_text())
    assert m["domain"]["voxel_size"] == pytest.approx(0.05)  # resolution replaced voxel_size
    assert m["stages"][0]["params"]["band"] == 1.5
    assert main(["validate", str(cfg), "--set", "model.sphere.radius=0.7"]) == 0
    assert "radius: 0.7" in capsys.readouterr().out


@pytest.mark.parametrize("opt, message", [
    ("stages[0].voxelise.band=100", "--set stages[0].voxelise.band=100: must be <= 64"),
    ("stages[0].voxelise.bnd=4", "--set stages[0].voxelise.bnd=4: unknown key 'bnd' (did you mean 'band'?)"),
    ("stages[3].voxelise.band=4", "--set stages[3].voxelise.band=4: stages[3]: index out of range"),
    ("domain.resolution=abc", "--set domain.resolution=abc: must be a valid integer"),
    ("domain.resolution", "--set domain.resolution: expected KEY.PATH=VALUE"),
    ("model.sphere.radius=[1", "--set model.sphere.radius=[1: value is not valid YAML"),
])
def test_bad_set_names_the_option(tmp_path, capsys, opt, message) -> None:
    cfg = tmp_path / "part.yaml"
    cfg.write_text(CFG)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out"), "--set", opt]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert not (tmp_path / "out" / "part").exists()


def test_help_describes_convert_and_set(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "convert" in text and "--set" in text and "import frepvdb" in text
    with pytest.raises(SystemExit):
        main(["convert", "--help"])
    text = capsys.readouterr().out
    for opt in ("--voxel-size", "--resolution", "--band", "--rfunc", "--method", "--surface", "--allow-open"):
        assert opt in text


def test_convert_reads_the_mesh_once(tmp_path, torus, monkeypatch) -> None:
    """The bounds and the job's mesh node come from one reading and check of the file (6 s of
    a 1.3M-face mesh's 45 s conversion was the second); a later load reads the file again."""
    from pipeline.mesh import meshio

    reads = []
    real = meshio._read
    monkeypatch.setattr(meshio, "_read", lambda p: reads.append(p) or real(p))
    assert main(["convert", str(torus[0]), str(tmp_path / "t.vdb"), "--resolution", "32"]) == 0
    assert len(reads) == 1
    meshio.load_mesh(torus[0])
    assert len(reads) == 2
