"""The stage protocol (stages/base.py): every stage declares its parameters, the grids it adds
and its memory, and the written .vdb holds the grids in the order the stages declare."""

from __future__ import annotations

import inspect
import json

from pipeline.cli import main
from pipeline.io.vdbgrids import vdb
from stages import REGISTRY
from stages.base import FrepBand, StageParams


def test_every_stage_follows_the_protocol() -> None:
    for name, stage in REGISTRY.items():
        assert issubclass(stage.Params, StageParams), name
        assert list(inspect.signature(stage.run).parameters) == ["ctx", "p"], name
        assert len(inspect.signature(stage.grids).parameters) == 1, name
        assert len(inspect.signature(stage.estimate_bytes).parameters) == 3, name
        made = set().union(*(getattr(s, "PRODUCES", ()) for s in REGISTRY.values()))
        assert set(getattr(stage, "REQUIRES", ())) <= made, name
        if FrepBand in getattr(stage, "PRODUCES", ()) and FrepBand not in getattr(stage, "REQUIRES", ()):
            assert callable(stage.estimate_band) and callable(stage.enumeration_bytes), name


JOB = """\
name: order
domain: {bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 24}
model: {union: [{sphere: {center: [-0.4, 0, 0], radius: 0.3}}, {sphere: {center: [0.4, 0, 0], radius: 0.3}}]}
stages:
  - voxelise: {band: 2}
  - hfrep:
      density: true
      attributes:
        - {name: paint, formula: "d"}
  - components: {}
  - export: {vdb: true}
"""


def test_grids_are_written_in_the_declared_order(tmp_path) -> None:
    """hfrep makes its attribute first and its distance grids last; the file still lists
    surface, hfrep, density, then the attribute (hfrep's ``grids``), after frep and before
    component."""
    cfg = tmp_path / "order.yaml"
    cfg.write_text(JOB)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    folder = tmp_path / "out" / "order"
    manifest = json.loads((folder / "manifest.json").read_text())
    order = ["frep", "surface", "hfrep", "density", "paint", "component"]
    assert list(manifest["grids"]) == order  # pyopenvdb lists a file's grids by name, so the manifest says
    assert next(s for s in manifest["stages"] if s["name"] == "export")["stats"]["grids"] == order
    assert sorted(m["name"] for m in vdb.readAllGridMetadata(str(folder / "order.vdb"))) == sorted(order)


def test_each_stage_estimates_its_own_memory(tmp_path) -> None:
    """The loader asks every stage (``estimate_bytes``): voxelise, components and export hold
    the band; hfrep adds the distance it solves (more for the whole interior than for the
    coarse one)."""
    from pipeline.job.config import load_jobs

    big = JOB.replace("resolution: 24", "resolution: 600")
    est = {}
    for interior in ("coarse", "fine"):
        cfg = tmp_path / f"{interior}.yaml"
        cfg.write_text(big.replace("density: true", f"density: true\n      interior: {interior}")
                       .replace("      attributes:\n        - {name: paint, formula: \"d\"}\n", ""))
        est[interior] = load_jobs(cfg)[0].memory_estimate
    for e in est.values():
        assert set(e) == {"voxelise", "hfrep", "components", "export"}
        assert e["voxelise"] == e["components"] == e["export"] < e["hfrep"]
    assert est["coarse"]["hfrep"] < est["fine"]["hfrep"]
