"""Batch runs: many jobs (configs, ``jobs:`` lists, ``frames:`` sweeps) on an executor.

Executors are real engines, not a home-made scheduler: ``local`` is a process pool
(:class:`concurrent.futures.ProcessPoolExecutor`), ``dask`` is Dask distributed, on an existing
scheduler (``--scheduler``) or a ``LocalCluster`` (``--workers``). A job travels to a worker as
a small reference (config path + job name); the worker loads and validates it itself, so model
trees never need to be pickled. One job's failure is reported in its manifest and the summary
and does not stop the others. A job whose outputs exist with the same job hash is skipped
unless ``force``.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numba

from pipeline.job.config import Job
from pipeline.job.outputs import prepare_out_root
from pipeline.job.refs import JobRef, load_ref, ref_of
from pipeline.job.runner import failure_status, run_job
from pipeline.util.errors import ConfigError, on_interrupt

# --- executors ----------------------------------------------------------------------------------


def cores_per_worker(workers: int) -> int:
    """Numba threads for each of ``workers`` processes on this machine: its cores divided
    among them, so a pool does not oversubscribe the cores."""
    return max(1, min(numba.config.NUMBA_NUM_THREADS, (os.cpu_count() or 1) // workers))


def share_cores(workers: int) -> None:
    """In a worker process: run the parallel kernels (the eikonal FIM's waves, ...) on
    :func:`cores_per_worker` threads. Numba's thread count belongs to the calling thread: call
    it on the thread that runs the tasks (a pool worker's main thread; Dask's executor threads
    get it per task, :func:`_with_threads`)."""
    numba.set_num_threads(cores_per_worker(workers))


def _with_threads(args: tuple[int, Callable, Any]) -> Any:
    """A Dask task: ``fn(item)`` on ``threads`` Numba threads (set on the task's own thread)."""
    threads, fn, item = args
    numba.set_num_threads(threads)
    return fn(item)


def _worker_init(workers: int) -> None:
    """Pool worker start-up: share the cores; SIGTERM unwinds the running job (its staging
    folder is removed and its lock released) instead of killing the process mid-write."""
    import signal

    share_cores(workers)
    signal.signal(signal.SIGTERM, on_interrupt)


class Executor:
    """``map`` keeps order (bricks), ``map_unordered`` yields results as they finish (jobs)."""

    workers: int = 1

    def map(self, fn: Callable, items: list) -> list:
        return [fn(x) for x in items]

    def map_unordered(self, fn: Callable, items: list) -> Iterator:
        for x in items:
            yield fn(x)

    def close(self, interrupted: bool = False) -> None:
        pass

    def describe(self) -> str:
        return "inline"


class LocalExecutor(Executor):
    """A process pool over this machine's cores (spawned workers: safe with threads and OpenVDB)."""

    def __init__(self, workers: int | None = None):
        self.workers = workers or os.cpu_count() or 1
        self.pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_worker_init, initargs=(self.workers,))

    def map(self, fn, items):
        return list(self.pool.map(fn, items))

    def map_unordered(self, fn, items):
        futures = [self.pool.submit(fn, x) for x in items]
        for f in as_completed(futures):
            yield f.result()

    def close(self, interrupted: bool = False):
        if interrupted:  # SIGTERM the workers: each removes its job's staging folder and lock
            for proc in list(getattr(self.pool, "_processes", {}).values()):
                proc.terminate()
        self.pool.shutdown(wait=True, cancel_futures=interrupted)

    def describe(self):
        return f"local process pool, {self.workers} workers"


#: seconds to wait for an existing Dask scheduler (``--scheduler``) to answer
SCHEDULER_TIMEOUT = 5.0


class DaskExecutor(Executor):
    """Dask distributed: an existing scheduler, or a LocalCluster of worker processes."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None):
        from dask.distributed import Client, LocalCluster

        self.cluster = None
        if scheduler:
            try:  # an address nobody answers is bad input: a few seconds, then one line and exit 2
                self.client = Client(scheduler, timeout=SCHEDULER_TIMEOUT)
            except (OSError, TimeoutError, ValueError, TypeError) as e:
                why = " ".join(str(e).split())[:160] or type(e).__name__
                raise ConfigError.one(f"--scheduler {scheduler}", None, (), f"cannot reach the Dask scheduler within "
                                      f"{SCHEDULER_TIMEOUT:g} s ({why})") from None
        else:
            # no dashboard; the scheduler's HTTP endpoints (health, metrics) on a free port of
            # this host only: with dashboard_address=None Distributed still serves them on every
            # interface at :8787, and warns when another cluster holds that port
            self.cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                                        processes=True, dashboard_address=None,
                                        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
            self.client = Client(self.cluster)
        self.workers = len(self.client.scheduler_info()["workers"])
        # our own workers share this machine's cores; a remote cluster's workers keep theirs
        self.threads = cores_per_worker(self.workers) if self.cluster is not None else None
        self.address = self.client.scheduler.address

    def _submit(self, fn, items):
        if self.threads is None:
            return self.client.map(fn, items, pure=False)
        return self.client.map(_with_threads, [(self.threads, fn, x) for x in items], pure=False)

    def map(self, fn, items):
        return self.client.gather(self._submit(fn, items))

    def map_unordered(self, fn, items):
        from dask.distributed import as_completed as dask_completed

        for f in dask_completed(self._submit(fn, items)):
            yield f.result()

    def close(self, interrupted: bool = False):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def describe(self):
        return f"dask {self.address}, {self.workers} workers"


def make_executor(kind: str = "local", workers: int | None = None, scheduler: str | None = None,
                  jobs: int = 1) -> Executor:
    """The executor for a run; a single unbricked job on 'local' runs inline (no pool to start)."""
    if kind == "dask":
        return DaskExecutor(scheduler, workers)
    if jobs <= 1 and (workers or 1) <= 1:
        return Executor()
    return LocalExecutor(workers)


# --- running one job ------------------------------------------------------------------------------


def up_to_date(job: Job, out: Path) -> bool:
    """Outputs of this exact job (same job hash) exist and the run succeeded."""
    m = out / job.name / "manifest.json"
    if not m.exists():
        return False
    try:
        data = json.loads(m.read_text())
    except (OSError, ValueError):
        return False
    return data.get("job_sha256") == job.job_sha256 and data.get("status", "ok") == "ok"


def execute(job: Job, out: Path, force: bool = False, executor: Executor | None = None,
            progress: Any = None) -> dict:
    """Run one job; never raises for a job's own failure: returns its summary row (the job's
    folder then holds its previous outputs, if any, and ``manifest.failed.json``)."""

    t0 = time.perf_counter()
    row = {"name": job.name, "config": job.config_path, "status": "ok", "seconds": 0.0, "message": ""}
    if not force and up_to_date(job, out):
        row.update(status="skipped", message="outputs up to date (same job hash); --force reruns")
        return row
    try:
        manifest = run_job(job, out, progress=progress, executor=executor)
        row["active_voxels"] = manifest["grids"].get("frep", {}).get("active_voxels")
        row["components"] = manifest.get("components", {}).get("count")
        row["outputs"] = len(manifest["outputs"])
        row["warnings"] = list(manifest.get("warnings", []))
    except Exception as e:  # the job failed; the batch goes on
        status, message = failure_status(e)
        row.update(status=status, message=message)
        if status == "failed":
            row["traceback"] = traceback.format_exc()
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def execute_ref(args: tuple[JobRef, str, bool]) -> dict:
    """Worker entry point: load the job by reference and run it (inline bricks)."""
    ref, out, force = args
    try:
        job = load_ref(ref)
    except ConfigError as e:
        return {"name": ref.name, "config": ref.config, "status": "input-error", "message": "\n".join(e.lines())}
    return execute(job, Path(out), force)


# --- a batch ----------------------------------------------------------------------------------------


def run_batch(jobs: list[Job], out: Path, executor: Executor, force: bool = False,
              on_done: Callable[[dict], None] | None = None, progress: Any = None) -> list[dict]:
    """Run every job; bricked jobs run here with their bricks on the executor, the others are
    spread over the executor's workers. Returns the summary rows in job order."""
    out = prepare_out_root(out)
    check_unique_names(jobs)
    rows: dict[str, dict] = {}
    parallel = [j for j in jobs if not j.bricks]
    here = [j for j in jobs if j.bricks]
    if isinstance(executor, Executor) and type(executor) is Executor:
        here, parallel = jobs, []  # inline: everything in this process, with stage progress
    for row in executor.map_unordered(execute_ref, [(ref_of(j), str(out), force) for j in parallel]):
        rows[row["name"]] = row
        if on_done:
            on_done(row)
    for job in here:
        row = execute(job, out, force, executor, progress)
        rows[job.name] = row
        if on_done:
            on_done(row)
    _write_frame_series(jobs, out, rows)
    return [rows[j.name] for j in jobs]


def check_unique_names(jobs: list[Job]) -> None:
    """Two jobs of one batch never write the same folder: a duplicate name is an input error
    naming both places (the same config given twice included)."""
    first: dict[str, Job] = {}
    problems = []
    for j in jobs:
        if j.name in first:
            o = first[j.name]
            if Path(o.config_path).resolve() == Path(j.config_path).resolve() and o.index == j.index:
                problems.append((j.config_path, None, (), "this config is given twice; each job runs once"))
                continue
            problems.append((j.config_path, j.name_line, (), f"job name {j.name!r} is also the name of a job in "
                             f"{o.config_path}{f':{o.name_line}' if o.name_line else ''} (outputs go to "
                             "<out>/<name>/; give each job its own name)"))
        else:
            first[j.name] = j
    if problems:
        raise ConfigError(problems)


def _write_frame_series(jobs: Iterable[Job], out: Path, rows: dict) -> None:
    """A .pvd per frame series, pointing at each frame's .vti/.vtp (for ParaView's time slider)."""
    series: dict[str, list[Job]] = {}
    for j in jobs:
        if j.frame:
            series.setdefault(j.frame["series"], []).append(j)
    if not series:
        return
    from pipeline.io.vtkio import write_pvd  # VTK takes ~1 s to import: only for frame series

    for name, frames in series.items():
        for kind in ("vti", "vtp"):
            done = [j for j in frames if rows.get(j.name, {}).get("status") in ("ok", "skipped")]
            entries = [(j.t, f"{j.name}/{j.name}.{kind}") for j in done if (out / j.name / f"{j.name}.{kind}").exists()]
            if entries:
                write_pvd(out / f"{name}_{kind}.pvd", entries)
