"""Progress display: a bar on a terminal, silence in logs and CI."""

from __future__ import annotations

import sys


class StageProgress:
    """Context manager and callable: ``progress("message")`` advances on stage names."""

    def __init__(self, name: str, total: int, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.name, self.total, self.bar = name, total, None

    def __enter__(self) -> StageProgress:
        if self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, desc=self.name, file=self.stream, leave=False, unit="stage")
        return self

    def __call__(self, message: str) -> None:
        if self.bar is not None:
            from stages import REGISTRY

            if message in REGISTRY and (self.bar.n or self.bar.postfix):
                self.bar.update(1)
            self.bar.set_postfix_str(message, refresh=True)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
