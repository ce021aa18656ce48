"""Polygon mesh loading and checking for the BSP-field and ADF conversions.

``load_mesh`` reads .off .obj .stl .ply through trimesh and returns the mesh together with a
:class:`MeshReport`. The BSP-field construction of bsp-fields.txt section 3 assumes "a closed
manifold [...] with no degenerate boundary elements"; the report says whether the input meets
that assumption (watertight, consistent winding, degenerate faces) and gives the topology
(connected components, genus per component from the Euler characteristic). A mesh that does
not load, is empty or has no faces raises :class:`MeshError`; an open mesh still loads, with a
warning, because section 4.2 of the paper converts incomplete meshes too.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh

SUFFIXES = (".off", ".obj", ".stl", ".ply")


class MeshError(ValueError):
    """A mesh file that cannot be used: missing, unreadable, empty or without faces."""


@dataclass
class MeshReport:
    """Checks and topology of a loaded mesh."""

    path: str
    faces: int
    vertices: int
    watertight: bool
    winding_consistent: bool
    degenerate_faces: int
    components: int
    genus: list[int]
    volume: float
    area: float = float("nan")
    warnings: list[str] = field(default_factory=list)


def _trimesh():
    """trimesh, imported on first use: it takes ~0.3 s, which a run without meshes need not pay."""
    import trimesh

    return trimesh


def _fail(path: Path, why: str) -> MeshError:
    return MeshError(f"{path}: {why}")


def _read(path: Path) -> trimesh.Trimesh:
    """Load ``path`` as one triangle mesh (scenes are concatenated), or raise MeshError.

    The bytes are read here and handed to trimesh: text formats that are not UTF-8 (a Latin-1
    byte in a comment) are transcoded first, since trimesh's own fallback needs an encoding
    detector. A file trimesh cannot parse, or that parses to nothing, is "not a mesh"."""
    if path.is_dir():
        raise _fail(path, "is a folder, not a mesh file")
    if not path.is_file():
        raise _fail(path, "mesh file not found")
    if path.suffix.lower() not in SUFFIXES:
        raise _fail(path, f"unsupported mesh format {path.suffix!r} (use {', '.join(SUFFIXES)})")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise _fail(path, f"cannot read mesh file ({exc.strerror or exc})") from None
    if not data:
        raise _fail(path, "mesh file is empty")
    kind = path.suffix.lower()[1:]
    try:
        # process=False: checked first, processed after (processing drops NaN vertices silently)
        tm = _trimesh()
        plain = _plain_off(data) if kind == "off" else None
        if plain is not None:
            loaded = tm.Trimesh(vertices=plain[0], faces=plain[1], process=False)
        else:
            loaded = tm.load(io.BytesIO(_as_utf8(data, kind)), file_type=kind, force="mesh", process=False,
                             resolver=tm.resolvers.FilePathResolver(str(path)))
    except Exception as exc:  # trimesh raises many exception types on bad input
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"not a mesh: this .{kind} file does not parse ({_clip(msg)})") from None
    if not isinstance(loaded, _trimesh().Trimesh) or len(loaded.vertices) == 0:
        raise _fail(path, f"not a mesh: no vertices and no faces could be read from this .{kind} file")
    _check_coordinates(loaded, path)
    loaded.process()  # what process=True does: merge vertices so that shared edges are seen
    return loaded


def _plain_off(data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices, faces) of an OFF file in its plain form: an ``OFF`` line, the counts, one
    vertex of 3 numbers a line, then triangles ``3 a b c`` (the shared meshes, trimesh's own
    exports), parsed in bulk (trimesh's parser splits every line in Python: 0.1-0.2 s for 50k
    faces). Anything else (comments, colours, polygons, counts on the header line, bad indices,
    non-UTF-8 bytes) returns None, and trimesh parses it as before (and reports its errors)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return None
    if "#" in text:
        return None
    lines = [ln for ln in text.splitlines() if ln.strip()]  # blank lines are skipped, as trimesh does
    if len(lines) < 2 or lines[0].strip() != "OFF":
        return None
    counts = lines[1].split()
    if len(counts) < 2 or not all(c.isdigit() for c in counts):
        return None
    nv, nf = int(counts[0]), int(counts[1])
    body = lines[2:]
    if nv == 0 or nf == 0 or len(body) < nv + nf:
        return None
    try:
        v = np.array(" ".join(body[:nv]).split(), dtype=np.float64)
        f = np.array(" ".join(body[nv:nv + nf]).split(), dtype=np.int64)
    except ValueError:
        return None
    if v.size != 3 * nv or f.size != 4 * nf:
        return None
    f = f.reshape(nf, 4)
    if np.any(f[:, 0] != 3) or f[:, 1:].min() < 0 or f[:, 1:].max() >= nv:
        return None
    return v.reshape(nv, 3), np.ascontiguousarray(f[:, 1:])


def _clip(text: str, limit: int = 160) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:limit] + "..."


def _as_utf8(data: bytes, kind: str) -> bytes:
    """Text meshes as UTF-8: bytes that are not UTF-8 are read as Latin-1 (every byte is a
    character; the numbers and keywords are ASCII either way). Binary STL/PLY stay as they are."""
    if not _is_text(data, kind):
        return data
    try:
        data.decode("utf-8")
        return data
    except UnicodeDecodeError:
        return data.decode("latin-1").encode("utf-8")


def _is_text(data: bytes, kind: str) -> bool:
    if kind == "stl":  # binary: an 80-byte header, a face count, 50 bytes per face
        binary = len(data) >= 84 and len(data) == 84 + 50 * int.from_bytes(data[80:84], "little")
        return not binary and data.lstrip()[:5].lower() == b"solid"
    if kind == "ply":
        return b"format ascii" in data[:data.find(b"end_header")] if b"end_header" in data else False
    return True  # OBJ, OFF


def component_genus(mesh: trimesh.Trimesh) -> list[int]:
    """Genus of every edge-connected component from its Euler characteristic.

    For an orientable surface with b boundary loops, chi = V - E + F = 2 - 2g - b.
    """
    labels = _trimesh().graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    out: list[int] = []
    nv = max(int(mesh.faces.max()) + 1, 1) if len(mesh.faces) else 1
    for lab in np.unique(labels):
        faces = mesh.faces[labels == lab]
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        # unique rows by one int64 key each (np.unique(axis=0) sorts structured rows: ~5x slower)
        key, counts = np.unique(edges[:, 0].astype(np.int64) * nv + edges[:, 1], return_counts=True)
        uniq = np.stack([key // nv, key % nv], axis=1)
        chi = len(np.unique(faces)) - len(uniq) + len(faces)
        boundary = _boundary_loops(uniq[counts == 1])
        out.append(int(round((2 - chi - boundary) / 2)))
    return out


def _boundary_loops(edges: np.ndarray) -> int:
    """Number of closed boundary loops formed by the boundary edges (graph components)."""
    if len(edges) == 0:
        return 0
    return len(_trimesh().graph.connected_components(edges, min_len=1))


def check_mesh(mesh: trimesh.Trimesh, path: str = "<mesh>") -> MeshReport:
    """Build the :class:`MeshReport` of an already loaded mesh."""
    degenerate = int(np.count_nonzero(mesh.area_faces <= 1e-12 * max(mesh.scale, 1e-300) ** 2))
    genus = component_genus(mesh)
    watertight = bool(mesh.is_watertight)
    report = MeshReport(
        path=path,
        faces=len(mesh.faces),
        vertices=len(mesh.vertices),
        watertight=watertight,
        winding_consistent=bool(mesh.is_winding_consistent),
        degenerate_faces=degenerate,
        components=len(genus),
        genus=genus,
        volume=float(mesh.volume) if watertight else float("nan"),
        area=float(mesh.area_faces.sum()),
    )
    if not watertight:
        report.warnings.append(f"{path}: mesh is not closed (not watertight); the field is not exact")
    if not report.winding_consistent:
        report.warnings.append(f"{path}: face winding is inconsistent")
    if degenerate:
        report.warnings.append(f"{path}: {degenerate} degenerate (zero-area) faces")
    if watertight and report.volume < 0:
        report.warnings.append(f"{path}: faces are oriented inwards (negative volume)")
    return report


def load_mesh(path: str | Path) -> tuple[trimesh.Trimesh, MeshReport]:
    """Load a polygon mesh (.off .obj .stl .ply) and check it.

    Raises :class:`MeshError` (a ValueError) naming the file when it is missing, unreadable,
    empty or has no faces. Vertices are merged (trimesh ``process=True``) so that the
    watertightness test sees shared edges.
    """
    p = Path(path)
    held = _HELD.get(str(p.resolve()))
    if held is not None:
        return held
    mesh = _read(p)
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise _fail(p, "mesh has no faces")
    return mesh, check_mesh(mesh, str(p))


_HELD: dict[str, tuple[trimesh.Trimesh, MeshReport]] = {}


@contextmanager
def holding(path: str | Path, loaded: tuple[trimesh.Trimesh, MeshReport]) -> Iterator[None]:
    """Inside the block, :func:`load_mesh` of ``path`` returns ``loaded`` (what it returned
    before) instead of reading and checking the file again: ``frepvdb convert`` reads the mesh
    for its bounds, then builds the job's mesh node from the same file (6 s for 1.3M faces).
    Nothing is kept after the block. The loaded mesh is never modified (the node repairs a copy)."""
    key = str(Path(path).resolve())
    _HELD[key] = loaded
    try:
        yield
    finally:
        _HELD.pop(key, None)


#: largest vertex coordinate: beyond it squared distances and plane equations of the BSP-field
#: lose every digit of a voxel-sized detail (and 1e30 squared overflows float32 arithmetic)
MAX_MESH_COORDINATE = 1e12


def _check_coordinates(mesh: trimesh.Trimesh, path: Path) -> None:
    """A mesh with problems (as distinct from a file that is not a mesh): NaN or infinite
    vertices, or coordinates too large to compute with."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise _fail(path, f"mesh with problems: {int(bad.sum())} vertices are not finite numbers (NaN or inf), "
                          f"the first is vertex {first}")
    big = float(np.abs(v).max())
    if big > MAX_MESH_COORDINATE:
        raise _fail(path, f"mesh with problems: a vertex coordinate of {big:.3g} is beyond the limit of "
                          f"{MAX_MESH_COORDINATE:g}; scale the mesh to the model's units")
