import numpy as np

from ptmcore.fit import PTM, fit_matrix, fit_ptm, light_matrix

from helpers import dome, stack_from_luminance


def test_light_matrix_rows():
    d = np.array([[0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [0.3, -0.4, np.sqrt(0.75)]])
    m = light_matrix(d)
    np.testing.assert_allclose(m[2], [0.09, 0.16, -0.12, 0.3, -0.4, 1.0])


def test_fit_recovers_coefficients_exactly():
    rng = np.random.default_rng(3)
    d = dome(24, seed=3)
    h, w = 17, 23
    a = (rng.normal(size=(h, w, 6)) * 0.05).astype(np.float32)
    a[..., 5] += 0.5
    values = np.einsum("nk,hwk->nhw", light_matrix(d), a)
    assert values.min() > 0 and values.max() < 1
    ptm = fit_ptm(stack_from_luminance(values), d)
    # Only 16-bit quantisation of the stored stack separates the fit from the truth.
    np.testing.assert_allclose(ptm.coefficients, a, atol=2e-4)
    for k in range(3):
        np.testing.assert_allclose(ptm.luminance(d[k]), values[k], atol=2e-5)


def test_fit_matrix_is_pseudoinverse():
    d = dome(12, seed=1)
    lam = light_matrix(d)
    p = fit_matrix(d)
    np.testing.assert_allclose(p @ lam, np.eye(6), atol=1e-9)


def test_relight_multiplies_chroma():
    coef = np.zeros((2, 2, 6), np.float32)
    coef[..., 5] = 0.5
    chroma = np.array([1.2, 0.9, 0.8], np.float32) * np.ones((2, 2, 3), np.float32)
    rgb = PTM(coef, chroma).relight(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(rgb[0, 0], [0.6, 0.45, 0.4])


def test_display_fit_reproduces_the_photographs_as_rtiviewer_renders(shared_fixture):
    from ptmcore import load_stack, read_image, read_lp
    from ptmcore.fit import fit_ptm_display

    lights = read_lp(shared_fixture / "reference_8x5.lp")
    coef, rgb = fit_ptm_display(load_stack(lights.paths), lights.directions)
    errors = []
    for k, path in enumerate(lights.paths):
        lum = coef @ light_matrix(lights.directions[k : k + 1])[0].astype(np.float32)
        rendered = np.clip(rgb * lum[..., None] / 255, 0, 255)
        errors.append(np.abs(rendered - read_image(path)).mean())
    # A 6-term polynomial fitted to 12 real photographs: measured 1.9 levels mean.
    assert np.mean(errors) < 2.5


def test_display_fit_keeps_saturated_colours(tmp_path):
    import tifffile

    from ptmcore import load_stack
    from ptmcore.fit import fit_ptm_display
    from ptmcore.images import linear_to_srgb

    d = dome(10, seed=2)
    colour = np.array([0.9, 0.05, 0.02])  # a saturated red, linear
    paths = []
    for k, light in enumerate(d):
        img = np.broadcast_to(colour * light[2], (3, 4, 3))
        paths.append(tmp_path / f"{k}.tif")
        tifffile.imwrite(paths[-1], np.round(img * 65535).astype(np.uint16))
    coef, rgb = fit_ptm_display(load_stack(paths), d)
    assert rgb[1, 1, 0] == 255  # the strongest channel uses the full 8-bit range
    rendered = rgb[1, 1] * (light_matrix(d) @ coef[1, 1])[:, None] / 255
    expected = linear_to_srgb(colour * d[:, 2:3]) * 255
    top = np.argmax(d[:, 2])
    # The colour is exact near the zenith (channel ratios)...
    np.testing.assert_allclose(rgb[1, 1] / 255, expected[top] / expected[top, 0], rtol=0.02)
    # ...and a 6-term polynomial with one colour per pixel (which cannot follow sRGB's hue
    # shift with brightness, least in sRGB's linear toe) stays within 6 % + 5 levels at every
    # light, elevations down to 15°.
    np.testing.assert_allclose(rendered, expected, rtol=0.06, atol=5.0)
