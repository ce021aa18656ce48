"""Benchmark of the components stage (components seed) against dense anchors.

1. Sparse enumeration + labelling (Algorithm 1 + section 4.2) vs a uniform grid of the same cell
   size labelled with ``scipy.ndimage.label`` (face connectivity), depths 7..10: wall time, peak
   memory (RSS above the warmed-up baseline, each run in a fresh process), counts.
2. Algorithm 1 with corner control range and continuation vs plain revised-affine subdivision
   ([17], ``continuation=False``): the trend of the paper's Table 1.
3. Components on bricks (pipeline.topology.component_bricks) run inline vs the unsplit detection: the
   cost of the split (coarse levels revisited per brick, per-brick call overhead) and of the
   driver's label unification; results checked equal.
4. (issue 14) Sparse detection vs dense evaluation of the compiled model at the cell centres +
   ``cc3d.connected_components``, depths 9 and 10 (512^3, 1024^3 cells), each in a fresh process.
5. (issues 13, 14) Lattices: a ``union`` (min_max) of N random spheres (radius 0.03-0.05 in
   [-1, 1]^3, as bench/lattice.py), N = 1 .. 10^4, depths 7 and 8: the detection with per-cell
   tapes, the same descent over the whole tape (``CellTapes`` off: the code before session 29),
   and dense evaluation + cc3d; runs over ``--timeout`` seconds (default 300) are stopped.

Run: ``.venv/bin/python bench/components.py`` (prints Markdown tables; ``--bricked``: table 3
only, ``--cc3d``: table 4 only, ``--lattice [--timeout S]``: table 5 only).
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TWO_SPHERES = {"union": [{"sphere": {"center": [-0.5, 0, 0], "radius": 0.35}},
                         {"sphere": {"center": [0.5, 0, 0], "radius": 0.35}}]}
DEMO = {"difference": [{"superellipsoid": {"radii": [1, 1, 1], "exponents": [0.3, 0.3]}},
                       {"box": {"min": [-1.3, -0.02, -1.3], "max": [1.3, 0.02, 1.3]}}]}
NOISE = {"expr": "81 - 100*x^2 - 100*y^2 - 100*z^2 + (3.8*sin(15*x) + 1.6*sin(11.1*x + 1.1*sin(15*x)))"
                 " * (3.8*sin(15*y) + 1.3*sin(11.1*x + 1.1*sin(15*x)))"
                 " * (3.8*sin(15*z) + 2.6*sin(11.1*x + 1.1*sin(15*x)))"}
MODELS = {"two spheres": (TWO_SPHERES, -1.0, 2.0), "demo (Fig. 3)": (DEMO, -1.25, 2.5),
          "solid noise (Fig. 4)": (NOISE, -1.8, 3.6)}


def lattice(n: int, seed: int = 20240613) -> dict:
    """A union (min_max) of n spheres of radius 0.03-0.05 with centres in [-1, 1]^3."""
    rng = np.random.default_rng(seed)
    c, r = rng.uniform(-1, 1, (n, 3)), rng.uniform(0.03, 0.05, n)
    return {"union": [{"sphere": {"center": [float(v) for v in p], "radius": float(q)}}
                      for p, q in zip(c, r, strict=True)], "rfunc": "min_max"}


def _model(name: str) -> tuple[dict, float, float]:
    if name.startswith("lattice "):
        return lattice(int(name.split()[1])), -1.1, 2.2
    return MODELS[name]


def _node(raw: dict):
    from pipeline.job.config import _Ctx, build_node

    return build_node(raw, ("model",), _Ctx("bench", raw, Path(".")))


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def sparse(model, lo: float, size: float, depth: int) -> dict:
    from pipeline.topology import components as cc

    cc.detect(model, np.full(3, lo), size, 4)  # warm up (Numba cache, imports)
    base = _rss_mb()
    t0 = time.perf_counter()
    found = cc.detect(model, np.full(3, lo), size, depth)
    return {"seconds": time.perf_counter() - t0, "peak_mb": _rss_mb() - base, "count": found.count,
            "cells": len(found.tree)}


def dense(model, lo: float, size: float, depth: int) -> dict:
    """f at the centres of a uniform grid of the same cell size (slab by slab), f > 0, label."""
    from scipy import ndimage

    n = 2**depth
    base = _rss_mb()
    t0 = time.perf_counter()
    ax = lo + (np.arange(n) + 0.5) * size / n
    yy, zz = np.meshgrid(ax, ax, indexing="ij")
    inside = np.empty((n, n, n), bool)
    for i in range(n):
        pts = np.stack([np.full(n * n, ax[i]), yy.ravel(), zz.ravel()], axis=1)
        inside[i] = (model.evaluate(pts) > 0).reshape(n, n)
    _, count = ndimage.label(inside)
    return {"seconds": time.perf_counter() - t0, "peak_mb": _rss_mb() - base, "count": int(count),
            "cells": n**3}


def dense_cc3d(model, lo: float, size: float, depth: int) -> dict:
    """The issue-14 anchor: f at the cell centres of a uniform grid of the same cell size,
    evaluated by NumPy on the compiled model (the tape, slab by slab, as fast as NumPy gets it),
    inside = f > 0, labelled with ``cc3d.connected_components`` (6-connected)."""
    import cc3d

    from pipeline.model.tape import compile_model, evaluate_with

    tape = compile_model(model)
    n = 2**depth
    base = _rss_mb()
    t0 = time.perf_counter()
    ax = lo + (np.arange(n) + 0.5) * size / n
    yy, zz = np.meshgrid(ax, ax, indexing="ij")
    inside = np.empty((n, n, n), bool)
    for i in range(n):
        pts = np.stack([np.full(n * n, ax[i]), yy.ravel(), zz.ravel()], axis=1)
        f = evaluate_with(tape, pts) if tape is not None else model.evaluate(pts)
        inside[i] = (f > 0).reshape(n, n)
    t1 = time.perf_counter()
    _, count = cc3d.connected_components(inside, connectivity=6, return_N=True, out_dtype=np.uint32)
    return {"seconds": time.perf_counter() - t0, "eval_s": t1 - t0, "label_s": time.perf_counter() - t1,
            "peak_mb": _rss_mb() - base, "count": int(count), "cells": n**3}


def table_cc3d(names=("demo (Fig. 3)",), depths=(9, 10)) -> None:
    print("\n### Sparse detection (Algorithm 1 + section 4.2) vs dense evaluation + cc3d\n")
    print("| model | depth (cells a side) | sparse s | sparse MB | dense eval s | cc3d s | dense total s "
          "| dense MB | dense / sparse | counts sparse / dense |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        for depth in depths:
            s = _child("sparse", name, depth)
            d = _child("cc3d", name, depth) if _dense_fits(depth) else {"error": "skipped: memory"}
            if "error" in s or "error" in d:
                print(f"| {name} | {depth} ({2**depth}) | {s.get('seconds', float('nan')):.2f} | - | {d.get('error', '')} "
                      f"| - | - | - | - | {s.get('count', '-')} |")
                continue
            print(f"| {name} | {depth} ({2**depth}) | {s['seconds']:.2f} | {s['peak_mb']:.0f} | {d['eval_s']:.2f} "
                  f"| {d['label_s']:.2f} | {d['seconds']:.2f} | {d['peak_mb']:.0f} "
                  f"| {d['seconds'] / s['seconds']:.1f}x | {s['count']} / {d['count']} |")


def continuation(model, lo: float, size: float, depth: int, on: bool) -> dict:
    from pipeline.topology import components as cc

    cc.detect(model, np.full(3, lo), size, 3, continuation=on)
    t0 = time.perf_counter()
    tree = cc.enumerate_octree(model, np.full(3, lo), size, depth, continuation=on)
    t1 = time.perf_counter()
    comp = cc.label_cells(tree)
    return {"enumeration_s": t1 - t0, "detection_s": time.perf_counter() - t1, "count": comp.count,
            "affine_tests": tree.stats["affine_tests"], "border": tree.stats["border_cells"]}


def bricked(model, lo: float, size: float, depth: int, brick: int) -> dict:
    """Unsplit ``detect`` vs ``detect_bricked`` inline (one process: the work a pool shares)."""
    from pipeline.topology import component_bricks as cb
    from pipeline.topology import components as cc

    origin = np.full(3, lo)
    cb.detect_bricked(model, origin, size, 4, 4)  # warm up
    t0 = time.perf_counter()
    whole = cc.detect(model, origin, size, depth)
    t1 = time.perf_counter()
    split = cb.detect_bricked(model, origin, size, depth, brick)
    t2 = time.perf_counter()
    info = split.tree.stats["bricked"]
    same = split.count == whole.count and np.array_equal(split.labels, whole.labels)
    return {"unsplit_s": t1 - t0, "bricked_s": t2 - t1, "merge_s": info["merge_seconds"], "bricks": info["bricks"],
            "unions": info["cross_face_unions"], "cells": len(whole.tree), "count": whole.count, "same": bool(same)}


def whole_tape(model, lo: float, size: float, depth: int) -> dict:
    """:func:`sparse` with the descent's per-cell tapes off: every cell bounded and every corner
    evaluated with the whole tape."""
    from pipeline.topology import components as cc

    cc.CellTapes.start = classmethod(lambda cls, model, tape: None)
    return sparse(model, lo, size, depth)


def _child(kind: str, name: str, depth: int, flag: str = "", timeout: float = 3600) -> dict:
    cmd = [sys.executable, __file__, "--one", kind, name, str(depth), flag]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"stopped after {timeout:g} s"}
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _one(kind: str, name: str, depth: int, flag: str) -> None:
    raw, lo, size = _model(name)
    model = _node(raw)
    if kind == "sparse":
        res = sparse(model, lo, size, depth)
    elif kind == "whole":
        res = whole_tape(model, lo, size, depth)
    elif kind == "dense":
        res = dense(model, lo, size, depth)
    elif kind == "cc3d":
        res = dense_cc3d(model, lo, size, depth)
    elif kind == "bricked":
        res = bricked(model, lo, size, depth, int(flag))
    else:
        res = continuation(model, lo, size, depth, flag == "on")
    print(json.dumps(res))


def _dense_fits(depth: int) -> bool:
    import psutil

    need = (2**depth) ** 3 * 5  # bool mask + 32-bit labels
    return need < 0.5 * psutil.virtual_memory().available


def table_sparse_vs_dense(name: str = "two spheres") -> None:
    print(f"\n### Sparse labelling vs dense scipy.ndimage.label - {name}\n")
    print("| depth | cells (sparse) | sparse s | dense s | time ratio dense/sparse | sparse MB | dense MB "
          "| memory ratio | counts |")
    print("|---|---|---|---|---|---|---|---|---|")
    for depth in (7, 8, 9, 10):
        s = _child("sparse", name, depth)
        d = _child("dense", name, depth) if _dense_fits(depth) else {"error": "skipped: memory"}
        if "error" in s or "error" in d:
            print(f"| {depth} | {s.get('cells', '-')} | {s.get('seconds', float('nan')):.2f} | {d.get('error', '')} "
                  f"| - | {s.get('peak_mb', float('nan')):.0f} | - | - | {s.get('count', '-')} |")
            continue
        print(f"| {depth} | {s['cells']} | {s['seconds']:.2f} | {d['seconds']:.2f} | {d['seconds'] / s['seconds']:.1f} "
              f"| {s['peak_mb']:.0f} | {d['peak_mb']:.0f} | {d['peak_mb'] / max(s['peak_mb'], 1):.1f} "
              f"| {s['count']} / {d['count']} |")


def table_lattice(counts=(1, 100, 1000, 10_000), depths=(7, 8), timeout: float = 300) -> None:
    print("\n### Lattices: detection with per-cell tapes vs the whole tape vs dense evaluation + cc3d\n")
    print("| spheres | depth (cells a side) | per-cell tapes s | whole tape s | whole / per-cell | dense eval + cc3d s "
          "| dense / per-cell | counts per-cell / whole / dense |")
    print("|---|---|---|---|---|---|---|---|")

    def cell(r: dict, key: str = "seconds") -> str:
        return r["error"] if "error" in r else f"{r[key]:.2f}"

    def ratio(r: dict, s: dict) -> str:
        return "-" if "error" in r or "error" in s else f"{r['seconds'] / s['seconds']:.1f}x"

    for n in counts:
        for depth in depths:
            name = f"lattice {n}"
            s = _child("sparse", name, depth, timeout=timeout)
            w = _child("whole", name, depth, timeout=timeout)
            d = _child("cc3d", name, depth, timeout=timeout) if _dense_fits(depth) else {"error": "skipped: memory"}
            print(f"| {n} | {depth} ({2**depth}) | {cell(s)} | {cell(w)} | {ratio(w, s)} | {cell(d)} | {ratio(d, s)} "
                  f"| {s.get('count', '-')} / {w.get('count', '-')} / {d.get('count', '-')} |", flush=True)


def table_continuation() -> None:
    print("\n### Algorithm 1 (control range + continuation) vs plain affine subdivision [17]\n")
    print("| model | depth | enumeration s (ours) | enumeration s ([17]) | detection s | affine tests ours / [17] "
          "| border cells ours / [17] | count ours / [17] |")
    print("|---|---|---|---|---|---|---|---|")
    for name, depths in (("demo (Fig. 3)", (6, 7, 8)), ("solid noise (Fig. 4)", (6, 7, 8))):
        for depth in depths:
            on = _child("cont", name, depth, "on")
            off = _child("cont", name, depth, "off")
            print(f"| {name} | {depth} | {on['enumeration_s']:.2f} | {off['enumeration_s']:.2f} "
                  f"| {on['detection_s']:.2f} | {on['affine_tests']} / {off['affine_tests']} "
                  f"| {on['border']} / {off['border']} | {on['count']} / {off['count']} |")


def table_bricked() -> None:
    print("\n### Components on bricks (inline) vs unsplit\n")
    print("| model | depth | brick (cells) | bricks | cells | unsplit s | bricked s | ratio | merge s "
          "| cross-face unions | same labels |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in ("two spheres", "demo (Fig. 3)"):
        for depth, brick in ((7, 32), (8, 32), (8, 64)):
            r = _child("bricked", name, depth, str(brick))
            if "error" in r:
                print(f"| {name} | {depth} | {brick} | {r['error']} |")
                continue
            print(f"| {name} | {depth} | {brick} | {r['bricks']} | {r['cells']} | {r['unsplit_s']:.2f} "
                  f"| {r['bricked_s']:.2f} | {r['bricked_s'] / r['unsplit_s']:.1f} | {r['merge_s']:.3f} "
                  f"| {r['unions']} | {'yes' if r['same'] else 'NO'} |")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        _one(sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5] if len(sys.argv) > 5 else "")
    else:
        if sys.argv[1:] == ["--bricked"]:
            table_bricked()
            sys.exit(0)
        if sys.argv[1:2] == ["--lattice"]:
            table_lattice(timeout=float(sys.argv[3]) if sys.argv[2:3] == ["--timeout"] else 300)
            sys.exit(0)
        if sys.argv[1:2] == ["--cc3d"]:  # optional depths after it (default 9 10)
            table_cc3d(depths=tuple(int(d) for d in sys.argv[2:]) or (9, 10))
            sys.exit(0)
        table_sparse_vs_dense()
        table_continuation()
        table_bricked()
