"""Hostile arguments: negative numbers in comma lists, lengths out of range, options that do
nothing without another, empty paths. Each bad one is one line on stderr, exit status 2, no
traceback, and nothing written anywhere (issue 16)."""

from pathlib import Path

import numpy as np
import pytest
import tifffile

from ptmcore.errors import InputError
from ptmcore.lp import write_lp
from reconstruct.cli.main import main
from reconstruct.cli.parser import build_parser
from reconstruct.pipeline.options import BOUNDS, CompareOptions, RunOptions

from helpers import dome, run_cli as _call, sphere_normals, tree as _tree

H, W = 24, 32


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> dict[str, Path]:
    """A small capture of a sphere (lit from all round), its normals as .npy, its .lp, and
    one run's result folder (for relight)."""
    root = tmp_path_factory.mktemp("hostile")
    cap = root / "cap"
    cap.mkdir()
    normals, _ = sphere_normals(H, W, 11.0)
    dirs = dome(10, seed=2)
    names = []
    for k, d in enumerate(dirs):
        shade = np.clip(normals @ d, 0, None) * 0.7
        names.append(f"p{k:02d}.tif")
        tifffile.imwrite(cap / names[-1], np.round(np.repeat(shade[..., None], 3, axis=2) * 65535).astype(np.uint16))
    write_lp(cap / "lights.lp", names, dirs)
    np.save(root / "normals.npy", normals)
    result = root / "result"
    assert main(["run", str(cap), "-o", str(result), "-q"]) == 0
    return {"cap": cap, "lp": cap / "lights.lp", "npy": root / "normals.npy", "res": result, "root": root}


# {cap}: capture folder, {lp}: its .lp, {npy}: a normal map, {res}: a run's result, {out}: a
# path that must not be created. Needles must all be in the one error line.
BAD = [
    # lengths out of range (the range is named)
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "1e20"], ["--pixel-size", "between"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "1e200"], ["--pixel-size", "between"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "1e-300"], ["--pixel-size", "between"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "1e-7"], ["--pixel-size", "1e-06"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "20000"], ["--pixel-size", "10000"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "nan"], ["--pixel-size"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "inf"], ["--pixel-size"]),
    (["run", "{cap}", "-o", "{out}", "--step", "100001"], ["--step", "100000"]),
    (["run", "{cap}", "-o", "{out}", "--step", "1" + "0" * 30], ["--step"]),
    (["run", "{cap}", "-o", "{out}", "--intrinsics", "100,100,16,12", "--distance", "1e9"], ["--distance", "between"]),
    (["run", "{cap}", "-o", "{out}", "--intrinsics", "100,100,16,12", "--distance", "1e-4"], ["--distance", "between"]),
    (["run", "{cap}", "-o", "{out}", "--flatten", "highpass", "--flatten-cutoff", "1e300"], ["--flatten-cutoff", "between"]),
    (["run", "{cap}", "-o", "{out}", "--flatten", "highpass", "--flatten-cutoff", "1"], ["--flatten-cutoff", "between"]),
    (["run", "{cap}", "-o", "{out}", "--solid", "1e300"], ["--solid", "between"]),
    (["run", "{cap}", "-o", "{out}", "--solid", "1e-9"], ["--solid", "between"]),
    (["integrate", "{npy}", "-o", "{out}", "--pixel-size", "1e20"], ["--pixel-size", "between"]),
    (["integrate", "{npy}", "-o", "{out}", "--step", "1000000"], ["--step", "between"]),
    (["batch", "{cap}", "-o", "{out}", "--pixel-size", "1e-300"], ["--pixel-size", "between"]),
    (["compare", "{res}", "{npy}", "-o", "{out}", "--tolerance", "1e9"], ["--tolerance", "between"]),
    (["compare", "{res}", "{npy}", "-o", "{out}", "--max-distance", "1e-300"], ["--max-distance", "between"]),
    # options that do nothing without another, or cannot go with it
    (["run", "{cap}", "-o", "{out}", "--distance", "300"], ["--distance needs --intrinsics"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "0.1", "--distance", "300"], ["--distance needs --intrinsics"]),
    (["integrate", "{npy}", "-o", "{out}", "--distance", "300"], ["--distance needs --intrinsics"]),
    (["batch", "{cap}", "-o", "{out}", "--distance", "300"], ["--distance needs --intrinsics"]),
    (["run", "{cap}", "-o", "{out}", "--flatten-cutoff", "100"], ["--flatten-cutoff needs --flatten highpass"]),
    (["run", "{cap}", "-o", "{out}", "--flatten", "plane", "--flatten-cutoff", "100"], ["--flatten-cutoff needs"]),
    (["run", "{cap}", "-o", "{out}", "--intrinsics", "100,100,16,12", "--integrator", "fc"], ["--integrator fc", "perspective"]),
    (["run", "{cap}", "-o", "{out}", "--scan-units", "cm"], ["--scan-units needs --scan"]),
    (["batch", "{cap}", "-o", "{out}", "--scan-units", "cm"], ["--scan-units", "manifest"]),
    (["run", "{cap}", "-o", "{out}", "--decimate", "100", "--max-error", "0.1"], ["decimate", "not both"]),
    (["compare", "{res}", "{npy}", "-o", "{out}", "--min-fraction", "0.5"], ["--min-fraction needs --tolerance"]),
    (["compare", "{res}", "{npy}", "-o", "{out}", "--scale", "--no-align"], ["--scale", "--no-align"]),
    (["relight", "{res}", "--light", "0,0,1", "--gain", "3", "-o", "{out}"], ["--gain needs --mode diffuse-gain"]),
    (["relight", "{res}", "--light", "0,0,1", "--mode", "diffuse-gain", "--kd", "0.5", "-o", "{out}"],
     ["--kd needs --mode specular"]),
    (["relight", "{res}", "--light", "0,0,1", "--exponent", "20", "-o", "{out}"], ["--exponent needs --mode specular"]),
    (["relight", "{res}", "--sweep", "4", "--light", "0,0,1", "-o", "{out}"], ["--sweep", "--light"]),
    # rendering parameters are checked before the source is read (an .lp is no source)
    (["relight", "{lp}", "--light", "0,0,1", "--mode", "specular", "--kd", "-1", "-o", "{out}"],
     ["--kd must be a number from 0 to 100, not -1"]),
    (["relight", "{lp}", "--sweep", "4", "--mode", "specular", "--exponent", "nan", "-o", "{out}"],
     ["--exponent must be a number from 0 to 10000, not nan"]),
    (["relight", "{lp}", "--light", "0,0,1", "--mode", "diffuse-gain", "--gain", "0", "-o", "{out}"],
     ["--gain must be a number above 0, at most 1000, not 0"]),
    (["relight", "{res}", "--sweep", "4", "--azimuth", "-30", "-o", "{out}"], ["--sweep", "--azimuth"]),
    # negative numbers reach the option's own check, which names it
    (["relight", "{res}", "--light", "-0.7,0,0.71,1", "-o", "{out}"], ["--light must be three numbers"]),
    (["relight", "{res}", "--light", "-0.7,0,-0.71", "-o", "{out}"], ["horizon"]),
    (["run", "{cap}", "-o", "{out}", "--intrinsics", "-100,100,16,12"], ["--intrinsics"]),
    (["integrate", "{npy}", "-o", "{out}", "--intrinsics", "-100,100,16,12", "--distance", "300"], ["--intrinsics"]),
    (["calibrate", "{cap}", "-o", "{out}", "--intrinsics", "-400,400,16,12"], ["--intrinsics"]),
    (["calibrate", "{cap}", "-o", "{out}", "--sphere", "-5,10,-3"], ["--sphere", "radius"]),
    # a real option after one that wants a value is still an option
    (["relight", "{res}", "--light", "-o", "{out}"], ["--light", "expected one argument"]),
    (["run", "{cap}", "--intrinsics", "-o", "{out}"], ["--intrinsics", "expected one argument"]),
    (["run", "{cap}", "-o", "{out}", "--pixle-size", "0.1"], ["unrecognized arguments"]),
    (["run", "{cap}", "-o", "{out}", "--pixel-size", "-1"], ["--pixel-size", "positive"]),
    # empty paths: never the current folder
    (["run", "{cap}", "-o", ""], ["-o/--output", "empty path"]),
    (["run", "", "-o", "{out}"], ["capture", "empty path"]),
    (["run", "{cap}", "-o", "{out}", "--lp", ""], ["--lp", "empty path"]),
    (["run", "{cap}", "-o", "{out}", "--mask", ""], ["--mask", "empty path"]),
    (["run", "{cap}", "-o", "{out}", "--light-positions", ""], ["--light-positions", "empty path"]),
    (["run", "{cap}", "-o", "{out}", "--intensities", ""], ["--intensities", "empty path"]),
    (["run", "{cap}", "-o", "{out}", "--ground-truth", ""], ["--ground-truth", "empty path"]),
    (["batch", "{cap}", "-o", ""], ["-o/--output", "empty path"]),
    (["relight", "{res}", "--light", "0,0,1", "-o", ""], ["-o/--output", "empty path"]),
    (["calibrate", "{cap}", "-o", ""], ["-o/--output", "empty path"]),
    (["calibrate", "{cap}", "-o", "{out}", "--diagnostic", ""], ["--diagnostic", "empty path"]),
    (["compare", "{res}", "{npy}", "-o", ""], ["-o/--output", "empty path"]),
    (["integrate", "{npy}", "-o", ""], ["-o/--output", "empty path"]),
    (["integrate", "{npy}", "-o", "{out}", "--mask", ""], ["--mask", "empty path"]),
    (["lights", "{lp}", "-o", ""], ["-o/--output", "empty path"]),
    (["demo", "-o", ""], ["-o/--output", "empty path"]),
    (["preview", "{res}", "--screenshot", ""], ["--screenshot", "empty path"]),
]


@pytest.mark.parametrize("argv, needles", BAD, ids=[" ".join(a[:1] + a[2:])[:60] for a, _ in BAD])
def test_bad_arguments_are_one_line_and_write_nothing(shared, tmp_path, monkeypatch, capsys, argv, needles):
    # The current folder is watched too: an empty path used to mean it.
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    paths = {k: str(v) for k, v in shared.items()} | {"out": str(tmp_path / "out")}
    before = _tree(tmp_path, shared["root"])
    code, stdout, err = _call([a.format(**paths) for a in argv], capsys)
    assert code == 2, (stdout, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert _tree(tmp_path, shared["root"]) == before


INTO_RESULT = [(a, n) for a, n in BAD if a[0] in ("run", "integrate", "compare") and "{out}" in a]


@pytest.mark.parametrize("argv, needles", INTO_RESULT, ids=[" ".join(a[:1] + a[2:])[:60] for a, _ in INTO_RESULT])
def test_bad_arguments_leave_an_earlier_result_byte_identical(shared, tmp_path, capsys, argv, needles):
    import shutil

    earlier = tmp_path / "earlier"
    shutil.copytree(shared["res"], earlier)
    before = {str(p.relative_to(earlier)): p.read_bytes() for p in earlier.rglob("*") if p.is_file()}
    paths = {k: str(v) for k, v in shared.items()} | {"out": str(earlier)}
    code, _, err = _call([a.format(**paths) for a in argv], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert {str(p.relative_to(earlier)): p.read_bytes() for p in earlier.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["earlier"]


# --- negative numbers in comma lists ----------------------------------------------------------

@pytest.mark.parametrize("argv, option, value", [
    (["relight", "r", "-o", "x.png", "--light", "-0.7,0,0.71"], "light", "-0.7,0,0.71"),
    (["relight", "r", "-o", "x.png", "--light", "-.7,-0,0.71"], "light", "-.7,-0,0.71"),
    (["relight", "r", "-o", "x.png", "--light=-0.7,0,0.71"], "light", "-0.7,0,0.71"),
    (["relight", "r", "-o", "x.png", "--light", "-1e-1,0,1"], "light", "-1e-1,0,1"),
    (["relight", "r", "-o", "x.png", "--azimuth", "-45", "--elevation", "30"], "azimuth", -45.0),
    (["preview", "r", "--light", "-0.7,0,0.71"], "light", "-0.7,0,0.71"),
    (["run", "c", "-o", "o", "--intrinsics", "-100,100,16,12"], "intrinsics", "-100,100,16,12"),
    (["run", "c", "-o", "o", "--intrinsics", "100,100,-16,-12"], "intrinsics", "100,100,-16,-12"),
    (["batch", "c", "-o", "o", "--intrinsics", "-100,100,16,12"], "intrinsics", "-100,100,16,12"),
    (["integrate", "n.npy", "-o", "o", "--intrinsics", "-100,100,16,12"], "intrinsics", "-100,100,16,12"),
    (["calibrate", "c", "-o", "l.lp", "--intrinsics", "-400,400,16,12"], "intrinsics", "-400,400,16,12"),
    (["calibrate", "c", "-o", "l.lp", "--sphere", "-5,10,3", "--sphere", "20,-4,3"], "sphere", ["-5,10,3", "20,-4,3"]),
])
def test_negative_numbers_are_values(argv, option, value):
    assert getattr(build_parser().parse_args(argv), option) == value


def test_relight_from_the_left_with_a_negative_light(shared, tmp_path, capsys):
    # The README's own form: a light from the left lights the sphere's left side.
    left, eq = tmp_path / "left.png", tmp_path / "eq.png"
    code, _, err = _call(["relight", shared["res"], "--light", "-0.7,0,0.71", "-o", left], capsys)
    assert code == 0, err
    assert _call(["relight", shared["res"], "--light=-0.7,0,0.71", "-o", eq], capsys)[0] == 0
    from PIL import Image

    image = np.asarray(Image.open(left).convert("L"), np.float64)
    assert image.shape == (H, W)
    # The image is display-encoded (sRGB); the sides compared in linear light.
    from ptmcore.images import srgb_to_linear

    linear = srgb_to_linear(image / 255.0)
    assert linear[:, 6:W // 2 - 2].mean() > 2 * linear[:, W // 2 + 2:W - 6].mean()
    np.testing.assert_array_equal(image, np.asarray(Image.open(eq).convert("L"), np.float64))


def test_run_with_a_negative_principal_point(shared, tmp_path, capsys):
    out = tmp_path / "out"
    code, _, err = _call(["run", shared["cap"], "-o", out, "--intrinsics", "100,100,-5,12", "--distance", "300", "-q"],
                         capsys)
    assert code == 0, err
    assert (out / "mesh.ply").is_file()


def test_smallest_pixel_size_keeps_the_mesh(shared, tmp_path, capsys):
    # 1e-300 mm collapsed the mesh to a point; the smallest accepted size keeps it apart.
    import trimesh

    out = tmp_path / "out"
    code, _, err = _call(["run", shared["cap"], "-o", out, "--pixel-size", BOUNDS["pixel_size"][0], "-q"], capsys)
    assert code == 0, err
    vertices = np.asarray(trimesh.load(out / "mesh.ply", process=False).vertices)
    assert len(np.unique(vertices, axis=0)) == H * W
    np.testing.assert_allclose(np.ptp(vertices[:, 0]), (W - 1) * 1e-6, rtol=1e-3)


# --- the Python API refuses alike ------------------------------------------------------------

@pytest.mark.parametrize("kwargs, needle", [
    ({"pixel_size": 1e20}, "--pixel-size"),
    ({"pixel_size": 1e-300}, "--pixel-size"),
    ({"step": 100_001}, "--step"),
    ({"intrinsics": "100,100,16,12", "distance": 1e7}, "--distance"),
    ({"distance": 300.0}, "--distance needs --intrinsics"),
    ({"flatten_cutoff": 100.0}, "--flatten-cutoff needs"),
    ({"flatten": "highpass", "flatten_cutoff": 1.0}, "--flatten-cutoff"),
    ({"solid": 1e300}, "--solid"),
    ({"intrinsics": "100,100,16,12", "integrator": "fc"}, "perspective"),
    ({"mask": ""}, "--mask"),
    ({"lp": ""}, "--lp"),
])
def test_run_options_refuse(kwargs, needle):
    with pytest.raises(InputError, match=needle):
        RunOptions(**kwargs)


@pytest.mark.parametrize("kwargs, needle", [
    ({"tolerance": 1e9}, "--tolerance"),
    ({"max_distance": 0.0}, "--max-distance"),
    ({"min_fraction": 0.5}, "--min-fraction needs --tolerance"),
    ({"scale": True, "no_align": True}, "--scale"),
])
def test_compare_options_refuse(kwargs, needle):
    with pytest.raises(InputError, match=needle):
        CompareOptions(**kwargs)


def test_bounds_are_inclusive_and_pairs_accepted():
    low, high = BOUNDS["pixel_size"]
    assert RunOptions(pixel_size=low).pixel_size == low and RunOptions(pixel_size=high).pixel_size == high
    assert RunOptions(step=BOUNDS["step"][1]).step == BOUNDS["step"][1]
    assert RunOptions(intrinsics="100,100,16,12", distance=300.0).distance == 300.0
    assert RunOptions(flatten="highpass", flatten_cutoff=50.0).flatten_cutoff == 50.0
    assert CompareOptions(tolerance=0.1, min_fraction=0.5).min_fraction == 0.5
