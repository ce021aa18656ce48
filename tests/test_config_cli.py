"""Config validation and the CLI: bad input gets exit 2 with file:line and the YAML path."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb

GOOD = """name: {name}
domain:
  bounds: [[-1, -1, -1], [1, 1, 1]]
  resolution: 48
model:
  union:
    - sphere: {{center: [-0.3, 0, 0], radius: 0.4}}
    - sphere: {{center: [0.3, 0, 0], radius: 0.4}}
stages:
  - voxelise: {{band: 3}}
  - export: {{vdb: true}}
"""

# (label, config text, expected line, text the message must contain)
BAD = [
    ("malformed yaml", "name: x\ndomain: [unclosed\n", 3, "malformed YAML"),
    ("unknown node", GOOD.format(name="x").replace("sphere: {center: [0.3", "spere: {center: [0.3"), 8,
     "model.union[1].spere: unknown node type 'spere' (did you mean 'sphere'?)"),
    ("negative radius", GOOD.format(name="x").replace("[0.3, 0, 0], radius: 0.4", "[0.3, 0, 0], radius: -1"), 8,
     "model.union[1].sphere.radius: must be > 0"),
    ("missing key", GOOD.format(name="x").replace("  resolution: 48\n", ""), 2,
     "domain: give exactly one of voxel_size or resolution"),
    ("missing model param", GOOD.format(name="x").replace("{center: [-0.3, 0, 0], radius: 0.4}", "{center: [-0.3, 0, 0]}"),
     7, "model.union[0].sphere.radius: missing required key"),
    ("unknown key", GOOD.format(name="x").replace("radius: 0.4}\n    - sphere", "radius: 0.4, radiuss: 2}\n    - sphere", 1),
     7, "model.union[0].sphere.radiuss: unknown key 'radiuss' (did you mean 'radius'?)"),
    ("unknown stage", GOOD.format(name="x").replace("voxelise: {band: 3}", "voxelize: {band: 3}"), 10,
     "stages[0].voxelize: unknown stage 'voxelize' (did you mean 'voxelise'?)"),
    ("nan formula", GOOD.format(name="x").replace("- sphere: {center: [0.3, 0, 0], radius: 0.4}", '- expr: "sqrt(x - 2)"'),
     8, "model.union[1].expr: the field is not a finite number"),
    ("division by zero", GOOD.format(name="x").replace("- sphere: {center: [0.3, 0, 0], radius: 0.4}", '- expr: "x / (2 - 2)"'),
     8, "model.union[1].expr: bad formula: column 3: division by zero"),
    ("huge domain", GOOD.format(name="x").replace("resolution: 48", "resolution: 400000"), 4,
     "domain.resolution: this domain needs an estimated"),
    ("wrong type", GOOD.format(name="x").replace("band: 3", "band: wide"), 10, "stages[0].voxelise.band: must be a valid number"),
    ("two node types", GOOD.format(name="x").replace("  union:\n", "  intersection: []\n  union:\n"), 5,
     "model: a node has exactly one type key, found 2"),
    ("empty union", "name: x\ndomain: {bounds: [[0, 0, 0], [1, 1, 1]], resolution: 8}\nmodel:\n  union: []\n"
     "stages:\n  - voxelise: {}\n", 4, "model.union: List should have at least 1 item"),
]


@pytest.mark.parametrize("label, text, line, message", BAD, ids=[b[0] for b in BAD])
def test_bad_configs_exit_2_with_line(tmp_path, capsys, label, text, line, message):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    out = tmp_path / "out"
    code = main(["run", str(cfg), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"bad.yaml:{line} " in err or f"bad.yaml:{line}:" in err, err
    assert message in err, err
    assert "Traceback" not in err
    assert not any(out.rglob("*.vdb")) if out.exists() else True


def test_validate_prints_normalised_config(tmp_path, capsys):
    cfg = tmp_path / "good.yaml"
    cfg.write_text(GOOD.format(name="good"))
    assert main(["validate", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "voxel_size: 0.041666" in out and "rfunc: r0" not in out or "union" in out
    assert "band: 3.0" in out and "block: auto" in out


def test_run_writes_vdb_and_manifest(tmp_path):
    cfg = tmp_path / "good.yaml"
    cfg.write_text(GOOD.format(name="pair"))
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out)]) == 0
    m = json.loads((out / "pair" / "manifest.json").read_text())
    for key in ("name", "config", "config_sha256", "domain", "outputs", "grids", "stages", "warnings", "inputs"):
        assert key in m
    assert m["grids"]["frep"]["active_voxels"] > 0
    assert {"path": "pair.vdb", "kind": "vdb"} in m["outputs"]
    assert m["stages"][0]["name"] == "voxelise" and m["stages"][0]["stats"]["voxels_evaluated"] > 0
    g = vdb.read(str(out / "pair" / "pair.vdb"), "frep")
    assert g.metadata["frepvdb_config"] == "pair"
    assert g.metadata["frepvdb_config_sha256"] == m["config_sha256"]
    assert json.loads(g.metadata["frepvdb_params"])["band"] == 3.0
    assert not list(out.glob(".*"))  # no staging folders left behind


def test_failed_job_leaves_no_output_and_others_run(tmp_path, capsys):
    good = tmp_path / "good.yaml"
    good.write_text(GOOD.format(name="good"))
    bad = tmp_path / "bad.yaml"
    bad.write_text(GOOD.format(name="bad").replace("radius: 0.4}", "radius: 0}", 1))
    out = tmp_path / "out"
    assert main(["run", str(bad), str(good), "--out", str(out)]) == 2
    assert (out / "good" / "good.vdb").exists()
    assert not (out / "bad").exists()


def test_console_script_and_exit_codes(tmp_path):
    exe = Path(sys.executable).parent / "frepvdb"
    cfg = tmp_path / "c.yaml"
    cfg.write_text(GOOD.format(name="c").replace("radius: 0.4}", "radius: -0.4}", 1))
    r = subprocess.run([str(exe), "run", str(cfg), "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and "c.yaml:7 model.union[0].sphere.radius: must be > 0" in r.stderr
    r = subprocess.run([str(exe), "info", str(tmp_path / "missing.vdb")], capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_memory_check_counts_the_hfrep_interior(tmp_path, capsys, monkeypatch):
    """The narrow band of a sphere at 2000^3 fits in 16 GiB, its interior distance does not."""
    import pipeline.job.config as config

    monkeypatch.setattr(config, "_available_memory", lambda: 16 * 2**30)  # a fixed machine size
    text = ("name: big\ndomain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 2000}\n"
            "model: {sphere: {radius: 0.8}}\nstages:\n  - voxelise: {band: 3}\n")
    cfg = tmp_path / "big.yaml"
    cfg.write_text(text)
    assert main(["validate", str(cfg)]) == 0
    cfg.write_text(text + "  - hfrep: {interior: fine}\n")
    assert main(["validate", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "big.yaml:2 domain.resolution: this domain needs an estimated" in err
    assert "interior distance of the hfrep stage" in err


def test_a_run_without_vtk_previews_or_meshes_does_not_import_them(tmp_path):
    """Start-up (issue 13: keep it low): VTK (~1 s), matplotlib and trimesh (~0.3 s) are imported
    only by runs that write VTK files or previews or read meshes; a .vdb-only FRep run in a fresh
    interpreter leaves them unloaded (and the .vdb is written)."""
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text("name: tiny\ndomain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 8}\n"
                   "model: {sphere: {radius: 0.5}}\nstages:\n  - voxelise: {band: 3}\n  - export: {vdb: true}\n")
    args = ["run", str(cfg), "--out", str(tmp_path / "out")]
    code = (f"import sys; from pipeline.cli import main; rc = main({args!r}); "
            "print(rc, sorted(m for m in ('vtk', 'matplotlib', 'trimesh') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "0 []", r.stdout
    assert (tmp_path / "out" / "tiny" / "tiny.vdb").is_file()
