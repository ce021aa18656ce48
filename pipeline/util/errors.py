"""Errors the CLI turns into exit codes: ConfigError -> 2 (bad config or input), others -> 1."""

from __future__ import annotations

import threading

_INTERRUPT = threading.Event()


def on_interrupt(signum, frame) -> None:
    """Signal handler for SIGINT/SIGTERM: remember the request, then unwind as Ctrl-C does.
    A compiled (Numba) call that the KeyboardInterrupt hits reports it as a SystemError; the
    flag lets the runner tell that from a real failure."""
    _INTERRUPT.set()
    raise KeyboardInterrupt


def interrupted() -> bool:
    return _INTERRUPT.is_set()


def format_path(path: tuple) -> str:
    """('model', 'union', 1, 'sphere', 'radius') -> 'model.union[1].sphere.radius'."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


class ConfigError(Exception):
    """One or more problems in a config or an input it names, each with file, line, YAML path."""

    def __init__(self, problems: list[tuple[str, int | None, tuple, str]]):
        self.problems = problems
        super().__init__("\n".join(self.lines()))

    @classmethod
    def one(cls, file: str, line: int | None, path: tuple, message: str) -> ConfigError:
        return cls([(file, line, path, message)])

    def lines(self) -> list[str]:
        out = []
        for file, line, path, message in self.problems:
            where = f"{file}:{line}" if line else file
            p = format_path(path)
            out.append(f"{where} {p}: {message}" if p else f"{where}: {message}")
        return out


class InputError(ValueError):
    """A problem with an input named by the config (a mesh, a .vdb, a formula) found while building
    the model or running a stage. ``path`` is the YAML path relative to where it was found: the
    model node ``node`` (its ``where``, e.g. ``model.union[1].hfrep``) when given, else the node
    being built or the stage's parameters; the job layer prefixes that path, finds the line
    (pipeline.job.config.line_of) and re-raises a ConfigError."""

    def __init__(self, message: str, path: tuple = (), node: str | None = None):
        super().__init__(message)
        self.path = tuple(path)
        self.node = node


class RunError(RuntimeError):
    """A failure while running a stage (exit 1)."""
