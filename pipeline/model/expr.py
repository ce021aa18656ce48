"""``expr``: a formula in x, y, z and t, parsed into model-tree nodes (never Python ``eval``).

Grammar (recursive descent, usual precedence, ``^`` right-associative and binding tighter
than unary minus, so -x^2 = -(x^2))::

    expr   := term (('+' | '-') term)*
    term   := unary (('*' | '/') unary)*
    unary  := ('-' | '+') unary | power
    power  := atom ('^' unary)?
    atom   := number | name | name '(' expr (',' expr)* ')' | '(' expr ')'

Names: x, y, z, t, pi, e, plus the extra variables a caller passes to ``parse_formula`` (attribute
formulas of the ``hfrep`` stage add the distance ``d``; model ``expr`` nodes add none, so ``d``
is an unknown name there). Functions: sqrt exp log sin cos abs min max (min/max take two or
more arguments) and pow(a, b). The parsed nodes are ordinary nodes with a ``field`` method, so
formulas get evaluation and affine bounds from the same machinery as every other node.
Constant sub-expressions are folded; a constant division by zero or a constant that is not
finite is a parse error.

Limits: a formula is at most MAX_FORMULA_LENGTH characters and nests at most
MAX_FORMULA_DEPTH levels (parentheses, function calls, exponents). Sums and products are
n-ary nodes and runs of unary signs collapse, so a long formula evaluates without deep
recursion: 1,000 terms are one node with 1,000 children.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import reduce
from typing import Any

import numpy as np
from pydantic import Field

from pipeline.model import ops
from pipeline.model.base import Node, Params, register


class FormulaError(ValueError):
    """A formula that does not parse; ``column`` is 1-based."""

    def __init__(self, message: str, column: int):
        super().__init__(f"column {column}: {message}")
        self.column = column


_TOKEN = re.compile(r"\s*(?:(\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)|([A-Za-z_]\w*)|(\S))")
_FUNCS = {"sqrt": 1, "exp": 1, "log": 1, "sin": 1, "cos": 1, "abs": 1, "min": -2, "max": -2, "pow": 2}
_CONSTS = {"pi": math.pi, "e": math.e}

#: characters of one formula
MAX_FORMULA_LENGTH = 20_000
#: nesting of parentheses, function calls and exponents (the parser and the evaluation recurse
#: per level, a few Python frames each)
MAX_FORMULA_DEPTH = 60


@dataclass
class _Tok:
    kind: str  # num | name | op | end
    text: str
    col: int


def _tokenise(src: str) -> list[_Tok]:
    toks, pos = [], 0
    while pos < len(src):
        m = _TOKEN.match(src, pos)
        if m is None or m.end() == pos:
            break
        col = m.start(m.lastindex) + 1
        kind = {1: "num", 2: "name", 3: "op"}[m.lastindex]
        toks.append(_Tok(kind, m.group(m.lastindex), col))
        pos = m.end()
    toks.append(_Tok("end", "", len(src) + 1))
    return toks


# --- expression nodes ---------------------------------------------------------------------


class _ExprNode(Node):
    """Internal formula nodes: not configurable on their own, so ``Params`` is empty."""

    def __init__(self, *args: Any):
        super().__init__(Params())
        self.args = args


class Const(_ExprNode):
    def field(self, x, y, z, t):
        return self.args[0]


class Var(_ExprNode):
    def field(self, x, y, z, t):
        return {"x": x, "y": y, "z": z, "t": t}[self.args[0]]


class Param(_ExprNode):
    """An extra variable (e.g. the distance ``d`` of attribute formulas, hfrep seed section 7).

    Its value is read at evaluation time from the mapping given to ``parse_formula``; the
    caller stores arrays there (shaped like x, y, z) before evaluating the tree.
    """

    def field(self, x, y, z, t):
        name, env = self.args
        return env[name]


class BinOp(_ExprNode):
    def field(self, x, y, z, t):
        op, a, b = self.args
        return _apply(op, a.field(x, y, z, t), b.field(x, y, z, t))


class Chain(_ExprNode):
    """a op1 b op2 c ...: a left-to-right run of + and - (or of * and /) as one node, so that a
    formula of many terms is one level deep; args: the first operand, then (op, operand) pairs."""

    def field(self, x, y, z, t):
        first, rest = self.args
        acc = first.field(x, y, z, t)
        for op, node in rest:
            acc = _apply(op, acc, node.field(x, y, z, t))
        return acc


def _apply(op: str, a: Any, b: Any) -> Any:
    if op == "+":
        return a + b
    if op == "-":
        return a - b
    if op == "*":
        return a * b
    return ops.div(a, b)


class Neg(_ExprNode):
    def field(self, x, y, z, t):
        return -self.args[0].field(x, y, z, t)


class Pow(_ExprNode):
    """a ^ b. A constant integer exponent is exact on any base; a constant real exponent needs
    a >= 0; a variable exponent is exp(b log a)."""

    def field(self, x, y, z, t):
        base, expo = self.args
        fa = base.field(x, y, z, t)
        if isinstance(expo, Const):
            return ops.pow_(fa, expo.args[0])
        return ops.exp(expo.field(x, y, z, t) * ops.log(fa))


class Func(_ExprNode):
    _UNARY = {"sqrt": ops.sqrt, "exp": ops.exp, "log": ops.log, "sin": ops.sin, "cos": ops.cos, "abs": ops.abs_}

    def field(self, x, y, z, t):
        name, args = self.args
        vals = [a.field(x, y, z, t) for a in args]
        if name in self._UNARY:
            return self._UNARY[name](vals[0])
        if name == "min":
            return reduce(ops.minimum, vals)
        if name == "max":
            return reduce(ops.maximum, vals)
        return Pow(args[0], args[1]).field(x, y, z, t)  # pow(a, b)


# --- parser ---------------------------------------------------------------------------------


class _Parser:
    def __init__(self, src: str, variables: dict[str, Any] | None = None):
        if len(src) > MAX_FORMULA_LENGTH:
            raise FormulaError(f"formula too long: {len(src):,} characters (the limit is {MAX_FORMULA_LENGTH:,})",
                               MAX_FORMULA_LENGTH + 1)
        self.toks = _tokenise(src)
        self.i = 0
        self.variables = variables
        self.depth = 0

    def nested(self, tok: _Tok) -> None:
        """Enter one nesting level (a parenthesis, a call, an exponent); the caller leaves it."""
        self.depth += 1
        if self.depth > MAX_FORMULA_DEPTH:
            raise FormulaError(f"formula nested deeper than {MAX_FORMULA_DEPTH} levels (the limit)", tok.col)

    @property
    def tok(self) -> _Tok:
        return self.toks[self.i]

    def take(self, text: str | None = None) -> _Tok:
        tok = self.tok
        if text is not None and tok.text != text:
            found = tok.text or "end of formula"
            raise FormulaError(f"expected {text!r}, found {found!r}", tok.col)
        self.i += 1
        return tok

    def parse(self) -> Node:
        if self.tok.kind == "end":
            raise FormulaError("empty formula", 1)
        node = self.expr()
        if self.tok.kind != "end":
            raise FormulaError(f"unexpected {self.tok.text!r}", self.tok.col)
        return node

    def expr(self) -> Node:
        return self.chain(("+", "-"), self.term)

    def term(self) -> Node:
        return self.chain(("*", "/"), self.unary)

    def chain(self, opers: tuple[str, str], operand) -> Node:
        """operand (op operand)* as one Chain node, constants folded left to right."""
        first, first_col, rest = operand(), self.tok.col, []
        while self.tok.text in opers:
            op = self.take()
            rhs = operand()
            if op.text == "/" and isinstance(rhs, Const) and rhs.args[0] == 0:
                raise FormulaError("division by zero", op.col)
            if not rest and isinstance(first, Const) and isinstance(rhs, Const):
                first = _fold(BinOp(op.text, first, rhs), op.col)  # a constant prefix stays one constant
            else:
                rest.append((op.text, rhs))
        return first if not rest else _fold(Chain(first, rest), first_col)

    def unary(self) -> Node:
        """A run of signs, counted rather than recursed into (``- - - x`` is ``-x``)."""
        negate, col = False, self.tok.col
        while self.tok.text in ("-", "+"):
            negate ^= self.take().text == "-"
        inner = self.power()
        return _fold(Neg(inner), col) if negate else inner

    def power(self) -> Node:
        node = self.atom()
        if self.tok.text == "^":
            op = self.take()
            self.nested(op)
            node = _fold(Pow(node, self.unary()), op.col)
            self.depth -= 1
        return node

    def atom(self) -> Node:
        tok = self.take()
        if tok.kind == "num":
            return Const(float(tok.text))
        if tok.text == "(":
            self.nested(tok)
            node = self.expr()
            self.take(")")
            self.depth -= 1
            return node
        if tok.kind == "name":
            return self.name(tok)
        found = tok.text or "end of formula"
        raise FormulaError(f"unexpected {found!r}", tok.col)

    def name(self, tok: _Tok) -> Node:
        n = tok.text
        if n in ("x", "y", "z", "t"):
            return Var(n)
        if self.variables is not None and n in self.variables:
            return Param(n, self.variables)
        if n in _CONSTS:
            return Const(_CONSTS[n])
        if n not in _FUNCS:
            known = ", ".join(["x", "y", "z", "t", *(self.variables or ()), *_CONSTS, *_FUNCS])
            raise FormulaError(f"unknown name {n!r} (known: {known})", tok.col)
        self.take("(")
        self.nested(tok)
        args = [self.expr()]
        while self.tok.text == ",":
            self.take()
            args.append(self.expr())
        self.take(")")
        self.depth -= 1
        want = _FUNCS[n]
        if (want > 0 and len(args) != want) or (want < 0 and len(args) < -want):
            need = f"{want}" if want > 0 else f"at least {-want}"
            raise FormulaError(f"{n}() takes {need} argument(s), got {len(args)}", tok.col)
        return _fold(Func(n, args), tok.col)


def _fold(node: Node, col: int) -> Node:
    """Replace a node whose arguments are all constants by its value."""
    kids = [a for a in node.args if isinstance(a, Node)] + [
        a for arg in node.args if isinstance(arg, list) for a in arg
    ]
    if isinstance(node, Chain):
        kids = [node.args[0]] + [n for _, n in node.args[1]]
    if not kids or not all(isinstance(k, Const) for k in kids):
        return node
    if isinstance(node, BinOp) and node.args[0] == "/" and node.args[2].args[0] == 0:
        raise FormulaError("division by zero", col)
    with np.errstate(all="ignore"):
        val = float(np.asarray(node.field(np.zeros(1), np.zeros(1), np.zeros(1), 0.0)).reshape(-1)[0])
    if not math.isfinite(val):
        raise FormulaError("constant sub-expression is not a finite number", col)
    return Const(val)


def parse_formula(src: str, variables: dict[str, Any] | None = None) -> Node:
    """Parse a formula into expression nodes; raises FormulaError with the column.

    ``variables``: extra variable names (keys) beyond x, y, z, t; the parsed tree reads their
    values from this same mapping when evaluated, so fill it before calling ``field``. Names
    of constants and functions cannot be shadowed (x, y, z, t are checked first too).
    """
    if variables:
        clash = sorted(set(variables) & ({"x", "y", "z", "t"} | set(_CONSTS) | set(_FUNCS)))
        if clash:
            raise ValueError(f"extra variables may not reuse built-in names: {clash}")
    return _Parser(src, variables).parse()


@register("expr")
class Expr(Node):
    """A formula node: ``expr: "1 - x^2 - y^2 - z^2"`` or ``expr: {formula: ...}``."""

    class Params(Params):
        formula: str = Field(min_length=1)

    scalar_field = "formula"

    def __init__(self, params, where=""):
        super().__init__(params, where)
        self.tree = parse_formula(params.formula)

    def field(self, x, y, z, t):
        return self.tree.field(x, y, z, t)
