"""``mesh``: a polygon mesh as an exact field (BSP-field, bsp-fields section 3) or as an
approximate distance field (approximate-distance-fields eq. 4-7), usable like any node."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.field.affine import AffineForm
from pipeline.mesh.adf import ADFField
from pipeline.mesh.bsp import BSPField
from pipeline.mesh.meshio import MeshError, load_mesh
from pipeline.model.base import Node, Params, register
from pipeline.model.tape import NotTraceable, Sym
from pipeline.util.errors import InputError


@register("mesh")
class Mesh(Node):
    """``mesh: {path: part.off, rfunc: r0, planes: optimised}``; ``method: adf`` for the
    trimmed-and-joined distance field (``join: requiv | rconj``, ``p``).

    Evaluation is the compiled field of :mod:`pipeline.mesh.bsp` / :mod:`pipeline.mesh.adf`. Bounds are
    their rigorous interval bounds over the box hull of the coordinate forms (exact under
    translations; a rotated or deformed mesh gets the hull of its transformed box).
    """

    oracle = True
    finite_by_construction = True  # vertices are finite and within MAX_MESH_COORDINATE (meshio)

    class Params(Params):
        path: str
        method: Literal["bsp", "adf"] = "bsp"
        rfunc: Literal["min_max", "r0", "sardf"] = "r0"
        planes: Literal["naive", "optimised"] = "optimised"
        seed: int = 0
        join: Literal["requiv", "rconj"] = "requiv"
        p: float = Field(default=2.0, ge=1)
        allow_open: bool = Field(default=False, description="convert a mesh that is not closed (with a warning)")

    def __init__(self, params, where=""):
        super().__init__(params, where)
        try:
            mesh, self.report = load_mesh(params.path)
        except MeshError as e:
            raise InputError(str(e)) from None
        if not self.report.watertight and not params.allow_open:
            # SPEC: a mesh that is not closed is bad input; bsp-fields section 4.2 shows what its
            # field looks like, so users can still ask for it explicitly
            raise InputError(f"{params.path}: mesh is not closed (not watertight), so its field has no "
                             "inside; set allow_open: true (frepvdb convert: --allow-open) to convert it anyway (the "
                             "field is then not exact)")
        self.warnings = list(self.report.warnings)
        if not self.report.winding_consistent:
            mesh = self._repair_winding(mesh)
        if params.method == "bsp":
            self.impl = BSPField.from_mesh(mesh, rfunc=params.rfunc, planes=params.planes, seed=params.seed)
            self.stats = dict(self.impl.stats)
            nodes = self.stats["nodes"]
            if params.rfunc != "min_max" and nodes > SLOW_TREE:
                self.warnings.append(
                    f"{params.path}: rfunc {params.rfunc} evaluates all {nodes:,} nodes of the BSP-tree at every "
                    "voxel near the surface (about 1 ns per node and voxel: seconds to minutes at 256^3); "
                    "rfunc: min_max has the same zero set and sign and evaluates only the nodes near each voxel "
                    "(docs/performance.md)")
        else:
            try:
                self.impl = ADFField.from_mesh(mesh, join=params.join, p=params.p)
            except ValueError as e:
                raise InputError(f"{params.path}: {e}") from None
            self.stats = {"faces": int(len(mesh.faces)), "method": "adf", "join": params.join, "p": params.p}

    def _repair_winding(self, mesh):
        """Faces wound inconsistently are re-oriented along the face adjacency (trimesh's
        fix_winding), then outwards; the warning says how many were flipped. A mesh that cannot be
        oriented consistently (non-orientable) is refused: its BSP-field would have a wrong sign."""
        import trimesh

        fixed = mesh.copy()
        trimesh.repair.fix_winding(fixed)
        if fixed.is_watertight and fixed.volume < 0:
            fixed.invert()
        if not fixed.is_winding_consistent:
            raise InputError(f"{self.params.path}: face winding is inconsistent and cannot be repaired "
                             "(the surface is not orientable); fix the mesh")
        flipped = int(np.count_nonzero(~_same_orientation(fixed.faces, mesh.faces)))  # rows keep their order
        self.warnings = [w for w in self.warnings if "winding is inconsistent" not in w]
        self.warnings.append(f"{self.params.path}: face winding was inconsistent: {flipped} of {len(mesh.faces)} "
                             "faces flipped to one outward orientation")
        self.report.winding_repaired = flipped
        return fixed

    def field(self, x, y, z, t):
        if isinstance(x, Sym) or isinstance(y, Sym) or isinstance(z, Sym):
            return self._lower(x, y, z)
        if isinstance(x, AffineForm):
            boxes = [AffineForm.interval(v) if isinstance(v, AffineForm) else (v, v) for v in (x, y, z)]
            lo = np.stack([np.broadcast_to(b[0], x.c.shape) for b in boxes], axis=1)
            hi = np.stack([np.broadcast_to(b[1], x.c.shape) for b in boxes], axis=1)
            flo, fhi = self.impl.bound(lo, hi)
            return AffineForm.from_interval(flo, fhi)
        shape = np.broadcast(x, y, z).shape
        pts = np.stack([np.broadcast_to(v, shape).ravel() for v in (x, y, z)], axis=1)
        return self.impl.evaluate(pts).reshape(shape)

    def _lower(self, x, y, z):
        """The BSP-field as one tape clause for ``min_max``: an oracle the tape's kernels run with
        the exact short-circuit rules of pipeline.mesh.bsp_minmax, which each cell of the voxelise
        descent specialises to the node its box starts from. r0 and sardf depend on every node
        everywhere (no exact pruning), so they stay a node-by-node oracle; the ADF field likewise."""
        if self.params.method != "bsp" or self.params.rfunc != "min_max":
            raise NotTraceable("mesh fields other than min_max BSP-fields are evaluated by their kernel")
        traced = next(v for v in (x, y, z) if isinstance(v, Sym))
        return traced.tb.bsp_field(x, y, z, self.impl.minmax_tree)

    def _make_sign_proxy(self) -> Node:
        """The min_max BSP-field of the same tree for r0 and sardf: the same sign at every point
        (an R-function's sign is min/max's), evaluated with the short-circuit kernels that skip
        the subtrees a cell's bounds exclude, where r0 and sardf depend on every node."""
        if self.params.method != "bsp" or self.params.rfunc == "min_max":
            return self
        twin = self.with_params(rfunc="min_max")
        twin.impl = self.impl.with_rfunc("min_max")
        return twin

    @property
    def faces_per_area(self) -> float:
        """Faces per unit of surface area: a mesh finer than the voxels is voxelised in smaller
        blocks (pipeline.voxel.voxelise.block_for)."""
        r = self.report
        return r.faces / r.area if r.area > 0 else 0.0

    def describe(self) -> dict:
        """Manifest entry: the mesh checks and the BSP-tree counts (Table 1 of bsp-fields)."""
        r = self.report
        return {"where": self.where, "path": self.params.path, "method": self.params.method,
                "faces": r.faces, "vertices": r.vertices, "watertight": r.watertight,
                "winding_consistent": r.winding_consistent, "degenerate_faces": r.degenerate_faces,
                "winding_repaired": getattr(r, "winding_repaired", 0),
                "components": r.components, "genus": r.genus, "tree": self.stats}


SLOW_TREE = 5000  # BSP nodes above which an r0 / sardf mesh field gets a warning about its cost


def _same_orientation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per face: do the index triples a and b list the same vertices in the same cyclic order?"""
    rolled = [np.roll(b, r, axis=1) for r in range(3)]
    return np.any([np.all(a == x, axis=1) for x in rolled], axis=0)
