"""frepvdb: FRep and mesh fields to sparse OpenVDB grids."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: modules whose compiled functions are called by compiled functions of other modules
KERNEL_PROVIDERS = (
    "mesh/bsp_minmax.py", "distance/fim.py", "distance/eikonal.py", "mesh/bsp_build.py", "field/rkernels.py",
)


def _numba_cache_dir() -> None:
    """Point Numba's on-disk cache at a folder keyed by the kernel providers' sources.

    Numba's cache checks only the source file of each compiled function: a kernel of
    pipeline/model/tape.py that calls one of pipeline/mesh/bsp_minmax.py keeps its old machine code when
    only bsp_minmax.py changes (an upgrade, an edit) and silently runs the old formula. Keying
    the cache by the contents of every module whose kernels others call makes such a change
    recompile (tests/test_numba_cache.py checks the list). A user's NUMBA_CACHE_DIR is kept."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    here = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for name in KERNEL_PROVIDERS:
        h.update((here / name).read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "frepvdb" / "numba"
    os.environ["NUMBA_CACHE_DIR"] = str(base / h.hexdigest()[:16])


_numba_cache_dir()
