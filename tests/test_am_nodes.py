"""AM nodes (pipeline/model/am.py: shell, tpms, lattice): the tape conformance of tests/test_tape.py
(values = node evaluation, bounds hold, specialised = full), the formulas themselves, and a
graded gyroid infill of a shelled box that voxelises into one component whose wall thickness,
measured on the written grid, follows its formula within a voxel."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

import frepvdb as fv
from pipeline.io.vdbgrids import vdb
from pipeline.job.config import ConfigError
from tests.test_tape import check_tape, job_of

BOX = "{box: {min: [-0.6, -0.6, -0.6], max: [0.6, 0.6, 0.6]}}"
AM_NODES = {
    "shell_inside": f"shell: {{of: {BOX}, thickness: 0.1}}",
    "shell_outside": "shell: {of: {sphere: {radius: 0.5}}, thickness: 0.1, side: outside}",
    "shell_both": "shell: {of: {torus: {major: 0.6, minor: 0.2}}, thickness: 0.08, side: both}",
    "tpms_gyroid": "tpms: {type: gyroid, cell: 0.5, thickness: 0.05}",
    "tpms_schwarz_p": 'tpms: {type: schwarz_p, cell: "0.4 + 0.1 * x", thickness: "0.03 + 0.02 * (y + 1)"}',
    "tpms_diamond": f'tpms: {{type: diamond, cell: 0.6, thickness: "0.02 + 0.1 * max(d, 0)", d_from: {BOX}}}',
    "lattice_struts": "lattice: {struts: [[[0, 0, 0], [0.5, 0.5, 0]], [[0, 0, 0], [0, 0, 0.7]]], radius: 0.1}",
    "lattice_cubic": "lattice: {pattern: cubic, cell: 0.5, bounds: [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]], radius: 0.05}",
    "lattice_bcc": "lattice: {pattern: bcc, cell: 0.5, bounds: [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]], radius: 0.05}",
    "lattice_octet": "lattice: {pattern: octet, cell: 1.0, bounds: [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]], radius: 0.05}",
}


@pytest.mark.parametrize("name", sorted(AM_NODES))
def test_am_nodes_conform_to_the_tape(tmp_path, name) -> None:
    check_tape(job_of(tmp_path, AM_NODES[name]))


def test_shell_sides() -> None:
    s = fv.sphere(0.5)
    p = np.array([[0.47, 0, 0], [0.42, 0, 0], [0.53, 0, 0], [0.3, 0, 0]])
    np.testing.assert_allclose(fv.shell(s, 0.1).evaluate(p), [0.03, 0.02, -0.03, -0.1], atol=1e-12)
    np.testing.assert_allclose(fv.shell(s, 0.1, "outside").evaluate(p), [-0.03, -0.08, 0.03, -0.2], atol=1e-12)
    np.testing.assert_allclose(fv.shell(s, 0.1, "both").evaluate(p), [0.02, -0.03, 0.02, -0.15], atol=1e-12)


@pytest.mark.parametrize("kind", ["gyroid", "schwarz_p", "diamond"])
def test_tpms_zero_set_and_wall_thickness(kind) -> None:
    """The wall's mid-surface is the TPMS (field = T/2 there) and along the normal the wall ends
    at +-T/2 to first order."""
    from pipeline.model.am import _TPMS

    cell, T = 0.5, 0.04
    k = 2 * math.pi / cell
    shape = fv.tpms(kind, cell, T)
    rng = np.random.default_rng(0)
    for _ in range(40):
        x, y = rng.uniform(-1, 1, 2)
        zs = np.linspace(0, cell, 400)
        g = np.array([_TPMS[kind](k * x, k * y, k * z)[0] for z in zs])
        cross = np.flatnonzero(np.sign(g[:-1]) != np.sign(g[1:]))
        if not len(cross):  # this line misses the surface (Schwarz P: cos X + cos Y > 1)
            continue
        i = cross[0]
        lo, hi = zs[i], zs[i + 1]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.sign(_TPMS[kind](k * x, k * y, k * mid)[0]) == np.sign(g[i]) else (lo, mid)
        p = np.array([x, y, lo])
        assert shape.evaluate(p) == pytest.approx(T / 2, abs=1e-9)
        _, gx, gy, gz = _TPMS[kind](*(k * p))
        n = np.array([gx, gy, gz]) / math.sqrt(gx * gx + gy * gy + gz * gz)
        for s in (T / 2, -T / 2):
            assert abs(shape.evaluate(p + s * n)) < 0.05 * T  # first order: within 5% of T


def test_lattice_patterns_and_capsules() -> None:
    box = [[0, 0, 0], [2, 1, 1]]
    counts = {k: len(fv.lattice(pattern=k, cell=1.0, bounds=box, radius=0.1).node().segments)
              for k in ("cubic", "bcc", "octet")}
    assert counts == {"cubic": 20, "bcc": 16, "octet": 46}  # two cells: shared face struts once
    cap = fv.lattice(struts=[[[0, 0, 0], [1, 0, 0]]], radius=0.2)
    np.testing.assert_allclose(cap.evaluate([[0.5, 0.1, 0], [1.3, 0, 0], [-0.2, 0, 0]]), [0.1, -0.1, 0.0],
                               atol=1e-12)


@pytest.mark.parametrize("kwargs, message", [
    ({"type": "gyroid", "cell": "0.4 +", "thickness": 0.1}, "tpms.cell: bad formula"),
    ({"type": "gyroid", "cell": -1, "thickness": 0.1}, "tpms.cell: must be a number > 0 or a formula"),
    ({"type": "twisted", "cell": 1, "thickness": 0.1}, "tpms.type: must be 'gyroid', 'schwarz_p' or 'diamond'"),
])
def test_bad_tpms_parameters(kwargs, message) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        fv.tpms(**kwargs)


def test_d_without_d_from_is_an_input_error(tmp_path) -> None:
    with pytest.raises(ConfigError, match=r"model.tpms: thickness: bad formula: .*unknown name 'd'.*d_from"):
        job_of(tmp_path, 'tpms: {type: gyroid, cell: 0.5, thickness: "0.1 * d"}')
    with pytest.raises(ConfigError, match=r"lattice: give exactly one of struts"):
        job_of(tmp_path, "lattice: {radius: 0.1}")
    with pytest.raises(ConfigError, match=r"model.lattice: 1,000,000 cells of 0.01 .* use a larger cell"):
        job_of(tmp_path, "lattice: {pattern: cubic, cell: 0.01, bounds: [[0, 0, 0], [1, 1, 1]], radius: 0.001}")


@pytest.mark.parametrize("part_kind", ["frep", "mesh"])
def test_graded_gyroid_infill_of_a_shelled_part(tmp_path, part_kind) -> None:
    """Part [-0.5, 0.5]^3 (an FRep box, or a 12-triangle box mesh as a BSP-field): a 0.06 shell
    plus a gyroid infill (cell 0.4) whose wall is 0.03 + 0.1 d thick, d the part's field (the
    distance to its surface inside). One component; the wall thickness measured on the written
    grid along the gyroid normal matches the formula within a voxel."""
    import trimesh

    from pipeline.model.am import _TPMS

    h, cell = 0.01, 0.4
    if part_kind == "frep":
        part = fv.box([-0.5] * 3, [0.5] * 3)
    else:
        trimesh.creation.box((1.0, 1.0, 1.0)).export(str(tmp_path / "part.stl"))
        part = fv.mesh(tmp_path / "part.stl", rfunc="min_max")
    infill = part & fv.tpms("gyroid", cell, "0.03 + 0.1 * d", d_from=part)
    model = fv.union(fv.shell(part, 0.06), infill, rfunc="min_max")
    cfg = fv.config(model, [[-0.56] * 3, [0.56] * 3], voxel_size=h,
                    stages=[{"voxelise": {"band": 2}}, {"components": {"tolerance": 0.02}}, {"export": {"report": False}}])
    (m,) = fv.run(cfg, out=tmp_path / "out")
    assert m["components"]["count"] == 1
    g = vdb.read(str(tmp_path / "out" / "model" / "model.vdb"), "frep")
    n = 56
    dense = np.zeros((2 * n + 1,) * 3, np.float32)
    g.copyToArray(dense, (-n, -n, -n))

    def sample(pts: np.ndarray) -> np.ndarray:  # trilinear, world -> index space
        return map_coordinates(dense, (pts / h + n).T, order=1)

    def thickness_formula(p: np.ndarray) -> float:
        d = part.evaluate(p)
        assert d == pytest.approx(0.5 - np.abs(p).max(), abs=1e-9)  # the distance to the surface inside
        return 0.03 + 0.1 * d

    k = 2 * math.pi / cell
    rng = np.random.default_rng(5)
    errors = []
    while len(errors) < 40:
        x, y = rng.uniform(-0.3, 0.3, 2)
        zs = np.linspace(-0.3, 0.3, 600)
        gv = _TPMS["gyroid"](k * x, k * y, k * zs)[0]
        for i in np.flatnonzero(np.sign(gv[:-1]) != np.sign(gv[1:]))[:2]:
            p = np.array([x, y, 0.5 * (zs[i] + zs[i + 1])])
            _, gx, gy, gz = _TPMS["gyroid"](*(k * p))
            nrm = np.array([gx, gy, gz]) / math.sqrt(gx * gx + gy * gy + gz * gz)
            s = np.linspace(0, 0.08, 321)
            ends = []
            for sign in (1, -1):
                v = sample(p + sign * s[:, None] * nrm)
                j = np.flatnonzero(v <= 0)[0]  # first voxel past the wall's face
                ends.append(s[j - 1] + (s[j] - s[j - 1]) * v[j - 1] / (v[j - 1] - v[j]))
            errors.append(sum(ends) - thickness_formula(p))
    errors = np.abs(errors)
    assert errors.max() < h, errors.max()
