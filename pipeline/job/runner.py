"""Run a job: config -> model tree -> stages -> files, with a manifest and atomic outputs.

A job writes into a staging folder next to ``<out>/<name>/`` and swaps it in only when every
stage succeeded and every file was verified and flushed (pipeline.job.outputs), so a failed run
never leaves half-written outputs behind and never removes the previous ones.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from pathlib import Path

from pipeline.io.vdbgrids import grid_stats
from pipeline.job.config import Job, input_error_path, line_of, locate_nonfinite
from pipeline.job.context import JobContext
from pipeline.job.outputs import (
    JobBusy,
    JobLock,
    fsync_tree,
    job_dir,
    new_staging,
    os_error_line,
    prepare_out_root,
    swap_in,
    verify_outputs,
    write_failure,
)
from pipeline.util.atomic import write_json
from pipeline.util.errors import ConfigError, InputError, interrupted
from pipeline.voxel.voxelise import NonFiniteField
from stages import REGISTRY


def run_job(job: Job, out_root: str | Path, progress=None, executor=None) -> dict:
    """Run every stage of ``job`` into ``<out_root>/<name>/``; returns the manifest.

    Holds the job's lock throughout; outputs are staged, verified, flushed and swapped in only when
    everything succeeded. On any failure the previous outputs stay as they were,
    ``manifest.failed.json`` is written beside them, and the exception is re-raised (ConfigError
    for bad input, :class:`JobFailed` with one line for an OS write error)."""
    folder = job_dir(prepare_out_root(out_root), job.name)
    with JobLock(folder):
        staging = new_staging(folder)
        try:
            return _run_staged(job, staging, folder, progress, executor)
        except BaseException as e:
            shutil.rmtree(staging, ignore_errors=True)
            if interrupted() and not isinstance(e, KeyboardInterrupt):
                raise KeyboardInterrupt from e  # hit inside compiled code: reported as a SystemError
            if isinstance(e, Exception):
                _record_failure(job, folder, e, staging)
            if isinstance(e, OSError):
                raise JobFailed(os_error_line(e, staging, folder)) from e
            raise


class JobFailed(RuntimeError):
    """A job that could not finish, with the one line that says why (exit 1)."""


def _run_staged(job: Job, staging: Path, folder: Path, progress, executor) -> dict:
    ctx = JobContext(job, staging, progress=progress, executor=executor)
    records = [_run_stage(ctx, name, params) for name, params in job.stages]
    manifest = _manifest(ctx, records)
    write_json(staging / "manifest.json", manifest)
    for hook in ctx.after_manifest:
        hook(ctx, manifest)
    verify_outputs(staging, manifest["outputs"], ctx.grids, main_vdb=f"{job.name}.vdb")
    fsync_tree(staging)
    swap_in(staging, folder)
    return manifest


def failure_status(e: BaseException, staging: Path | None = None, folder: Path | None = None) -> tuple[str, str]:
    """(status, one-line message) of a job's failure, as the manifest and the summary say it."""
    if isinstance(e, ConfigError):
        return "input-error", "\n".join(e.lines())
    if isinstance(e, OSError):
        return "failed", os_error_line(e, staging, folder)
    if isinstance(e, (JobFailed, JobBusy)):
        return "failed", str(e)
    return "failed", f"{type(e).__name__}: {str(e)[:500]}"


def _record_failure(job: Job, folder: Path, e: Exception, staging: Path) -> None:
    status, message = failure_status(e, staging, folder)
    # the disk that refused the outputs may refuse this too; the summary still says why
    with contextlib.suppress(OSError):
        write_failure(folder, {
            "name": job.name, "config": job.config_path, "config_sha256": job.config_sha256,
            "job_sha256": job.job_sha256, "status": status, "error": message,
            "previous_outputs_kept": (folder / "manifest.json").exists(),
            "outputs": [], "grids": {}, "stages": [], "warnings": []})


def _run_stage(ctx: JobContext, name: str, params) -> dict:
    if ctx.progress:
        ctx.progress(f"{name}")
    t0 = time.perf_counter()
    stage = REGISTRY[name]
    try:
        stats = stage.run(ctx, params) or {}
    except NonFiniteField as e:
        err = locate_nonfinite(ctx.job, e.point)
        raise err or ConfigError.one(ctx.job.config_path, None, ("model",), str(e)) from None
    except InputError as e:
        path = input_error_path(ctx.job, params, e)
        raise ConfigError.one(ctx.job.config_path, line_of(ctx.job.raw, path), path, str(e)) from None
    for grid in stage.grids(params):  # the grids a stage adds go in the order it declares
        if grid in ctx.grids:
            ctx.grids[grid] = ctx.grids.pop(grid)
    return {"name": name, "seconds": round(time.perf_counter() - t0, 4),
            "params": params.model_dump(mode="json", by_alias=True), "stats": stats}


def _manifest(ctx: JobContext, records: list[dict]) -> dict:
    job = ctx.job
    m = {
        "name": job.name,
        "config": job.config_path,
        "config_sha256": job.config_sha256,
        "job_sha256": job.job_sha256,
        "status": "ok",
        "inputs": _inputs(job),
        "domain": job.domain.to_json(),
        "t": job.t,
        "outputs": ctx.outputs + [{"path": "manifest.json", "kind": "manifest"}],
        "grids": {name: grid_stats(g, job.domain.voxel_size) for name, g in ctx.grids.items()},
        "stages": records,
        "warnings": model_warnings(job) + ctx.warnings,
    }
    meshes = [n.describe() for n in job.model.walk() if hasattr(n, "describe")]
    if meshes:
        m["meshes"] = meshes
    if job.frame:
        m["frame"] = job.frame
    if job.memory_estimate:  # the per-stage peak estimate checked before the run (config._check_memory)
        m["memory_estimate_bytes"] = dict(job.memory_estimate)
    m.update(ctx.manifest)
    return m


def model_warnings(job: Job) -> list[str]:
    """Warnings raised while building the model (e.g. a mesh that is not closed)."""
    return [f"{n.where}: {w}" for n in job.model.walk() for w in getattr(n, "warnings", [])]


def _inputs(job: Job) -> list[dict]:
    """The config and every file the model reads, with SHA-256 hashes."""
    import hashlib

    out = [{"path": job.config_path, "kind": "config", "sha256": job.config_sha256}]
    for node in job.model.walk():
        path = getattr(node.params, "path", None)
        if isinstance(path, str) and Path(path).exists():
            out.append({"path": path, "kind": node.kind, "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest()})
    return out
