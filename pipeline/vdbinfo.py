"""`frepvdb info FILE.vdb`: a readable summary of every grid in a .vdb file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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
        vmin, vmax = grid.evalMinMax()
        lines.append(f"  index bbox:    {_fmt(tuple(lo))} .. {_fmt(tuple(hi))}")
        lines.append(f"  world bbox:    {_fmt(tuple(wlo))} .. {_fmt(tuple(whi))}  (voxel centres)")
        lines.append(f"  active min:    {_fmt(_value(vmin))}")
        lines.append(f"  active max:    {_fmt(_value(vmax))}")
    meta = {k: v for k, v in grid.metadata.items() if k not in _SKIP_META}
    if meta:
        lines.append("  metadata:")
        lines.extend(f"    {k}: {_fmt(meta[k])}" for k in sorted(meta))
    return lines


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
