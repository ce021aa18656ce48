"""VTK and mesh files from pyopenvdb grids, written with VTK's own writers, each one atomically.

Conventions (see docs/outputs.md): voxel (i, j, k) has its centre at world (i, j, k) * voxel_size,
so a ``.vti`` point sits on a voxel centre and a ``.vtu`` hexahedron spans the voxel's cube
(centre +- voxel_size / 2). Grid values are read in bulk: dense boxes with ``copyToArray``
(C++) and the active voxels with pyopenvdb's value iterator, which costs O(active voxels).
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from vtkmodules.util import numpy_support as nps
from vtkmodules.vtkCommonCore import (
    VTK_FLOAT,
    VTK_ID_TYPE,
    VTK_INT,
    VTK_UNSIGNED_CHAR,
    vtkDataArray,
    vtkDoubleArray,
    vtkPoints,
)
from vtkmodules.vtkCommonDataModel import (
    VTK_HEXAHEDRON,
    vtkCellArray,
    vtkImageData,
    vtkPolyData,
    vtkUnstructuredGrid,
)
from vtkmodules.vtkIOCore import vtkWriter
from vtkmodules.vtkIOGeometry import vtkOBJWriter
from vtkmodules.vtkIOPLY import vtkPLYWriter
from vtkmodules.vtkIOXML import (
    vtkXMLImageDataWriter,
    vtkXMLPolyDataWriter,
    vtkXMLUnstructuredGridWriter,
    vtkXMLWriter,
)

from pipeline.io.meshkernels import (
    centroid_voxels,
    chunk_ids,
    face_normals_kernel,
    gather_chunk,
    group_boxes,
    group_by_id,
    split_polygons,
    unit_rows,
    vertex_normal_sums,
    weld_kernel,
)
from pipeline.io.vdbgrids import compiled_for
from pipeline.sparse.grid import pack_keys
from pipeline.util.atomic import atomic_path

DEFAULT_MAX_POINTS = 16_000_000  # .vti points before a stride is applied (64 MB per float array)
DENSE_FALLBACK = 8  # dense box read for inactive samples when the box is <= 8x their count
SURFACE_SOURCES = ("surface", "frep", "hfrep", "density")  # mesh source preference
_HEX = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.int64
)  # VTK_HEXAHEDRON corner order
_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], np.int64)

Grids = Mapping[str, Any]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N,3) arrays (explicit: several times faster than np.cross)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
                     a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def face_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unnormalised triangle normals (length = twice the area), float64: one compiled pass
    (the fancy-indexed NumPy version made five (M,3) temporaries)."""
    return face_normals_kernel(np.ascontiguousarray(points), np.ascontiguousarray(triangles, dtype=np.int64))


# --- reading grids in bulk ----------------------------------------------------------------
def is_vector(grid: Any) -> bool:
    """True for Vec3S grids (values are 3-tuples)."""
    return grid.valueTypeName.startswith("vec3")


def union_active_bbox(grids: Iterable[Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """Index-space (lo, hi) inclusive bounding box of the active voxels of all grids."""
    boxes = [g.evalActiveVoxelBoundingBox() for g in grids if g.activeVoxelCount() > 0]
    if not boxes:
        return None
    lo = np.min([b[0] for b in boxes], axis=0).astype(np.int64)
    hi = np.max([b[1] for b in boxes], axis=0).astype(np.int64)
    return lo, hi


def read_dense(grid: Any, lo: Iterable[int], shape: Iterable[int], out: np.ndarray | None = None) -> np.ndarray:
    """Values (active or not) of the box starting at voxel ``lo``: (nx, ny, nz) or (nx, ny, nz, 3).

    ``out`` (float32, C-contiguous, of that shape) is filled instead of a new array: ``copyToArray``
    writes every value of the box (leaf values, tile values, the background)."""
    shape = tuple(int(n) for n in shape) + ((3,) if is_vector(grid) else ())
    if out is None:
        out = np.zeros(shape, dtype=np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"read_dense: out must be C-contiguous float32 {shape}, got {out.dtype} {out.shape}")
    grid.copyToArray(out, tuple(int(c) for c in lo))
    return out


def active_voxels(grid: Any) -> tuple[np.ndarray, np.ndarray]:
    """(ijk (N,3) int64, values (N,) or (N,3) float32) of every active voxel; tiles expanded."""
    coords: list[tuple] = []
    values: list[Any] = []
    tiles: list[tuple] = []
    for item in grid.citerOnValues():
        if item.count == 1:
            coords.append(item.min)
            values.append(item.value)
        else:
            tiles.append((item.min, item.max, item.value))
    ijk = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    vals = np.asarray(values, dtype=np.float32).reshape((-1, 3) if is_vector(grid) else (-1,))
    for lo, hi, value in tiles:
        axes = [np.arange(a, b + 1, dtype=np.int64) for a, b in zip(lo, hi, strict=True)]
        box = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        ijk = np.concatenate([ijk, box])
        fill = np.broadcast_to(np.asarray(value, np.float32), (len(box),) + vals.shape[1:])
        vals = np.concatenate([vals, fill])
    return ijk, vals


CHUNK_LOG2 = 5  # sample_values reads 32^3 chunks: few copyToArray calls, small buffers
MAX_CHUNK_GROUPS = 1 << 24  # counting sort over the chunks' bounding box up to this many chunks


def sample_values(grid: Any, ijk: np.ndarray) -> np.ndarray:
    """Values of a scalar grid at integer voxels ``ijk`` (N,3), active or not, exactly as
    OpenVDB stores them (tiles, background).

    One ``copyToArray`` per 32^3 chunk the points touch: the cost follows the points, not the
    grid's active voxel count (a per-voxel iterator pass over 30 M voxels takes about a minute).
    The points are grouped by chunk with a counting sort over the chunks' bounding box (a
    comparison sort of every point's key when that box is huge); only the bounding box of a
    chunk's points is read (a few layers where a flat face crosses it), into one reused buffer.
    """
    ijk = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
    out = np.empty(len(ijk), np.float32)
    if len(ijk) == 0:
        return out
    if is_vector(grid):
        raise ValueError("sample_values reads scalar grids")
    reads = compiled_for(grid)
    if reads is not None:  # an accessor per point in C++, in parallel: no chunk reads
        reads.sample(grid, ijk, out)
        return out
    ids, _, dims = chunk_ids(ijk, CHUNK_LOG2)
    if math.prod(dims.tolist()) <= MAX_CHUNK_GROUPS:
        order, starts = group_by_id(ids, int(math.prod(dims.tolist())))
    else:
        keys = pack_keys(ijk >> CHUNK_LOG2)
        order = np.argsort(keys, kind="stable")
        sk = keys[order]
        starts = np.append(np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]]), len(sk))
    groups = np.flatnonzero(starts[1:] > starts[:-1])
    boxes = group_boxes(ijk, order, starts, groups)  # read only the points' box within each chunk
    flat = np.empty(1 << (3 * CHUNK_LOG2), np.float32)
    for g, (lo, hi) in zip(groups.tolist(), boxes.tolist(), strict=True):
        shape = (hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1)
        buf = flat[: shape[0] * shape[1] * shape[2]].reshape(shape)
        read_dense(grid, lo, shape, out=buf)
        gather_chunk(out, buf, ijk, order[starts[g]:starts[g + 1]], lo[0], lo[1], lo[2])
    return out


class GridSampler:
    """Vectorised lookup of a grid's values at integer voxel coordinates.

    Active voxels come from one pass of the value iterator (sorted packed keys, then
    ``searchsorted``); the few inactive coordinates fall back to an OpenVDB accessor, so tiles and
    the background are returned exactly as OpenVDB stores them.
    """

    def __init__(self, grid: Any) -> None:
        self.grid = grid
        ijk, vals = active_voxels(grid)
        keys = pack_keys(ijk) if len(ijk) else np.zeros(0, np.int64)
        order = np.argsort(keys)
        self.keys, self.values = keys[order], vals[order]
        self.active_ijk = ijk[order]

    def sample(self, ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values, active mask) at ``ijk`` (N,3)."""
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        q = pack_keys(ijk)
        pos = np.minimum(np.searchsorted(self.keys, q), max(len(self.keys) - 1, 0))
        found = self.keys[pos] == q if len(self.keys) else np.zeros(len(q), bool)
        out = np.empty((len(q),) + self.values.shape[1:], np.float32)
        out[found] = self.values[pos[found]]
        missing = np.flatnonzero(~found)
        if len(missing):
            out[missing] = self._inactive_values(ijk[missing])
        return out, found

    def _inactive_values(self, ijk: np.ndarray) -> np.ndarray:
        """Values at inactive voxels: one dense read when their box is compact, else an accessor."""
        lo, hi = ijk.min(axis=0), ijk.max(axis=0)
        if math.prod((hi - lo + 1).tolist()) <= max(DENSE_FALLBACK * len(ijk), 4096):
            box = read_dense(self.grid, lo, hi - lo + 1)
            rel = ijk - lo
            return box[rel[:, 0], rel[:, 1], rel[:, 2]]
        acc = self.grid.getConstAccessor()
        return np.asarray([acc.getValue(tuple(int(c) for c in v)) for v in ijk], np.float32)


# --- .vti -----------------------------------------------------------------------------------
def vti_stride(shape: Iterable[int], max_points: int) -> int:
    """Smallest stride s with prod(ceil(n / s)) <= max_points."""
    shape = [int(n) for n in shape]
    s = max(1, math.floor((math.prod(shape) / max(max_points, 1)) ** (1 / 3)))
    while math.prod(-(-n // s) for n in shape) > max_points:
        s += 1
    return s


def _strided_box(grid: Any, lo: np.ndarray, shape: np.ndarray, stride: int) -> np.ndarray:
    """Values at lo + stride * m over the box in VTK point order: (mz, my, mx[, 3]), x fastest.

    One y-plane read at a time (``copyToArray`` of nx x 1 x nz, the fastest of the three plane
    orientations in OpenVDB 10) into one reused buffer, its strided rows transposed into the
    output: no whole-box temporary, one copy of the values."""
    nx, ny, nz = (int(n) for n in shape)
    dims = [-(-n // stride) for n in (nx, ny, nz)]
    comps = (3,) if is_vector(grid) else ()
    out = np.empty((dims[2], dims[1], dims[0]) + comps, np.float32)
    reads = compiled_for(grid)
    if reads is not None:  # only the strided points, read in parallel in C++
        reads.strided_box(grid, tuple(int(c) for c in lo), tuple(dims), int(stride), out)
        return out
    buf = np.empty((nx, 1, nz) + comps, np.float32)
    for m, j in enumerate(range(int(lo[1]), int(lo[1]) + ny, stride)):
        read_dense(grid, (int(lo[0]), j, int(lo[2])), (nx, 1, nz), out=buf)
        out[:, m] = np.swapaxes(buf[::stride, 0, ::stride], 0, 1)
    return out


def _point_array(name: str, arr: np.ndarray) -> vtkDataArray:
    """VTK array from an (mz, my, mx[, 3]) array in point order (x fastest); shares its memory
    (numpy_to_vtk keeps a reference to it on the VTK array)."""
    flat = np.ascontiguousarray(arr).reshape((-1, 3) if arr.ndim == 4 else (-1,))
    out = nps.numpy_to_vtk(flat, deep=False, array_type=VTK_FLOAT)
    out.SetName(name)
    return out


def _field(name: str, values: Iterable[float]) -> vtkDoubleArray:
    arr = vtkDoubleArray()
    arr.SetName(name)
    for v in values:
        arr.InsertNextValue(float(v))
    return arr


def _write(writer: vtkXMLWriter | vtkWriter, data: Any, path: Path) -> None:
    if isinstance(writer, vtkXMLWriter):  # LZ4: a fraction of zlib's time, ParaView reads it
        writer.SetCompressorTypeToLZ4()
        # appended data raw, not base64 (ParaView's own default): half the write time, 3/4 of the size
        writer.EncodeAppendedDataOff()
    with atomic_path(path) as tmp:
        writer.SetFileName(str(tmp))
        writer.SetInputData(data)
        if writer.Write() != 1:
            raise OSError(f"VTK could not write {path}")


def write_vti(
    path: str | os.PathLike, grids: Grids, voxel_size: float, max_points: int = DEFAULT_MAX_POINTS
) -> dict:
    """Image data over the union active bounding box, every grid a point array (Vec3S: 3 components).

    When the box has more than ``max_points`` points, every ``stride``-th voxel along each axis is
    kept; origin and spacing are set so points stay at their voxels' world centres.
    Returns ``{"path", "kind", "stride", "dimensions", "origin", "spacing"}``.
    """
    path = Path(path)
    box = union_active_bbox(grids.values())
    if box is None:
        raise ValueError(f"{path.name}: no grid has active voxels, nothing to write")
    lo, hi = box
    shape = hi - lo + 1
    stride = vti_stride(shape, max_points)
    dims = [-(-int(n) // stride) for n in shape]
    image = vtkImageData()
    image.SetDimensions(*dims)
    image.SetOrigin(*(lo * voxel_size).tolist())
    image.SetSpacing(*([stride * voxel_size] * 3))
    for name, grid in grids.items():
        image.GetPointData().AddArray(_point_array(name, _strided_box(grid, lo, shape, stride)))
    image.GetFieldData().AddArray(_field("voxel_size", [voxel_size]))
    image.GetFieldData().AddArray(_field("stride", [stride]))
    image.GetFieldData().AddArray(_field("index_origin", lo.tolist()))
    _write(vtkXMLImageDataWriter(), image, path)
    return {
        "path": path.name, "kind": "vti", "stride": stride, "dimensions": dims,
        "origin": (lo * voxel_size).tolist(), "spacing": stride * voxel_size,
    }


# --- surface mesh (.vtp, .ply, .obj) --------------------------------------------------------
@dataclass
class SurfaceMesh:
    """Triangle mesh, counter-clockwise seen from outside (normals point out of the solid)."""

    points: np.ndarray  # (N, 3) float32 world
    triangles: np.ndarray  # (M, 3) int32 (int64 beyond 2^31 points)
    normals: np.ndarray  # (N, 3) float32 unit point normals
    source: str  # the grid that was meshed
    isovalue: float
    labels: np.ndarray | None = None  # (M,) int32 component label per triangle

    @property
    def signed_volume(self) -> float:
        """Enclosed volume (positive when outward-oriented and closed)."""
        a, b, c = (self.points[self.triangles[:, n]].astype(np.float64) for n in range(3))
        return float(np.einsum("ij,ij->i", a, cross(b, c)).sum() / 6.0)


def pick_surface_source(grids: Grids) -> str:
    """The grid to mesh: the first of surface, frep, hfrep, density that is present and active."""
    for name in SURFACE_SOURCES:
        if name in grids and grids[name].activeVoxelCount() > 0:
            return name
    raise ValueError(f"no grid to mesh: need one of {', '.join(SURFACE_SOURCES)}; got {sorted(grids)}")


def _inside_negative(name: str, grid: Any) -> bool:
    """Level sets (OpenVDB convention) are negative inside; everything else is FRep, positive inside."""
    return name == "surface" or _is_level_set(grid)


def _is_level_set(grid: Any) -> bool:
    return str(grid.gridClass) == "level set"


def _needs_flip(name: str, grid: Any) -> bool:
    """Whether volumeToMesh's triangles must be reversed to wind counter-clockwise from outside.

    volumeToMesh winds counter-clockwise around the lower-valued side, and reverses that for
    grids of class level set (Houdini's clockwise convention). So a counter-clockwise outward
    mesh needs a flip for level-set-class grids that are negative inside and for other grids that
    are positive inside: exactly when the two flags agree.
    """
    return _is_level_set(grid) == _inside_negative(name, grid)


def default_isovalue(name: str, grid: Any) -> float:
    """0 for fields, 0.5 for fog volumes (density)."""
    return 0.5 if name == "density" or str(grid.gridClass) == "fog volume" else 0.0


def triangle_indices(triangles: np.ndarray) -> np.ndarray:
    """Triangle indices for the mesh kernels: C-contiguous int32 or int64 (kept as they come;
    any other integer type as int64)."""
    t = np.ascontiguousarray(triangles)
    return t if t.dtype in (np.int32, np.int64) else t.astype(np.int64)


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    return unit_rows(vertex_normal_sums(np.ascontiguousarray(points), triangle_indices(triangles)))


def triangle_labels(
    component: Any, points: np.ndarray, triangles: np.ndarray, voxel_size: float
) -> np.ndarray:
    """Label per triangle: the nearest non-zero ``component`` voxel among the 8 around its centroid.

    The nearest of the 8 is the rounded centroid: where it holds a label that is the answer
    (one sample per triangle); only the other triangles read all 8 corners."""
    points = np.ascontiguousarray(points)
    triangles = triangle_indices(triangles)
    out = np.empty(len(triangles), np.int32)
    # a chunk of triangles at a time: their centroid voxels (int64 (M, 3)) were 0.4 GB at 1024^3
    for s in range(0, len(triangles), LABEL_CHUNK):
        part = triangles[s:s + LABEL_CHUNK]
        out[s:s + len(part)] = np.rint(sample_values(component, centroid_voxels(points, part, float(voxel_size))))
    todo = np.flatnonzero(out <= 0)
    if len(todo):
        c = points[triangles[todo]].astype(np.float64).mean(axis=1) / voxel_size
        base = np.floor(c).astype(np.int64)
        ijk = (base[:, None, :] + _CORNERS[None]).reshape(-1, 3)
        labels = np.rint(sample_values(component, ijk)).astype(np.int32).reshape(-1, 8)
        dist = np.linalg.norm(ijk.reshape(-1, 8, 3) - c[:, None, :], axis=2)
        dist[labels <= 0] = np.inf
        picked = labels[np.arange(len(labels)), np.argmin(dist, axis=1)]
        out[todo] = np.where(np.isfinite(dist.min(axis=1)), picked, 0)
    return np.maximum(out, 0).astype(np.int32)


LABEL_CHUNK = 1 << 21  # triangles per centroid sampling pass of triangle_labels


def weld(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident points and drop degenerate (zero-area) triangles.

    volumeToMesh emits coincident vertices and zero-area triangles where the field is exactly
    the isovalue at a voxel centre; they would get zero normals and confuse importers.
    Bit-identical float32 points are merged (a hash table, in first-occurrence order), a triangle
    is dropped when its float64 cross product is exactly zero, unused points are dropped.
    """
    if len(points) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    return weld_kernel(points, points.view(np.uint32), triangle_indices(triangles))


def extract_surface(
    grids: Grids,
    voxel_size: float,
    source: str | None = None,
    isovalue: float | None = None,
    adaptivity: float = 0.0,
) -> SurfaceMesh:
    """Mesh the isosurface of one grid with OpenVDB's volumeToMesh, oriented outwards.

    ``source`` defaults to :func:`pick_surface_source`; ``isovalue`` to 0 (0.5 for density).
    Quads are split into triangles. When a ``component`` grid is present each triangle gets
    its label.
    """
    name = source or pick_surface_source(grids)
    grid = grids[name]
    iso = default_isovalue(name, grid) if isovalue is None else float(isovalue)
    points, tris, quads = grid.convertToPolygons(isovalue=iso, adaptivity=float(adaptivity))
    tris, quads = np.ascontiguousarray(tris).reshape(-1, 3), np.ascontiguousarray(quads).reshape(-1, 4)
    # int32 indices while they fit: the triangles are the mesh's largest arrays (17 M rows at
    # 1024^3, where export's memory peaks)
    index = np.int32 if len(points) < 2**31 else np.int64
    triangles = split_polygons(tris, quads, _needs_flip(name, grid),
                               np.empty((len(tris) + 2 * len(quads), 3), index))
    del tris, quads
    points, triangles = weld(np.asarray(points, dtype=np.float32), triangles)
    labels = None
    if "component" in grids and len(triangles):
        labels = triangle_labels(grids["component"], points, triangles, voxel_size)
    return SurfaceMesh(points, triangles, vertex_normals(points, triangles), name, iso, labels)


def _shared(arr: np.ndarray, dtype: type, vtk_type: int) -> vtkDataArray:
    """VTK array over ``arr``'s memory when it already has the type and layout (numpy_to_vtk
    keeps a reference to it), else over a converted copy."""
    arr = np.ascontiguousarray(arr, dtype=dtype)
    return nps.numpy_to_vtk(arr, deep=False, array_type=vtk_type)


def mesh_polydata(mesh: SurfaceMesh) -> vtkPolyData:
    """vtkPolyData with point normals ("Normals") and the component label as cell data."""
    poly = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(_shared(mesh.points, np.float32, VTK_FLOAT))
    poly.SetPoints(pts)
    cells = vtkCellArray()
    # 32-bit cell storage for int32 triangles (vtkCellArray keeps either): no 64-bit copy
    wide = mesh.triangles.dtype != np.int32
    itype, vtype = (np.int64, VTK_ID_TYPE) if wide else (np.int32, VTK_INT)
    offsets = np.arange(0, 3 * len(mesh.triangles) + 1, 3, dtype=itype)
    cells.SetData(_shared(offsets, itype, vtype), _shared(mesh.triangles.reshape(-1), itype, vtype))
    poly.SetPolys(cells)
    normals = _shared(mesh.normals, np.float32, VTK_FLOAT)
    normals.SetName("Normals")
    poly.GetPointData().SetNormals(normals)
    if mesh.labels is not None:
        labels = _shared(mesh.labels, np.int32, VTK_INT)
        labels.SetName("component")
        poly.GetCellData().AddArray(labels)
    return poly


def write_vtp(path: str | os.PathLike, mesh: SurfaceMesh) -> dict:
    """XML PolyData of the mesh. Returns the manifest entry."""
    path = Path(path)
    poly = mesh_polydata(mesh)
    poly.GetFieldData().AddArray(_field("isovalue", [mesh.isovalue]))
    _write(vtkXMLPolyDataWriter(), poly, path)
    return {"path": path.name, "kind": "vtp", "source": mesh.source, "points": len(mesh.points),
            "triangles": len(mesh.triangles)}


def write_ply(path: str | os.PathLike, mesh: SurfaceMesh) -> dict:
    """Binary PLY (vertices, normals, triangles) for Blender."""
    path = Path(path)
    writer = vtkPLYWriter()
    writer.SetFileTypeToBinary()
    writer.SetArrayName("")  # no colours: Blender reads positions, normals and faces
    _write(writer, mesh_polydata(mesh), path)
    return {"path": path.name, "kind": "ply", "points": len(mesh.points), "triangles": len(mesh.triangles)}


def write_obj(path: str | os.PathLike, mesh: SurfaceMesh) -> dict:
    """Wavefront OBJ (vertices, normals, triangles), Y is not swapped: world axes as in the .vdb."""
    path = Path(path)
    _write(vtkOBJWriter(), mesh_polydata(mesh), path)
    return {"path": path.name, "kind": "obj", "points": len(mesh.points), "triangles": len(mesh.triangles)}


# --- .vtu of the active voxels ----------------------------------------------------------------
def union_active(samplers: Iterable[GridSampler]) -> np.ndarray:
    """Sorted unique ijk (N,3) of the voxels active in any of the sampled grids."""
    parts = [s.active_ijk for s in samplers]
    ijk = np.concatenate(parts) if parts else np.zeros((0, 3), np.int64)
    _, first = np.unique(pack_keys(ijk), return_index=True)
    return ijk[first]


def hex_cells(ijk: np.ndarray, voxel_size: float) -> vtkUnstructuredGrid:
    """Unstructured grid with one hexahedron per voxel (shared corner points)."""
    corners = (ijk[:, None, :] + _HEX[None]).reshape(-1, 3)
    keys, inverse = np.unique(pack_keys(corners), return_inverse=True)
    uniq = np.empty((len(keys), 3), np.int64)
    uniq[inverse] = corners
    ug = vtkUnstructuredGrid()
    pts = vtkPoints()
    pts.SetData(nps.numpy_to_vtk(((uniq - 0.5) * voxel_size).astype(np.float32), deep=True))
    ug.SetPoints(pts)
    cells = vtkCellArray()
    cells.SetData(
        nps.numpy_to_vtk(np.arange(0, 8 * len(ijk) + 1, 8, dtype=np.int64), deep=True,
                         array_type=VTK_ID_TYPE),
        nps.numpy_to_vtk(inverse.astype(np.int64).reshape(-1), deep=True, array_type=VTK_ID_TYPE),
    )
    ug.SetCells(VTK_HEXAHEDRON, cells)
    return ug


def write_vtu(
    path: str | os.PathLike, grids: Grids, voxel_size: float, max_cells: int | None = None
) -> dict:
    """Active voxels (union over grids) as hexahedra; every grid's value is cell data.

    Also an ``active_<name>`` (0/1) cell array per grid, since the union holds voxels that are
    inactive in some grids. ValueError when more than ``max_cells`` voxels would be written.
    """
    path = Path(path)
    largest = max((int(g.activeVoxelCount()) for g in grids.values()), default=0)
    if max_cells is not None and largest > max_cells:
        raise ValueError(f"{path.name}: {largest} active voxels exceed max_cells={max_cells}")
    samplers = {name: GridSampler(grid) for name, grid in grids.items()}
    ijk = union_active(samplers.values())
    if len(ijk) == 0:
        raise ValueError(f"{path.name}: no grid has active voxels, nothing to write")
    if max_cells is not None and len(ijk) > max_cells:
        raise ValueError(f"{path.name}: {len(ijk)} active voxels exceed max_cells={max_cells}")
    ug = hex_cells(ijk, voxel_size)
    for name, sampler in samplers.items():
        values, active = sampler.sample(ijk)
        arr = nps.numpy_to_vtk(np.ascontiguousarray(values), deep=True, array_type=VTK_FLOAT)
        arr.SetName(name)
        ug.GetCellData().AddArray(arr)
        flag = nps.numpy_to_vtk(active.astype(np.uint8), deep=True, array_type=VTK_UNSIGNED_CHAR)
        flag.SetName(f"active_{name}")
        ug.GetCellData().AddArray(flag)
    ug.GetFieldData().AddArray(_field("voxel_size", [voxel_size]))
    _write(vtkXMLUnstructuredGridWriter(), ug, path)
    return {"path": path.name, "kind": "vtu", "cells": len(ijk)}


# --- .pvd collections -------------------------------------------------------------------------
def write_pvd(path: str | os.PathLike, frames: Iterable[tuple[float, str | os.PathLike]]) -> dict:
    """ParaView collection of (time, file) frames; file paths are stored relative to the .pvd."""
    path = Path(path)
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    count = 0
    for time, file in frames:
        rel = Path(file)
        if rel.is_absolute():
            rel = Path(os.path.relpath(rel.resolve(), path.parent.resolve()))
        ET.SubElement(coll, "DataSet", timestep=repr(float(time)), group="", part="0",
                      file=rel.as_posix())
        count += 1
    ET.indent(root)
    with atomic_path(path) as tmp:
        ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
    return {"path": path.name, "kind": "pvd", "frames": count}


# --- one call for the export stage ------------------------------------------------------------
MESH_WRITERS = {"vtp": write_vtp, "ply": write_ply, "obj": write_obj}


def write_vtk_outputs(
    out_dir: str | os.PathLike,
    name: str,
    grids: Grids,
    voxel_size: float,
    kinds: Iterable[str] = ("vti", "vtp"),
    max_points: int = DEFAULT_MAX_POINTS,
    max_cells: int | None = None,
    adaptivity: float = 0.0,
) -> tuple[list[dict], SurfaceMesh | None]:
    """Write ``<out_dir>/<name>.<kind>`` for each kind in vti, vtu, vtp, ply, obj.

    Returns the manifest ``outputs`` entries and the surface mesh (None when no mesh kind was
    asked for), so previews can reuse it. ValueError when a requested file cannot be made (no
    active voxels, no grid to mesh, more than ``max_cells`` voxels for the .vtu).
    """
    out_dir = Path(out_dir)
    kinds = list(dict.fromkeys(kinds))
    unknown = set(kinds) - {"vti", "vtu", *MESH_WRITERS}
    if unknown:
        raise ValueError(f"unknown VTK output kind(s) {sorted(unknown)}; use vti, vtu, vtp, ply, obj")
    entries: list[dict] = []
    if "vti" in kinds:
        entries.append(write_vti(out_dir / f"{name}.vti", grids, voxel_size, max_points))
    if "vtu" in kinds:
        entries.append(write_vtu(out_dir / f"{name}.vtu", grids, voxel_size, max_cells))
    mesh = None
    mesh_kinds = [k for k in kinds if k in MESH_WRITERS]
    if mesh_kinds:
        mesh = extract_surface(grids, voxel_size, adaptivity=adaptivity)
        entries.extend(MESH_WRITERS[k](out_dir / f"{name}.{k}", mesh) for k in mesh_kinds)
    return entries, mesh
