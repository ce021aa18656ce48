"""ParaView (pvpython, offscreen through Xvfb) opens the .vti, .vtp and .pvd and contours them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from clientlib import HERE, foreground_fraction, require, run, with_display

SPHERE_BOUNDS = [-0.85, 0.85, -0.4, 0.45, -0.4, 0.4]  # union of the two spheres


@pytest.fixture(scope="module")
def paraview(outputs: dict) -> dict:
    out = outputs["dir"]
    run(with_display([require("pvpython"), str(HERE / "pv_script.py"), str(out), str(out / "pv.json")]), out)
    return json.loads((out / "pv.json").read_text())


def test_vti_arrays_and_geometry(paraview: dict, outputs: dict) -> None:
    vti = paraview["vti"]
    assert vti["arrays"] == sorted(outputs["grids"])
    assert vti["color_components"] == 3
    assert vti["dimensions"] == outputs["vti"]["dimensions"] == [49, 49, 49]
    assert vti["points"] == 49**3
    assert vti["origin"] == pytest.approx(outputs["vti"]["origin"])
    assert vti["spacing"] == pytest.approx([outputs["voxel"]] * 3)


def test_contour_of_frep_finds_both_spheres(paraview: dict, outputs: dict) -> None:
    contour = paraview["contour"]
    assert contour["points"] > 1000
    assert contour["bounds"] == pytest.approx(SPHERE_BOUNDS, abs=0.5 * outputs["voxel"])
    assert foreground_fraction(outputs["dir"] / "pv_contour.png") > 0.05


def test_vtp_mesh_with_normals_and_labels(paraview: dict, outputs: dict) -> None:
    vtp, mesh = paraview["vtp"], outputs["mesh"]
    assert vtp["points"] == len(mesh.points) and vtp["cells"] == len(mesh.triangles)
    assert "Normals" in vtp["point_arrays"] and vtp["cell_arrays"] == ["component"]
    assert vtp["component_range"] == [1.0, 2.0]
    assert vtp["bounds"] == pytest.approx(SPHERE_BOUNDS, abs=0.5 * outputs["voxel"])


def test_pvd_series_times_and_growth(paraview: dict) -> None:
    pvd = paraview["pvd"]
    assert pvd["times"] == [0.0, 1.0, 2.0] and pvd["arrays"] == ["frep"]
    xmax = np.array([c["bounds"][1] for c in pvd["contours"]])
    assert xmax == pytest.approx([0.85, 0.90, 0.95], abs=0.01)  # frame t grows the spheres by 0.05 t
