"""Relighting files are display-encoded whatever the capture's bit depth (issue 17): a PTM of
16-bit (linear) photographs holds them encoded as sRGB, as viewers show a PTM, unless
``--ptm-encoding linear`` asks for linear light; the normals are still computed in linear light."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli.main import main
from data_synthetic import write_capture
from ptmcore.images import linear_to_srgb, read_image, srgb_to_linear
from ptmcore.lp import read_lp
from ptmcore.ptmencoded import EncodedFit, fit_ptm_encoded, fit_ptm_rgb_encoded
from ptmcore.ptmfile import read_ptm
from ptmcore.reduce import reduce_photographs
from ptmcore.rtifile import fit_rti_hsh


def _directions(n: int) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    e = np.radians(np.linspace(25, 65, n))
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1)


@pytest.fixture(scope="module")
def photographs():
    rng = np.random.default_rng(3)
    return [rng.integers(0, 65536, (13, 17, 3), dtype=np.uint16) for _ in range(9)]


def test_16_bit_photographs_fitted_as_srgb(photographs):
    """The kernel's sRGB table gives the fit of the photographs encoded as sRGB floats."""
    d = _directions(len(photographs))
    as_srgb = [linear_to_srgb(p.astype(np.float64) / 65535).astype(np.float32) for p in photographs]
    c, rgb = fit_ptm_encoded(photographs, d, encoding="srgb", threads=2)
    ref_c, ref_rgb = fit_ptm_encoded(as_srgb, d, threads=2)  # floats: × 255, as stored
    np.testing.assert_allclose(c, ref_c, rtol=1e-4, atol=2e-3)
    assert np.abs(rgb.astype(int) - ref_rgb).max() <= 1  # truncated bytes at a boundary
    np.testing.assert_allclose(fit_ptm_rgb_encoded(photographs, d, encoding="srgb"),
                               fit_ptm_rgb_encoded(as_srgb, d), rtol=1e-4, atol=2e-3)
    np.testing.assert_allclose(fit_rti_hsh(photographs, d, 2, encoding="srgb"), fit_rti_hsh(as_srgb, d, 2),
                               rtol=1e-4, atol=1e-5)
    # Linear files of 16-bit photographs are their samples as stored, bit for bit.
    stored = fit_ptm_encoded(photographs, d)
    linear = fit_ptm_encoded(photographs, d, encoding="linear")
    np.testing.assert_array_equal(stored[0], linear[0])
    np.testing.assert_array_equal(stored[1], linear[1])
    assert np.mean(c[..., 5]) > np.mean(stored[0][..., 5])  # encoded: brighter than linear


def test_8_bit_and_float_photographs(photographs):
    d = _directions(len(photographs))
    bytes8 = [(p >> 8).astype(np.uint8) for p in photographs]
    # sRGB photographs fitted as sRGB are HP's own fit, bit for bit.
    np.testing.assert_array_equal(fit_ptm_encoded(bytes8, d, encoding="srgb")[0], fit_ptm_encoded(bytes8, d)[0])
    decoded = [srgb_to_linear(b.astype(np.float64) / 255).astype(np.float32) for b in bytes8]
    np.testing.assert_allclose(fit_ptm_encoded(bytes8, d, encoding="linear")[0], fit_ptm_encoded(decoded, d)[0],
                               rtol=1e-4, atol=2e-3)
    # 8-bit photographs taken as linear (--no-linearize) are encoded for display.
    encoded = [linear_to_srgb(b.astype(np.float64) / 255).astype(np.float32) for b in bytes8]
    np.testing.assert_allclose(fit_ptm_encoded(bytes8, d, encoding="srgb", linearize=False)[0],
                               fit_ptm_encoded(encoded, d)[0], rtol=1e-4, atol=2e-3)
    # Float TIFFs: the curve computed in the kernel.
    floats = [p.astype(np.float32) / 60000 - 0.02 for p in photographs]  # some below 0, some above 1
    clipped = [linear_to_srgb(np.clip(f, 0, 1).astype(np.float64)).astype(np.float32) for f in floats]
    np.testing.assert_allclose(fit_ptm_encoded(floats, d, encoding="srgb")[0], fit_ptm_encoded(clipped, d)[0],
                               rtol=1e-4, atol=2e-3)


def test_encoding_must_be_known():
    with pytest.raises(ValueError, match="encoding"):
        EncodedFit(_directions(6), encoding="gamma")


def test_stack_does_not_depend_on_the_files_encoding(photographs):
    d = _directions(len(photographs))
    a = reduce_photographs(photographs, fit=EncodedFit(d, encoding="srgb"), threads=2)
    b = reduce_photographs(photographs, fit=EncodedFit(d, encoding="linear"), threads=2)
    np.testing.assert_array_equal(a.luminance, b.luminance)
    np.testing.assert_array_equal(a.chroma, b.chroma)


@pytest.fixture(scope="module")
def capture16(tmp_path_factory):
    folder = tmp_path_factory.mktemp("enc") / "cap"
    write_capture(folder, "tablet", shape=(48, 64), n_lights=16, encoding="tiff16", seed=2)
    return folder


def _display_mean(path) -> float:
    """Mean brightness, 0..255, of a 16-bit linear photograph shown as a photograph is shown."""
    return float(np.mean(255 * linear_to_srgb(read_image(path).astype(np.float64) / 65535)))


@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_relit_16_bit_capture_is_as_bright_as_its_photographs(capture16, tmp_path, encoding):
    """`reconstruct relight` under a photograph's light is as bright as that photograph shown
    on a screen, whichever encoding the files hold."""
    out = tmp_path / "out"
    assert main(["run", str(capture16), "-o", str(out), "--ptm-encoding", encoding]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["ptm"]["encoding"] == {"srgb": "sRGB", "linear": "linear"}[encoding]
    # The web page knows what its planes hold (the published basis's own encoding, chosen with
    # it: --basis-encoding), and has the run's normal and height maps.
    viewer = json.loads((out / "web" / "viewer.json").read_text())
    assert viewer["encoding"] == report["relighting"]["encoding"] and set(viewer["layers"]) == {"normals", "height"}
    assert all((out / "web" / layer["src"]).is_file() for layer in viewer["layers"].values())
    lights = read_lp(next(capture16.glob("*.lp")))
    for k in (0, len(lights) // 2):
        x, y, z = lights.directions[k]
        png = tmp_path / f"relit_{encoding}_{k}.png"
        assert main(["relight", str(out), "--light", f"{x},{y},{z}", "-o", str(png)]) == 0
        relit = read_image(png).astype(np.float64)
        shown = _display_mean(lights.paths[k])
        assert abs(relit.mean() - shown) < 0.08 * shown, (relit.mean(), shown)


def test_ptm_file_of_16_bit_capture_is_display_encoded(capture16, tmp_path):
    """What RTIViewer shows of the .ptm: its colour times its luminance, about the photographs'
    display brightness (it was the linear brightness, several times darker in the shadows)."""
    out = tmp_path / "out"
    assert main(["run", str(capture16), "-o", str(out)]) == 0
    ptm = read_ptm(out / "coefficients.ptm")
    lights = read_lp(next(capture16.glob("*.lp")))
    shown = np.mean([_display_mean(p) for p in lights.paths])
    relit = np.mean([ptm.render(d).astype(np.float64).mean() for d in lights.directions])
    assert abs(relit - shown) < 0.08 * shown, (relit, shown)


def test_a_run_from_a_linear_ptm_publishes_it_as_linear(capture16, tmp_path):
    """`reconstruct run coefficients.ptm` of a run whose report.json says the PTM holds linear
    light writes web/ saying so, so the page and `reconstruct relight` encode it for display."""
    first = tmp_path / "first"
    assert main(["run", str(capture16), "-o", str(first), "--ptm-encoding", "linear", "--outputs", "relight"]) == 0
    again = tmp_path / "again"
    assert main(["run", str(first / "coefficients.ptm"), "-o", str(again)]) == 0
    assert json.loads((again / "web" / "viewer.json").read_text())["encoding"] == "linear"
    plain = tmp_path / "plain"
    (plain / "in").mkdir(parents=True)
    (plain / "in" / "c.ptm").write_bytes((first / "coefficients.ptm").read_bytes())  # no report beside it
    assert main(["run", str(plain / "in" / "c.ptm"), "-o", str(plain / "out")]) == 0
    assert json.loads((plain / "out" / "web" / "viewer.json").read_text())["encoding"] == "srgb"
