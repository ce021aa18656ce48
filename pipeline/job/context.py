"""What a running job carries from stage to stage."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pipeline.job.config import Job
from pipeline.job.refs import call_with, ref_of
from pipeline.util.errors import RunError

T = TypeVar("T")


@dataclass
class JobContext:
    job: Job
    out_dir: Path  # <out>/<name>/
    grids: dict[str, Any] = field(default_factory=dict)  # name -> OpenVDB grid, in write order
    results: dict[type, Any] = field(default_factory=dict)  # typed stage results (stages.base), by type
    outputs: list[dict] = field(default_factory=list)  # {"path", "kind"} relative to out_dir
    warnings: list[str] = field(default_factory=list)
    manifest: dict[str, Any] = field(default_factory=dict)  # extra manifest sections
    progress: Any = None  # callable(str) or None
    after_manifest: list = field(default_factory=list)  # callables(ctx, manifest) run once it exists
    executor: Any = None  # pipeline.job.batch.Executor for bricks (None: run bricks inline)

    def map(self, fn, items: list) -> list:
        """Map over the executor's workers (in order), or inline when there is none."""
        return self.executor.map(fn, items) if self.executor is not None else [fn(x) for x in items]

    def map_with(self, fn: Callable[[Any, Any], Any], items: list, part: str | None = None) -> list:
        """``[fn(job, item) for item in items]`` on the executor's workers, in order (inline when
        there is none); with ``part``, ``fn(job.<part>, item)``. A worker loads the job from its
        reference (pipeline.job.refs), so ``fn`` must be a module-level function."""
        if self.executor is None:
            arg = self.job if part is None else getattr(self.job, part)
            return [fn(arg, x) for x in items]
        ref = ref_of(self.job)
        return self.executor.map(call_with, [(fn, ref, part, x) for x in items])

    def put(self, result: Any) -> None:
        """Hand a typed result (e.g. stages.base.FrepBand) to the stages after this one."""
        self.results[type(result)] = result

    def get(self, kind: type[T]) -> T:
        """The result of type ``kind`` an earlier stage put (the loader checks ``REQUIRES``)."""
        try:
            return self.results[kind]
        except KeyError:
            raise RunError(f"no {kind.__name__}: the stage that makes it has not run") from None

    @property
    def voxel_size(self) -> float:
        return self.job.domain.voxel_size

    def add_output(self, path: Path, kind: str, **extra: Any) -> None:
        self.outputs.append({"path": str(Path(path).relative_to(self.out_dir)), "kind": kind, **extra})

    def grid_metadata(self, stage: str, params: Any) -> dict:
        """Metadata every grid carries: config name and hash, the stage and its parameters."""
        return {
            "frepvdb_config": self.job.name,
            "frepvdb_config_sha256": self.job.config_sha256,
            "frepvdb_stage": stage,
            "frepvdb_params": params.model_dump_json(by_alias=True),
            "frepvdb_t": float(self.job.t),
        }
