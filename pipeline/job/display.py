"""Progress display: on a terminal one bar for jobs and one for the running stage, with the
fraction done and a time estimate; silence in logs and CI (when stderr is not a terminal).

Stages report through ``ctx.progress(message)`` (pipeline/job/runner.py passes
:meth:`BatchProgress.stage`). A stage that knows its fraction calls :func:`pipeline.util.progress.tick` with ``done``
and ``total`` (files, bytes, blocks); the voxeliser's level messages (``level 64: 512 cells``,
pipeline/voxel/voxelise.py) are turned into a fraction by :class:`LevelEstimate`, which predicts the
cells of the levels still to come from the growth seen so far (the band's cells grow about 4x
per halving for a surface: the voxelise seed's adaptive descent).
"""

from __future__ import annotations

import math
import re
import sys
import time
from collections.abc import Callable
from typing import Any

from pipeline.voxel.voxelise import block_for
from stages import REGISTRY

_LEVEL = re.compile(r"^level (\d+): (\d+) cells$")


def format_eta(seconds: float) -> str:
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class LevelEstimate:
    """Fraction of a voxelise descent done, from the cells bounded per level.

    Levels run from the root size down to the block size, halving; the cost of a level is
    proportional to its cells. Cells still to come are extrapolated with the growth ratio per
    level: 4 (a surface's cells per halving) until a level has ``CALIBRATE`` cells, then the last
    observed ratio (within 2..8); the block evaluation at the end counts as one more level of
    the last size. Time per cell is measured from the first level on (compilation and set-up
    before it are not cells), so there is no estimate of the time left before the second level.
    The fraction shown never goes down."""

    CALIBRATE = 256

    def __init__(self, block: int = 4, clock: Callable[[], float] = time.monotonic):
        self.block = block
        self.clock = clock
        self.start = clock()
        self.levels: list[tuple[int, int, float]] = []  # (size, cells, time)
        self.shown = 0.0

    def update(self, size: int, cells: int) -> tuple[float, float]:
        """(fraction done, seconds left) after the level of ``size`` with ``cells`` cells."""
        now = self.clock()
        self.levels.append((size, cells, now))
        done = float(sum(c for _, c, _ in self.levels))
        ratio = 4.0
        if len(self.levels) >= 2 and cells >= self.CALIBRATE and self.levels[-2][1] > 0:
            ratio = min(max(cells / self.levels[-2][1], 2.0), 8.0)
        remaining_levels = max(int(round(math.log2(size / self.block))), 0) if size > self.block else 0
        last, rest = float(cells), 0.0
        for _ in range(remaining_levels):
            last *= ratio
            rest += last
        rest += last  # the evaluation of the blocks
        self.shown = max(self.shown, done / (done + rest))
        first_size, first_cells, first_t = self.levels[0]
        timed = done - first_cells  # cells bounded since the first level's message
        eta = rest * (now - first_t) / timed if timed > 0 and now > first_t else math.inf
        return self.shown, eta


class BatchProgress:
    """``job_done(row)`` advances the jobs bar; ``stage(message)`` updates the stage bar."""

    def __init__(self, jobs: list, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.jobs = jobs
        self.jobs_bar = self.stage_bar = None
        self.current = ""  # the running stage
        self.started = time.monotonic()
        self.levels: LevelEstimate | None = None
        self.block: int | None = None  # the jobs' voxelise block (_block), found once
        self.last = ""  # the last line shown on the stage bar (tests read it)

    def __enter__(self) -> BatchProgress:
        if self.enabled:
            from tqdm import tqdm

            self.jobs_bar = tqdm(total=len(self.jobs), desc="jobs", unit="job", file=self.stream, position=0)
            self.stage_bar = tqdm(total=0, desc="stage", bar_format="{desc}: {postfix}", file=self.stream,
                                  position=1, leave=False)
        return self

    def job_done(self, row: dict) -> None:
        if self.jobs_bar is not None:
            self.jobs_bar.set_postfix_str(f"{row['name']}: {row['status']}", refresh=False)
            self.jobs_bar.update(1)

    def stage(self, message: str, done: float | None = None, total: float | None = None) -> None:
        """A stage's news: its name when it starts (pipeline/job/runner.py), then messages, with
        ``done`` of ``total`` when the stage knows them."""
        if not self.enabled:
            return

        if message in REGISTRY:  # a stage starts
            self.current, self.started = message, time.monotonic()
            self.levels = LevelEstimate(self._block()) if message == "voxelise" else None
            self._show(message)
            return
        frac = eta = None
        m = _LEVEL.match(message)
        if done is not None and total:
            frac = min(max(done / total, 0.0), 1.0)
            elapsed = time.monotonic() - self.started
            eta = elapsed * (1 - frac) / frac if frac > 0 else math.inf
        elif m and self.levels is not None:
            frac, eta = self.levels.update(int(m.group(1)), int(m.group(2)))
        elif message.startswith("evaluated") and self.levels is not None:
            frac, eta = 1.0, 0.0
        prefix = f"{self.current} " if self.current else ""
        if frac is None:
            self._show(f"{prefix}{message}")
        else:
            self._show(f"{prefix}{100 * frac:3.0f}% (about {format_eta(eta)} left): {message}")

    stage.takes_fraction = True  # type: ignore[attr-defined]  # for tick()

    def _show(self, line: str) -> None:
        self.last = line
        if self.stage_bar is not None:
            self.stage_bar.set_postfix_str(line, refresh=True)

    def _block(self) -> int:
        """The voxelise block size of the jobs (4 when they differ or none says); once per batch
        (block_for walks each job's model tree)."""
        if self.block is None:
            blocks = {block_for(j.model, p.block, j.domain.voxel_size) for j in self.jobs
                      for n, p in getattr(j, "stages", []) if n == "voxelise"}
            self.block = blocks.pop() if len(blocks) == 1 else 4
        return self.block

    def __exit__(self, *exc: Any) -> None:
        for bar in (self.stage_bar, self.jobs_bar):
            if bar is not None:
                bar.close()
