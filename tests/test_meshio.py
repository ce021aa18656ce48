"""Mesh loading and checks (pipeline.mesh.meshio)."""

from __future__ import annotations

from pathlib import Path

import pytest
import trimesh

from pipeline.mesh.meshio import MeshError, load_mesh

MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("empty.off", ""),
        ("garbage.off", "this is not a mesh\n\x00\x01 at all\n"),
        ("nofaces.off", "OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n"),
        ("garbage.stl", "solid x\n facet nonsense\nendsolid\n"),
        ("empty.obj", "# nothing\n"),
    ],
)
def test_bad_files_raise_mesh_error_naming_file(tmp_path: Path, name: str, text: str) -> None:
    path = _write(tmp_path / name, text)
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    msg = str(info.value)
    assert name in msg
    assert "\n" not in msg
    assert isinstance(info.value, ValueError)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match="missing.off"):
        load_mesh(tmp_path / "missing.off")


def test_unsupported_suffix(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match=r"model\.xyz"):
        load_mesh(_write(tmp_path / "model.xyz", "1 2 3\n"))


def test_closed_box_report(tmp_path: Path) -> None:
    path = tmp_path / "box.stl"
    trimesh.creation.box((1, 2, 3)).export(path)
    mesh, rep = load_mesh(path)
    assert rep.watertight and rep.winding_consistent
    assert (rep.faces, rep.vertices, rep.components, rep.genus) == (12, 8, 1, [0])
    assert rep.degenerate_faces == 0
    assert rep.volume == pytest.approx(6.0)
    assert rep.warnings == []


def test_torus_genus_and_components(tmp_path: Path) -> None:
    torus = trimesh.creation.torus(1.0, 0.3)
    sphere = trimesh.creation.icosphere(1).apply_translation([5, 0, 0])
    path = tmp_path / "two.ply"
    trimesh.util.concatenate([torus, sphere]).export(path)
    _, rep = load_mesh(path)
    assert rep.components == 2
    assert sorted(rep.genus) == [0, 1]


def test_open_mesh_loads_with_warning(tmp_path: Path) -> None:
    box = trimesh.creation.box((1, 1, 1))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    path = tmp_path / "open.obj"
    open_box.export(path)
    mesh, rep = load_mesh(path)
    assert len(mesh.faces) == 10
    assert not rep.watertight
    assert any("not closed" in w and "open.obj" in w for w in rep.warnings)
    assert rep.genus == [0]


def test_inverted_mesh_warns(tmp_path: Path) -> None:
    box = trimesh.creation.box((1, 1, 1))
    inv = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    path = tmp_path / "inv.off"
    inv.export(path)
    _, rep = load_mesh(path)
    assert rep.volume < 0
    assert any("inwards" in w for w in rep.warnings)


@pytest.mark.realdata
def test_shared_open_cube_warns() -> None:
    path = MESHES / "open_cube.off"
    if not path.is_file():
        pytest.skip("shared meshes absent")
    _, rep = load_mesh(path)
    assert not rep.watertight
    assert any("not closed" in w for w in rep.warnings)


def test_plain_off_parse_is_trimeshs(tmp_path: Path) -> None:
    """meshio._plain_off (the bulk parser of plain triangle OFF files) gives trimesh's vertices and
    faces, blank lines and CRLF included; comments, polygons and bad indices go to trimesh."""
    import io

    import numpy as np

    from pipeline.mesh.meshio import _plain_off

    torus = trimesh.creation.torus(1.0, 0.3)
    text = trimesh.exchange.off.export_off(torus)
    lines = text.splitlines()
    variants = [text, "\r\n".join(lines), "\n\n".join(lines[:2]) + "\n\n" + "\n".join(lines[2:]) + "\n\n"]
    for v in variants:
        data = v.encode()
        ref = trimesh.load(io.BytesIO(data), file_type="off", force="mesh", process=False)
        got = _plain_off(data)
        assert got is not None
        np.testing.assert_array_equal(got[0], ref.vertices)
        np.testing.assert_array_equal(got[1], ref.faces)
    quad = "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    for other in ("# c\n" + text, quad, text.replace("\n3 0 ", "\n3 99999 ", 1)):
        assert _plain_off(other.encode()) is None
    path = tmp_path / "quad.off"
    path.write_text(quad)
    mesh, _ = load_mesh(path)
    assert len(mesh.faces) == 2
