"""Jobs by reference: a worker (a process of the pool, a Dask worker) gets a small reference
(config path + job name) and loads and validates the job itself, so model trees are never
pickled. Stages send work to the workers through :meth:`pipeline.job.context.JobContext.map_with`,
which pairs each item with the job's reference here; the stage's function receives the loaded job
(or its model) and never imports this layer."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.job.config import Job, load_jobs
from pipeline.util.errors import ConfigError


@dataclass(frozen=True)
class JobRef:
    """What a worker needs to find a job again."""

    config: str
    name: str


def ref_of(job: Job) -> JobRef:
    return JobRef(str(Path(job.config_path).resolve()), job.name)


def load_ref(ref: JobRef) -> Job:
    """The job a reference names, loaded once per process and config version (bricks of one
    job reuse it instead of re-validating the config for every brick)."""
    return _load_ref(ref.config, ref.name, Path(ref.config).stat().st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _load_ref(config: str, name: str, mtime_ns: int) -> Job:
    jobs = load_jobs(config, select=name)
    if not jobs:
        raise ConfigError.one(config, None, (), f"no job named {name!r} in this config")
    return jobs[0]


def call_with(args: tuple[Callable[[Any, Any], Any], JobRef, str | None, Any]) -> Any:
    """Worker side of ``JobContext.map_with``: ``fn(job, item)``, or ``fn(job.<part>, item)``."""
    fn, ref, part, item = args
    job = load_ref(ref)
    return fn(job if part is None else getattr(job, part), item)
