"""``reconstruct run`` writing and reading .ptm files, and ``reconstruct relight``."""

import dataclasses
import json

import numpy as np
import pytest
from PIL import Image

from reconstruct.cli.main import main

from helpers import run_cli as _run
from ptmcore.images import read_image
from ptmcore.lp import read_lp
from ptmcore.fit import light_matrix
from ptmcore.ptmencoded import fit_ptm_encoded
from ptmcore.ptmfile import read_ptm


@pytest.fixture(scope="module")
def jpeg_result(tmp_path_factory):
    from data_synthetic import write_capture

    root = tmp_path_factory.mktemp("jpeg")
    info = write_capture(root / "cap", "tablet", shape=(90, 120), n_lights=24, encoding="jpeg8", seed=5)
    assert main(["run", str(info.folder), "-o", str(root / "out"), "-q"]) == 0
    return info, root / "out"


def test_run_writes_a_ptm_that_reproduces_the_photographs(jpeg_result):
    info, out = jpeg_result
    ptm = read_ptm(out / "coefficients.ptm")
    assert ptm.format == "PTM_FORMAT_LRGB" and (ptm.width, ptm.height) == (120, 90)
    lights = read_lp(info.lp_path)
    coef, rgb = fit_ptm_encoded(lights.paths, lights.directions)
    to_photo, to_fit = [], []
    for path, d in zip(lights.paths, lights.directions):
        rendered = ptm.render(d).astype(float)
        exact = np.clip(rgb * (coef @ light_matrix(d[None])[0])[..., None] / 255, 0, 255)
        to_photo.append(np.abs(rendered - read_image(path)).mean())
        to_fit.append(np.abs(rendered - exact).mean())
    # The file renders its float fit to within 8-bit quantisation (measured 0.4 levels)...
    assert np.mean(to_fit) < 0.75
    # ...and the photographs as well as a biquadratic can: measured 7.8 levels mean on this
    # scene, whose cast shadows and wedge walls under 15° lights no polynomial follows.
    assert np.mean(to_photo) < 9.0
    report = json.loads((out / "report.json").read_text())
    assert report["ptm"]["format"] == "PTM_FORMAT_LRGB"
    assert len(report["ptm"]["rms_error"]) == 6 and max(report["ptm"]["rms_error"]) < 1.0
    info_json = json.loads((out / "web" / "info.json").read_text())
    # web/ holds the basis chosen for the capture (--basis auto), in Relight's format.
    chosen = report["relighting"]["name"]
    assert info_json["type"] == ("hsh" if chosen.startswith("hsh") else chosen)
    assert all((out / "web" / f"plane_{k}.jpg").exists() for k in range(-(-info_json["nplanes"] // 3)))


def test_rgb_format(tmp_path, capsys, jpeg_result):
    info, _ = jpeg_result
    out = tmp_path / "rgb"
    code, stdout, err = _run(["run", info.folder, "-o", out, "--ptm-format", "rgb", "-q"], capsys)
    assert code == 0, err
    ptm = read_ptm(out / "coefficients.ptm")
    assert ptm.format == "PTM_FORMAT_RGB" and ptm.coefficients.shape == (90, 120, 3, 6)
    # The published basis is fitted to the stack, whatever the .ptm's format.
    assert (out / "web" / "info.json").is_file()


def test_run_from_a_ptm_file(tmp_path, capsys, shared_fixture):
    out = tmp_path / "from_ptm"
    code, stdout, err = _run(["run", shared_fixture / "reference_8x5.ptm", "-o", out, "-q"], capsys)
    assert code == 0, err
    normals = np.load(out / "normals.npy")
    assert normals.shape == (5, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
    for name in ("height.tif", "mesh.ply", "mesh.obj", "albedo.png", "web/info.json"):
        assert (out / name).exists(), name
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["format"] == "PTM_FORMAT_LRGB" and report["parameters"]["normals"] == "ptm"


def test_run_from_our_own_ptm_matches_its_normals(tmp_path, capsys, jpeg_result):
    _, out = jpeg_result
    again = tmp_path / "again"
    code, _, err = _run(["run", out / "coefficients.ptm", "-o", again, "-q"], capsys)
    assert code == 0, err
    assert np.load(again / "normals.npy").shape == (90, 120, 3)


def test_relight_modes_lights_and_sweep(tmp_path, capsys, jpeg_result):
    _, out = jpeg_result
    images = {}
    for name, args in {
        "left": ["--azimuth", "180", "--elevation", "20"],
        "right": ["--light", "1,0,0.35"],
        "specular": ["--light", "1,0,0.35", "--mode", "specular"],
        "gain": ["--light", "1,0,0.35", "--mode", "diffuse-gain", "--gain", "3"],
    }.items():
        code, _, err = _run(["relight", out, "-o", tmp_path / f"{name}.png", *args], capsys)
        assert code == 0, err
        images[name] = np.asarray(Image.open(tmp_path / f"{name}.png")).astype(float)
        assert images[name].shape == (90, 120, 3)
    assert np.abs(images["left"] - images["right"]).mean() > 2
    assert np.abs(images["specular"] - images["right"]).mean() > 1
    assert np.abs(images["gain"] - images["right"]).mean() > 1
    code, _, err = _run(["relight", out / "coefficients.ptm", "--sweep", "6", "-o", tmp_path / "turn.gif"], capsys)
    assert code == 0, err
    with Image.open(tmp_path / "turn.gif") as gif:
        assert gif.n_frames == 6


@pytest.mark.parametrize("layout", ["lrgb", "rgb"])
def test_a_sweep_renders_as_single_lights_do(tmp_path, layout):
    # renders() does the light-independent work once; each frame must be the image of
    # ptmcore.relight's functions called for that light alone (maxima found per band inside).
    from ptmcore.ptmfile import write_ptm
    from ptmcore.relight import as_lrgb, diffuse_gain, relight, specular_enhancement
    from reconstruct.viewer.relighting import MODES, render, renders, sweep_lights

    def alone(ptm, light, mode, **p):
        if mode == "default" and not ptm.is_lrgb:
            return ptm.render(light)
        coef, rgb = as_lrgb(ptm)
        if mode == "specular":
            return specular_enhancement(coef, rgb, light, **p)
        return relight(diffuse_gain(coef, **p) if mode == "diffuse-gain" else coef, rgb, light)

    rng = np.random.default_rng(3)
    # Concave polynomials with their maxima inside the disk, and a few arbitrary ones.
    base = np.array([-60.0, -50.0, 5.0, 20.0, -10.0, 150.0])
    if layout == "lrgb":
        coef = base + rng.normal(scale=15.0, size=(23, 31, 6))
        write_ptm(tmp_path / "t.ptm", coef, rng.integers(0, 256, (23, 31, 3), dtype=np.uint8))
    else:
        write_ptm(tmp_path / "t.ptm", base + rng.normal(scale=15.0, size=(23, 31, 3, 6)))
    ptm = read_ptm(tmp_path / "t.ptm")
    if layout == "lrgb":  # a PTM built in memory may hold float64 coefficients
        ptm = dataclasses.replace(ptm, coefficients=ptm.coefficients.astype(np.float64))
    lights = sweep_lights(5, 25.0)
    for mode in MODES:
        params = {"diffuse-gain": {"gain": 2.5}, "specular": {"kd": 0.5, "ks": 0.8, "exponent": 40.0}}.get(mode, {})
        frames = list(renders(ptm, lights, mode, **params))
        assert len(frames) == len(lights)
        for light, frame in zip(lights, frames):
            expected = alone(ptm, light, mode, **params)
            np.testing.assert_array_equal(frame, expected)
            np.testing.assert_array_equal(render(ptm, light, mode, **params), expected)
        assert any(np.any(frames[0] != f) for f in frames[1:])  # the light moves
    # A bad parameter is refused when the sweep is asked for, before its long work.
    for mode, bad in (("specular", {"ks": -0.5}), ("specular", {"exponent": np.inf}), ("diffuse-gain", {"gain": 0})):
        with pytest.raises(ValueError, match=f"{next(iter(bad))} must be a"):
            renders(ptm, lights, mode, **bad)


@pytest.mark.parametrize(
    "args, needle",
    [
        ([], "give either --light"),
        (["--light", "1,0"], "three numbers"),
        (["--light", "1,0,-1"], "horizon"),
        (["--azimuth", "10"], "go together"),
        (["--light", "0,0,1", "--azimuth", "3", "--elevation", "4"], "give either"),
    ],
)
def test_relight_bad_lights(tmp_path, capsys, jpeg_result, args, needle):
    _, out = jpeg_result
    code, _, err = _run(["relight", out, "-o", tmp_path / "x.png", *args], capsys)
    assert code == 2 and needle in err and err.count("\n") == 1
    assert not (tmp_path / "x.png").exists()


def test_relight_bad_sources(tmp_path, capsys):
    code, _, err = _run(["relight", tmp_path, "-o", tmp_path / "x.png", "--light", "0,0,1"], capsys)
    assert code == 2 and "no coefficients.ptm" in err
    bad = tmp_path / "bad.ptm"
    bad.write_bytes(b"PTM_1.2\nPTM_FORMAT_LRGB\n-5\n")
    code, _, err = _run(["relight", bad, "-o", tmp_path / "x.png", "--light", "0,0,1"], capsys)
    assert code == 2 and "bad.ptm" in err and "Traceback" not in err
    code, _, err = _run(["run", bad, "-o", tmp_path / "o"], capsys)
    assert code == 2 and "bad.ptm" in err


def test_hsh_rti_written_and_relit(tmp_path, capsys, jpeg_result):
    from ptmcore.rtifile import read_rti_hsh

    info, _ = jpeg_result
    out = tmp_path / "hsh"
    code, _, err = _run(["run", info.folder, "-o", out, "--hsh", "-q"], capsys)
    assert code == 0, err
    rti = read_rti_hsh(out / "coefficients.rti")
    assert rti.order == 3 and (rti.width, rti.height) == (120, 90)
    lights = read_lp(info.lp_path)
    # HSH of order 3 follows this tablet better than the PTM (BENCHMARKS.md, leave-one-out).
    hsh_err = np.mean([np.abs(rti.render(d).astype(float) - read_image(p)).mean()
                       for p, d in zip(lights.paths, lights.directions)])
    ptm = read_ptm(out / "coefficients.ptm")
    ptm_err = np.mean([np.abs(ptm.render(d).astype(float) - read_image(p)).mean()
                       for p, d in zip(lights.paths, lights.directions)])
    assert hsh_err < ptm_err
    report = json.loads((out / "report.json").read_text())
    assert report["ptm"]["hsh_rti"]["order"] == 3
    assert not any("HSH" in w for w in report["warnings"])  # 24 lights hold its 9 coefficients
    code, _, err = _run(["relight", out, "--basis", "hsh", "--light", "0.3,0.2,0.9", "-o", tmp_path / "h.png"], capsys)
    assert code == 0, err
    code, _, err = _run(["relight", out / "coefficients.rti", "--light", "0.3,0.2,0.9", "--mode", "specular",
                         "-o", tmp_path / "s.png"], capsys)
    assert code == 2 and "needs a PTM" in err
    code, _, err = _run(["relight", info.folder, "--basis", "hsh", "--light", "0,0,1", "-o", tmp_path / "x.png"], capsys)
    assert code == 2 and "coefficients.rti" in err


def test_hsh_of_few_lights_is_warned(tmp_path, capsys):
    """9 coefficients per channel from 12 photographs: relit between the lights the HSH strays
    (half as bright midway on a 16-light tablet); the run says so, and still writes it."""
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(40, 50), n_lights=12, encoding="jpeg8", seed=2)
    code, _, err = _run(["run", info.folder, "-o", tmp_path / "out", "--hsh", "-q"], capsys)
    assert code == 0, err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert any("HSH of order 3" in w and "12 photographs" in w for w in report["warnings"])
    assert (tmp_path / "out" / "coefficients.rti").is_file()

