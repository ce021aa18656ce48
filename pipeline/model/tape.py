"""The model lowered once to a flat tape, and compiled evaluators over it (issue 13).

**Lowering.** A model tree is traced: every node's own ``field(x, y, z, t)`` formula runs once
on :class:`Sym` values, which record each operation as a clause (op, a, b, const) instead of
computing it. Identical clauses are shared (hash-consing: a subtree used twice is one set of
clauses) and clauses whose operands are constants are folded. So a node type still writes
its formula once (with :mod:`pipeline.model.ops`) and gets the tape for free; nodes whose formula
cannot be traced (oracles that sample meshes, grids or solved fields) make :func:`compile_model`
return None and the model keeps the node-by-node evaluator.

**Evaluators** (Numba, one clause loop per point or per box; cf. libfive's and Fidget's tapes):

- :func:`eval_blocks`: values at the voxel centres of blocks, each block with its own tape;
  :func:`eval_leaves`: the same, written into the blocks' 8^3 leaves in one pass (the band is
  marked on the leaves afterwards: pipeline.voxel.band);
- :func:`bound_boxes`: interval bounds over boxes, each box with its own tape, recording for
  every ``min``/``max`` clause which operand decides it over the box;
- :func:`specialise`: from those choices, the box's shortened tape — a ``min`` whose operand
  intervals do not overlap *is* the lower operand everywhere in the box, so the other operand's
  clauses are dropped when nothing else uses them. This is exact (the same value to the bit)
  for ``min``/``max`` (``min_max`` R-functions, boxes, cylinders, clamps). ``r0`` and ``sardf``
  depend on both operands everywhere and are never pruned (their clauses are monotone, so their
  bounds are simply the values at the interval ends).

Children of a cell start from their parent's shortened tape, so a union of 10^4 parts costs,
per voxel, what the few parts near it cost.

Tape layout: arrays ``op, a, b`` (int64) and ``c`` (float64) of one or many tapes back to back;
tape ``i`` is ``start[i] .. start[i] + length[i]`` and its value is the one of clause
``start[i] + res[i]``. Operands ``a, b`` are positions within the tape (earlier clauses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import prange

from pipeline.field.rkernels import compress, r0_and, sardf_and
from pipeline.mesh.bsp_minmax import (
    BLOCK_TREE_MAX,
    BVH_STACK,
    block_values,
    box_bound,
    box_near_surface,
    point_plane,
    point_value,
    specialise_box,
    surface_bvh,
    tree_depth,
)
from pipeline.util.jit import njit

# --- opcodes ------------------------------------------------------------------------------------
X, Y, Z, CONST, ADD, SUB, MUL, DIV, NEG, SQRT, SQR, ABS, EXP, LOG, SIN, COS, POWC, MIN, MAX, R0AND, \
    SARDFAND, COMPRESS, BSPXY, BSP, ADDC, MULC, RSUBC, DIVC, RDIVC = range(29)
NAMES = ["x", "y", "z", "const", "add", "sub", "mul", "div", "neg", "sqrt", "sqr", "abs", "exp", "log", "sin",
         "cos", "powc", "min", "max", "r0and", "sardfand", "compress", "bspxy", "bsp", "addc", "mulc", "rsubc",
         "divc", "rdivc"]
ORACLES = {BSPXY, BSP}  # never folded: their value needs the oracle arrays
# the arithmetic of one operand and the clause's constant c (a + c, a * c, c - a, a / c, c / a): a
# constant operand is not a clause of its own, so a sphere is 11 clauses, not 15 (Fidget's
# register-immediate opcodes do the same)
IMMEDIATE = {ADDC, MULC, RSUBC, DIVC, RDIVC}
UNARY = {NEG, SQRT, SQR, ABS, EXP, LOG, SIN, COS, POWC, COMPRESS} | IMMEDIATE


# storage of a tape's clauses: an opcode fits a byte and an operand index 32 bits (17 bytes a
# clause with its float64 constant instead of 32: the pools of a descent's fine levels hold
# hundreds of millions of clauses, and on this project's VMs their first touch is what costs)
OP_T = np.int8
IX_T = np.int32


class NotTraceable(TypeError):
    """A node's formula uses something the tape cannot record (an oracle, a Python branch)."""


class TapeBuilder:
    """Collects clauses in order; identical clauses are shared, constant ones folded."""

    def __init__(self) -> None:
        self.op: list[int] = []
        self.a: list[int] = []
        self.b: list[int] = []
        self.c: list[float] = []
        self.memo: dict[tuple, int] = {}
        self.trees: list = []  # min_max BSP-trees of the mesh clauses, in order
        self.tree_base: dict[int, int] = {}  # id(tree) -> index of its first node in the oracle arrays
        self.nodes = 0

    def bsp_field(self, x, y, z, tree) -> Sym:
        """The min_max BSP-field of ``tree`` at traced coordinates: one oracle clause (BSP,
        operands BSPXY(x, y) and z, constant = the node it starts from, the root at first)."""
        if id(tree) not in self.tree_base:
            self.tree_base[id(tree)] = self.nodes
            self.trees.append(tree)
            self.nodes += len(tree.mode)
        root = float(self.tree_base[id(tree)] + len(tree.mode) - 1)
        xs, ys, zs = (v if isinstance(v, Sym) else self.const(float(v)) for v in (x, y, z))
        xy = self.emit(BSPXY, xs.pos, ys.pos, root)
        return self.emit(BSP, xy.pos, zs.pos, root)

    def oracle(self) -> Oracle:
        """The BSP-trees of the traced mesh clauses as one set of arrays (child indices global)."""
        if not self.trees:
            return Oracle.empty()
        parts = [(t, self.tree_base[id(t)]) for t in self.trees]
        shift = [np.where(t.pos >= 0, t.pos + b, -1) for t, b in parts], [np.where(t.neg >= 0, t.neg + b, -1)
                                                                           for t, b in parts]
        depth = max(int(tree_depth(t.pos.astype(np.int64), t.neg.astype(np.int64))) for t, _ in parts)  # stack room
        return Oracle(np.ascontiguousarray(np.concatenate([t.normals for t, _ in parts]), np.float64),
                      np.concatenate([t.offsets for t, _ in parts]).astype(np.float64),
                      np.concatenate(shift[0]).astype(np.int64), np.concatenate(shift[1]).astype(np.int64),
                      np.concatenate([t.mode for t, _ in parts]).astype(np.int64), depth,
                      *_surfaces([(t, b, len(t.mode)) for t, b in parts]))

    def emit(self, op: int, a: int = -1, b: int = -1, c: float = 0.0) -> Sym:
        ops = self.op
        if op == NEG and ops[a] == NEG:  # -(-v) is v: unions -min(-a, -b) then chain into one min tree
            return Sym(self, self.a[a])
        if op in _MINMAX:
            if ops[a] == NEG and ops[b] == NEG:
                # min(-a, -b) is -max(a, b) exactly: a min_max union (-min(-a, -b)) becomes a max
                # tree with no negation per part
                return self.emit(NEG, self.emit(MAX if op == MIN else MIN, self.a[a], self.a[b]).pos)
            if a == b:  # min(v, v) is v (a part given twice)
                return Sym(self, a)
        elif op in _ARITH and (ops[a] == CONST) != (ops[b] == CONST):
            op, a, b, c = self._immediate(op, a, b)
        if (op, c) in _IDENTITY:  # a + 0, a * 1, a / 1, a ** 1 are a (a centre at 0, a unit radius)
            return Sym(self, a)
        if op in _COMMUTATIVE and a > b:  # one key for both orders
            a, b = b, a
        key = (op, a, b, c)
        pos = self.memo.get(key)
        if pos is None:
            if op not in _LEAVES and ops[a] == CONST and (b < 0 or ops[b] == CONST):
                return self.const(self._fold(op, a, b, c))
            pos = len(ops)
            ops.append(op)
            self.a.append(a)
            self.b.append(b)
            self.c.append(c)
            self.memo[key] = pos
        return Sym(self, pos)

    def _immediate(self, op: int, a: int, b: int) -> tuple[int, int, int, float]:
        """(op, a, -1, c) of an arithmetic clause with exactly one constant operand."""
        if self.op[b] == CONST:
            return immediate_clause(op, a, self.c[b], False)
        return immediate_clause(op, b, self.c[a], True)

    def const(self, v: float) -> Sym:
        v = float(v)
        key = (CONST, -1, -1, v)
        pos = self.memo.get(key)
        if pos is None:
            pos = len(self.op)
            self.op.append(CONST)
            self.a.append(-1)
            self.b.append(-1)
            self.c.append(v)
            self.memo[key] = pos
        return Sym(self, pos)

    def _fold(self, op: int, a: int, b: int, c: float) -> float:
        """The value of a clause whose operands are all constants."""
        va = self.c[a]
        vb = self.c[b] if b >= 0 else 0.0
        with np.errstate(all="ignore"):
            return float(_scalar_eval(op, va, vb, c))


_MINMAX = frozenset((MIN, MAX))
_ARITH = frozenset((ADD, SUB, MUL, DIV))
_COMMUTATIVE = frozenset((ADD, MUL, MIN, MAX, R0AND))
_LEAVES = frozenset((X, Y, Z, CONST)) | ORACLES  # never folded
# clauses equal to their operand: exactly (a * 1, a / 1, a ** 1, a + -0) or but for the sign of a
# zero (-0 + 0 is +0; the field's sign tests compare with 0, where the two zeros are equal)
_IDENTITY = frozenset(((ADDC, 0.0), (MULC, 1.0), (DIVC, 1.0), (POWC, 1.0)))


@njit(cache=True)
def _scalar_eval(op, va, vb, c):
    return _apply(op, va, vb, c)


_NUMBERS = frozenset((float, int, np.float64, np.float32, np.int64, np.int32))
# (op, the number first) -> (immediate opcode, its constant is the number (True) or its negation)
_IMMEDIATE_OF = {(ADD, False): (ADDC, True), (ADD, True): (ADDC, True), (SUB, False): (ADDC, False),
                 (SUB, True): (RSUBC, True), (MUL, False): (MULC, True), (MUL, True): (MULC, True),
                 (DIV, False): (DIVC, True), (DIV, True): (RDIVC, True)}


def immediate_clause(op: int, pos: int, k: float, number_first: bool) -> tuple[int, int, int, float]:
    """(opcode, operand, -1, constant) of ``op`` between clause ``pos`` and the number k (first
    when ``number_first``): a - k is a + (-k) to the bit in IEEE arithmetic."""
    imm, same = _IMMEDIATE_OF[op, number_first]
    return imm, pos, -1, k if same else -k


class Sym:
    """A traced value: position of its clause in the builder. Arithmetic records clauses."""

    __slots__ = ("tb", "pos")
    __array_priority__ = 1000  # numpy scalars defer to our operators

    def __init__(self, tb: TapeBuilder, pos: int) -> None:
        self.tb = tb
        self.pos = pos

    def _lift(self, other) -> Sym:
        if isinstance(other, Sym):
            return other
        if isinstance(other, (int, float, np.floating, np.integer)) and not isinstance(other, bool):
            return self.tb.const(float(other))
        raise NotTraceable(f"cannot trace an operation with {type(other).__name__}")

    def _bin(self, op: int, other, swap: bool = False) -> Sym:
        if type(other) in _NUMBERS and self.tb.op[self.pos] != CONST:  # no constant clause to look up
            return self.tb.emit(*immediate_clause(op, self.pos, float(other), swap))
        o = self._lift(other)
        a, b = (o, self) if swap else (self, o)
        return self.tb.emit(op, a.pos, b.pos)

    def __add__(self, o):
        return self._bin(ADD, o)

    def __radd__(self, o):
        return self._bin(ADD, o, True)

    def __sub__(self, o):
        return self._bin(SUB, o)

    def __rsub__(self, o):
        return self._bin(SUB, o, True)

    def __mul__(self, o):
        return self._bin(MUL, o)

    def __rmul__(self, o):
        return self._bin(MUL, o, True)

    def __truediv__(self, o):
        return self._bin(DIV, o)

    def __rtruediv__(self, o):
        return self._bin(DIV, o, True)

    def __neg__(self):
        return self.tb.emit(NEG, self.pos)

    def __pos__(self):
        return self

    def __bool__(self):
        raise NotTraceable("a formula branches on a traced value")

    def unary(self, op: int, c: float = 0.0) -> Sym:
        return self.tb.emit(op, self.pos, -1, c)


def binary(op: int, a, b) -> Sym:
    """``op`` of two values at least one of which is a Sym."""
    s = a if isinstance(a, Sym) else b
    return s.tb.emit(op, s._lift(a).pos, s._lift(b).pos)


# --- a compiled model ----------------------------------------------------------------------------


@dataclass
class Oracle:
    """The BSP-trees (pipeline.mesh.bsp_minmax layout) that the tape's mesh clauses evaluate, back to
    back with global child indices; ``depth``: the longest root path (stack room).

    The surfaces of the closed meshes among them (``Tree.surface``, triangles), as one triangle
    BVH (bsp_minmax.surface_bvh's arrays, back to back: ``tri`` (T, 9), ``sbox`` (N, 6), ``skid``
    and ``sspan`` (N, 2), global indices), and per tree ``minfo`` (M, 3): first node, end node,
    BVH root (-1: no surface, an open mesh), ``mtol`` (M, 2): the distance within which a triangle
    counts as meeting a box, and the point value below which a sign is not trusted."""

    normals: np.ndarray
    offsets: np.ndarray
    pos: np.ndarray
    neg: np.ndarray
    mode: np.ndarray
    depth: int
    tri: np.ndarray = None
    sbox: np.ndarray = None
    skid: np.ndarray = None
    sspan: np.ndarray = None
    minfo: np.ndarray = None
    mtol: np.ndarray = None

    def __post_init__(self):
        if self.tri is None:
            z2 = np.zeros((0, 2), np.int64)
            self.tri, self.sbox, self.skid, self.sspan = np.zeros((0, 9)), np.zeros((0, 6)), z2, z2.copy()
            self.minfo, self.mtol = np.zeros((0, 3), np.int64), np.zeros((0, 2))

    @classmethod
    def empty(cls) -> Oracle:
        z = np.zeros(0, np.int64)
        return cls(np.zeros((0, 3)), np.zeros(0), z, z, z, 0)

    def arrays(self) -> tuple:
        """The arguments the kernels take after the tape arrays."""
        return (self.normals, self.offsets, self.pos, self.neg, self.mode, self.tri, self.sbox, self.skid,
                self.sspan, self.minfo, self.mtol), self.depth


SURFACE_MARGIN = 1e-6  # x the mesh's diagonal: a triangle this near a box may meet the field's zero set there


def _surfaces(parts: list) -> tuple:
    """The Oracle's surface arrays for trees (tree, first node, node count); a tree without a
    ``surface`` (an open mesh, a polygon set) gets BVH root -1. The BVH of a tree is built once."""
    tris, boxes, kids, spans = [np.zeros((0, 9))], [np.zeros((0, 6))], [np.zeros((0, 2), np.int64)], \
        [np.zeros((0, 2), np.int64)]
    minfo, mtol = [], []
    nt = nn = 0
    for tree, base, count in parts:
        surf = getattr(tree, "surface", None)
        if surf is None or len(surf) == 0:
            minfo.append((base, base + count, -1))
            mtol.append((0.0, 0.0))
            continue
        if getattr(tree, "_bvh", None) is None:
            tree._bvh = surface_bvh(np.ascontiguousarray(surf, dtype=np.float64))
        flat, box, kid, span = tree._bvh
        tris.append(flat)
        boxes.append(box)
        kids.append(np.where(kid >= 0, kid + nn, -1))
        spans.append(span + np.array([nt, 0]))
        minfo.append((base, base + count, nn))
        size = float(np.linalg.norm(np.ptp(flat.reshape(-1, 3), axis=0)))
        big = float(np.abs(flat).max())
        # the zero set lies within the build's tolerances (1e-9 x size) of the triangles; the SAT
        # test and a plane's value at a point round at ~1e-16 x the coordinates
        mtol.append((SURFACE_MARGIN * size + 1e-12 * big, 1e-12 * (size + big)))
        nt += len(flat)
        nn += len(box)
    return (np.ascontiguousarray(np.concatenate(tris)), np.ascontiguousarray(np.concatenate(boxes)),
            np.ascontiguousarray(np.concatenate(kids)), np.ascontiguousarray(np.concatenate(spans)),
            np.array(minfo, np.int64).reshape(-1, 3), np.array(mtol, np.float64).reshape(-1, 2))


@dataclass
class Tape:
    """One tape (arrays as in the module docstring, a single tape starting at 0) and the
    oracle arrays of its mesh clauses."""

    op: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    res: int
    oracle: Oracle = None

    def __post_init__(self):
        if self.oracle is None:
            self.oracle = Oracle.empty()
        self.op, self.a, self.b = _clause_arrays(self.op, self.a, self.b)

    def __len__(self) -> int:
        return len(self.op)

    @property
    def shortens(self) -> bool:
        """Whether a cell's box can shorten the tape: it has a min / max (or a mesh clause,
        whose walk can start deeper) for :func:`specialise` to decide."""
        return bool(np.isin(self.op, (MIN, MAX, BSP)).any())

    def counts(self) -> dict[str, int]:
        u, n = np.unique(self.op, return_counts=True)
        return {NAMES[int(k)]: int(v) for k, v in zip(u, n, strict=True)}


def _clause_arrays(op, a, b) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """op, a, b in their storage types (OP_T, IX_T; no copy when they are already)."""
    return (np.ascontiguousarray(op, dtype=OP_T), np.ascontiguousarray(a, dtype=IX_T),
            np.ascontiguousarray(b, dtype=IX_T))


@dataclass
class TapePool:
    """Tapes back to back (the layout of the module docstring), one per cell of a level of a
    descent (voxelise's, components'): tape i starts at start[i] and has length[i] clauses."""

    start: np.ndarray
    length: np.ndarray
    res: np.ndarray
    op: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    oracle: Oracle  # the mesh clauses' trees, shared by every tape of the pool

    def __post_init__(self):
        self.op, self.a, self.b = _clause_arrays(self.op, self.a, self.b)

    @classmethod
    def single(cls, tape: Tape) -> TapePool:
        one = np.zeros(1, np.int64)
        return cls(one, np.array([len(tape)], np.int64), np.array([tape.res], np.int64), tape.op, tape.a,
                   tape.b, tape.c, tape.oracle)

    def arrays(self) -> tuple:
        return self.start, self.length, self.res, self.op, self.a, self.b, self.c

    def with_arrays(self, arrays: tuple) -> TapePool:
        """A pool of new tapes (specialise's result) over the same oracle."""
        return TapePool(*arrays, self.oracle)

    @property
    def max_length(self) -> int:
        return int(self.length.max()) if len(self.length) else 0

    def decision_arrays(self, tape_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(choff, choices) for the decisions of boxes with the tapes ``tape_of``: box q's clause k
        at choices[choff[q] + k] (int32: a mesh clause records its start node)."""
        lens = self.length[tape_of]
        choff = np.concatenate([[0], np.cumsum(lens)[:-1]]).astype(np.int64)
        return choff, np.zeros(int(lens.sum()), np.int32)

    def evaluate(self, points: np.ndarray, tape_of: np.ndarray | None = None) -> np.ndarray:
        """Values at points (N, 3), point i by tape ``tape_of[i]`` (None: tape 0). Consecutive
        points of the same tape are evaluated together, so give the points of a tape together."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if tape_of is None:
            bs = point_batches(len(p))
            bt = np.zeros(len(bs) - 1, np.int64)
        else:  # runs of one tape: cells that share their parent's tape share its start
            tape_of = np.asarray(tape_of, np.int64)
            bs = point_batches(len(p), self.start[tape_of])
            bt = tape_of[bs[:-1]]
        return eval_points(p, bs, bt, *self.arrays(), *self.oracle.arrays(), max(self.max_length, 1))

    def surface_sides(self, lo: np.ndarray, hi: np.ndarray, tape_of: np.ndarray | None = None,
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Per closed box lo[q]..hi[q] (world, (N, 3)) with tape ``tape_of[q]`` (None: tape 0),
        :func:`_surface_cull` over the box: kind 1 when the tape is one closed mesh's clause at
        the plain coordinates and no triangle comes near the box (the field has no zero there;
        its sign is that of ``value``), 2 when one does (the surface may cross the box), 0 when
        this does not apply (other tapes, open meshes, a point value too near 0 to trust)."""
        n = len(lo)
        tape_of = np.zeros(n, np.int64) if tape_of is None else np.asarray(tape_of, np.int64)
        orc, odepth = self.oracle.arrays()
        if n == 0 or orc[9].shape[0] == 0:
            return np.zeros(n, np.int8), np.zeros(n)
        return _surface_sides(np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64),
                              tape_of, self.start, self.res, self.op, self.a, self.b, self.c, orc, odepth)

    def specialised(self, tape_of: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> TapePool:
        """Tape i of the result: tape ``tape_of[i]`` shortened to the closed box lo[i]..hi[i]
        (world, (N, 3)) by the interval decisions of :func:`bound_boxes` and :func:`specialise`:
        the same values as that tape everywhere in the box, to the bit."""
        tape_of = np.asarray(tape_of, np.int64)
        choff, choices = self.decision_arrays(tape_of)
        if len(tape_of):
            bound_boxes(np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64),
                        tape_of, *self.arrays(), *self.oracle.arrays(), max(self.max_length, 1), choff, choices)
        return self.with_arrays(specialise(np.arange(len(tape_of), dtype=np.int64), tape_of, *self.arrays(),
                                           choff, choices))


def compile_model(model, t: float = 0.0) -> Tape | None:
    """The model's tape (after dead-clause removal), or None when a node cannot be traced.

    Traced once per model and time in a process (the tape is kept on the model: voxelise, every
    brick of it and components use the same one; tracing 10^4 parts takes ~0.5 s of Python)."""
    cache = model.__dict__.setdefault("_tapes", {}) if hasattr(model, "__dict__") else {}
    if float(t) not in cache:
        cache[float(t)] = _trace(model, t)
    return cache[float(t)]


def _trace(model, t: float) -> Tape | None:
    tb = TapeBuilder()
    x, y, z = tb.emit(X), tb.emit(Y), tb.emit(Z)
    try:
        with np.errstate(all="ignore"):
            out = model.field(x, y, z, float(t))
    except NotTraceable:
        return None
    except (TypeError, AttributeError, ValueError):  # a node's formula works on arrays only
        return None
    if not isinstance(out, Sym):
        out = tb.const(float(out))
    full = (np.array(tb.op, np.int64), np.array(tb.a, np.int64), np.array(tb.b, np.int64),
            np.array(tb.c, np.float64))
    op, a, b, c, res = _compact(*full, out.pos)
    return Tape(op, a, b, c, res, tb.oracle())


def bound_with(tape: Tape, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval bounds of one tape over boxes lo..hi (B, 3)."""
    lo = np.ascontiguousarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.ascontiguousarray(hi, dtype=np.float64).reshape(-1, 3)
    n = len(lo)
    one = np.zeros(1, np.int64)
    choff = np.arange(n, dtype=np.int64) * len(tape)
    choices = np.zeros(n * len(tape), np.int32)
    return bound_boxes(lo, hi, np.zeros(n, np.int64), one, np.array([len(tape)]), np.array([tape.res]),
                       tape.op, tape.a, tape.b, tape.c, *tape.oracle.arrays(), max(len(tape), 1), choff, choices)


def evaluate_with(tape: Tape, points: np.ndarray) -> np.ndarray:
    """Values of one tape at points (N, 3)."""
    return TapePool.single(tape).evaluate(points)


def eval_blocks_with(tape: Tape, origins: np.ndarray, block: int, h: float) -> np.ndarray:
    """Values (N, block, block, block) of one tape at the voxel centres of blocks (the voxeliser's
    lattice evaluator, :func:`eval_blocks`)."""
    o = np.ascontiguousarray(origins, dtype=np.int64).reshape(-1, 3)
    n = len(tape)
    return eval_blocks(o, int(block), float(h), np.zeros(len(o), np.int64), np.zeros(1, np.int64), np.array([n]),
                       np.array([tape.res]), tape.op, tape.a, tape.b, tape.c, *tape.oracle.arrays(), max(n, 1))


def gradient_with(tape: Tape, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values (N,) and gradients (N, 3) of one tape at points (N, 3) (forward mode)."""
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return eval_points_grad(p, np.zeros(1, np.int64), np.array([len(tape)]), np.array([tape.res]), tape.op, tape.a,
                            tape.b, tape.c, *tape.oracle.arrays())


def _compact(op, a, b, c, res):
    """Keep the clauses the result depends on (tracing may leave unused ones), renumbered."""
    n = len(op)
    alias = np.arange(n, dtype=np.int64)
    choice = np.zeros(n, np.int8)
    nop, na, nb, nc, nres = _specialise_one(op, a, b, c, alias, choice, np.int64(res))
    return nop, na, nb, nc, nres


# --- the clause arithmetic (Numba) -----------------------------------------------------------------


@njit(cache=True, inline="always")
def _powc(v, p):
    if v < 0.0 and p != np.floor(p):  # np.floor: math.floor is an int64 in Numba (overflows at 1e20)
        return math.nan
    if v == 0.0 and p < 0:
        return math.inf
    return v ** p


@njit(cache=True, inline="always")
def _div(va, vb):
    """va / vb with NumPy's IEEE results where Numba would raise (division by zero)."""
    if vb == 0.0:
        return math.nan if va == 0.0 or va != va else math.copysign(math.inf, va) * math.copysign(1.0, vb)
    return va / vb


@njit(cache=True)
def _apply(op, va, vb, c):
    """The value of one clause (twin of numpy's semantics in pipeline.model.ops / rfunctions)."""
    if op == ADD:
        return va + vb
    if op == SUB:
        return va - vb
    if op == MUL:
        return va * vb
    if op == DIV:
        return _div(va, vb)
    if op == ADDC:
        return va + c
    if op == MULC:
        return va * c
    if op == RSUBC:
        return c - va
    if op == DIVC:
        return _div(va, c)
    if op == RDIVC:
        return _div(c, va)
    if op == NEG:
        return -va
    if op == SQRT:
        return math.sqrt(va) if va >= 0.0 else math.nan
    if op == SQR:
        return va * va
    if op == ABS:
        return abs(va)
    if op == EXP:
        return math.exp(va) if va < 709.7 else math.inf
    if op == LOG:
        if va > 0.0:
            return math.log(va)
        return -math.inf if va == 0.0 else math.nan
    if op == SIN:
        return math.sin(va)
    if op == COS:
        return math.cos(va)
    if op == POWC:
        return _powc(va, c)
    if op == MIN:
        return min(va, vb) if va == va and vb == vb else math.nan
    if op == MAX:
        return max(va, vb) if va == va and vb == vb else math.nan
    if op == R0AND:
        return r0_and(va, vb)
    if op == SARDFAND:
        return sardf_and(va, vb, c)
    if op == COMPRESS:
        return compress(va, c)
    return c  # CONST


@njit(cache=True)
def _specialise_batch(x, y, z, m, st, orc, sj, sv, cn, co, cp, cq, cm):
    """The mesh tree from node ``st`` specialised to the box of the points (x, y, z)[:m]; the
    root in the scratch tree, or -1 when a coordinate is not finite."""
    lo0 = hi0 = x[0]
    lo1 = hi1 = y[0]
    lo2 = hi2 = z[0]
    for v in range(1, m):
        lo0, hi0 = min(lo0, x[v]), max(hi0, x[v])
        lo1, hi1 = min(lo1, y[v]), max(hi1, y[v])
        lo2, hi2 = min(lo2, z[v]), max(hi2, z[v])
    big = max(max(abs(lo0), abs(hi0)), max(max(abs(lo1), abs(hi1)), max(abs(lo2), abs(hi2))))
    if not math.isfinite(big + lo0 + lo1 + lo2):
        return -1
    pad = 1e-14 * (1.0 + big)  # as _bound_bsp: covers the rounding of a plane's value at a point
    return specialise_box(lo0, lo1, lo2, hi0, hi1, hi2, st, orc[0], orc[1], orc[2], orc[3], orc[4], pad, sj, sv,
                          cn, co, cp, cq, cm)


# costly clauses worth running once per distinct coordinate value (cheap ones cost less than the copy)
SEPARABLE = (DIV, DIVC, RDIVC, SQRT, EXP, LOG, SIN, COS, POWC, R0AND, SARDFAND, COMPRESS)


@njit(cache=True, inline="always")
def _clause_dep(o, ia, ib, dep):
    """Bits of the coordinates (x 1, y 2, z 4) a clause depends on; a mesh oracle on all."""
    if o == X:
        return 1
    if o == Y:
        return 2
    if o == Z:
        return 4
    if o == CONST:
        return 0
    if o in (BSP, BSPXY):
        return 7
    return dep[ia] | (dep[ib] if ib >= 0 else 0)


@njit(cache=True, inline="always")
def _on_lattice(o, ia, ib, ck, reg, k, lat, dk):
    """Clause k over a lat^3 lattice batch when it depends on the coordinates ``dk`` only: the
    value at each point whose other coordinates are the first is computed, the others copy it
    (their representative comes earlier in the batch's order)."""
    v = 0
    for i in range(lat):
        ri = (i if dk & 1 else 0) * lat
        for j in range(lat):
            rj = (ri + (j if dk & 2 else 0)) * lat
            for w in range(lat):
                r = rj + (w if dk & 4 else 0)
                if r == v:
                    reg[k, v] = _apply(o, reg[ia, v], reg[ib, v] if ib >= 0 else 0.0, ck)
                else:
                    reg[k, v] = reg[k, r]
                v += 1


@njit(cache=True)
def _run_batch(op, a, b, c, s, n, res, px, py, pz, reg, m, orc, sj, sv, spec, cn, co, cp, cq, cm, treg, tfa, lat,
               dep):
    """Clause-major: each clause runs over the m points of the batch (the dispatch on the
    opcode is paid once per clause, the inner loops are plain arithmetic). With ``spec`` (the
    points of a voxel block: close together) a mesh clause first specialises its BSP-tree to
    the bounding box of the batch's own coordinates (exact, bsp_minmax.specialise_box) into the
    scratch tree (cn, co, cp, cq, cm), then runs the points on that: tree-major
    (bsp_minmax.block_values, registers ``treg``, ``tfa``) when it fits, else point by point.

    With ``lat`` > 0 the m points are a lat^3 lattice (voxel centres, x slowest): a costly
    clause (:data:`SEPARABLE`) that depends on one or two of the coordinates only (``dep``:
    scratch for the coordinate bits of each clause) runs once per distinct value of them and is
    copied to the rest - a superellipsoid's three powers, a gyroid's six sines and cosines.
    The same operations on the same operands: the same values to the bit."""
    for k in range(n):
        o = op[s + k]
        ck = c[s + k]
        if lat:
            dk = _clause_dep(o, a[s + k], b[s + k], dep)
            dep[k] = dk
            if 0 < dk < 7 and o in SEPARABLE:
                _on_lattice(o, a[s + k], b[s + k], ck, reg, k, lat, dk)
                continue
        if o == X:
            reg[k, :m] = px[:m]
            continue
        if o == Y:
            reg[k, :m] = py[:m]
            continue
        if o == Z:
            reg[k, :m] = pz[:m]
            continue
        if o == CONST:
            reg[k, :m] = ck
            continue
        ia, ib = a[s + k], b[s + k]
        if o == BSP:  # the mesh oracle from its start node; coordinates: BSPXY's operands and z
            xa, ya, st = a[s + ia], b[s + ia], np.int64(ck)
            if spec and m > 1:
                root = _specialise_batch(reg[xa], reg[ya], reg[ib], m, st, orc, sj, sv, cn, co, cp, cq, cm)
                if 0 <= root < treg.shape[0]:
                    block_values(reg[xa], reg[ya], reg[ib], m, root, cn, co, cp, cq, cm, treg, tfa, reg[k])
                    continue
                if root >= 0:
                    for v in range(m):
                        reg[k, v] = point_value(reg[xa, v], reg[ya, v], reg[ib, v], root, cn, co, cp, cq, cm, sj,
                                                sv)
                    continue
            for v in range(m):
                reg[k, v] = point_value(reg[xa, v], reg[ya, v], reg[ib, v], st, orc[0], orc[1], orc[2], orc[3],
                                        orc[4], sj, sv)
            continue
        if o == BSPXY:
            continue  # carries the operands only
        if o == ADD:
            for v in range(m):
                reg[k, v] = reg[ia, v] + reg[ib, v]
        elif o == SUB:
            for v in range(m):
                reg[k, v] = reg[ia, v] - reg[ib, v]
        elif o == MUL:
            for v in range(m):
                reg[k, v] = reg[ia, v] * reg[ib, v]
        elif o == SQR:
            for v in range(m):
                reg[k, v] = reg[ia, v] * reg[ia, v]
        elif o == NEG:
            for v in range(m):
                reg[k, v] = -reg[ia, v]
        elif o == ADDC:
            for v in range(m):
                reg[k, v] = reg[ia, v] + ck
        elif o == MULC:
            for v in range(m):
                reg[k, v] = reg[ia, v] * ck
        elif o == RSUBC:
            for v in range(m):
                reg[k, v] = ck - reg[ia, v]
        elif o == ABS:
            for v in range(m):
                reg[k, v] = abs(reg[ia, v])
        elif o == SQRT:
            for v in range(m):
                reg[k, v] = _apply(SQRT, reg[ia, v], 0.0, ck)
        elif o == POWC:
            for v in range(m):
                reg[k, v] = _powc(reg[ia, v], ck)
        elif o == R0AND:
            for v in range(m):
                reg[k, v] = r0_and(reg[ia, v], reg[ib, v])
        elif o == MIN:
            for v in range(m):
                reg[k, v] = _apply(MIN, reg[ia, v], reg[ib, v], ck)
        elif o == MAX:
            for v in range(m):
                reg[k, v] = _apply(MAX, reg[ia, v], reg[ib, v], ck)
        elif ib >= 0:
            for v in range(m):
                reg[k, v] = _apply(o, reg[ia, v], reg[ib, v], ck)
        else:
            for v in range(m):
                reg[k, v] = _apply(o, reg[ia, v], 0.0, ck)
    return reg[res]


@njit(parallel=True, cache=True)
def eval_blocks(origins, block, h, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen):
    """Values (N, block, block, block) at the voxel centres of blocks, block n with tape
    ``tape_of[n]`` (index into start/length/res)."""
    n = origins.shape[0]
    m = block * block * block
    out = np.empty((n, block, block, block))
    # scratch once per chunk of blocks; at most 64 chunks, since a mesh's scratch tree has room
    # for its whole tree (150 MB for 1.3M faces) and must not be allocated per few blocks
    per = max(16, (n + 63) // 64)
    for ch in prange((n + per - 1) // per):
        reg, sj, sv, cn, co, cp, cq, cm, px, py, pz, treg, tfa, dep = _block_scratch(maxlen, m, odepth, orc)
        for q in range(ch * per, min(n, (ch + 1) * per)):
            _block_values(q, origins, block, h, tape_of, start, length, res, op, a, b, c, orc, reg, sj, sv, cn, co,
                          cp, cq, cm, px, py, pz, out, treg, tfa, dep)
    return out


@njit(cache=True, inline="always")
def _block_scratch(maxlen, m, odepth, orc):
    """One thread's scratch for :func:`_block_values` on blocks of m voxels: clause registers,
    the mesh walk's stacks, the block specialisation's node arrays, the voxel coordinates, the
    tree-major mesh registers and their flags, the clauses' coordinate bits."""
    nn = max(orc[0].shape[0], 1)
    reg = np.empty((max(maxlen, 1), m))
    sj = np.empty((3, odepth + 2), np.int64)
    sv = np.empty((4, odepth + 2))
    cn, co = np.empty((nn, 3)), np.empty(nn)
    cp, cq, cm = np.empty(nn, np.int64), np.empty(nn, np.int64), np.empty(nn, np.int64)
    treg = np.empty((min(nn, BLOCK_TREE_MAX) if orc[0].shape[0] else 0, m))  # tree-major mesh registers
    return (reg, sj, sv, cn, co, cp, cq, cm, np.empty(m), np.empty(m), np.empty(m), treg, np.empty(m),
            np.empty(max(maxlen, 1), np.int64))


@njit(cache=True)
def _block_values(q, origins, block, h, tape_of, start, length, res, op, a, b, c, orc, reg, sj, sv, cn, co, cp, cq,
                  cm, px, py, pz, out, treg, tfa, dep, slot=-1):
    """Values of block q's voxel centres into out[q] (into out[slot] when slot >= 0)."""
    m = block * block * block
    v = 0
    for i in range(block):
        for j in range(block):
            for k in range(block):
                px[v] = (origins[q, 0] + i) * h
                py[v] = (origins[q, 1] + j) * h
                pz[v] = (origins[q, 2] + k) * h
                v += 1
    tp = tape_of[q]
    vals = _run_batch(op, a, b, c, start[tp], length[tp], res[tp], px, py, pz, reg, m, orc, sj, sv, True, cn,
                      co, cp, cq, cm, treg, tfa, block, dep)
    v = 0
    row = q if slot < 0 else slot
    for i in range(block):
        for j in range(block):
            for k in range(block):
                out[row, i, j, k] = vals[v]
                v += 1


@njit(cache=True, parallel=True)
def first_nonfinite(v: np.ndarray, valid: np.ndarray) -> int:
    """Flat index of the first valid non-finite value of the blocks v (N, b, b, b), or -1."""
    n = v.shape[0]
    first = np.full(n, -1, np.int64)
    for q in prange(n):
        fv, fok = v[q].reshape(-1), valid[q].reshape(-1)
        for w in range(fv.size):
            if fok[w] and not np.isfinite(fv[w]):
                first[q] = q * fv.size + w
                break
    for q in range(n):
        if first[q] >= 0:
            return first[q]
    return -1


@njit(parallel=True, cache=True)
def eval_leaves(origins, block, h, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen, lstart, lblocks,
                     imin, imax, limit, outside, values, known):
    """:func:`eval_blocks` and the scatter of the blocks into their 8^3 leaves in one parallel
    pass over the leaves (no (N, b, b, b) float64 values or domain arrays). Leaf r holds the
    blocks ``lblocks[lstart[r]:lstart[r + 1]]``; its ``values`` start at ``outside`` and
    ``known`` at False (each leaf writes only its own rows, and touches them first from the
    thread that fills them; the caller marks the band on the leaves). A block's voxels inside
    the domain imin..imax are known and hold their value clamped to +-limit (float32); those
    beyond hold ``outside``. Returns (the flat index q * b^3 + v of the first non-finite value in
    the domain, in block order, or -1; how many values were clamped; how many voxels were
    evaluated in the domain)."""
    nl = lstart.shape[0] - 1
    m = block * block * block
    per = max(4, (nl + 63) // 64)
    nch = (nl + per - 1) // per
    bad = np.full(nch, -1, np.int64)
    nclamp = np.zeros(nch, np.int64)
    nvalid = np.zeros(nch, np.int64)
    for ch in prange(nch):
        reg, sj, sv, cn, co, cp, cq, cm, px, py, pz, treg, tfa, dep = _block_scratch(maxlen, m, odepth, orc)
        bv = np.empty((1, block, block, block))
        first = -1
        for r in range(ch * per, min(nl, (ch + 1) * per)):
            values[r] = outside
            known[r] = False
            for e in range(lstart[r], lstart[r + 1]):
                q = lblocks[e]
                _block_values(q, origins, block, h, tape_of, start, length, res, op, a, b, c, orc, reg, sj, sv, cn,
                              co, cp, cq, cm, px, py, pz, bv, treg, tfa, dep, 0)
                oi, oj, ok = origins[q, 0] & 7, origins[q, 1] & 7, origins[q, 2] & 7
                for i in range(block):
                    for j in range(block):
                        for k in range(block):
                            if not (imin[0] <= origins[q, 0] + i <= imax[0] and imin[1] <= origins[q, 1] + j <= imax[1]
                                    and imin[2] <= origins[q, 2] + k <= imax[2]):
                                continue
                            f = bv[0, i, j, k]
                            if not np.isfinite(f):
                                w = q * m + (i * block + j) * block + k
                                if first < 0 or w < first:
                                    first = w
                                continue
                            if abs(f) > limit:
                                nclamp[ch] += 1
                                f = min(max(f, -limit), limit)
                            values[r, oi + i, oj + j, ok + k] = f
                            known[r, oi + i, oj + j, ok + k] = True
                            nvalid[ch] += 1
        bad[ch] = first
    worst = -1
    for ch in range(nch):
        if bad[ch] >= 0 and (worst < 0 or bad[ch] < worst):
            worst = bad[ch]
    return worst, nclamp.sum(), nvalid.sum()


@njit(parallel=True, cache=True)
def eval_points(pts, bs, bt, start, length, res, op, a, b, c, orc, odepth, maxlen):
    """Values at points (N, 3) in batches of at most BATCH points of one tape: batch q is
    points bs[q]..bs[q + 1] - 1 (``bs`` ends with N), evaluated by tape bt[q] (index into
    start/length/res). The registers, stacks and coordinate rows allocated once per chunk of
    batches (per batch they cost as much as the arithmetic of a short tape)."""
    n = pts.shape[0]
    out = np.empty(n)
    nb = bt.shape[0]
    width = 1  # the widest batch: a descent's cells have a few points each, and long tapes at the top
    for q in range(nb):
        width = max(width, bs[q + 1] - bs[q])
    # chunks of batches, each with its own registers: at most 256, and fewer when the registers
    # of the longest tape are large (a union of 10^4 parts: 110k clauses x 19 points = 17 MB)
    chunks = max(1, min(nb, 256, (1 << 26) // (8 * max(maxlen, 1) * width)))
    per = (nb + chunks - 1) // chunks
    for ch in prange((nb + per - 1) // per):
        reg = np.empty((max(maxlen, 1), width))
        sj = np.empty((2, odepth + 2), np.int64)
        sv = np.empty((2, odepth + 2))
        px, py, pz = np.empty(BATCH), np.empty(BATCH), np.empty(BATCH)
        none_n, none_f, none_i, none_r = np.empty((0, 3)), np.empty(0), np.empty(0, np.int64), np.empty((0, BATCH))
        for q in range(ch * per, min(nb, (ch + 1) * per)):
            lo = bs[q]
            m = bs[q + 1] - lo
            tp = bt[q]
            for v in range(m):
                px[v], py[v], pz[v] = pts[lo + v, 0], pts[lo + v, 1], pts[lo + v, 2]
            vals = _run_batch(op, a, b, c, start[tp], length[tp], res[tp], px, py, pz, reg, m, orc, sj, sv, False,
                              none_n, none_f, none_i, none_i, none_i, none_r, none_f, 0, none_i)
            out[lo:lo + m] = vals[:m]
    return out


def point_batches(n: int, keys: np.ndarray | None = None) -> np.ndarray:
    """``bs`` of :func:`eval_points` for n points: each run of equal ``keys`` (None: all n
    points) cut into batches of at most BATCH points."""
    if keys is None:
        return np.append(np.arange(0, n, BATCH, dtype=np.int64), np.int64(n))
    runs = np.concatenate([[0], np.flatnonzero(keys[1:] != keys[:-1]) + 1, [n]]).astype(np.int64)
    per_run = (np.diff(runs) + BATCH - 1) // BATCH
    first = np.repeat(runs[:-1], per_run)
    within = np.arange(int(per_run.sum()), dtype=np.int64) - np.repeat(np.cumsum(per_run) - per_run, per_run)
    return np.append(first + within * BATCH, np.int64(n))


BATCH = 128  # points per register row of eval_points (64 -> 128: 0.16 -> 0.11 s for 3M points of the demo)


# --- gradients (forward mode) -------------------------------------------------------------------


@njit(cache=True, inline="always")
def _partials(op, va, vb, c, r):
    """(d r / d a, d r / d b) of one clause with value r = op(va, vb): the forward-mode rule of
    every opcode (one-sided where the clause has a crease: min / max / abs take the operand they
    return; sardf inside its window is the C1 quadratic)."""
    if op == ADD:
        return 1.0, 1.0
    if op == SUB:
        return 1.0, -1.0
    if op == MUL:
        return vb, va
    if op == DIV:  # Numba raises on a float division by zero: the undefined cases are NaN
        return (1.0 / vb, -va / (vb * vb)) if vb != 0.0 else (math.nan, math.nan)
    if op == ADDC:
        return 1.0, 0.0
    if op == MULC:
        return c, 0.0
    if op == RSUBC:
        return -1.0, 0.0
    if op == DIVC:
        return (1.0 / c if c != 0.0 else math.nan), 0.0
    if op == RDIVC:
        return (-c / (va * va) if va != 0.0 else math.nan), 0.0
    if op == NEG:
        return -1.0, 0.0
    if op == SQRT:
        return (0.5 / r if r > 0.0 else math.inf), 0.0
    if op == SQR:
        return 2.0 * va, 0.0
    if op == ABS:
        return (1.0 if va > 0 else (-1.0 if va < 0 else 0.0)), 0.0
    if op == EXP:
        return r, 0.0
    if op == LOG:
        return (1.0 / va if va != 0.0 else math.inf), 0.0
    if op == SIN:
        return math.cos(va), 0.0
    if op == COS:
        return -math.sin(va), 0.0
    if op == POWC:
        return c * _powc(va, c - 1.0), 0.0
    if op == MIN:
        return (1.0, 0.0) if r == va else (0.0, 1.0)
    if op == MAX:
        return (1.0, 0.0) if r == va else (0.0, 1.0)
    if op == R0AND:  # f1 + f2 - sqrt(f1^2 + f2^2) (eq. 2), in any of its algebraic forms
        rho = math.hypot(va, vb)
        return (1.0 - va / rho, 1.0 - vb / rho) if rho > 0 else (0.5, 0.5)
    if op == SARDFAND:
        rho = math.hypot(va, vb)
        u = va - vb
        w = c * rho
        if abs(u) >= w:  # min outside the window
            return (1.0, 0.0) if r == va else (0.0, 1.0)
        e = 0.5 - u * u / (2.0 * w * w)  # d/dw of (u^2 + w^2) / (2 w), times dw/dfi = c fi / rho
        return 0.5 * (1.0 - u / w - e * c * va / rho), 0.5 * (1.0 + u / w - e * c * vb / rho)
    if op == COMPRESS:
        a = abs(va)
        return (1.0 if not a > c else c / a), 0.0
    return 0.0, 0.0


@njit(cache=True)
def _grad_point(op, a, b, c, s, n, px, py, pz, v, g, orc, sj, sv):
    """Values v[k] and gradients g[k] (d/dx, d/dy, d/dz) of every clause of the tape at s..s+n at
    one point. A mesh clause's gradient is its deciding plane's normal (bsp_minmax.point_plane)
    carried through its coordinate clauses (the chain rule over transforms)."""
    for k in range(n):
        o = op[s + k]
        ck = c[s + k]
        g[k, 0] = g[k, 1] = g[k, 2] = 0.0
        if o == X:
            v[k], g[k, 0] = px, 1.0
            continue
        if o == Y:
            v[k], g[k, 1] = py, 1.0
            continue
        if o == Z:
            v[k], g[k, 2] = pz, 1.0
            continue
        if o == CONST or o == BSPXY:  # noqa: SIM109 (plain compares in the kernel)
            v[k] = ck
            continue
        ia, ib = a[s + k], b[s + k]
        if o == BSP:
            xa, ya = a[s + ia], b[s + ia]
            val, j, sg = point_plane(v[xa], v[ya], v[ib], np.int64(ck), orc[0], orc[1], orc[2], orc[3], orc[4], sj,
                                     sv)
            v[k] = val
            nx, ny, nz = sg * orc[0][j, 0], sg * orc[0][j, 1], sg * orc[0][j, 2]
            for d in range(3):
                g[k, d] = nx * g[xa, d] + ny * g[ya, d] + nz * g[ib, d]
            continue
        va = v[ia]
        vb = v[ib] if ib >= 0 else 0.0
        r = _apply(o, va, vb, ck)
        v[k] = r
        da, db = _partials(o, va, vb, ck, r)
        for d in range(3):  # 0 * inf is 0 here: an operand that does not vary adds nothing
            ga = da * g[ia, d] if g[ia, d] != 0.0 else 0.0
            gb = db * g[ib, d] if ib >= 0 and g[ib, d] != 0.0 else 0.0
            g[k, d] = ga + gb


@njit(parallel=True, cache=True)
def eval_points_grad(pts, start, length, res, op, a, b, c, orc, odepth):
    """Values (N,) and gradients (N, 3) of tape 0 at points (N, 3), forward mode (exact where the
    model is differentiable; one-sided on creases)."""
    n = pts.shape[0]
    val = np.empty(n)
    grad = np.empty((n, 3))
    ln = length[0]
    nb = (n + 255) // 256
    for q in prange(nb):
        v = np.empty(max(ln, 1))
        g = np.empty((max(ln, 1), 3))
        sj = np.empty((4, odepth + 2), np.int64)
        sv = np.empty((2, odepth + 2))
        for i in range(q * 256, min(n, (q + 1) * 256)):
            _grad_point(op, a, b, c, start[0], ln, pts[i, 0], pts[i, 1], pts[i, 2], v, g, orc, sj, sv)
            val[i] = v[res[0]]
            grad[i, 0], grad[i, 1], grad[i, 2] = g[res[0], 0], g[res[0], 1], g[res[0], 2]
    return val, grad


# --- interval bounds --------------------------------------------------------------------------------

_UP = 1.0 + 4.0 * 2.220446049250313e-16  # outward rounding of every interval end
_TINY = 1e-300


@njit(cache=True, inline="always")
def _down(v):
    return v - abs(v) * (_UP - 1.0) - _TINY if v == v else -math.inf


@njit(cache=True, inline="always")
def _upv(v):
    return v + abs(v) * (_UP - 1.0) + _TINY if v == v else math.inf


@njit(cache=True)
def _trig_range(lo, hi, phase):
    """Range of sin(x + phase) over [lo, hi] (phase 0: sin, pi/2: cos)."""
    if not (hi - lo < 2.0 * math.pi) or lo != lo or hi != hi:
        return -1.0, 1.0
    a, b = lo + phase, hi + phase
    s1, s2 = math.sin(a), math.sin(b)
    mn, mx = min(s1, s2), max(s1, s2)
    # maxima at pi/2 + 2k pi, minima at -pi/2 + 2k pi
    k = math.ceil((a - 0.5 * math.pi) / (2.0 * math.pi))
    if 0.5 * math.pi + 2.0 * math.pi * k <= b:
        mx = 1.0
    k = math.ceil((a + 0.5 * math.pi) / (2.0 * math.pi))
    if -0.5 * math.pi + 2.0 * math.pi * k <= b:
        mn = -1.0
    return mn, mx


@njit(cache=True, inline="always")
def _interval(o, alo, ahi, blo, bhi, c):
    """Interval of one clause; returns (lo, hi, choice): choice 1/2 when min/max is decided by
    operand a/b over the whole interval, else 0. Inlined into the bound walk (a call per clause
    was ~10 % of the bound pass of a 10^4-sphere union)."""
    if o == ADD:
        return alo + blo, ahi + bhi, 0
    if o == SUB:
        return alo - bhi, ahi - blo, 0
    if o == MUL:
        p1, p2, p3, p4 = alo * blo, alo * bhi, ahi * blo, ahi * bhi
        lo = min(min(p1, p2), min(p3, p4))
        hi = max(max(p1, p2), max(p3, p4))
        if lo != lo or hi != hi:
            return -math.inf, math.inf, 0
        return lo, hi, 0
    if o == DIV:
        if blo <= 0.0 <= bhi:
            return -math.inf, math.inf, 0
        p1, p2, p3, p4 = alo / blo, alo / bhi, ahi / blo, ahi / bhi
        return min(min(p1, p2), min(p3, p4)), max(max(p1, p2), max(p3, p4)), 0
    if o == ADDC:
        return alo + c, ahi + c, 0
    if o == RSUBC:
        return c - ahi, c - alo, 0
    if o == MULC:
        p1, p2 = alo * c, ahi * c
        if p1 != p1 or p2 != p2:  # 0 * inf
            return -math.inf, math.inf, 0
        return min(p1, p2), max(p1, p2), 0
    if o == DIVC:
        if c == 0.0:
            return -math.inf, math.inf, 0
        p1, p2 = alo / c, ahi / c
        return min(p1, p2), max(p1, p2), 0
    if o == RDIVC:
        if alo <= 0.0 <= ahi:
            return -math.inf, math.inf, 0
        p1, p2 = c / alo, c / ahi
        return min(p1, p2), max(p1, p2), 0
    if o == NEG:
        return -ahi, -alo, 0
    if o == SQRT:
        return math.sqrt(max(alo, 0.0)), math.sqrt(max(ahi, 0.0)), 0
    if o == SQR:
        if alo >= 0.0:
            return alo * alo, ahi * ahi, 0
        if ahi <= 0.0:
            return ahi * ahi, alo * alo, 0
        return 0.0, max(alo * alo, ahi * ahi), 0
    if o == ABS:
        if alo >= 0.0:
            return alo, ahi, 0
        if ahi <= 0.0:
            return -ahi, -alo, 0
        return 0.0, max(-alo, ahi), 0
    if o == EXP:
        return _apply(EXP, alo, 0.0, 0.0), _apply(EXP, ahi, 0.0, 0.0), 0
    if o == LOG:
        return _apply(LOG, max(alo, 0.0), 0.0, 0.0), _apply(LOG, max(ahi, 0.0), 0.0, 0.0), 0
    if o == SIN:
        lo, hi = _trig_range(alo, ahi, 0.0)
        return lo, hi, 0
    if o == COS:
        lo, hi = _trig_range(alo, ahi, 0.5 * math.pi)
        return lo, hi, 0
    if o == POWC:
        return _pow_interval(alo, ahi, c)
    if o == MIN:
        if ahi < blo:
            return alo, ahi, 1
        if bhi < alo:
            return blo, bhi, 2
        return min(alo, blo), min(ahi, bhi), 0
    if o == MAX:
        if alo > bhi:
            return alo, ahi, 1
        if blo > ahi:
            return blo, bhi, 2
        return max(alo, blo), max(ahi, bhi), 0
    if o == R0AND:  # nondecreasing in both arguments
        return r0_and(alo, blo), r0_and(ahi, bhi), 0
    if o == SARDFAND:
        return sardf_and(alo, blo, c), sardf_and(ahi, bhi, c), 0
    if o == COMPRESS:
        return compress(alo, c), compress(ahi, c), 0
    return c, c, 0


@njit(cache=True)
def _pow_interval(lo, hi, p):
    if p == np.floor(p):  # an integer exponent (np.floor: math.floor is an int64 in Numba)
        # every float of magnitude >= 2^53 is an even integer; below that int() is exact
        even = abs(p) >= 2.0**53 or int(p) % 2 == 0
        n = 1 if p >= 0 else -1  # only the sign of the exponent matters below
        if n >= 0 and even:  # even: like sqr
            if lo >= 0.0:
                return lo ** p, hi ** p, 0
            if hi <= 0.0:
                return hi ** p, lo ** p, 0
            return 0.0, max(lo ** p, hi ** p), 0
        if n >= 0:  # odd: increasing
            return lo ** p, hi ** p, 0
        if lo > 0.0:  # negative powers: decreasing on x > 0
            return hi ** p, lo ** p, 0
        if hi < 0.0:
            a, b = lo ** p, hi ** p
            return min(a, b), max(a, b), 0
        return -math.inf, math.inf, 0
    if hi < 0.0:
        return math.nan, math.nan, 0
    lo = max(lo, 0.0)
    if p > 0:
        return lo ** p, hi ** p, 0
    return (hi ** p if hi > 0 else math.inf), (lo ** p if lo > 0 else math.inf), 0


def bound_boxes(lo, hi, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen, choff, choices):
    """Interval (flo, fhi) of box q's tape over [lo_q, hi_q]; ``choices[choff[q] + k]`` receives
    the decision of clause k of box q's tape (1/2: operand a/b decides the min/max, 0: not; for
    a mesh clause 3 + the node the box starts from, when deeper than the clause's own)."""
    return _bound_pass(lo, hi, lo, hi, False, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen, choff,
                       choices)


def bound_cull_decide(lo, hi, dlo, dhi, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen, choff,
                      choices):
    """One pass of a descent level: the interval (flo, fhi) of box q's tape over its culling box
    [lo_q, hi_q] and, for every box not culled by it (neither flo > 0 nor fhi < 0), the
    decisions of its clauses over its (smaller) decision box [dlo_q, dhi_q] into
    ``choices[choff[q]:]``, as :func:`bound_boxes` records them. A mesh clause's walk over the
    decision box starts from the node the culling walk reached when the decision box lies in
    the culling box (that node's field is the mesh's there), else from its own start node.

    A box whose tape is one closed mesh's clause at the plain coordinates (a mesh model, or a
    cell of a CSG model where only the mesh is left) is culled by the mesh's surface instead
    (:func:`_surface_cull`): kept, with the interval (-inf, inf), when a triangle comes within
    tape.SURFACE_MARGIN of its culling box; else culled with the sign of the field at one
    point, (flo, fhi) = (v, v). The field's zero set is the closed surface, so this keeps
    exactly the boxes the surface meets (the interval walk kept a superset: its bounds of
    hundreds of nearly tied planes over a box ten voxels wide were often loose) at the cost of a
    BVH query and one point walk, where the walk visited the planes near the box. Such a kept
    box records no decisions (its tape has no min/max), and no start node either: the walk that
    found it over the decision box cost more than it saved, since each voxel block specialises
    the tree to its own box anyway (bsp_minmax.specialise_box, which passes the decided nodes
    above the block's start node in a few steps each; torus50k at 256^3: bounds 0.76 -> 0.21 s
    of one core, block evaluation unchanged), so the blocks' trees start from the root."""
    return _bound_pass(lo, hi, dlo, dhi, True, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen, choff,
                       choices)


@njit(parallel=True, cache=True)
def _bound_pass(lo, hi, dlo, dhi, decide, tape_of, start, length, res, op, a, b, c, orc, odepth, maxlen, choff,
                choices):
    """The kernel of :func:`bound_boxes` (``decide`` False: decisions over the bounded box, for
    every box) and :func:`bound_cull_decide` (True)."""
    nbox = lo.shape[0]
    flo = np.empty(nbox)
    fhi = np.empty(nbox)
    per = 64 if nbox >= 1024 else 1  # few boxes (the top levels, long tapes): one per thread
    for ch in prange((nbox + per - 1) // per):
        rlo = np.empty(maxlen)  # scratch once per chunk of boxes, not per box
        rhi = np.empty(maxlen)
        tlo = np.empty(maxlen)
        thi = np.empty(maxlen)
        sj = np.empty((3, odepth + 2), np.int64)
        sv = np.empty((4, odepth + 2))
        stack = np.empty(BVH_STACK, np.int64)
        for q in range(ch * per, min(nbox, (ch + 1) * per)):
            tp = tape_of[q]
            s, ln, ch0 = start[tp], length[tp], choff[q]
            if decide and orc[9].shape[0] > 0:
                kind, v = _surface_cull(q, lo, hi, dlo, dhi, s, res[tp], op, a, b, c, orc, sj, sv, stack)
                if kind == 1:  # no triangle near the box: one sign, that of a point
                    flo[q] = fhi[q] = v
                    continue
                if kind == 2:  # the surface comes near: kept (no interval needed), nothing to decide
                    flo[q], fhi[q] = -np.inf, np.inf
                    continue
            _bound_one(lo[q], hi[q], s, ln, op, a, b, c, rlo, rhi, choices, ch0, orc, sj, sv)
            flo[q] = rlo[res[tp]]
            fhi[q] = rhi[res[tp]]
            if decide:
                if flo[q] > 0 or fhi[q] < 0:
                    continue  # culled: no tape needed
                inner = True
                for d in range(3):
                    inner = inner and lo[q, d] <= dlo[q, d] and dhi[q, d] <= hi[q, d]
                if not inner:
                    choices[ch0:ch0 + ln] = 0  # mesh walks start afresh
                _bound_one(dlo[q], dhi[q], s, ln, op, a, b, c, rlo, rhi, choices, ch0, orc, sj, sv)
            _relevance(op, a, s, ln, res[tp], b, rlo, rhi, choices, ch0, tlo, thi)
    return flo, fhi


@njit(parallel=True, cache=True)
def _surface_sides(lo, hi, tape_of, start, res, op, a, b, c, orc, odepth):
    """The kernel of :meth:`TapePool.surface_sides` (each box its own decision box)."""
    n = lo.shape[0]
    kind = np.zeros(n, np.int8)
    value = np.zeros(n)
    per = 64
    for ch in prange((n + per - 1) // per):
        sj = np.empty((3, odepth + 2), np.int64)
        sv = np.empty((4, odepth + 2))
        stack = np.empty(BVH_STACK, np.int64)
        for q in range(ch * per, min(n, (ch + 1) * per)):
            tp = tape_of[q]
            kind[q], value[q] = _surface_cull(q, lo, hi, lo, hi, start[tp], res[tp], op, a, b, c, orc, sj, sv, stack)
    return kind, value


@njit(cache=True)
def _surface_cull(q, lo, hi, dlo, dhi, s, r, op, a, b, c, orc, sj, sv, stack):
    """Box q's culling by the surface, for a tape that is one closed mesh's clause at the plain
    coordinates: (1, v) when no triangle comes near the culling box lo..hi (the field has no zero
    there, so its sign is that of its value v at one point of the box, one where the clause's
    start node holds), (2, 0) when one does (the box is kept), (0, 0) when this does not apply (other
    tapes, open meshes, a point value too near 0 to trust its sign): the interval walk decides."""
    k = s + r
    if op[k] != BSP:
        return 0, 0.0
    xy = s + a[k]
    if op[xy] != BSPXY or op[s + a[xy]] != X or op[s + b[xy]] != Y or op[s + b[k]] != Z:
        return 0, 0.0
    st = np.int64(c[k])
    minfo, mtol = orc[9], orc[10]
    m = -1
    for i in range(minfo.shape[0]):
        if minfo[i, 0] <= st < minfo[i, 1]:
            m = i
    if m < 0 or minfo[m, 2] < 0:
        return 0, 0.0
    if box_near_surface(lo[q, 0], lo[q, 1], lo[q, 2], hi[q, 0], hi[q, 1], hi[q, 2], mtol[m, 0], minfo[m, 2], orc[5],
                        orc[6], orc[7], orc[8], stack):
        return 2, 0.0
    # a point of the culling box inside the decision box (where the start node's field is the
    # mesh's: the cell grown by at most one voxel; both boxes hold the cell's voxels)
    p0 = 0.5 * (max(lo[q, 0], dlo[q, 0]) + min(hi[q, 0], dhi[q, 0]))
    p1 = 0.5 * (max(lo[q, 1], dlo[q, 1]) + min(hi[q, 1], dhi[q, 1]))
    p2 = 0.5 * (max(lo[q, 2], dlo[q, 2]) + min(hi[q, 2], dhi[q, 2]))
    v = point_value(p0, p1, p2, st, orc[0], orc[1], orc[2], orc[3], orc[4], sj, sv)
    if abs(v) > mtol[m, 1] + 1e-12 * (abs(p0) + abs(p1) + abs(p2)):  # NaN compares False
        return 1, v
    return 0, 0.0


@njit(cache=True)
def _bound_one(lo, hi, s, ln, op, a, b, c, rlo, rhi, choices, ch0, orc, sj, sv):
    for k in range(ln):
        o = op[s + k]
        if o == X:
            rlo[k], rhi[k] = lo[0], hi[0]
        elif o == Y:
            rlo[k], rhi[k] = lo[1], hi[1]
        elif o == Z:
            rlo[k], rhi[k] = lo[2], hi[2]
        elif o == CONST:
            rlo[k], rhi[k] = c[s + k], c[s + k]
        elif o == BSP:
            _bound_bsp(k, s, a, b, c, rlo, rhi, choices, ch0, orc, sj, sv)
        elif o == BSPXY:
            rlo[k], rhi[k] = 0.0, 0.0
        else:
            ia, ib = a[s + k], b[s + k]
            blo = rlo[ib] if ib >= 0 else 0.0
            bhi = rhi[ib] if ib >= 0 else 0.0
            vlo, vhi, chc = _interval(o, rlo[ia], rhi[ia], blo, bhi, c[s + k])
            rlo[k], rhi[k] = _down(vlo), _upv(vhi)
            choices[ch0 + k] = chc


@njit(cache=True)
def _bound_bsp(k, s, a, b, c, rlo, rhi, choices, ch0, orc, sj, sv):
    """Mesh clause k over the box of its coordinate intervals; records a deeper start node."""
    ia, ib = a[s + k], b[s + k]
    xa, ya = a[s + ia], b[s + ia]
    lo0, hi0, lo1, hi1, lo2, hi2 = rlo[xa], rhi[xa], rlo[ya], rhi[ya], rlo[ib], rhi[ib]
    # a node recorded by an earlier walk over a box holding this one (bound_cull_decide), else
    # the clause's own start node
    st = np.int64(choices[ch0 + k] - 3) if choices[ch0 + k] >= 3 else np.int64(c[s + k])
    if not (math.isfinite(lo0) and math.isfinite(hi0) and math.isfinite(lo1) and math.isfinite(hi1)
            and math.isfinite(lo2) and math.isfinite(hi2)):
        rlo[k], rhi[k] = -math.inf, math.inf
        return
    pad = 1e-14 * (1.0 + max(max(abs(lo0), abs(hi0)), max(max(abs(lo1), abs(hi1)), max(abs(lo2), abs(hi2)))))
    flo, fhi, nst = box_bound(lo0, lo1, lo2, hi0, hi1, hi2, st, orc[0], orc[1], orc[2], orc[3], orc[4], pad, sj,
                              sv)
    rlo[k], rhi[k] = _down(flo), _upv(fhi)
    if nst != st:
        choices[ch0 + k] = 3 + nst


@njit(cache=True)
def _relevance(op, a, s, ln, res, b, rlo, rhi, choices, ch0, tlo, thi):
    """Prune min/max operands that cannot matter anywhere in the box, looking past the sibling:
    below ``tlo[k]`` clause k's value does not change the tape's result (it is under a max that
    something else exceeds), above ``thi[k]`` likewise for a min. Thresholds flow down through
    min, max and neg; a value used by several clauses keeps the least restrictive threshold.
    An operand whose whole interval lies beyond its threshold is dropped (exact)."""
    tlo[:ln] = np.inf
    thi[:ln] = -np.inf
    tlo[res] = -np.inf
    thi[res] = np.inf
    for k in range(ln - 1, -1, -1):
        o = op[s + k]
        if o in (X, Y, Z, CONST):
            continue
        ia, ib = a[s + k], b[s + k]
        if o == MAX:
            ta, tb = max(tlo[k], rlo[ib]), max(tlo[k], rlo[ia])
            if rhi[ia] < ta:
                choices[ch0 + k] = 2
                tlo[ib] = min(tlo[ib], tlo[k])
                thi[ib] = max(thi[ib], thi[k])
                continue
            if rhi[ib] < tb:
                choices[ch0 + k] = 1
                tlo[ia] = min(tlo[ia], tlo[k])
                thi[ia] = max(thi[ia], thi[k])
                continue
            tlo[ia], tlo[ib] = min(tlo[ia], ta), min(tlo[ib], tb)
            thi[ia], thi[ib] = np.inf, np.inf
        elif o == MIN:
            ta, tb = min(thi[k], rhi[ib]), min(thi[k], rhi[ia])
            if rlo[ia] > ta:
                choices[ch0 + k] = 2
                tlo[ib] = min(tlo[ib], tlo[k])
                thi[ib] = max(thi[ib], thi[k])
                continue
            if rlo[ib] > tb:
                choices[ch0 + k] = 1
                tlo[ia] = min(tlo[ia], tlo[k])
                thi[ia] = max(thi[ia], thi[k])
                continue
            thi[ia], thi[ib] = max(thi[ia], ta), max(thi[ib], tb)
            tlo[ia], tlo[ib] = -np.inf, -np.inf
        elif o == NEG:
            tlo[ia] = min(tlo[ia], -thi[k])
            thi[ia] = max(thi[ia], -tlo[k])
        else:
            tlo[ia] = -np.inf
            thi[ia] = np.inf
            if ib >= 0:
                tlo[ib] = -np.inf
                thi[ib] = np.inf


# --- specialisation ----------------------------------------------------------------------------------


@njit(cache=True)
def _specialise_one(op, a, b, c, alias, choice, res):
    """The tape with every decided min/max replaced by its deciding operand and the clauses
    nothing uses any more removed (exact: see the module docstring). ``alias``/``choice`` are
    scratch/decisions of length len(op)."""
    n = len(op)
    for k in range(n):
        alias[k] = k
        if (op[k] == MIN or op[k] == MAX) and choice[k] != 0:
            alias[k] = alias[a[k]] if choice[k] == 1 else alias[b[k]]
    live = np.zeros(n, np.bool_)
    live[alias[res]] = True
    for k in range(n - 1, -1, -1):
        if live[k] and alias[k] == k:
            if a[k] >= 0:
                live[alias[a[k]]] = True
            if b[k] >= 0:
                live[alias[b[k]]] = True
    newpos = np.full(n, -1, np.int64)
    m = 0
    for k in range(n):
        if live[k] and alias[k] == k:
            newpos[k] = m
            m += 1
    nop = np.empty(m, OP_T)
    na = np.empty(m, IX_T)
    nb = np.empty(m, IX_T)
    nc = np.empty(m, np.float64)
    for k in range(n):
        p = newpos[k]
        if p < 0:
            continue
        nop[p] = op[k]
        na[p] = newpos[alias[a[k]]] if a[k] >= 0 else -1
        nb[p] = newpos[alias[b[k]]] if b[k] >= 0 else -1
        nc[p] = c[k]
    return nop, na, nb, nc, newpos[alias[res]]


# flag on a clause's decision: the clause stays in the box's shortened tape (a mesh clause's
# decision 3 + start node stays below it: a BSP-tree of 2^30 nodes would take ~100 GB)
KEPT = np.int32(1 << 30)


@njit(cache=True)
def _spec_count(op, a, b, s, ln, res, choices, ch0, alias, live):
    """The first half of :func:`_specialise_one` for the tape at s..s+ln with decisions at
    choices[ch0:], with caller-owned scratch (no allocation per cell): every clause the
    shortened tape keeps gets the flag KEPT on its decision, for :func:`_spec_write`. Returns
    how many are kept. The tape is in topological order, so the result (the last clause kept)
    is at the shortened tape's end."""
    for k in range(ln):
        alias[k] = k
        ck = choices[ch0 + k] & ~KEPT  # (flags of an earlier count of the same decisions)
        choices[ch0 + k] = ck
        if ck != 0 and (op[s + k] == MIN or op[s + k] == MAX):
            alias[k] = alias[a[s + k]] if ck == 1 else alias[b[s + k]]
        live[k] = False
    live[alias[res]] = True
    m = 0
    for k in range(ln - 1, -1, -1):
        if live[k] and alias[k] == k:
            m += 1
            choices[ch0 + k] |= KEPT
            if a[s + k] >= 0:
                live[alias[a[s + k]]] = True
            if b[s + k] >= 0:
                live[alias[b[s + k]]] = True
    return m


@njit(cache=True)
def _spec_write(op, a, b, c, s, ln, choices, ch0, alias, newpos, oop, oa, ob, oc, o0):
    """The second half: the clauses flagged by :func:`_spec_count` written from o0 on, their
    operands renumbered (one pass: a clause's operands come before it)."""
    m = 0
    for k in range(ln):
        ck = choices[ch0 + k]
        kept = (ck & KEPT) != 0
        ck &= ~KEPT
        alias[k] = k
        if ck != 0 and (op[s + k] == MIN or op[s + k] == MAX):
            alias[k] = alias[a[s + k]] if ck == 1 else alias[b[s + k]]
        if not kept:
            continue
        newpos[k] = m
        oop[o0 + m] = op[s + k]
        oa[o0 + m] = newpos[alias[a[s + k]]] if a[s + k] >= 0 else -1
        ob[o0 + m] = newpos[alias[b[s + k]]] if b[s + k] >= 0 else -1
        oc[o0 + m] = c[s + k] if op[s + k] != BSP or ck < 3 else float(ck - 3)
        m += 1


@njit(parallel=True, cache=True)
def specialise(keep, tape_of, start, length, res, op, a, b, c, choff, choices):
    """The shortened tape of every kept box (``keep``: box indices), as a new pool; returns
    (start, length, res, op, a, b, c) with tape i belonging to box keep[i]. Two parallel passes
    over the boxes: count each shortened tape, flagging the clauses it keeps in ``choices`` (a
    later call with the same decisions clears the flags first), then write it at its offset (no
    room is reserved for the parents' lengths: at fine levels that would be gigabytes). Three
    loops over a tape in all; six before the flags (docs/performance.md, session 31).

    A box whose decisions change nothing keeps its parent's tape: when such boxes hold more
    clauses than the parents' pool, the new pool starts with a copy of the parents' pool and
    their tapes point into it (the same clauses; the demo's r0 tape is not shortened by its
    blocks, whose 785k copies took 0.6 GB at 1024^3)."""
    nk = len(keep)
    maxlen = 1
    for i in range(nk):
        maxlen = max(maxlen, length[tape_of[keep[i]]])
    nlen = np.empty(nk, np.int64)
    same = np.empty(nk, np.bool_)
    per = 16
    nch = (nk + per - 1) // per
    for ch in prange(nch):
        alias = np.empty(maxlen, np.int64)
        live = np.empty(maxlen, np.bool_)
        for i in range(ch * per, min(nk, (ch + 1) * per)):
            q = keep[i]
            tp = tape_of[q]
            m = _spec_count(op, a, b, start[tp], length[tp], res[tp], choices, choff[q], alias, live)
            nlen[i] = m
            same[i] = m == length[tp] and _keeps_starts(op, start[tp], length[tp], choices, choff[q])
    shared = 0
    for i in range(nk):
        if same[i]:
            shared += nlen[i]
    base = op.shape[0] if shared > op.shape[0] else 0  # share when it saves more than the copy
    nstart = np.zeros(nk, np.int64)
    nres = np.empty(nk, np.int64)
    total = base
    for i in range(nk):
        if base > 0 and same[i]:
            tp = tape_of[keep[i]]
            nstart[i], nres[i] = start[tp], res[tp]
        else:
            nstart[i] = total
            nres[i] = nlen[i] - 1
            total += nlen[i]
    pop, pa, pb, pc = np.empty(total, OP_T), np.empty(total, IX_T), np.empty(total, IX_T), np.empty(total)
    if base > 0:
        pop[:base] = op
        pa[:base] = a
        pb[:base] = b
        pc[:base] = c
    for ch in prange(nch):
        alias = np.empty(maxlen, np.int64)
        newpos = np.empty(maxlen, np.int64)
        for i in range(ch * per, min(nk, (ch + 1) * per)):
            if base > 0 and same[i]:
                continue
            q = keep[i]
            tp = tape_of[q]
            _spec_write(op, a, b, c, start[tp], length[tp], choices, choff[q], alias, newpos, pop, pa, pb, pc,
                        nstart[i])
    return nstart, nlen, nres, pop, pa, pb, pc


@njit(cache=True)
def _keeps_starts(op, s, ln, choices, ch0) -> bool:
    """No mesh clause of the tape at s..s+ln gets a new start node from the decisions at
    choices[ch0:] (with every clause kept, the shortened tape is then the tape itself)."""
    n = 0
    for k in range(ln):
        n += op[s + k] == BSP and (choices[ch0 + k] & ~KEPT) >= 3
    return n == 0
