"""A run never destroys anything (issue 11): job names that escape --out, failed reruns, full
disks, duplicate and concurrent jobs, interrupted runs, bad --out.

Every case puts sentinel files beside, above and inside ``--out`` and checks that they are still
there with their content afterwards; previous good outputs are read back with pyopenvdb.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb
from pipeline.job.outputs import JobLock, job_name_problem, recover, staging_dir, verify_outputs

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable

BALL = """{name}domain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: {res}}}
model: {{sphere: {{center: {center}, radius: 0.6}}}}
stages:
  - voxelise: {{band: 3}}
{more}  - export: {{vdb: true{vtk}}}
"""


def ball(name: str | None = "ball", res: int = 24, center: str = "[0, 0, 0]", vtk: str = "", more: str = "") -> str:
    head = "" if name is None else f"name: {json.dumps(name, ensure_ascii=False)}\n"  # YAML rejects \\ud83c-style surrogate pairs
    return BALL.format(name=head, res=res, center=center, vtk=vtk, more=more)


FAR = "[5, 5, 5]"  # nothing of the sphere in the domain: a .vti export fails ("no grid has active voxels")


def snapshot(*folders: Path) -> dict[str, str]:
    """Every file under the folders (recursively) with the SHA-256 of its content."""
    out = {}
    for folder in folders:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture()
def project(tmp_path: Path, monkeypatch) -> Path:
    """A user's project folder with files beside, above and inside the default --out."""
    proj = tmp_path / "project"
    (proj / "src").mkdir(parents=True)
    (proj / "notes.txt").write_text("my notes\n")
    (proj / "src" / "a.py").write_text("print('hi')\n")
    (tmp_path / "above.txt").write_text("above\n")
    (proj / "outputs" / "other").mkdir(parents=True)
    (proj / "outputs" / "other" / "result.txt").write_text("another job's result\n")
    monkeypatch.chdir(proj)
    return proj


def run_cli(*args: str) -> tuple[int, str]:
    """The CLI in a subprocess (as a user runs it): exit code and stderr."""
    r = subprocess.run([PY, "-m", "pipeline.cli", *args], capture_output=True, text=True, timeout=300)
    return r.returncode, r.stderr


def assert_one_line(err: str) -> None:
    assert "Traceback" not in err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1, err


# --- names that would escape --out ---------------------------------------------------------------


@pytest.mark.parametrize("name", ["..", ".", "...", "../x", "a/b", "/abs", ".hidden", "a\x00b", "tab\there",
                                  " lead", "x" * 300, "é" * 101])
def test_bad_job_names_are_refused_and_nothing_moves(project, capsys, name) -> None:
    before = snapshot(project.parent)
    cfg = project / "job.yaml"
    cfg.write_text(ball(name))
    before = snapshot(project.parent)
    assert main(["run", "job.yaml"]) == 2
    err = capsys.readouterr().err
    assert_one_line(err)
    assert "job.yaml:1 name:" in err
    assert snapshot(project.parent) == before


@pytest.mark.parametrize("stem", ["..", ".", ".hidden"])
def test_a_bad_name_taken_from_the_file_stem_names_the_file(project, capsys, stem) -> None:
    cfg = project / f"{stem}.yaml"
    cfg.write_text(ball(None))
    before = snapshot(project.parent)
    assert main(["run", cfg.name]) == 2
    err = capsys.readouterr().err
    assert_one_line(err)
    assert f"{stem}.yaml" in err and "add a `name:` key" in err
    assert snapshot(project.parent) == before


def test_dotdot_in_a_subprocess_leaves_the_project_as_it_was(project) -> None:
    """The reported case, as the user ran it: a real process, default --out."""
    (project / "name_dotdot.yaml").write_text(ball(".."))
    before = snapshot(project.parent)
    code, err = run_cli("run", "name_dotdot.yaml")
    assert code == 2
    assert_one_line(err)
    assert snapshot(project.parent) == before


_NAMES = st.one_of(
    st.text(min_size=0, max_size=40),
    st.text(alphabet=st.sampled_from("./\\-_ a\u00e9\u4e2d\x00\n"), max_size=12),
    st.from_regex(r"[A-Za-z0-9_.-]{1,12}", fullmatch=True),
    st.integers(190, 260).map(lambda n: "n" * n),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=_NAMES)
def test_no_job_name_ever_writes_outside_out(tmp_path_factory, name) -> None:
    base = tmp_path_factory.mktemp("names")
    (base / "beside.txt").write_text("beside\n")
    out = base / "out"
    out.mkdir()
    (out / "keep.txt").write_text("inside\n")
    cfg = base / "cfg.yaml"
    cfg.write_text(ball(name, res=8))
    sentinels = snapshot(base)
    code = main(["run", str(cfg), "--out", str(out)])
    after = snapshot(base)
    assert code in (0, 2)
    # every file there before is unchanged; every new file lies inside <out>/<name>/
    assert all(after.get(p) == h for p, h in sentinels.items())
    new = set(after) - set(sentinels)
    name = name or "cfg"  # an empty name: the job is named after the config file
    if job_name_problem(name):
        assert code == 2 and not new
    else:
        assert code == 0
        assert all(Path(p).resolve().parent.parent == (out / name).resolve().parent or
                   (out / name).resolve() in Path(p).resolve().parents for p in new)
        assert {Path(p).name for p in new} >= {f"{name}.vdb", "manifest.json"}
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


# --- failed reruns, full disks -------------------------------------------------------------------


def test_a_failed_rerun_keeps_the_previous_outputs(project, capsys) -> None:
    cfg = project / "job.yaml"
    cfg.write_text(ball("ball"))
    assert main(["run", "job.yaml"]) == 0
    folder = project / "outputs" / "ball"
    good = snapshot(folder)
    others = snapshot(project / "outputs" / "other", project / "src")
    cfg.write_text(ball("ball", center=FAR, vtk=", vtk: [vti]"))  # nothing to write: .vti fails
    assert main(["run", "job.yaml"]) == 1
    err = capsys.readouterr().err
    assert "job 'ball' failed" in err and "Traceback" not in err
    after = snapshot(folder)
    failed = after.pop(str(folder / "manifest.failed.json"))
    assert failed and after == good
    assert vdb.read(str(folder / "ball.vdb"), "frep").activeVoxelCount() > 0
    m = json.loads((folder / "manifest.failed.json").read_text())
    assert m["status"] == "failed" and m["previous_outputs_kept"] is True
    assert json.loads((folder / "manifest.json").read_text())["status"] == "ok"
    assert snapshot(project / "outputs" / "other", project / "src") == others
    # a later success replaces the folder: the failure manifest goes with the old outputs
    cfg.write_text(ball("ball", res=20))
    assert main(["run", "job.yaml"]) == 0
    assert not (folder / "manifest.failed.json").exists()


def _limited_run(cfg: Path, out: Path, limit_bytes: int) -> subprocess.CompletedProcess:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run([PY, "-m", "pipeline.cli", "run", str(cfg), "--out", str(out), "--force"],
                          capture_output=True, text=True, preexec_fn=limit, timeout=300)


@pytest.mark.parametrize("vtk", ["", ", vtk: [vti, vtp], previews: true"])
def test_a_full_disk_fails_and_keeps_the_old_outputs(tmp_path, vtk) -> None:
    """RLIMIT_FSIZE: OpenVDB's writer truncates silently, Python's raise EFBIG. Either way the
    run must end non-zero, with the previous outputs intact and no truncated file in place."""
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("ball", res=24, vtk=vtk))
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out)]) == 0
    folder = out / "ball"
    good = snapshot(folder)
    cfg.write_text(ball("ball", res=64, vtk=vtk))  # a bigger grid: its .vdb exceeds the limit
    r = _limited_run(cfg, out, 60_000)
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr and "cannot write" in r.stderr and str(folder) in r.stderr
    after = snapshot(folder)
    after.pop(str(folder / "manifest.failed.json"), None)
    assert after == good
    grid = vdb.read(str(folder / "ball.vdb"), "frep")
    assert grid.activeVoxelCount() > 0
    manifest = json.loads((folder / "manifest.json").read_text())
    verify_outputs(folder, manifest["outputs"])  # every listed file is complete
    assert sorted(p.name for p in out.iterdir()) == ["ball"]  # no staging debris, no lock


def test_a_full_disk_on_the_first_run_leaves_no_output(tmp_path) -> None:
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("ball", res=64))
    out = tmp_path / "out"
    r = _limited_run(cfg, out, 60_000)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert sorted(p.name for p in (out / "ball").iterdir()) == ["manifest.failed.json"]


# --- one writer per job -------------------------------------------------------------------------


def test_duplicate_job_names_in_one_batch_are_an_input_error(tmp_path, capsys) -> None:
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text(ball("same"))
    b.write_text(ball("same", center="[0.1, 0, 0]"))
    out = tmp_path / "out"
    assert main(["run", str(a), str(b), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{b}:1" in err and f"{a}:1" in err and "'same'" in err
    assert main(["run", str(a), str(a), "--out", str(out)]) == 2
    assert "given twice" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_a_second_run_of_a_job_being_written_is_refused(tmp_path, capsys) -> None:
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("ball"))
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out)]) == 0
    good = snapshot(out / "ball")
    with JobLock(out / "ball"):  # another run holds the job
        assert main(["run", str(cfg), "--out", str(out), "--force"]) == 1
        err = capsys.readouterr().err
        assert "being written by another run" in err and f"pid {os.getpid()}" in err
        assert snapshot(out / "ball") == good
    assert not (out / ".ball.lock").exists()
    assert main(["run", str(cfg), "--out", str(out), "--force"]) == 0


def test_two_concurrent_processes_never_interleave(tmp_path) -> None:
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("ball", res=96, more="  - hfrep: {}\n"))
    out = tmp_path / "out"
    procs = [subprocess.Popen([PY, "-m", "pipeline.cli", "run", str(cfg), "--out", str(out), "--force"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes in ([0, 0], [0, 1]), results  # the second finished after, or was refused
    if codes == [0, 1]:
        assert any("being written by another run" in err for _, err in results)
    manifest = json.loads((out / "ball" / "manifest.json").read_text())
    verify_outputs(out / "ball", manifest["outputs"])
    for entry in manifest["outputs"]:
        assert (out / "ball" / entry["path"]).is_file()


# --- interrupted runs ------------------------------------------------------------------------------


def _start_and_wait_for_staging(cfg: Path, out: Path) -> subprocess.Popen:
    proc = subprocess.Popen([PY, "-m", "pipeline.cli", "run", str(cfg), "--out", str(out), "--force"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stage = staging_dir(out / "ball")
    t0 = time.time()
    while not stage.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < 120
        time.sleep(0.02)
    time.sleep(0.3)
    return proc


def _rerun_in_progress(tmp_path: Path):
    """A good first run, then a slow rerun of the same job caught while it writes its staging
    folder: (config, --out, snapshot of the good outputs, the running process). The rerun must
    outlast the signal by a margin on a loaded machine: at 160^3 about 1.1 s were left once the
    staging folder appeared, at 256^3 1.6 s (session 26), and in a full-suite run on a loaded
    machine the rerun exited 0 before the signal with each; at 384^3 2.7 s are left. The rerun
    is stopped 0.3 s after its staging folder appears, so its size costs nothing."""
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("ball", res=20))
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out)]) == 0
    good = snapshot(out / "ball")
    cfg.write_text(ball("ball", res=384, more="  - hfrep: {}\n"))
    return cfg, out, good, _start_and_wait_for_staging(cfg, out)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_removes_the_staging_folder_and_keeps_the_outputs(tmp_path, sig) -> None:
    cfg, out, good, proc = _rerun_in_progress(tmp_path)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1 and "interrupted" in err and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["ball"]
    assert snapshot(out / "ball") == good


def test_kill_9_debris_is_removed_by_the_next_run(tmp_path) -> None:
    cfg, out, good, proc = _rerun_in_progress(tmp_path)
    proc.kill()
    proc.wait()
    assert snapshot(out / "ball") == good  # the job folder is never half-written
    cfg.write_text(ball("ball", res=24))
    assert main(["run", str(cfg), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["ball"]


def test_a_swap_cut_between_its_renames_is_completed(tmp_path) -> None:
    """Where renameat2 is missing the swap is two renames; a kill between them leaves the old
    outputs at .<name>.old and no job folder: the next run puts them back first."""
    folder = tmp_path / "ball"
    old = tmp_path / ".ball.old"
    old.mkdir()
    (old / "ball.vdb").write_bytes(b"old outputs")
    recover(folder)
    assert (folder / "ball.vdb").read_bytes() == b"old outputs" and not old.exists()


# --- bad --out --------------------------------------------------------------------------------------


@pytest.mark.parametrize("out", ["notes.txt", "/dev/null", "/proc", "/proc/x/y", "/sys/frepvdb", "", "  "])
def test_bad_out_is_one_line_and_exit_2(project, capsys, out) -> None:
    (project / "job.yaml").write_text(ball("ball"))
    before = snapshot(project)
    assert main(["run", "job.yaml", "--out", out]) == 2
    err = capsys.readouterr().err
    assert_one_line(err)
    assert err.startswith("error: --out")
    assert snapshot(project) == before


def test_a_job_folder_that_is_a_file_or_a_link_is_not_touched(tmp_path, capsys) -> None:
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("ball"))
    out = tmp_path / "out"
    out.mkdir()
    (out / "ball").write_text("a file of the user's\n")
    assert main(["run", str(cfg), "--out", str(out)]) in (1, 2)
    assert (out / "ball").read_text() == "a file of the user's\n"
    (out / "ball").unlink()
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "precious.txt").write_text("x\n")
    (out / "ball").symlink_to(target)
    assert main(["run", str(cfg), "--out", str(out)]) in (1, 2)
    assert "symbolic link" in capsys.readouterr().err
    assert sorted(p.name for p in target.iterdir()) == ["precious.txt"]


def test_a_5000_character_mesh_path_is_an_input_error(tmp_path, capsys) -> None:
    cfg = tmp_path / "job.yaml"
    cfg.write_text(ball("m").replace("{sphere: {center: [0, 0, 0], radius: 0.6}}", "{mesh: {path: " + "x" * 5000 + ".off}}"))
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert_one_line(err)
    assert "job.yaml:3 model.mesh" in err and len(err) < 400


_HALF_MADE = """\
import sys
import pipeline.cli as cli
from pipeline.util import errors


class HalfMade:  # like llvmlite's objects when an interrupt hit a Numba compilation
    def __del__(self):
        raise AttributeError("half made")


left = []


def fake_main(argv=None):
    left.append(HalfMade())
    if {interrupt}:
        errors._INTERRUPT.set()
        print("interrupted", file=sys.stderr)
    return 1


cli.main = fake_main
cli.run()
"""


@pytest.mark.parametrize("interrupt", [True, False])
def test_an_interrupted_run_exits_without_tracebacks_of_objects_finalised_at_exit(interrupt: bool) -> None:
    """The SIGTERM test above failed once on a clean clone: the signal hit a Numba compilation and
    llvmlite's ``ObjectRef.__del__`` raised at exit, printed as a traceback after "interrupted".
    The entry point (``pipeline.cli.run``) hides those after an interrupt; without one Python
    still prints them (the control case, so the check can fail)."""
    proc = subprocess.run([sys.executable, "-c", _HALF_MADE.format(interrupt=interrupt)], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 1
    assert ("Traceback" in proc.stderr) != interrupt, proc.stderr
