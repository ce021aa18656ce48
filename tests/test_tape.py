"""Conformance of the compiled tape (pipeline.model.tape) over every node type and random trees:

- the tape's values equal the node-by-node evaluation (to float rounding);
- its interval bounds contain every value in the box;
- a box's specialised tape gives the same values as the full tape in that box, bit for bit
  (min/max pruning is exact), and is no longer;
- its forward-mode gradients equal central differences (away from creases);
- nodes that cannot be traced (oracles) are reported as such, and keep the old evaluator.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.job.config import load_job
from pipeline.model import tape as pt
from tests.test_written_grids import frep_config, tree

NODES = {
    "sphere": "sphere: {center: [0.1, -0.2, 0.05], radius: 0.6}",
    "box": "box: {min: [-0.5, -0.4, -0.3], max: [0.6, 0.5, 0.4]}",
    "cylinder": "cylinder: {center: [0, 0, 0], radius: 0.3, axis: x, height: 1.2}",
    "cone": "cone: {radius: 0.5, height: 1.0}",
    "torus": "torus: {center: [0, 0, 0], major: 0.6, minor: 0.2, axis: y}",
    "ellipsoid": "ellipsoid: {center: [0, 0, 0], radii: [0.7, 0.4, 0.3]}",
    "superellipsoid": "superellipsoid: {radii: [0.8, 0.7, 0.6], exponents: [0.3, 0.6]}",
    "halfspace": "halfspace: {normal: [0.3, 0.4, 0.866], offset: 0.1}",
    "blobby": "blobby: {blobs: [{center: [0, 0, 0], radius: 0.5}, {center: [0.4, 0, 0], radius: 0.4}]}",
    "expr": 'expr: "1 - x^2 - y^2 - z^2 + 0.2 * sin(7 * x) * cos(5 * y) - exp(-z) / 9 + log(2 + x)"',
    # one constant operand: the immediate opcodes (a + c, a * c, c - a, a / c, c / a), division by
    # zero included (x / 0 at x = 0 is NaN, 1 / x at x = 0 is inf: the node evaluator's results)
    "expr_immediates": 'expr: "(3 - x) / (1.5 + y) + 2 * z - 0.5 / (x - 0.3) + x / 0.7 - y * 0 + 1 / (z + 0.2) + 4"',
    "union_min_max": "union: {of: [{sphere: {radius: 0.4}}, {box: {min: [0, 0, 0], max: [0.7, 0.7, 0.7]}}], rfunc: min_max}",
    "intersection_r0": "intersection: {of: [{sphere: {radius: 0.7}}, {box: {min: [-0.5, -0.5, -0.5], max: [0.5, 0.5, 0.5]}}], rfunc: r0}",
    "difference_sardf": "difference: {of: [{sphere: {radius: 0.7}}, {cylinder: {radius: 0.2}}], rfunc: sardf}",
    "complement": "complement: {of: {sphere: {radius: 0.5}}}",
    "blend": "blend: {of: [{sphere: {center: [-0.3, 0, 0], radius: 0.4}}, {sphere: {center: [0.3, 0, 0], radius: 0.4}}], a0: 0.2}",
    "offset": "offset: {distance: 0.1, of: {box: {min: [-0.4, -0.4, -0.4], max: [0.4, 0.4, 0.4]}}}",
    "morph": "morph: {from: {sphere: {radius: 0.5}}, to: {box: {min: [-0.4, -0.4, -0.4], max: [0.4, 0.4, 0.4]}}, t: 0.3}",
    "translate": "translate: {by: [0.1, 0.2, -0.1], of: {torus: {major: 0.5, minor: 0.15}}}",
    "rotate": "rotate: {axis: [1, 1, 0], angle: 30, of: {box: {min: [-0.4, -0.2, -0.3], max: [0.4, 0.2, 0.3]}}}",
    "scale": "scale: {by: [1.5, 0.8, 1.0], of: {sphere: {radius: 0.4}}}",
    "twist": "twist: {rate: 90, of: {box: {min: [-0.3, -0.1, -0.6], max: [0.3, 0.1, 0.6]}}}",
    "taper": "taper: {range: [-0.5, 0.5], scale: [0.5, 1.0], of: {cylinder: {radius: 0.4, height: 1.0}}}",
    "bend": "bend: {rate: 1.0, of: {box: {min: [-0.6, -0.1, -0.1], max: [0.6, 0.1, 0.1]}}}",
    "shell": "shell: {of: {torus: {major: 0.6, minor: 0.2}}, thickness: 0.08, side: both}",
    "tpms": 'tpms: {type: schwarz_p, cell: "0.4 + 0.1 * x", thickness: "0.03 + 0.02 * (y + 1)"}',
    "lattice": "lattice: {pattern: cubic, cell: 0.5, bounds: [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]], radius: 0.05}",
}


def job_of(tmp_path, model: str):
    cfg = tmp_path / "m.yaml"
    cfg.write_text(frep_config(model, res=16))
    return load_job(cfg)


def check_tape(job, seed: int = 0) -> pt.Tape:
    tp = pt.compile_model(job.model, job.t)
    assert tp is not None
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1.2, 1.2, (4000, 3))
    ref = job.model.evaluate(p, job.t)
    got = pt.evaluate_with(tp, p)
    ok = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(got), ok)
    np.testing.assert_allclose(got[ok], ref[ok], rtol=1e-9, atol=1e-12)
    check_gradient(tp, p)
    check_lattice(tp, rng)
    # boxes of several sizes: bounds contain the values; the specialised tape is exact there
    for size in (0.5, 0.12, 0.03):
        lo = rng.uniform(-1.2, 1.2 - size, (40, 3))
        hi = lo + size
        flo, fhi = pt.bound_with(tp, lo, hi)
        for q in range(len(lo)):
            pts = rng.uniform(lo[q], hi[q], (64, 3))
            v = pt.evaluate_with(tp, pts)
            fin = np.isfinite(v)
            assert np.all(v[fin] >= flo[q]) and np.all(v[fin] <= fhi[q]), (size, q)
            sub = specialised(tp, lo[q], hi[q])
            assert len(sub) <= len(tp)
            np.testing.assert_array_equal(pt.evaluate_with(sub, pts), v)
    return tp


def check_gradient(tp: pt.Tape, p: np.ndarray) -> None:
    """Forward-mode gradients (pt.gradient_with): the values are the tape's to the bit, and the
    gradient is the central difference (step 1e-6) to 1e-5 relative wherever both are finite,
    except at the few points within a step of a crease (min/max/abs, mesh planes): at most 1 %."""
    v, g = pt.gradient_with(tp, p)
    np.testing.assert_array_equal(v, pt.evaluate_with(tp, p))
    step = 1e-6
    fd = np.stack([(pt.evaluate_with(tp, p + step * e) - pt.evaluate_with(tp, p - step * e)) / (2 * step)
                   for e in np.eye(3)], axis=1)
    ok = np.all(np.isfinite(fd), axis=1) & np.all(np.isfinite(g), axis=1) & np.isfinite(v)
    err = np.linalg.norm(g - fd, axis=1) / np.maximum(1.0, np.linalg.norm(fd, axis=1))
    assert np.mean(err[ok] < 1e-5) >= 0.99, np.sort(err[ok])[-20:]
    assert np.mean(np.all(np.isfinite(g), axis=1)[np.isfinite(v)]) >= 0.99  # defined almost everywhere


def check_lattice(tp: pt.Tape, rng: np.random.Generator) -> None:
    """Blocks of voxel centres (eval_blocks: a clause of one or two coordinates runs once per
    distinct value of them, pt.SEPARABLE) give the point evaluator's values to the bit, NaN and
    inf included, at every block size the voxeliser offers."""
    for block, h in ((2, 0.05), (4, 0.013), (8, 0.0071)):
        blocks = rng.integers(int(-1.2 / h), int(1.2 / h) - block, (30, 3))
        got = pt.eval_blocks_with(tp, blocks, block, h)
        np.testing.assert_array_equal(got.reshape(-1), pt.evaluate_with(tp, block_points(blocks, block, h)))


def block_points(blocks: np.ndarray, block: int, h: float) -> np.ndarray:
    """World centres of the voxels of blocks (N, 3) of ``block``^3, in eval_blocks' order."""
    idx = np.stack(np.meshgrid(*[np.arange(block)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return ((np.asarray(blocks)[:, None, :] + idx[None]) * h).reshape(-1, 3)


def test_lattice_clauses_of_one_coordinate_run_once_per_value(tmp_path) -> None:
    """Costly clauses of one coordinate (|x|^e, sin z, sqrt(y + 2), 1 / (x - 0.31)) and of two
    ((x y)^0.5, NaN where x y < 0; log(z + y + 2.5), -inf or NaN below) run once per distinct
    value on a block lattice: the values are the point evaluator's to the bit (check_lattice)."""
    from pipeline.job.config import _Ctx, build_node

    raw = {"expr": "1 - abs(x)^6.67 - (x * y)^0.5 + sin(9 * z) * sqrt(y + 2) + 0.01 / (x - 0.31)"
                   " - log(z + y + 2.5) / 7"}  # not finite everywhere: a job would refuse it
    tp = pt.compile_model(build_node(raw, ("model",), _Ctx("lattice", raw, tmp_path)), 0.0)
    check_lattice(tp, np.random.default_rng(3))


def specialised(tp: pt.Tape, lo: np.ndarray, hi: np.ndarray) -> pt.Tape:
    """The tape of one box, through the same kernels the voxeliser uses."""
    n = len(tp)
    choices = np.zeros(n, np.int32)
    pt.bound_boxes(lo[None], hi[None], np.zeros(1, np.int64), np.zeros(1, np.int64), np.array([n]),
                  np.array([tp.res]), tp.op, tp.a, tp.b, tp.c, *tp.oracle.arrays(), n, np.zeros(1, np.int64),
                  choices)
    s, ln, r, op, a, b, c = pt.specialise(np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64),
                                         np.array([n]), np.array([tp.res]), tp.op, tp.a, tp.b, tp.c,
                                         np.zeros(1, np.int64), choices)
    return pt.Tape(op, a, b, c, int(r[0]), tp.oracle)


@pytest.mark.parametrize("name", sorted(NODES))
def test_every_traceable_node_conforms(tmp_path, name) -> None:
    check_tape(job_of(tmp_path, NODES[name]))


def test_every_registered_node_type_is_covered() -> None:
    from pipeline.oracles import REGISTRY

    covered = {k.split("_")[0] for k in NODES} | {"mesh", "grid", "hfrep", "component"}
    assert set(REGISTRY) <= covered, set(REGISTRY) - covered


def test_oracle_nodes_are_not_traced(tmp_path) -> None:
    """Nodes that sample a mesh's BSP-tree keep the node-by-node evaluator (reported in stats)."""
    import trimesh

    path = tmp_path / "ico.off"
    trimesh.creation.icosphere(1, 0.6).export(str(path))
    job = job_of(tmp_path, f"union: [{{mesh: {{path: {path}}}}}, {{sphere: {{radius: 0.2}}}}]")
    assert pt.compile_model(job.model, job.t) is None


def test_auto_block_follows_the_oracles(tmp_path) -> None:
    """``block: auto`` is 8 for every node type the tape records (each lowers to a tape without a
    mesh clause) and 4 once an oracle is in the tree (a min_max mesh: a BSP clause; an r0 mesh:
    not traced), decided from the node types without tracing the model."""
    import trimesh

    from pipeline.voxel.voxelise import block_for

    for name, node in NODES.items():
        job = job_of(tmp_path, node)
        tp = pt.compile_model(job.model, job.t)
        assert tp is not None and not np.any((tp.op == pt.BSP) | (tp.op == pt.BSPXY)), name
        assert block_for(job.model) == 8, name
    assert block_for(job.model, block=4) == 4  # a block that is given is kept
    path = tmp_path / "ico.off"
    trimesh.creation.icosphere(1, 0.6).export(str(path))
    for rfunc in ("min_max", "r0"):
        job = job_of(tmp_path, f"union: [{{mesh: {{path: {path}, rfunc: {rfunc}}}}}, {{sphere: {{radius: 0.2}}}}]")
        assert "_tapes" not in job.model.__dict__
        assert block_for(job.model) == 4
        assert "_tapes" not in job.model.__dict__  # nothing traced to decide


def test_union_of_many_parts_specialises_to_the_few_near_a_cell(tmp_path) -> None:
    rng = np.random.default_rng(2)
    kids = ", ".join(f"{{sphere: {{center: [{x:.3f}, {y:.3f}, {z:.3f}], radius: 0.04}}}}"
                     for x, y, z in rng.uniform(-1, 1, (500, 3)))
    job = job_of(tmp_path, f"union: {{of: [{kids}], rfunc: min_max}}")
    tp = check_tape(job)
    c = np.array([0.0, 0.0, 0.0])
    sub = specialised(tp, c - 0.05, c + 0.05)
    assert len(sub) < len(tp) / 20, (len(sub), len(tp))


def test_shared_subtrees_are_one_set_of_clauses(tmp_path) -> None:
    one = pt.compile_model(job_of(tmp_path, "sphere: {radius: 0.5}").model)
    twice = pt.compile_model(job_of(tmp_path, "union: {of: [{sphere: {radius: 0.5}}, {sphere: {radius: 0.5}}], "
                                             "rfunc: min_max}").model)
    assert len(twice) <= len(one) + 1


def test_identity_clauses_are_their_operand(tmp_path) -> None:
    """A centre at 0, a unit radius or exponent, a unit scale leave no clause (x + 0, x / 1,
    x ** 1, x * 1 are x): configs/demo.yaml's tape went from 43 to 31 clauses."""
    model = ("difference: {of: [{superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}},"
             " {box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}}], rfunc: r0}")
    tp = check_tape(job_of(tmp_path, model))
    ident = {(pt.ADDC, 0.0), (pt.MULC, 1.0), (pt.DIVC, 1.0), (pt.POWC, 1.0)}
    assert not [k for k in range(len(tp)) if (int(tp.op[k]), float(tp.c[k])) in ident]
    assert len(tp) == 32 and tp.op[-1] == pt.COMPRESS  # 31 and the job's value compression
    assert int(np.sum(tp.op == pt.POWC)) == 4  # |x|^e, |y|^e, |z|^e, F^0.15; the F^1 is gone
    assert int(np.sum(tp.op == pt.ABS)) == 3  # |x| shared by the superellipsoid and the box


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(model=tree(), seed=st.integers(0, 100))
def test_random_trees_conform(tmp_path_factory, model, seed) -> None:
    check_tape(job_of(tmp_path_factory.mktemp("t"), model), seed)


def _ico(tmp_path, name="ico.off", k=2, r=0.7):
    import trimesh

    path = tmp_path / name
    trimesh.creation.icosphere(k, r).export(str(path))
    return path


def test_min_max_mesh_is_one_oracle_clause_specialised_to_a_start_node(tmp_path) -> None:
    """A min_max BSP-field is one tape clause (pipeline.mesh.bsp_minmax's short-circuit kernels): the
    tape equals the BSP kernel to the bit, bounds hold, and a small cell on the surface starts
    from a node below the root (its voxels skip the root path and
    the subtrees the cell's bounds exclude). A torus: its tree's root is a chain of POS_ONLY nodes
    (min of planes), which a cell skips down to the first plane near it."""
    import trimesh

    from pipeline.mesh.bsp import _subtree_sizes, evaluate_tree

    path = tmp_path / "torus.off"
    trimesh.creation.torus(0.5, 0.2, major_sections=24, minor_sections=12).export(str(path))
    job = job_of(tmp_path, f"mesh: {{path: {path}, rfunc: min_max}}")
    tp = check_tape(job)
    assert tp.counts().get("bsp") == 1 and len(tp) <= 6, tp.counts()
    t = next(iter(job.model.walk())).impl.tree
    p = np.random.default_rng(3).uniform(-0.9, 0.9, (5000, 3))
    full = evaluate_tree(t, p, "min_max")  # every node, no shortcut
    np.testing.assert_array_equal(pt.evaluate_with(tp, p), full)
    c = np.array([0.7, 0.0, 0.0])
    sub = specialised(tp, c - 0.03, c + 0.03)
    start = int(sub.c[sub.op == pt.BSP][0])
    sizes = _subtree_sizes(tp.oracle.pos, tp.oracle.neg)
    assert sizes[start] < len(sizes), (sizes[start], len(sizes))
    q = np.random.default_rng(4).uniform(c - 0.03, c + 0.03, (500, 3))
    np.testing.assert_array_equal(pt.evaluate_with(sub, q), pt.evaluate_with(tp, q))


def test_meshes_in_csg_with_transforms_conform(tmp_path) -> None:
    """Two min_max meshes (one rotated, scaled, moved) with primitives: one tape holding both
    trees, equal to the node-by-node evaluation, bounds and specialisation exact."""
    a, b = _ico(tmp_path, "a.off", 2, 0.6), _ico(tmp_path, "b.off", 1, 0.4)
    moved = (f"{{rotate: {{axis: [1, 1, 0], angle: 35, of: {{scale: {{by: [1.4, 0.8, 1], of: "
             f"{{translate: {{by: [0.5, 0, 0], of: {{mesh: {{path: {b}, rfunc: min_max}}}}}}}}}}}}}}}}")
    model = (f"difference: {{of: [{{union: {{of: [{{mesh: {{path: {a}, rfunc: min_max}}}}, {moved}], "
             f"rfunc: min_max}}}}, {{cylinder: {{radius: 0.15, height: 3}}}}], rfunc: min_max}}")
    job = job_of(tmp_path, model)
    tp = check_tape(job)
    assert tp.counts().get("bsp") == 2
    trees = [n.impl.minmax_tree for n in job.model.walk() if type(n).__name__ == "Mesh"]
    assert len(tp.oracle.mode) == sum(len(t.mode) for t in trees)


def _displaced_ico(tmp_path, k: int = 3):
    """A noise-displaced icosphere (bench/mesh.py's generator): nearly convex, so its optimised
    BSP-tree is a deep chain of GENERAL nodes, the case block specialisation is for."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=k)
    u = m.vertices
    r = 0.7 * (1.0 + 0.05 * np.sin(5 * u[:, 0]) * np.sin(7 * u[:, 1]) * np.sin(6 * u[:, 2]))
    path = tmp_path / f"dico{k}.off"
    trimesh.Trimesh(u * r[:, None], m.faces, process=False).export(str(path))
    return path


def _blocks_near_surface(tp: pt.Tape, h: float, n: int, seed: int) -> np.ndarray:
    """Origins (voxel indices) of n 4^3 blocks whose voxels straddle the zero set."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1.0, 1.0, (20000, 3))
    v = pt.evaluate_with(tp, p)
    near = p[np.abs(v) < 4 * h]
    return np.floor(near[:n] / h).astype(np.int64) - 2


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10**6), h=st.sampled_from([0.004, 0.011, 0.03]))
def test_block_specialised_mesh_tree_is_exact(tmp_path, seed, h) -> None:
    """eval_blocks specialises each mesh clause's BSP-tree to the box of its block's points
    (bsp_minmax.specialise_box) before running them: the values are the unspecialised kernel's
    to the bit, for a deep-chain displaced icosphere moved by a rotation (boxes of transformed
    coordinates), at blocks on the surface and anywhere in the domain; the specialised tree of a
    surface block is a small part of the whole."""
    from pipeline.mesh.bsp_minmax import specialise_box

    path = _displaced_ico(tmp_path)
    job = job_of(tmp_path, f"rotate: {{axis: [1, 2, 0], angle: 25, of: {{mesh: {{path: {path}, rfunc: min_max}}}}}}")
    tp = pt.compile_model(job.model, 0.0)
    blocks = np.concatenate([_blocks_near_surface(tp, h, 150, seed),
                             np.random.default_rng(seed).integers(int(-1.1 / h), int(1.1 / h), (50, 3))])
    got = pt.eval_blocks_with(tp, blocks, 4, h)
    np.testing.assert_array_equal(got.reshape(-1), pt.evaluate_with(tp, block_points(blocks, 4, h)))
    o = tp.oracle
    nn = len(o.mode)
    scratch = (np.empty((nn, 3)), np.empty(nn), *(np.empty(nn, np.int64) for _ in range(3)))
    sj, sv = np.empty((3, o.depth + 2), np.int64), np.empty((4, o.depth + 2))
    c = np.array([0.7, 0.0, 0.0])
    live = 0
    root = specialise_box(*(c - 2 * h), *(c + 2 * h), nn - 1, o.normals, o.offsets, o.pos, o.neg, o.mode, 1e-14,
                          sj, sv, *scratch)
    stack = [root]
    while stack:
        j = stack.pop()
        live += 1
        stack += [int(x) for x in (scratch[2][j], scratch[3][j]) if x >= 0]
    assert live < nn / 4, (live, nn)


def test_tape_is_traced_once_per_model_and_not_pickled(tmp_path) -> None:
    """compile_model keeps the tape on the model (voxelise, bricks and components share it);
    a pickled model (sent to a worker) leaves it behind and traces its own, equal one."""
    import pickle

    job = job_of(tmp_path, NODES["union_min_max"])
    tp = pt.compile_model(job.model, job.t)
    assert pt.compile_model(job.model, job.t) is tp
    copy = pickle.loads(pickle.dumps(job.model))
    assert "_tapes" not in vars(copy)
    again = pt.compile_model(copy, job.t)
    assert again is not tp and np.array_equal(again.op, tp.op) and np.array_equal(again.c, tp.c)


def test_fused_cull_and_decide_pass_is_exact(tmp_path) -> None:
    """bound_cull_decide (one pass per descent level): the culling interval is bound_boxes's over
    the culling box, and a kept box's decisions made over its decision box (the mesh walks
    starting where the culling walk stopped) give a tape equal to the full one there, bit for
    bit. Meshes in CSG with transforms, so min/max pruning and mesh start nodes both occur."""
    # 5,120 faces: median cuts, so boxes near the surface start deep in the tree
    a, b = _ico(tmp_path, "a.off", 4, 0.6), _ico(tmp_path, "b.off", 1, 0.4)
    moved = f"{{translate: {{by: [0.4, 0.1, 0], of: {{mesh: {{path: {b}, rfunc: min_max}}}}}}}}"
    model = (f"union: {{of: [{{mesh: {{path: {a}, rfunc: min_max}}}}, {moved}, {{sphere: {{center: [-0.5, 0, 0], "
             f"radius: 0.3}}}}], rfunc: min_max}}")
    tp = pt.compile_model(job_of(tmp_path, model).model)
    rng = np.random.default_rng(7)
    n, nb = len(tp), 300
    dlo = rng.uniform(-0.9, 0.7, (nb, 3))
    dhi = dlo + rng.uniform(0.02, 0.2, (nb, 1))
    pad = rng.uniform(0.0, 0.1, (nb, 1))
    lo, hi = dlo - pad, dhi + pad
    # some decision boxes lie elsewhere than their culling box: their walks must start afresh
    far = np.arange(0, nb, 5)
    lo[far], hi[far] = dlo[far[::-1]] - pad[far], dhi[far[::-1]] + pad[far]
    one, z = np.array([n]), np.zeros(nb, np.int64)
    args = (z, np.zeros(1, np.int64), one, np.array([tp.res]), tp.op, tp.a, tp.b, tp.c, *tp.oracle.arrays(), n,
            np.arange(nb, dtype=np.int64) * n)
    ref = pt.bound_boxes(lo, hi, *args, np.zeros(nb * n, np.int32))
    choices = np.zeros(nb * n, np.int32)
    flo, fhi = pt.bound_cull_decide(lo, hi, dlo, dhi, *args, choices)
    np.testing.assert_array_equal(flo, ref[0])
    np.testing.assert_array_equal(fhi, ref[1])
    kept = np.flatnonzero(~((flo > 0) | (fhi < 0)))
    assert 20 < len(kept) < nb
    s, ln, r, op, qa, qb, qc = pt.specialise(kept, z, np.zeros(1, np.int64), one, np.array([tp.res]), tp.op, tp.a,
                                              tp.b, tp.c, np.arange(nb, dtype=np.int64) * n, choices)
    shorter = 0
    for i, q in enumerate(kept):
        sub = pt.Tape(op[s[i]:s[i] + ln[i]], qa[s[i]:s[i] + ln[i]], qb[s[i]:s[i] + ln[i]], qc[s[i]:s[i] + ln[i]],
                      int(r[i]), tp.oracle)
        pts = rng.uniform(dlo[q], dhi[q], (48, 3))
        np.testing.assert_array_equal(pt.evaluate_with(sub, pts), pt.evaluate_with(tp, pts))
        shorter += len(sub) < n or bool(np.any(sub.c[sub.op == pt.BSP] != tp.c[tp.op == pt.BSP][:1]))
    assert shorter > 0


def _clip_meets(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Independent triangle-box test: clip the triangle by the box's six halfspaces
    (Sutherland-Hodgman); something left means they meet."""
    poly = [np.asarray(v, float) for v in tri]
    for axis in range(3):
        for bound, sign in ((lo[axis], 1.0), (hi[axis], -1.0)):
            out = []
            for i in range(len(poly)):
                p, q = poly[i], poly[(i + 1) % len(poly)]
                dp, dq = sign * (p[axis] - bound), sign * (q[axis] - bound)
                if dp >= 0:
                    out.append(p)
                if (dp >= 0) != (dq >= 0):
                    out.append(p + (q - p) * (dp / (dp - dq)))
            poly = out
            if not poly:
                return False
    return True


def test_surface_bvh_query_is_exact() -> None:
    """bsp_minmax.box_near_surface (the voxeliser's cull of closed-mesh cells): with margin 0 it
    says whether some triangle meets the box, as clipping each triangle by the box does, on boxes
    of many sizes around a torus; a margin makes it say yes for a box that far from the surface."""
    import trimesh

    from pipeline.mesh.bsp_minmax import BVH_STACK, box_near_surface, surface_bvh

    m = trimesh.creation.torus(0.6, 0.25, major_sections=24, minor_sections=12)
    tris = np.ascontiguousarray(m.vertices[m.faces], dtype=np.float64)
    flat, box, kid, span = surface_bvh(tris)
    assert sorted(map(tuple, flat.reshape(-1, 3, 3).reshape(-1, 9))) == sorted(map(tuple, tris.reshape(-1, 9)))
    stack = np.empty(BVH_STACK, np.int64)
    rng = np.random.default_rng(5)
    hits = 0
    for _ in range(400):
        c = rng.uniform(-1.0, 1.0, 3)
        w = rng.uniform(0.002, 0.15, 3) * rng.choice([1.0, 3.0])
        lo, hi = c - w, c + w
        got = box_near_surface(*lo, *hi, 0.0, 0, flat, box, kid, span, stack)
        cand = tris[np.all((tris.min(axis=1) <= hi) & (tris.max(axis=1) >= lo), axis=1)]
        want = any(_clip_meets(t, lo, hi) for t in cand)
        assert got == want, (lo, hi)
        hits += want
        if not want:  # grown to reach the nearest surface point, it meets it
            cp = trimesh.proximity.closest_point(m, c[None])[0][0]
            gap = float(np.max(np.maximum(np.maximum(lo - cp, cp - hi), 0.0)))
            assert box_near_surface(*lo, *hi, gap * (1 + 1e-9) + 1e-12, 0, flat, box, kid, span, stack)
    assert 50 < hits < 350


def test_closed_mesh_cells_are_culled_by_the_surface(tmp_path) -> None:
    """A closed min_max mesh: the voxeliser keeps exactly the blocks whose band-dilated box the
    surface comes near (tape._surface_cull), not the superset the interval walk kept where the
    field's magnitude is below the distance (concave edges: 14 voxels away on this box with
    holes at 32^3). Every voxel within the band of the surface is in an evaluated block; the
    values are the walk's; an open mesh has no surface and keeps the interval walk."""
    import trimesh

    from pipeline.mesh.bsp import BSPField
    from pipeline.voxel.voxelise import sample_blocks
    from tests.test_written_grids import _box_with_holes

    mesh = _box_with_holes()
    path = tmp_path / "holes.off"
    mesh.export(str(path))
    cfg = tmp_path / "m.yaml"
    cfg.write_text(frep_config(f"mesh: {{path: {path}, rfunc: min_max}}", res=32))
    job = load_job(cfg)
    dom, band = job.domain, 3.0
    h = dom.voxel_size
    s = sample_blocks(job.model, dom.index_min, dom.index_max, h, band, 4, job.t)
    d = trimesh.proximity.closest_point(mesh, (s.blocks + 1.5) * h)[1] / h
    assert d.max() <= (band + 1.5) * np.sqrt(3) + 1e-6, d.max()  # the dilated box's farthest point
    # voxels within the band: in evaluated blocks
    rng = np.random.default_rng(2)
    surf = trimesh.sample.sample_surface(mesh, 3000, seed=3)[0]
    ijk = np.rint((surf + rng.uniform(-band * h, band * h, surf.shape)) / h).astype(np.int64)
    ijk = ijk[np.all((ijk >= dom.index_min) & (ijk <= dom.index_max), axis=1)]
    near = ijk[trimesh.proximity.closest_point(mesh, ijk * h)[1] <= band * h]
    have = {tuple(b) for b in s.blocks}
    assert len(near) > 1000 and all(tuple((v // 4) * 4) in have for v in near)
    np.testing.assert_array_equal(s.values.reshape(-1), job.model.evaluate(block_points(s.blocks, 4, h), job.t))
    # without the surface (the interval walk) far blocks are kept
    walk = load_job(cfg)
    walk.model.impl.minmax_tree.surface = None
    w = sample_blocks(walk.model, dom.index_min, dom.index_max, h, band, 4, walk.t)
    assert len(w.blocks) > len(s.blocks) and {tuple(b) for b in w.blocks} >= have
    opened = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)
    assert BSPField.from_mesh(opened, rfunc="min_max").surface is None
    assert BSPField.from_mesh(mesh, rfunc="min_max").surface is not None


@pytest.mark.parametrize("band", [1, 3])
def test_surface_culled_mesh_in_csg_written_everywhere(tmp_path, band) -> None:
    """A closed min_max mesh in CSG with primitives (cells where only the mesh is left are culled
    by its surface, the others by interval walks): every voxel of the written grid has the
    model's sign and the band is closed, at band 1 and 3."""
    from tests.test_written_grids import _box_with_holes, check_frep_everywhere

    path = tmp_path / "holes.off"
    _box_with_holes().apply_scale(0.8).export(str(path))
    model = (f"difference: {{of: [{{union: {{of: [{{mesh: {{path: {path}, rfunc: min_max}}}}, "
             f"{{sphere: {{center: [0.6, 0.5, 0.4], radius: 0.3}}}}], rfunc: min_max}}}}, "
             f"{{cylinder: {{center: [-0.4, 0, 0], radius: 0.12, axis: z}}}}], rfunc: min_max}}")
    r = check_frep_everywhere(tmp_path, frep_config(model, res=36, band=band))
    assert r["active"] > 0 and r["unclosed"] == 0 and r["wrong"] == 0


@pytest.mark.parametrize("p", [2.0, 3.0, -2.0, -3.0, 0.5, 1e20, -1e20, 2.0**60 + 2.0**8, 1e300])
def test_constant_powers_match_numpy_for_huge_exponents(p) -> None:
    """x ** p on the tape (values and interval bounds) as NumPy computes it, for exponents past
    int64 (an integer test by math.floor overflowed in Numba: (-0.5) ** 1e20 was NaN)."""
    tb = pt.TapeBuilder()
    x = tb.emit(pt.X)
    tb.emit(pt.Y), tb.emit(pt.Z)
    out = x.unary(pt.POWC, p)
    op, a, b, c, res = pt._compact(np.array(tb.op), np.array(tb.a), np.array(tb.b), np.array(tb.c, float), out.pos)
    tape = pt.Tape(op, a, b, c, res)
    xs = np.array([-2.0, -1.0, -0.5, -0.1, 0.1, 0.5, 1.0, 2.0])
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1)
    with np.errstate(all="ignore"):
        ref = np.power(xs, p)
    got = pt.evaluate_with(tape, pts)
    assert np.array_equal(np.isnan(got), np.isnan(ref)) and np.array_equal(np.isinf(got), np.isinf(ref))
    np.testing.assert_allclose(got, ref, rtol=1e-14)  # NumPy squares p = 2 exactly; pow may be 1 ulp off
    lo = np.array([[-0.5, 0, 0], [0.1, 0, 0], [-2.0, 0, 0], [-1.0, 0, 0]])
    hi = np.array([[0.5, 0, 0], [2.0, 0, 0], [-0.1, 0, 0], [1.0, 0, 0]])
    flo, fhi = pt.bound_with(tape, lo, hi)
    for q in range(len(lo)):
        v = pt.evaluate_with(tape, np.linspace(lo[q], hi[q], 101))
        v = v[np.isfinite(v)]
        assert (v >= flo[q]).all() and (v <= fhi[q]).all(), (q, flo[q], fhi[q], v.min(), v.max())


@pytest.mark.parametrize("model", [
    "difference:\n  - superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}\n"
    "  - box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}\nrfunc: r0",
    "union:\n  - sphere: {center: [0.3, 0, 0], radius: 0.5}\n  - cylinder: {radius: 0.2, axis: z}\nrfunc: min_max",
    'expr: "1e31 * (0.5 - x^2 - y^2 - z^2)"',  # values beyond FINITE_LIMIT: clamped and counted
    "mesh",
])
def test_fused_leaves_equal_blocks_then_assembly(tmp_path, model) -> None:
    """voxelise_tape (blocks evaluated, band-marked and written into their leaves in one compiled
    pass) gives assemble(sample_blocks(...))'s leaves, known voxels' values, band, proven boxes and
    statistics, on a domain whose low faces cut leaves and blocks."""
    from pipeline.voxel.voxelise import assemble, sample_blocks, voxelise_tape
    from tests.test_written_grids import _box_with_holes

    if model == "mesh":
        path = tmp_path / "holes.off"
        _box_with_holes().export(str(path))
        model = f"mesh: {{path: {path}, rfunc: min_max}}"
    cfg = tmp_path / "m.yaml"
    cfg.write_text(frep_config(model, res=37, lo=-1.13, hi=1.21))
    job = load_job(cfg)
    dom = job.domain
    assert np.any(dom.index_min % 4)  # the low faces cut blocks
    a = assemble(sample_blocks(job.model, dom.index_min, dom.index_max, dom.voxel_size, 2.5, 4, job.t),
                 dom.index_min, dom.index_max, dom.voxel_size, 2.5)
    b = voxelise_tape(pt.compile_model(job.model, job.t), dom.index_min, dom.index_max, dom.voxel_size, 2.5, 4)
    np.testing.assert_array_equal(a.blocks.origins, b.blocks.origins)
    np.testing.assert_array_equal(a.blocks.values.view(np.int32), b.blocks.values.view(np.int32))
    np.testing.assert_array_equal(a.blocks.active, b.blocks.active)
    assert a.blocks.background == b.blocks.background
    np.testing.assert_array_equal(a.inside_boxes, b.inside_boxes)
    np.testing.assert_array_equal(a.outside_boxes, b.outside_boxes)
    same = {k: v for k, v in a.stats.items() if not k.endswith("seconds")}
    assert same == {k: v for k, v in b.stats.items() if not k.endswith("seconds")}
    assert a.stats["active_voxels"] > 0 and ("1e31" not in model or a.stats["values_clamped"] > 0)


def test_specialise_shares_unchanged_tapes(tmp_path) -> None:
    """A box whose decisions change nothing points at its parent's clauses (the pool then starts
    with the parents' pool): every box's tape has the clauses that specialising it alone gives,
    and the final pool of the demo's r0 model is smaller than one copy per block."""
    from pipeline.voxel import voxelise as vx

    cfg = tmp_path / "m.yaml"
    cfg.write_text(frep_config(
        "difference:\n  - superellipsoid: {radii: [1, 1, 1], exponents: [0.3, 0.3]}\n"
        "  - union:\n    - box: {min: [-1.3, -0.02, -1.3], max: [1.3, 0.02, 1.3]}\n"
        "    - sphere: {center: [0.5, 0.5, 0], radius: 0.3}\n    rfunc: min_max\nrfunc: r0", res=48))
    job = load_job(cfg)
    calls = []
    orig = pt.specialise

    def spy(keep, tape_of, start, length, res, op, a, b, c, choff, choices):
        out = orig(keep, tape_of, start, length, res, op, a, b, c, choff, choices)
        calls.append(((keep, tape_of, start, length, res, op, a, b, c, choff, choices), out))
        return out

    vx.specialise = spy
    try:
        dom = job.domain
        _, pool = vx.enumerate_cells_tape(pt.compile_model(job.model, job.t), dom.index_min, dom.index_max,
                                          dom.voxel_size, 3.0, 4)
    finally:
        vx.specialise = orig
    shared = 0
    for args, (s, ln, r, op, a, b, c) in calls:
        keep = args[0]
        shared += int(len(op) < ln.sum() or np.any(s[1:] < s[:-1]))
        for i in range(len(keep)):
            one = orig(keep[i:i + 1], *args[1:])
            assert ln[i] == one[1][0] and r[i] == one[2][0]
            sl = slice(s[i], s[i] + ln[i])
            for got, want in zip((op, a, b, c), one[3:], strict=True):
                np.testing.assert_array_equal(got[sl], want)
    assert shared > 0  # some level shared its parents' tapes
    assert len(pool.op) < pool.length.sum()


def test_lattice_descent_pools_are_exact_and_compact(tmp_path) -> None:
    """A dense strut lattice (the lattice node, octet) through voxelise's descent: the tape of
    every block (specialised level by level, each from its parent's) gives the whole tape's
    values at the block's voxel centres to the bit, its clauses are far fewer than the whole
    tape's, and every pool keeps the storage types (int8 opcodes, int32 operands), so no kernel
    compiles a second signature. Calling specialise again with the same decisions (the flags of
    the first call's count left in them) gives the same pool."""
    from pipeline.voxel import voxelise as vx

    job = job_of(tmp_path, "lattice: {pattern: octet, cell: 0.5, bounds: [[-1, -1, -1], [1, 1, 1]], radius: 0.04}")
    tp = pt.compile_model(job.model, 0.0)
    assert tp.op.dtype == pt.OP_T and tp.a.dtype == pt.IX_T and tp.b.dtype == pt.IX_T
    calls = []
    orig = pt.specialise

    def spy(*args):
        out = orig(*args)
        calls.append((args, out))
        return out

    vx.specialise = spy
    try:
        h = 0.03
        lo, hi = np.full(3, int(-1.1 / h)), np.full(3, int(1.1 / h))
        levels, pool = vx.enumerate_cells_tape(tp, lo, hi, h, 3.0, 8)
    finally:
        vx.specialise = orig
    assert len(levels.blocks) > 100 and pool.length.mean() < len(tp) / 10
    for args, out in calls:
        assert out[3].dtype == pt.OP_T and out[4].dtype == pt.IX_T and out[5].dtype == pt.IX_T
        again = orig(*args)
        for x, y in zip(out, again, strict=True):
            np.testing.assert_array_equal(x, y)
    pick = np.random.default_rng(5).choice(len(levels.blocks), 40, replace=False)
    pts = block_points(levels.blocks[pick], 8, h)
    got = pool.evaluate(pts, np.repeat(pick, 512))
    np.testing.assert_array_equal(got, pt.evaluate_with(tp, pts))
