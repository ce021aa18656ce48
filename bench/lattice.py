"""Benchmark (issue 13): cost per active voxel of a union of N parts vs one part, same run.

    .venv/bin/python bench/lattice.py [--quick] [--res 128 256] [--counts 1 10 100 1000 10000]
                                      [--shapes spheres capsules] [--timeout S]
                                      [--patterns octet bcc cubic] [--cells 0.4 0.2 0.1]

A ``union`` (rfunc min_max) of N random parts in [-1, 1]^3 (seed fixed), domain [-1.1, 1.1]^3:

* spheres: radius 0.03-0.05;
* capsules: rods, i.e. a ``cylinder`` with ``height:`` (radius 0.01-0.02, length 0.06-0.1)
  along a random coordinate axis (no capsule primitive exists in pipeline/model; rods inside a
  ``rotate`` about random axes make a 10^4-part config that the config loader refuses: more
  than its limit of 250,000 values).

Each config is generated as a YAML file (10^4 children for N = 10^4) and run as a whole
process ``frepvdb run CONFIG --out DIR --force`` (voxelise band 3, export vdb). Printed per row:
wall seconds of the process, the voxelise stage's seconds and counters from manifest.json
(active voxels, voxels evaluated), microseconds of voxelise per active voxel, and the ratio of
that cost to N = 1's at the same resolution and shape. N = 1 has a few hundred active voxels, so
its cost per active voxel is mostly the fixed cost of a voxelise call; the row "1 big" (one part
of the same kind, large: a sphere of radius 0.8, a rod of radius 0.5 and length 1.2, with
~10^5 active voxels) is the cost of one primitive per voxel over many voxels, and the last
column is the ratio to it. The issue's target is a ratio within 3x at N = 10^4; the last lines
say whether it is met against either baseline. A run over ``--timeout`` is killed and printed as
"stopped". The default is 128^3 only (256^3 with ``--res 128 256``).

``--patterns`` adds strut lattices as additive-manufacturing users make them: a ``lattice`` node
(capsules along the struts of a unit cell repeated over [-1, 1]^3, strut radius 0.075 x the
cell) for each cell size of ``--cells``, run with voxelise (band 3), components and a .vdb
export. Dense lattices are the opposite of the random parts above: most voxels lie in the band
and every block meets dozens of struts. Printed: struts, tape clauses, active voxels, the
voxelise and components seconds, and voxelise's cost per active voxel against "1 big" sphere's.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FREPVDB = ROOT / ".venv" / "bin" / "frepvdb"
SEED = 20240613
TARGET = 3.0


@dataclass
class Result:
    status: str  # ok | stopped | failed: ...
    wall_s: float | None = None
    voxelise_s: float | None = None
    active: int | None = None
    evaluated: int | None = None

    @property
    def us_per_active(self) -> float | None:
        if self.voxelise_s is None or not self.active:
            return None
        return self.voxelise_s / self.active * 1e6


def sphere_yaml(rng: np.random.Generator) -> str:
    c = rng.uniform(-1, 1, 3)
    r = rng.uniform(0.03, 0.05)
    return f"  - sphere: {{center: [{c[0]:.5f}, {c[1]:.5f}, {c[2]:.5f}], radius: {r:.5f}}}"


def capsule_yaml(rng: np.random.Generator) -> str:
    c = rng.uniform(-1, 1, 3)
    axis = "xyz"[int(rng.integers(3))]
    r, length = rng.uniform(0.01, 0.02), rng.uniform(0.06, 0.1)
    return (f"  - cylinder: {{center: [{c[0]:.5f}, {c[1]:.5f}, {c[2]:.5f}], radius: {r:.5f},"
            f" height: {length:.5f}, axis: {axis}}}")


PART = {"spheres": sphere_yaml, "capsules": capsule_yaml}
# one large part of the same kind: the cost of "one primitive per voxel" over many active voxels
BIG = {"spheres": "  - sphere: {center: [0.0, 0.0, 0.0], radius: 0.8}",
       "capsules": "  - cylinder: {center: [0.0, 0.0, 0.0], radius: 0.5, height: 1.2, axis: z}"}


def write_config(folder: Path, shape: str, n: int, res: int) -> tuple[Path, str]:
    """N random parts (n = 0: the one big part of BIG)."""
    rng = np.random.default_rng(SEED)
    name = f"{shape}_{n}_{res}"
    parts = BIG[shape] if n == 0 else "\n".join(PART[shape](rng) for _ in range(n))
    text = (f"name: {name}\ndomain:\n  bounds: [[-1.1, -1.1, -1.1], [1.1, 1.1, 1.1]]\n  resolution: {res}\n"
            f"model:\n  union:\n    rfunc: min_max\n    of:\n{_indent(parts)}\n"
            "stages:\n  - voxelise: {band: 3}\n  - export: {vdb: true}\n")
    cfg = folder / f"{name}.yaml"
    cfg.write_text(text)
    return cfg, name


def _indent(block: str) -> str:
    return "\n".join("    " + ln for ln in block.splitlines())


def run_cli(cfg: Path, name: str, out: Path, timeout: float) -> Result:
    t0 = time.perf_counter()
    p = subprocess.Popen([str(FREPVDB), "run", str(cfg), "--out", str(out), "--force"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        return Result("stopped")
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        return Result(f"failed (exit {p.returncode}): {(err.strip().splitlines() or ['?'])[-1][:120]}", wall)
    manifest = json.loads((out / name / "manifest.json").read_text())
    vox = next(s for s in manifest["stages"] if s["name"] == "voxelise")
    return Result("ok", wall, float(vox["seconds"]), int(vox["stats"]["active_voxels"]),
                  int(vox["stats"]["voxels_evaluated"]))


def pattern_config(folder: Path, pattern: str, cell: float, res: int) -> tuple[Path, str]:
    name = f"{pattern}_{cell:g}_{res}".replace(".", "p")
    text = (f"name: {name}\ndomain:\n  bounds: [[-1.1, -1.1, -1.1], [1.1, 1.1, 1.1]]\n  resolution: {res}\n"
            f"model:\n  lattice: {{pattern: {pattern}, cell: {cell:g}, bounds: [[-1, -1, -1], [1, 1, 1]],"
            f" radius: {0.075 * cell:g}}}\n"
            "stages:\n  - voxelise: {band: 3}\n  - components: {}\n  - export: {vdb: true}\n")
    cfg = folder / f"{name}.yaml"
    cfg.write_text(text)
    return cfg, name


def pattern_row(cfg: Path, name: str, out: Path, res: int, big: Result | None, timeout: float) -> str:
    from pipeline.job.config import load_job  # the struts the node makes from the config

    struts = len(load_job(cfg).model.segments)
    r = run_cli(cfg, name, out, timeout)
    label = f"| {name.split('_')[0]} | {name.split('_')[1].replace('p', '.')} | {res} | {struts:,} |"
    if r.status != "ok":
        return f"{label} {r.status} | - | - | - | - | - | - |"
    stages = {s["name"]: s for s in json.loads((out / name / "manifest.json").read_text())["stages"]}
    vox = stages["voxelise"]
    return (f"{label} {vox['stats']['tape_clauses']:,} | {r.active:,} | {r.wall_s:.2f} | {r.voxelise_s:.2f} |"
            f" {stages['components']['seconds']:.2f} | {r.us_per_active:.3f} | {_ratio(r, big)} |")


def _ratio(r: Result, base: Result | None) -> str:
    if base is None or not base.us_per_active or not r.us_per_active:
        return "-"
    return f"{r.us_per_active / base.us_per_active:.2f}x"


def fmt_row(shape: str, res: int, n: int, r: Result, one: Result | None, big: Result | None,
            timeout: float) -> str:
    label = "1 big" if n == 0 else f"{n:,}"
    if r.status == "stopped":
        return f"| {shape} | {res} | {label} | > {timeout:.0f} s (stopped) | - | - | - | - | - | - |"
    if r.status != "ok":
        return f"| {shape} | {res} | {label} | {r.status} | - | - | - | - | - | - |"
    return (f"| {shape} | {res} | {label} | {r.wall_s:.2f} | {r.voxelise_s:.2f} | {r.active:,} | {r.evaluated:,} |"
            f" {r.us_per_active:.2f} | {_ratio(r, one)} | {_ratio(r, big)} |")


def verdict(shape: str, res: int, rows: dict[int, Result], base_n: int, timeout: float) -> str:
    what = "N = 1" if base_n == 1 else "1 big part"
    if base_n not in rows or 10_000 not in rows:
        return f"- {shape} {res}^3 vs {what}: {what} or N = 10^4 not run"
    base, top = rows[base_n], rows[10_000]
    if top.status == "stopped":
        return f"- {shape} {res}^3 vs {what}: N = 10^4 stopped after {timeout:.0f} s: target NOT met (not measured)"
    if not (base.us_per_active and top.us_per_active):
        return f"- {shape} {res}^3 vs {what}: not measured ({base.status} / {top.status})"
    ratio = top.us_per_active / base.us_per_active
    met = "met" if ratio <= TARGET else "NOT met"
    return (f"- {shape} {res}^3: N = 10^4 costs {ratio:.2f}x {what} per active voxel:"
            f" target (<= {TARGET:.0f}x) {met}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="64^3, N = 1, 10, 100, spheres (smoke run, < 60 s)")
    ap.add_argument("--res", type=int, nargs="+", default=[128])
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 10, 100, 1000, 10_000])
    ap.add_argument("--shapes", nargs="+", default=list(PART), choices=list(PART))
    ap.add_argument("--timeout", type=float, default=150.0, help="seconds per run (default 150)")
    ap.add_argument("--patterns", nargs="*", default=[], choices=["octet", "bcc", "cubic"],
                    help="strut lattices (the lattice node) after the random parts")
    ap.add_argument("--cells", type=float, nargs="+", default=[0.4, 0.2, 0.1], help="cell sizes of --patterns")
    args = ap.parse_args()
    if args.quick:
        args.res, args.counts, args.shapes, args.timeout = [64], [1, 10, 100], ["spheres"], 40.0
    print(f"## Union of N parts (min_max), voxelise band 3, whole `frepvdb run`\n\nload average at start:"
          f" {' '.join(f'{v:.2f}' for v in os.getloadavg())} (2 cores; other processes share the machine),"
          f" timeout per run {args.timeout:.0f} s\n")
    print("| shape | res | N | wall s | voxelise s | active voxels | voxels evaluated | us / active voxel |"
          " cost vs N=1 | cost vs 1 big |\n|---|---|---|---|---|---|---|---|---|---|", flush=True)
    verdicts = []
    with tempfile.TemporaryDirectory(prefix="bench_lattice_") as tmp:
        folder = Path(tmp)
        for shape in args.shapes:
            for res in args.res:
                rows: dict[int, Result] = {}
                for n in [0, *args.counts]:
                    cfg, name = write_config(folder, shape, n, res)
                    rows[n] = run_cli(cfg, name, folder / "out", args.timeout)
                    print(fmt_row(shape, res, n, rows[n], rows.get(1), rows.get(0), args.timeout), flush=True)
                verdicts += [verdict(shape, res, rows, 1, args.timeout), verdict(shape, res, rows, 0, args.timeout)]
        if args.patterns:
            print("\n## Strut lattices (the lattice node), voxelise band 3 + components + .vdb, whole `frepvdb run`\n\n"
                  "| pattern | cell | res | struts | tape clauses | active voxels | wall s | voxelise s | components s |"
                  " voxelise us / active voxel | vs 1 big sphere |\n|---|---|---|---|---|---|---|---|---|---|---|",
                  flush=True)
            for res in args.res:
                cfg, name = write_config(folder, "spheres", 0, res)
                big = run_cli(cfg, name, folder / "out", args.timeout)
                for pattern in args.patterns:
                    for cell in args.cells:
                        cfg, name = pattern_config(folder, pattern, cell, res)
                        print(pattern_row(cfg, name, folder / "out", res, big, args.timeout), flush=True)
    print("\n" + "\n".join(verdicts))
    print(f"\nload average at end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
