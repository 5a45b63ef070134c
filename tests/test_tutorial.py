"""docs/tutorial.md runs: its Python blocks are executed in order, in one namespace."""

from __future__ import annotations

import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"


def test_tutorial_runs(tmp_path, monkeypatch, capsys):
    blocks = re.findall(r"^```python\n(.*?)^```", DOC.read_text(encoding="utf-8"), flags=re.M | re.S)
    assert len(blocks) >= 8
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "tutorial"}
    for k, block in enumerate(blocks, 1):
        exec(compile(block, f"{DOC.name} block {k}", "exec"), namespace)
    out = capsys.readouterr().out
    assert "run_capture gives the same normals" in out
    assert (tmp_path / "tutorial_output" / "run" / "mesh.ply").is_file()
    assert (tmp_path / "tutorial_output" / "by_hand" / "coefficients.ptm").is_file()
