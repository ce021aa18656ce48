"""The Python API (package frepvdb) and the YAML loader build the same models: same values,
same compiled tapes, same written grids; operators, chaining, to_yaml round trips, run()."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import frepvdb as fv
from pipeline.cli import main
from pipeline.io.vdbgrids import vdb
from pipeline.job.config import load_job
from pipeline.model import tape as pt
from pipeline.oracles import REGISTRY

BOUNDS = [[-1.2, -1.2, -1.2], [1.2, 1.2, 1.2]]


def config_text(model_yaml: str, res: int = 24) -> str:
    body = "\n".join("  " + line for line in model_yaml.strip().splitlines())
    return (f"name: job\ndomain: {{bounds: {BOUNDS}, resolution: {res}}}\nmodel:\n{body}\n"
            "stages:\n  - voxelise: {band: 3}\n  - export: {vdb: true, report: false}\n")


def yaml_job(tmp_path, model_yaml: str, res: int = 24):
    cfg = tmp_path / "job.yaml"
    cfg.write_text(config_text(model_yaml, res))
    return load_job(cfg)


def assert_same_model(shape: fv.Shape, job, seed: int = 0) -> None:
    """Same tape arrays (bit for bit), the same compiled values (bit for bit) and the same NumPy
    reference values at random points.

    The NumPy reference (``Node.evaluate``) is compared to 4 ulp of the value's scale, not to the
    bit: NumPy's SIMD transcendental ufuncs on strided column views are not bit-reproducible from
    call to call (a full ``make test`` run once gave 1.1e-16 on 8 of 2000 points of
    ``sin(9 * x)`` for two identical models). The compiled tape is what the grids are written
    from, and it is deterministic, so it is held to the bit."""
    node = shape.node(job.domain, job.t)
    a, b = pt.compile_model(node, job.t), pt.compile_model(job.model, job.t)
    assert a is not None and b is not None
    for k in ("op", "a", "b", "c"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    assert a.res == b.res
    p = np.random.default_rng(seed).uniform(-1.3, 1.3, (2000, 3))
    np.testing.assert_array_equal(pt.evaluate_with(a, p), pt.evaluate_with(b, p))
    va, vb = node.evaluate(p), job.model.evaluate(p)
    np.testing.assert_array_equal(np.isfinite(va), np.isfinite(vb))
    fin = np.isfinite(va)
    tol = 4 * np.finfo(np.float64).eps * np.maximum(1.0, np.abs(va[fin]))
    assert np.all(np.abs(va[fin] - vb[fin]) <= tol), np.abs(va[fin] - vb[fin]).max()


# --- random small trees, written twice: once with the API, once by hand in YAML ---------------

coord = st.floats(-0.5, 0.5).map(lambda v: round(v, 3))
size = st.floats(0.2, 0.7).map(lambda v: round(v, 3))
FAMILIES = ["r0", "min_max", "sardf"]


@st.composite
def leaf(draw):
    c = [draw(coord) for _ in range(3)]
    r = draw(size)
    kind = draw(st.sampled_from(["sphere", "box", "torus", "cylinder", "expr"]))
    if kind == "sphere":
        return fv.sphere(r, c), f"{{sphere: {{center: {c}, radius: {r}}}}}"
    if kind == "box":
        lo, hi = [v - r for v in c], [v + r for v in c]
        return fv.box(lo, hi), f"{{box: {{min: {lo}, max: {hi}}}}}"
    if kind == "torus":
        return fv.torus(r, r / 3, c, axis="y"), f"{{torus: {{center: {c}, major: {r}, minor: {r / 3}, axis: y}}}}"
    if kind == "cylinder":
        return fv.cylinder(r, c, height=2 * r), f"{{cylinder: {{center: {c}, radius: {r}, height: {2 * r}}}}}"
    f = f"{r} - x^2 - y^2 - z^2 + 0.1 * sin(9 * x)"
    return fv.expr(f), f'{{expr: "{f}"}}'


@st.composite
def tree(draw, depth: int = 0):
    if depth >= 2 or draw(st.booleans()):
        return draw(leaf())
    (a, ya), (b, yb) = draw(tree(depth + 1)), draw(tree(depth + 1))
    kind = draw(st.sampled_from(["|", "&", "-", "~", "union", "translate", "rotate", "scale", "twist", "offset",
                                 "blend"]))
    fam = draw(st.sampled_from(FAMILIES))
    v = [draw(coord) for _ in range(3)]
    if kind == "|":
        return a | b, f"{{union: [{ya}, {yb}]}}"
    if kind == "&":
        return a & b, f"{{intersection: [{ya}, {yb}]}}"
    if kind == "-":
        return a - b, f"{{difference: [{ya}, {yb}]}}"
    if kind == "~":
        return ~a, f"{{complement: {{of: {ya}}}}}"
    if kind == "union":
        return fv.union(a, b, rfunc=fam), f"{{union: {{of: [{ya}, {yb}], rfunc: {fam}}}}}"
    if kind == "translate":
        return a.translate(v), f"{{translate: {{by: {v}, of: {ya}}}}}"
    if kind == "rotate":
        return a.rotate(35, v if any(v) else "x"), f"{{rotate: {{angle: 35, axis: {v if any(v) else 'x'}, of: {ya}}}}}"
    if kind == "scale":
        return a.scale(1.3), f"{{scale: {{by: 1.3, of: {ya}}}}}"
    if kind == "twist":
        return a.twist(60, axis="x"), f"{{twist: {{rate: 60, axis: x, of: {ya}}}}}"
    if kind == "offset":
        return a.offset(0.05), f"{{offset: {{of: {ya}, distance: 0.05}}}}"
    return a.blend(b, a0=0.1, rfunc=fam), f"{{blend: {{of: [{ya}, {yb}], a0: 0.1, rfunc: {fam}}}}}"


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(pair=tree())
def test_api_and_yaml_build_identical_tapes_and_values(tmp_path_factory, pair) -> None:
    shape, text = pair
    tmp = tmp_path_factory.mktemp("api")
    assert_same_model(shape, yaml_job(tmp, text))  # hand-written YAML
    assert_same_model(shape, yaml_job(tmp, shape.to_yaml()))  # the API's own YAML
    assert fv.load(shape.to_yaml()) == shape


def test_operator_precedence_and_chaining() -> None:
    a, b, c = fv.sphere(0.5), fv.box([-0.4] * 3, [0.4] * 3), fv.cylinder(0.2)
    assert (a | b & c) == fv.union(a, fv.intersection(b, c))  # & binds tighter than |
    assert (a - b | c) == fv.union(fv.difference(a, b), c)  # - tighter than |
    assert (a - b - c) == fv.difference(fv.difference(a, b), c)  # left to right
    assert (~a & b) == fv.intersection(fv.complement(a), b)  # ~ binds tightest
    chained = a.translate([1, 0, 0]).rotate(90, "z").scale(2)
    assert chained == fv.scale(fv.rotate(fv.translate(a, [1, 0, 0]), 90, "z"), 2)
    # the chain applies in order: translate first, so the centre lands at rotate(x) * 2 = (0, 2, 0)
    assert chained.evaluate([0, 2, 0]) == pytest.approx(1.0)
    assert chained.evaluate([2, 0, 0]) < 0


def test_every_node_type_is_a_function_and_single_child_nodes_are_methods() -> None:
    for kind, cls in REGISTRY.items():
        assert callable(getattr(fv, kind)), kind
        if cls.child_fields == ("of",):
            assert callable(getattr(fv.Shape, kind)), kind


def test_evaluate_and_bound_shapes() -> None:
    s = fv.sphere(1.0, [0.5, 0, 0])
    assert s.evaluate([0.5, 0, 0]) == pytest.approx(1.0)
    np.testing.assert_allclose(s.evaluate(np.array([[0.5, 0, 0], [2.5, 0, 0]])), [1.0, -1.0])
    assert s([[1.5, 0, 0]]) == pytest.approx([0.0])
    lo, hi = s.bound([0.4, -0.1, -0.1], [0.6, 0.1, 0.1])
    assert lo <= 1.0 - np.sqrt(0.03) + 1e-12 and hi >= 1.0 and lo < hi
    rng = np.random.default_rng(1)
    blo = rng.uniform(-1, 1, (50, 3))
    bhi = blo + 0.3
    flo, fhi = (s - fv.box([0, 0, 0], [1, 1, 1])).bound(blo, bhi)
    for q in range(50):
        v = (s - fv.box([0, 0, 0], [1, 1, 1])).evaluate(rng.uniform(blo[q], bhi[q], (40, 3)))
        assert np.all(v >= flo[q]) and np.all(v <= fhi[q])


def test_bad_parameters_get_the_config_messages() -> None:
    with pytest.raises(fv.ConfigError, match=r"sphere.radius: must be > 0"):
        fv.sphere(-1)
    with pytest.raises(fv.ConfigError, match=r"box.*min must be below max"):
        fv.box([1, 1, 1], [0, 0, 0])
    with pytest.raises(fv.ConfigError, match=r"expr.formula: bad formula: column 7: expected"):
        fv.expr("1 + (x")
    with pytest.raises(fv.ConfigError, match=r"unknown key 'raduis' \(did you mean 'radius'\?\)"):
        fv.sphere(raduis=1)
    with pytest.raises(TypeError, match="positional"):
        fv.sphere(1, [0, 0, 0], 3)


def test_voxelise_in_memory_equals_the_written_grid(tmp_path) -> None:
    shape = (fv.sphere(0.7) - fv.box([-0.2, -1, -1], [0.2, 1, 1])).twist(40)
    grid = fv.voxelise(shape, BOUNDS, resolution=32, band=2)
    assert isinstance(grid, vdb.FloatGrid) and grid.name == "frep"
    (manifest,) = fv.run(fv.config(shape, BOUNDS, resolution=32, stages=[{"voxelise": {"band": 2}},
                                                                           {"export": {"report": False}}]),
                         out=tmp_path / "out")
    written = vdb.read(str(tmp_path / "out" / "model" / "model.vdb"), "frep")
    assert grid.activeVoxelCount() == written.activeVoxelCount() == manifest["grids"]["frep"]["active_voxels"] > 0
    lo, hi = written.evalActiveVoxelBoundingBox()
    shape_ = tuple(h - l + 1 for l, h in zip(lo, hi, strict=True))
    a, b = np.zeros(shape_, np.float32), np.zeros(shape_, np.float32)
    grid.copyToArray(a, lo)
    written.copyToArray(b, lo)
    np.testing.assert_array_equal(a, b)
    assert grid.transform.voxelSize()[0] == pytest.approx(2.4 / 32)


def test_run_a_config_file_with_overrides(tmp_path) -> None:
    cfg = tmp_path / "part.yaml"
    cfg.write_text(config_text("{sphere: {radius: 0.5}}", res=16))
    (m,) = fv.run(cfg, out=tmp_path / "out", overrides=["domain.resolution=40", "model.sphere.radius=0.6"])
    assert m["domain"]["dims"] == [41, 41, 41]
    g = vdb.read(str(tmp_path / "out" / "job" / "job.vdb"), "frep")
    acc = g.getConstAccessor()
    h = 2.4 / 40
    assert acc.getValue((round(0.55 / h), 0, 0)) > 0 > acc.getValue((round(0.65 / h), 0, 0))  # radius 0.6
    with pytest.raises(fv.ConfigError, match=r"--set stages\[0\].voxelise.band=0: must be > 0"):
        fv.run(cfg, out=tmp_path / "out", overrides=["stages[0].voxelise.band=0"])


def test_mesh_shapes_keep_absolute_paths_in_yaml(tmp_path, monkeypatch) -> None:
    import trimesh

    trimesh.creation.icosphere(2, 0.5).export(str(tmp_path / "ball.off"))
    monkeypatch.chdir(tmp_path)
    s = fv.mesh("ball.off", rfunc="min_max") | fv.sphere(0.2, [0.5, 0, 0])
    assert str(tmp_path / "ball.off") in s.to_yaml()
    elsewhere = tmp_path / "sub"
    elsewhere.mkdir()
    job = yaml_job(elsewhere, s.to_yaml())
    p = np.random.default_rng(3).uniform(-0.8, 0.8, (500, 3))
    np.testing.assert_array_equal(s.node(job.domain).evaluate(p), job.model.evaluate(p))


# --- the docs' examples run (docs/python-api.md, docs/coming-from.md, README.md) --------------

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "docs" / "python-api.md", ROOT / "docs" / "coming-from.md", ROOT / "README.md"]


def doc_examples() -> list[tuple[str, str, str]]:
    """(id, language, code) of every ```python / ```sh / ```yaml block that starts with
    '# example: <name>' in the API docs and the README."""
    out = []
    for doc in DOCS:
        for lang, code in re.findall(r"```(python|sh|yaml)\n(.*?)```", doc.read_text(), flags=re.S):
            m = re.match(r"# example: (\w+)", code)
            if m:
                out.append((f"{doc.stem}:{m.group(1)}", lang, code))
    return out


def test_api_docs_have_examples() -> None:
    ids = {i for i, _, _ in doc_examples()}
    for want in ("python-api:operators", "python-api:voxelise_and_save", "coming-from:vdb_tool",
                 "coming-from:fogleman", "coming-from:ntop_infill", "README:python"):
        assert want in ids, want


@pytest.mark.parametrize("name, lang, code", doc_examples(), ids=[i for i, _, _ in doc_examples()])
def test_doc_example_runs(tmp_path, monkeypatch, name, lang, code) -> None:
    import trimesh

    monkeypatch.chdir(tmp_path)
    trimesh.creation.icosphere(3, 0.5).export("part.stl")  # the docs' part.stl: a closed mesh
    if lang == "python":
        exec(compile(code, name, "exec"), {"__name__": "__doc_example__"})  # noqa: S102 - our own docs
    elif lang == "sh":
        lines = [ln for ln in code.splitlines() if ln.startswith("frepvdb ")]
        assert lines
        for line in lines:
            assert main(shlex.split(line)[1:]) == 0, line
    else:
        (tmp_path / "job.yaml").write_text(code)
        assert main(["run", "job.yaml", "--out", "outputs"]) == 0
        assert list((tmp_path / "outputs").glob("*/manifest.json"))
