"""A capture larger than --memory-limit runs from a memory-mapped stack, with the same results."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from data_synthetic import write_capture
from ptmcore.diskstack import disk_array
from reconstruct.cli.main import main
from reconstruct.pipeline import RunOptions, load_capture, run_capture
from reconstruct.pipeline.capture import plan_stack


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
    assert plan_stack(photographs, RunOptions(memory_limit=1.0)).on_disk
    assert not plan_stack(photographs, RunOptions(memory_limit=1e6)).on_disk
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


def test_released_rows_leave_the_process_but_not_the_file(tmp_path):
    from ptmcore.diskstack import release_rows, resident_bytes

    n, h, w = 3, 64, 4096  # a row is a page, so each plane's band is whole pages
    a = disk_array(tmp_path, (n, h, w), np.uint8)
    expected = (np.arange(n * h * w, dtype=np.int64) % 251).astype(np.uint8).reshape(n, h, w)
    a[:] = expected
    full = resident_bytes(a)
    assert full >= a.nbytes * 0.9
    release_rows(a, 0, 32, range(1, 3))  # the first half of planes 1 and 2
    assert full - resident_bytes(a) >= 2 * 32 * w
    release_rows(a, 0, h)
    assert resident_bytes(a) < full / 10
    np.testing.assert_array_equal(np.asarray(a), expected)  # read back from the file


def test_release_never_touches_other_arrays(tmp_path):
    from ptmcore.diskstack import is_disk_array, release_rows

    plain = np.full((2, 8, 4096), 9, np.uint8)
    release_rows(plain, 0, 8)
    assert (plain == 9).all()
    a = disk_array(tmp_path, (2, 8, 4096), np.uint8)
    a[:] = 5
    view, copy = a[1:], np.memmap.__getitem__(a, [0, 1])
    assert is_disk_array(a) and not is_disk_array(view) and not is_disk_array(copy)
    copy[:] = 3
    release_rows(copy, 0, 8)
    assert (np.asarray(copy) == 3).all() and (np.asarray(a) == 5).all()


def test_a_large_stack_goes_to_a_file_by_default(capture, tmp_path, monkeypatch):
    import reconstruct.pipeline.capture as capture_module

    photographs = sorted(capture.glob("*.png")) or sorted(capture.glob("*.jp*g")) or sorted(capture.glob("*.tif"))
    assert not plan_stack(photographs, RunOptions()).on_disk  # a small stack stays in memory
    monkeypatch.setattr(capture_module, "STACK_FILE_MB", 0.0)
    assert plan_stack(photographs, RunOptions()).on_disk
    assert not plan_stack(photographs, RunOptions(memory_limit=1e6)).on_disk  # an explicit limit it fits in
    b = run_capture(capture, tmp_path / "file", RunOptions())
    a = run_capture(capture, tmp_path / "memory", RunOptions(memory_limit=1e6))
    np.testing.assert_array_equal(np.load(a.output / "normals.npy"), np.load(b.output / "normals.npy"))
    report = json.loads((b.output / "report.json").read_text())
    assert report["inputs"]["stack"] == "file"
    assert json.loads((a.output / "report.json").read_text())["inputs"]["stack"] == "memory"
    # Memory was not short: no warning.
    assert not any("did not fit" in w for w in b.report.warnings)


def test_a_full_disk_is_an_input_error(tmp_path, monkeypatch):
    import errno
    import os

    from ptmcore.errors import InputError

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full, raising=False)
    with pytest.raises(InputError, match="no room for the photographs' stack"):
        disk_array(tmp_path, (4, 1024, 1024), np.uint8)
    assert list(tmp_path.iterdir()) == []  # the file went with the error


def test_a_sample_grid_leaves_the_stack_on_disk(tmp_path):
    from pathlib import Path as P

    from ptmcore.diskstack import resident_bytes
    from ptmcore.images import ImageStack

    n, h, w = 4, 256, 4096
    a = disk_array(tmp_path, (n, h, w), np.uint8)
    a[:] = 7
    stack = ImageStack(a, np.ones((h, w, 3), np.float32), [P(f"{k}.jpg") for k in range(n)], 8, True,
                       np.zeros(n, np.int64))
    codes = stack.grid(16)
    assert codes.shape == (n, 16, 256) and (codes == 7).all()
    assert resident_bytes(a) < a.nbytes / 10  # reading a sparse grid maps much of the file
