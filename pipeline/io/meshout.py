"""Printable meshes: closed, consistently oriented triangle meshes of a grid's zero set, and
their writers (binary STL, 3MF, binary PLY, OBJ), optionally one mesh per component.

The surface is OpenVDB's volumeToMesh (``convertToPolygons``, adaptivity 0) of the ``frep``
grid (or a level set): on a closed zero set its polygons share every edge exactly, so after
splitting quads into two triangles, merging bit-identical vertices and dropping triangles with a
repeated vertex the mesh is watertight. volumeToMesh winds every polygon the same way around the
lower-valued side; the winding is set outward from the sign of the enclosed volume, so the
result does not depend on the grid's class or sign convention.

Formats written here without extra dependencies: STL (binary: 80-byte header, uint32 count,
50 bytes per triangle), 3MF (3MF Core Specification 1.3: an OPC zip with
``[Content_Types].xml``, ``_rels/.rels`` and the model part ``3D/3dmodel.model``), PLY (binary
little endian) and OBJ (text).
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.meshkernels import merge_kernel
from pipeline.util.atomic import atomic_path
from pipeline.util.progress import tick

MESH_KINDS = ("stl", "3mf", "ply", "obj")


@dataclass
class TriMesh:
    """Triangles ``triangles`` (M, 3) over ``vertices`` (N, 3) float64, counter-clockwise seen
    from outside (right-hand normals point out of the solid)."""

    vertices: np.ndarray
    triangles: np.ndarray
    _open: int | None = field(default=None, repr=False)  # cached open_edges()

    @property
    def signed_volume(self) -> float:
        """Enclosed volume by the divergence theorem (positive for an outward closed mesh)."""
        if len(self.triangles) == 0:
            return 0.0
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)

    def open_edges(self) -> int:
        """Edges used by other than exactly two triangles (0 for a closed 2-manifold mesh)."""
        if self._open is None:
            e = np.sort(self.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
            keys = e[:, 0] * (int(e.max(initial=0)) + 1) + e[:, 1]
            _, counts = np.unique(keys, return_counts=True)
            self._open = int(np.count_nonzero(counts != 2))
        return self._open

    def normals(self) -> np.ndarray:
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(length > 0, length, 1.0)


#: the isovalue is moved this many voxels towards the inside: a sample exactly at the isovalue
#: (a model zero at a voxel centre, common with round numbers) makes volumeToMesh emit distinct
#: vertices at one point, which any tolerance-based welder (trimesh, slicers) then joins into
#: edges of four triangles; 1e-3 voxel keeps every vertex resolvable in float32 and moves the
#: surface by a thousandth of a voxel
ISO_NUDGE = 1e-3


def zero_set(grid: Any, isovalue: float = 0.0) -> TriMesh:
    """The isosurface of ``grid`` (world coordinates), triangulated, merged, oriented outward."""
    inside = -1.0 if str(grid.gridClass) == "level set" else 1.0  # level sets are negative inside
    iso = float(isovalue) + inside * ISO_NUDGE * float(grid.transform.voxelSize()[0])
    pts, tris, quads = grid.convertToPolygons(isovalue=iso, adaptivity=0.0)
    q = np.asarray(quads, np.int64).reshape(-1, 4)
    t = np.concatenate([np.asarray(tris, np.int64).reshape(-1, 3), q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    mesh = _merge(np.asarray(pts, np.float64).reshape(-1, 3), t)
    if mesh.signed_volume < 0:  # volumeToMesh winds around the lower side: frep grids come out inward
        mesh = TriMesh(mesh.vertices, np.ascontiguousarray(mesh.triangles[:, ::-1]))
    return mesh


def _merge(points: np.ndarray, tris: np.ndarray) -> TriMesh:
    """Merge vertices of equal coordinates; drop triangles with a repeated vertex (never
    zero-area ones with three distinct vertices: they carry edges the neighbours share).
    Vertices in first-occurrence order when the points are float32 values (a compiled hash
    table), else in coordinate order (``np.unique``)."""
    if len(points) == 0:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    single = points.astype(np.float32) + np.float32(0.0)  # + 0: -0.0 becomes 0.0, equal values equal bits
    if np.array_equal(single, points):  # volumeToMesh's float32 points: a hash table, not a sort of rows

        source, t = merge_kernel(np.ascontiguousarray(single).view(np.uint32),
                                 np.ascontiguousarray(tris, dtype=np.int64))
        return TriMesh(np.ascontiguousarray(points[source]), t)
    uniq, inverse = np.unique(points, axis=0, return_inverse=True)
    t = inverse.reshape(-1)[tris]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    used, remap = np.unique(t, return_inverse=True)
    return TriMesh(np.ascontiguousarray(uniq[used]), np.ascontiguousarray(remap.reshape(-1, 3), dtype=np.int64))


def split_components(mesh: TriMesh, labels: np.ndarray) -> dict[int, TriMesh]:
    """One mesh per component label. Each connected piece of the surface goes whole to the most
    common label of its triangles (a piece is one closed sheet, so every part stays closed)."""
    piece = _pieces(mesh)
    out: dict[int, list[np.ndarray]] = {}
    for p in np.unique(piece):
        rows = np.flatnonzero(piece == p)
        lab = labels[rows]
        lab = lab[lab > 0]
        k = int(np.bincount(lab).argmax()) if len(lab) else 0
        out.setdefault(k, []).append(rows)
    return {k: _submesh(mesh, np.concatenate(rows)) for k, rows in sorted(out.items())}


def _pieces(mesh: TriMesh) -> np.ndarray:
    """Connected piece of each triangle (through shared vertices)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m, n = len(mesh.triangles), len(mesh.vertices)
    rows = np.repeat(np.arange(m), 3)
    g = coo_matrix((np.ones(3 * m), (rows, mesh.triangles.reshape(-1))), shape=(m, n)).tocsr()
    _, lab = connected_components(g @ g.T, directed=False)
    return lab


def _submesh(mesh: TriMesh, rows: np.ndarray) -> TriMesh:
    t = mesh.triangles[np.sort(rows)]
    used, remap = np.unique(t, return_inverse=True)
    return TriMesh(mesh.vertices[used], remap.reshape(-1, 3).astype(np.int64))


# --- writers ------------------------------------------------------------------------------------

_STL = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def write_stl(path: str | Path, mesh: TriMesh, header: str = "frepvdb") -> dict:
    """Binary STL: 84 + 50 n bytes."""
    rec = np.zeros(len(mesh.triangles), _STL)
    rec["n"] = mesh.normals()
    rec["v"] = mesh.vertices[mesh.triangles]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii", "replace")[:80].ljust(80, b" "))
        f.write(np.uint32(len(rec)).tobytes())
        f.write(rec.tobytes())
    return _entry(path, "stl", mesh)


_CONTENT_TYPES = ('<?xml version="1.0" encoding="UTF-8"?>\n'
                  '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
                  '<Default Extension="rels" ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
                  '<Default Extension="model" ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/>'
                  '</Types>\n')
_RELS = ('<?xml version="1.0" encoding="UTF-8"?>\n'
         '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
         '<Relationship Target="/3D/3dmodel.model" Id="rel0" '
         'Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/></Relationships>\n')


def write_3mf(path: str | Path, meshes: TriMesh | dict[int, TriMesh], unit: str = "millimeter") -> dict:
    """3MF: one object per mesh (per component when given a dict), each a build item."""
    parts = meshes if isinstance(meshes, dict) else {1: meshes}
    objects, items = [], []
    for oid, (_, m) in enumerate(sorted(parts.items()), start=1):
        verts = "".join(f'<vertex x="{x:.9g}" y="{y:.9g}" z="{z:.9g}"/>' for x, y, z in m.vertices.tolist())
        tris = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for a, b, c in m.triangles.tolist())
        objects.append(f'<object id="{oid}" type="model"><mesh><vertices>{verts}</vertices>'
                       f'<triangles>{tris}</triangles></mesh></object>')
        items.append(f'<item objectid="{oid}"/>')
    model = ('<?xml version="1.0" encoding="UTF-8"?>\n'
             f'<model unit="{unit}" xml:lang="en-US" '
             'xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">'
             f'<resources>{"".join(objects)}</resources><build>{"".join(items)}</build></model>\n')
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("[Content_Types].xml", _CONTENT_TYPES)
        z.writestr("_rels/.rels", _RELS)
        z.writestr("3D/3dmodel.model", model)
    total = TriMesh(*_concat(parts))
    return {**_entry(path, "3mf", total), "objects": len(parts)}


def _concat(parts: dict[int, TriMesh]) -> tuple[np.ndarray, np.ndarray]:
    verts, tris, off = [], [], 0
    for _, m in sorted(parts.items()):
        verts.append(m.vertices)
        tris.append(m.triangles + off)
        off += len(m.vertices)
    return (np.concatenate(verts) if verts else np.zeros((0, 3)),
            np.concatenate(tris) if tris else np.zeros((0, 3), np.int64))


def write_ply(path: str | Path, mesh: TriMesh) -> dict:
    """Binary little-endian PLY: float vertices, uchar-counted int triangles."""
    head = (f"ply\nformat binary_little_endian 1.0\ncomment frepvdb\nelement vertex {len(mesh.vertices)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {len(mesh.triangles)}\nproperty list uchar int vertex_indices\nend_header\n")
    face = np.zeros(len(mesh.triangles), np.dtype([("k", "u1"), ("i", "<i4", 3)]))
    face["k"], face["i"] = 3, mesh.triangles
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(mesh.vertices.astype("<f4").tobytes())
        f.write(face.tobytes())
    return _entry(path, "ply", mesh)


def write_obj(path: str | Path, mesh: TriMesh) -> dict:
    """Wavefront OBJ text (1-based indices)."""
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write("# frepvdb\n")
        np.savetxt(f, mesh.vertices, fmt="v %.9g %.9g %.9g")
        np.savetxt(f, mesh.triangles + 1, fmt="f %d %d %d")
    return _entry(path, "obj", mesh)


WRITERS: dict[str, Callable[..., dict]] = {"stl": write_stl, "3mf": write_3mf, "ply": write_ply, "obj": write_obj}


def _entry(path: str | Path, kind: str, mesh: TriMesh) -> dict:
    return {"path": Path(path).name, "kind": kind, "vertices": len(mesh.vertices),
            "triangles": len(mesh.triangles), "volume": round(mesh.signed_volume, 12),
            "open_edges": mesh.open_edges()}


def surface_grid(grids: dict[str, Any]) -> tuple[str, Any]:
    """The grid whose zero set is the part: ``frep`` (the model's own field), else ``surface``."""
    for name in ("frep", "surface"):
        if grids.get(name) is not None and grids[name].activeVoxelCount() > 0:
            return name, grids[name]
    raise ValueError(f"no grid to mesh: need frep or surface with active voxels; got {sorted(grids)}")


def write_meshes(out_dir: Path, name: str, grids: dict[str, Any], kinds: list[str], voxel_size: float,
                 per_component: bool = False, progress: Callable[..., None] | None = None
                 ) -> tuple[list[dict], list[str]]:
    """``<name>_mesh.<kind>`` for each kind (and ``<name>_mesh_<k>.<kind>`` per component with
    ``per_component``, when a ``component`` grid exists; 3MF then holds one object per
    component). Returns (manifest entries, warnings); ``progress`` gets the files done of all."""
    from pipeline.io.vtkio import triangle_labels  # VTK takes ~1 s to import: only when meshes are written

    source, grid = surface_grid(grids)
    mesh = zero_set(grid)
    warnings = []
    if mesh.open_edges():
        warnings.append(f"the {source} surface is not closed ({mesh.open_edges()} open edges): the part "
                        "touches the domain's faces; enlarge the domain for a printable mesh")
    parts: dict[int, TriMesh] = {}
    if per_component and grids.get("component") is not None and len(mesh.triangles):
        labels = triangle_labels(grids["component"], mesh.vertices.astype(np.float32), mesh.triangles, voxel_size)
        parts = split_components(mesh, labels)
    elif per_component:
        warnings.append("mesh_per_component: no component grid (add the components stage); one mesh written")
    entries: list[dict] = []
    kinds = list(dict.fromkeys(kinds))
    total = len(kinds) + len(parts) * sum(k != "3mf" for k in kinds)
    for kind in kinds:
        path = out_dir / f"{name}_mesh.{kind}"
        entries.append(write_3mf(path, parts or mesh) if kind == "3mf" else WRITERS[kind](path, mesh))
        tick(progress, f"wrote {path.name}", len(entries), total)
        if kind != "3mf":
            for k, part in parts.items():
                entries.append({**WRITERS[kind](out_dir / f"{name}_mesh_{k}.{kind}", part), "component": k})
                tick(progress, f"wrote {entries[-1]['path']}", len(entries), total)
    for e in entries:
        e["source"] = source
    return entries, warnings


def export_meshes(ctx: Any, grids: dict[str, Any], kinds: list[str], per_component: bool) -> list[str]:
    """The export stage's ``mesh:`` option: write the meshes, register them in the manifest (so
    pipeline.job.outputs verifies them), pass on the warnings; returns the file names."""
    entries, warnings = write_meshes(ctx.out_dir, ctx.job.name, grids, kinds, ctx.voxel_size, per_component,
                                     progress=ctx.progress)
    for e in entries:
        ctx.add_output(ctx.out_dir / e["path"], e["kind"], **{k: v for k, v in e.items() if k not in ("path", "kind")})
    ctx.warnings.extend(warnings)
    return [e["path"] for e in entries]
