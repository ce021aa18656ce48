"""Numba's threading layer (pipeline/__init__.py): a parallel kernel costs the same to launch
after thousands of launches as at the first ones. With Numba's TBB layer on Debian's libtbb the
launch cost grew from ~22 us to ~0.9 ms over 12,000 launches, so the component detection of
one small model took 0.1 s in a fresh process and 30 s after a few dozen models."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import sys, time
import numpy as np
import pipeline, numba
from pipeline.sparse.grid import leaf_has_active
a = np.zeros((2, 8, 8, 8), bool)
leaf_has_active(a)
def per_call(n):
    t0 = time.perf_counter()
    for _ in range(n):
        leaf_has_active(a)
    return (time.perf_counter() - t0) / n
first = per_call(500)
for _ in range(8):
    per_call(1000)
last = per_call(500)
print(numba.threading_layer(), first, last)
"""


def _probe(env: dict) -> tuple[str, float, float]:
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=300, cwd=ROOT, env=env)
    assert r.returncode == 0, r.stderr
    layer, first, last = r.stdout.split()
    return layer, float(first), float(last)


def test_launch_cost_does_not_grow_with_the_launches() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    layer, first, last = _probe(env)
    assert layer == "omp"  # libgomp is there on Debian (.ci/setup.sh installs it when missing)
    assert last < 3 * first + 20e-6, (first, last)


def test_a_users_choice_of_layer_is_kept() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    env["NUMBA_THREADING_LAYER"] = "workqueue"
    assert _probe(env)[0] == "workqueue"


def test_idle_openmp_threads_spin_briefly_unless_the_user_says() -> None:
    """A short spin (pipeline.GOMP_SPINCOUNT) keeps two processes on two cores from slowing each
    other; a user's OMP_WAIT_POLICY or GOMP_SPINCOUNT is kept."""
    code = "import os, pipeline; print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))"
    base = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    for extra, want in (({}, "10000 None"), ({"GOMP_SPINCOUNT": "5"}, "5 None"),
                        ({"OMP_WAIT_POLICY": "active"}, "None active")):
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                           env={**base, **extra}, timeout=120)
        assert r.stdout.strip() == want, (extra, r.stdout, r.stderr)
