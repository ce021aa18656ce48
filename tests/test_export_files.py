"""Round trips of every export file: .vdb through pyopenvdb, VTK files through VTK's readers,
previews as images, report.html as text, `describe_vdb` output.

The scene: two spheres on a 49^3 voxel domain, built directly with pyopenvdb, with every grid
the pipeline writes (frep, surface, hfrep, density, component, color), so expected values are
known analytically. ``sample_grids`` is also used by tests/clients.
"""

from __future__ import annotations

import base64
import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import vtk
from vtk.util import numpy_support as nps

from pipeline.io import previews, report, vtkio
from pipeline.io.vdbgrids import grid_stats, linear_transform, vdb
from pipeline.io.vdbinfo import describe_vdb
from pipeline.io.vdbio import metadata_value, set_grid_metadata, write_vdb

VOXEL = 0.05
HALF = 24  # index domain [-HALF, HALF]^3
SPHERES = (((-0.45, 0.0, 0.0), 0.4), ((0.5, 0.1, 0.0), 0.35))
BAND = 3
SPHERE_VOLUME = sum(4.0 / 3.0 * np.pi * r**3 for _, r in SPHERES)


def sphere_fields(voxel: float = VOXEL, half: int = HALF) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (negative inside) to the two spheres, and the label (1, 2) of the nearer one."""
    idx = np.arange(-half, half + 1)
    p = np.stack(np.meshgrid(idx, idx, idx, indexing="ij"), axis=-1) * voxel
    dists = [np.linalg.norm(p - np.array(c), axis=-1) - r for c, r in SPHERES]
    return np.minimum(*dists), np.where(dists[0] < dists[1], 1.0, 2.0)


def _grid(arr: np.ndarray, background, name: str, voxel: float, half: int, grid_type=vdb.FloatGrid):
    grid = grid_type(background)
    grid.name = name
    grid.transform = linear_transform(voxel)
    grid.copyFromArray(np.ascontiguousarray(arr), (-half, -half, -half))
    return grid


def sample_grids(voxel: float = VOXEL, half: int = HALF) -> dict:
    """Every grid the pipeline writes, in the SPEC's conventions, for the two-sphere scene."""
    d, label = sphere_fields(voxel, half)
    bg = BAND * voxel
    band = np.abs(d) < bg
    surface = _grid(np.where(band, d, bg).astype(np.float32), bg, "surface", voxel, half)
    surface.signedFloodFill()
    surface.gridClass = vdb.GridClass.LEVEL_SET
    frep = surface.deepCopy()  # FRep: negated, inactive inside +bg, outside -bg
    frep.name = "frep"
    vdb.ax("@frep = -@frep;", frep)
    frep.background = -bg
    frep.gridClass = vdb.GridClass.UNKNOWN
    hfrep = _grid((-d).astype(np.float32), -10.0, "hfrep", voxel, half)
    density = _grid(np.clip(0.5 - d / (2 * bg), 0.0, 1.0).astype(np.float32), 0.0, "density", voxel, half)
    density.gridClass = vdb.GridClass.FOG_VOLUME
    component = _grid(np.where(band, label, 0.0).astype(np.float32), 0.0, "component", voxel, half)
    rgb = np.where((label == 1)[..., None], [1.0, 0.2, 0.1], [0.1, 0.3, 1.0])
    rgb = np.where(band[..., None], rgb, 0.0).astype(np.float32)
    color = _grid(rgb, (0.0, 0.0, 0.0), "color", voxel, half, vdb.Vec3SGrid)
    return {g.name: g for g in (frep, surface, hfrep, density, component, color)}


def sample_manifest(grids: dict, voxel: float = VOXEL) -> dict:
    """A manifest with the SPEC's keys for the sample grids."""
    return {
        "name": "spheres", "config": "configs/spheres.yaml", "config_sha256": "ab" * 32,
        "domain": {"bounds": [[-1.2] * 3, [1.2] * 3], "voxel_size": voxel},
        "outputs": [{"path": "spheres.vdb", "kind": "vdb"}, {"path": "spheres.vti", "kind": "vti"}],
        "grids": {n: grid_stats(g, voxel) for n, g in grids.items()},
        "stages": [{"name": "voxelise", "seconds": 1.25, "stats": {"voxels_evaluated": 8827}},
                   {"name": "components", "seconds": 0.5, "stats": {"count": 2}}],
        "components": {"count": 2, "volumes": [0.268, 0.180]},
        "quality": {"surface": {"grad_norm_mean": 0.9987, "grad_norm_p99": 1.0421}},
        "warnings": ["hfrep: 12 voxels near the medial axis clamped"],
    }


@pytest.fixture(scope="module")
def grids() -> dict:
    return sample_grids()


@pytest.fixture(scope="module")
def mesh(grids: dict) -> vtkio.SurfaceMesh:
    return vtkio.extract_surface(grids, VOXEL)


def expected_frep(ijk: tuple[int, int, int]) -> float:
    p = np.array(ijk) * VOXEL
    return -min(np.linalg.norm(p - np.array(c)) - r for c, r in SPHERES)


def band_voxel() -> tuple[int, int, int]:
    """A voxel in the narrow band of sphere 1: x = -0.75 is 0.1 inside its surface (bg = 0.15)."""
    return (-15, 0, 0)


def _read(reader_cls, path: Path):
    reader = reader_cls()
    reader.SetFileName(str(path))
    reader.Update()
    return reader.GetOutput()


def _no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.startswith(".")]


# --- .vdb ------------------------------------------------------------------------------------
def test_vdb_round_trip_names_classes_values_metadata(grids: dict, tmp_path: Path) -> None:
    for g in grids.values():
        set_grid_metadata(g, {"config_name": "spheres", "config_hash": "ab" * 32,
                              "stage": {"band": 3, "rfunc": "r0"}, "bounds_min": [-1.2, -1.2, -1.2]})
    set_grid_metadata(grids["component"], {"count": 2, "volumes": [0.268, 0.180]})
    path = write_vdb(tmp_path / "spheres.vdb", list(grids.values()), {"config": "spheres.yaml", "n": 2})
    read, file_meta = vdb.readAll(str(path))
    back = {g.name: g for g in read}
    assert sorted(back) == sorted(grids)
    assert file_meta["config"] == "spheres.yaml" and file_meta["n"] == 2
    assert back["surface"].gridClass == "level set"
    assert back["density"].gridClass == "fog volume"
    assert back["frep"].gridClass == "unknown"
    assert back["color"].valueTypeName == "vec3s"
    for name, g in grids.items():
        assert back[name].activeVoxelCount() == g.activeVoxelCount()
    ijk = band_voxel()
    acc = back["frep"].getConstAccessor()
    assert acc.getValue(ijk) == pytest.approx(expected_frep(ijk), abs=1e-6)
    assert acc.isValueOn(ijk)
    assert acc.getValue((-9, 0, 0)) == pytest.approx(BAND * VOXEL)  # centre of sphere 1: inactive +bg
    assert not acc.isValueOn((-9, 0, 0))
    assert acc.getValue((HALF, HALF, HALF)) == pytest.approx(-BAND * VOXEL)  # far outside: -bg
    assert back["surface"].getConstAccessor().getValue(ijk) == pytest.approx(-expected_frep(ijk), abs=1e-6)
    assert back["component"].getConstAccessor().getValue(ijk) == 1.0
    assert back["color"].getConstAccessor().getValue(ijk) == pytest.approx((1.0, 0.2, 0.1))
    meta = back["component"].metadata
    assert meta["count"] == 2 and json.loads(meta["volumes"]) == [0.268, 0.18]
    assert json.loads(back["frep"]["stage"]) == {"band": 3, "rfunc": "r0"}
    assert back["frep"]["bounds_min"] == pytest.approx((-1.2, -1.2, -1.2))
    assert _no_temp_files(tmp_path)


def test_vdb_half_float_per_grid(grids: dict, tmp_path: Path) -> None:
    path = write_vdb(tmp_path / "h.vdb", [grids["surface"], grids["frep"]], {}, half_float={"surface"})
    assert not grids["surface"].saveFloatAsHalf  # the caller's grid is left as it was
    meta = {m["name"]: m for m in vdb.readAllGridMetadata(str(path))}
    assert meta["surface"]["is_saved_as_half_float"] is True
    assert meta["frep"]["is_saved_as_half_float"] is False
    back = vdb.read(str(path), "surface").getConstAccessor()
    ijk = band_voxel()
    assert back.getValue(ijk) == pytest.approx(-expected_frep(ijk), rel=1e-3)  # half: 11-bit mantissa


def test_vdb_failed_write_leaves_previous_file(grids: dict, tmp_path: Path) -> None:
    path = write_vdb(tmp_path / "c.vdb", [grids["component"]])
    before = path.read_bytes()
    big = grids["component"].deepCopy()
    big.fill((0, 0, 0), (0, 0, 0), 5000.0, True)
    with pytest.raises(ValueError, match="half precision"):
        write_vdb(path, [big], half_float=True)
    assert path.read_bytes() == before
    assert _no_temp_files(tmp_path)
    with pytest.raises(ValueError, match="unique"):
        write_vdb(tmp_path / "d.vdb", [grids["frep"], grids["frep"]])
    assert not (tmp_path / "d.vdb").exists()


@pytest.fixture(params=["thread", "fork"])
def beside(request, monkeypatch) -> str:
    """write_vdb_beside's two ways: a thread through the compiled writer (where it is built),
    a forked child through pyopenvdb."""
    from pipeline.io import vdbgrids

    if request.param == "fork":
        monkeypatch.setattr(vdbgrids, "_leafbuild", None)
    elif vdbgrids._leafbuild is None:
        pytest.skip("the compiled writer is not built (tests/test_leafbuild.py says why)")
    return request.param


def test_vdb_written_beside_is_the_same_file(grids: dict, tmp_path: Path, beside: str) -> None:
    """write_vdb_beside (a thread or a forked child writes while this process goes on): the same
    grids, values, classes, half-float flags and file metadata as write_vdb, the caller's flags
    left as they were, no temp file."""
    from pipeline.io.vdbio import PendingWrite, ThreadedWrite, write_vdb_beside

    names = list(grids)
    pending = write_vdb_beside(tmp_path / "b.vdb", list(grids.values()), {"config": "x", "n": 2},
                               half_float={"surface"})
    assert isinstance(pending, ThreadedWrite if beside == "thread" else PendingWrite)
    assert not grids["surface"].saveFloatAsHalf  # the thread writes copies that carry the flags
    assert pending.wait() == tmp_path / "b.vdb" and not grids["surface"].saveFloatAsHalf
    write_vdb(tmp_path / "a.vdb", list(grids.values()), {"config": "x", "n": 2}, half_float={"surface"})
    (ga, ma), (gb, mb) = vdb.readAll(str(tmp_path / "a.vdb")), vdb.readAll(str(tmp_path / "b.vdb"))
    assert sorted(g.name for g in gb) == sorted(names) and [g.name for g in ga] == [g.name for g in gb]
    assert ma == mb
    for x, y in zip(ga, gb, strict=True):
        assert x.activeVoxelCount() == y.activeVoxelCount() and x.gridClass == y.gridClass
        assert dict(x.metadata) == dict(y.metadata)
        lo, hi = x.evalActiveVoxelBoundingBox()
        shape = tuple(int(b - a + 1) for a, b in zip(lo, hi, strict=True)) + ((3,) if x.valueTypeName == "vec3s" else ())
        ax, ay = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        x.copyToArray(ax, ijk=lo)
        y.copyToArray(ay, ijk=lo)
        assert np.array_equal(ax, ay), x.name
    meta = {m["name"]: m for m in vdb.readAllGridMetadata(str(tmp_path / "b.vdb"))}
    assert meta["surface"]["is_saved_as_half_float"] and not meta["frep"]["is_saved_as_half_float"]
    assert _no_temp_files(tmp_path)


def test_vdb_written_by_a_thread_reports_its_error(grids: dict, tmp_path: Path, beside: str) -> None:
    """Both ways: an OS error comes back from wait() as an OSError with its errno, bad arguments
    are refused at once. The thread's cancel() lets the write end without a file in place; an
    error of the compiled writer itself is a RuntimeError with OpenVDB's message."""
    import errno

    from pipeline.io.vdbgrids import _leafbuild
    from pipeline.io.vdbio import write_vdb_beside

    (tmp_path / "file").write_text("not a folder")
    pending = write_vdb_beside(tmp_path / "file" / "x.vdb", [grids["frep"]])
    with pytest.raises(OSError) as err:
        pending.wait()
    assert err.value.errno in (errno.EEXIST, errno.ENOTDIR)
    with pytest.raises(ValueError, match="unique"):
        write_vdb_beside(tmp_path / "d.vdb", [grids["frep"], grids["frep"]])
    pending = write_vdb_beside(tmp_path / "c.vdb", list(grids.values()))
    pending.cancel()
    pending.cancel()  # once is enough; a second call does nothing
    assert not (tmp_path / "c.vdb").exists() and _no_temp_files(tmp_path)
    if beside == "thread":
        with pytest.raises(RuntimeError, match="no_such_folder"):
            _leafbuild.write_file([grids["frep"]], str(tmp_path / "no_such_folder" / "y.vdb"), {}, [False])
        with pytest.raises(ValueError, match="not a FloatGrid"):
            _leafbuild.write_file([1], str(tmp_path / "z.vdb"), {}, [False])


def test_vdb_written_beside_reports_the_childs_error(grids: dict, tmp_path: Path, monkeypatch) -> None:
    """The forked child (no compiled writer; its OS errors and bad arguments: the test above): a
    child killed without a word comes back as an OSError (EIO, with the signal and the file);
    cancel() kills and reaps a child that is still writing, and no file appears."""
    import errno
    import os
    import signal
    import time

    from pipeline.io import vdbgrids, vdbio
    from pipeline.io.vdbio import write_vdb_beside

    monkeypatch.setattr(vdbgrids, "_leafbuild", None)
    slow = vdbio._write_now

    def stalled(*args):  # the forked child inherits this: it is still writing when killed
        time.sleep(60)
        slow(*args)

    monkeypatch.setattr(vdbio, "_write_now", stalled)
    pending = write_vdb_beside(tmp_path / "k.vdb", list(grids.values()))
    os.kill(pending._pid, signal.SIGKILL)  # as the OOM killer would: no report on the pipe
    with pytest.raises(OSError, match="killed by signal 9") as err:
        pending.wait()
    assert err.value.errno == errno.EIO and err.value.filename == str(tmp_path / "k.vdb")
    t0 = time.perf_counter()
    pending = write_vdb_beside(tmp_path / "c.vdb", list(grids.values()))
    pending.cancel()
    pending.cancel()  # once is enough; a second call does nothing
    assert time.perf_counter() - t0 < 30 and not (tmp_path / "c.vdb").exists()


def test_cancelled_child_leaves_no_temporary_file(grids: dict, tmp_path: Path, monkeypatch) -> None:
    """A forked writer killed by cancel() after it made its temporary file: the file goes with
    it (a race: under load the child got that far, and CI found the file left behind)."""
    import time

    from pipeline.io import vdbgrids, vdbio
    from pipeline.io.vdbio import write_vdb_beside
    from pipeline.util.atomic import atomic_path

    monkeypatch.setattr(vdbgrids, "_leafbuild", None)

    def stuck(path, grids, meta, halves, tmp_name=None):  # the child: its temporary file, then no progress
        with atomic_path(path, tmp_name):
            time.sleep(60)

    monkeypatch.setattr(vdbio, "_write_now", stuck)
    pending = write_vdb_beside(tmp_path / "c.vdb", list(grids.values()))
    t0 = time.perf_counter()
    while _no_temp_files(tmp_path):
        assert time.perf_counter() - t0 < 30
        time.sleep(0.01)
    pending.cancel()
    assert not (tmp_path / "c.vdb").exists() and _no_temp_files(tmp_path)


def test_metadata_value_conversions() -> None:
    assert metadata_value(np.float32(1.5)) == 1.5 and isinstance(metadata_value(np.int64(3)), int)
    assert metadata_value((1, 2, 3)) == (1, 2, 3)
    assert metadata_value(np.array([0.5, 1.0, 2.0])) == (0.5, 1.0, 2.0)
    assert json.loads(metadata_value({"a": (1, 2), "b": None})) == {"a": [1, 2], "b": None}
    assert json.loads(metadata_value([1, 2])) == [1, 2]
    assert metadata_value(2**70) == str(2**70)
    assert metadata_value(True) is True


def test_describe_vdb(grids: dict, tmp_path: Path) -> None:
    set_grid_metadata(grids["surface"], {"config_name": "spheres"})
    path = write_vdb(tmp_path / "s.vdb", [grids["surface"], grids["color"]], {"config": "s.yaml"})
    text = describe_vdb(path)
    assert "grid 'surface'" in text and "grid 'color'" in text
    assert "level set" in text and "vec3s" in text
    n = grids["surface"].activeVoxelCount()
    assert re.search(rf"active voxels: {n}\b", text)
    assert "voxel size:    (0.05, 0.05, 0.05)" in text
    lo, hi = grids["surface"].evalActiveVoxelBoundingBox()
    assert f"index bbox:    ({lo[0]}, {lo[1]}, {lo[2]}) .. ({hi[0]}, {hi[1]}, {hi[2]})" in text
    assert f"world bbox:    ({lo[0] * VOXEL:.6g}," in text
    vmin, _ = grids["surface"].evalMinMax()
    assert f"active min:    {vmin:.6g}" in text
    assert "config_name: spheres" in text and "config: s.yaml" in text
    colour = text[text.index("grid 'color'"):]
    assert "active min:    (0.1, 0.2, 0.1)  (per component)" in colour
    assert "active max:    (1, 0.3, 1)  (per component)" in colour
    with pytest.raises(ValueError, match="no such file"):
        describe_vdb(tmp_path / "missing.vdb")
    bad = tmp_path / "bad.vdb"
    bad.write_bytes(b"not a vdb at all")
    with pytest.raises(ValueError, match="not a readable OpenVDB file"):
        describe_vdb(bad)


# --- .vti ------------------------------------------------------------------------------------
def test_vti_arrays_extent_and_values(grids: dict, tmp_path: Path) -> None:
    info = vtkio.write_vti(tmp_path / "s.vti", grids, VOXEL)
    image = _read(vtk.vtkXMLImageDataReader, tmp_path / "s.vti")
    pd = image.GetPointData()
    assert sorted(pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())) == sorted(grids)
    assert info["stride"] == 1
    assert image.GetDimensions() == (2 * HALF + 1,) * 3  # hfrep is active over the whole domain
    assert image.GetOrigin() == pytest.approx((-HALF * VOXEL,) * 3)
    assert image.GetSpacing() == pytest.approx((VOXEL,) * 3)
    assert pd.GetArray("color").GetNumberOfComponents() == 3
    for ijk in [band_voxel(), (10, 2, 0), (0, 0, 0), (-20, 17, 5)]:
        pid = image.FindPoint(*(np.array(ijk) * VOXEL))
        assert image.GetPoint(pid) == pytest.approx(tuple(np.array(ijk) * VOXEL))
        for name, grid in grids.items():
            want = grid.getConstAccessor().getValue(ijk)
            assert pd.GetArray(name).GetTuple(pid) == pytest.approx(np.atleast_1d(want), abs=1e-7)
    pid = image.FindPoint(*(np.array(band_voxel()) * VOXEL))
    assert pd.GetArray("hfrep").GetValue(pid) == pytest.approx(expected_frep(band_voxel()), abs=1e-6)


def test_vti_stride_keeps_world_positions(grids: dict, tmp_path: Path) -> None:
    info = vtkio.write_vti(tmp_path / "s.vti", grids, VOXEL, max_points=20_000)
    image = _read(vtk.vtkXMLImageDataReader, tmp_path / "s.vti")
    assert info["stride"] == 2 and image.GetNumberOfPoints() <= 20_000
    assert image.GetDimensions() == (25, 25, 25)
    assert image.GetSpacing() == pytest.approx((2 * VOXEL,) * 3)
    frep = nps.vtk_to_numpy(image.GetPointData().GetArray("frep")).reshape(25, 25, 25)  # [k, j, i]
    acc = grids["frep"].getConstAccessor()
    for m in [(0, 0, 0), (7, 12, 12), (24, 3, 19)]:
        ijk = tuple(-HALF + 2 * c for c in m)
        assert image.GetPoint(image.ComputePointId(m)) == pytest.approx(tuple(np.array(ijk) * VOXEL))
        assert frep[m[2], m[1], m[0]] == pytest.approx(acc.getValue(ijk))
    assert float(image.GetFieldData().GetArray("stride").GetValue(0)) == 2.0


@pytest.mark.parametrize("shape,limit", [((49, 49, 49), 20_000), ((1000, 10, 10), 999), ((7, 7, 7), 343)])
def test_vti_stride_is_smallest_that_fits(shape: tuple, limit: int) -> None:
    s = vtkio.vti_stride(shape, limit)
    assert np.prod([-(-n // s) for n in shape]) <= limit
    assert s == 1 or np.prod([-(-n // (s - 1)) for n in shape]) > limit


# --- surface mesh ----------------------------------------------------------------------------
@pytest.mark.parametrize("source", ["surface", "frep", "hfrep", "density"])
def test_mesh_is_outward_and_encloses_the_spheres(grids: dict, source: str) -> None:
    m = vtkio.extract_surface(grids, VOXEL, source=source)
    assert m.signed_volume == pytest.approx(SPHERE_VOLUME, rel=0.03)
    centres = np.array([SPHERES[0][0] if p[0] < 0 else SPHERES[1][0] for p in m.points])
    outward = np.einsum("ij,ij->i", m.normals, m.points - centres)
    assert (outward > 0).mean() > 0.999
    radius = np.linalg.norm(m.points - centres, axis=1)
    expect = np.where(m.points[:, 0] < 0, SPHERES[0][1], SPHERES[1][1])
    assert np.abs(radius - expect).max() < 0.5 * VOXEL


def test_vtp_normals_and_component_labels(mesh: vtkio.SurfaceMesh, tmp_path: Path) -> None:
    vtkio.write_vtp(tmp_path / "s.vtp", mesh)
    poly = _read(vtk.vtkXMLPolyDataReader, tmp_path / "s.vtp")
    assert poly.GetNumberOfPoints() == len(mesh.points) and poly.GetNumberOfPolys() == len(mesh.triangles)
    normals = nps.vtk_to_numpy(poly.GetPointData().GetNormals())
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    labels = nps.vtk_to_numpy(poly.GetCellData().GetArray("component"))
    centroid_x = nps.vtk_to_numpy(poly.GetPoints().GetData())[mesh.triangles].mean(axis=1)[:, 0]
    assert set(np.unique(labels)) == {1, 2}
    assert np.all(labels[centroid_x < -0.1] == 1) and np.all(labels[centroid_x > 0.1] == 2)


def test_ply_and_obj_hold_the_same_mesh(mesh: vtkio.SurfaceMesh, tmp_path: Path) -> None:
    vtkio.write_ply(tmp_path / "s.ply", mesh)
    vtkio.write_obj(tmp_path / "s.obj", mesh)
    for reader in (vtk.vtkPLYReader, vtk.vtkOBJReader):
        poly = _read(reader, tmp_path / ("s.ply" if reader is vtk.vtkPLYReader else "s.obj"))
        assert poly.GetNumberOfPoints() == len(mesh.points)
        assert poly.GetNumberOfCells() == len(mesh.triangles)
        pts = nps.vtk_to_numpy(poly.GetPoints().GetData())
        assert np.allclose(pts, mesh.points, atol=1e-6)
        cells = nps.vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        assert np.array_equal(cells, mesh.triangles)
    assert _no_temp_files(tmp_path)


# --- .vtu ------------------------------------------------------------------------------------
def test_vtu_hexahedra_over_active_voxels(grids: dict, tmp_path: Path) -> None:
    sub = {k: grids[k] for k in ("frep", "component", "color")}
    info = vtkio.write_vtu(tmp_path / "s.vtu", sub, VOXEL)
    ug = _read(vtk.vtkXMLUnstructuredGridReader, tmp_path / "s.vtu")
    n = grids["frep"].activeVoxelCount()  # component and color share frep's band topology
    assert info["cells"] == n and ug.GetNumberOfCells() == n
    assert set(np.unique(nps.vtk_to_numpy(ug.GetCellTypes()))) == {vtk.VTK_HEXAHEDRON}
    cd = ug.GetCellData()
    assert {cd.GetArrayName(i) for i in range(cd.GetNumberOfArrays())} == {
        "frep", "component", "color", "active_frep", "active_component", "active_color"}
    assert nps.vtk_to_numpy(cd.GetArray("active_frep")).all()
    frep = nps.vtk_to_numpy(cd.GetArray("frep"))
    bounds = np.array([ug.GetCell(c).GetBounds() for c in range(0, n, 97)])
    centres = np.round((bounds[:, 0::2] + bounds[:, 1::2]) / 2 / VOXEL).astype(int)
    assert np.allclose(bounds[:, 1::2] - bounds[:, 0::2], VOXEL, atol=1e-6)
    acc = grids["frep"].getConstAccessor()
    for row, ijk in zip(range(0, n, 97), centres, strict=True):
        assert frep[row] == pytest.approx(acc.getValue(tuple(int(c) for c in ijk)))
        assert acc.isValueOn(tuple(int(c) for c in ijk))
    volume = vtk.vtkMeshQuality()
    volume.SetInputData(ug)
    volume.SetHexQualityMeasureToVolume()
    volume.Update()
    vols = nps.vtk_to_numpy(volume.GetOutput().GetCellData().GetArray("Quality"))
    assert np.allclose(vols, VOXEL**3, rtol=1e-4)  # correctly ordered hexahedra have +volume


def test_vtu_union_topology_and_limit(grids: dict, tmp_path: Path) -> None:
    sub = {k: grids[k] for k in ("frep", "density")}
    info = vtkio.write_vtu(tmp_path / "u.vtu", sub, VOXEL)
    ug = _read(vtk.vtkXMLUnstructuredGridReader, tmp_path / "u.vtu")
    active = nps.vtk_to_numpy(ug.GetCellData().GetArray("active_frep")).astype(bool)
    assert info["cells"] >= grids["density"].activeVoxelCount()
    assert active.sum() == grids["frep"].activeVoxelCount()
    inactive_frep = nps.vtk_to_numpy(ug.GetCellData().GetArray("frep"))[~active]
    assert np.all(np.isclose(np.abs(inactive_frep), BAND * VOXEL))  # +-bg where frep is inactive
    with pytest.raises(ValueError, match="max_cells"):
        vtkio.write_vtu(tmp_path / "big.vtu", sub, VOXEL, max_cells=1000)
    assert not (tmp_path / "big.vtu").exists()


def test_pvd_frames_resolve(grids: dict, tmp_path: Path) -> None:
    frames = []
    for t in range(3):
        vtkio.write_vti(tmp_path / f"f{t}.vti", {"frep": grids["frep"]}, VOXEL)
        frames.append((0.5 * t, tmp_path / f"f{t}.vti" if t else f"f{t}.vti"))
    vtkio.write_pvd(tmp_path / "series.pvd", frames)
    root = ET.parse(tmp_path / "series.pvd").getroot()
    sets = root.findall("./Collection/DataSet")
    assert root.get("type") == "Collection"
    assert [float(d.get("timestep")) for d in sets] == [0.0, 0.5, 1.0]
    assert [d.get("file") for d in sets] == ["f0.vti", "f1.vti", "f2.vti"]
    for d in sets:
        image = _read(vtk.vtkXMLImageDataReader, tmp_path / d.get("file"))
        assert image.GetPointData().GetArray("frep") is not None


def test_failed_vtk_write_keeps_previous_file(grids: dict, tmp_path: Path) -> None:
    path = tmp_path / "s.vti"
    vtkio.write_vti(path, {"frep": grids["frep"]}, VOXEL)
    before = path.read_bytes()
    with pytest.raises(ValueError, match="no grid has active voxels"):
        vtkio.write_vti(path, {"empty": vdb.FloatGrid()}, VOXEL)
    assert path.read_bytes() == before and _no_temp_files(tmp_path)


# --- previews and report ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def preview_paths(grids: dict, mesh: vtkio.SurfaceMesh, tmp_path_factory) -> list[Path]:
    out = tmp_path_factory.mktemp("run") / "previews"
    return previews.write_previews(out, grids, VOXEL, mesh=mesh)


def test_previews_exist_sized_and_not_blank(grids: dict, preview_paths: list[Path]) -> None:
    names = {p.name for p in preview_paths}
    assert names == {f"slices_{n}.png" for n in grids} | {previews.SURFACE_PNG}
    for path in preview_paths:
        img = mpimg.imread(path)[..., :3]
        h, w = img.shape[:2]
        assert (w, h) == ((1500, 520) if path.name.startswith("slices_") else (800, 700))
        packed = (np.round(img * 255).astype(np.uint32) * [65536, 256, 1]).sum(axis=2)
        assert len(np.unique(packed)) > 50  # many distinct colours
        assert img.std() > 0.05
    frep = mpimg.imread(preview_paths[0].parent / "slices_frep.png")[..., :3]
    assert (frep.max(axis=2) < 0.1).mean() > 0.002  # the black zero contour is drawn
    hfrep = mpimg.imread(preview_paths[0].parent / "slices_hfrep.png")[..., :3]
    red = (hfrep[..., 0] > 0.6) & (hfrep[..., 2] < 0.45)
    assert red.mean() > 0.01  # inside is visibly red although the background is -10
    surface = mpimg.imread(preview_paths[0].parent / previews.SURFACE_PNG)[..., :3]
    blue = (surface[..., 2] > surface[..., 0] + 0.1).mean()
    orange = (surface[..., 0] > surface[..., 2] + 0.2).mean()
    assert blue > 0.02 and orange > 0.02  # both components coloured


@pytest.mark.parametrize("order", ["as given", "reversed"])
def test_each_slice_picture_is_what_a_fresh_figure_draws(grids: dict, order: str) -> None:
    """The slice sheet draws its axes once and each grid over them: every grid's picture, drawn
    after the others on the shared sheet, is pixel for pixel the picture of a sheet made for it
    alone (nothing of an earlier grid's colour bar, contours or image is left, no panel moves)."""
    box = vtkio.union_active_bbox(grids.values())
    assert box is not None
    lo, hi = box
    ref = previews.centre_slices(grids["frep"], lo, hi, VOXEL)
    names = list(grids) if order == "as given" else list(grids)[::-1]

    def picture(sheet: previews.SliceSheet, name: str) -> np.ndarray:
        sheet.draw(name, grids[name], previews.centre_slices(grids[name], lo, hi, VOXEL), ref, 0.0)
        out = sheet.rgb()
        sheet.clear()
        return out

    slices = previews.centre_slices(grids[names[0]], lo, hi, VOXEL)
    shared = previews.SliceSheet(slices, 100)
    kinds = set()
    for name in names:
        alone = picture(previews.SliceSheet(slices, 100), name)
        assert np.array_equal(picture(shared, name), alone), name
        kinds.add(previews._kind(name, grids[name], (0.0, 1.0) if previews.is_vector(grids[name])
                                 else previews.value_range(grids[name], slices)))
    assert kinds == {"signed", "sequential", "labels", "rgb"}  # every way a grid is drawn


def test_preview_file_names_are_safe() -> None:
    assert previews.safe_name("color") == "color" and previews.safe_name("a/b c") == "a_b_c"


def test_report_embeds_previews_and_tables(grids: dict, preview_paths: list[Path]) -> None:
    manifest = sample_manifest(grids)
    path = report.write_report(preview_paths[0].parent.parent / "report.html", manifest)
    text = path.read_text()
    uris = re.findall(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", text)
    assert len(uris) == len(preview_paths)
    assert base64.b64decode(uris[0]) == (preview_paths[0].parent / previews.SURFACE_PNG).read_bytes()
    for name in grids:
        assert f"<td>{name}</td>" in text
    assert "<td>voxelise</td>" in text and "voxels_evaluated=8827" in text
    assert str(grids["frep"].activeVoxelCount()) in text
    assert "count: <b>2</b>" in text and "0.268" in text
    assert "grad_norm_p99" in text and "1.0421" in text
    assert "12 voxels near the medial axis clamped" in text
    assert "spheres.vti" in text and "<h2>Field quality</h2>" in text
    assert "src='file:" not in text and "src=\"http" not in text  # self-contained


def test_write_vtk_outputs_names_and_entries(grids: dict, tmp_path: Path) -> None:
    entries, m = vtkio.write_vtk_outputs(tmp_path, "spheres", grids, VOXEL, kinds=["vti", "vtp", "ply", "obj"])
    assert [e["path"] for e in entries] == ["spheres.vti", "spheres.vtp", "spheres.ply", "spheres.obj"]
    assert [e["kind"] for e in entries] == ["vti", "vtp", "ply", "obj"]
    assert all((tmp_path / e["path"]).stat().st_size > 0 for e in entries)
    assert m is not None and m.source == "surface" and entries[1]["triangles"] == len(m.triangles)
    with pytest.raises(ValueError, match="unknown VTK output"):
        vtkio.write_vtk_outputs(tmp_path, "x", grids, VOXEL, kinds=["stl"])
    with pytest.raises(ValueError, match="no grid to mesh"):
        vtkio.write_vtk_outputs(tmp_path, "c", {"component": grids["component"]}, VOXEL, kinds=["vtp"])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(e["path"] for e in entries)


def test_sample_values_reads_leaves_tiles_and_background_exactly() -> None:
    """The chunked reader returns what OpenVDB stores (active and inactive voxels, a tile,
    the background), equal to the per-voxel sampler, for points across chunk borders."""
    from pipeline.io.vtkio import GridSampler, sample_values

    g = vdb.FloatGrid(-2.5)
    g.fill((0, 0, 0), (15, 15, 15), 7.0, True)  # whole leaves: tiles of 8^3
    acc = g.getAccessor()
    rng = np.random.default_rng(3)
    pts = rng.integers(-40, 72, size=(3000, 3))
    for v, (i, j, k) in enumerate(pts[:500].tolist()):
        acc.setValueOn((i, j, k), float(v))
    for i, j, k in pts[500:700].tolist():
        acc.setValueOff((i, j, k), 3.25)
    query = np.concatenate([pts, rng.integers(-64, 96, size=(5000, 3)), [[31, 31, 31], [32, 32, 32], [-1, -1, -1]]])
    expected, _ = GridSampler(g).sample(query)
    np.testing.assert_array_equal(sample_values(g, query), expected)
    one = g.getConstAccessor()
    assert all(sample_values(g, q[None])[0] == np.float32(one.getValue(tuple(int(c) for c in q))) for q in query[:300])
