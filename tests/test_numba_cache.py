"""Numba's cache does not see changes in called modules (pipeline/__init__.py keys it instead):
every module whose compiled functions other compiled functions call must be in the key."""

from __future__ import annotations

import ast
import os
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
