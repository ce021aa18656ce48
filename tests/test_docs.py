"""The user guide's examples run, every config in configs/ validates, and the guide documents
every node type and parameter."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.oracles import REGISTRY

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "user-guide.md"


def guide_examples() -> list[tuple[str, str]]:
    text = GUIDE.read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, flags=re.S)
    out = []
    for b in blocks:
        m = re.match(r"# example: (\w+)", b)
        assert m, "every yaml block in the guide starts with '# example: <name>'"
        out.append((m.group(1), b))
    return out


@pytest.mark.parametrize("name, text", guide_examples(), ids=[n for n, _ in guide_examples()])
def test_guide_example_runs(tmp_path, name, text):
    cfg = tmp_path / f"{name}.yaml"
    cfg.write_text(text)
    assert main(["validate", str(cfg)]) == 0
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    manifests = sorted((tmp_path / "out").glob("*/manifest.json"))
    assert manifests
    for path in manifests:
        assert json.loads(path.read_text())["grids"]["frep"]["active_voxels"] > 0


@pytest.mark.parametrize("cfg", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_configs_validate(cfg, capsys):
    assert main(["validate", str(cfg)]) == 0, capsys.readouterr().err


def test_guide_documents_every_node_and_parameter():
    text = GUIDE.read_text()
    for kind, cls in REGISTRY.items():
        assert f"`{kind}`" in text, f"node {kind} is not in the user guide"
        for name, f in cls.Params.model_fields.items():
            key = f.alias or name
            assert f"`{key}`" in text, f"parameter {kind}.{key} is not in the user guide"
