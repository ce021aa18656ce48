"""The model tree: small composable nodes with one formula each.

A node is a class with a pydantic ``Params`` model (its YAML parameters) and one method,
``field(x, y, z, t)``, written with :mod:`pipeline.model.ops` and ordinary operators. The same code
evaluates the field on arrays of points and bounds it on arrays of boxes with revised affine
arithmetic, so new node types plug in without touching the evaluator: register the class with
``@register("name")`` and it is available in configs.

Sign convention (SPEC): f > 0 inside, f = 0 on the boundary, f < 0 outside.
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict

from pipeline.field.affine import AffineForm

REGISTRY: dict[str, type[Node]] = {}
AXES = {"x": 0, "y": 1, "z": 2}


def register(kind: str):
    """Class decorator: make a node type available in configs under ``kind``."""

    def deco(cls: type[Node]) -> type[Node]:
        cls.kind = kind
        REGISTRY[kind] = cls
        return cls

    return deco


def _finite(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError("must be a finite number")
    return v


def _finite_vec(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if not all(math.isfinite(c) for c in v):
        raise ValueError("must be three finite numbers")
    return v


Real = Annotated[float, AfterValidator(_finite)]
Vec3 = Annotated[tuple[float, float, float], AfterValidator(_finite_vec)]


class Params(BaseModel):
    """Base of every node's parameters: unknown keys are errors, values are validated."""

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, frozen=True)


class Node(ABC):
    """A model-tree node. Subclasses set ``Params`` and implement ``field``."""

    kind: ClassVar[str] = "node"
    Params: ClassVar[type[Params]] = Params
    #: parameter names that hold child nodes (a node, or a list of nodes)
    child_fields: ClassVar[tuple[str, ...]] = ()
    #: the bare YAML form: a list is shorthand for {<list_field>: [...]}
    list_field: ClassVar[str | None] = None
    #: the node does expensive work (a solve) when first evaluated: loading a config does not
    #: evaluate a tree that holds one (its values are checked as the stages evaluate it)
    solves_on_first_use: ClassVar[bool] = False
    #: an oracle: the node samples a mesh, a grid or a solved field (pipeline.oracles) instead
    #: of a formula the tape records, and its voxels cost more to evaluate
    oracle: ClassVar[bool] = False
    #: the node's sign is a function of its children's signs alone (coordinate maps, positive
    #: factors, R-functions, complement): :meth:`sign_proxy` may replace its children
    sign_from_children: ClassVar[bool] = False
    #: the node's values are finite at every finite point whatever its parameters (a mesh's
    #: BSP-field or ADF: plane distances of finite, bounded vertices): loading a config does not
    #: evaluate it to look for NaN or inf (pipeline.job.config.locate_nonfinite)
    finite_by_construction: ClassVar[bool] = False
    #: the node's values at a point are finite wherever its children's values at that same point
    #: are (R-functions under their magnitude control, complement): not evaluated either
    finite_from_children: ClassVar[bool] = False

    def __init__(self, params: Params, where: str = ""):
        self.params = params
        self.where = where  # YAML path of this node, for error messages

    def __getstate__(self) -> dict:
        # the compiled tapes pipeline.model.tape.compile_model keeps on the model are not sent to
        # workers (a mesh's tape holds its whole BSP-tree again); a worker traces its own
        state = self.__dict__.copy()
        state.pop("_tapes", None)
        state.pop("_sign_proxy", None)  # made again where needed (it shares the mesh's arrays)
        return state

    # --- the one formula ------------------------------------------------------------------
    @abstractmethod
    def field(self, x: Any, y: Any, z: Any, t: float) -> Any:
        """Defining function; x, y, z are arrays (evaluate) or AffineForms (bound)."""

    # --- the two ways to use it -----------------------------------------------------------
    def evaluate(self, points: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Field values at (N,3) points."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        with np.errstate(all="ignore"):
            out = self.field(p[:, 0], p[:, 1], p[:, 2], float(t))
        return np.broadcast_to(np.asarray(out, dtype=np.float64), (len(p),)).copy()

    def evaluate_xyz(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Field values at points given as three coordinate arrays of one shape."""
        with np.errstate(all="ignore"):
            out = self.field(x, y, z, float(t))
        return np.broadcast_to(np.asarray(out, dtype=np.float64), np.shape(x))

    def bound_form(self, lo: np.ndarray, hi: np.ndarray, t: float = 0.0) -> AffineForm:
        """Revised affine form of the field over boxes lo..hi (B,3)."""
        x, y, z = AffineForm.coordinates(lo, hi)
        with np.errstate(all="ignore"):
            f = self.field(x, y, z, float(t))
        if not isinstance(f, AffineForm):  # constant field
            c = np.broadcast_to(np.asarray(f, float), x.c.shape).copy()
            f = AffineForm(c, np.zeros_like(x.g), np.zeros_like(x.e))
        return f

    def bound(self, lo: np.ndarray, hi: np.ndarray, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Rigorous (lower, upper) bound of the field over each box lo..hi (B,3)."""
        flo, fhi = self.bound_form(lo, hi, t).interval()
        flo = np.where(np.isnan(flo), -np.inf, flo)
        fhi = np.where(np.isnan(fhi), np.inf, fhi)
        return flo, fhi

    # --- the sign alone -------------------------------------------------------------------
    def sign_proxy(self) -> Node:
        """A model with this one's sign at every point that is cheaper to evaluate and to bound,
        or ``self``. R-functions have the sign of min/max (bsp-fields section 2), so a mesh's
        r0 / sardf BSP-field has the sign of its min_max field, whose kernels prune the tree per
        cell; a node whose sign follows from its children's signs (``sign_from_children``) is
        the same node over their proxies, with min_max set operations. The voxeliser finds the
        band's sign changes with the proxy and evaluates the model only where the band's
        distance test reads values (pipeline.voxel.voxelise.voxelise); components and
        collisions depend on the sign alone and use it throughout. Made once per node (so its
        tape is traced once)."""
        proxy = self.__dict__.get("_sign_proxy")
        if proxy is None:
            proxy = self.__dict__["_sign_proxy"] = self._make_sign_proxy()
        return proxy

    def _make_sign_proxy(self) -> Node:
        if not self.sign_from_children:
            return self
        update: dict[str, Any] = {}
        for name in self.child_fields:
            v = getattr(self.params, name)
            olds = list(v) if isinstance(v, (list, tuple)) else [v]
            kids = [c.sign_proxy() for c in olds]
            if any(k is not c for k, c in zip(kids, olds, strict=True)):
                update[name] = kids if isinstance(v, (list, tuple)) else kids[0]
        if not update:
            return self
        if "rfunc" in type(self.params).model_fields:
            update["rfunc"] = "min_max"
        return self.with_params(**update)

    def with_params(self, **update: Any) -> Node:
        """A copy of this node with some parameters replaced (no re-validation, no cached tapes)."""
        clone = copy.copy(self)
        clone.__dict__.pop("_tapes", None)
        clone.__dict__.pop("_sign_proxy", None)
        clone.params = self.params.model_copy(update=update)
        return clone

    # --- tree helpers ---------------------------------------------------------------------
    def children(self) -> list[Node]:
        out: list[Node] = []
        for name in self.child_fields:
            v = getattr(self.params, name)
            out.extend(v if isinstance(v, (list, tuple)) else [v])
        return out

    def walk(self):
        yield self
        for c in self.children():
            yield from c.walk()

    def __repr__(self) -> str:
        return f"<{self.kind} at {self.where or 'model'}>"


def axis_index(name: str) -> int:
    return AXES[name]


#: (u, v, w) as positions in (x, y, z), w along the axis; and back
_TO_UVW = {"x": (1, 2, 0), "y": (2, 0, 1), "z": (0, 1, 2)}
_TO_XYZ = {a: tuple(order.index(k) for k in range(3)) for a, order in _TO_UVW.items()}


def permute(x, y, z, axis: str):
    """(u, v, w) with w along ``axis``: lets z-axis formulas serve any axis."""
    xyz = (x, y, z)
    return tuple(xyz[i] for i in _TO_UVW[axis])


def unpermute(u, v, w, axis: str):
    """Inverse of :func:`permute`: back from (u, v, w) to (x, y, z)."""
    uvw = (u, v, w)
    return tuple(uvw[i] for i in _TO_XYZ[axis])


def local_uvw(x, y, z, center, axis: str):
    """(u, v, w) of the point relative to ``center``, w along ``axis``."""
    return permute(x - center[0], y - center[1], z - center[2], axis)
