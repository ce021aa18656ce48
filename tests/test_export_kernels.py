"""The export stage's compiled kernels (pipeline.io.meshkernels) against the NumPy code they
replaced, and the files written with them read back against the grids: the merged mesh is the
same mesh (vertex for vertex, up to the order of the vertices), normals and labels the same
values, the .vti every strided value of every grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import vtk
from vtk.util import numpy_support as nps

from pipeline.io import meshkernels, vtkio
from pipeline.io.vdbgrids import linear_transform, vdb
from tests.test_export_files import VOXEL, sample_grids


# --- the NumPy code the kernels replaced (pipeline/io/vtkio.py before session 7) ----------------
def _ref_face_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    p = points.astype(np.float64)
    a = p[tris[:, 0]]
    return np.cross(p[tris[:, 1]] - a, p[tris[:, 2]] - a)


def _ref_weld(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points = np.ascontiguousarray(points, dtype=np.float32)
    rows = points.view(np.dtype((np.void, 12))).reshape(-1)
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    uniq = points[first]
    t = inverse.reshape(-1)[tris]
    t = t[np.abs(_ref_face_normals(uniq, t)).max(axis=1) > 0.0]
    used = np.unique(t)
    remap = np.full(len(uniq), -1, np.int64)
    remap[used] = np.arange(len(used))
    return uniq[used], remap[t]


def _ref_vertex_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    face = _ref_face_normals(points, tris)
    corners = tris.reshape(-1)
    acc = np.stack([np.bincount(corners, np.repeat(face[:, c], 3), minlength=len(points)) for c in range(3)], 1)
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    return (acc / np.where(length > 0, length, 1.0)).astype(np.float32)


def _canonical(points: np.ndarray, tris: np.ndarray, *per_point: np.ndarray) -> list[np.ndarray]:
    """Points sorted by their bytes, triangles renumbered, rotated to start at their smallest
    index (orientation kept) and sorted; per-point arrays in the points' order."""
    key = np.ascontiguousarray(points).view(np.dtype((np.void, points.itemsize * 3))).reshape(-1)
    order = np.argsort(key, kind="stable")
    rank = np.empty(len(points), np.int64)
    rank[order] = np.arange(len(points))
    t = rank[tris]
    r = np.argmin(t, axis=1)
    t = np.stack([t[np.arange(len(t)), (r + k) % 3] for k in range(3)], axis=1)
    t = t[np.lexsort(t.T[::-1])]
    return [points[order], t, *(a[order] for a in per_point)]


def _soup(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points on a coarse lattice (many exact repeats, -0.0 beside 0.0) and triangles over them,
    some with a repeated corner, some collinear (zero area, distinct corners)."""
    rng = np.random.default_rng(seed)
    pts = (rng.integers(-3, 4, size=(3000, 3)) * 0.25).astype(np.float32)
    pts[rng.random(len(pts)) < 0.05, 0] = np.float32(-0.0)
    tris = rng.integers(0, len(pts), size=(4000, 3))
    tris[:200, 2] = tris[:200, 0]  # repeated corner
    line = rng.integers(0, len(pts), size=200)
    pts[line] = [0.5, 0.5, 0.5]
    tris[200:400] = np.stack([line, line[::-1], line], axis=1)  # coincident after merging
    return pts, tris


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weld_is_the_unique_sort_weld(seed: int) -> None:
    pts, tris = _soup(seed)
    got_p, got_t = vtkio.weld(pts, tris)
    ref_p, ref_t = _ref_weld(pts, tris)
    assert got_p.dtype == np.float32 and got_t.dtype == np.int64
    assert len(got_p) == len(ref_p) and len(got_t) == len(ref_t) and len(ref_t) < len(tris) - 200
    for a, b in zip(_canonical(got_p, got_t), _canonical(ref_p, ref_t), strict=True):
        np.testing.assert_array_equal(a, b)
    # -0.0 and 0.0 stay distinct, as np.unique on the bytes kept them
    zero_x = got_p[got_p[:, 0] == 0.0]
    assert np.signbit(zero_x[:, 0]).any() and (~np.signbit(zero_x[:, 0])).any()


def test_weld_keeps_first_occurrence_order_and_empty_input() -> None:
    pts = np.array([[1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1], [0, 1, 0]], np.float32)
    p, t = vtkio.weld(pts, np.array([[0, 1, 3], [2, 4, 3], [0, 2, 1]]))
    np.testing.assert_array_equal(p, pts[[0, 1, 3]])
    np.testing.assert_array_equal(t, [[0, 1, 2], [0, 1, 2]])  # the third has a repeated corner
    p, t = vtkio.weld(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    assert p.shape == (0, 3) and t.shape == (0, 3)


def test_normals_equal_the_numpy_formulas() -> None:
    pts, tris = _soup(4)
    pts += np.random.default_rng(5).normal(0.0, 0.01, pts.shape).astype(np.float32)
    np.testing.assert_array_equal(vtkio.face_normals(pts, tris), _ref_face_normals(pts, tris))
    np.testing.assert_array_equal(vtkio.vertex_normals(pts, tris), _ref_vertex_normals(pts, tris))


def test_split_polygons_and_centroid_voxels() -> None:
    rng = np.random.default_rng(6)
    tris = rng.integers(0, 100, size=(7, 3)).astype(np.uint32)
    quads = rng.integers(0, 100, size=(11, 4)).astype(np.uint32)
    q = quads.astype(np.int64)
    want = np.concatenate([tris.astype(np.int64), q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    np.testing.assert_array_equal(meshkernels.split_polygons(tris, quads, False), want)
    np.testing.assert_array_equal(meshkernels.split_polygons(tris, quads, True), want[:, ::-1])
    pts = rng.normal(0.0, 1.0, (100, 3)).astype(np.float32)
    t = rng.integers(0, 100, size=(5000, 3))
    ref = np.rint(pts[t].astype(np.float64).mean(axis=1) / 0.013).astype(np.int64)
    np.testing.assert_array_equal(meshkernels.centroid_voxels(pts, t, 0.013), ref)


def _shell_grid() -> vdb.FloatGrid:
    """Values -1, 0 and +1 at random (-1 on the border): the zero set passes exactly through
    voxel centres, where volumeToMesh emits coincident vertices and zero-area triangles."""
    rng = np.random.default_rng(11)
    arr = rng.choice(np.array([-1.0, 0.0, 1.0], np.float32), size=(12, 12, 12), p=[0.4, 0.3, 0.3])
    arr = np.pad(arr.astype(np.float32)[1:-1, 1:-1, 1:-1], 1, constant_values=-1.0)
    g = vdb.FloatGrid(-1.0)
    g.name = "hfrep"
    g.transform = linear_transform(0.1)
    g.copyFromArray(arr, (0, 0, 0))
    return g


@pytest.mark.parametrize("source", ["surface", "frep", "density", "shell"])
def test_extracted_mesh_is_the_numpy_pipeline_mesh(source: str) -> None:
    """The whole extract_surface (split, flip, weld, normals) against the NumPy steps."""
    grids = {"hfrep": _shell_grid()} if source == "shell" else sample_grids()
    name = "hfrep" if source == "shell" else source
    voxel = 0.1 if source == "shell" else VOXEL
    m = vtkio.extract_surface(grids, voxel, source=name)
    g = grids[name]
    pts, tr, qu = g.convertToPolygons(isovalue=m.isovalue, adaptivity=0.0)
    qu = np.asarray(qu, np.int64).reshape(-1, 4)
    t = np.concatenate([np.asarray(tr, np.int64).reshape(-1, 3), qu[:, [0, 1, 2]], qu[:, [0, 2, 3]]])
    if vtkio._needs_flip(name, g):
        t = t[:, ::-1]
    rp, rt = _ref_weld(np.asarray(pts, np.float32), t)
    if source == "shell":
        assert len(rp) < len(pts) and len(rt) < len(t)  # the case has points to merge, triangles to drop
    for a, b in zip(_canonical(m.points, m.triangles, m.normals), _canonical(rp, rt, _ref_vertex_normals(rp, rt)),
                    strict=True):
        np.testing.assert_array_equal(a, b)


# --- reading grids ------------------------------------------------------------------------------
def test_sample_values_far_apart_points_use_the_sorting_path() -> None:
    """Points whose 32^3 chunks span more than MAX_CHUNK_GROUPS (the comparison-sort path) read
    what an accessor reads."""
    g = vdb.FloatGrid(-4.0)
    acc = g.getAccessor()
    rng = np.random.default_rng(7)
    pts = np.concatenate([rng.integers(-300_000, 300_000, size=(400, 3)), rng.integers(-20, 20, size=(400, 3))])
    for v, (i, j, k) in enumerate(pts[::3].tolist()):
        acc.setValueOn((i, j, k), float(v))
    chunks = (pts >> vtkio.CHUNK_LOG2).max(axis=0) - (pts >> vtkio.CHUNK_LOG2).min(axis=0) + 1
    assert np.prod(chunks.astype(float)) > vtkio.MAX_CHUNK_GROUPS
    one = g.getConstAccessor()
    want = np.array([one.getValue(tuple(int(c) for c in p)) for p in pts], np.float32)
    np.testing.assert_array_equal(vtkio.sample_values(g, pts), want)


def test_read_dense_into_a_buffer_overwrites_every_value() -> None:
    g = sample_grids()["frep"]
    buf = np.full((9, 1, 40), np.nan, np.float32)
    vtkio.read_dense(g, (-30, 0, -20), (9, 1, 40), out=buf)
    np.testing.assert_array_equal(buf, vtkio.read_dense(g, (-30, 0, -20), (9, 1, 40)))
    assert np.isfinite(buf).all()
    with pytest.raises(ValueError, match="C-contiguous float32"):
        vtkio.read_dense(g, (0, 0, 0), (9, 1, 40), out=np.zeros((9, 1, 40), np.float64))


@pytest.mark.parametrize("max_points", [10**9, 20_000, 4_000])
def test_vti_holds_every_strided_value(tmp_path: Path, max_points: int) -> None:
    """Every point array of the .vti read back equals the grid's value (copyToArray of the whole
    box, the reference) at every strided voxel, Vec3S included."""
    grids = sample_grids()
    rng = np.random.default_rng(8)  # no symmetry: a transposed or mirrored plane shows
    noise = vdb.FloatGrid(0.5)
    noise.name = "noise"
    noise.copyFromArray(rng.random((30, 41, 23), np.float32), (-20, -17, -9))
    rgb = vdb.Vec3SGrid((0.0, 0.0, 0.0))
    rgb.name = "rgb"
    rgb.copyFromArray(rng.random((19, 13, 33, 3), np.float32), (-5, 3, -20))
    grids |= {"noise": noise, "rgb": rgb}
    info = vtkio.write_vti(tmp_path / "s.vti", grids, VOXEL, max_points=max_points)
    reader = vtk.vtkXMLImageDataReader()
    reader.SetFileName(str(tmp_path / "s.vti"))
    reader.Update()
    image = reader.GetOutput()
    head = (tmp_path / "s.vti").read_bytes()[:4096]
    assert b'<AppendedData encoding="raw">' in head and b'compressor="vtkLZ4DataCompressor"' in head
    lo, hi = vtkio.union_active_bbox(grids.values())
    s = info["stride"]
    assert s == vtkio.vti_stride(hi - lo + 1, max_points) and (s > 1) == (max_points < 10**6)
    for name, grid in grids.items():
        full = vtkio.read_dense(grid, lo, hi - lo + 1)[::s, ::s, ::s]
        want = np.moveaxis(full, (0, 1, 2), (2, 1, 0)).reshape((-1, 3) if full.ndim == 4 else -1)
        got = nps.vtk_to_numpy(image.GetPointData().GetArray(name))
        np.testing.assert_array_equal(got, want)


# --- the surface picture ------------------------------------------------------------------------
def _square(x0: float, y0: float, size: float, z: float, facing_viewer: bool = True) -> tuple:
    pts = np.array([[x0, y0, z], [x0 + size, y0, z], [x0 + size, y0 + size, z], [x0, y0 + size, z]], np.float32)
    tris = np.array([[0, 1, 2], [0, 2, 3]]) if facing_viewer else np.array([[0, 2, 1], [0, 3, 2]])
    return pts, tris


def test_raster_surface_depth_coverage_and_shading() -> None:
    """Three squares seen along -z: the nearer one wins wherever both cover a pixel centre, whatever
    the drawing order; a face turned away is not drawn; colour = palette x (0.25 + 0.75 n.light)."""
    parts = [_square(0.5, 0.5, 1.0, 0.5), _square(0.0, 0.0, 1.0, 0.0), _square(-1.0, -1.0, 4.0, 1.0, False)]
    pts = np.concatenate([p for p, _ in parts])
    tris = np.concatenate([t + 4 * n for n, (_, t) in enumerate(parts)])
    labels = np.array([2, 2, 1, 1, 3, 3], np.int32)
    palette = np.eye(3)
    light = np.array([0.0, 0.6, 0.8])
    img = meshkernels.raster_surface(pts, tris, labels, palette, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                                     np.array([0, 0, 1.0]), light, 0.0, 0.0, 10.0, 17, 16)
    assert img.shape == (16, 17, 4)
    c = (np.arange(17) + 0.5) / 10.0  # pixel centres (x by column, y by row)
    r = (np.arange(16) + 0.5) / 10.0
    in_near = ((r[:, None] >= 0.5) & (r[:, None] <= 1.5)) & ((c[None] >= 0.5) & (c[None] <= 1.5))
    in_far = ((r[:, None] <= 1.0) & (c[None] <= 1.0)) & ~in_near
    np.testing.assert_array_equal(img[..., 3], (in_near | in_far).astype(np.float32))
    shade = np.float32(0.25 + 0.75 * 0.8)
    np.testing.assert_allclose(img[in_near][:, :3], np.tile([0.0, shade, 0.0], (in_near.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(img[in_far][:, :3], np.tile([shade, 0.0, 0.0], (in_far.sum(), 1)), atol=1e-6)
    plain = meshkernels.raster_surface(pts, tris, np.zeros(0, np.int32), np.array([[0.5, 0.5, 0.5]]),
                                       np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]),
                                       light, 0.0, 0.0, 10.0, 17, 16)
    np.testing.assert_allclose(plain[in_near | in_far][:, :3], 0.5 * shade, atol=1e-6)


def test_raster_of_a_closed_mesh_has_no_holes() -> None:
    """The sphere meshes of the sample scene, seen from the preview's view: every pixel centre
    well inside a sphere's projected disc is covered, none well outside both."""
    from pipeline.io.previews import View

    grids = sample_grids()
    m = vtkio.extract_surface(grids, VOXEL)
    view = View.from_angles()
    scale = 200.0
    xy = view.project(m.points.astype(np.float64))
    lo = xy.min(axis=0)
    w, h = (int(np.ceil(e * scale)) + 1 for e in xy.max(axis=0) - lo)
    img = meshkernels.raster_surface(m.points, m.triangles, np.zeros(0, np.int32), np.ones((1, 3)), view.right,
                                     view.up, view.eye, view.light, float(lo[0]), float(lo[1]), scale, w, h)
    px = lo[0] + (np.arange(w) + 0.5) / scale
    py = lo[1] + (np.arange(h) + 0.5) / scale
    covered = img[..., 3] > 0
    near = np.zeros((h, w), bool)
    far = np.ones((h, w), bool)
    for centre, radius in (((-0.45, 0.0, 0.0), 0.4), ((0.5, 0.1, 0.0), 0.35)):
        cx, cy = view.project(np.array(centre))
        d = np.hypot(px[None] - cx, py[:, None] - cy)
        near |= d < radius - VOXEL
        far &= d > radius + VOXEL
    assert near.sum() > 1000 and covered[near].all() and not covered[far].any()


def test_polydata_keeps_its_arrays_alive_without_copies(tmp_path: Path) -> None:
    """mesh_polydata hands VTK the NumPy arrays without copying (numpy_to_vtk deep=False keeps a
    reference on the VTK buffer): the polydata still holds the mesh after every NumPy array of it
    is gone and the memory reused."""
    import gc

    m = vtkio.extract_surface(sample_grids(), VOXEL)
    want = (m.points.copy(), m.triangles.copy(), m.normals.copy(), m.labels.copy())
    poly = vtkio.mesh_polydata(vtkio.SurfaceMesh(m.points.copy(), m.triangles.copy(), m.normals.copy(),
                                                 m.source, m.isovalue, m.labels.copy()))
    del m
    gc.collect()
    junk = [np.full(n, -7, np.int64) for n in (10, 1000, 100_000, 1_000_000) for _ in range(8)]
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(tmp_path / "p.vtp"))
    writer.SetInputData(poly)
    assert writer.Write() == 1 and len(junk) == 32
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(tmp_path / "p.vtp"))
    reader.Update()
    back = reader.GetOutput()
    np.testing.assert_array_equal(nps.vtk_to_numpy(back.GetPoints().GetData()), want[0])
    np.testing.assert_array_equal(nps.vtk_to_numpy(back.GetPolys().GetConnectivityArray()).reshape(-1, 3), want[1])
    np.testing.assert_array_equal(nps.vtk_to_numpy(back.GetPolys().GetOffsetsArray()), np.arange(0, 3 * len(want[1]) + 1, 3))
    np.testing.assert_array_equal(nps.vtk_to_numpy(back.GetPointData().GetNormals()), want[2])
    np.testing.assert_array_equal(nps.vtk_to_numpy(back.GetCellData().GetArray("component")), want[3])


def _ref_merge(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """pipeline.io.meshout._merge before session 7: np.unique over the float64 rows."""
    uniq, inverse = np.unique(points, axis=0, return_inverse=True)
    t = inverse.reshape(-1)[tris]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    used, remap = np.unique(t, return_inverse=True)
    return uniq[used], remap.reshape(-1, 3)


@pytest.mark.parametrize("float32_points", [True, False])
def test_printable_mesh_merge_is_the_unique_sort_merge(float32_points: bool) -> None:
    """meshout._merge (hash table for float32 points, np.unique otherwise) against np.unique:
    equal coordinates merged (-0.0 with 0.0), triangles with a repeated vertex dropped, collinear
    ones with three distinct vertices kept."""
    from pipeline.io import meshout

    pts, tris = _soup(9)
    pts = pts.astype(np.float64)
    if not float32_points:
        pts[::7] += 1e-12  # not float32 values: the np.unique path
    got = meshout._merge(pts, tris)
    ref_v, ref_t = _ref_merge(pts, tris)
    assert len(got.vertices) == len(ref_v) < len(pts) and len(got.triangles) == len(ref_t)
    assert got.vertices.dtype == np.float64 and got.triangles.dtype == np.int64
    for a, b in zip(_canonical(got.vertices + 0.0, got.triangles), _canonical(ref_v + 0.0, ref_t), strict=True):
        np.testing.assert_array_equal(a, b)
    zeros = got.vertices[got.vertices[:, 0] == 0.0]
    assert len(np.unique(zeros, axis=0)) == len(zeros)  # no point left twice as 0.0 and -0.0
