"""Printable meshes (pipeline.io.meshout, export ``mesh:``): the written STL / 3MF / PLY / OBJ files
read back closed, consistently wound and outward, with the volume of the model and of the grid."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
import zipfile

import numpy as np
import pytest
import trimesh

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb

NS = {"m": "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"}


def read_3mf(path) -> list[trimesh.Trimesh]:
    """Each object of a 3MF file as a Trimesh (standard-library XML: trimesh's loader needs lxml)."""
    with zipfile.ZipFile(path) as z:
        assert {"[Content_Types].xml", "_rels/.rels", "3D/3dmodel.model"} <= set(z.namelist())
        root = ET.fromstring(z.read("3D/3dmodel.model"))
    out = []
    for obj in root.iterfind("m:resources/m:object", NS):
        v = [[float(e.get(k)) for k in "xyz"] for e in obj.iterfind("m:mesh/m:vertices/m:vertex", NS)]
        f = [[int(e.get(k)) for k in ("v1", "v2", "v3")] for e in obj.iterfind("m:mesh/m:triangles/m:triangle", NS)]
        out.append(trimesh.Trimesh(np.array(v), np.array(f), process=False))
    assert len(root.findall("m:build/m:item", NS)) == len(out)
    return out


def run_model(tmp_path, model: str, res: int = 128, extra: str = "", mesh: str = "[stl, 3mf, ply, obj]",
              per_component: bool = False):
    cfg = tmp_path / "part.yaml"
    cfg.write_text(f"name: part\ndomain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: {res}}}\n"
                   f"model: {model}\nstages:\n  - voxelise: {{band: 2}}\n{extra}"
                   f"  - export: {{mesh: {mesh}, mesh_per_component: {str(per_component).lower()}, report: false}}\n")
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    folder = tmp_path / "out" / "part"
    return folder, json.loads((folder / "manifest.json").read_text())


def grid_inside_volume(path, res: int) -> float:
    """Voxels with frep > 0 (band values and inside tiles), times the voxel volume."""
    g = vdb.read(str(path), "frep")
    h = 2.0 / res
    n = int(round(1.0 / h))
    a = np.zeros((2 * n + 1,) * 3, np.float32)
    g.copyToArray(a, (-n, -n, -n))
    return float(np.count_nonzero(a > 0)) * h**3


def check_closed(m: trimesh.Trimesh) -> None:
    m.merge_vertices()  # STL stores triangles without shared vertices
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # outward: the enclosed volume is positive


@pytest.mark.parametrize("model, volume", [
    ("{sphere: {radius: 0.8}}", 4 / 3 * math.pi * 0.8**3),
    ("{torus: {major: 0.6, minor: 0.25}}", 2 * math.pi**2 * 0.6 * 0.25**2),
])
def test_meshes_are_watertight_and_have_the_volume(tmp_path, model, volume) -> None:
    folder, manifest = run_model(tmp_path, model)
    grid_volume = grid_inside_volume(folder / "part.vdb", 128)
    assert grid_volume == pytest.approx(volume, rel=0.01)
    stl = trimesh.load(str(folder / "part_mesh.stl"))
    n = len(stl.faces)
    assert (folder / "part_mesh.stl").stat().st_size == 84 + 50 * n
    meshes = {"stl": stl, "ply": trimesh.load(str(folder / "part_mesh.ply")),
              "obj": trimesh.load(str(folder / "part_mesh.obj"), process=False),
              "3mf": read_3mf(folder / "part_mesh.3mf")[0]}
    for kind, m in meshes.items():
        check_closed(m)
        assert len(m.faces) == n, kind
        assert m.volume == pytest.approx(volume, rel=0.01), kind
        assert m.volume == pytest.approx(grid_volume, rel=0.01), kind
    kinds = {o["kind"]: o for o in manifest["outputs"]}
    assert {"stl", "3mf", "ply", "obj"} <= set(kinds)
    assert kinds["stl"]["open_edges"] == 0 and kinds["stl"]["triangles"] == n


def test_one_mesh_per_component(tmp_path) -> None:
    model = "{union: [{sphere: {center: [-0.5, 0, 0], radius: 0.3}}, {box: {min: [0.2, -0.3, -0.3], max: [0.8, 0.3, 0.3]}}]}"
    folder, manifest = run_model(tmp_path, model, res=64, extra="  - components: {}\n", mesh="[stl, 3mf]",
                                 per_component=True)
    parts = [trimesh.load(str(folder / f"part_mesh_{k}.stl")) for k in (1, 2)]
    for m in parts:
        check_closed(m)
    vols = sorted(m.volume for m in parts)
    assert vols[0] == pytest.approx(4 / 3 * math.pi * 0.3**3, rel=0.03)
    assert vols[1] == pytest.approx(0.6**3, rel=0.03)
    objects = read_3mf(folder / "part_mesh.3mf")
    assert len(objects) == 2
    for m in objects:
        check_closed(m)
    assert not (folder / "part_mesh_3.stl").exists()


def test_a_part_cut_by_the_domain_is_reported_open(tmp_path) -> None:
    folder, manifest = run_model(tmp_path, "{sphere: {radius: 1.2}}", res=32, mesh="[stl]")
    assert any("not closed" in w for w in manifest["warnings"])
    assert next(o for o in manifest["outputs"] if o["kind"] == "stl")["open_edges"] > 0


def test_verify_catches_truncated_stl_and_3mf(tmp_path) -> None:
    from pipeline.job.outputs import verify_outputs

    folder, manifest = run_model(tmp_path, "{sphere: {radius: 0.5}}", res=32, mesh="[stl, 3mf]")
    entries = [o for o in manifest["outputs"] if o["kind"] in ("stl", "3mf")]
    verify_outputs(folder, entries)
    for e in entries:
        p = folder / e["path"]
        p.write_bytes(p.read_bytes()[:-7])
        with pytest.raises(OSError, match="STL|3MF"):
            verify_outputs(folder, [e])


def test_zeros_at_voxel_centres_still_give_a_closed_mesh(tmp_path) -> None:
    """The torus's inner equator (radius 0.4) passes exactly through voxel centres at h = 0.02:
    volumeToMesh at isovalue 0 gave coincident distinct vertices there, which trimesh's welding
    turned into edges of four triangles; the nudged isovalue (meshout.ISO_NUDGE) does not."""
    import frepvdb as fv

    part = fv.torus(0.6, 0.2) - fv.box([-1, -0.05, -1], [1, 0.05, 1])
    part.save(tmp_path / "cut.stl", [[-1, -1, -1], [1, 1, 1]], voxel_size=0.02)
    m = trimesh.load(str(tmp_path / "cut.stl"))
    assert m.is_watertight and m.is_winding_consistent
    torus = 2 * math.pi**2 * 0.6 * 0.2**2
    slab = 2 * 0.1 * math.pi * 0.2**2  # the tube crosses the 0.1-wide slab twice
    assert m.volume == pytest.approx(torus - slab, rel=0.01)
