"""The block FIM continued across bricks: domain decomposition with ghost-layer exchange.

A job with ``bricks:`` has its solve split by brick (bricks of ``brick`` voxels aligned to the
8^3 leaves, as the voxeliser splits it). Each round, every brick with work is sent to a worker
with its own blocks and, read-only, the face-neighbour blocks of other bricks at their current
values (the ghost layers the upwind stencils read, two voxels deep for the second-order
scheme); the worker runs the block FIM (:func:`pipeline.distance.fim.fim`) on its own blocks to
convergence and returns them. The driver writes them back, and each own block that changed
and touches another brick puts that brick's touching block on the next round's seed list.
Rounds end when no brick has seeds: then every block is a fixed point of the local update
with the final values of all its neighbours, i.e. a fixed point of the global scheme, the
same one the unsplit FIM converges to (Jeong & Whitaker 2008 make the same argument for
their GPU blocks). The first-order pass converges from above, monotonically; the
second-order pass starts from its result, as in the unsplit solve.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.distance.fim import FROZEN, block_colour, fim
from pipeline.sparse.access import FACE_ROWS27


def brick_of_blocks(origins: np.ndarray, brick: int) -> np.ndarray:
    """Brick number (0..B-1) of every block: blocks whose origins share ``origins // brick``."""
    key = np.floor_divide(origins, brick)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    return inverse.reshape(-1)


def relax_brick(task: tuple) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Worker side of one brick: the block FIM on its own blocks, ghost blocks read-only.

    ``task`` = (d, state, inside, nbr27, colour, n_own, seeds, limit, tol, max_sweeps, order2,
    max_visits, limit_in) over the local blocks (own first, then ghosts). Returns (own distances,
    own blocks that changed, (visits, updates, sweeps, converged)).
    """
    d, state, inside, nbr27, colour, n_own, seeds, limit, tol, max_sweeps, order2, max_visits, limit_in = task
    before = d[:n_own].copy()
    counters = fim(d, state, inside, nbr27, colour, seeds, limit, tol, max_sweeps, order2, max_visits, limit_in)
    own = d[:n_own]
    changed = np.nonzero(((own != before) & ~(np.isinf(own) & np.isinf(before))).reshape(n_own, -1).any(axis=1))[0]
    return own, changed, counters


class BrickedFIM:
    """Rounds of per-brick FIM runs over a map function (an executor's ``map`` or inline)."""

    def __init__(self, d, state, inside, nbr27, brick: int, origins: np.ndarray,
                 map_fn: Callable[[Callable, list], list] | None = None) -> None:
        self.d, self.state, self.inside, self.nbr27 = d, state, inside, nbr27
        self.map = map_fn or (lambda fn, items: [fn(x) for x in items])
        self.brick_of = brick_of_blocks(origins, brick)
        self.colour = block_colour(origins)
        self.n_bricks = int(self.brick_of.max()) + 1 if len(origins) else 0
        self.own = [np.nonzero(self.brick_of == b)[0] for b in range(self.n_bricks)]
        face_nbr = nbr27[:, FACE_ROWS27]
        self.ghosts = []
        for blocks in self.own:
            n = face_nbr[blocks].reshape(-1)
            n = np.unique(n[n >= 0])
            self.ghosts.append(n[self.brick_of[n] != self.brick_of[blocks[0]]] if len(blocks) else n)

    def solve(self, seeds: np.ndarray, limit: float, tol: float, max_sweeps: int, order2: bool,
              visits_per_block: int, limit_in: float = np.inf) -> dict:
        """Run rounds from the global ``seeds`` until no brick has work, or until the block
        visits of all rounds pass ``visits_per_block`` per block (then ``converged`` is
        False: the bound of a non-monotone pass). Counters for the manifest."""
        pending = [set() for _ in range(self.n_bricks)]
        for s in seeds:
            pending[self.brick_of[s]].add(int(s))
        totals = {"rounds": 0, "brick_runs": 0, "block_visits": 0, "voxel_updates": 0, "sweeps": 0}
        budget = visits_per_block * max(len(self.d), 1)
        converged = True
        while any(pending) and converged and totals["block_visits"] < budget:
            work = [b for b in range(self.n_bricks) if pending[b]]
            tasks = [self._task(b, pending[b], limit, tol, max_sweeps, order2, visits_per_block, limit_in)
                     for b in work]
            pending = [set() for _ in range(self.n_bricks)]
            for b, (own_d, changed, (visits, updates, sweeps, ok)) in zip(work, self.map(relax_brick, tasks),
                                                                          strict=True):
                self.d[self.own[b]] = own_d
                self._schedule(self.own[b][changed], pending)
                totals["block_visits"] += int(visits)
                totals["voxel_updates"] += int(updates)
                totals["sweeps"] += int(sweeps)
                converged &= bool(ok)
            totals["rounds"] += 1
            totals["brick_runs"] += len(work)
        totals["converged"] = converged and not any(pending)
        return totals

    def pass_runner(self, limit: float, tol: float, max_sweeps: int, limit_in: float = np.inf):
        """``run_pass(seeds, order2, visits_per_block)`` for :func:`pipeline.distance.eikonal.run_passes`."""
        def run(seeds, order2, visits_per_block):
            return self.solve(seeds, limit, tol, max_sweeps, order2, visits_per_block, limit_in)
        return run

    def _task(self, b: int, seeds: set, limit, tol, max_sweeps, order2, visits_per_block, limit_in) -> tuple:
        own, ghost = self.own[b], self.ghosts[b]
        rows = np.concatenate([own, ghost])
        nbr = _local_index(rows, self.nbr27[rows])
        state = self.state[rows].copy()
        state[len(own):] = FROZEN  # ghosts are read-only boundary values
        local_seeds = _local_index(rows, np.fromiter(seeds, np.int64, len(seeds)))
        return (self.d[rows].copy(), state, self.inside[rows], nbr, self.colour[rows], len(own), np.sort(local_seeds),
                limit, tol, max_sweeps, order2, visits_per_block * len(own), limit_in)

    def _schedule(self, changed: np.ndarray, pending: list[set]) -> None:
        """Blocks of other bricks that touch a changed block go on their brick's seed list."""
        if len(changed) == 0:
            return
        n = self.nbr27[changed][:, FACE_ROWS27].reshape(-1)
        src = np.repeat(changed, len(FACE_ROWS27))
        ok = (n >= 0)
        n, src = n[ok], src[ok]
        other = self.brick_of[n] != self.brick_of[src]
        for blk in np.unique(n[other]):
            pending[self.brick_of[blk]].add(int(blk))


def _local_index(rows: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Position in ``rows`` of each global block number (-1 where absent or negative); cost
    follows the brick's size, not the whole grid's."""
    order = np.argsort(rows)
    pos = np.minimum(np.searchsorted(rows[order], blocks), len(rows) - 1)
    return np.where((blocks >= 0) & (rows[order][pos] == blocks), order[pos], -1)
