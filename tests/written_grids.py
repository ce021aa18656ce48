"""Helpers for tests that read the WRITTEN grids back and check them against ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.io.vdbgrids import vdb
from pipeline.job.config import load_job
from pipeline.job.runner import run_job

ACTIVE = np.float32(3.0e38)  # sentinel written over active values to read the active mask back


def run_config(tmp: Path, text: str, name: str = "job"):
    """Run a config through the runner (as `frepvdb run` does); (job, job folder, manifest)."""
    cfg = tmp / f"{name}.yaml"
    cfg.write_text(text)
    job = load_job(cfg)
    run_job(job, tmp / "out")
    folder = tmp / "out" / job.name
    manifest = json.loads((folder / "manifest.json").read_text(),
                          parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"not JSON: {c}")))
    return job, folder, manifest


def read_box(path: Path, grid: str, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values (active, tiles and background alike) and the active mask of ``grid`` over the index
    box lo..hi (inclusive), exactly as the file stores them."""
    g = vdb.read(str(path), grid)
    shape = tuple(int(n) for n in np.asarray(hi) - np.asarray(lo) + 1)
    vals = np.zeros(shape, np.float32)
    g.copyToArray(vals, tuple(int(c) for c in lo))
    marked = g.deepCopy()
    vdb.ax(f"@{grid} = {float(ACTIVE):.9g};", marked)
    mask = np.zeros(shape, np.float32)
    marked.copyToArray(mask, tuple(int(c) for c in lo))
    return vals, mask == ACTIVE


def unclosed_pairs(vals: np.ndarray, active: np.ndarray) -> int:
    """Face-neighbour pairs with a sign change (f > 0 vs f <= 0) where a voxel is inactive."""
    inside = vals > 0
    bad = 0
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        change = inside[tuple(a)] != inside[tuple(b)]
        bad += int(np.count_nonzero(change & ~(active[tuple(a)] & active[tuple(b)])))
    return bad


def model_values(job, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The model evaluated densely (float64) at every voxel centre of the index box lo..hi."""
    h = job.domain.voxel_size
    axes = [np.arange(lo[i], hi[i] + 1) * h for i in range(3)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    return job.model.evaluate_xyz(x, y, z, job.t).astype(np.float64)
