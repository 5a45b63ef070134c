"""Issue 36, hostile light files and captures: an ``.lp`` with a NUL byte, numbers Python reads
but a light file does not mean (``0_5``), UTF-16, photographs listed twice or named ``#…``, a
broken ``lights.lp``, ground truth of another size, and a capture that lights no pixel three
times. Each is one line naming the file (and line), exit status 2, nothing written, or a run
that works."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from data_synthetic import write_capture
from ptmcore.errors import InputError
from ptmcore.intensity import read_intensities
from ptmcore.lp import MAX_TEXT_BYTES, read_lp, write_lp
from ptmcore.nearlight import read_light_positions
from ptmcore.psdataset import read_ps_dataset
from reconstruct.cli.main import main
from reconstruct.pipeline import RunOptions, load_capture
from reconstruct.pipeline.stages import MIN_DETERMINED_FRACTION
from reconstruct.surface.accuracy import load_ground_truth, normal_accuracy

FEW = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("lp_capture") / "capture"
    write_capture(folder, shape=(32, 40), n_lights=8, seed=4)
    return folder


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    # Module-scoped: hypothesis runs many examples in one call of a test function.
    return tmp_path_factory.mktemp("lp_files")


def _copy(good: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "capture"
    shutil.copytree(good, folder)
    return folder


def _lines(folder: Path) -> list[str]:
    return (folder / "lights.lp").read_text().splitlines()


def _refused(source: Path, tmp_path: Path, capsys, *words: str) -> str:
    """Run ``reconstruct run source``: exit 2, one line holding ``words``, no output folder."""
    out = tmp_path / "out"
    assert main(["run", str(source), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    for word in words:
        assert word in err[0], err[0]
    assert not out.exists()
    return err[0]


def _error(read, *args) -> str:
    with pytest.raises(InputError) as exc:
        read(*args)
    return str(exc.value)


# --- 1. a NUL byte in a photograph's name --------------------------------------------------------


def test_nul_in_a_photograph_name_names_the_lp_and_its_line(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    lines = _lines(folder)
    lines[4] = lines[4].replace("img_003", "img_0\0" + "03")
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")
    message = _refused(folder, tmp_path, capsys, str(folder / "lights.lp"), "line 5", "NUL")
    assert "\0" not in message
    assert "line 5" in _error(read_lp, folder / "lights.lp")


# --- 2. numbers are plain decimals, in every light text reader -----------------------------------


@pytest.mark.parametrize("value", ["0_5", "1_0e-1", "\u0665", "\uff15", "\u0660.\u0665"])
def test_numbers_python_reads_but_a_light_file_does_not_mean_are_refused(good, tmp_path, capsys, value):
    folder = _copy(good, tmp_path)
    lines = _lines(folder)
    name, x, y, z = lines[1].split()
    lines[1] = f"{name} {value} {y} {z}"
    (folder / "lights.lp").write_text("\n".join(lines) + "\n", encoding="utf-8")
    _refused(folder, tmp_path, capsys, str(folder / "lights.lp"), "line 2", "not three numbers")


def _plain(token: str) -> bool:
    return re.fullmatch(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?", token) is not None


#: Numbers as light files write them, and as Python's float() also takes them.
_DIGITS = "0123456789"
_OTHER_DIGITS = "\u0660\u0661\u0665\u06f5\u0967\uff10\uff15"
_TOKEN = st.one_of(
    st.floats(0.05, 0.95).map(lambda v: f"{v:.6f}"),
    st.floats(0.05, 0.95).map(repr),
    st.tuples(st.integers(1, 9), st.integers(0, 99)).map(lambda t: f"{t[0]}_{t[1]}e-2"),
    st.tuples(st.floats(0.05, 0.95).map(lambda v: f"{v:.4f}"), st.integers(0, 5), st.sampled_from(_OTHER_DIGITS))
      .map(lambda t: t[0][: 2 + t[1] % 4] + t[2] + t[0][3 + t[1] % 4:]),
    st.sampled_from(["nan", "inf", "-inf", "0x1p-1", "1e", ".", "+", "1..2", "Infinity", "1e999"]),
)


def _lp_value(path: Path, token: str) -> float:
    path.write_text(f"3\na.png {token} 0 1\nb.png 0 0.5 1\nc.png 0 -0.5 1\n", encoding="utf-8")
    return read_lp(path).directions[0, 0] * math.sqrt(float(token) ** 2 + 1)


def _intensity_value(path: Path, token: str) -> float:
    path.write_text(f"1\n{token}\n1\n", encoding="utf-8")
    return read_intensities(path, 3)[1]


def _position_value(path: Path, token: str) -> float:
    path.write_text(f"name,x,y,z\na.png,{token},0,100\n", encoding="utf-8")
    return read_light_positions(path)[1][0, 0]


@FEW
@given(token=_TOKEN)
@pytest.mark.parametrize("read", [_lp_value, _intensity_value, _position_value])
def test_light_text_readers_take_plain_decimals_only(scratch, read, token):
    path = scratch / "numbers.txt"
    try:
        value = read(path, token)
    except InputError as exc:
        assert str(exc).startswith(str(path)) and "line 2" in str(exc), str(exc)
        assert not _plain(token) or not math.isfinite(float(token)), token
        return
    assert _plain(token), token
    assert value == pytest.approx(float(token))


def test_dataset_light_directions_take_plain_decimals_only(tmp_path):
    folder = tmp_path / "dataset"
    folder.mkdir()
    (folder / "light_directions.txt").write_text("0 0 1\n0.1 0_2 0.9\n0 0.5 1\n")
    (folder / "light_intensities.txt").write_text("1 1 1\n1 1 1\n1 1 1\n")
    message = _error(read_ps_dataset, folder)
    assert message.startswith(str(folder / "light_directions.txt")) and "line 2" in message


# --- bounded reads -------------------------------------------------------------------------------


@pytest.mark.parametrize("read", [read_lp, lambda p: read_intensities(p, 3), read_light_positions])
def test_a_light_text_file_larger_than_any_is_refused_unread(tmp_path, read):
    path = tmp_path / "huge.txt"
    with open(path, "wb") as f:
        f.truncate(MAX_TEXT_BYTES + 1)  # sparse: costs nothing to make
    message = _error(read, path)
    assert message.startswith(str(path)) and "more than" in message


def test_a_light_position_file_of_one_huge_field_is_one_line(tmp_path):
    path = tmp_path / "light_positions.csv"
    path.write_text("name,x,y,z\n" + "a" * 200_000 + ",1,2,3\n")
    assert _error(read_light_positions, path).startswith(f"{path}: line 2:")


def test_a_dataset_normals_file_that_is_a_fifo_is_named_as_one(tmp_path):
    from test_psdataset import _write_dataset

    folder = tmp_path / "ball"
    _write_dataset(folder, gt=False)
    os.mkfifo(folder / "Normal_gt.mat")
    message = _error(read_ps_dataset, folder)
    assert message.startswith(str(folder / "Normal_gt.mat")) and "pipe" in message


# --- 3. UTF-16 -----------------------------------------------------------------------------------


def test_utf16_lp_with_a_byte_order_mark_reads_and_without_one_says_so(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    text = (folder / "lights.lp").read_text().replace("\n", "\r\n")
    expected = read_lp(folder / "lights.lp")
    for codec in ("utf-16", "utf-16-be"):  # Notepad's "Unicode" writes a byte-order mark
        data = text.encode(codec)
        (folder / "lights.lp").write_bytes(data if codec == "utf-16" else b"\xfe\xff" + data)
        lights = read_lp(folder / "lights.lp")
        assert lights.paths == expected.paths
        np.testing.assert_array_equal(lights.directions, expected.directions)
    for codec in ("utf-16-le", "utf-16-be"):
        (folder / "lights.lp").write_bytes(text.encode(codec))
        _refused(folder, tmp_path, capsys, str(folder / "lights.lp"), "UTF-16", "save it as UTF-8")


# --- 4. a photograph listed twice ----------------------------------------------------------------


def test_a_photograph_listed_twice_is_a_warning_naming_the_lines(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    lines = _lines(folder)
    lines[8] = lines[8].replace("img_007", "img_000")
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")
    loaded = load_capture(folder, RunOptions())
    assert any("lines 2 and 9" in w and "img_000.tif" in w for w in loaded.warnings), loaded.warnings
    out = tmp_path / "out"
    assert main(["run", str(folder), "-o", str(out)]) == 0
    assert "lines 2 and 9" in capsys.readouterr().out
    assert any("lines 2 and 9" in w for w in json.loads((out / "report.json").read_text())["warnings"])


# --- 5. photographs named '#…' -------------------------------------------------------------------


def test_a_photograph_named_with_a_hash_is_read(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    (folder / "img_000.tif").rename(folder / "#1.tif")
    lines = _lines(folder)
    lines[1] = lines[1].replace("img_000.tif", "#1.tif")
    lines[2:2] = ["# written by hand"]
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")
    lights = read_lp(folder / "lights.lp")
    assert len(lights) == 8 and lights.paths[0] == folder / "#1.tif"
    out = tmp_path / "out"
    assert main(["run", str(folder), "-o", str(out), "-q"]) == 0, capsys.readouterr().err
    assert (out / "mesh.ply").exists()


def test_an_entry_commented_out_is_a_comment_when_the_count_leaves_it_out(good, tmp_path):
    folder = _copy(good, tmp_path)
    lines = _lines(folder)
    lines[1] = "#" + lines[1]
    lines[0] = "7"
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")
    assert [p.name for p in read_lp(folder / "lights.lp").paths] == [f"img_{k:03d}.tif" for k in range(1, 8)]
    lines[0] = "9"
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")
    message = _error(read_lp, folder / "lights.lp")
    assert "declares 9 photographs but lists 8 (7 besides the lines starting with '#')" in message


_NAME = st.text(st.characters(codec="utf-8", exclude_categories=("Cs", "Cc", "Zs", "Zl", "Zp"),
                              exclude_characters="\\/"), min_size=1, max_size=10).filter(lambda n: n.strip("."))


@FEW
@given(names=st.lists(st.tuples(st.booleans(), _NAME).map(lambda t: "#" * t[0] + t[1]), min_size=3, max_size=8,
                      unique=True),
       comments=st.lists(st.tuples(st.integers(0, 8), st.sampled_from(
           ["# relight 1.0", "#", "## lights", "#old.jpg 0.1 0.2 0.9", "# x 1 2 3", "  # indented"])), max_size=3))
def test_names_and_comments_read_back_as_written(scratch, names, comments):
    """Names, '#…' ones too, read back as written; comments are skipped (an entry commented
    out among them when no photograph's name starts with '#': the count then tells which)."""
    if any(n.startswith("#") for n in names):
        comments = [(at, c) for at, c in comments if len(c.split()) < 4]
    k = np.arange(len(names))
    # Six decimals, as write_lp writes them: read back to within a rounding of the normalising.
    directions = np.round(np.stack([0.3 * np.cos(k), 0.3 * np.sin(k), np.ones(len(names))], axis=1), 6)
    path = scratch / "names.lp"
    write_lp(path, names, directions)
    lines = path.read_text(encoding="utf-8").splitlines()
    for at, comment in comments:
        lines.insert(1 + at % len(lines), comment)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    lights = read_lp(path)
    assert [p.name for p in lights.paths] == names
    np.testing.assert_allclose(lights.directions, directions / np.linalg.norm(directions, axis=1)[:, None],
                               atol=1e-12)


# --- 6. a broken lights.lp -----------------------------------------------------------------------


@pytest.mark.parametrize("kind, name, words", [
    ("dangling", "lights.lp", ("symbolic link to", "which does not exist")),
    ("loop", "lights.lp", ("symbolic links",)),
    ("folder", "x.lp", ("folder",)),
])
def test_a_broken_lp_in_the_capture_is_named(good, tmp_path, capsys, kind, name, words):
    folder = _copy(good, tmp_path)
    (folder / "lights.lp").unlink()
    if kind == "dangling":
        (folder / name).symlink_to(tmp_path / "gone.lp")
    elif kind == "loop":
        (folder / name).symlink_to(name)
    else:
        (folder / name).mkdir()
    message = _refused(folder, tmp_path, capsys, str(folder / name), *words)
    assert "no .lp" not in message


def test_a_broken_lp_beside_another_is_not_passed_over(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    (folder / "lights.lp").rename(folder / "old.lp")
    (folder / "lights.lp").symlink_to(tmp_path / "gone.lp")
    _refused(folder, tmp_path, capsys, "several .lp files", "lights.lp", "old.lp")


# --- 7. ground truth of another size --------------------------------------------------------------


def test_ground_truth_of_another_size_names_its_file(good, tmp_path, capsys):
    folder = _copy(good, tmp_path)
    normals_file = folder / "ground_truth" / "normals.npy"
    np.save(normals_file, np.load(normals_file)[:30, :30])
    (folder / "ground_truth" / "mask.png").unlink()
    (folder / "ground_truth" / "height.npy").unlink()
    _refused(folder, tmp_path, capsys, str(normals_file), "30×30", "40×32")
    truth = load_ground_truth(folder / "ground_truth")
    message = _error(normal_accuracy, np.zeros((32, 40, 3), np.float32), truth)
    assert message.startswith(str(normals_file)) and "40×32" in message


def test_a_broken_dataset_mask_is_named_not_ignored(tmp_path):
    from test_psdataset import _write_dataset

    folder = tmp_path / "ball"
    _write_dataset(folder, with_mask=False)
    (folder / "mask.png").symlink_to(tmp_path / "gone.png")
    assert _error(read_ps_dataset, folder).startswith(str(folder / "mask.png"))


# --- 8. a capture that lights no pixel three times ------------------------------------------------


def _darken(folder: Path, lit: np.ndarray) -> None:
    """Every photograph black outside ``lit`` (H, W), and pixel (0, 0) lit differently in each,
    so that none is black everywhere or a copy of another."""
    for k, p in enumerate(sorted(folder.glob("img_*.tif"))):
        img = np.where(lit[..., None], tifffile.imread(p), 0)
        img[0, 0] = 1000 * (k + 1)
        tifffile.imwrite(p, img)


def _dark_capture(good: Path, tmp_path: Path, *pixels: tuple[int, int]) -> Path:
    """The capture lit only at ``pixels`` (and (0, 0))."""
    folder = _copy(good, tmp_path)
    lit = np.zeros((32, 40), bool)
    for at in pixels:
        lit[at] = True
    _darken(folder, lit)
    return folder


def test_a_capture_lighting_no_pixel_is_refused_and_a_partly_dark_one_warned_of(good, tmp_path, capsys):
    dark = _dark_capture(good, tmp_path / "dark")
    _refused(dark, tmp_path, capsys, str(dark), "no surface", "1 of the photographs' 1,280 pixels")

    half = _copy(good, tmp_path / "half")
    left = np.zeros((32, 40), bool)
    left[:, :20] = True
    _darken(half, left)
    out = tmp_path / "out"
    assert main(["run", str(half), "-o", str(out)]) == 0
    assert "too few lit" in capsys.readouterr().out
    assert (out / "mesh.ply").exists()


@pytest.mark.parametrize("normals, fit", [("ptm", "plain"), ("ptm", "irls"), ("ptm-debiased", "plain"),
                                          ("ptm-debiased", "irls"), ("ps", "plain")])
def test_every_normal_method_refuses_a_capture_lighting_no_pixel(good, tmp_path, capsys, normals, fit):
    dark = _dark_capture(good, tmp_path)
    out = tmp_path / "out"
    assert main(["run", str(dark), "-o", str(out), "-q", "--normals", normals, "--fit", fit]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no surface" in err[0] and "1,280 pixels" in err[0], err
    assert not out.exists()


def test_the_threshold_is_a_fraction_of_the_object(good, tmp_path):
    """One determined pixel of 1,280 is under MIN_DETERMINED_FRACTION, two are not; with a
    mask, the object is the mask."""
    from PIL import Image

    from reconstruct.pipeline import estimate_normals

    assert 1 < MIN_DETERMINED_FRACTION * 32 * 40 < 2
    one = _dark_capture(good, tmp_path / "one")
    message = _error(estimate_normals, load_capture(one, RunOptions()), RunOptions())
    assert message.startswith(str(one)) and "1 of the photographs' 1,280 pixels" in message
    two = _dark_capture(good, tmp_path / "two", (16, 30))
    assert estimate_normals(load_capture(two, RunOptions()), RunOptions()).undetermined == 32 * 40 - 2
    mask = np.zeros((32, 40), np.uint8)
    mask[:, 20:] = 255
    mask[16, 30] = 0
    Image.fromarray(mask).save(tmp_path / "mask.png")
    capture = load_capture(two, RunOptions(mask=tmp_path / "mask.png"))
    message = _error(estimate_normals, capture, RunOptions())
    assert "0 of the mask's 639 pixels" in message
