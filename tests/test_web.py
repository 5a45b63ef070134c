import json
import math
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


# ---------------------------------------------------------------------------------------------
# export_relightable: every basis in Relight's web format, decoded as OpenLIME decodes it


from xml.etree import ElementTree  # noqa: E402

from ptmcore.hsh import hsh_basis  # noqa: E402
from ptmcore.published import PublishedBasis  # noqa: E402
from reconstruct.report.web import DZ_OVERLAP, DZ_TILE_SIZE, export_relightable, pyramid_levels  # noqa: E402

#: Lights of the comparisons, unit (x, y, z); all above OpenLIME's HSH horizon margin (0.15 rad).
UNIT_LIGHTS = [light_direction(azimuth_deg=a, elevation_deg=e) for a, e in LIGHTS]


def _waves(h, w, k, rng):
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.zeros((h, w, k))
    for i in range(k):
        for _ in range(3):
            fx, fy = rng.uniform(0.5, 4, 2) * 2 * np.pi / np.array([w, h])
            out[..., i] += np.sin(fx * cols + fy * rows + rng.uniform(0, 2 * np.pi)) / 3
    return out


def _colour(h, w, rng):
    return np.clip(128 + 100 * _waves(h, w, 3, rng), 0, 255).astype(np.uint8)


def _orthonormal(d, k, rng):
    """K orthonormal RGB components over D directions, (K, D, 3)."""
    q, _ = np.linalg.qr(rng.normal(size=(3 * d, k)))
    return q.T.reshape(k, d, 3)


def _network(hidden, rng):
    """A random decoder (k = 9) whose output under a light is mostly within 0–1 and changes
    with the light as much as with the code."""
    layers = []
    for a, b in ((11, hidden), (hidden, hidden), (hidden, 3)):
        layers.append((rng.normal(0, 1 / np.sqrt(a), (a, b)).astype(np.float32),
                       rng.normal(0, 0.1, b).astype(np.float32)))
    layers[0][0][9:] *= 3
    layers[2][0][...] *= 0.25
    layers[2][1][...] = 0.5
    return layers


def make_basis(kind, h=48, w=64, seed=0, encoding="srgb"):
    """A small synthetic PublishedBasis: smooth random planes, relit values mostly within 0–1."""
    rng = np.random.default_rng(seed)
    if kind == "neural":
        # 30 hidden units: padded to 32 in OpenLIME's layout.
        return PublishedBasis("neural", "rgb", (2 * _waves(h, w, 9, rng)).astype(np.float32), encoding,
                              network=_network(30, rng), name="neural")
    if kind == "ptm":
        planes = 0.15 * _waves(h, w, 6, rng)
        planes[..., 0] += 0.6
        return PublishedBasis("ptm", "lrgb", planes.astype(np.float32), encoding, colour=_colour(h, w, rng), name="ptm")
    if kind.startswith("hsh"):
        order = int(kind[3:])
        planes = 0.2 * _waves(h, w, order * order, rng)
        planes[..., 0] += 1.5  # H0 = 1/√(2π): a mean luminance of 0.6
        return PublishedBasis("hsh", "lrgb", planes.astype(np.float32), encoding, colour=_colour(h, w, rng),
                              order=order, name=kind)
    if kind == "rbf":
        d, k = 24, 5  # 5 planes: two JPEGs, the last with one empty channel
        lights = dome(d, seed=seed)
        basis = np.concatenate([rng.uniform(0.3, 0.6, (1, d, 3)), _orthonormal(d, k, rng)])
        planes = 0.8 * _waves(h, w, k, rng)
        return PublishedBasis("rbf", "mrgb", planes.astype(np.float32), encoding, lights=lights, sigma=0.35,
                              basis=basis.astype(np.float32), name="rbf")
    r, k = 5, 7
    basis = np.concatenate([rng.uniform(0.3, 0.6, (1, r * r, 3)), _orthonormal(r * r, k, rng)])
    planes = 0.8 * _waves(h, w, k, rng)
    return PublishedBasis("bln", "mrgb", planes.astype(np.float32), encoding, resolution=r,
                          basis=basis.astype(np.float32), name="bilinear")


def _read_plane(folder, j, info):
    """Plane j's bytes (H, W, 3): the whole JPEG, or the finest level of its pyramid stitched
    back, each tile without its overlap."""
    whole = folder / f"plane_{j}.{info['format']}"
    if whole.exists():
        return np.asarray(Image.open(whole).convert("RGB"))
    dzi = ElementTree.parse(folder / f"plane_{j}.dzi").getroot()
    size, over = int(dzi.get("TileSize")), int(dzi.get("Overlap"))
    h, w = info["height"], info["width"]
    top = len(pyramid_levels(w, h, size)) - 1
    out = np.zeros((h, w, 3), np.uint8)
    for y in range(-(-h // size)):
        for x in range(-(-w // size)):
            tile = np.asarray(Image.open(folder / f"plane_{j}_files/{top}/{x}_{y}.{dzi.get('Format')}").convert("RGB"))
            ox, oy = (over if x else 0), (over if y else 0)
            part = out[y * size:(y + 1) * size, x * size:(x + 1) * size]
            part[...] = tile[oy:oy + part.shape[0], ox:ox + part.shape[1]]
    return out


def _elu(z):
    return np.where(z > 0, z, np.expm1(np.minimum(z, 0)))


def openlime_neural(folder, light):
    """The folder rendered as OpenLIME's ShaderNeural renders it, written from its source: the
    planes plane_1…plane_3 swizzled by ``colorspace``, rescaled by min and max, and the three
    layers read from the flat padded arrays as ``layerN_weights[cols/4 · i + j]`` (vec4 j of
    output i); the codes as decoded, (H, W, 9), and the rendering (H, W, 3), 0–1 before clipping."""
    info = json.loads((folder / "info.json").read_text())
    swizzle = ["rgb".index(c) for c in info["colorspace"]]
    tex = np.concatenate([_read_plane(folder, j, info)[..., swizzle] for j in (1, 2, 3)], axis=-1) / 255.0
    low, high = np.ravel(info["min"]), np.ravel(info["max"])
    codes = tex * (high - low) + low
    n = -(-info["samples"] // 4) * 4
    c = -(-(info["planes"] + 2) // 4) * 4
    w1, w2, w3 = (np.reshape(info["weights"][i], shape) for i, shape in enumerate([(n, c), (n, n), (3, n)]))
    b1, b2, b3 = (np.asarray(b) for b in info["biases"])
    x = np.zeros(codes.shape[:2] + (c,))
    x[..., : info["planes"]] = codes
    x[..., info["planes"]: info["planes"] + 2] = light[:2]
    h1 = _elu(x @ w1.T + b1)
    h2 = _elu(h1 @ w2.T + b2)
    return codes, (h2 @ w3.T + b3)[..., swizzle]


def _decoded(folder):
    """info.json, and every channel's value as OpenLIME's shader computes it: (byte/255 − bias)·scale,
    (H, W, 3·njpegs), with the bytes."""
    info = json.loads((folder / "info.json").read_text())
    material = info["materials"][0]
    n = -(-info["nplanes"] // 3)
    raw = np.concatenate([_read_plane(folder, j, info) for j in range(n)], axis=-1)
    scale, bias = np.array(material["scale"]), np.array(material["bias"])
    return info, (raw / 255.0 - bias) * scale, raw


def _openlime_hsh(light):
    """ShaderRTI's HSH.lightWeights, its 9 terms, with its constants (π as 3.1415, 0.15 rad)."""
    pi = 3.1415
    phi = np.arctan2(light[1], light[0])
    phi = phi + 2 * pi if phi < 0 else phi
    theta = min(np.arccos(light[2]), pi / 2 - 0.15)
    cp, ct = np.cos(phi), np.cos(theta)
    ct2 = ct * ct
    s = np.sqrt(ct - ct2)
    k = np.sqrt(30 / pi)
    return np.array([1 / np.sqrt(2 * pi), np.sqrt(6 / pi) * cp * s, np.sqrt(3 / (2 * pi)) * (-1 + 2 * ct),
                     np.sqrt(6 / pi) * s * np.sin(phi), k * np.cos(2 * phi) * (-ct + ct2),
                     k * cp * (-1 + 2 * ct) * s, np.sqrt(5 / (2 * pi)) * (1 - 6 * ct + 6 * ct2),
                     k * (-1 + 2 * ct) * s * np.sin(phi), k * (-ct + ct2) * np.sin(2 * phi)])


def _openlime_rbf(lights, sigma, light):
    """ShaderRTI's RBF.rbf: normalised exp(−d²/σ²), weights ≤ 0.001 dropped, renormalised."""
    w = np.exp(-np.sum((lights - light) ** 2, axis=1) / sigma ** 2)
    w /= w.sum()
    w[w <= 0.001] = 0
    return w / w.sum()


def _openlime_bln(resolution, light):
    """ShaderRTI's BLN.lightWeights as weights of the R² nodes (node x + y·R)."""
    s = np.abs(light).sum()
    x = ((light[0] + light[1]) / s + 1) / 2 * (resolution - 1)
    y = ((light[1] - light[0]) / s + 1) / 2 * (resolution - 1)
    sx, sy = (int(min(resolution - 2, max(0, np.floor(v)))) for v in (x, y))
    dx, dy = x - sx, y - sy
    w = np.zeros(resolution * resolution)
    for (ix, iy), v in {(sx, sy): (1 - dx) * (1 - dy), (sx + 1, sy): dx * (1 - dy),
                        (sx, sy + 1): (1 - dx) * dy, (sx + 1, sy + 1): dx * dy}.items():
        w[ix + iy * resolution] += v
    return w


def lrgb_weights(info, extras, light):
    """The weight of every coefficient channel: OpenLIME's PTM and HSH (order ≤ 3); for HSH of
    order 4, which only this project's page shows, the page's (ptmcore.hsh) terms."""
    channels = info["nplanes"] - 3
    if info["type"] == "ptm":
        terms = np.array([1.0, light[0], light[1], light[0] ** 2, light[0] * light[1], light[1] ** 2])
    elif extras["order"] <= 3:
        terms = _openlime_hsh(light)
    else:
        terms = hsh_basis(np.reshape(light, (1, 3)), extras["order"])[0]
    return np.resize(terms, channels) if len(terms) < channels else terms[:channels]


def mrgb_basis(info):
    """ShaderRTI.loadBasis: (nplanes + 1, D, 3), row 0 byte/255, rows p ≥ 1 (byte − 127)/range[p − 1]."""
    raw = np.array(info["basis"], np.float64).reshape(info["nplanes"] + 1, -1, 3)
    ranges = np.array(info["materials"][0]["range"])
    return np.concatenate([raw[:1] / 255.0, (raw[1:] - 127.0) / ranges[:, None, None]])


def mrgb_light_basis(info, basis, light):
    """OpenLIME's RBF/BLN lightWeights: B_p = Σ_d v_d · basis[p, d], (nplanes + 1, 3)."""
    if info["type"] == "rbf":
        v = _openlime_rbf(np.reshape(info["lights"], (-1, 3)), info["sigma"], light)
    else:
        v = _openlime_bln(info["resolution"], light)
    return np.einsum("d,pdc->pc", v, basis)


def openlime_render(folder, light):
    """The folder rendered as OpenLIME's shader renders it (before clipping), 0–1."""
    info, values, _ = _decoded(folder)
    extras = json.loads((folder / "viewer.json").read_text())
    if info["colorspace"] == "lrgb":
        w = lrgb_weights(info, extras, light)
        return values[..., :3] * (values[..., 3:] @ w)[..., None]
    b = mrgb_light_basis(info, mrgb_basis(info), light)
    return b[0] + values[..., : info["nplanes"]] @ b[1:]


KINDS = ["ptm", "hsh2", "hsh3", "hsh4", "rbf", "bln"]


@pytest.mark.parametrize("tiles", [False, True])
@pytest.mark.parametrize("kind", KINDS)
def test_openlime_decoding_matches_the_basis(tmp_path, kind, tiles):
    """Decoded as OpenLIME decodes it, the folder renders the basis' own formula to within a
    bound derived from the quantisation and the JPEG error, at every light.

    A coefficient value is within ``scale · (0.5 + J) / 255`` (half a quantisation step, then J
    levels of JPEG error, measured here against the exact bytes: at quality 100, J ≤ 2 for
    whole RGB planes and J ≤ 4 for YCbCr tiles); the
    colour within J/255; an MRGB basis row within 0.5/255 (mean) or 0.5/range (components; the
    light's weights are non-negative and sum to 1). The bound of the rendering follows by the
    triangle inequality, per pixel; for HSH it adds OpenLIME's own constants (π as 3.1415, the
    horizon margin) times the coefficients.
    """
    basis = make_basis(kind, h=60, w=300 if tiles else 80)
    folder = tmp_path / "web"
    export_relightable(folder, basis, quality=100, tiles=tiles)
    info, values, raw = _decoded(folder)
    extras = json.loads((folder / "viewer.json").read_text())
    material = info["materials"][0]
    scale, bias = np.array(material["scale"]), np.array(material["bias"])
    k = basis.planes.shape[2]
    first = 3 if info["colorspace"] == "lrgb" else 0
    exact = np.zeros(raw.shape)
    exact[..., first:first + k] = (basis.planes - (-bias[first:first + k] * scale[first:first + k])) / np.where(
        scale[first:first + k] > 0, scale[first:first + k], 1) * 255
    if first:
        exact[..., :3] = basis.colour
    jpeg = np.abs(raw - np.rint(exact)).max()
    # Whole planes are RGB JPEGs; libvips' tiles YCbCr, whose conversion rounds twice more.
    assert jpeg <= (4 if tiles else 2), jpeg
    eps = scale * (0.5 + jpeg) / 255  # per channel
    eps[:first] = jpeg / 255
    # Channels past the basis' terms are exactly zero (scale 0) whatever their bytes.
    assert np.all(values[..., first + k:] == 0)
    for light in UNIT_LIGHTS:
        viewer = openlime_render(folder, light)
        expected = basis.render(light).astype(np.float64)
        if info["colorspace"] == "lrgb":
            w = lrgb_weights(info, extras, light)
            exact_w = basis.weights(light)
            delta = np.abs(w[:k] - exact_w)
            colour = basis.colour / 255.0
            lum = values[..., 3:] @ w
            bound = eps[0] * np.abs(lum)[..., None] + colour * (
                (np.abs(w) * eps[3:]).sum() + (np.abs(basis.planes) @ delta)[..., None])
        else:
            ranges = np.array(material["range"])
            b = mrgb_light_basis(info, mrgb_basis(info), light)
            bound = 0.5 / 255 + np.abs(b[1:k + 1]).T @ eps[:k] + (np.abs(basis.planes) @ (0.5 / ranges[:k]))[..., None]
        err = np.abs(viewer - expected)
        assert np.all(err <= bound + 1e-6), (kind, light, (err - bound).max())
        assert bound.max() < 0.06, bound.max()  # the bound says something: a few levels at most
        assert err.mean() < 0.01, err.mean()


@pytest.mark.parametrize("tiles", [False, True])
def test_openlime_neural_decoding_matches_the_basis(tmp_path, tiles):
    """Decoded as OpenLIME's ShaderNeural decodes it (a NumPy transcription of its padded
    layout), the folder gives the network's own rendering of the codes it holds, to float32
    rounding; those codes are the basis' within half a quantisation step plus J levels of JPEG
    error (J as in test_openlime_decoding_matches_the_basis); and so the rendering is the
    basis' within a few levels. Measured at quality 100: mean |Δ| 0.0009 (whole planes) and
    0.0019 (tiles), max 0.006 and 0.014 (1.5 and 3.5 levels); the tolerances are a mean of
    0.003 and a max of 0.02."""
    basis = make_basis("neural", h=60, w=300 if tiles else 80)
    folder = tmp_path / "web"
    export_relightable(folder, basis, quality=100, tiles=tiles)
    info = json.loads((folder / "info.json").read_text())
    low, high = np.array(info["min"]), np.array(info["max"])
    np.testing.assert_array_equal(np.float32(low), basis.planes.reshape(-1, 9).min(0))
    np.testing.assert_array_equal(np.float32(high), basis.planes.reshape(-1, 9).max(0))
    codes, _ = openlime_neural(folder, UNIT_LIGHTS[0])
    step = (high - low) / 255
    raw = np.concatenate([_read_plane(folder, j, info) for j in (1, 2, 3)], axis=-1)
    jpeg = np.abs(raw - np.rint((basis.planes - low) / step)).max()
    assert jpeg <= (4 if tiles else 2), jpeg
    assert np.all(np.abs(codes - basis.planes) <= step * (0.5 + jpeg) + 1e-6)
    held = _replace(basis, planes=codes.astype(np.float32))
    for light in UNIT_LIGHTS:
        _, viewer = openlime_neural(folder, light)
        np.testing.assert_allclose(viewer, held.render(light), atol=2e-5)
        err = np.abs(viewer - basis.render(light))
        assert err.mean() < 0.003 and err.max() < 0.02, (light, err.mean(), err.max())


def test_info_json_of_a_neural_basis(tmp_path):
    """OpenLIME's NeuralRTI keys, its plane names from 1, and the network padded as ShaderNeural
    indexes it, every number the float32 it was."""
    basis = make_basis("neural")
    written = export_relightable(tmp_path, basis, quality=90, tiles=False, pixel_size_mm=0.02)
    assert [p.name for p in written] == ["plane_1.jpg", "plane_2.jpg", "plane_3.jpg", "info.json", "viewer.json",
                                         "index.html"]
    info = json.loads((tmp_path / "info.json").read_text())
    assert list(info) == ["width", "height", "format", "pixelSizeInMM", "type", "colorspace", "planes", "samples",
                          "quality", "min", "max", "weights", "biases"]
    assert (info["type"], info["colorspace"], info["planes"], info["samples"]) == ("neural", "rgb", 9, 30)
    assert (info["width"], info["height"], info["quality"]) == (64, 48, 90)
    assert [len(w) for w in info["weights"]] == [32 * 12, 32 * 32, 3 * 32]
    assert [len(b) for b in info["biases"]] == [32, 32, 3]
    (w1, b1), (w2, b2), (w3, b3) = basis.network
    m1 = np.float32(info["weights"][0]).reshape(32, 12)
    np.testing.assert_array_equal(m1[:30, :11], w1.T)
    assert not m1[30:].any() and not m1[:, 11].any()
    m2 = np.float32(info["weights"][1]).reshape(32, 32)
    np.testing.assert_array_equal(m2[:30, :30], w2.T)
    assert not m2[30:].any() and not m2[:, 30:].any()
    m3 = np.float32(info["weights"][2]).reshape(3, 32)
    np.testing.assert_array_equal(m3[:, :30], w3.T)
    assert not m3[:, 30:].any()
    for got, want in zip(info["biases"], (b1, b2, b3)):
        np.testing.assert_array_equal(np.float32(got)[: want.size], want)
        assert not np.any(got[want.size:])
    extras = json.loads((tmp_path / "viewer.json").read_text())
    assert extras == {"encoding": "srgb", "layers": {}, "basis": "neural", "terms": 9, "layout": "image"}
    export_relightable(tmp_path / "tiled", basis, tiles=True)
    names = sorted(p.name for p in (tmp_path / "tiled").iterdir())
    assert names == ["index.html", "info.json", "plane_1.dzi", "plane_1_files", "plane_2.dzi", "plane_2_files",
                     "plane_3.dzi", "plane_3_files", "viewer.json"]


def test_info_json_per_type(tmp_path):
    """The keys Relight writes for each type, in the types and shapes OpenLIME reads."""
    for kind, keys in {
        "ptm": ["width", "height", "format", "type", "colorspace", "nplanes", "quality", "materials"],
        "hsh2": ["width", "height", "format", "type", "colorspace", "nplanes", "quality", "materials"],
        "rbf": ["width", "height", "format", "type", "colorspace", "sigma", "lights", "nplanes", "quality",
                "basis", "materials"],
        "bln": ["width", "height", "format", "type", "resolution", "colorspace", "nplanes", "quality", "basis",
                "materials"],
    }.items():
        basis = make_basis(kind)
        folder = tmp_path / kind
        written = export_relightable(folder, basis, quality=90, tiles=False)
        info = json.loads((folder / "info.json").read_text())
        assert list(info) == keys
        njpegs = -(-info["nplanes"] // 3)
        assert [p.name for p in written] == [f"plane_{j}.jpg" for j in range(njpegs)] + [
            "info.json", "viewer.json", "index.html"]
        assert info["nplanes"] % 3 == 0
        material = info["materials"][0]
        assert all(len(material[key]) == info["nplanes"] for key in material)
        extras = json.loads((folder / "viewer.json").read_text())
        assert extras["layout"] == "image" and extras["terms"] == basis.planes.shape[2]
        assert extras["basis"] == basis.name and extras["encoding"] == "srgb"
        if kind == "ptm":
            assert (info["type"], info["colorspace"], info["nplanes"]) == ("ptm", "lrgb", 9)
        if kind == "hsh2":
            # 4 terms in 6 channels: nplanes a multiple of 3 for OpenLIME's vec3 uniforms.
            assert (info["type"], info["nplanes"], extras["order"]) == ("hsh", 9, 2)
            assert material["scale"][-2:] == [0.0, 0.0] and material["bias"][-2:] == [0.0, 0.0]
        if kind == "rbf":
            assert info["colorspace"] == "mrgb" and info["nplanes"] == 6 and info["sigma"] == pytest.approx(0.35)
            np.testing.assert_allclose(np.reshape(info["lights"], (-1, 3)), basis.lights)
        if kind == "bln":
            assert info["type"] == "bilinear" and info["resolution"] == 5 and info["nplanes"] == 9
        if info["colorspace"] == "mrgb":
            d = len(info["lights"]) // 3 if kind == "rbf" else info["resolution"] ** 2
            assert len(info["basis"]) == (info["nplanes"] + 1) * d * 3
            assert all(isinstance(b, int) and 0 <= b <= 255 for b in info["basis"])
            rows = np.reshape(info["basis"], (info["nplanes"] + 1, d, 3))
            k = basis.planes.shape[2]
            assert (rows[k + 1:] == 127).all()  # padding components are zero
            # Relight's ranges: each component's bytes reach 127 ± 127.
            assert all(np.abs(rows[p] - 127).max() == 127 for p in range(1, k + 1))


def test_hsh_order_4_is_rendered_from_16_planes(tmp_path):
    basis = make_basis("hsh4")
    export_relightable(tmp_path, basis, tiles=False)
    info = json.loads((tmp_path / "info.json").read_text())
    extras = json.loads((tmp_path / "viewer.json").read_text())
    assert (info["nplanes"], extras["order"], extras["terms"]) == (21, 4, 16)


def test_tiled_pyramid_layout(tmp_path):
    """The .dzi, the levels and the tile grid of each plane, as OpenLIME's "deepzoom" layout reads them."""
    h, w = 300, 1017  # odd: levels are halved rounding up
    basis = make_basis("rbf", h=h, w=w)
    written = export_relightable(tmp_path, basis, tiles=True)
    info = json.loads((tmp_path / "info.json").read_text())
    njpegs = -(-info["nplanes"] // 3)
    names = [p.name for p in written]
    assert names == [n for j in range(njpegs) for n in (f"plane_{j}.dzi", f"plane_{j}_files")] + [
        "info.json", "viewer.json", "index.html"]
    levels = pyramid_levels(w, h)
    assert levels == [(128, 38), (255, 75), (509, 150), (1017, 300)]
    # OpenLIME: nlevels = ceil(log2(max side / tile size)) + 1, level 0 the single tile.
    assert len(levels) == math.ceil(math.log2(max(w, h) / DZ_TILE_SIZE)) + 1
    extras = json.loads((tmp_path / "viewer.json").read_text())
    assert extras["layout"] == "deepzoom"
    assert extras["tiles"] == {"format": "jpg", "size": DZ_TILE_SIZE, "overlap": DZ_OVERLAP,
                               "levels": [list(level) for level in levels]}
    for j in range(njpegs):
        dzi = ElementTree.parse(tmp_path / f"plane_{j}.dzi").getroot()
        assert dzi.tag == "{http://schemas.microsoft.com/deepzoom/2008}Image"
        assert (dzi.get("Format"), dzi.get("Overlap"), dzi.get("TileSize")) == ("jpg", "1", "254")
        size = dzi.find("{http://schemas.microsoft.com/deepzoom/2008}Size")
        assert (size.get("Width"), size.get("Height")) == (str(w), str(h))
        files = tmp_path / f"plane_{j}_files"
        assert sorted(p.name for p in files.iterdir()) == [str(n) for n in range(len(levels))]
        for level, (lw, lh) in enumerate(levels):
            cols, rows = -(-lw // 254), -(-lh // 254)
            tiles = {p.name for p in (files / str(level)).iterdir()}
            assert tiles == {f"{x}_{y}.jpg" for x in range(cols) for y in range(rows)}
            for x in range(cols):
                for y in range(rows):
                    x0, y0 = max(0, 254 * x - 1), max(0, 254 * y - 1)
                    x1, y1 = min(lw, 254 * (x + 1) + 1), min(lh, 254 * (y + 1) + 1)
                    assert Image.open(files / str(level) / f"{x}_{y}.jpg").size == (x1 - x0, y1 - y0)
    # No staging folder is left.
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_stitched_tiles_give_the_planes(tmp_path):
    basis = make_basis("bln", h=270, w=530)
    export_relightable(tmp_path / "whole", basis, quality=100, tiles=False)
    export_relightable(tmp_path / "tiled", basis, quality=100, tiles=True)
    _, _, whole = _decoded(tmp_path / "whole")
    _, _, tiled = _decoded(tmp_path / "tiled")
    assert tiled.shape == whole.shape
    # Two JPEG encodings of the same bytes, each within J of them (2 for RGB planes, 4 for
    # YCbCr tiles: test_openlime_decoding_matches_the_basis), so within 6 of each other; a seam or
    # a shifted tile would be off by tens of levels along its edge.
    diff = np.abs(tiled.astype(int) - whole)
    assert diff.max() <= 6 and diff.mean() < 0.5, (diff.max(), diff.mean())


def test_auto_tiles_above_the_threshold(tmp_path):
    basis = make_basis("ptm", h=40, w=90)
    export_relightable(tmp_path / "a", basis, tile_threshold=100)
    assert (tmp_path / "a" / "plane_0.jpg").exists()
    export_relightable(tmp_path / "b", basis, tile_threshold=89)
    assert (tmp_path / "b" / "plane_0.dzi").exists() and not (tmp_path / "b" / "plane_0.jpg").exists()


def test_a_failing_pyramid_leaves_nothing_partial(tmp_path, monkeypatch):
    import pyvips

    real = pyvips.Image.dzsave
    calls = []

    def failing(self, *args, **kwargs):
        calls.append(1)
        real(self, *args, **kwargs)  # the tiles are written, then the disk "fills up"
        if len(calls) == 2:
            raise pyvips.Error("unable to write tile", "no space left on device")

    monkeypatch.setattr(pyvips.Image, "dzsave", failing)
    with pytest.raises(InputError, match="tiles of plane_1"):
        export_relightable(tmp_path, make_basis("ptm", h=40, w=300), tiles=True)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["plane_0.dzi", "plane_0_files"]  # plane_1 all or nothing; no info.json yet


def test_rewriting_a_pyramid_replaces_it(tmp_path):
    export_relightable(tmp_path, make_basis("ptm", h=40, w=600, seed=1), tiles=True)
    export_relightable(tmp_path, make_basis("ptm", h=40, w=300, seed=2), tiles=True)
    levels = sorted(p.name for p in (tmp_path / "plane_0_files").iterdir())
    assert levels == ["0", "1"]  # the 600-pixel pyramid's third level is gone
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def _replace(published, **changes):
    from dataclasses import replace

    return replace(published, **changes)


@pytest.mark.parametrize(
    ("change", "message"),
    [({"colorspace": "mrgb"}, "colour space"), ({"colour": None}, "colour"),
     ({"planes": np.zeros((48, 64, 5), np.float32)}, "6 coefficient planes"),
     ({"type": "cubic"}, "basis type"), ({"encoding": "gamma"}, "encoding")],
)
def test_bad_lrgb_bases_are_rejected(tmp_path, change, message):
    with pytest.raises(ValueError, match=message):
        export_relightable(tmp_path / "web", _replace(make_basis("ptm"), **change))
    assert not (tmp_path / "web").exists()


@pytest.mark.parametrize(
    ("kind", "change", "message"),
    [("hsh3", {"order": 4}, "order"), ("rbf", {"sigma": 0.0}, "sigma"),
     ("rbf", {"lights": np.zeros((3, 3))}, "light directions"), ("bln", {"resolution": 4}, "resolution"),
     ("bln", {"basis": np.zeros((3, 25, 3))}, "basis of shape"),
     ("rbf", {"planes": np.full((48, 64, 5), np.nan, np.float32)}, "finite"),
     ("neural", {"planes": np.zeros((48, 64, 8), np.float32)}, "9 code planes"),
     ("neural", {"planes": np.full((48, 64, 9), np.inf, np.float32)}, "codes are not finite"),
     ("neural", {"network": None}, "network"),
     ("neural", {"network": [(np.zeros((11, 4)), np.zeros(4)), (np.zeros((4, 4)), np.zeros(4))]}, "three layers"),
     ("neural", {"network": [(np.zeros((11, 4)), np.zeros(4)), (np.zeros((4, 4)), np.zeros(4)),
                             (np.zeros((4, 3)), np.full(3, np.nan))]}, "network is not finite"),
     ("neural", {"colorspace": "mrgb"}, "colour space")],
)
def test_bad_bases_are_rejected(tmp_path, kind, change, message):
    with pytest.raises(ValueError, match=message):
        export_relightable(tmp_path / "web", _replace(make_basis(kind), **change))
    assert not (tmp_path / "web").exists()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"quality": 0}, "quality"), ({"pixel_size_mm": -2.0}, "pixel size"), ({"tiles": "yes"}, "tiles"),
     ({"tile_threshold": 0}, "tile_threshold")],
)
def test_bad_export_options_are_rejected(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message):
        export_relightable(tmp_path / "web", make_basis("bln"), **kwargs)
    assert not (tmp_path / "web").exists()


def test_unwritable_folder_is_an_input_error(tmp_path):
    (tmp_path / "taken").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        export_relightable(tmp_path / "taken", make_basis("hsh3"))
