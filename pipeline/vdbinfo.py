"""`frepvdb info FILE.vdb`: a readable summary of every grid in a .vdb file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.grid import vdb

_SKIP_META = {"name", "class"}  # shown in the grid's header line


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, tuple):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return str(value)


def _read(path: Path) -> tuple[list, dict]:
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    try:
        grids, meta = vdb.readAll(str(path))
    except Exception as exc:  # pyopenvdb raises IOError/KeyError/RuntimeError by case
        raise ValueError(f"{path}: not a readable OpenVDB file ({exc})") from exc
    return grids, meta


def _voxel_size(grid: Any) -> tuple[float, float, float]:
    return tuple(float(c) for c in grid.transform.voxelSize())


def describe_grid(grid: Any) -> list[str]:
    """Lines describing one grid: class, type, voxel size, active voxels, bboxes, range, metadata."""
    lines = [f"grid '{grid.name}'"]
    lines.append(f"  class:         {grid.gridClass}")
    lines.append(f"  value type:    {grid.valueTypeName}")
    lines.append(f"  voxel size:    {_fmt(_voxel_size(grid))}")
    lines.append(f"  background:    {_fmt(_value(grid.background))}")
    n = int(grid.activeVoxelCount())
    lines.append(f"  active voxels: {n}")
    if n:
        lo, hi = grid.evalActiveVoxelBoundingBox()
        wlo = grid.transform.indexToWorld(lo)
        whi = grid.transform.indexToWorld(hi)
        lines.append(f"  index bbox:    {_fmt(tuple(lo))} .. {_fmt(tuple(hi))}")
        lines.append(f"  world bbox:    {_fmt(tuple(wlo))} .. {_fmt(tuple(whi))}  (voxel centres)")
        lines.extend(_range_lines(grid))
    meta = {k: v for k, v in grid.metadata.items() if k not in _SKIP_META}
    if meta:
        lines.append("  metadata:")
        lines.extend(f"    {k}: {_fmt(meta[k])}" for k in sorted(meta))
    return lines


def _range_lines(grid: Any) -> list[str]:
    """Min/max of the active values; for vector grids per component and of the magnitude.

    (OpenVDB's evalMinMax orders vectors lexicographically, which says little about a field.)
    """
    if not grid.valueTypeName.startswith("vec"):
        vmin, vmax = grid.evalMinMax()
        return [f"  active min:    {_fmt(float(vmin))}", f"  active max:    {_fmt(float(vmax))}"]
    values = np.array([item.value for item in grid.citerOnValues()], dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(values, axis=1)
    return [f"  active min:    {_fmt(tuple(values.min(axis=0).tolist()))}  (per component)",
            f"  active max:    {_fmt(tuple(values.max(axis=0).tolist()))}  (per component)",
            f"  |value| range: {_fmt(float(norm.min()))} .. {_fmt(float(norm.max()))}"]


def _value(v: Any) -> Any:
    return tuple(float(c) for c in v) if isinstance(v, tuple) else float(v)


def describe_vdb(path: str | os.PathLike) -> str:
    """Text summary of every grid in ``path``; ValueError when the file is missing or unreadable."""
    path = Path(path)
    grids, meta = _read(path)
    lines = [f"file: {path}", f"grids: {len(grids)}"]
    if meta:
        lines.append("file metadata:")
        lines.extend(f"  {k}: {_fmt(meta[k])}" for k in sorted(meta))
    for grid in grids:
        lines.extend(describe_grid(grid))
    return "\n".join(lines) + "\n"
