"""BSP-fields on the shared CGAL meshes (/work/shared/meshes), all three R-function families.

Point counts (chosen to keep this file under ~90 s on 2 cores): per mesh 3000 random points in
the bounding box enlarged by 10 % for the sign test, 1000 points sampled on the faces, and 20
random lines of 200 samples for the crossing count. Meshes whose optimised tree has more than
``MAX_FACES`` input faces are left out (their build alone takes tens of seconds; the benchmark
bench/bsp_table1.py covers them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline.mesh.bsp import BSPField
from pipeline.mesh.meshio import load_mesh

MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"
FAMILIES = ("min_max", "r0", "sardf")
MAX_FACES = 1500
# Once not met: r0 reached |f| = 2.8e-8 on the faces of part.off (bound 1.2e-9). Met since the
# magnitude control of r0 and the compiled tree build (measured 1.1e-15); the check stays, so a
# regression shows.
R0_PRECISION_NOT_MET: set[str] = set()

pytestmark = pytest.mark.realdata


def _closed_meshes() -> list[str]:
    if not MESHES.is_dir():
        return []
    names = []
    for path in sorted(MESHES.glob("*.off")):
        mesh, rep = load_mesh(path)
        if rep.watertight and rep.faces <= MAX_FACES:
            names.append(path.stem)
    return names


@pytest.fixture(scope="module", params=_closed_meshes() or ["<absent>"])
def case(request):
    if request.param == "<absent>":
        pytest.skip(f"{MESHES} is absent")
    mesh, _ = load_mesh(MESHES / f"{request.param}.off")
    field = BSPField.from_mesh(mesh, rfunc="r0", planes="optimised")
    return mesh, {fam: field.with_rfunc(fam) for fam in FAMILIES}


def test_sign_equals_containment(case) -> None:
    mesh, fields = case
    lo, hi = mesh.bounds
    ext = hi - lo
    p = np.random.default_rng(0).uniform(lo - 0.1 * ext, hi + 0.1 * ext, (3000, 3))
    _, dist, _ = trimesh.proximity.closest_point(mesh, p)
    p = p[dist > 1e-6]
    inside = mesh.contains(p)
    for fam, field in fields.items():
        agree = np.mean((field.evaluate(p) > 0) == inside)
        assert agree >= 0.999, f"{fam}: sign agrees on {agree:.5f} only"


def test_zero_on_faces(case, request) -> None:
    mesh, fields = case
    s, _ = trimesh.sample.sample_surface(mesh, 1000, seed=1)
    size = float(np.linalg.norm(mesh.extents))
    name = request.node.callspec.id
    for fam, field in fields.items():
        worst = np.abs(field.evaluate(s)).max()
        if fam == "r0" and name in R0_PRECISION_NOT_MET:
            assert worst >= 1e-9 * size, f"r0 now meets the bound on {name}: update R0_PRECISION_NOT_MET"
            continue
        assert worst < 1e-9 * size, f"{fam}: |f| = {worst:.3g} on the surface"


def _crossings(mesh: trimesh.Trimesh, a: np.ndarray, b: np.ndarray) -> int:
    """Number of surface crossings of the segment a-b (ray/mesh intersections with t < |b - a|)."""
    d = b - a
    length = float(np.linalg.norm(d))
    loc, _, _ = mesh.ray.intersects_location([a], [d / length], multiple_hits=True)
    loc = np.asarray(loc, dtype=float).reshape(-1, 3)
    t = np.linalg.norm(loc - a, axis=1)
    t = np.unique(np.round(t[(t > 0) & (t < length)] / length, 9))
    return len(t)


def test_sign_changes_equal_crossings(case) -> None:
    mesh, fields = case
    rng = np.random.default_rng(2)
    lo, hi = mesh.bounds
    ext = hi - lo
    checked = 0
    for _ in range(20):
        a, b = rng.uniform(lo - 0.2 * ext, hi + 0.2 * ext, (2, 3))
        n = _crossings(mesh, a, b)
        ts = np.linspace(0, 1, 200)
        p = a + ts[:, None] * (b - a)
        _, dist, _ = trimesh.proximity.closest_point(mesh, p)
        if dist.min() < 1e-6 * np.linalg.norm(ext):
            continue  # a sample on the surface would make the count ambiguous
        # sampling must resolve every crossing: each pair of crossings is more than a step apart
        inside = mesh.contains(p)
        if np.count_nonzero(np.diff(inside.astype(int))) != n:
            continue
        checked += 1
        for fam, field in fields.items():
            changes = np.count_nonzero(np.diff(np.sign(field.evaluate(p))))
            assert changes == n, f"{fam}: {changes} sign changes, {n} crossings"
    assert checked >= 10
