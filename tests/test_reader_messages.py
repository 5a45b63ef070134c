"""The messages of the small-file readers (issue 16): each names the file or option at fault and
says what is wrong in plain words, never a library's advice or a wrong diagnosis."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
from PIL import Image

from helpers import dome, run_cli, sphere_normals
from ptmcore.errors import InputError
from ptmcore.lp import read_lp, write_lp
from ptmcore.psdataset import read_ps_dataset
from reconstruct.calibration.calibrate import calibrate
from reconstruct.pipeline.capture import read_mask
from reconstruct.surface.accuracy import load_ground_truth
from reconstruct.surface.normalmaps import read_normal_map


def _error(call, *args, **kwargs) -> InputError:
    with pytest.raises(InputError) as exc:
        call(*args, **kwargs)
    return exc.value


def _one_line(code: int, err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _capture(folder, n: int = 12, lights: bool = True):
    """A small 16-bit capture of a sphere (with its .lp unless ``lights`` is False)."""
    folder.mkdir(parents=True, exist_ok=True)
    normals, _ = sphere_normals(30, 36, 13.0)
    dirs = dome(n, seed=3)
    names = []
    for k, d in enumerate(dirs):
        shade = np.clip(normals @ d, 0, None) * 0.7
        names.append(f"img_{k:02d}.tif")
        tifffile.imwrite(folder / names[-1], np.round(np.repeat(shade[..., None], 3, 2) * 65535).astype(np.uint16))
    if lights:
        write_lp(folder / "lights.lp", names, dirs)
    return folder


# --- too few photographs ------------------------------------------------------------------------

def test_too_few_photographs_names_the_lp(tmp_path):
    lp = tmp_path / "two.lp"
    lp.write_text("2\na.jpg 0 0 1\nb.jpg 0 1 1\n")
    exc = _error(read_lp, lp)
    assert exc.path == str(lp)
    assert "lists 2 photographs; at least 3 are needed" in str(exc)
    assert "photograph(s) given" not in str(exc)


def test_too_few_photographs_names_the_lp_on_the_command_line(tmp_path, capsys):
    cap = _capture(tmp_path / "cap", n=2)
    line = _one_line(*run_cli(["run", cap, "-o", tmp_path / "out"], capsys)[::2])
    assert str(cap / "lights.lp") in line and "at least 3" in line


def test_too_few_lights_names_the_dataset_file(tmp_path):
    folder = tmp_path / "ds"
    folder.mkdir()
    (folder / "light_directions.txt").write_text("0 0 1\n0 1 1\n")
    (folder / "light_intensities.txt").write_text("1 1 1\n1 1 1\n")
    (folder / "filenames.txt").write_text("001.png\n002.png\n")
    exc = _error(read_ps_dataset, folder)
    assert exc.path == str(folder / "light_directions.txt") and "at least 3 photographs" in exc.problem


# --- spheres ------------------------------------------------------------------------------------

def _flat_photographs(folder, n: int):
    folder.mkdir()
    paths = []
    for k in range(n):
        paths.append(folder / f"p{k}.png")
        Image.fromarray(np.full((40, 50, 3), 90 + k, np.uint8)).save(paths[-1])
    return paths


def test_no_spheres_names_the_folder_and_the_option(tmp_path):
    paths = _flat_photographs(tmp_path / "shots", 4)
    exc = _error(calibrate, paths)
    assert exc.path == str(tmp_path / "shots")
    assert "no spheres found" in exc.problem and "--sphere X,Y,R" in exc.problem


def test_too_few_photographs_for_spheres_names_the_folder_and_the_option(tmp_path):
    paths = _flat_photographs(tmp_path / "shots", 2)
    exc = _error(calibrate, paths)
    assert exc.path == str(tmp_path / "shots")
    assert "at least 3" in exc.problem and "--sphere X,Y,R" in exc.problem
    assert "explicitly" not in exc.problem


def test_no_spheres_on_the_command_line(tmp_path, capsys):
    _flat_photographs(tmp_path / "shots", 4)
    line = _one_line(*run_cli(["calibrate", tmp_path / "shots", "-o", tmp_path / "l.lp"], capsys)[::2])
    assert str(tmp_path / "shots") in line and "no spheres found" in line and "--sphere X,Y,R" in line
    # `run` has no --sphere: it points to the command that has.
    line = _one_line(*run_cli(["run", tmp_path / "shots", "-o", tmp_path / "out"], capsys)[::2])
    assert str(tmp_path / "shots") in line and "reconstruct calibrate --sphere X,Y,R" in line


# --- .npy files ---------------------------------------------------------------------------------

def test_text_file_as_npy_is_not_given_numpy_advice(tmp_path):
    path = tmp_path / "normals.npy"
    path.write_text("0 0 1\n0 0 1\n")
    exc = _error(read_normal_map, path)
    assert exc.path == str(path) and "not a NumPy .npy array file" in exc.problem
    assert "pickle" not in str(exc)


def test_text_file_as_npy_on_the_command_line(tmp_path, capsys):
    path = tmp_path / "normals.npy"
    path.write_text("hello")
    line = _one_line(*run_cli(["integrate", path, "-o", tmp_path / "out"], capsys)[::2])
    assert str(path) in line and "not a NumPy .npy array file" in line and "pickle" not in line


@pytest.mark.parametrize(
    "array, needle",
    [
        (np.zeros((4, 5, 3), np.uint8), "must hold floats"),
        (np.zeros((4, 5), np.float32), "H×W×3"),
        (np.zeros((4, 5, 4), np.float32), "H×W×3"),
        (np.zeros((1, 1, 3), np.float32) + [0, 0, 1], "1×1 pixels"),
        (np.full((4, 5, 3), np.nan, np.float32), "no valid normal"),
        (np.full((4, 5, 3), [0, 0, np.inf]), "infinite"),
        (np.array([{"pickled": True}], dtype=object), "Python objects"),
        (np.zeros(3, dtype=[("x", "f4")]), "plain numbers"),
    ],
)
def test_bad_npy_normal_maps(tmp_path, array, needle):
    path = tmp_path / "n.npy"
    np.save(path, array, allow_pickle=True)
    exc = _error(read_normal_map, path)
    assert exc.path == str(path) and needle in exc.problem
    assert "allow_pickle" not in exc.problem


def test_truncated_npy(tmp_path):
    path = tmp_path / "n.npy"
    np.save(path, np.zeros((20, 30, 3), np.float32))
    path.write_bytes(path.read_bytes()[:300])
    exc = _error(read_normal_map, path)
    assert exc.path == str(path) and "truncated" in exc.problem and "20×30×3" in exc.problem


def test_bad_ground_truth_names_its_file(tmp_path):
    gt = tmp_path / "gt"
    gt.mkdir()
    (gt / "normals.npy").write_text("not an array")
    exc = _error(load_ground_truth, gt)
    assert exc.path == str(gt / "normals.npy") and "not a NumPy .npy array file" in exc.problem
    np.save(gt / "normals.npy", np.zeros((4, 5, 3), np.float32))
    np.save(gt / "height.npy", np.zeros((5, 4), np.float32))
    exc = _error(load_ground_truth, gt)
    assert exc.path == str(gt / "height.npy") and "a 5×4 array" in exc.problem and "shape (5, 4)" in exc.problem


# --- .lp vectors --------------------------------------------------------------------------------

def test_huge_lp_vector_is_not_called_below_the_horizon(tmp_path):
    lp = tmp_path / "l.lp"
    lp.write_text("3\na.jpg 0 0 1\nb.jpg 1e200 0 1e200\nc.jpg 0 1 1\n")
    exc = _error(read_lp, lp)
    assert exc.path == str(lp) and exc.problem.startswith("line 3:")
    assert "sensible length" in exc.problem and "horizon" not in exc.problem


# 'nan' is not a number a light file may hold (tests/test_lp.py); 1e400 overflows to inf.
@pytest.mark.parametrize("vector, needle", [("0 0 0", "zero length"), ("1e-9 0 1e-9", "zero length"),
                                            ("1e400 0 1", "not finite"), ("2e6 0 2e6", "sensible length")])
def test_bad_lp_vectors_name_their_line(tmp_path, vector, needle):
    lp = tmp_path / "l.lp"
    lp.write_text(f"3\na.jpg 0 0 1\nc.jpg 0 1 1\nb.jpg {vector}\n")
    exc = _error(read_lp, lp)
    assert exc.problem.startswith("line 4:") and "'b.jpg'" in exc.problem and needle in exc.problem
    assert "horizon" not in exc.problem


def test_light_positions_are_still_normalised(tmp_path):
    lp = tmp_path / "l.lp"
    lp.write_text("3\na.jpg 0 0 500\nb.jpg 300 0 400\nc.jpg 0 -3e5 4e5\n")
    np.testing.assert_allclose(read_lp(lp).directions, [[0, 0, 1], [0.6, 0, 0.8], [0, -0.6, 0.8]])


def test_huge_dataset_vector_is_not_called_below_the_horizon(tmp_path):
    folder = tmp_path / "ds"
    folder.mkdir()
    (folder / "light_directions.txt").write_text("0 0 1\n1e200 0 1e200\n0 1 1\n")
    (folder / "light_intensities.txt").write_text("1\n1\n1\n")
    exc = _error(read_ps_dataset, folder)
    assert exc.path == str(folder / "light_directions.txt") and exc.problem.startswith("line 2:")
    assert "sensible length" in exc.problem and "horizon" not in exc.problem


# --- duplicate .lp entries ----------------------------------------------------------------------

def test_duplicate_lp_entries_are_warned_of_by_line(tmp_path):
    lp = tmp_path / "l.lp"
    lp.write_text("# made by hand\n5\na.jpg 0 0 1\nb.jpg 0.5 0 0.8\nc.jpg 0 0.5 0.8\n"
                  "a.jpg 0.5 0.5 0.7\nd.jpg 0.5 0 0.8\n")
    warnings = read_lp(lp).warnings
    assert warnings == (
        "lines 3 and 6 list the same photograph a.jpg with different directions",
        "lines 4 and 7 give the same light direction (b.jpg, d.jpg)",
    )


def test_repeated_lp_line_is_warned_of(tmp_path):
    lp = tmp_path / "l.lp"
    lp.write_text("4\na.jpg 0 0 1\nb.jpg 0.5 0 0.8\nc.jpg 0 0.5 0.8\nb.jpg 0.5 0 0.8\n")
    assert read_lp(lp).warnings == ("lines 3 and 5 list the same photograph b.jpg with the same direction",)


def test_distinct_lp_entries_give_no_warning(tmp_path):
    write_lp(tmp_path / "l.lp", [f"{k}.jpg" for k in range(12)], dome(12, seed=2))
    assert read_lp(tmp_path / "l.lp").warnings == ()


# --- masks --------------------------------------------------------------------------------------

def test_mask_of_the_wrong_size_speaks_of_what_it_masks(tmp_path):
    path = tmp_path / "m.png"
    Image.fromarray(np.full((10, 12), 255, np.uint8)).save(path)
    exc = _error(read_mask, path, (20, 30), "the normal map")
    assert exc.path == str(path)
    assert "--mask image is 12×10 pixels" in exc.problem and "the normal map, 30×20" in exc.problem
    assert "photographs" not in exc.problem
    assert "the photographs, 30×20" in _error(read_mask, path, (20, 30)).problem


def test_integrate_mask_of_the_wrong_size_speaks_of_the_normal_map(tmp_path, capsys):
    normals, _ = sphere_normals(20, 30, 8.0)
    np.save(tmp_path / "n.npy", normals.astype(np.float32))
    Image.fromarray(np.full((10, 12), 255, np.uint8)).save(tmp_path / "m.png")
    line = _one_line(*run_cli(["integrate", tmp_path / "n.npy", "-o", tmp_path / "out", "--mask",
                               tmp_path / "m.png"], capsys)[::2])
    assert str(tmp_path / "m.png") in line and "normal map" in line and "photographs" not in line
