"""Issue 17: every bad input gets one clear line and exit 2 -- encodings, recursion, corrupt
files, absurd sizes, alias bombs. No traceback, no crash, bounded time and memory.

Configs are validated in-process (``pipeline.cli.main``); inputs that could crash the
interpreter or exhaust memory run the CLI in a subprocess with an address-space limit.
"""

from __future__ import annotations

import random
import resource
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.cli import main

GOOD = """name: good
domain:
  bounds: [[-1, -1, -1], [1, 1, 1]]
  resolution: 24
model:
  union:
    - sphere: {center: [-0.3, 0, 0], radius: 0.4}
    - sphere: {center: [0.3, 0, 0], radius: 0.4}
stages:
  - voxelise: {band: 3}
  - export: {vdb: true}
"""
MAX_MESSAGE = 400  # characters of one error line
GIB = 2**30


def good(old: str, new: str) -> str:
    """GOOD with the first ``old`` replaced by ``new``."""
    assert old in GOOD
    return GOOD.replace(old, new, 1)


def check_one_line(err: str, words: list[str]) -> None:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert len(lines[0]) <= MAX_MESSAGE, lines[0][:500]
    for w in words:
        assert w in lines[0], (w, lines[0])


def validate(tmp_path: Path, capsys, content: str | bytes, name: str = "bad.yaml") -> tuple[int, str, float]:
    cfg = tmp_path / name
    cfg.write_bytes(content if isinstance(content, bytes) else content.encode())
    start = time.perf_counter()
    code = main(["validate", str(cfg)])
    return code, capsys.readouterr().err, time.perf_counter() - start


def run_cli(args: list[str], cwd: Path, memory: int = 3 * GIB, timeout: float = 60) -> tuple[subprocess.CompletedProcess, float]:
    """The CLI in a child process under an address-space limit (a crash or an allocation stays there)."""
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))

    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=cwd, capture_output=True, text=True,
                          errors="replace", timeout=timeout, preexec_fn=limit)
    return proc, time.perf_counter() - start


# --- configs that are not UTF-8, or not plain YAML ----------------------------------------------

ENCODINGS = [
    ("latin-1 comment", b"# caf\xe9\n" + GOOD.encode(), ["bad.yaml:1", "not UTF-8", "0xe9", "byte offset 5"]),
    ("utf-16", GOOD.encode("utf-16"), ["bad.yaml:1", "UTF-16"]),
    ("random bytes", bytes(random.Random(7).randrange(128, 256) for _ in range(600)), ["bad.yaml:1", "not UTF-8"]),
    ("latin-1 on line 7", GOOD.replace("radius: 0.4}\n    - sphere", "radius: 0.4} # \xe9\n    - sphere", 1)
     .encode("latin-1"), ["bad.yaml:7", "not UTF-8"]),
    ("control character", GOOD.replace("name: good", "name: go\x01od").encode(), ["bad.yaml:1", "control character"]),
    ("list as a key", b"{[1, 2]: 3}\n", ["bad.yaml:1", "a key must be a name or a number, found a list"]),
    ("mapping as a key", b"? {a: 1}\n: 2\n", ["bad.yaml:1", "found a mapping"]),
    ("recursive alias", b"a: &x [1, *x]\n", ["bad.yaml:1", "recursive"]),
]


@pytest.mark.parametrize("label, content, words", ENCODINGS, ids=[e[0] for e in ENCODINGS])
def test_encodings_and_keys(tmp_path, capsys, label, content, words):
    code, err, seconds = validate(tmp_path, capsys, content)
    assert code == 2
    check_one_line(err, words)
    assert seconds < 5


# --- limits: nesting, aliases, size, formulas, frames, children ------------------------------------

BOMB = "\n".join(
    [f"l0: &l0 [{', '.join(['lol'] * 9)}]"]
    + [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 9)]) + "\n"


def model(node: str) -> str:
    return GOOD.replace("""  union:
    - sphere: {center: [-0.3, 0, 0], radius: 0.4}
    - sphere: {center: [0.3, 0, 0], radius: 0.4}
""", f"  {node}\n")


LIMITS = [
    ("nested 130 deep", "a: " + "[" * 130 + "]" * 130 + "\n", 1, ["nested deeper than 100 levels", "limit"]),
    ("alias bomb", BOMB, 6, ["more than 250,000 values once aliases are expanded"]),
    ("many aliases", "a: &a 1\nb: [" + ", ".join(["*a"] * 1001) + "]\n", 2, ["more than 1000 aliases"]),
    ("formula of 1000 terms", model('expr: "0.5' + " - x*x/1000" * 1000 + '"'), 6, ["good"]),
    ("1000 nested parentheses", model('expr: "' + "(" * 1000 + "1 - x" + ")" * 1000 + '"'), 6,
     ["model.expr: bad formula", "nested deeper than 60 levels"]),
    ("10000 unary minuses", model('expr: "' + "-" * 10000 + '(x*x - 0.25)"'), 6, ["good"]),
    ("right-nested powers", model('expr: "' + "x^" * 500 + 'x"'), 6, ["nested deeper than 60 levels"]),
    ("formula too long", model('expr: "1' + " + 0" * 6000 + '"'), 6, ["formula too long", "24,001 characters",
                                                                     "limit is 20,000"]),
    ("frames count", GOOD + "frames: {count: 100000}\n", 12, ["frames.count: at most 10,000 frames", "100,000"]),
    ("children per node", model("union: [" + ", ".join(["{expr: x}"] * 50_001) + "]"), 6,
     ["model.union: more than 50,000 children in one node (the limit)"]),
]


@pytest.mark.parametrize("label, text, line, words", LIMITS, ids=[x[0] for x in LIMITS])
def test_limits(tmp_path, capsys, label, text, line, words):
    code, err, seconds = validate(tmp_path, capsys, text)
    if words == ["good"]:  # within the limits: it validates
        assert code == 0, err
    else:
        assert code == 2
        check_one_line(err, [f"bad.yaml:{line}", *words])
    assert seconds < 6


def test_config_file_size_limit_refuses_before_parsing(tmp_path):
    big = GOOD + "junk: [" + "1, " * (18 * 2**20) + "]\n"  # a 54 MB list under an unknown key
    (tmp_path / "big.yaml").write_text(big)
    proc, seconds = run_cli(["validate", "big.yaml"], tmp_path, memory=2 * GIB)
    assert proc.returncode == 2
    check_one_line(proc.stderr, ["big.yaml", "config file too large", "the limit is 2,097,152"])
    assert seconds < 10


def test_unknown_key_over_a_large_list_is_refused_quickly(tmp_path, capsys):
    code, err, seconds = validate(tmp_path, capsys, GOOD + "junk: [" + "1, " * 100_000 + "]\n")
    assert code == 2
    check_one_line(err, ["bad.yaml:12 junk: unknown key 'junk'"])
    assert seconds < 5


# --- domains, numbers and vectors ---------------------------------------------------------------------

VALUES = [
    ("voxel_size inf", good("resolution: 24", "voxel_size: .inf"), 4, "domain.voxel_size: must be a finite number"),
    ("voxel_size nan", good("resolution: 24", "voxel_size: .nan"), 4, "domain.voxel_size: must be a finite number"),
    ("resolution 1.2e+29", good("resolution: 24", "resolution: 1.2e+29"), 4, "domain.resolution: must be a smaller number"),
    ("resolution above 2^30", good("resolution: 24", "resolution: 2000000000"), 4,
     "domain.resolution: must be <= 1073741824"),
    ("tiny voxel size", good("resolution: 24", "voxel_size: 1.0e-12"), 4,
     "domain.voxel_size: index coordinates exceed OpenVDB's 32-bit range"),
    ("radius true", good("radius: 0.4", "radius: true"), 7, "model.union[0].sphere.radius: must be a number, not true/false"),
    ("band false", good("band: 3", "band: false"), 10, "stages[0].voxelise.band: must be a number, not true/false"),
    ("resolution true", good("resolution: 24", "resolution: true"), 4,
     "domain.resolution: must be a number, not true/false"),
    ("center true", good("center: [-0.3, 0, 0]", "center: [true, 0, 0]"), 7,
     "model.union[0].sphere.center[0]: must be a number, not true/false"),
    ("box max of two", model("box: {min: [0, 0, 0], max: [0.8, 0.8]}"), 6,
     "model.box.max: must be three numbers [x, y, z], got 2"),
    ("box max of four", model("box: {min: [0, 0, 0], max: [1, 1, 1, 1]}"), 6,
     "model.box.max: must be three numbers [x, y, z], got 4"),
    ("bounds of one corner", good("[[-1, -1, -1], [1, 1, 1]]", "[[-1, -1, -1]]"), 3,
     "domain.bounds: must be a list of 2 items, got 1"),
    ("half_float unknown grid", good("vdb: true", "half_float: [nosuchgrid]"), 11,
     "stages[1].export.half_float[0]: no stage before export makes a grid named 'nosuchgrid' (grids here: frep)"),
    ("half_float grid of a later stage", good("vdb: true", "half_float: [surface]"), 11,
     "stages[1].export.half_float[0]: no stage before export makes a grid named 'surface'"),
    ("half_float grid not written", GOOD.replace("  - export: {vdb: true}", "  - components: {}\n"
                                                 "  - export: {grids: [frep], half_float: [frep, component]}"), 12,
     "stages[2].export.half_float[1]: grid 'component' is not in export.grids, so it is not written"),
    ("export grids unknown", good("vdb: true", "grids: [frep, hfrpe]"), 11,
     "stages[1].export.grids[1]: no stage before export makes a grid named 'hfrpe'"),
    ("parameters a list", model("sphere: [1, 2]"), 6, "model.sphere: parameters of sphere must be a mapping, got a list"),
    ("parameters a boolean", model("offset: true"), 6,
     "model.offset: parameters of offset must be a mapping, got true (a boolean)"),
]


@pytest.mark.parametrize("label, text, line, words", VALUES, ids=[v[0] for v in VALUES])
def test_values_are_checked_at_validation(tmp_path, capsys, label, text, line, words):
    code, err, seconds = validate(tmp_path, capsys, text)
    assert code == 2, err
    check_one_line(err, [f"bad.yaml:{line} {words}"])
    for internal in ("LineList", "LineDict", "NoneType", "tuple[", "dict["):
        assert internal not in err
    assert seconds < 5


def test_blend_takes_the_list_shorthand(tmp_path, capsys):
    code, err, _ = validate(tmp_path, capsys, model(
        "blend: [{sphere: {center: [-0.3, 0, 0], radius: 0.4}}, {sphere: {center: [0.3, 0, 0], radius: 0.4}}]"))
    assert code == 0, err


def test_resolution_of_a_billion_is_refused_by_its_estimate(tmp_path):
    (tmp_path / "bad.yaml").write_text(good("resolution: 24", "resolution: 1000000000"))
    proc, seconds = run_cli(["validate", "bad.yaml"], tmp_path, memory=2 * GIB)
    assert proc.returncode == 2
    check_one_line(proc.stderr, ["bad.yaml:4 domain.resolution: this domain needs an estimated", "GiB available"])
    assert seconds < 10


# --- meshes -------------------------------------------------------------------------------------------

TETRA_OFF = "OFF\n# {comment}\n4 4 0\n{v}\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 3 1\n3 0 2 3\n3 1 3 2\n"
TETRA_OBJ = "# {comment}\nv {v}\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
TETRA_STL = ("solid t {comment}\n" + "".join(
    f"facet normal 0 0 0\nouter loop\nvertex {a}\nvertex {b}\nvertex {c}\nendloop\nendfacet\n"
    for a, b, c in [("{v}", "0 1 0", "1 0 0"), ("{v}", "1 0 0", "0 0 1"), ("{v}", "0 0 1", "0 1 0"),
                    ("1 0 0", "0 1 0", "0 0 1")]) + "endsolid t\n")
TETRA_PLY = ("ply\nformat ascii 1.0\ncomment {comment}\nelement vertex 4\nproperty float x\nproperty float y\n"
             "property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n"
             "{v}\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
MESHES = {"off": TETRA_OFF, "obj": TETRA_OBJ, "stl": TETRA_STL, "ply": TETRA_PLY}


def mesh_config(tmp_path: Path, suffix: str, content: bytes, extra: str = "") -> Path:
    (tmp_path / f"m.{suffix}").write_bytes(content)
    cfg = tmp_path / "mesh.yaml"
    cfg.write_text(model(f"mesh: {{path: m.{suffix}{extra}}}").replace("[[-1, -1, -1], [1, 1, 1]]",
                                                                        "[[-0.5, -0.5, -0.5], [1.5, 1.5, 1.5]]"))
    return cfg


@pytest.mark.parametrize("suffix", sorted(MESHES))
def test_text_mesh_with_a_latin1_byte_loads(tmp_path, capsys, suffix):
    content = MESHES[suffix].format(comment="caf\xe9", v="0 0 0").encode("latin-1")
    cfg = mesh_config(tmp_path, suffix, content)
    code = main(["validate", str(cfg)])
    assert code == 0, capsys.readouterr().err


BAD_MESHES = [
    ("off", "garbage", lambda: bytes(random.Random(3).randrange(256) for _ in range(2000)), "", ["not a mesh"]),
    ("obj", "text without geometry", lambda: b"hello\nworld\n", "", ["not a mesh", "no vertices and no faces"]),
    ("off", "nan vertex", lambda: TETRA_OFF.format(comment="x", v="nan 0 0").encode(), ", allow_open: true",
     ["mesh with problems", "not finite", "vertex 0"]),
    ("obj", "1e30 coordinates", lambda: TETRA_OBJ.format(comment="x", v="1e30 0 0").encode(), ", allow_open: true",
     ["mesh with problems", "1e+30", "limit"]),
    ("stl", "a folder", None, "", ["is a folder"]),
]


@pytest.mark.parametrize("suffix, label, content, extra, words", BAD_MESHES, ids=[b[1] for b in BAD_MESHES])
def test_bad_meshes(tmp_path, capsys, suffix, label, content, extra, words):
    if content is None:
        (tmp_path / f"m.{suffix}").mkdir()
        cfg = tmp_path / "mesh.yaml"
        cfg.write_text(model(f"mesh: {{path: m.{suffix}}}"))
    else:
        cfg = mesh_config(tmp_path, suffix, content(), extra)
    assert main(["validate", str(cfg)]) == 2
    err = capsys.readouterr().err
    check_one_line(err, ["mesh.yaml:6 model.mesh:", *words])
    assert "charset" not in err and "No module" not in err


# --- collide ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("tolerance, words", [
    ("inf", ["--tolerance must be a finite number > 0, got inf"]),
    ("nan", ["--tolerance must be a finite number > 0, got nan"]),
    ("0", ["--tolerance must be a finite number > 0, got 0"]),
    ("-1", ["--tolerance must be a finite number > 0, got -1"]),
    ("1e-300", ["--tolerance 1e-300 is finer than the limit"]),
])
def test_collide_tolerance(tmp_path, capsys, tolerance, words):
    cfg = tmp_path / "a.yaml"
    cfg.write_text(GOOD)
    start = time.perf_counter()
    assert main(["collide", str(cfg), str(cfg), f"--tolerance={tolerance}"]) == 2
    check_one_line(capsys.readouterr().err, words)
    assert time.perf_counter() - start < 5


# --- info on files that are not good .vdb files -------------------------------------------------------


@pytest.fixture(scope="module")
def good_vdb(tmp_path_factory) -> bytes:
    out = tmp_path_factory.mktemp("vdb")
    (out / "good.yaml").write_text(GOOD)
    assert main(["run", str(out / "good.yaml"), "--out", str(out / "out")]) == 0
    return (out / "out" / "good" / "good.vdb").read_bytes()


def _flipped(data: bytes, seed: int, flips: int) -> bytes:
    r, out = random.Random(seed), bytearray(data)
    for _ in range(flips):
        i = r.randrange(8, len(out))
        out[i] ^= 1 << r.randrange(8)
    return bytes(out)


def test_info_good_file(tmp_path, good_vdb):
    (tmp_path / "g.vdb").write_bytes(good_vdb)
    proc, _ = run_cli(["info", "g.vdb"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "grid 'frep'" in proc.stdout


def test_info_refuses_damaged_headers_with_the_byte_offset(tmp_path, good_vdb):
    cases = [
        ("truncated.vdb", good_vdb[: len(good_vdb) // 2], ["truncated.vdb: byte", "file is truncated", "ends at byte"]),
        ("header.vdb", good_vdb[:100], ["header.vdb: byte", "truncated or corrupt", "runs past the end"]),
        ("magic.vdb", b"XDB " + good_vdb[4:], ["magic.vdb: byte 0: not an OpenVDB file"]),
        ("empty.vdb", b"", ["empty.vdb: byte 0: not an OpenVDB file"]),
        ("count.vdb", good_vdb[:57] + struct.pack("<i", -5) + good_vdb[61:], ["count.vdb: byte 57: corrupt header"]),
        ("text.vdb", b"hello, I am not a grid\n" * 10, ["text.vdb: byte 0"]),
    ]
    for name, content, words in cases:
        (tmp_path / name).write_bytes(content)
        proc, seconds = run_cli(["info", name], tmp_path, memory=2 * GIB)
        assert proc.returncode == 2, (name, proc.stderr)
        check_one_line(proc.stderr, words)
        assert seconds < 10


def test_info_on_bit_flipped_files_never_crashes(tmp_path, good_vdb):
    """Flipped bits anywhere: exit 0 (the flip was harmless) or 2, one short line, never a
    signal or a traceback -- OpenVDB may crash, but in the child process of `info`."""
    codes = []
    for seed in range(8):
        (tmp_path / "f.vdb").write_bytes(_flipped(good_vdb, seed, flips=1 + seed * 5))
        proc, seconds = run_cli(["info", "f.vdb"], tmp_path, memory=2 * GIB)
        assert proc.returncode in (0, 2), (seed, proc.returncode, proc.stderr[-500:])
        if proc.returncode == 2:
            check_one_line(proc.stderr, ["f.vdb"])
        codes.append(proc.returncode)
        assert seconds < 15
    assert 2 in codes


def test_info_folder_and_missing_file(tmp_path, capsys):
    assert main(["info", str(tmp_path)]) == 2
    check_one_line(capsys.readouterr().err, ["is a folder, not a .vdb file"])
    assert main(["info", str(tmp_path / "missing.vdb")]) == 2
    check_one_line(capsys.readouterr().err, ["no such file"])


# --- Dask scheduler -----------------------------------------------------------------------------------


def test_unreachable_scheduler_is_exit_2_in_seconds(tmp_path, capsys):
    cfg = tmp_path / "a.yaml"
    cfg.write_text(GOOD)
    # what is timed is the wait for the scheduler, not the first import of Distributed (seconds
    # when the other test worker is compiling kernels)
    import distributed  # noqa: F401
    start = time.perf_counter()
    code = main(["run", str(cfg), "--out", str(tmp_path / "out"), "--executor", "dask", "--scheduler",
                 "tcp://127.0.0.1:9"])
    assert code == 2
    check_one_line(capsys.readouterr().err, ["--scheduler tcp://127.0.0.1:9: cannot reach the Dask scheduler"])
    assert time.perf_counter() - start < 10


# --- mutated configs: validate answers 0 or 2, quickly ------------------------------------------------

FIELD_VALUES = st.sampled_from([True, False, None, 0, -1, 1e308, float("inf"), float("nan"), "x", "", [], [1],
                                [1, 2, 3, 4], {}, {"a": 1}, "sphere", "[[", "&a", "*a"])


@st.composite
def mutated_config(draw) -> bytes:
    lines = GOOD.splitlines(keepends=True)
    data = "".join(lines).encode()
    kind = draw(st.sampled_from(["bytes", "rename", "swap", "line"]))
    if kind == "bytes":  # random bytes inserted anywhere
        at = draw(st.integers(0, len(data)))
        return data[:at] + draw(st.binary(min_size=1, max_size=8)) + data[at:]
    if kind == "rename":  # a key renamed
        keys = ["name", "domain", "bounds", "resolution", "model", "union", "sphere", "center", "radius", "stages",
                "voxelise", "band", "export", "vdb"]
        old = draw(st.sampled_from(keys))
        new = draw(st.sampled_from([*keys, "box", "expr", "blend", "frames", "jobs", "t", "mesh", "offset"]))
        return data.replace(f"{old}:".encode(), f"{new}:".encode(), 1)
    if kind == "swap":  # a value replaced by one of another type
        import json

        targets = ["24", "0.4", "3", "true", "good", "[-0.3, 0, 0]", "[[-1, -1, -1], [1, 1, 1]]"]
        old = draw(st.sampled_from(targets))
        return data.replace(old.encode(), json.dumps(draw(FIELD_VALUES)).encode(), 1)
    i = draw(st.integers(0, len(lines) - 1))  # a line dropped or doubled
    return "".join(lines[:i] + ([lines[i]] * draw(st.integers(0, 2))) + lines[i + 1:]).encode()


@pytest.mark.parametrize("node", ["voxelise: {center: [-0.3, 0, 0]}", "3", "{}"])
def test_node_type_errors_stay_short_under_a_long_path(tmp_path, capsys, node: str) -> None:
    """A stage's name (or no node at all) where a node belongs: the message lists the node types
    on lines of their own, so no line passes the bar however long the config's path (found by
    hypothesis under pytest-xdist's longer temporary folders: one line of 430 characters)."""
    deep = tmp_path / ("a-long-folder-name-" * 3) / ("another-long-folder-" * 3)
    deep.mkdir(parents=True)
    code, err, _ = validate(deep, capsys, GOOD.replace("sphere: {center: [-0.3, 0, 0], radius: 0.4}", node, 1))
    assert code == 2 and "model.union[0]" in err.splitlines()[0] and "sphere, superellipsoid" in err
    assert len(str(deep)) > 150 and all(len(line) <= MAX_MESSAGE for line in err.splitlines())


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(content=mutated_config())
def test_mutated_configs_validate_or_exit_2(tmp_path, capsys, content):
    code, err, seconds = validate(tmp_path, capsys, content, name="m.yaml")
    assert code in (0, 2), err
    assert "Traceback" not in err
    if code == 2:
        assert all(len(line) <= MAX_MESSAGE for line in err.splitlines())
    assert seconds < 5
