"""Sparse voxelisation: narrow-band size, culling, inside tiles, and the written .vdb."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.io.vdbgrids import frep_to_vdb, vdb
from pipeline.oracles import REGISTRY
from pipeline.voxel.voxelise import enumerate_cells, voxelise


def node(kind: str, **params):
    cls = REGISTRY[kind]
    return cls(cls.Params.model_validate(params))


def cube_domain(n: int, half: float = 1.0):
    h = 2 * half / n
    return np.array([-n // 2] * 3), np.array([n // 2] * 3), h


@pytest.mark.parametrize("n", [64, 192])
def test_sphere_band_matches_analytic_volume(n):
    """Active voxels within 10% of the analytic shell 4 pi r^2 (2 band h) at two resolutions."""
    r, band = 0.6, 3.0
    imin, imax, h = cube_domain(n)
    res = voxelise(node("sphere", radius=r), imin, imax, h, band)
    shell = 4 * math.pi * r * r * 2 * band * h / h**3
    assert abs(res.stats["active_voxels"] / shell - 1) < 0.10
    # every active voxel is really within band (+1 voxel of slack for the gradient estimate)
    ijk, vals = res.blocks.active_voxels()
    d = r - np.linalg.norm(ijk * h, axis=1)
    assert np.abs(d).max() <= (band + 1) * h
    np.testing.assert_allclose(vals, d, atol=1e-6)
    # and every voxel within band - 1 of the surface is active (the band has no holes)
    lo = imin
    dense = np.stack(np.meshgrid(*[np.arange(lo[0], imax[0] + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    near = dense[np.abs(r - np.linalg.norm(dense * h, axis=1)) < (band - 1) * h]
    act = set(map(tuple, ijk))
    assert all(tuple(p) in act for p in near)


def test_culling_keeps_work_near_the_band():
    imin, imax, h = cube_domain(256)
    res = voxelise(node("sphere", radius=0.6), imin, imax, h, 3.0)
    s = res.stats
    assert s["voxels_evaluated"] <= 3.0 * s["active_voxels"]
    assert s["voxels_evaluated"] < 0.1 * 257**3  # far from the dense 257^3
    assert s["cells_culled_inside"] > 0 and s["cells_culled_outside"] > 0


def test_work_grows_with_area_not_volume():
    """Doubling the resolution multiplies evaluated voxels by ~4 (surface), not 8 (volume)."""
    ev = []
    for n in (128, 256):
        imin, imax, h = cube_domain(n)
        ev.append(voxelise(node("torus", major=0.6, minor=0.2), imin, imax, h, 3.0).stats["voxels_evaluated"])
    ratio = ev[1] / ev[0]
    assert 3.0 < ratio < 5.0, ratio


def test_inside_tiles_are_inside():
    imin, imax, h = cube_domain(128)
    model = node("difference", of=[node("sphere", radius=0.8), node("sphere", radius=0.3)])
    res = voxelise(model, imin, imax, h, 3.0)
    assert len(res.inside_boxes) > 0
    rng = np.random.default_rng(0)
    for lo, hi in res.inside_boxes:
        pts = rng.integers(lo, hi + 1, size=(50, 3)) * h
        pts = np.vstack([pts, lo * h, hi * h])
        assert np.all(model.evaluate(pts) > 0)


def test_proven_outside_cells_hold_no_surface():
    """Enumeration never drops a cell that contains part of the zero set."""
    imin, imax, h = cube_domain(128)
    model = node("torus", major=0.6, minor=0.2, axis="y")
    lv = enumerate_cells(model, imin, imax, h, 3.0, 4)
    kept = set(map(tuple, lv.blocks))
    rng = np.random.default_rng(2)
    # points on the torus surface
    u, v = rng.uniform(0, 2 * np.pi, (2, 2000))
    p = np.stack([(0.6 + 0.2 * np.cos(v)) * np.cos(u), 0.2 * np.sin(v), (0.6 + 0.2 * np.cos(v)) * np.sin(u)], 1)
    vox = np.round(p / h).astype(np.int64)
    blocks = (vox // 4) * 4
    assert all(tuple(b) in kept for b in blocks)


def test_vdb_round_trip(tmp_path):
    imin, imax, h = cube_domain(96)
    model = node("box", min=(-0.5, -0.4, -0.3), max=(0.5, 0.4, 0.3))
    res = voxelise(model, imin, imax, h, 3.0)
    g = frep_to_vdb(res.blocks, res.inside_boxes, "frep")
    path = tmp_path / "box.vdb"
    vdb.write(str(path), grids=[g])
    back = vdb.read(str(path), "frep")
    assert back.activeVoxelCount() == res.stats["active_voxels"]
    assert back.transform.voxelSize()[0] == pytest.approx(h)
    acc = back.getConstAccessor()
    ijk, vals = res.blocks.active_voxels()
    for p, v in zip(ijk[::97], vals[::97], strict=True):
        assert acc.getValue(tuple(int(c) for c in p)) == pytest.approx(v, abs=1e-7)
        assert acc.isValueOn(tuple(int(c) for c in p))
    bg = abs(back.background)
    assert back.background < 0  # outside
    assert acc.getValue((0, 0, 0)) == pytest.approx(bg) and not acc.isValueOn((0, 0, 0))  # deep inside
    assert acc.getValue((40, 0, 0)) == pytest.approx(-bg)  # outside
    # world <-> index as OpenVDB sees it: voxel centres at integer multiples of h
    ijk0 = back.transform.worldToIndexCellCentered((0.5, 0.0, 0.0))
    assert tuple(ijk0) == (round(0.5 / h), 0, 0)


def test_nonfinite_field_is_reported():
    from pipeline.model.expr import Expr
    from pipeline.voxel.voxelise import NonFiniteField

    imin, imax, h = cube_domain(32)
    bad = Expr(Expr.Params(formula="1/x - 2"))
    with pytest.raises(NonFiniteField) as err:
        voxelise(bad, imin, imax, h, 3.0)
    assert err.value.point[0] == 0.0  # the voxel where 1/x is not finite is the one reported


def _dense_band(origins, values, known, band):
    """Reference of mark_band on a dense copy: S = known voxels that are 0 or have a known face
    neighbour of the other sign (f > 0); the reach = known voxels within ceil(band) - 1 voxels
    (L-infinity, separable through the leaves that exist) of S; active = S, or in the reach and |f| <= band * |grad| (central differences
    where both neighbours are in the reach, one-sided where one is). Also returns how many S
    voxels the distance test alone leaves out."""
    from scipy import ndimage

    pad = 9
    lo = origins.min(axis=0)
    shape = tuple(origins.max(axis=0) - lo + 8 + 2 * pad)  # unknown padding on every side
    v, kn, exists = np.zeros(shape), np.zeros(shape, bool), np.zeros(shape, bool)
    for r, o in enumerate(origins - lo + pad):
        sl = tuple(slice(c, c + 8) for c in o)
        v[sl], kn[sl], exists[sl] = values[r], known[r], True
    sign = kn & (v == 0)
    for axis in range(3):
        for shift in (1, -1):
            nv, nk = np.roll(v, shift, axis), np.roll(kn, shift, axis)
            sign |= kn & nk & ((nv > 0) != (v > 0))
    reach = int(np.ceil(max(band, 1.0))) - 1
    inreach = sign.copy()
    for axis in range(3):  # separable, through the leaves that exist (in a voxelised grid every
        line = [1, 1, 1]  # voxel between S and its reach is evaluated, so its leaf exists)
        line[axis] = 2 * reach + 1
        inreach = ndimage.binary_dilation(inreach, np.ones(line, bool)) & exists if reach > 0 else inreach
    inreach &= kn
    g2 = np.zeros(shape)
    for axis in range(3):
        lo_v, hi_v = np.roll(v, 1, axis), np.roll(v, -1, axis)
        lo_k, hi_k = np.roll(inreach, 1, axis), np.roll(inreach, -1, axis)
        d = np.where(lo_k & hi_k, 0.5 * (hi_v - lo_v), np.where(hi_k, hi_v - v, np.where(lo_k, v - lo_v, 0.0)))
        g2 += d * d
    near = np.abs(v) <= band * np.sqrt(g2)
    out = sign | (inreach & near)
    by_sign = int((sign & ~near).sum())
    return np.stack([out[tuple(slice(c, c + 8) for c in o)] for o in origins - lo + pad]), by_sign


@pytest.mark.parametrize("band", [1.0, 2.5, 9.5])
def test_mark_band_reads_neighbours_across_leaves(band):
    """mark_band (parallel passes over the leaves, each setting only its own voxels from ghost
    layers of its neighbour leaves; a reach of 9 voxels takes two dilation passes) against a dense
    reference, on leaves that touch along every axis, both ways, with gaps, unknown voxels, zeros
    (0 counts as outside and is active) and values both near and far from zero relative to their
    gradients."""
    from pipeline.sparse.grid import BlockGrid
    from pipeline.voxel.voxelise import mark_band

    rng = np.random.default_rng(7)
    cells = np.array([(i, j, k) for i in range(4) for j in range(3) for k in range(3)])
    cells = cells[rng.random(len(cells)) < 0.7]
    origins = (cells - 1) * 8
    L = len(origins)
    # sparse sign changes, so that the reach is not everything
    values = rng.choice([-1.0, 0.0, 1.0], size=(L, 8, 8, 8), p=[0.01, 0.002, 0.988]).astype(np.float32)
    values *= rng.random((L, 8, 8, 8)).astype(np.float32) * 4 + 0.5
    known = rng.random((L, 8, 8, 8)) < 0.9
    stale = rng.random((L, 8, 8, 8)) < 0.5  # mark_band sets every flag, whatever was there
    want, by_sign_want = _dense_band(origins, values, known, band)
    grid = BlockGrid(0.1, -1.0, origins, values.copy(), stale)
    rows = [np.flatnonzero((origins == o).all(axis=1))[0] for o in grid.origins]  # the grid's (sorted) order
    by_sign = mark_band(grid, known[rows], band)
    assert by_sign == by_sign_want
    assert by_sign > 0 or band > 3  # a wide reach gives every sign change a |grad| from afar
    assert np.array_equal(grid.active, want[rows])
    assert 0 < grid.active.sum() < known.sum()  # both tests decide some voxels each way


def _active_set(res) -> np.ndarray:
    g = res.blocks
    b, i, j, k = np.nonzero(g.active)
    co = g.origins[b] + np.stack([i, j, k], axis=1)
    return co[np.lexsort(co.T[::-1])]


@pytest.mark.parametrize("model", ["bumpy_mesh_min_max", "demo_r0"])
def test_band_does_not_depend_on_block_size(tmp_path, model):
    """The same active voxels and values whatever block size the evaluation used. A min/max
    BSP-field of a mesh has creases everywhere and |f| / |grad f| <= band far from its surface;
    the band test used to take one-sided differences at block faces and to keep such far voxels
    only where their block happened to be evaluated (1.5-2.4 % of a mesh's band moved between
    blocks of 4 and 8)."""
    import trimesh

    if model == "bumpy_mesh_min_max":
        m = trimesh.creation.icosphere(4)
        v = m.vertices
        r = 0.8 * (1.0 + 0.08 * np.sin(5 * v[:, 0]) * np.sin(7 * v[:, 1]) * np.sin(6 * v[:, 2]))
        path = tmp_path / "bumpy.off"
        trimesh.Trimesh(v * r[:, None], m.faces, process=False).export(str(path))
        model_node = node("mesh", path=str(path), rfunc="min_max")
    else:
        from pipeline.job.config import load_jobs

        cfg = tmp_path / "demo.yaml"
        cfg.write_text("name: d\ndomain: {bounds: [[-1.2, -1.2, -1.2], [1.2, 1.2, 1.2]], resolution: 96}\n"
                       "model:\n  difference:\n    - superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}\n"
                       "    - box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}\n  rfunc: r0\n"
                       "stages: [voxelise: {band: 3}]\n")
        model_node = load_jobs(cfg)[0].model
    imin, imax, h = cube_domain(96)
    runs = {b: voxelise(model_node, imin, imax, h, 3.0, b) for b in (2, 4, 8)}
    ref = _active_set(runs[4])
    assert len(ref) > 10_000
    for b in (2, 8):
        assert np.array_equal(_active_set(runs[b]), ref), b
        assert runs[b].stats["blocks_evaluated"] != runs[4].stats["blocks_evaluated"]
    vals = {b: runs[b].blocks.values[runs[b].blocks.active] for b in runs}
    assert np.array_equal(vals[2], vals[4]) and np.array_equal(vals[8], vals[4])


def test_written_band_does_not_depend_on_block_size(tmp_path):
    """What users receive: the frep grid that `frepvdb run` writes with block 2, 4 or 8 (a min_max
    mesh with creases, band 2.5, whose cull pad rounds up to 3), read back with pyopenvdb: the
    same active voxels, and the same value at every voxel of the domain (inactive voxels, tiles
    and background hold +-background by their sign: copyToArray over the domain)."""
    import trimesh

    from pipeline.cli import main

    mesh = trimesh.creation.icosphere(3)
    v = mesh.vertices
    r = 0.8 * (1.0 + 0.1 * np.sin(5 * v[:, 0]) * np.sin(7 * v[:, 1]))
    trimesh.Trimesh(v * r[:, None], mesh.faces, process=False).export(str(tmp_path / "m.off"))
    grids = {}
    for b in (2, 4, 8):
        cfg = tmp_path / f"b{b}.yaml"
        cfg.write_text(f"name: b{b}\ndomain: {{bounds: [[-1, -1, -1], [1, 1, 1]], resolution: 80}}\n"
                       f"model:\n  mesh: {{path: {tmp_path / 'm.off'}, rfunc: min_max}}\n"
                       f"stages:\n  - voxelise: {{band: 2.5, block: {b}}}\n  - export: {{vdb: true}}\n")
        assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
        grids[b] = vdb.read(str(tmp_path / "out" / f"b{b}" / f"b{b}.vdb"), "frep")
    ref = grids[4]
    dense = {}
    for b, g in grids.items():
        assert g.activeVoxelCount() == ref.activeVoxelCount() > 5000
        assert g.evalActiveVoxelBoundingBox() == ref.evalActiveVoxelBoundingBox()
        a = np.zeros((81, 81, 81), np.float32)
        g.copyToArray(a, ijk=(-40, -40, -40))
        on = np.zeros(a.shape, bool)
        for item in g.citerOnValues():
            if item.count == 1:
                i, j, k = (c + 40 for c in item.min)
                on[i, j, k] = True
        dense[b] = (a, on)
    for b in (2, 8):
        on = dense[4][1]
        assert np.array_equal(dense[b][1], on), b
        assert np.array_equal(dense[b][0], dense[4][0]), b


def test_coalesced_boxes_fill_the_same_pruned_tree():
    """coalesce_boxes: the same voxels as the boxes (random cells of a random octree, some
    cut by a domain's faces), fewer boxes, and one fill per merged box gives, after prune,
    the tree of one fill per box (node counts, values)."""
    from pipeline.sparse.grid import coalesce_boxes

    rng = np.random.default_rng(3)
    boxes = []

    def split(o, size):
        if size > 2 and rng.random() < 0.6:
            for d in np.ndindex(2, 2, 2):
                split(o + np.array(d) * size // 2, size // 2)
        elif rng.random() < 0.5:
            boxes.append([o, o + size - 1])

    split(np.array([-32, -32, -32]), 64)
    b = np.array(boxes, np.int64)
    b = b[np.all((b[:, 0] <= 30) & (b[:, 1] >= -29), axis=1)]
    b = np.clip(b, -29, 30)  # the domain's faces cut some cells
    merged = coalesce_boxes(b)
    assert 0 < len(merged) < 0.6 * len(b)

    def dense(bs):
        out = np.zeros((64, 64, 64), np.int64)
        for lo, hi in bs:
            out[lo[0] + 32:hi[0] + 33, lo[1] + 32:hi[1] + 33, lo[2] + 32:hi[2] + 33] += 1
        return out

    assert np.array_equal(dense(merged), dense(b) > 0) and dense(merged).max() == 1

    def tree(bs):
        g = vdb.FloatGrid(-1.0)
        g.copyFromArray(np.full((3, 3, 3), 0.5, np.float32), (-2, 5, 9))  # some active band
        for lo, hi in bs:
            g.fill(tuple(int(c) for c in lo), tuple(int(c) for c in hi), 1.0, False)
        g.prune()
        arr = np.zeros((64, 64, 64), np.float32)
        g.copyToArray(arr, (-32, -32, -32))
        return g.leafCount(), g.nonLeafCount(), g.activeVoxelCount(), arr

    a, c = tree(b), tree(merged)
    assert a[:3] == c[:3] and np.array_equal(a[3], c[3])


def _bumpy_mesh(tmp_path, level: int = 3):
    import trimesh

    m = trimesh.creation.icosphere(level)
    v = m.vertices
    r = 0.8 * (1.0 + 0.08 * np.sin(5 * v[:, 0]) * np.sin(7 * v[:, 1]) * np.sin(6 * v[:, 2]))
    path = tmp_path / "bumpy.off"
    trimesh.Trimesh(v * r[:, None], m.faces, process=False).export(str(path))
    return path


def _voxels(res) -> dict:
    """{voxel index: float32 value} of every voxel of every leaf, and the active ones."""
    g = res.blocks
    b, i, j, k = np.nonzero(np.ones_like(g.active))
    co = g.origins[b] + np.stack([i, j, k], axis=1)
    keys = [tuple(c) for c in co]
    return dict(zip(keys, g.values[b, i, j, k], strict=True)), set(map(tuple, _active_set(res)))


@pytest.mark.parametrize("case", ["r0", "sardf", "union_r0", "translated_difference"])
def test_sign_proxy_run_equals_evaluating_every_block(tmp_path, case):
    """An r0 / sardf mesh is enumerated and evaluated with its min_max twin (the same sign) and
    evaluated itself only in the reach of the sign changes: the same active voxels with the same
    float32 values as evaluating the model at every block's voxel, and the same sign at every
    voxel of both runs' leaves; far fewer model evaluations."""
    from pipeline.voxel.voxelise import assemble, sample_blocks

    path = str(_bumpy_mesh(tmp_path))
    mesh = node("mesh", path=path, rfunc="sardf" if case == "sardf" else "r0")
    if case == "union_r0":
        model = node("union", of=[mesh, node("sphere", center=[0.7, 0, 0], radius=0.3)], rfunc="r0")
    elif case == "translated_difference":
        model = node("translate", by=[0.05, -0.03, 0.0],
                     of=node("difference", of=[mesh, node("sphere", center=[0, 0, 0.8], radius=0.25)], rfunc="r0"))
    else:
        model = mesh
    proxy = model.sign_proxy()
    assert proxy is not model and all(getattr(n.params, "rfunc", "min_max") == "min_max" for n in proxy.walk())
    assert proxy.sign_proxy() is proxy  # min_max all the way down: its own proxy
    imin, imax, h = cube_domain(72)
    got = voxelise(model, imin, imax, h, 3.0, 4)
    want = assemble(sample_blocks(model, imin, imax, h, 3.0, 4), imin, imax, h, 3.0)
    assert got.stats["sign_proxy"] and got.stats["exact_rounds"] == 1
    assert got.stats["exact_voxels"] < 0.6 * want.stats["voxels_evaluated"], (got.stats, want.stats)
    vg, ag = _voxels(got)
    vw, aw = _voxels(want)
    assert ag == aw and len(aw) > 5000
    assert all(vg[v] == vw[v] for v in aw)
    common = vg.keys() & vw.keys()
    assert all(np.sign(vg[v]) == np.sign(vw[v]) for v in common)
    assert got.stats["background"] == want.stats["background"]


def test_sign_proxy_of_nodes():
    """A model without an r0 / sardf mesh is its own proxy: nothing to refine."""
    from pipeline.voxel.voxelise import exact_in_reach

    sphere = node("sphere", center=[0, 0, 0], radius=0.5)
    assert sphere.sign_proxy() is sphere
    u = node("union", of=[sphere, node("box", min=[0, 0, 0], max=[1, 1, 1])], rfunc="r0")
    assert u.sign_proxy() is u and exact_in_reach(u, 0.1, 0.0) is None


def test_sign_proxy_signs_agree(tmp_path):
    """Meshes with r0 / sardf have a min_max twin; set operations, complements and coordinate
    maps over them are copies over the proxies (the model is untouched); a node whose sign needs
    its children's values (offset) is its own proxy. The signs agree."""
    path = str(_bumpy_mesh(tmp_path, 2))
    mesh = node("mesh", path=path)
    off = node("offset", distance=0.05, of=mesh)
    assert off.sign_proxy() is off
    model = node("complement", of=node("rotate", angle=30, axis="x",
                                       of=node("intersection", of=[mesh, node("sphere", radius=0.7)])))
    proxy = model.sign_proxy()
    assert proxy is not model and proxy.params.of.params.of.params.rfunc == "min_max"
    assert model.params.of.params.of.params.rfunc == "r0"  # the model itself is untouched
    p = np.random.default_rng(5).uniform(-1, 1, (20000, 3))
    assert np.array_equal(np.sign(proxy.evaluate(p)), np.sign(model.evaluate(p)))


def _mesh_node(tmp_path, subdivisions: int = 4):
    import trimesh

    from pipeline.job.config import _Ctx, build_node

    m = trimesh.creation.icosphere(subdivisions)
    m.vertices *= 0.8 + 0.05 * np.sin(5 * m.vertices[:, :1]) * np.sin(7 * m.vertices[:, 1:2])
    m.export(str(tmp_path / "ico.off"))
    raw = {"mesh": {"path": str(tmp_path / "ico.off"), "rfunc": "min_max"}}
    return build_node(raw, ("model",), _Ctx("test", raw, tmp_path))


@pytest.mark.parametrize("kind", ["tape", "affine"])
def test_stop_after_ends_the_descent_like_a_shallower_run(tmp_path, kind) -> None:
    """An enumeration that stops after a level (stop_after) has the cells of one told to stop
    at that size: the memory estimate's early stop is the descent it replaced."""
    from pipeline.model.tape import compile_model
    from pipeline.voxel.voxelise import enumerate_cells_tape

    model = node("torus", major=0.6, minor=0.2)
    imin, imax, h = cube_domain(256)

    def run(**kw):
        if kind == "tape":
            return enumerate_cells_tape(compile_model(model), imin, imax, h, 3.0, 8, root_size=64, **kw)[0]
        return enumerate_cells(model, imin, imax, h, 3.0, 8, root_size=64, **kw)

    early = run(stop_after=lambda size, ambiguous: size <= 16 and ambiguous > 100)
    shallow = run(stop_size=16)
    assert early.stats["levels"] == shallow.stats["levels"] and early.stats["levels"][-1]["size"] == 16
    assert np.array_equal(early.blocks, shallow.blocks) and len(early.blocks) > 100
    assert len(run().blocks) > len(early.blocks)  # without a stop it goes on down to the blocks


def test_memory_estimate_of_a_mesh_uses_the_voxelisers_tape(tmp_path, monkeypatch) -> None:
    """The estimate enumerates with the compiled, per-cell specialised tape, as voxelise does:
    bounding every box with the whole BSP-tree took 61 s for a 1.3M-face mesh at 512^3, four
    times its voxelisation. The mesh node's own (whole-tree) bounds must not be called."""
    from pipeline.job.config import Domain
    from pipeline.voxel.voxelise import LEAF_PEAK_BYTES, WORK_BYTES, estimate_band_bytes, estimate_interior_voxels

    mesh = _mesh_node(tmp_path)
    dom = Domain(bounds=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), voxel_size=2.0 / 512)

    def whole_tree(*args, **kwargs):
        raise AssertionError("the estimate bounded boxes with the whole tree")

    monkeypatch.setattr(type(mesh), "bound", whole_tree)
    monkeypatch.setattr(type(mesh), "bound_form", whole_tree)
    need = estimate_band_bytes(mesh, dom, 3.0)
    monkeypatch.undo()
    leaves = len(voxelise(mesh, dom.index_min, dom.index_max, dom.voxel_size, 3.0).blocks.origins)
    actual = leaves * LEAF_PEAK_BYTES + WORK_BYTES
    assert 0.7 * actual < need < 2 * actual, (need, actual)
    monkeypatch.setattr(type(mesh), "bound", whole_tree)
    inside = estimate_interior_voxels(mesh, dom, 3.0)
    ball = 4 / 3 * math.pi * 0.8 ** 3 / dom.voxel_size ** 3
    assert 0.7 * ball < inside < 1.3 * ball


def test_a_mesh_finer_than_the_voxels_gets_blocks_of_two_with_the_same_grid(tmp_path) -> None:
    """block_for: 2 where a mesh has more than DENSE_MESH faces per 4 x 4 voxels of surface,
    else 4 (8 without oracles); an explicit block wins. The written grid does not depend on it."""
    from pipeline.voxel.voxelise import DENSE_MESH, block_for

    mesh = _mesh_node(tmp_path, 4)  # 5120 faces on ~8 units of area
    coarse = math.sqrt(2 * DENSE_MESH / mesh.faces_per_area) / 4  # twice the density threshold
    assert block_for(mesh, "auto", coarse) == 2 and block_for(mesh, "auto", coarse / 2) == 4
    assert block_for(mesh, 4, coarse) == 4 and block_for(mesh) == 4 and block_for(node("sphere", radius=1)) == 8
    imin, imax, h = cube_domain(int(2 / coarse) + 1)
    dense = []
    for b in (2, 4):
        res = voxelise(mesh, imin, imax, h, 3.0, block=b)
        g = frep_to_vdb(res.blocks, res.inside_boxes, "frep", outside_boxes=res.outside_boxes, domain=(imin, imax))
        a = np.zeros(tuple(imax - imin + 1), np.float32)
        g.copyToArray(a, tuple(int(v) for v in imin))
        dense.append((a, g.activeVoxelCount()))
    assert dense[0][1] == dense[1][1] > 0 and np.array_equal(dense[0][0], dense[1][0])
