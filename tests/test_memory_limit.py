"""A capture larger than --memory-limit runs from a memory-mapped stack, with the same results."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from data_synthetic import write_capture
from ptmcore.reduce import disk_array
from reconstruct.cli.main import main
from reconstruct.pipeline import RunOptions, load_capture, run_capture
from reconstruct.pipeline.capture import stack_on_disk


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("cap") / "capture"
    write_capture(folder, shape=(40, 56), n_lights=12, seed=5)
    return folder


def test_disk_array_leaves_nothing_behind(tmp_path):
    a = disk_array(tmp_path, (3, 4, 5), np.uint16)
    a[:] = 7
    assert isinstance(a, np.memmap) and a.sum() == 7 * 60
    assert list(tmp_path.iterdir()) == []  # unlinked as soon as it was mapped


def test_the_limit_decides(capture):
    photographs = sorted(capture.glob("*.png")) or sorted(capture.glob("*.jp*g")) or sorted(capture.glob("*.tif"))
    assert photographs
    assert stack_on_disk(photographs, RunOptions(memory_limit=1.0))
    assert not stack_on_disk(photographs, RunOptions(memory_limit=1e6))
    in_memory = load_capture(capture, RunOptions(memory_limit=1e6), scratch=capture.parent)
    assert not isinstance(in_memory.stack.luminance, np.memmap)
    on_disk = load_capture(capture, RunOptions(memory_limit=1.0), scratch=capture.parent)
    assert isinstance(on_disk.stack.luminance, np.memmap)
    np.testing.assert_array_equal(np.asarray(on_disk.stack.luminance), in_memory.stack.luminance)
    assert any("did not fit" in w for w in on_disk.warnings)
    # Without a scratch folder the stack stays in memory whatever the limit.
    assert not isinstance(load_capture(capture, RunOptions(memory_limit=1.0)).stack.luminance, np.memmap)


def test_a_run_from_disk_gives_the_same_files(capture, tmp_path):
    a = run_capture(capture, tmp_path / "memory", RunOptions(memory_limit=1e6))
    b = run_capture(capture, tmp_path / "disk", RunOptions(memory_limit=1.0))
    np.testing.assert_array_equal(np.load(a.output / "normals.npy"), np.load(b.output / "normals.npy"))
    assert (a.output / "coefficients.ptm").read_bytes() == (b.output / "coefficients.ptm").read_bytes()
    assert any("did not fit" in w for w in b.report.warnings)
    # Nothing but the published files: the stack's file never appeared in the folder.
    assert sorted(p.name for p in b.output.iterdir()) == sorted(p.name for p in a.output.iterdir())


def test_cli_memory_limit(capture, tmp_path, capsys):
    assert main(["run", str(capture), "-o", str(tmp_path / "out"), "--memory-limit", "1", "-q"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["parameters"]["memory_limit"] == 1.0
    with pytest.raises(SystemExit) as exc:  # argparse's own exit status for a bad value
        main(["run", str(capture), "-o", str(tmp_path / "bad"), "--memory-limit", "-3", "-q"])
    assert exc.value.code == 2
    assert "--memory-limit" in capsys.readouterr().err
