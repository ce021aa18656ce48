"""Atomic file writes: write to a temporary name in the same folder, then rename.

The temporary name keeps the file's suffix (writers such as matplotlib pick the format from
it). On any exception the temporary file is removed and the target is left as it was, so a
failed run never leaves a half-written output.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | os.PathLike, tmp_name: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` in one rename.
    ``tmp_name``: the temporary file's name, chosen by the caller (it must not exist), for a
    caller that has to remove it after a writer it cannot wait for (a killed child process)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if tmp_name is None:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    else:
        tmp = str(path.parent / tmp_name)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.close(fd)
    try:
        try:
            yield Path(tmp)
        except OSError as e:
            if e.filename and e.filename != tmp:
                raise
            # writers that get a file object (PIL, json) lose the name: say which file failed
            raise OSError(e.errno, e.strerror or str(e), str(path)) from e
        _fsync(tmp)  # the data is on disk before the name points at it
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _fsync(path: str) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path: str | os.PathLike, data) -> None:
    """Strict JSON (no ``NaN``/``Infinity``, which JSON does not have: non-finite floats are
    written as null) so that every JSON reader can read a manifest."""
    text = json.dumps(_finite(data), indent=2, default=_default, allow_nan=False) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _finite(o):
    import math

    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def _default(o):
    import numpy as np

    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return _finite(float(o))
    if isinstance(o, np.ndarray):
        return _finite(o.tolist())
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
