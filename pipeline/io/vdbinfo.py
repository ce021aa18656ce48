"""`frepvdb info FILE.vdb`: a readable summary of every grid in a .vdb file.

A damaged file can crash OpenVDB's reader (a segfault takes the interpreter with it), so the
command checks the header and the grid offsets itself (:func:`check_vdb_header`) and then reads
the file in a child process (:func:`describe_vdb_isolated`): a crash there is "file is corrupt".
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.vdbgrids import min_max, vdb

_SKIP_META = {"name", "class"}  # shown in the grid's header line


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, tuple):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return str(value)


def _clip(text: str, limit: int = 200) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit] + "..."


def _check_path(path: Path) -> None:
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not a .vdb file")
    if not path.is_file():
        raise ValueError(f"{path}: no such file")


def _read(path: Path) -> tuple[list, dict]:
    _check_path(path)
    try:
        grids, meta = vdb.readAll(str(path))
    except Exception as exc:  # pyopenvdb raises IOError/KeyError/RuntimeError by case
        raise ValueError(f"{path}: not a readable OpenVDB file ({_clip(exc)})") from exc
    return grids, meta


# --- the header, read without OpenVDB -----------------------------------------------------------

VDB_MAGIC = 0x56444220  # "VDB " as a little-endian int64 at byte 0
_OFFSETS_FROM_VERSION = 222  # file versions whose header layout check_vdb_header knows (OpenVDB >= 3)


class _Bytes:
    """A cursor over the file's bytes that reports where a field runs past the end."""

    def __init__(self, data: bytes, path: Path):
        self.data, self.pos, self.path = data, 0, path

    def fail(self, at: int, why: str) -> ValueError:
        return ValueError(f"{self.path}: byte {at}: {why}")

    def take(self, n: int, what: str) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise self.fail(self.pos, f"file is truncated or corrupt ({what} of {n:,} bytes runs past the end "
                                      f"of the {len(self.data):,}-byte file)")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str, what: str) -> int:
        return struct.unpack("<" + fmt, self.take(struct.calcsize(fmt), what))[0]

    def string(self, what: str) -> str:
        return self.take(self.unpack("I", f"length of {what}"), what).decode("latin-1")


def check_vdb_header(path: Path, data: bytes) -> None:
    """Check the magic number, the file metadata and every grid's offsets against the file
    size, so that a truncated or damaged header is reported here with its byte offset."""
    b = _Bytes(data, path)
    if len(data) < 8 or struct.unpack("<q", data[:8])[0] != VDB_MAGIC:
        raise b.fail(0, "not an OpenVDB file (no VDB magic number)")
    b.pos = 8
    version = b.unpack("I", "file version")
    if version < _OFFSETS_FROM_VERSION:
        return  # an old layout: left to OpenVDB (in the child process)
    b.take(8, "library version")
    has_offsets = b.unpack("B", "grid offsets flag")
    b.take(36, "file UUID")
    for _ in range(_count(b, "file metadata count")):
        b.string("metadata name")
        b.string("metadata type")
        b.take(b.unpack("I", "metadata size"), "metadata value")
    if not has_offsets:
        return
    for _ in range(_count(b, "grid count")):
        start = b.pos
        name = b.string("grid name")
        b.string("grid type")
        b.string("grid instance parent")
        grid, block, end = (b.unpack("q", "grid offset") for _ in range(3))
        if not b.pos <= grid <= block <= end:
            raise b.fail(start, f"corrupt header: grid {_clip(name, 40)!r} has offsets {grid}, {block}, {end}")
        if end > len(data):
            raise b.fail(len(data), f"file is truncated: grid {_clip(name, 40)!r} ends at byte {end:,}")
        b.pos = end


def _count(b: _Bytes, what: str) -> int:
    at = b.pos
    n = b.unpack("i", what)
    if not 0 <= n <= len(b.data):
        raise b.fail(at, f"corrupt header ({what} {n:,})")
    return n


def describe_vdb_isolated(path: str | os.PathLike, timeout: float = 600.0) -> str:
    """:func:`describe_vdb` in a child process, after :func:`check_vdb_header`: a file that
    crashes OpenVDB's reader is reported as corrupt instead of crashing this process."""
    path = Path(path)
    _check_path(path)
    try:
        check_vdb_header(path, path.read_bytes())
    except OSError as e:
        raise ValueError(f"{path}: cannot read ({e.strerror or e})") from None
    try:
        proc = subprocess.run([sys.executable, "-m", "pipeline.io.vdbinfo", str(path)], capture_output=True,
                              text=True, errors="replace", timeout=timeout, preexec_fn=_limit_child_memory)
    except subprocess.TimeoutExpired:
        raise ValueError(f"{path}: reading the file took more than {timeout:g} s; is it corrupt?") from None
    if proc.returncode == 0:
        return proc.stdout
    if proc.returncode < 0:
        sig = signal.Signals(-proc.returncode).name
        raise ValueError(f"{path}: file is corrupt (OpenVDB's reader crashed on it: {sig})")
    lines = proc.stderr.strip().splitlines()
    raise ValueError(_clip(lines[-1] if lines else f"{path}: not a readable OpenVDB file", 300))


def _limit_child_memory() -> None:
    """A corrupt size field can make OpenVDB allocate without bound: cap the child at the
    machine's physical memory (a real file larger than that cannot be read anyway)."""
    import resource

    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = total if hard == resource.RLIM_INFINITY else min(total, hard)
    if soft == resource.RLIM_INFINITY or soft > cap:
        resource.setrlimit(resource.RLIMIT_AS, (cap, hard))


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
        vmin, vmax = min_max(grid)
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


def _main(argv: list[str]) -> int:
    """The child process of :func:`describe_vdb_isolated`: the summary on stdout, or one line
    on stderr and exit 2."""
    try:
        sys.stdout.write(describe_vdb(argv[0]))
    except (OSError, ValueError, MemoryError) as e:
        print(_clip(e, 300), file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
