"""Numba's cache does not see changes in called modules (pipeline/__init__.py keys it instead):
every module whose compiled functions other compiled functions call must be in the key."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pipeline

ROOT = Path(pipeline.__file__).resolve().parent


def _compiled(tree: ast.Module) -> set[str]:
    """Compiled functions: decorated with a jit, or made by one (``key3 = njit(...)(key_of)``)."""
    decorated = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)
                 and any("jit" in ast.unparse(d) or "vectorize" in ast.unparse(d) for d in n.decorator_list)}
    made = {t.id for n in ast.walk(tree) if isinstance(n, ast.Assign) and isinstance(n.value, ast.Call)
            and isinstance(n.value.func, ast.Call) and "jit" in ast.unparse(n.value.func.func)
            for t in n.targets if isinstance(t, ast.Name)}
    return decorated | made


def _calls(fn: ast.FunctionDef) -> set[str]:
    return {n.func.id for n in ast.walk(fn) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}


def test_every_kernel_provider_keys_the_cache() -> None:
    trees = {p.relative_to(ROOT).as_posix(): ast.parse(p.read_text()) for p in ROOT.rglob("*.py")}
    kernels = {name: _compiled(t) for name, t in trees.items()}
    providers = set()
    for name, tree in trees.items():
        imported = {a.asname or a.name: n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
                    and n.module and n.module.startswith("pipeline.") for a in n.names}
        for fn in (n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name in kernels[name]):
            for called in _calls(fn) & set(imported):
                src = imported[called].removeprefix("pipeline.").replace(".", "/") + ".py"
                if called in kernels.get(src, set()):
                    providers.add(src)
    assert "mesh/bsp_minmax.py" in providers  # the scan sees tape.py's calls
    assert providers <= set(pipeline.KERNEL_PROVIDERS), providers - set(pipeline.KERNEL_PROVIDERS)


def test_cache_folder_changes_with_a_provider(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    pipeline._numba_cache_dir()
    first = os.environ["NUMBA_CACHE_DIR"]
    assert first.startswith(str(tmp_path))
    monkeypatch.setattr(pipeline, "KERNEL_PROVIDERS", pipeline.KERNEL_PROVIDERS[1:])
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    pipeline._numba_cache_dir()
    assert os.environ["NUMBA_CACHE_DIR"] != first


def test_first_run_says_it_compiles(tmp_path, monkeypatch) -> None:
    """A run that found no cache folder for these sources tells the user it is compiling."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "not-yet"))
    assert pipeline._cache_is_new()
    monkeypatch.setattr(pipeline, "CACHE_IS_NEW", pipeline._cache_is_new())
    notice = pipeline.first_run_notice()
    assert notice is not None and "compiling" in notice and str(tmp_path / "not-yet") in notice
    (tmp_path / "not-yet").mkdir()
    assert not pipeline._cache_is_new()
    monkeypatch.setattr(pipeline, "CACHE_IS_NEW", False)
    assert pipeline.first_run_notice() is None


def _parallel_callers(trees: dict[str, ast.Module]) -> list[str]:
    """Compiled functions that call a ``parallel=True`` compiled function (of their module or
    imported from another pipeline module)."""
    parallel, compiled, imported = set(), set(), {}
    for name, tree in trees.items():
        module = "pipeline." + name.removesuffix(".py").replace("/", ".")
        imported[module] = {a.asname or a.name: f"{n.module}.{a.name}" for n in ast.walk(tree)
                            if isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("pipeline.")
                            for a in n.names}
        compiled |= {f"{module}.{f}" for f in _compiled(tree)}
        parallel |= {f"{module}.{n.name}" for n in tree.body if isinstance(n, ast.FunctionDef)
                     and any("parallel=True" in ast.unparse(d) for d in n.decorator_list)}
    found = []
    for name, tree in trees.items():
        module = "pipeline." + name.removesuffix(".py").replace("/", ".")
        for fn in (n for n in tree.body if isinstance(n, ast.FunctionDef) and f"{module}.{n.name}" in compiled):
            for called in _calls(fn):
                target = imported[module].get(called, f"{module}.{called}")
                if target in parallel:
                    found.append(f"{module}.{fn.name} -> {target}")
    return found


def test_no_compiled_function_calls_a_parallel_one() -> None:
    """Numba's cache crashes such a caller (numba issues #8578, #4807): compiled in a process
    that loaded the parallel callee from the cache, it segfaults when it is loaded later.
    Parallel kernels are called from Python."""
    trees = {p.relative_to(ROOT).as_posix(): ast.parse(p.read_text()) for p in ROOT.rglob("*.py")}
    assert _parallel_callers(trees) == []
    probe = ast.parse("from numba import njit\n@njit(parallel=True)\ndef p(a):\n    return a\n"
                      "@njit(cache=True)\ndef q(a):\n    return p(a)\n")
    assert _parallel_callers({"probe.py": probe}) == ["pipeline.probe.q -> pipeline.probe.p"]  # the scan sees one


MERGE = """
import sys
import numpy as np
from pipeline.io import meshkernels as mk
rng = np.random.default_rng(3)
pts = rng.integers(0, 40, (3000, 3)).astype(np.float32)
tris = rng.integers(0, 3000, (5000, 3)).astype(np.int64)
if sys.argv[1] == "callee":
    mk.unique_rows_first(pts.view(np.uint32))
else:
    source, t = mk.merge_kernel(pts.view(np.uint32), tris)
    p, w = mk.weld_kernel(pts, pts.view(np.uint32), tris)
    print(len(source), len(t), len(p), len(w))
"""


def test_mesh_merges_run_from_the_cache_after_their_parallel_step(tmp_path) -> None:
    """The order that crashed ``frepvdb convert x.vdb x.stl``: one process caches the parallel
    point merge (a run that wrote a .vtp), the next compiles the mesh merge, the third loads it."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", MERGE, step], env=env, capture_output=True, text=True,
                           timeout=600, cwd=ROOT.parent) for step in ("callee", "compile", "load")]
    assert [r.returncode for r in runs] == [0, 0, 0], runs[-1].stderr[-2000:]
    assert runs[1].stdout == runs[2].stdout and runs[2].stdout.strip()
