"""Smoke test of bench/scale.py at tiny sizes: every table has its rows, bricked == unsplit,
the end-to-end child reports every stage, and a stage over the time or memory limit is stopped
and reported."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load_scale() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_scale", ROOT / "bench" / "scale.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_scale"] = module
    spec.loader.exec_module(module)
    return module


scale = _load_scale()

SETUPS = (("inline", 1), ("local", 1), ("local", 2))  # Dask is covered by tests/test_batch.py


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> dict:
    folder = tmp_path_factory.mktemp("scale")
    return {
        "batch": scale.batch_throughput(folder, n=16, count=2, setups=SETUPS, warmup=0),
        "bricks": scale.brick_cost(folder, sizes=(64,), bricks=(32,), workers=2),
        "e2e": [scale.run_e2e(folder, 16, stage_limit=300)],
    }


def _table_rows(table: str) -> list[list[str]]:
    lines = table.splitlines()
    assert lines[0].startswith("| ") and set(lines[1]) <= set("|-")
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]


def test_batch_table(measured: dict) -> None:
    rows = measured["batch"]
    assert [(r["executor"], r["workers"]) for r in rows] == list(SETUPS)
    assert all(r["jobs"] == 2 and r["jobs_per_s"] > 0 for r in rows)
    assert [r["speedup"] for r in rows if r["workers"] == 1] == [1.0, 1.0]
    assert rows[2]["speedup"] == pytest.approx(rows[1]["seconds"] / rows[2]["seconds"])
    cells = _table_rows(scale.batch_table(rows))
    assert [(c[0], c[1]) for c in cells] == [(k, str(w)) for k, w in SETUPS]
    assert cells[-1][-1].endswith("x")


def test_bricked_equals_unsplit(measured: dict) -> None:
    rows = measured["bricks"]
    assert [(r["brick"], r["executor"]) for r in rows] == [
        (None, "inline"), (32, "inline"), (32, "local pool, 2 workers")]
    assert rows[1]["bricks"] == rows[2]["bricks"] > 8
    for r in rows:
        assert r["active_a"] == r["active_b"] > 0 and r["leaves_a"] == r["leaves_b"]
        assert r["max_abs_diff_band"] == r["max_abs_diff"] == r["background_diff"] == 0.0
        assert r["identical"]
        assert r["components"] == rows[0]["components"] == 2  # the demo's two pieces
        assert r["surface_active_equal"] and r["surface_max_diff_vox"] < 1e-3
    assert rows[1]["hfrep_rounds"] >= 2 and rows[2]["hfrep_rounds"] == rows[1]["hfrep_rounds"]
    cells = _table_rows(scale.brick_table(rows))
    assert [c[1] for c in cells] == ["unsplit", "32", "32"]


def test_e2e_table(measured: dict) -> None:
    (row,) = measured["e2e"]
    assert row["failure"] is None and row["done"] is not None
    assert [s["stage"] for s in row["stages"]] == ["load", "voxelise", "components", "hfrep", "export"]
    assert all(s["finished"] and s["peak_rss_mib"] > 50 for s in row["stages"])
    assert row["peak_rss_mib"] == max(s["peak_rss_mib"] for s in row["stages"])
    cells = _table_rows(scale.e2e_table([row]))
    assert [c[1] for c in cells] == ["load", "voxelise", "components", "hfrep", "export", "**whole job**"]


def test_e2e_stage_limit_is_reported(tmp_path: Path) -> None:
    row = scale.run_e2e(tmp_path, 16, stage_limit=0.5)
    assert row["done"] is None
    assert "ran longer than 0.5 s" in row["failure"]
    assert not row["stages"][-1]["finished"]


def test_e2e_memory_limit_is_reported(tmp_path: Path) -> None:
    row = scale.run_e2e(tmp_path, 16, max_rss_gib=0.1)
    assert row["done"] is None
    assert row["failure"].startswith("stopped: RSS") and "limit of 0.1 GiB" in row["failure"]


def test_median_row_takes_each_stage_median_and_range() -> None:
    def run(vox: float, hf: float, done: bool = True) -> dict:
        stages = [{"stage": "voxelise", "seconds": vox, "peak_rss_mib": 10 * vox, "finished": True},
                  {"stage": "hfrep", "seconds": hf, "peak_rss_mib": 10 * hf, "finished": True}]
        return {"n": 8, "voxel_size": 0.3, "stages": stages, "failure": None if done else "x", "wall_s": vox + hf,
                "done": {"grids": {}} if done else None, "peak_rss_mib": 10 * max(vox, hf), "load": (0, 0, 0)}

    row = scale.median_row([run(1.0, 5.0), run(3.0, 4.0), run(2.0, 9.0), run(99.0, 99.0, done=False)])
    secs = {s["stage"]: s["seconds"] for s in row["stages"]}
    assert secs == {"voxelise": 2.0, "hfrep": 5.0} and row["runs"] == 3  # the unfinished run is left out
    assert row["spread"] == {"voxelise": (1.0, 3.0), "hfrep": (4.0, 9.0)}
    assert row["wall_s"] == 7.0 and row["peak_rss_mib"] == 50.0  # medians of 6, 7, 11 and 50, 40, 90
    cells = _table_rows(scale.spread_table([row]))
    assert len(cells) == 2 and cells[1][2:] == ["3", "5.00", "4.00", "9.00"]
