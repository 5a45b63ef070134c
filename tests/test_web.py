import json
import os

import numpy as np
import pytest
import simplejpeg
from PIL import Image

from ptmcore.errors import InputError
from ptmcore.fit import fit_matrix
from ptmcore.relight import light_direction, relight
from reconstruct.report.web import PLANE_TERMS, export_openlime, lrgb_planes

from helpers import dome

LIGHTS = [(0, 30), (90, 60), (200, 45), (0, 90), (315, 15), (135, 75)]


def _synthetic_ptm(h=96, w=128):
    """A PTM fitted to a Lambertian, wavy surface, in 0–255 units, and a textured colour."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 6 * np.sin(cols / 9) * np.cos(rows / 13) + 0.002 * (cols - w / 2) ** 2
    dz_drow, dz_dcol = np.gradient(z)
    n = np.stack([-dz_dcol, dz_drow, np.ones_like(z)], -1)  # y up: ∂z/∂y = −∂z/∂row
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    d = dome(40, seed=1)
    lum = 230 * np.clip(np.einsum("hwc,nc->nhw", n, d), 0, None)
    coef = (fit_matrix(d) @ lum.reshape(len(d), -1)).T.reshape(h, w, 6).astype(np.float32)
    base = np.stack(
        [120 + 80 * np.sin(cols / 17), 110 + 60 * np.cos(rows / 11), 90 + 50 * np.sin((rows + cols) / 23)], -1
    )
    base += 40 * ((cols // 16 + rows // 16) % 2)[..., None]  # sharp edges for the JPEG
    return coef, np.clip(base, 0, 255).astype(np.uint8)


def _openlime_dequantise(folder):
    """The three planes' channel values as OpenLIME's shader sees them: (byte/255 − bias)·scale."""
    info = json.loads((folder / "info.json").read_text())
    material = info["materials"][0]
    scale = np.array(material["scale"], np.float64).reshape(-1, 3)
    bias = np.array(material["bias"], np.float64).reshape(-1, 3)
    njpegs = -(-info["nplanes"] // 3)
    values = []
    for j in range(njpegs):
        c = np.asarray(Image.open(folder / f"plane_{j}.{info['format']}").convert("RGB"), np.float64) / 255.0
        values.append((c - bias[j]) * scale[j])
    return info, values


def _openlime_render(values, light):
    """ShaderRTI's LRGB rendering of a PTM: l = Σ base[k]·value_k, color = l·basecolor (0–255 here)."""
    x, y = light[0], light[1]
    base = [1.0, x, y, x * x, x * y, y * y]  # PTM.lightWeights
    lum = np.zeros(values[0].shape[:2])
    for j in range(1, len(values)):
        for c in range(3):
            lum += base[3 * (j - 1) + c] * values[j][..., c]
    return np.clip(lum[..., None] * values[0] * 255.0, 0.0, 255.0)


def test_info_json_keys_and_types(tmp_path):
    coef, rgb = _synthetic_ptm(24, 40)
    written = export_openlime(tmp_path / "web", coef, rgb, pixel_size_mm=0.025, quality=92)
    folder = tmp_path / "web"
    assert written == [folder / f"plane_{j}.jpg" for j in range(3)] + [folder / n for n in ("info.json", "viewer.json", "index.html")]
    info = json.loads((folder / "info.json").read_text())
    assert info["width"] == 40 and info["height"] == 24
    assert isinstance(info["width"], int) and isinstance(info["height"], int)
    assert info["format"] == "jpg"
    assert info["type"] == "ptm"
    assert info["colorspace"] == "lrgb"
    assert info["nplanes"] == 9 and isinstance(info["nplanes"], int)
    assert info["quality"] == 92
    assert info["pixelSizeInMM"] == pytest.approx(0.025) and isinstance(info["pixelSizeInMM"], float)
    assert isinstance(info["materials"], list) and len(info["materials"]) == 1
    material = info["materials"][0]
    for key in ("scale", "bias"):
        assert len(material[key]) == 9
        assert all(isinstance(v, float) and np.isfinite(v) for v in material[key])
    assert material["scale"][:3] == [1.0, 1.0, 1.0] and material["bias"][:3] == [0.0, 0.0, 0.0]
    assert all(s > 0 for s in material["scale"])


def test_pixel_size_only_when_known(tmp_path):
    coef, rgb = _synthetic_ptm(8, 16)
    export_openlime(tmp_path, coef, rgb)
    assert "pixelSizeInMM" not in json.loads((tmp_path / "info.json").read_text())


def test_planes_are_rgb_jpegs_without_subsampling(tmp_path):
    # Coefficients of one plane must not be mixed by a YCbCr transform or subsampled.
    coef, rgb = _synthetic_ptm(16, 24)
    export_openlime(tmp_path, coef, rgb)
    for j in range(3):
        data = (tmp_path / f"plane_{j}.jpg").read_bytes()
        height, width, colorspace, subsampling = simplejpeg.decode_jpeg_header(data)
        assert (height, width, colorspace, subsampling) == (16, 24, "RGB", "444")


def test_openlime_rendering_matches_relight(tmp_path):
    """Decode the JPEGs and render them the way OpenLIME's shader does.

    Measured at quality 95 on this PTM, over the lights below: mean |Δ| ≤ 0.56 and max |Δ| ≤ 2.4
    grey levels against :func:`relight` (which truncates, adding up to 1). The tolerance allows
    mean 1.0 and max 4. Most of the error is the colour plane's JPEG; the coefficient planes
    alone contribute below 0.7 levels.
    """
    coef, rgb = _synthetic_ptm()
    export_openlime(tmp_path, coef, rgb, quality=95)
    info, values = _openlime_dequantise(tmp_path)
    assert len(values) == 3
    for azimuth, elevation in LIGHTS:
        light = light_direction(azimuth_deg=azimuth, elevation_deg=elevation)
        viewer = _openlime_render(values, light)
        expected = relight(coef, rgb, light).astype(np.float64)
        err = np.abs(viewer - expected)
        assert err.mean() < 1.0, (azimuth, elevation, err.mean())
        assert err.max() <= 4.0, (azimuth, elevation, err.max())


def test_plane_channels_hold_the_terms_in_openlime_order(tmp_path):
    # plane_1 = (1, x, y) = (a5, a3, a4), plane_2 = (x², xy, y²) = (a0, a2, a1), in a/255 units.
    assert PLANE_TERMS == ((5, 3, 4), (0, 2, 1))
    rows, cols = np.mgrid[0:32, 0:48].astype(np.float32)
    ramps = [cols, rows, cols + rows, cols - rows, 2 * rows - cols, rows * 0.5 + 3]
    coef = np.stack([(k + 1) * 10 * r / r.max() - 5 * k for k, r in enumerate(ramps)], -1).astype(np.float32)
    rgb = np.full((32, 48, 3), 128, np.uint8)
    export_openlime(tmp_path, coef, rgb)
    _, values = _openlime_dequantise(tmp_path)
    np.testing.assert_allclose(values[0], 128 / 255)
    for j, terms in enumerate(PLANE_TERMS, start=1):
        for c, k in enumerate(terms):
            span = (coef[..., k].max() - coef[..., k].min()) / 255
            np.testing.assert_allclose(values[j][..., c], coef[..., k] / 255, atol=3 * span / 255)


def test_quantisation_covers_the_range_to_half_a_step():
    coef, rgb = _synthetic_ptm(40, 60)
    coef[..., 2] = 7.5  # a constant term
    planes, scale, bias = lrgb_planes(coef, rgb)
    np.testing.assert_array_equal(planes[0], rgb)
    for j, terms in enumerate(PLANE_TERMS, start=1):
        for c, k in enumerate(terms):
            byte = planes[j][..., c]
            s, b = scale[3 * j + c], bias[3 * j + c]
            value = (byte / 255.0 - b) * s
            if k == 2:
                assert (byte == 0).all()
                np.testing.assert_allclose(value, 7.5 / 255, rtol=1e-12)
                continue
            assert byte.min() == 0 and byte.max() == 255
            np.testing.assert_allclose(value, coef[..., k] / 255.0, atol=s / 510 * 1.001)


def test_folder_is_created_and_no_temporaries_are_left(tmp_path):
    coef, rgb = _synthetic_ptm(8, 8)
    folder = tmp_path / "a" / "b"
    written = export_openlime(folder, coef, rgb)
    assert all(p.exists() for p in written)
    assert sorted(os.listdir(folder)) == ["index.html", "info.json", "plane_0.jpg", "plane_1.jpg", "plane_2.jpg",
                                          "viewer.json"]


def test_folder_that_is_a_file_is_an_input_error(tmp_path):
    coef, rgb = _synthetic_ptm(8, 8)
    (tmp_path / "taken").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        export_openlime(tmp_path / "taken", coef, rgb)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"quality": 0}, "quality"), ({"quality": 101}, "quality"), ({"quality": 9.5}, "quality"),
     ({"pixel_size_mm": -1.0}, "pixel size"), ({"pixel_size_mm": float("nan")}, "pixel size"),
     ({"encoding": "gamma"}, "encoding")],
)
def test_bad_options_are_rejected(tmp_path, kwargs, message):
    coef, rgb = _synthetic_ptm(8, 8)
    with pytest.raises(ValueError, match=message):
        export_openlime(tmp_path, coef, rgb, **kwargs)
    assert not any(tmp_path.iterdir())


def test_bad_arrays_are_rejected(tmp_path):
    coef, rgb = _synthetic_ptm(8, 8)
    bad = coef.copy()
    bad[3, 3, 4] = np.nan
    with pytest.raises(ValueError, match="finite"):
        export_openlime(tmp_path, bad, rgb)
    with pytest.raises(ValueError, match="rgb"):
        export_openlime(tmp_path, coef, rgb[:, :5])
    with pytest.raises(ValueError, match="rgb"):
        export_openlime(tmp_path, coef, rgb.astype(np.float32))
