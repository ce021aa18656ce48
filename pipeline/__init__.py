"""frepvdb: FRep and mesh fields to sparse OpenVDB grids."""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

#: modules whose compiled functions are called by compiled functions of other modules, and the
#: decorator that compiles them all (its options, such as the error model, are not in Numba's key)
KERNEL_PROVIDERS = (
    "mesh/bsp_minmax.py", "distance/fim.py", "distance/eikonal.py", "mesh/bsp_build.py", "field/rkernels.py",
    "sparse/access.py", "sparse/grid.py", "field/stencils.py", "field/zeroset.py", "util/jit.py",
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


def _cache_is_new() -> bool:
    cache = os.environ.get("NUMBA_CACHE_DIR")
    return bool(cache) and not Path(cache).is_dir()


#: no cache folder for these sources when this process started (looked at on import: the first
#: compiled function makes the folder, and building a model compiles some)
CACHE_IS_NEW = _cache_is_new()


def first_run_notice() -> str | None:
    """A line for the user when this process found no cache folder for these sources: the run
    compiles every kernel it uses first (about 3 minutes for the demo on 2 cores; later runs load
    them in about a second), and without a word that looks like a hang."""
    if not CACHE_IS_NEW:
        return None
    return (f"note: first run of this frepvdb version: compiling its kernels, a few minutes; they are "
            f"cached in {os.environ['NUMBA_CACHE_DIR']} for the runs after this one")


#: Numba's threading layers in the order we want them: GNU OpenMP first. With the TBB layer
#: (Numba's default when libtbb is present, as on Debian) the cost of launching a parallel
#: kernel grows with the number of launches in a process: 22 us for the first thousand, 0.9 ms
#: after twelve thousand (2026-12-03, numba 0.68, libtbb 2021.8), so a long run, a test session
#: or a batch worker gets slower the longer it lives, and exit waits for TBB's shutdown. With
#: OpenMP a launch stays ~2 us (tests/test_threading.py). libgomp is not fork-safe: our
#: executors start their workers with ``spawn``.
THREADING_LAYER_PRIORITY = "omp tbb workqueue"
#: How long (busy-wait iterations) an idle OpenMP thread spins before it sleeps. libgomp's
#: default (300,000) keeps idle threads busy for long enough that two processes on two cores
#: slow each other down (two demo runs at 512^3 side by side: 27.5 s, with TBB 23.4 s); 10,000
#: gives 24.7 s, while a run of many small kernels is as fast as with the default (sleeping at
#: once, OMP_WAIT_POLICY=passive, made component detection 4.5x slower).
GOMP_SPINCOUNT = "10000"


def _threading_layer() -> None:
    """Prefer OpenMP unless the user chose a layer (NUMBA_THREADING_LAYER[_PRIORITY]), with a
    short spin unless the user set OpenMP's wait policy or spin count."""
    if not (os.environ.get("OMP_WAIT_POLICY") or os.environ.get("GOMP_SPINCOUNT")):
        os.environ["GOMP_SPINCOUNT"] = GOMP_SPINCOUNT  # read when Numba first loads libgomp
    if os.environ.get("NUMBA_THREADING_LAYER") or os.environ.get("NUMBA_THREADING_LAYER_PRIORITY"):
        return
    os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = THREADING_LAYER_PRIORITY  # also for subprocesses
    numba = sys.modules.get("numba")
    if numba is not None:  # imported before us: its config has read the environment already
        numba.config.THREADING_LAYER_PRIORITY = THREADING_LAYER_PRIORITY.split()


_threading_layer()
