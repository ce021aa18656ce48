"""The package's layers (docs/architecture.md): every import points down, and no two modules
import each other, directly or through others, counting imports inside functions too (so none
of those can be hiding a cycle)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: bottom to top; a module may import its own layer and the layers before it
LAYERS = ["util", "field", "mesh", "model", "sparse", "io", "voxel", "distance", "topology", "oracles",
          "stages", "job", "cli", "frepvdb"]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer_of(module: str) -> int | None:
    """Layer index of a module of ours (None: the package roots, which hold no code of a layer)."""
    parts = module.split(".")
    if parts[0] in ("stages", "frepvdb"):
        return LAYERS.index(parts[0])
    if parts[0] == "pipeline" and len(parts) > 1:
        return LAYERS.index(parts[1])
    return None


def _type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports_of(path: Path, modules: set[str], me: str | None = None) -> list[tuple[str, int, bool]]:
    """(imported module of ours, line, inside a function) for every import statement."""
    me = me or module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out: list[tuple[str, int, bool]] = []

    def target(node: ast.ImportFrom | ast.Import) -> list[str]:
        if isinstance(node, ast.Import):
            return [a.name for a in node.names]
        base = node.module or ""
        if node.level:
            pkg = package.split(".")[: len(package.split(".")) - node.level + 1]
            base = ".".join(pkg + ([base] if base else []))
        return [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if _type_checking(child):
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for name in target(child):
                    while name and name not in modules:
                        name = name.rpartition(".")[0]
                    if name and name != me:
                        out.append((name, child.lineno, in_function))
            else:
                walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(ast.parse(path.read_text()), False)
    return out


def graph() -> dict[str, list[tuple[str, int, bool]]]:
    files = [p for d in ("pipeline", "stages", "frepvdb") for p in (ROOT / d).rglob("*.py")]
    modules = {module_name(p) for p in files}
    return {module_name(p): imports_of(p, modules) for p in files}


def test_every_module_has_a_layer() -> None:
    missing = [m for m in graph() if layer_of(m) is None and m not in ("pipeline",)]
    assert not missing, f"modules outside every layer: {missing}"


def upward(g: dict[str, list[tuple[str, int, bool]]]) -> list[str]:
    found = []
    for mod, imports in g.items():
        for name, line, late in imports:
            lo, hi = layer_of(mod), layer_of(name)
            if lo is not None and hi is not None and hi > lo:
                found.append(f"{mod}:{line} imports {name} ({LAYERS[lo]} -> {LAYERS[hi]}{', in a function' if late else ''})")
    return found


def test_imports_point_down() -> None:
    bad = upward(graph())
    assert not bad, "\n".join(bad)


def test_no_import_cycles() -> None:
    g = {m: sorted({n for n, _, _ in imps}) for m, imps in graph().items()}
    # a module imports its package's __init__ when Python loads it; an __init__ that imports the
    # package's own modules (oracles registers its nodes) is the one allowed back edge
    cycles = _cycles({m: [n for n in ns if not m.startswith(n + ".")] for m, ns in g.items()})
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def _cycles(g: dict[str, list[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    for root in g:
        if root in index:
            continue
        work = [(root, iter(g.get(root, [])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(g.get(w, []))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


@pytest.mark.parametrize("g, cyclic", [({"a": ["b"], "b": ["c"], "c": []}, False),
                                       ({"a": ["b"], "b": ["c"], "c": ["a"]}, True),
                                       ({"a": ["b"], "b": ["a"], "c": ["a"]}, True)])
def test_the_cycle_finder_finds_cycles(g, cyclic) -> None:
    assert bool(_cycles(g)) == cyclic


def test_the_layer_check_sees_an_upward_import_in_a_function(tmp_path) -> None:
    src = tmp_path / "x.py"
    src.write_text("import numpy\n\n\ndef f():\n    from pipeline.job import config\n    return config\n")
    imps = imports_of(src, {"pipeline.job.config", "pipeline.job", "pipeline.field.x"}, me="pipeline.field.x")
    assert imps == [("pipeline.job.config", 5, True)]
    assert upward({"pipeline.field.x": imps}) == [
        "pipeline.field.x:5 imports pipeline.job.config (field -> job, in a function)"]


def openvdb_users(files: list[Path]) -> list[str]:
    """Modules outside pipeline/io that import OpenVDB's module or the name ``vdb`` from ours."""
    found = []
    for p in files:
        for node in ast.walk(ast.parse(p.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [a.name for a in node.names if (node.module or "").startswith("pipeline")]
            if any(n.split(".")[0] in ("pyopenvdb", "openvdb") or n == "vdb" for n in names):
                found.append(f"{p}:{node.lineno}")
    return found


def test_only_the_io_layer_touches_openvdb() -> None:
    """Grids are made (pipeline.io.vdbgrids), written, read and inspected (vdbio, vdbinfo) in
    pipeline/io alone: the algorithms hand over BlockGrids, leaf streams and tile lists."""
    files = [p for d in ("pipeline", "stages", "frepvdb") for p in (ROOT / d).rglob("*.py")
             if not p.is_relative_to(ROOT / "pipeline" / "io")]
    assert not openvdb_users(files)


def test_the_openvdb_check_sees_an_import(tmp_path) -> None:
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("def f():\n    import pyopenvdb as v\n    return v\n")
    b.write_text("from pipeline.io.vdbgrids import frep_to_vdb, vdb\n")
    assert len(openvdb_users([a, b])) == 2
