"""How any stage or kernel reports progress: a callable that takes a message, and for the
terminal display (pipeline/job/display.py) also the fraction done."""

from __future__ import annotations

from collections.abc import Callable


def tick(progress: Callable[..., None] | None, message: str, done: float | None = None,
         total: float | None = None) -> None:
    """Report to a progress callable; the fraction goes only to callables that take it
    (:meth:`BatchProgress.stage`), plain ``callable(str)`` ones get the message."""
    if progress is None:
        return
    if done is not None and total and getattr(progress, "takes_fraction", False):
        progress(message, done, total)
    else:
        progress(message)
