"""Command-line values that ask for unbounded work, and sphere values that do not fit the
photographs (issue 36): each is one line on stderr, exit status 2, no traceback, nothing
written; a value within its documented bound is taken. Property-based over every numeric
option of every command."""

import math
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ptmcore.errors import InputError
from ptmcore.lp import write_lp
from reconstruct.cli.main import main

from helpers import dome, run_cli as _call, sphere_normals, tree as _tree

H, W = 24, 32
#: The sphere capture: one black glossy sphere in a 160×120 frame.
SPHERE = (45.0, 45.0, 30.0)
SPHERE_SHAPE = (120, 160)


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> dict[str, Path]:
    """A small capture of a diffuse sphere and one run's result (for relight and preview),
    and a highlight-RTI capture with one glossy sphere (for calibrate)."""
    from data_synthetic.spheres import render_sphere_capture

    root = tmp_path_factory.mktemp("values")
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
    result = root / "result"
    assert main(["run", str(cap), "-o", str(result), "-q"]) == 0
    spheres = root / "spheres"
    render_sphere_capture(spheres, shape=SPHERE_SHAPE, n_lights=8, spheres=(SPHERE,), seed=0)
    (spheres / "truth.lp").unlink()  # the photographs only
    return {"res": result, "spheres": spheres, "root": root}


def _refused(argv: list, capsys, needles: list[str], *watched: Path) -> None:
    """``argv`` is one line naming ``needles``, exit status 2, and changes nothing under
    ``watched``."""
    before = _tree(*watched)
    code, out, err = _call(argv, capsys)
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert _tree(*watched) == before


# --- demo: lights and image size ----------------------------------------------------------

@pytest.mark.parametrize("args, needles", [
    (["--lights", "100000000"], ["--lights", "from 3 to 1000"]),
    (["--lights", "1e8"], ["--lights", "from 3 to 1000"]),
    (["--lights", "1001"], ["--lights", "from 3 to 1000"]),
    (["--size", "100000x100000"], ["100000×100000", "at most 16384"]),
    (["--size", "16385x16"], ["16385×16", "at most 16384"]),
    (["--size", "8000x6000"], ["48 images of 8000×6000", "GiB", "at most 4 GiB"]),
    (["--size", "2000x1500", "--lights", "1000"], ["1000 images of 2000×1500", "at most 4 GiB"]),
    (["--seed", "-1"], ["--seed", "at least 0"]),
    (["--lights", "2"], ["--lights", "from 3 to 1000"]),
])
def test_demo_refuses_sizes_it_cannot_render(tmp_path, monkeypatch, capsys, args, needles):
    monkeypatch.chdir(tmp_path)
    _refused(["demo", "-o", tmp_path / "out", *args], capsys, needles, tmp_path)
    assert not (tmp_path / "out").exists()


def test_write_capture_refuses_before_writing(tmp_path):
    from data_synthetic import write_capture
    from data_synthetic.capture import MAX_LIGHTS
    from reconstruct.cli.parser import DEMO_MAX_LIGHTS

    assert DEMO_MAX_LIGHTS == MAX_LIGHTS

    for kwargs, needle in [({"shape": (9000, 8000)}, "GiB"), ({"n_lights": 1001}, "1001 lights"),
                           ({"shape": (16, 20000)}, "at most 16384"),
                           ({"lights": np.tile([[0.0, 0.0, 1.0]], (1001, 1))}, "1001 lights"),
                           ({"shape": (16, 16), "scan_points": 257}, r"at most one per pixel \(256\)"),
                           ({"shape": (16, 16), "scan_points": 10**400}, "scan_points")]:
        with pytest.raises(InputError, match=needle):
            write_capture(tmp_path / "cap", **kwargs)
        assert not (tmp_path / "cap").exists()
    # The bounds themselves are taken.
    from data_synthetic.capture import MAX_RENDER_BYTES, check_capture_size, render_bytes

    check_capture_size((8, 16384), 1000)
    assert render_bytes((2000, 1500), 48) <= MAX_RENDER_BYTES
    info = write_capture(tmp_path / "cap", shape=(16, 16), n_lights=3, scan_points=256)
    assert len(info.image_paths) == 3


# --- preview: window and figure size ------------------------------------------------------

@pytest.mark.parametrize("size, needles", [
    ("100000x100000", ["--size", "both sides from 64 to 16384 pixels"]),
    ("16385x64", ["--size", "both sides from 64 to 16384 pixels"]),
    ("16384x16384", ["--size", "at most 67,108,864 pixels (8192x8192)"]),
    ("63x64", ["--size", "both sides from 64 to 16384 pixels"]),
])
def test_preview_size_is_bounded_at_the_parser(shared, tmp_path, capsys, size, needles):
    shot = tmp_path / "shot.png"
    _refused(["preview", shared["res"], "--screenshot", shot, "--size", size], capsys, needles, tmp_path, shared["res"])


def test_preview_api_refuses_a_size_beyond_the_bound(shared, tmp_path):
    from reconstruct.viewer.preview import render_screenshot
    from reconstruct.viewer.scene import load_scene

    scene = load_scene(shared["res"])
    for size in [(16385, 64), (9000, 9000)]:
        with pytest.raises(InputError, match="too large"):
            render_screenshot(scene, tmp_path / "shot.png", size=size)
    assert not (tmp_path / "shot.png").exists()
    # The bounds themselves render.
    from PIL import Image

    render_screenshot(scene, tmp_path / "shot.png", size=(16384, 64))
    assert Image.open(tmp_path / "shot.png").size == (16384, 64)


# --- relight: frames of a sweep -----------------------------------------------------------

def test_relight_sweep_is_bounded(shared, tmp_path, capsys):
    gif = tmp_path / "turn.gif"
    for count in ("361", "1e8"):
        _refused(["relight", shared["res"], "--sweep", count, "-o", gif], capsys, ["--sweep", "from 1 to 360"],
                 tmp_path, shared["res"])
    code, _, err = _call(["relight", shared["res"], "--sweep", "360", "-o", gif], capsys)
    assert code == 0, err
    from PIL import Image

    assert Image.open(gif).n_frames == 360


def test_sweep_frames_are_bounded_by_their_pixels():
    from reconstruct.viewer.relighting import check_sweep, sweep_lights

    with pytest.raises(ValueError, match="1 to 360"):
        sweep_lights(361)
    with pytest.raises(InputError, match=r"big\.ptm: 360 frames of 6000×4000 .* --sweep 89 or fewer"):
        check_sweep(360, 6000, 4000, "big.ptm")
    with pytest.raises(InputError, match="at most 65535"):
        check_sweep(2, 70000, 16, "wide.ptm")
    check_sweep(89, 6000, 4000, "big.ptm")


# --- calibrate: spheres and cameras -------------------------------------------------------

@pytest.mark.parametrize("sphere, needles", [
    ("80,60,1e9", ["(80, 60, 1e+09)", "160×120", "4 to 60 pixels"]),
    ("45,45,3", ["(45, 45, 3)", "4 to 60 pixels"]),
    ("45,45,61", ["(45, 45, 61)", "4 to 60 pixels"]),
    ("200,45,30", ["(200, 45, 30)", "outside the 160×120"]),
    ("45,nan,30", ["--sphere", "finite"]),
])
def test_calibrate_refuses_a_sphere_that_does_not_fit(shared, tmp_path, capsys, sphere, needles):
    lp = tmp_path / "lights.lp"
    _refused(["calibrate", shared["spheres"], "-o", lp, "--sphere", sphere], capsys, needles, tmp_path, shared["spheres"])
    # The sphere itself gives every light.
    code, _, err = _call(["calibrate", shared["spheres"], "-o", lp, "--sphere", ",".join(map(str, SPHERE))], capsys)
    assert code == 0, err
    assert lp.read_text().splitlines()[0] == "8"


def test_no_highlight_on_a_sphere_names_it(tmp_path, capsys):
    # Photographs without any highlight: nothing written, and the line names the sphere given.
    cap = tmp_path / "cap"
    cap.mkdir()
    for k in range(3):
        tifffile.imwrite(cap / f"p{k}.tif", np.full((48, 64), 2000 * (k + 1), np.uint16))
    _refused(["calibrate", cap, "-o", tmp_path / "lights.lp", "--sphere", "30,20,12"], capsys,
             ["none of the 3 photographs has a usable highlight", "(30, 20, 12)"], tmp_path)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cx=st.floats(-20, 180) | st.floats(), cy=st.floats(-20, 140) | st.floats(), r=st.floats(0, 70) | st.floats())
def test_calibration_takes_only_spheres_that_fit(shared, cx, cy, r):
    from ptmcore.images import load_stack
    from reconstruct.calibration.calibrate import calibrate_stack

    if "stack" not in shared:
        shared["stack"] = load_stack(sorted(shared["spheres"].glob("*.png")), min_photographs=1)
    h, w = SPHERE_SHAPE
    fits = bool(0 <= cx < w and 0 <= cy < h and 4 <= r <= h / 2)
    try:
        result = calibrate_stack(shared["stack"], spheres=[(cx, cy, r)])
    except InputError as exc:
        assert not fits, ((cx, cy, r), str(exc))
        assert f"{w}×{h}" in str(exc) or "finite" in str(exc), str(exc)
        return
    assert fits, (cx, cy, r)
    assert result.spheres == [(cx, cy, r)]


@pytest.mark.parametrize("args, needles", [
    (["--intrinsics", "1e12,1e12,80,60"], ["--intrinsics", "1 to 1e+08 pixels"]),
    (["--intrinsics", "400,400,1e9,60"], ["--intrinsics", "principal point"]),
    (["--focal-mm", "1e-300", "--sensor-width-mm", "20"], ["focal length", "1 to 1e+08 pixels"]),
])
def test_calibrate_refuses_a_camera_out_of_range(shared, tmp_path, capsys, args, needles):
    _refused(["calibrate", shared["spheres"], "-o", tmp_path / "lights.lp", *args], capsys, needles, tmp_path)


def test_intrinsics_are_bounded(tmp_path):
    from PIL import Image

    from reconstruct.calibration.camera import Intrinsics, intrinsics_from_exif

    for values in [(1e12, 1e12, 0, 0), (0.5, 400, 0, 0), (400, 400, 0, -2e6)]:
        with pytest.raises(ValueError):
            Intrinsics(*values)
    assert Intrinsics(1.0, 1e8, -1e6, 1e6).fy == 1e8
    # An EXIF focal length of 1e-9 mm on 1e9 pixels per inch of sensor: one line naming the file.
    exif = Image.Exif()
    exif.get_ifd(0x8769).update({0x920A: 1e-9, 0xA20E: 1e9, 0xA210: 2})
    Image.new("RGB", (30, 20)).save(tmp_path / "tiny.jpg", exif=exif)
    with pytest.raises(InputError, match=r"tiny\.jpg: the EXIF's focal length gives no usable camera"):
        intrinsics_from_exif(tmp_path / "tiny.jpg")


# --- every numeric option: within its bound, or one line -----------------------------------

def _whole(text: str) -> int | None:
    """What a whole-number option means by ``text`` (1e8 included), or None."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        return None
    return int(value) if value.is_integer() else None


def _real(text: str) -> float | None:
    """What a number option means by ``text``, or None when not a finite number."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _whole_in(low, high=math.inf):
    return lambda t: (v := _whole(t)) is not None and low <= v <= high


def _size_in(low, high):
    """A side of ``--size WxH``: digits only."""
    def fits(text: str) -> bool:
        try:
            return low <= int(text) <= high
        except ValueError:
            return False
    return fits


def _real_in(low, high, *, open_low: bool = False):
    return lambda t: (v := _real(t)) is not None and (low < v if open_low else low <= v) and v <= high


#: (command and arguments with {v} for the value, documented bound of the value). {missing}
#: is a source that does not exist, so an accepted value ends in its "not found" line;
#: {out} an output in a folder that exists; {file} a regular file (demo's -o below it).
OPTIONS = [
    ("run {missing} -o {out} --pixel-size {v}", _real_in(1e-6, 1e4)),
    ("run {missing} -o {out} --step {v}", _whole_in(1, 100_000)),
    ("run {missing} -o {out} --solid {v}", _real_in(1e-3, 1e6)),
    ("run {missing} -o {out} --flatten highpass --flatten-cutoff {v}", _real_in(2, 1e5)),
    ("run {missing} -o {out} --intrinsics 100,100,16,12 --distance {v}", _real_in(1e-3, 1e6)),
    ("run {missing} -o {out} --intrinsics {v},100,16,12", _real_in(1, 1e8)),
    ("run {missing} -o {out} --intrinsics 100,100,{v},12", _real_in(-1e6, 1e6)),
    ("run {missing} -o {out} --decimate {v}", _whole_in(1)),
    ("run {missing} -o {out} --max-error {v}", _real_in(0, math.inf, open_low=True)),
    ("run {missing} -o {out} --threads {v}", _whole_in(1, 1024)),
    ("run {missing} -o {out} --memory-limit {v}", _real_in(0, math.inf, open_low=True)),
    ("integrate {missing} -o {out} --pixel-size {v}", _real_in(1e-6, 1e4)),
    ("integrate {missing} -o {out} --step {v}", _whole_in(1, 100_000)),
    ("compare {missing} {missing} -o {out} --tolerance {v}", _real_in(1e-6, 1e6)),
    ("compare {missing} {missing} -o {out} --max-distance {v}", _real_in(1e-6, 1e6)),
    ("compare {missing} {missing} -o {out} --tolerance 1 --min-fraction {v}", _real_in(0, 1, open_low=True)),
    ("relight {missing} -o {out} --azimuth {v} --elevation 30", _real_in(-math.inf, math.inf)),
    ("relight {missing} -o {out} --azimuth 30 --elevation {v}", _real_in(0, 90)),
    ("relight {missing} -o {out} --light 0,0,1 --mode specular --kd {v}", _real_in(0, 100)),
    ("relight {missing} -o {out} --light 0,0,1 --mode specular --exponent {v}", _real_in(0, 10_000)),
    ("relight {missing} -o {out} --light 0,0,1 --mode diffuse-gain --gain {v}", _real_in(0, 1000, open_low=True)),
    ("relight {missing} -o {out} --sweep {v}", _whole_in(1, 360)),
    ("relight {missing} -o {out} --sweep 4 --elevation {v}", _real_in(0, 90, open_low=True)),
    ("preview {missing} --screenshot {out} --azimuth {v}", _real_in(-math.inf, math.inf)),
    ("preview {missing} --screenshot {out} --elevation {v}", _real_in(0, 90)),
    ("preview {missing} --screenshot {out} --size {v}x100", _size_in(64, 16384)),
    ("demo -o {file}/demo --lights {v}", _whole_in(3, 1000)),
    ("demo -o {file}/demo --seed {v}", _whole_in(0)),
    ("demo -o {file}/demo --size {v}x100", _size_in(16, 16384)),
    ("calibrate {missing} -o {out} --sphere {v},10,5", _real_in(-math.inf, math.inf)),
    ("calibrate {missing} -o {out} --focal-mm {v} --sensor-width-mm 20", _real_in(0, math.inf, open_low=True)),
]

#: Numbers as people (and slips) write them: whole and decimal, exponents, huge, tiny,
#: negative, NaN and infinities, and a little text.
VALUES = st.one_of(
    st.integers(-10**6, 10**6).map(str),
    st.integers(10**6, 10**40).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-1e7, 1e7).map(lambda v: f"{v:.3g}"),
    st.integers(-400, 400).map(lambda e: f"1e{e}"),
    st.sampled_from(["0", "-0", "1e8", "1e400", "-1e400", "nan", "inf", "0x10", "1_000", " 7 ", "", "x", "1,5"]),
)


@pytest.mark.parametrize("template, bound", OPTIONS, ids=[t.replace("{missing} ", "") for t, _ in OPTIONS])
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=VALUES)
def test_numeric_options_are_bounded(tmp_path, capsys, template, bound, value):
    missing = tmp_path / "missing"
    afile = tmp_path / "afile"
    afile.write_text("")
    before = _tree(tmp_path)
    words = template.split()
    argv = [w.format(missing=missing, out=tmp_path / "out.png", file=afile, v=value) for w in words]
    code, out, err = _call(argv, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (argv, out, err)
    # Taken: the command went on to its source (or demo to its output), which is not there.
    taken = str(missing) in lines[0] or str(afile) in lines[0]
    assert taken == bound(value), (argv, lines[0])
    assert _tree(tmp_path) == before



SYNTHETIC = ["--pixel-size", "--specular", "--shininess", "--ambient", "--noise", "--scan-noise", "--min-elevation",
             "--max-elevation", "--ring-elevation"]


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(option=st.sampled_from(SYNTHETIC + ["--lights", "--scan-points", "--seed"]),
       number=st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([1e300, 1e-300, 1e7, 1e6]),
       whole=st.integers(-10, 10**12) | st.integers(min_value=10**12))
def test_synthetic_capture_values(tmp_path, capsys, option, number, whole):
    # python -m data_synthetic: a capture written without a warning, or one line and nothing.
    import tempfile

    from data_synthetic.__main__ import main as synthetic

    value = repr(number) if option in SYNTHETIC else str(whole)
    folder = Path(tempfile.mkdtemp(dir=tmp_path)) / "cap"
    code = synthetic([str(folder), "--size", "16x16", "--lights", "3", "--scan-points", "0", f"{option}={value}"])
    err = capsys.readouterr().err
    if code == 0:
        assert err == "" and len(list(folder.glob("img_*.tif"))) >= 1, err
    else:
        assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert not folder.exists()
