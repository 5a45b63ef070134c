"""Issue 16: captures that cannot give a surface are refused with one line, before any output."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from data_synthetic import write_capture
from reconstruct.cli.main import main


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("hostile") / "capture"
    write_capture(folder, shape=(32, 40), n_lights=8, seed=4)
    return folder


def _photographs(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.tif"))


def _copy(good: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "capture"
    shutil.copytree(good, folder)
    return folder


def _refused(folder: Path, tmp_path: Path, capsys, *words: str) -> None:
    out = tmp_path / "out"
    assert main(["run", str(folder), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    for word in words:
        assert word in err[0], err[0]
    assert not out.exists()


def test_identical_photographs(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    first, *rest = _photographs(folder)
    for p in rest:
        shutil.copy(first, p)
    _refused(folder, tmp_path, capsys, "identical", str(folder))


@pytest.mark.parametrize("value", [0, 65535])
def test_black_or_clipped_photographs(good, tmp_path, capsys, value):
    folder = _copy(good, tmp_path)
    for p in _photographs(folder):
        img = tifffile.imread(p)
        tifffile.imwrite(p, np.full_like(img, value))
    _refused(folder, tmp_path, capsys, "black" if value == 0 else "clipped", str(folder))


def test_an_8_bit_photograph_in_a_16_bit_capture(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    odd = _photographs(folder)[2]
    img = tifffile.imread(odd)
    tifffile.imwrite(odd, (img >> 8).astype(np.uint8))
    _refused(folder, tmp_path, capsys, "mixed bit depth", odd.name, "8-bit", "16-bit")


def test_two_photographs_name_the_folder(tmp_path, capsys):
    folder = tmp_path / "capture"
    folder.mkdir()
    for k in range(2):
        Image.fromarray(np.full((8, 8), 40 + k, np.uint8)).save(folder / f"p{k}.png")
    (folder / "lights.lp").write_text("2\np0.png 0 0 1\np1.png 0.5 0 0.866\n")
    _refused(folder, tmp_path, capsys, str(folder))


def test_a_ptm_whose_scales_are_all_zero(tmp_path, shared_fixture):
    from ptmcore.errors import InputError
    from ptmcore.ptmfile import read_ptm

    src = sorted(shared_fixture.glob("*.ptm"))[0]
    lines = src.read_bytes().split(b"\n")
    lines[4] = b"0.000000 0.000000 0.000000 0.000000 0.000000 0.000000 "  # the scales' line
    bad = tmp_path / "zero.ptm"
    bad.write_bytes(b"\n".join(lines))
    with pytest.raises(InputError, match="all six scales are 0"):
        read_ptm(bad)


def test_no_triangles_is_an_error(good, tmp_path, capsys):
    mask = tmp_path / "dot.png"
    img = np.zeros((32, 40), np.uint8)
    img[10, 10] = 255
    Image.fromarray(img).save(mask)
    out = tmp_path / "out"
    assert main(["run", str(good), "-o", str(out), "-q", "--mask", str(mask)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no triangles" in err[0]
    assert not out.exists()
    normals = tmp_path / "n.npy"
    np.save(normals, np.array([[[0, 0, 1]]], np.float32))
    assert main(["integrate", str(normals), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0]
    assert not out.exists()


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_failed_run_leaves_an_earlier_result_byte_identical(good, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(good), "-o", str(out), "-q"]) == 0
    before = _snapshot(out)
    folder = _copy(good, tmp_path)
    first, *rest = _photographs(folder)
    for p in rest:
        shutil.copy(first, p)
    assert main(["run", str(folder), "-o", str(out), "-q", "--hsh"]) == 2
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture", "out"]


def test_the_capture_folder_is_never_the_output(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    before = _snapshot(folder)
    assert main(["run", str(folder), "-o", str(folder), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a reconstruct result" in err[0]
    assert _snapshot(folder) == before


def test_one_black_photograph_or_one_copied_over_another_is_named(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    photos = _photographs(folder)
    tifffile.imwrite(photos[3], np.zeros_like(tifffile.imread(photos[3])))
    _refused(folder, tmp_path, capsys, photos[3].name, "black everywhere")
    shutil.copy(good / photos[3].name, photos[3])
    shutil.copy(photos[1], photos[5])
    _refused(folder, tmp_path, capsys, f"{photos[5].name} = {photos[1].name}", "identical")
