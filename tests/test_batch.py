"""Batch runs on real executors: a Dask LocalCluster with 2 worker processes and the local
process pool; bricks assembled into one grid; failures isolated; resume by job hash."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb
from pipeline.job.batch import DaskExecutor, Executor, LocalExecutor, run_batch
from pipeline.job.config import load_jobs

BATCH = """name: batch
domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 40}}
stages:
  - voxelise: {{band: 3}}
  - export: {{vdb: true, vtk: [vti]}}
jobs:
  - {{name: ball, model: {{sphere: {{radius: 0.6}}}}}}
  - {{name: ring, model: {{torus: {{major: 0.6, minor: 0.2}}}}}}
  - {{name: cube, model: {{box: {{min: [-0.5, -0.5, -0.5], max: [0.5, 0.5, 0.5]}}}}}}
  - {{name: pair, model: {{union: [{{sphere: {{center: [-0.5, 0, 0], radius: 0.3}}}}, {{sphere: {{center: [0.5, 0, 0], radius: 0.3}}}}]}}}}
  - {{name: cone, model: {{cone: {{radius: 0.5, height: 1.0}}}}}}
  - {{name: blob, model: {{blobby: {{blobs: [{{center: [0, 0, 0], radius: 0.5}}, {{center: [0.4, 0, 0], radius: 0.4}}]}}}}}}
{extra}"""

FAILING = "  - {name: empty, model: {sphere: {center: [5, 5, 5], radius: 0.5}}}  # nothing inside: .vti fails\n"


def frep_dense(path: Path) -> tuple[int, np.ndarray, tuple]:
    g = vdb.read(str(path), "frep")
    lo, hi = g.evalActiveVoxelBoundingBox()
    a = np.zeros(tuple(np.array(hi) - np.array(lo) + 3), np.float32)
    g.copyToArray(a, tuple(c - 1 for c in lo))
    return int(g.activeVoxelCount()), a, lo


@pytest.fixture(scope="module")
def cluster():
    ex = DaskExecutor(workers=2)
    yield ex
    ex.close()


def test_dask_batch_equals_local(tmp_path, cluster):
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(BATCH.format(extra=""))
    jobs = load_jobs(cfg)
    assert len(jobs) == 6
    assert cluster.workers == 2
    rows_d = run_batch(jobs, tmp_path / "dask", cluster)
    rows_i = run_batch(load_jobs(cfg), tmp_path / "inline", Executor())
    assert [r["status"] for r in rows_d] == ["ok"] * 6 == [r["status"] for r in rows_i]
    for job in jobs:
        nd, ad, lod = frep_dense(tmp_path / "dask" / job.name / f"{job.name}.vdb")
        ni, ai, loi = frep_dense(tmp_path / "inline" / job.name / f"{job.name}.vdb")
        assert nd == ni and lod == loi and np.array_equal(ad, ai)


def test_local_pool_batch_with_a_failure(tmp_path):
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(BATCH.format(extra=FAILING))
    ex = LocalExecutor(2)
    try:
        rows = run_batch(load_jobs(cfg), tmp_path / "out", ex)
    finally:
        ex.close()
    status = {r["name"]: r["status"] for r in rows}
    assert status.pop("empty") == "failed"
    assert set(status.values()) == {"ok"}
    failed = json.loads((tmp_path / "out" / "empty" / "manifest.failed.json").read_text())
    assert failed["status"] == "failed" and "no grid has active voxels" in failed["error"]
    assert failed["previous_outputs_kept"] is False
    assert sorted(p.name for p in (tmp_path / "out" / "empty").iterdir()) == ["manifest.failed.json"]
    assert (tmp_path / "out" / "ring" / "ring.vdb").exists()


def test_cli_exit_status_and_resume(tmp_path, capsys):
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(BATCH.format(extra=FAILING))
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out), "--executor", "dask", "--workers", "2"]) == 1
    text = capsys.readouterr()
    assert "job 'empty' failed" in text.err and "7 jobs: 6 ok or up to date, 1 failed" in text.out
    before = (out / "ball" / "ball.vdb").stat().st_mtime_ns
    assert main(["run", str(cfg), "--out", str(out)]) == 1  # the failing job is retried, others skipped
    assert "skipped" in capsys.readouterr().out
    assert (out / "ball" / "ball.vdb").stat().st_mtime_ns == before
    cfg.write_text(BATCH.format(extra="").replace("radius: 0.6", "radius: 0.55"))
    assert main(["run", str(cfg), "--out", str(out)]) == 0  # changed job reruns, the rest are skipped
    assert (out / "ball" / "ball.vdb").stat().st_mtime_ns != before
    before = (out / "ring" / "ring.vdb").stat().st_mtime_ns
    assert main(["run", str(cfg), "--out", str(out), "--force"]) == 0
    assert (out / "ring" / "ring.vdb").stat().st_mtime_ns != before


BRICKED = """name: {name}
domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 80}}
{bricks}
model:
  union:
    - difference:
        - torus: {{major: 0.55, minor: 0.22}}
        - sphere: {{center: [0.55, 0, 0], radius: 0.2}}
    - sphere: {{center: [0, 0, 0.6], radius: 0.2}}
stages:
  - voxelise: {{band: 3}}
  - components: {{}}
  - export: {{vdb: true}}
"""


def test_bricks_on_dask_match_the_unsplit_run(tmp_path, cluster):
    whole = tmp_path / "whole.yaml"
    whole.write_text(BRICKED.format(name="whole", bricks=""))
    split = tmp_path / "split.yaml"
    split.write_text(BRICKED.format(name="split", bricks="bricks: {size: 32}"))
    (rw,) = run_batch(load_jobs(whole), tmp_path, Executor())
    (rs,) = run_batch(load_jobs(split), tmp_path, cluster)
    assert rw["status"] == rs["status"] == "ok", (rw, rs)
    mw = json.loads((tmp_path / "whole" / "manifest.json").read_text())
    ms = json.loads((tmp_path / "split" / "manifest.json").read_text())
    assert ms["stages"][0]["stats"]["bricks"] > 8
    nw, aw, low = frep_dense(tmp_path / "whole" / "whole.vdb")
    ns, as_, los = frep_dense(tmp_path / "split" / "split.vdb")
    assert nw == ns and low == los
    np.testing.assert_allclose(as_, aw, atol=1e-6)
    # components: same count, same labels up to renumbering
    assert ms["components"]["count"] == mw["components"]["count"] == 2
    lw = vdb.read(str(tmp_path / "whole" / "whole.vdb"), "component")
    ls = vdb.read(str(tmp_path / "split" / "split.vdb"), "component")
    lo, hi = lw.evalActiveVoxelBoundingBox()
    shape = tuple(np.array(hi) - np.array(lo) + 1)
    A, B = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    lw.copyToArray(A, lo)
    ls.copyToArray(B, lo)
    pairs = {(a, b) for a, b in zip(A.ravel(), B.ravel(), strict=True) if a or b}
    assert len(pairs) == 2 and len({a for a, _ in pairs}) == 2 and len({b for _, b in pairs}) == 2


def test_frames_sweep_writes_a_pvd_series(tmp_path):
    cfg = tmp_path / "frames.yaml"
    cfg.write_text("""name: grow
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 32}
frames: {count: 3, t: [0, 1]}
model:
  morph:
    from: {sphere: {radius: 0.3}}
    to: {sphere: {radius: 0.7}}
stages:
  - voxelise: {band: 2}
  - export: {vdb: true, vtk: [vti]}
""")
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == ["grow_f0000", "grow_f0001", "grow_f0002", "grow_vti.pvd"]
    ts = [json.loads((tmp_path / "out" / n / "manifest.json").read_text())["frame"]["t"] for n in names[:3]]
    assert ts == [0.0, 0.5, 1.0]
    import vtk

    r = vtk.vtkPVDReader() if hasattr(vtk, "vtkPVDReader") else None
    text = (tmp_path / "out" / "grow_vti.pvd").read_text()
    assert text.count("<DataSet") == 3 and 'timestep="0.5"' in text
    del r
    # the radius grows with t: the frep value at r = 0.5 changes sign across the series
    vals = []
    for n in names[:3]:
        g = vdb.read(str(tmp_path / "out" / n / f"{n}.vdb"), "frep")
        vals.append(g.getConstAccessor().getValue((8, 0, 0)))  # x = 0.5
    assert vals[0] < 0 < vals[2]


def numba_threads(_: int) -> int:
    import numba

    return numba.get_num_threads()


def test_pool_workers_share_the_cores() -> None:
    """Each of N pool workers runs its parallel kernels on cores // N threads (no oversubscription)."""
    import os

    ex = LocalExecutor(2)
    try:
        assert ex.map(numba_threads, [0, 1, 2, 3]) == [max(1, (os.cpu_count() or 1) // 2)] * 4
    finally:
        ex.close()


def test_dask_local_workers_share_the_cores(cluster) -> None:
    """Measured inside the tasks: Numba's thread count belongs to the calling thread, and Dask
    runs tasks on executor threads, not the thread ``client.run`` uses (with the count set only
    there, each of two workers ran its kernels on every core)."""
    import os

    assert cluster.map(numba_threads, list(range(6))) == [max(1, (os.cpu_count() or 1) // 2)] * 6


def test_local_cluster_keeps_its_http_endpoints_on_this_host() -> None:
    """Our LocalCluster has no dashboard, and the scheduler's HTTP endpoints listen on a free
    port of 127.0.0.1: not on every interface at :8787, where a second cluster (another batch
    run, a parallel test worker) found the port taken and Distributed warned."""
    import socket
    import warnings

    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen()
    except OSError:
        pass  # taken already: the case this test is about
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", UserWarning)
            ex = DaskExecutor(workers=1)
        try:
            link = ex.client.dashboard_link
            assert link.startswith("http://127.0.0.1:") and ":8787/" not in link, link
        finally:
            ex.close()
    finally:
        holder.close()


def test_bricked_r0_mesh_matches_the_unsplit_run(tmp_path):
    """Bricks sample an r0 mesh's sign proxy (its min_max twin) in the workers and the parent
    evaluates the mesh itself in the band's reach: the written grid equals the unsplit run's."""
    import trimesh

    m = trimesh.creation.icosphere(3)
    v = m.vertices * (0.8 + 0.06 * np.sin(5 * m.vertices[:, :1]) * np.sin(7 * m.vertices[:, 1:2]))
    trimesh.Trimesh(v, m.faces, process=False).export(str(tmp_path / "bumpy.off"))
    text = ("name: {name}\ndomain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 64}}\n{bricks}\n"
            "model:\n  mesh: {{path: bumpy.off}}\nstages:\n  - voxelise: {{band: 3}}\n  - export: {{vdb: true}}\n")
    pool = LocalExecutor(workers=2)  # real worker processes: the proxy travels pickled
    try:
        for name, bricks, ex in (("whole", "", Executor()), ("split", "bricks: {size: 32}", pool)):
            (tmp_path / f"{name}.yaml").write_text(text.format(name=name, bricks=bricks))
            (r,) = run_batch(load_jobs(tmp_path / f"{name}.yaml"), tmp_path, ex)
            assert r["status"] == "ok", r
    finally:
        pool.close()
    stats = [json.loads((tmp_path / n / "manifest.json").read_text())["stages"][0]["stats"] for n in ("whole", "split")]
    assert stats[1]["bricks"] > 8 and all(s["sign_proxy"] for s in stats), stats
    nw, aw, low = frep_dense(tmp_path / "whole" / "whole.vdb")
    ns, as_, los = frep_dense(tmp_path / "split" / "split.vdb")
    assert nw == ns > 5000 and low == los
    np.testing.assert_array_equal(as_, aw)
