"""HFRep field: sign of the FRep function times the smoothed unsigned distance (eq. 21).

hfrep seed, definition 4.1 (eq. 14) and section 5.1 step 4:
``F_HFRep(p) = F_st(F_FRep(p)) * F_smDF(p)`` (eq. 21), where ``F_smDF`` is the C1 (here C2)
spline of the discrete unsigned distance (eq. 20, :mod:`pipeline.distance.spline`) and ``F_st`` a C1
step with range (-1, 1) (section 6.3). Steps offered:

- ``sigmoid``: eq. 23, ``r / (1 + exp(-2x/sl)) - r/2`` with r = 2 (the paper's choice, range
  (-1, 1)); algebraically equal to ``tanh(x/sl)``;
- ``tanh``: ``tanh(x/sl)`` evaluated directly (same function as ``sigmoid`` with r = 2;
  kept as its own name because configs use both);
- ``rational``: ``x / sqrt(k + x^2)`` with ``k = sl^2`` (algebraic tails: the sign is
  restored more gently away from the surface).

Extra zeros (section 5.1 step 3 requires the interpolation not to add any): the cubic
spline of an unsigned distance dips slightly below zero next to the surface (about
-0.004 voxel for a sphere), which would flip the sign of eq. 21 there. The continuous
field therefore uses the regularised distance ``sqrt(s^2 + eps^2)`` of the spline value s
(C-infinity in s, positive, changes s by at most eps^2 / (2 s), default eps = 0.05 voxel),
so ``F_HFRep`` has exactly the zero set and the sign of ``F_FRep``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import prange
from scipy.special import expit

from pipeline.distance.eikonal import EikonalResult
from pipeline.distance.spline import TricubicSpline
from pipeline.sparse.blockwrite import LeafSource, mapped_empty
from pipeline.sparse.grid import LEAF, BlockGrid, merge_sorted, pack_keys
from pipeline.util.jit import njit

STEPS = ("sigmoid", "tanh", "rational")


def step_function(x: np.ndarray, step: str = "sigmoid", slope: float = 0.01, r: float = 2.0) -> np.ndarray:
    """C1 (here C-infinity) step F_st of the FRep value, range (-1, 1) (section 6.3).

    ``sigmoid`` is eq. 23 with range parameter ``r`` (r = 2 gives (-1, 1)); ``slope`` is the
    paper's sl (units of the FRep value).
    """
    x = np.asarray(x, dtype=np.float64)
    if slope <= 0:
        raise ValueError("slope must be > 0")
    if step == "sigmoid":
        return r * expit(2.0 * x / slope) - r / 2.0
    if step == "tanh":
        return np.tanh(x / slope)
    if step == "rational":
        return x / np.sqrt(slope * slope + x * x)
    raise ValueError(f"step must be one of {STEPS}, not {step!r}")


def hfrep_field(
    frep_values: np.ndarray, distance: np.ndarray, step: str = "sigmoid", slope: float = 0.01
) -> np.ndarray:
    """Eq. 21 on arrays: ``F_st(frep) * distance`` (distance = the smoothed unsigned distance)."""
    return step_function(frep_values, step, slope) * np.asarray(distance, dtype=np.float64)


def hfrep_blocks(
    frep: BlockGrid, result: EikonalResult, step: str = "sigmoid", slope: float = 0.01
) -> BlockGrid:
    """The discrete ``hfrep`` grid (positive inside) on the eikonal blocks.

    At voxel centres the interpolating spline equals the samples, so eq. 21 is evaluated
    on the samples. Where the frep band has no value (deeper inside or farther outside)
    the step is taken as +-1 from the solved sign: there |frep| exceeds the band, where
    F_st differs from +-1 by less than float32 resolution for slopes below band/10.
    Unsolved voxels (outside, beyond max_distance) are inactive with value -background.
    """
    dist = result.distance
    rows = frep.block_index(dist.origins)  # frep row of every distance block, -1 for none
    if step not in STEPS:
        raise ValueError(f"step must be one of {STEPS}, not {step!r}")
    if slope <= 0:
        raise ValueError("slope must be > 0")
    table = np.zeros((0, LEAF, LEAF, LEAF), np.float32)
    if step == "tanh":  # np.tanh's values, taken from a table (chunks of frep: no float64 copy of it)
        table = np.zeros(frep.values.shape, np.float32)
        for a in range(0, len(table), 8192):
            act = frep.active[a:a + 8192]
            table[a:a + 8192][act] = step_function(frep.values[a:a + 8192][act], step, slope)
    # float32 throughout (this grid covers the whole interior), on mappings the writer can
    # release as it writes (LeafSource.of(..., consume=True))
    values = mapped_empty(dist.values.shape, np.float32)
    active = mapped_empty(dist.active.shape, bool)  # a copy: fill_deep adds the deep voxels to it
    _hfrep_values(dist.values, dist.active, result.inside, rows, frep.values, frep.active, table,
                  STEPS.index(step), float(slope), np.float32(-dist.background), values, active)
    return BlockGrid(dist.voxel_size, -float(dist.background), dist.origins, values, active)


@njit(cache=True, parallel=True)
def _hfrep_values(dist, active, inside, rows, f, fact, table, mode, slope, outside, out, out_active):
    """One pass of :func:`hfrep_blocks`: float32(step) * distance at solved voxels, ``outside``
    elsewhere; the step is +-1 from the solved side where frep has no value. ``mode``: the
    index in STEPS; sigmoid and rational computed here with step_function's operations (the same
    float64 values, rounded to float32 as its result was), tanh read from ``table``.
    ``out_active``: a copy of ``active``, made here on both cores (np.copyto took one)."""
    for b in prange(dist.shape[0]):
        r = rows[b]
        out_active[b] = active[b]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    if not active[b, i, j, k]:
                        out[b, i, j, k] = outside
                        continue
                    s = np.float32(1.0) if inside[b, i, j, k] else np.float32(-1.0)
                    if r >= 0 and fact[r, i, j, k]:
                        x = np.float64(f[r, i, j, k])
                        if mode == 0:
                            s = np.float32(2.0 * (1.0 / (1.0 + math.exp(-(2.0 * x / slope)))) - 2.0 / 2.0)
                        elif mode == 2:
                            s = np.float32(x / math.sqrt(slope * slope + x * x))
                        else:
                            s = table[r, i, j, k]
                    out[b, i, j, k] = s * dist[b, i, j, k]


class HFRepField:
    """Continuous HFRep function (eq. 21) for the model tree: ``evaluate(points) -> values``.

    ``frep``: callable FRep field, (N,3) world points -> (N,) values, f > 0 inside (the
    model node being converted). ``distance``: the spline of the unsigned distance. The
    field is C1 wherever ``frep`` is C1 (the spline is C2, the step and the regulariser are
    smooth). Outside the spline's support the distance falls back to ``distance.fill``.
    """

    def __init__(
        self,
        frep: Callable[[np.ndarray], np.ndarray],
        distance: TricubicSpline,
        step: str = "sigmoid",
        slope: float = 0.01,
        eps: float | None = None,
    ) -> None:
        if step not in STEPS:
            raise ValueError(f"step must be one of {STEPS}, not {step!r}")
        self.frep = frep
        self.distance = distance
        self.step = step
        self.slope = float(slope)
        self.eps = 0.05 * distance.voxel_size if eps is None else float(eps)

    @classmethod
    def from_result(
        cls, frep: Callable[[np.ndarray], np.ndarray], result: EikonalResult, step: str = "sigmoid",
        slope: float = 0.01,
    ) -> HFRepField:
        """Build the distance spline from an eikonal result and wrap it."""
        return cls(frep, TricubicSpline(result.distance), step, slope)

    def smoothed_distance(self, points: np.ndarray) -> np.ndarray:
        """F_smDF (eq. 20) regularised to stay positive: sqrt(spline^2 + eps^2)."""
        s = self.distance(points)
        return np.sqrt(s * s + self.eps * self.eps)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """F_HFRep at (N,3) world points (positive inside)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(self.frep(p), dtype=np.float64).reshape(-1)
        return hfrep_field(f, self.smoothed_distance(p), self.step, self.slope)

    __call__ = evaluate


def density_leaves(res, ramp: float, tiles: tuple[np.ndarray, np.ndarray] | None = None,
                   ) -> tuple[LeafSource, np.ndarray, np.ndarray]:
    """The ``density`` fog volume (pipeline.io.vdbgrids.fog_grid) as (leaves, tile origins, tile
    values): 1 inside deeper than ``ramp``, falling linearly to 0 at the surface. The inside
    voxels a limited fine solve left unsolved (``res.deep_rows``, deeper than the limit, which
    is at least the ramp) are 1. Blocks that are 1 throughout become active tiles (what
    ``prune`` would make of them), the others leaves, made a batch at a time as they are
    written (a first pass finds the blocks that are 1 throughout). ``tiles``: (origins, values)
    of more leaf tiles (the coarse interior), merged with those of 1 into one list in key
    order, so that solid regions of 1 become a few boxes (vdbgrids.fill_tiles). Blocks that are 0
    throughout (outside, or unsolved) are neither: the background (0, inactive) is their value
    (42 % of the mixed blocks of the demo at 512^3, each a leaf copy into OpenVDB)."""
    d = res.distance
    n = len(d.origins)
    deep = np.full(n, -1, np.int64)  # row of each block in deep_mask, -1 for none
    deep_mask = np.zeros((0, LEAF, LEAF, LEAF), bool) if res.deep_mask is None else res.deep_mask
    if res.deep_rows is not None and len(res.deep_rows):
        deep[res.deep_rows] = np.arange(len(res.deep_rows))
    ramp32 = np.float32(ramp)
    kind = _density_kind(d.values, d.active, res.inside, deep, deep_mask, ramp32)
    ones = kind == ALL_ONE
    leaves = np.flatnonzero(kind == MIXED)

    def fill(lo, hi, values, active):  # active where > 0
        _density(d.values, d.active, res.inside, deep, deep_mask, ramp32, leaves[lo:hi], values, active)

    origins, t_v, pos = d.origins[ones], np.zeros(0, np.float32), np.zeros(0, np.int64)
    if tiles is not None:  # both lists in key order: merged, not sorted (8.6M rows at 2048^3)
        t_o, t_v = np.asarray(tiles[0], np.int64).reshape(-1, 3), np.asarray(tiles[1], np.float32).reshape(-1)
        keys = pack_keys(t_o)
        if len(keys) > 1 and not (keys[1:] > keys[:-1]).all():  # interior_tiles gives them in order
            order = np.argsort(keys, kind="stable")
            t_o, t_v = t_o[order], t_v[order]
        origins, pos = merge_sorted(origins, t_o)
    values = np.ones(len(origins), np.float32)
    values[pos] = t_v
    return LeafSource(d.voxel_size, 0.0, d.origins[leaves], fill=fill), origins, values


@njit(cache=True, inline="always")
def _density_at(values, active, inside, deep, deep_mask, ramp, b, i, j, k):
    """The density of one voxel: 1 at a deep voxel (``deep[b]`` its row of ``deep_mask``),
    clip(d / ramp, 0, 1) (float32) at a solved inside voxel, 0 elsewhere."""
    r = deep[b]
    if r >= 0 and deep_mask[r, i, j, k]:
        return np.float32(1.0)
    if inside[b, i, j, k] and active[b, i, j, k]:
        x = values[b, i, j, k] / ramp
        return min(max(x, np.float32(0.0)), np.float32(1.0))
    return np.float32(0.0)


@njit(cache=True, parallel=True)
def _density(values, active, inside, deep, deep_mask, ramp, rows, out, out_a):
    """out[t] = the density of block rows[t] (:func:`_density_at`), out_a[t] = out[t] > 0."""
    for t in prange(rows.shape[0]):
        b = rows[t]
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    x = _density_at(values, active, inside, deep, deep_mask, ramp, b, i, j, k)
                    out[t, i, j, k] = x
                    out_a[t, i, j, k] = x > 0


ALL_ZERO, ALL_ONE, MIXED = 0, 1, 2  # :func:`_density_kind`


@njit(cache=True, parallel=True)
def _density_kind(values, active, inside, deep, deep_mask, ramp):
    """Per block: ALL_ZERO, ALL_ONE or MIXED by its voxels' densities (bit 0: a voxel above
    0, bit 1: a voxel below 1; both set is MIXED)."""
    out = np.empty(values.shape[0], np.int8)
    for b in prange(values.shape[0]):
        seen = 0
        for i in range(8):
            for j in range(8):
                for k in range(8):
                    x = _density_at(values, active, inside, deep, deep_mask, ramp, b, i, j, k)
                    if x > 0.0:
                        seen |= 1
                    if x < 1.0:
                        seen |= 2
        out[b] = ALL_ONE if seen == 1 else (ALL_ZERO if seen == 2 else MIXED)
    return out
