"""Blender imports the .vdb as a volume object (all grids listed and loaded) and the .ply/.obj meshes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from clientlib import HERE, require, run

MESH_BOUNDS = [[-0.85, -0.4, -0.4], [0.85, 0.45, 0.4]]


@pytest.fixture(scope="module")
def blender(outputs: dict) -> dict:
    out = outputs["dir"]
    files = [str(out / f"spheres.{ext}") for ext in ("vdb", "ply", "obj")]
    run([require("blender"), "-b", "--factory-startup", "--python", str(HERE / "blender_script.py"), "--",
         *files, str(out / "blender.json")], out)
    return json.loads((out / "blender.json").read_text())


def test_vdb_is_a_volume_with_every_grid(blender: dict, outputs: dict) -> None:
    vol = blender["volume"]
    assert vol["object_type"] == "VOLUME" and vol["loaded"] and vol["error"] == ""
    assert sorted(vol["grids"]) == sorted(outputs["grids"])
    assert all(g["loaded"] for g in vol["grids"].values())
    assert vol["grids"]["color"]["type"] == "VECTOR_FLOAT" and vol["grids"]["color"]["channels"] == 3
    assert vol["grids"]["surface"]["type"] == "FLOAT" and vol["grids"]["density"]["type"] == "FLOAT"


def test_volume_bounds_are_world_units(blender: dict) -> None:
    lo, hi = (np.array(b) for b in blender["volume"]["bounds"])
    # hfrep is active on the whole domain [-1.2, 1.2]^3; Blender's box is leaf-aligned (8 voxels)
    assert np.all(lo <= -1.2 + 1e-6) and np.all(lo >= -1.2 - 8 * 0.05 - 1e-6)
    assert np.all(hi >= 1.2 - 1e-6) and np.all(hi <= 1.2 + 8 * 0.05 + 1e-6)


@pytest.mark.parametrize("kind", ["ply", "obj"])
def test_mesh_imports_with_same_counts_and_position(blender: dict, outputs: dict, kind: str) -> None:
    mesh, got = outputs["mesh"], blender[kind]
    assert got["type"] == "MESH"
    assert got["vertices"] == len(mesh.points)
    assert got["polygons"] == got["triangles"] == len(mesh.triangles)
    assert np.allclose(got["bounds"], MESH_BOUNDS, atol=0.5 * outputs["voxel"])
