"""Run a job: config -> model tree -> stages -> files, with a manifest and atomic outputs.

A job writes into a staging folder next to ``<out>/<name>/`` and swaps it in only when every
stage succeeded, so a failed run never leaves half-written outputs behind.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from pipeline.atomic import write_json
from pipeline.config import Job, locate_nonfinite
from pipeline.context import JobContext
from pipeline.errors import ConfigError, InputError
from pipeline.grid import grid_stats
from pipeline.voxelise import NonFiniteField


def run_job(job: Job, out_root: str | Path, progress=None, executor=None) -> dict:
    """Run every stage of ``job``; returns the manifest. Raises ConfigError for bad input."""
    out_root = Path(out_root)
    final = out_root / job.name
    staging = out_root / f".{job.name}.partial"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    ctx = JobContext(job, staging, progress=progress, executor=executor)
    try:
        records = [_run_stage(ctx, name, params) for name, params in job.stages]
        manifest = _manifest(ctx, records)
        write_json(staging / "manifest.json", manifest)
        for hook in ctx.after_manifest:
            hook(ctx, manifest)
        _swap_in(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return manifest


def _run_stage(ctx: JobContext, name: str, params) -> dict:
    from stages import REGISTRY

    if ctx.progress:
        ctx.progress(f"{name}")
    t0 = time.perf_counter()
    try:
        stats = REGISTRY[name].run(ctx, params) or {}
    except NonFiniteField as e:
        err = locate_nonfinite(ctx.job, e.point)
        raise err or ConfigError.one(ctx.job.config_path, None, ("model",), str(e)) from None
    except InputError as e:
        idx = [n for n, _ in ctx.job.stages].index(name)
        raise ConfigError.one(ctx.job.config_path, None, ("stages", idx, name), str(e)) from None
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
        "warnings": _model_warnings(job) + ctx.warnings,
    }
    meshes = [n.describe() for n in job.model.walk() if hasattr(n, "describe")]
    if meshes:
        m["meshes"] = meshes
    if job.frame:
        m["frame"] = job.frame
    m.update(ctx.manifest)
    return m


def _model_warnings(job: Job) -> list[str]:
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


def _swap_in(staging: Path, final: Path) -> None:
    old = final.with_name(f".{final.name}.old")
    if old.exists():
        shutil.rmtree(old)
    if final.exists():
        final.rename(old)
    staging.rename(final)
    if old.exists():
        shutil.rmtree(old)
