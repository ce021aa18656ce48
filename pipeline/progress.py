"""Progress display: on a terminal one bar for jobs and one for the running stage; silence in
logs and CI (when stderr is not a terminal)."""

from __future__ import annotations

import sys


class BatchProgress:
    """``job_done(row)`` advances the jobs bar; ``stage(message)`` updates the stage bar."""

    def __init__(self, jobs: list, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.jobs = jobs
        self.jobs_bar = self.stage_bar = None

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

    def stage(self, message: str) -> None:
        if self.stage_bar is not None:
            self.stage_bar.set_postfix_str(message, refresh=True)

    def __exit__(self, *exc) -> None:
        for bar in (self.stage_bar, self.jobs_bar):
            if bar is not None:
                bar.close()
