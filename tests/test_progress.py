"""Progress (pipeline/job/display.py, pipeline/util/progress.py): fractions and time estimates on a terminal, silence off one."""

from __future__ import annotations

import io

import pytest

from pipeline.job.batch import Executor, run_batch
from pipeline.job.config import load_jobs
from pipeline.job.display import BatchProgress, LevelEstimate, format_eta
from pipeline.util.progress import tick


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_level_estimate_rises_to_one_and_predicts_the_rest() -> None:
    clock = Clock()
    est = LevelEstimate(block=4, clock=clock)
    clock.t = 5.0  # compilation before the first level is not counted as cells
    f, eta = est.update(64, 8)
    assert eta == float("inf") and 0 < f < 0.01
    fracs = [f]
    for size, cells in [(32, 8), (16, 64), (8, 1024), (4, 2048)]:  # uneven growth
        clock.t += cells * 1e-3  # 1 ms per cell
        f, eta = est.update(size, cells)
        fracs.append(f)
    assert fracs == sorted(fracs) and fracs[-1] < 1  # never down; the blocks are still to evaluate
    assert eta == pytest.approx(2.048)  # 2048 blocks at 1 ms, the measured rate
    # exact 4x growth from 16 on: after the 16-level, 512 + 2048 cells and 2048 blocks remain
    clock.t = 0.0
    est2 = LevelEstimate(block=4, clock=clock)
    for size, cells in [(64, 2), (32, 32), (16, 128)]:
        clock.t += cells * 1e-3
        f, eta = est2.update(size, cells)
    assert f == pytest.approx(162 / (162 + 512 + 2048 + 2048))
    assert eta == pytest.approx(4.608)


class TTY(io.StringIO):
    def isatty(self) -> bool:
        return True


CFG = """name: job
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 48}
model: {torus: {major: 0.6, minor: 0.2}}
stages:
  - voxelise: {band: 2}
  - export: {vdb: true, mesh: [stl, ply], report: false}
"""


def run_with(stream, tmp_path) -> tuple[BatchProgress, list[str]]:
    cfg = tmp_path / "job.yaml"
    cfg.write_text(CFG)
    jobs = load_jobs(cfg)
    shown: list[str] = []
    with BatchProgress(jobs, stream=stream) as bp:
        show = bp._show
        bp._show = lambda line: (shown.append(line), show(line))
        rows = run_batch(jobs, tmp_path / "out", Executor(), force=True, on_done=bp.job_done, progress=bp.stage)
    assert rows[0]["status"] == "ok"
    return bp, shown


def test_a_terminal_shows_fractions_and_time_left(tmp_path) -> None:
    stream = TTY()
    _, shown = run_with(stream, tmp_path)
    vox = [s for s in shown if s.startswith("voxelise ") and "%" in s]
    assert vox and "left" in vox[0]
    pcts = [float(s.split("%")[0].split()[-1]) for s in vox]
    assert pcts == sorted(pcts) and pcts[-1] == 100  # the evaluated blocks end the stage
    assert any(s.startswith("export  50%") and "job_mesh.stl" in s for s in shown)
    assert any(s.startswith("export 100%") and "job_mesh.ply" in s for s in shown)
    assert "left" in stream.getvalue()  # tqdm drew them


def test_quiet_off_a_terminal(tmp_path) -> None:
    stream = io.StringIO()
    bp, shown = run_with(stream, tmp_path)
    assert not bp.enabled and stream.getvalue() == "" and shown == []


def test_tick_sends_fractions_only_to_callables_that_take_them() -> None:
    got: list = []
    tick(got.append, "wrote a.stl", 1, 2)
    assert got == ["wrote a.stl"]
    bp = BatchProgress([], stream=TTY())
    bp.enabled, bp.current = True, "export"
    tick(bp.stage, "wrote a.stl", 1, 4)
    assert bp.last.startswith("export  25%")
    assert format_eta(75) == "1:15" and format_eta(3725) == "1:02:05" and format_eta(float("inf")) == "?"
