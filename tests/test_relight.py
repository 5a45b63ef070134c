import inspect
import math

import numpy as np
import pytest
from PIL import Image

from ptmcore.errors import InputError
from ptmcore.fit import fit_ptm, light_matrix
from ptmcore.normals import normals_from_ptm, ptm_maximum
from ptmcore.ptmfile import PTMFile, read_ptm, write_ptm
from ptmcore.published import PublishedBasis
from ptmcore.relight import diffuse_gain, light_angles, light_direction, relight, specular_enhancement
from reconstruct.report.web import export_openlime, export_relightable
from reconstruct.report.webread import read_relightable
from reconstruct.viewer.relighting import load_source, render, renders, sweep_lights

from helpers import dome, run_cli, stack_from_luminance

S = math.sqrt(0.5)


def _poly(coef, light):
    """L under a unit light, in float64 (reference evaluation)."""
    return np.asarray(coef, np.float64) @ light_matrix(np.asarray(light, np.float64)[None, :2])[0]


def _at(coef, lu, lv):
    """Each pixel's polynomial at its own light projection (lu, lv), in float64."""
    rows = light_matrix(np.stack([np.ravel(lu), np.ravel(lv)], 1)).reshape(np.shape(coef))
    return np.einsum("hwk,hwk->hw", np.asarray(coef, np.float64), rows)


def _with_maximum_at(lu0, lv0, value, a0=-60.0, a1=-45.0, a2=15.0):
    """Concave polynomials (0–255 units) whose maximum over the disk is ``value`` at (lu0, lv0)."""
    lu0, lv0, value, a0, a1, a2 = np.broadcast_arrays(
        *(np.asarray(x, np.float64) for x in (lu0, lv0, value, a0, a1, a2))
    )
    # Zero gradient at (lu0, lv0): 2·a0·lu + a2·lv + a3 = 0 and a2·lu + 2·a1·lv + a4 = 0.
    a3 = -(2 * a0 * lu0 + a2 * lv0)
    a4 = -(a2 * lu0 + 2 * a1 * lv0)
    a5 = value - (a0 * lu0**2 + a1 * lv0**2 + a2 * lu0 * lv0 + a3 * lu0 + a4 * lv0)
    return np.stack([a0, a1, a2, a3, a4, a5], axis=-1)


# ---------------------------------------------------------------- light_direction


@pytest.mark.parametrize(
    ("azimuth", "elevation", "expected"),
    [
        (0, 0, (1, 0, 0)),  # from the right, grazing
        (90, 0, (0, 1, 0)),  # from the top of the image
        (180, 0, (-1, 0, 0)),
        (270, 0, (0, -1, 0)),
        (-90, 0, (0, -1, 0)),
        (0, 90, (0, 0, 1)),  # from the camera
        (45, 0, (S, S, 0)),
        (0, 45, (S, 0, S)),
        (135, 30, (-math.cos(math.radians(30)) * S, math.cos(math.radians(30)) * S, 0.5)),
    ],
)
def test_light_direction_from_angles(azimuth, elevation, expected):
    d = light_direction(azimuth_deg=azimuth, elevation_deg=elevation)
    assert d.shape == (3,)
    np.testing.assert_allclose(d, expected, atol=1e-12)
    assert np.linalg.norm(d) == pytest.approx(1.0)


def test_light_direction_from_vectors():
    np.testing.assert_allclose(light_direction(light=(2, 2, 2)), np.full(3, 1 / math.sqrt(3)))
    np.testing.assert_allclose(light_direction(light=[0.6, 0.0]), (0.6, 0.0, 0.8))
    np.testing.assert_allclose(light_direction(light=(0.0, -1.0)), (0.0, -1.0, 0.0))
    np.testing.assert_allclose(light_direction(light=np.array([0.0, 0.0, 5.0])), (0, 0, 1))


def test_light_angles_invert_light_direction():
    azimuths = np.array([0.0, 45.0, 90.0, 135.0, 200.0, 270.0, 359.0])
    elevations = np.array([0.0, 10.0, 30.0, 45.0, 60.0, 89.0, 5.0])
    dirs = np.stack([light_direction(azimuth_deg=a, elevation_deg=e) for a, e in zip(azimuths, elevations)])
    az, el = light_angles(dirs)
    assert az.shape == el.shape == (7,)
    np.testing.assert_allclose(az, azimuths, atol=1e-9)
    np.testing.assert_allclose(el, elevations, atol=1e-9)
    # One direction, and the conventions: from the top is 90°, from below the image −90° → 270°.
    assert light_angles((0.0, 1.0, 0.0))[0] == pytest.approx(90.0)
    assert light_angles((0.0, -S, -S))[0] == pytest.approx(270.0)
    assert light_angles((0.0, -S, -S))[1] == pytest.approx(-45.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"light": (0, 0, 0)}, "zero vector"),
        ({"light": (0.3, 0.2, -0.5)}, "below the horizon"),
        ({"azimuth_deg": 10, "elevation_deg": -5}, "below the horizon"),
        ({"azimuth_deg": 10, "elevation_deg": 95}, "zenith"),
        ({"light": (0.9, 0.9)}, "unit disk"),
        ({"light": (1, 2, 3, 4)}, "components"),
        ({"light": (np.nan, 0, 1)}, "not finite"),
        ({"azimuth_deg": np.inf, "elevation_deg": 30}, "finite"),
        ({"light": (0, 0, 1), "azimuth_deg": 10, "elevation_deg": 30}, "not both"),
        ({"azimuth_deg": 10}, "both azimuth_deg and elevation_deg"),
        ({}, "both azimuth_deg and elevation_deg"),
    ],
)
def test_light_direction_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        light_direction(**kwargs)


# ---------------------------------------------------------------- relight


def test_relight_reproduces_ptm_fitted_to_exact_polynomial_data():
    rng = np.random.default_rng(3)
    h, w = 12, 17
    true = np.stack(
        [
            rng.uniform(-0.2, -0.05, (h, w)),
            rng.uniform(-0.2, -0.05, (h, w)),
            rng.uniform(-0.05, 0.05, (h, w)),
            rng.uniform(-0.1, 0.1, (h, w)),
            rng.uniform(-0.1, 0.1, (h, w)),
            rng.uniform(0.45, 0.75, (h, w)),
        ],
        axis=-1,
    )
    directions = dome(45, seed=5)
    values = np.einsum("nk,hwk->nhw", light_matrix(directions), true)
    assert values.min() > 0 and values.max() < 1
    coef = fit_ptm(stack_from_luminance(values), directions, threads=1).coefficients * 255  # 0–255 units
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    lights = [directions[0], directions[7], light_direction(azimuth_deg=123, elevation_deg=37), (0, 0, 1)]
    for light in lights:
        expected = rgb * (_poly(true * 255, light) / 255)[..., None]
        out = relight(coef, rgb, light)
        assert out.dtype == np.uint8 and out.shape == (h, w, 3)
        # RTIViewer truncates: out = floor(expected) up to the fit's 16-bit input quantisation.
        diff = expected - out
        assert diff.min() > -1e-2 and diff.max() < 1 + 1e-2


def test_relight_photographs_are_reproduced():
    # Under the light of a photograph the PTM gives back that photograph's luminance.
    rng = np.random.default_rng(0)
    true = _with_maximum_at(rng.uniform(-0.4, 0.4, (6, 9)), rng.uniform(-0.4, 0.4, (6, 9)), 200.0)
    rgb = np.full((6, 9, 3), 255, np.uint8)
    for light in dome(8, seed=2):
        diff = _poly(true, light) - relight(true.astype(np.float32), rgb, light)[..., 1]
        assert diff.min() > -1e-3 and diff.max() < 1 + 1e-3  # truncated, as RTIViewer does


def test_relight_clips_and_truncates():
    coef = np.zeros((1, 5, 6), np.float32)
    coef[0, :, 5] = [-40.0, 0.0, 128.9, 255.0, 900.0]
    rgb = np.full((1, 5, 3), 255, np.uint8)
    rgb[..., 2] = 100
    out = relight(coef, rgb, (0, 0, 1))
    np.testing.assert_array_equal(out[0, :, 0], [0, 0, 128, 255, 255])  # 128.9 truncates to 128
    np.testing.assert_array_equal(out[0, :, 2], [0, 0, 50, 100, 255])  # 100·900/255 clips


def test_relight_rejects_mismatched_inputs():
    coef = np.zeros((4, 5, 6), np.float32)
    with pytest.raises(ValueError, match="rgb"):
        relight(coef, np.zeros((4, 6, 3), np.uint8), (0, 0, 1))
    with pytest.raises(ValueError, match="uint8"):
        relight(coef, np.zeros((4, 5, 3), np.float32), (0, 0, 1))
    with pytest.raises(ValueError, match=r"\(H, W, 6\)"):
        relight(np.zeros((4, 5, 9)), np.zeros((4, 5, 3), np.uint8), (0, 0, 1))


# ---------------------------------------------------------------- diffuse gain


def _concave_field(seed=0, shape=(9, 13)):
    rng = np.random.default_rng(seed)
    lu0 = rng.uniform(-0.6, 0.6, shape)
    lv0 = rng.uniform(-0.6, 0.6, shape)
    peak = rng.uniform(120, 240, shape)
    a0 = rng.uniform(-90, -30, shape)
    a1 = rng.uniform(-90, -30, shape)
    a2 = rng.uniform(-20, 20, shape)
    return _with_maximum_at(lu0, lv0, peak, a0, a1, a2).astype(np.float32)


def test_diffuse_gain_default_is_rtiviewers():
    assert inspect.signature(diffuse_gain).parameters["gain"].default == 2.0


@pytest.mark.parametrize("gain", [0.5, 2.0, 4.0, 10.0])
def test_diffuse_gain_keeps_the_maximum(gain):
    coef = _concave_field()
    lu0, lv0, interior = ptm_maximum(coef)
    assert interior.all()
    gained = diffuse_gain(coef, gain)
    assert gained.dtype == np.float32 and gained.shape == coef.shape
    lu1, lv1, interior1 = ptm_maximum(gained)
    assert interior1.all()
    np.testing.assert_allclose(lu1, lu0, atol=2e-5)
    np.testing.assert_allclose(lv1, lv0, atol=2e-5)
    peak = _at(coef, lu0, lv0)
    np.testing.assert_allclose(_at(gained, lu1, lv1), peak, rtol=1e-5)
    # Every other light departs from the peak g times as much: curvature scaled by g.
    for light in dome(6, seed=4):
        departure = _poly(coef, light) - peak
        np.testing.assert_allclose(_poly(gained, light) - peak, gain * departure, rtol=1e-4, atol=1e-2)


def test_diffuse_gain_one_is_the_identity():
    coef = _concave_field(seed=1)
    coef[0, 0] = [5.0, 3.0, 0.0, 1.0, -2.0, 40.0]  # convex: maximum on the rim
    np.testing.assert_array_equal(diffuse_gain(coef, 1.0), coef)
    rgb = np.full(coef.shape[:2] + (3,), 180, np.uint8)
    light = light_direction(azimuth_deg=30, elevation_deg=40)
    np.testing.assert_array_equal(relight(diffuse_gain(coef, 1.0), rgb, light), relight(coef, rgb, light))


def test_diffuse_gain_exaggerates_shading():
    # Away from each pixel's peak, a gain > 1 darkens more: the relit image has more contrast.
    coef = _concave_field(seed=2)
    rgb = np.full(coef.shape[:2] + (3,), 255, np.uint8)
    light = light_direction(azimuth_deg=200, elevation_deg=25)
    plain = relight(coef, rgb, light).astype(float)
    gained = relight(diffuse_gain(coef), rgb, light).astype(float)
    assert (gained <= plain + 1).all()
    assert gained.std() > plain.std()


@pytest.mark.parametrize("gain", [0.0, -1.0, np.nan, np.inf])
def test_diffuse_gain_rejects_bad_gain(gain):
    with pytest.raises(ValueError, match="gain"):
        diffuse_gain(_concave_field(), gain)


# ---------------------------------------------------------------- specular enhancement


def test_specular_without_lobe_is_the_diffuse_part():
    coef = _concave_field(seed=3)
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, coef.shape[:2] + (3,), dtype=np.uint8)
    light = light_direction(azimuth_deg=60, elevation_deg=50)
    # kd = 1, ks = 0 is the default rendering, byte for byte.
    plain = specular_enhancement(coef, rgb, light, kd=1.0, ks=0.0)
    np.testing.assert_array_equal(plain, relight(coef, rgb, light))
    out = specular_enhancement(coef, rgb, light, kd=0.4, ks=0.0).astype(float)
    expected = np.clip(0.4 * rgb * (_poly(coef, light) / 255)[..., None], 0, 255)
    diff = expected - out
    assert diff.min() > -1e-3 and diff.max() < 1 + 1e-3


def test_specular_with_known_maxima_is_the_same():
    """A viewer passes the maxima's normals once (``maximum=``): the same bytes."""
    coef = _concave_field(seed=5).astype(np.float32)
    rgb = np.random.default_rng(5).integers(0, 256, coef.shape[:2] + (3,), dtype=np.uint8)
    nu, nv, _ = ptm_maximum(coef)
    maximum = np.stack([nu, nv, np.sqrt(np.clip(1.0 - nu * nu - nv * nv, 0.0, 1.0))], axis=-1).astype(np.float32)
    for light in ([0.5, 0.2, 0.84], [-0.8, 0.1, 0.59]):
        np.testing.assert_array_equal(specular_enhancement(coef, rgb, light, maximum=maximum),
                                      specular_enhancement(coef, rgb, light))


def test_diffuse_gain_with_known_maxima_is_the_same():
    """A viewer passes the maxima's normals once (``maximum=``) to every gain: the same bytes."""
    coef = _concave_field(seed=6).astype(np.float32)
    coef[0, 0] = [5.0, 3.0, 0.0, 1.0, -2.0, 40.0]  # convex: its maximum is on the rim
    maximum = normals_from_ptm(coef)
    for gain in (0.5, 2.0, 7.5):
        np.testing.assert_array_equal(diffuse_gain(coef, gain, maximum=maximum), diffuse_gain(coef, gain))


@pytest.mark.parametrize("kd", [0.0, 0.4])
def test_specular_is_brightest_where_the_normal_bisects_light_and_view(kd):
    light = light_direction(azimuth_deg=0, elevation_deg=45)
    half = (light + (0, 0, 1)) / np.linalg.norm(light + (0, 0, 1))  # (0.383, 0, 0.924)
    lu0 = np.linspace(-0.8, 0.8, 81)[None, :]
    coef = _with_maximum_at(lu0, 0.0, 200.0)
    # Same luminance under this light everywhere, so only the lobe differs between pixels.
    coef[..., 5] += 100.0 - _poly(coef, light)
    np.testing.assert_allclose(_poly(coef, light), 100.0)
    rgb = np.full(coef.shape[:2] + (3,), 150, np.uint8)
    out = specular_enhancement(coef.astype(np.float32), rgb, light, kd=kd, ks=0.7, exponent=75)
    out = out[0, :, 0].astype(float)
    best = np.argmax(out)
    assert abs(lu0[0, best] - half[0]) <= 0.02
    assert out[best] > out[0] + 20 and out[best] > out[-1] + 20
    # At the bisector (n·h = 1): (kd·rgb + 255·ks)·L/255.
    assert out[best] == pytest.approx((kd * 150 + 255 * 0.7) * 100 / 255, abs=1.5)


def test_specular_lobe_formula_at_one_pixel():
    light = light_direction(azimuth_deg=120, elevation_deg=35)
    coef = _with_maximum_at(0.3, -0.2, 230.0)[None, None].astype(np.float32)
    rgb = np.array([[[200, 100, 50]]], np.uint8)
    n = np.array([0.3, -0.2, math.sqrt(1 - 0.13)])
    h = (light + (0, 0, 1)) / np.linalg.norm(light + (0, 0, 1))
    lum = _poly(coef, light)[0, 0]
    for kd, ks, e in [(0.4, 0.7, 75), (0.8, 0.3, 10), (0.2, 1.0, 1)]:
        expected = np.clip((kd * np.array([200, 100, 50]) + 255 * ks * max(n @ h, 0) ** e) * lum / 255, 0, 255)
        out = specular_enhancement(coef, rgb, light, kd=kd, ks=ks, exponent=e)[0, 0].astype(float)
        assert np.all((expected - out > -1e-3) & (expected - out < 1 + 1e-3))


def test_specular_defaults_are_rtiviewers():
    p = inspect.signature(specular_enhancement).parameters
    assert (p["kd"].default, p["ks"].default, p["exponent"].default) == (0.4, 0.7, 75)


@pytest.mark.parametrize("kwargs", [{"kd": -0.1}, {"ks": np.nan}, {"exponent": -2}])
def test_specular_rejects_bad_parameters(kwargs):
    coef = _concave_field()
    rgb = np.zeros(coef.shape[:2] + (3,), np.uint8)
    with pytest.raises(ValueError):
        specular_enhancement(coef, rgb, (0, 0, 1), **kwargs)


def test_display_srgb_is_the_srgb_transfer_function():
    from ptmcore.images import linear_to_srgb
    from ptmcore.relight import display_srgb

    levels = np.arange(256, dtype=np.uint8)
    out = display_srgb(levels.reshape(16, 16))
    assert out.dtype == np.uint8 and out.shape == (16, 16)
    expected = np.round(linear_to_srgb(levels / 255.0) * 255).astype(int)
    np.testing.assert_array_equal(out.ravel(), expected)
    # Monotonic, black and white kept, mid-grey brightened as sRGB does (0.5 → 188).
    assert (np.diff(out.ravel().astype(int)) >= 0).all()
    assert out.ravel()[0] == 0 and out.ravel()[255] == 255 and out.ravel()[128] == 188


# ---------------------------------------------------------------- reconstruct relight: the published basis


def _published_basis(kind, h=30, w=40, encoding="srgb"):
    """A small basis unlike the folder's PTM (so that which one was relit shows)."""
    rng = np.random.default_rng(11)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    colour = np.stack([100 + 80 * np.sin(cols / 5), 120 + 60 * np.cos(rows / 4), np.full((h, w), 150.0)], -1)
    if kind == "hsh3":
        planes = 0.1 * rng.normal(size=(h, w, 9)).astype(np.float32)
        planes[..., 0] += 1.2
        planes[..., 1] += 0.8 * np.sin(cols / 3)  # relief that turns with the light
        return PublishedBasis("hsh", "lrgb", planes, encoding, colour=colour.astype(np.uint8), order=3, name="hsh3")
    d = 25
    q, _ = np.linalg.qr(rng.normal(size=(3 * d, 4)))
    basis = np.concatenate([rng.uniform(0.2, 0.5, (1, d, 3)), q.T.reshape(4, d, 3)]).astype(np.float32)
    planes = np.stack([np.sin(cols / (3 + k) + k) * np.cos(rows / (4 + k)) for k in range(4)], -1)
    return PublishedBasis("bln", "mrgb", planes.astype(np.float32), encoding, resolution=5, basis=basis,
                          name="bilinear")


def _ptm_coefficients(h=30, w=40):
    """A grey PTM whose slope turns across the image (a PTM of one polynomial is refused)."""
    coef = np.broadcast_to(np.float32([-40, -40, 0, 10, 5, 180]), (h, w, 6)).copy()
    coef[..., 3] += 25 * np.sin(np.arange(w, dtype=np.float32) / 6)
    return coef


def _output_folder(root, kind="hsh3", encoding="srgb", ptm=True, tiles=False):
    """An output folder as `reconstruct run` leaves it, in small: coefficients.ptm and web/."""
    root.mkdir(parents=True, exist_ok=True)
    if ptm:
        write_ptm(root / "coefficients.ptm", _ptm_coefficients(), np.full((30, 40, 3), 200, np.uint8))
    export_relightable(root / "web", _published_basis(kind, encoding=encoding), tiles=tiles)
    return root


def _png(path):
    return np.asarray(Image.open(path).convert("RGB"))


@pytest.mark.parametrize("encoding", ["srgb", "linear"])
@pytest.mark.parametrize("kind", ["hsh3", "bln"])
def test_relight_renders_the_published_basis_by_default(tmp_path, capsys, kind, encoding):
    out = _output_folder(tmp_path / "out", kind, encoding)
    light = light_direction(azimuth_deg=30, elevation_deg=40)
    code, stdout, err = run_cli(["relight", out, "--light", ",".join(map(str, light)), "-o", tmp_path / "a.png"],
                                capsys)
    assert code == 0, err
    assert f"(published basis {_published_basis(kind).name}, " in stdout
    published = read_relightable(out / "web")
    # As the page shows it: display-encoded once (a linear basis brighter than its values).
    np.testing.assert_array_equal(_png(tmp_path / "a.png"), published.display(light))
    if encoding == "linear":
        raw = np.rint(np.clip(published.render(light), 0, 1) * 255)
        assert _png(tmp_path / "a.png").mean() > raw.mean() + 10
    # The web/ folder itself, or its info.json, renders the same.
    for source in (out / "web", out / "web" / "info.json"):
        code, _, err = run_cli(["relight", source, "--light", ",".join(map(str, light)), "-o", tmp_path / "b.png"],
                               capsys)
        assert code == 0, err
        np.testing.assert_array_equal(_png(tmp_path / "b.png"), _png(tmp_path / "a.png"))
    # --basis ptm renders the PTM (grey 200 everywhere: nothing like the basis).
    code, stdout, err = run_cli(["relight", out, "--basis", "ptm", "--light", ",".join(map(str, light)), "-o",
                                 tmp_path / "p.png"], capsys)
    assert code == 0 and "(PTM)" in stdout, err
    np.testing.assert_array_equal(_png(tmp_path / "p.png"), read_ptm(out / "coefficients.ptm").render(light))
    assert np.abs(_png(tmp_path / "p.png").astype(int) - _png(tmp_path / "a.png")).mean() > 5


def test_relight_modes_of_the_ptm_and_sweeps_of_the_basis(tmp_path, capsys):
    out = _output_folder(tmp_path / "out")
    # RTIViewer's modes are the PTM's, with the default --basis auto too.
    code, _, err = run_cli(["relight", out, "--light", "0.5,0,0.8", "--mode", "specular", "-o", tmp_path / "s.png"],
                           capsys)
    assert code == 0, err
    ptm = read_ptm(out / "coefficients.ptm")
    np.testing.assert_array_equal(_png(tmp_path / "s.png"), render(ptm, light_direction(light=(0.5, 0, 0.8)),
                                                                   "specular"))
    # A sweep of the published basis: each frame is its display under that light.
    code, _, err = run_cli(["relight", out, "--sweep", "4", "--elevation", "35", "-o", tmp_path / "turn.gif"], capsys)
    assert code == 0, err
    with Image.open(tmp_path / "turn.gif") as gif:
        assert gif.n_frames == 4 and gif.size == (40, 30)
    published = read_relightable(out / "web")
    frames = list(renders(published, sweep_lights(4, 35.0)))
    for frame, light in zip(frames, sweep_lights(4, 35.0)):
        np.testing.assert_array_equal(frame, published.display(light))
    assert np.abs(frames[0].astype(int) - frames[2]).mean() > 2  # the light turns
    with pytest.raises(InputError, match="specular mode needs a PTM"):
        renders(published, sweep_lights(2), "specular")


def test_relight_falls_back_to_the_ptm(tmp_path, capsys):
    # An older run: web/ holds the PTM itself (no basis named): coefficients.ptm is relit.
    old = tmp_path / "old"
    old.mkdir()
    coef = _ptm_coefficients()
    write_ptm(old / "coefficients.ptm", coef, np.full((30, 40, 3), 200, np.uint8))
    export_openlime(old / "web", coef, np.full((30, 40, 3), 200, np.uint8))
    assert isinstance(load_source(old), PTMFile)
    # A run from a .ptm: no coefficients.ptm, web/ of that PTM: web/ is relit.
    (old / "coefficients.ptm").unlink()
    assert isinstance(load_source(old), PublishedBasis)
    code, _, err = run_cli(["relight", old, "--light", "0,0,1", "--mode", "diffuse-gain", "-o", tmp_path / "x.png"],
                           capsys)
    assert code == 2 and "no coefficients.ptm" in err and err.count("\n") == 1
    # No web/ and no PTM.
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli(["relight", tmp_path / "empty", "--light", "0,0,1", "-o", tmp_path / "x.png"], capsys)
    assert code == 2 and "no web/ and no coefficients.ptm" in err and err.count("\n") == 1


@pytest.mark.parametrize(
    ("source", "args", "needles"),
    [
        ("web", ["--mode", "specular"], ["web", "specular mode", "coefficients.ptm"]),
        ("web/info.json", ["--mode", "diffuse-gain"], ["info.json", "diffuse-gain mode"]),
        ("web", ["--basis", "hsh"], ["--basis hsh", "give the output folder"]),
        ("broken", [], ["info.json", "malformed info.json"]),
        ("missing_plane", [], ["plane_1.jpg", "missing"]),
    ],
)
def test_relight_bad_web_sources(tmp_path, capsys, source, args, needles):
    out = _output_folder(tmp_path / "out")
    if source == "broken":
        (out / "web" / "info.json").write_text('{"width": 40, "height": 3')
        source = "."
    if source == "missing_plane":
        (out / "web" / "plane_1.jpg").unlink()
        source = "."
    code, _, err = run_cli(["relight", out / source, "--light", "0,0,1", *args, "-o", tmp_path / "x.png"], capsys)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    assert not (tmp_path / "x.png").exists()


def test_relight_a_tiled_basis(tmp_path, capsys):
    """A pyramid (large images) is read whole for `relight`: the tiles stitched back."""
    out = _output_folder(tmp_path / "out", "bln", tiles=True)
    assert (out / "web" / "plane_0.dzi").is_file()
    code, _, err = run_cli(["relight", out, "--azimuth", "200", "--elevation", "30", "-o", tmp_path / "t.png"],
                           capsys)
    assert code == 0, err
    light = light_direction(azimuth_deg=200, elevation_deg=30)
    expected = _published_basis("bln").display(light)
    assert np.abs(_png(tmp_path / "t.png").astype(int) - expected).mean() < 2
    np.testing.assert_array_equal(_png(tmp_path / "t.png"), read_relightable(out).display(light))


def test_a_run_publishing_the_neural_basis_is_relit_from_it(tmp_path, capsys, monkeypatch):
    """`run --basis neural --outputs relight` publishes NeuralRTI's basis in web/, and
    `reconstruct relight` of the folder renders it, close to the photograph of that light."""
    import json

    import ptmcore.bases
    from data_synthetic import write_capture
    from ptmcore.images import linear_to_srgb, read_image
    from ptmcore.lp import read_lp
    from ptmcore.neural import NeuralParameters

    # A tenth of the default's training steps: seconds, not tens of them.
    monkeypatch.setattr(ptmcore.bases, "NeuralParameters", lambda: NeuralParameters(min_steps=2048))

    info = write_capture(tmp_path / "cap", "tablet", shape=(40, 48), n_lights=24, seed=4, cast_shadows=False)
    out = tmp_path / "out"
    code, stdout, err = run_cli(["run", info.folder, "-o", out, "--basis", "neural", "--outputs", "relight"], capsys)
    assert code == 0, err
    assert "relighting basis in web/: neural, srgb" in stdout
    assert json.loads((out / "web" / "info.json").read_text())["type"] == "neural"
    report = json.loads((out / "report.json").read_text())
    assert report["relighting"]["name"] == "neural" and report["relighting"]["chosen_by"] == "asked"
    lights = read_lp(next(info.folder.glob("*.lp")))
    x, y, z = lights.directions[5]
    code, stdout, err = run_cli(["relight", out, "--light", f"{x},{y},{z}", "-o", tmp_path / "n.png"], capsys)
    assert code == 0, err
    assert "neural" in stdout
    relit = read_image(tmp_path / "n.png").astype(np.float64)
    shown = 255 * linear_to_srgb(read_image(lights.paths[5]).astype(np.float32) / 65535)  # 16-bit linear
    assert np.abs(relit - shown[..., :3]).mean() < 8  # measured 5.3 levels
