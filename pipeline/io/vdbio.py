"""Writing .vdb files atomically, and metadata conversion to the types pyopenvdb stores.

OpenVDB metadata holds str, bool, int, float and 3-vectors (int or float). Everything else
that a stage wants to record (lists, dicts, None, paths, NumPy scalars) is converted here:
NumPy scalars to Python numbers, 3-sequences of numbers to vec3i/vec3d, anything nested to a
JSON string, so that Houdini and Blender show it and scripts can ``json.loads`` it back.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import json
import os
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.vdbgrids import compiled_writer, min_max, vdb
from pipeline.util.atomic import atomic_path
from pipeline.util.errors import InputError

HALF_EXACT_INT = 2048  # largest integer below which every integer is exact in IEEE half precision
_INT64 = (-(2**63), 2**63 - 1)




def metadata_value(value: Any) -> str | bool | int | float | tuple:
    """Convert ``value`` to a type pyopenvdb stores as grid or file metadata."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool | str | float):
        return value
    if isinstance(value, int):
        return value if _INT64[0] <= value <= _INT64[1] else str(value)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    vec = _as_vec3(value)
    if vec is not None:
        return vec
    return json.dumps(_jsonable(value), sort_keys=True)


def _as_vec3(value: Any) -> tuple | None:
    """A 3-tuple of ints (vec3i) or floats (vec3d) when ``value`` is a sequence of 3 numbers."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, list | tuple) or len(value) != 3:
        return None
    if not all(isinstance(c, int | float | np.number) and not isinstance(c, bool) for c in value):
        return None
    if all(isinstance(c, int | np.integer) for c in value):
        ints = tuple(int(c) for c in value)
        return ints if all(-(2**31) <= c < 2**31 for c in ints) else None
    return tuple(float(c) for c in value)


def _jsonable(value: Any) -> Any:
    """Recursively turn NumPy types, tuples, sets and paths into JSON-serialisable values."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_jsonable(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)


def set_grid_metadata(grid: Any, meta: Mapping[str, Any]) -> None:
    """Set every ``meta`` item on ``grid`` (values converted by :func:`metadata_value`)."""
    for key, value in meta.items():
        grid[str(key)] = metadata_value(value)


def file_metadata_dict(meta: Mapping[str, Any]) -> dict[str, Any]:
    """File-level metadata converted item by item for ``pyopenvdb.write``."""
    return {str(k): metadata_value(v) for k, v in meta.items()}


def _half_names(grids: list, half_float: bool | Iterable[str]) -> set[str]:
    if half_float is True:
        return {g.name for g in grids}
    if half_float is False:
        return set()
    return set(half_float)


def _check_half_safe(grid: Any) -> None:
    """Refuse half precision for integer labels that half floats cannot represent exactly."""
    if grid.name != "component" or grid.activeVoxelCount() == 0:
        return
    _, vmax = min_max(grid)
    if float(vmax) > HALF_EXACT_INT:
        raise ValueError(
            f"grid 'component' has labels up to {int(vmax)}; half precision is exact only up to "
            f"{HALF_EXACT_INT}: write it in full precision"
        )


def write_vdb(
    path: str | os.PathLike,
    grids: list,
    file_metadata: Mapping[str, Any] | None = None,
    half_float: bool | Iterable[str] = False,
) -> Path:
    """Write ``grids`` to ``path`` atomically (temp file in the same folder, then ``os.replace``).

    ``half_float``: True stores every grid's floats as 16-bit halves, a set of names only those
    grids. Each grid's ``saveFloatAsHalf`` flag is restored afterwards. Names must be unique.
    """
    path = Path(path)
    _write_now(path, grids, file_metadata, _checked_halves(grids, half_float))
    return path


def _checked_halves(grids: list, half_float: bool | Iterable[str]) -> set[str]:
    names = [g.name for g in grids]
    if len(set(names)) != len(names) or any(not n for n in names):
        raise ValueError(f"grid names must be non-empty and unique, got {names}")
    halves = _half_names(grids, half_float)
    unknown = halves - set(names)
    if unknown:
        raise ValueError(f"half_float names grids that are not written: {sorted(unknown)}")
    for g in grids:
        if g.name in halves:
            _check_half_safe(g)
    return halves


def _write_now(path: Path, grids: list, file_metadata: Mapping[str, Any] | None, halves: set[str],
               tmp_name: str | None = None) -> None:
    """The atomic write of checked arguments (through the temporary file ``tmp_name`` when
    given); each grid's ``saveFloatAsHalf`` flag is set for it and restored afterwards."""
    saved = [g.saveFloatAsHalf for g in grids]
    try:
        for g in grids:
            g.saveFloatAsHalf = g.name in halves
        with atomic_path(path, tmp_name) as tmp:
            vdb.write(str(tmp), grids=list(grids), metadata=file_metadata_dict(file_metadata or {}))
    finally:
        for g, flag in zip(grids, saved, strict=True):
            g.saveFloatAsHalf = flag


class PendingWrite:
    """A .vdb being written by a forked child process (:func:`write_vdb_beside`); :meth:`wait`
    returns its path or raises the child's error (an OSError keeps its errno and file name)."""

    def __init__(self, path: Path, pid: int | None, errors: int | None, tmp: Path | None = None):
        self.path, self._pid, self._errors, self._tmp = path, pid, errors, tmp

    def wait(self) -> Path:
        if self._pid is None:
            return self.path
        pid, self._pid = self._pid, None
        _, status = os.waitpid(pid, 0)
        with os.fdopen(self._errors, "rb") as f:
            report = f.read()
        code = os.waitstatus_to_exitcode(status)
        if code == 0 and not report:
            return self.path
        if not report:  # killed (by the kernel's OOM killer, say) before it could say why
            how = f"killed by signal {-code}" if code < 0 else f"exited with status {code}"
            raise OSError(errno.EIO, f"the process writing it was {how}", str(self.path))
        err = json.loads(report)
        if err.get("errno") is not None:
            raise OSError(err["errno"], err["message"], err.get("filename") or str(self.path))
        raise RuntimeError(f"writing {self.path.name}: {err['message']}")

    def cancel(self) -> None:
        """Kill the child and reap it (used when the export fails; the output is not renamed into
        place, and the job's staging folder with any temp file in it is discarded)."""
        if self._pid is None:
            return
        import signal

        pid, self._pid = self._pid, None
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(self._errors)
        if self._tmp is not None:  # the child may have been killed after it made its temporary file
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._tmp)


class ThreadedWrite:
    """A .vdb being written by a thread of this process through the compiled writer
    (pipeline/io/leafbuild.cpp ``write_file``: pyopenvdb's io::File write without the GIL);
    :meth:`wait` returns its path or raises the thread's error."""

    def __init__(self, writer, path: Path, grids: list, file_metadata: Mapping[str, Any], halves: set[str]):
        self.path, self._error, self._cancelled = path, None, False
        args = (writer, list(grids), file_metadata_dict(file_metadata), [g.name in halves for g in grids])
        self._thread = threading.Thread(target=self._run, args=args, name=f"writing {path.name}", daemon=True)
        self._thread.start()

    def _run(self, writer, grids: list, metadata: dict, halves: list[bool]) -> None:
        try:
            with atomic_path(self.path) as tmp:
                writer(grids, str(tmp), metadata, halves)
                if self._cancelled:  # the temp file is removed, nothing is renamed into place
                    raise _Cancelled
        except BaseException as e:  # noqa: BLE001 - raised again by wait()
            self._error = e

    def wait(self) -> Path:
        self._thread.join()
        if self._error is not None:
            error, self._error = self._error, None
            raise error
        return self.path

    def cancel(self) -> None:
        """Let the write finish without renaming it into place (compiled code cannot be
        interrupted; the job's staging folder is discarded after this)."""
        self._cancelled = True
        self._thread.join()
        self._error = None


class _Cancelled(Exception):
    pass


def write_vdb_beside(
    path: str | os.PathLike,
    grids: list,
    file_metadata: Mapping[str, Any] | None = None,
    half_float: bool | Iterable[str] = False,
) -> ThreadedWrite | PendingWrite:
    """:func:`write_vdb` while this process goes on: in a thread through the compiled writer
    when it is built and takes every grid, else in a forked child (POSIX; elsewhere, or with
    FREPVDB_SERIAL_WRITE=1, it writes before returning). Bad arguments are refused here.

    Why not pyopenvdb in a thread: it holds the GIL while it compresses and writes (4-5 s for
    the demo's five grids at 1024^3), and the export's other work (VTK files, previews) holds
    the GIL too. The compiled writer releases it. The forked child shares the grids' memory
    copy-on-write and only reads it; it dies with this process (PR_SET_PDEATHSIG) and reports
    an error as JSON on a pipe. The thread costs less: at 1024^3 the demo's export took 8.1 s
    with it, 9.5 s with the child, whose write took 6.4 s of CPU against 4.8 s here (the
    fork's copy-on-write page faults)."""
    path = Path(path)
    halves = _checked_halves(grids, half_float)
    meta = dict(file_metadata or {})
    writer = compiled_writer(grids)
    if os.environ.get("FREPVDB_SERIAL_WRITE") == "1" or (writer is None and not hasattr(os, "fork")):
        _write_now(path, grids, meta, halves)
        return PendingWrite(path, None, None)
    if writer is not None:
        return ThreadedWrite(writer, path, grids, meta, halves)
    read_end, write_end = os.pipe()
    tmp_name = f".{path.stem}.{os.getpid()}-{next(_CHILD_WRITES)}.tmp{path.suffix}"  # known here: cancel removes it
    pid = os.fork()
    if pid == 0:  # the child: write, report, leave without running the parent's exit handlers
        code = 0
        try:
            os.close(read_end)
            _die_with_parent()
            _write_now(path, grids, meta, halves, tmp_name)
        except BaseException as e:  # noqa: BLE001 - everything goes back to the parent
            code = 1
            # short: the parent reads the pipe only after the child has exited, and a report
            # larger than the pipe's buffer (64 KiB) would block the child's write forever
            err = {"message": str(getattr(e, "strerror", None) or e)[:2000], "errno": getattr(e, "errno", None),
                   "filename": str(getattr(e, "filename", None) or "")[:4000] or None}
            with contextlib.suppress(Exception):
                os.write(write_end, json.dumps(err, default=str).encode())
        finally:
            os._exit(code)
    os.close(write_end)
    return PendingWrite(path, pid, read_end, path.parent / tmp_name)


_CHILD_WRITES = itertools.count()  # numbers the forked writers' temporary files within a process


def _die_with_parent() -> None:
    """Linux: the child gets SIGKILL when its parent dies (a killed run leaves no writer behind)."""
    with contextlib.suppress(Exception):
        import ctypes
        import signal

        ctypes.CDLL(None).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG


def read_grids(path: str | os.PathLike) -> dict:
    """Every grid of a .vdb file by name (OpenVDB's own errors, plain RuntimeErrors, pass up)."""
    return {g.name: g for g in vdb.readAll(str(path))[0]}


@dataclass
class DenseGrid:
    """A float grid read from a .vdb file as a dense array over its active bounding box grown by
    one voxel: ``values[i - lo]`` is voxel i (background where nothing is stored);
    ``origin`` + ``axes`` @ i is voxel i's world position (the grid's linear transform)."""

    values: np.ndarray
    lo: np.ndarray
    background: float
    level_set: bool
    origin: np.ndarray
    axes: np.ndarray


def read_dense(path: Path, name: str | None, max_voxels: int) -> DenseGrid:
    """The float grid ``name`` (default: the first float grid) of a .vdb file, densely; an
    InputError for a missing or unreadable file, a missing or non-float grid, or an active
    bounding box of more than ``max_voxels``."""
    grid = _read_grid(path, name)
    bbox = grid.evalActiveVoxelBoundingBox()
    lo = np.asarray(bbox[0], np.int64) - 1
    hi = np.asarray(bbox[1], np.int64) + 1
    dims = hi - lo + 1
    if np.prod(dims.astype(float)) > max_voxels:
        raise InputError(f"{path}: the active bounding box {dims.tolist()} is too large to sample")
    dense = np.zeros(tuple(int(d) for d in dims), np.float32)
    grid.copyToArray(dense, tuple(int(c) for c in lo))
    o = np.asarray(grid.transform.indexToWorld((0, 0, 0)))
    axes = np.stack([np.asarray(grid.transform.indexToWorld(tuple(e))) - o for e in np.eye(3)], axis=1)
    return DenseGrid(dense, lo, float(grid.background), grid.gridClass == vdb.GridClass.LEVEL_SET, o, axes)


def _read_grid(path: Path, name: str | None):
    if not path.exists():
        raise InputError(f"{path}: no such file")
    try:
        grids, _ = vdb.readAll(str(path))
    except Exception as e:  # pyopenvdb raises plain RuntimeError/IOError for bad files
        raise InputError(f"{path}: cannot read as a .vdb file ({e})") from None
    floats = [g for g in grids if g.valueTypeName == "float"]
    if name is not None:
        found = [g for g in grids if g.name == name]
        if not found:
            raise InputError(f"{path}: no grid named {name!r} (grids: {[g.name for g in grids]})")
        if found[0].valueTypeName != "float":
            raise InputError(f"{path}: grid {name!r} is {found[0].valueTypeName}, not float")
        return found[0]
    if not floats:
        raise InputError(f"{path}: no float grid in the file")
    return floats[0]
