"""The stage protocol, and the typed results stages hand to each other.

A stage is a module of this package with:

* ``Params`` -- a :class:`StageParams` model (unknown keys forbidden), validated by the loader;
* ``REQUIRES`` / ``PRODUCES`` -- the types of the results (below) it reads from the context
  and puts on it (optional); the loader checks that a stage before it produces each it requires;
* ``grids(params) -> list[str]`` -- the grids it adds, in the order they are written (the
  loader checks ``export.grids`` against them; the runner orders the context's grids by them);
* ``estimate_bytes(job, params, band: BandEstimate) -> (bytes, what)`` -- its peak memory, given
  the narrow band every stage holds, checked before the job starts (exit 2 with the estimate
  when it will not fit);
* a stage that produces the :class:`FrepBand` without requiring one (voxelise; components
  replaces it) also estimates it: ``estimate_band(job, params)
  -> BandEstimate``, after ``enumeration_bytes(job, params) -> (bytes, what)``, the memory of
  the estimate itself (checked first: the estimate enumerates the domain's top-level cells);
* ``run(ctx, params) -> dict`` -- the work; the dict goes into the manifest as the stage's stats.

Results other stages read go on the context by type (``ctx.put(FrepBand(...))``,
``ctx.get(FrepBand)``), grids by name (``ctx.grids``). A bad input found while running is an
``InputError(message, path)`` with ``path`` relative to the stage's parameters; the job layer
turns it into ``file:line`` (pipeline.job.config.stage_path).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict

from pipeline.sparse.grid import BlockGrid


class StageParams(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass
class FrepBand:
    """The sampled ``frep`` field as the later stages use it (made by voxelise, replaced by
    components when ``keep:`` removes pieces).

    ``blocks``: the band's leaves (f > 0 inside); ``inside_boxes``: (K, 2, 3) index boxes proven
    inside; ``band``: the band's half-width in voxels; ``signed``: every voxel of the leaves
    holds a value of its true sign (evaluated, or +-background by its cell's proof), so the
    eikonal set-up needs no flood fill of the band's signs."""

    blocks: BlockGrid
    inside_boxes: np.ndarray
    band: float
    signed: bool


@dataclass(frozen=True)
class BandEstimate:
    """The :class:`FrepBand` a job will hold, estimated before it runs: ``bytes`` of its grids,
    its half-width ``voxels`` (the producing stage's ``band``)."""

    bytes: float
    voxels: float


def band_only(job, params, band: BandEstimate) -> tuple[float, str]:
    """``estimate_bytes`` of a stage that holds no more than the band grids."""
    return band.bytes, "its narrow band"
