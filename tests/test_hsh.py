import numpy as np
import pytest

import ptmcore.hsh as hsh_module
from ptmcore.hsh import HSH, fit_hsh, hsh_angles, hsh_basis, hsh_fit_matrix

from helpers import dome, stack_from_luminance


def _unit(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def test_basis_shapes_and_nesting():
    d = dome(20, seed=2)
    b2, b3 = hsh_basis(d, 2), hsh_basis(d, 3)
    assert b2.shape == (20, 4) and b3.shape == (20, 9)
    assert b3.dtype == np.float64
    # Order 2 is the first four terms of order 3, as in RTIViewer's file layout.
    np.testing.assert_array_equal(b3[:, :4], b2)
    for bad in (1, 5, 0):
        with pytest.raises(ValueError, match="HSH order"):
            hsh_basis(d, bad)
    with pytest.raises(ValueError):
        hsh_basis(np.zeros((2, 3)), 3)


def test_zenith_light_values():
    b = hsh_basis(np.array([[0.0, 0.0, 1.0]]), 3)[0]
    # θ = 0: only the zonal terms (m = 0) survive, each at its value for cos θ = 1.
    expected = np.zeros(9)
    expected[0] = 1 / np.sqrt(2 * np.pi)
    expected[2] = np.sqrt(3 / (2 * np.pi))
    expected[6] = np.sqrt(5 / (2 * np.pi))
    np.testing.assert_allclose(b, expected, atol=1e-12)


def test_values_at_a_tilted_light_follow_rtiviewer_convention():
    # Azimuth 30°, elevation 40°: θ = 50° from the camera axis, φ = 30° from +x towards +y.
    light = _unit(30.0, 40.0)
    theta, phi = hsh_angles(light[None])
    np.testing.assert_allclose(theta, np.radians(50.0))
    np.testing.assert_allclose(phi, np.radians(30.0))
    c = np.cos(np.radians(50.0))
    s = np.sqrt(c - c * c)
    p = np.radians(30.0)
    k = np.sqrt(30 / np.pi)
    expected = [
        1 / np.sqrt(2 * np.pi),
        np.sqrt(6 / np.pi) * np.cos(p) * s,
        np.sqrt(3 / (2 * np.pi)) * (2 * c - 1),
        np.sqrt(6 / np.pi) * np.sin(p) * s,
        k * np.cos(2 * p) * (c * c - c),
        k * np.cos(p) * (2 * c - 1) * s,
        np.sqrt(5 / (2 * np.pi)) * (6 * c * c - 6 * c + 1),
        k * np.sin(p) * (2 * c - 1) * s,
        k * np.sin(2 * p) * (c * c - c),
    ]
    np.testing.assert_allclose(hsh_basis(light[None], 3)[0], expected, rtol=1e-12)


def test_azimuth_wraps_to_0_2pi_and_length_is_ignored():
    theta, phi = hsh_angles(np.array([[0.0, -2.0, 2.0]]))
    np.testing.assert_allclose(phi, [1.5 * np.pi])
    np.testing.assert_allclose(theta, [np.pi / 4])
    np.testing.assert_allclose(hsh_basis(np.array([[0.0, -2.0, 2.0]])),
                               hsh_basis(np.array([[0.0, -1.0, 1.0]])), atol=1e-15)


def test_lu_lv_input_equals_unit_vector():
    d = dome(10, seed=5)
    np.testing.assert_allclose(hsh_basis(d[:, :2], 3), hsh_basis(d, 3), atol=1e-12)


def test_theta_clamped_near_the_horizon_like_rtiviewer():
    grazing = np.array([[1.0, 0.0, 1e-3], [1.0, 0.0, -0.2]])
    limit = np.array([[np.cos(0.04), 0.0, np.sin(0.04)]])  # θ = π/2 − 0.04 exactly
    b = hsh_basis(grazing, 3)
    np.testing.assert_allclose(b, np.repeat(hsh_basis(limit, 3), 2, axis=0), atol=1e-12)


def test_orthonormal_over_the_hemisphere(monkeypatch):
    # Gautron et al.'s defining property, and a check of every normalisation constant.
    monkeypatch.setattr(hsh_module, "HORIZON_MARGIN", 0.0)
    x, wx = np.polynomial.legendre.leggauss(80)
    c, wc = (x + 1) / 2, wx / 2  # cos θ on [0, 1]; dω = d(cos θ) dφ
    n_phi = 64
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    cc, pp = np.meshgrid(c, phi, indexing="ij")
    weight = np.outer(wc, np.full(n_phi, 2 * np.pi / n_phi)).ravel()
    sin_t = np.sqrt(1 - cc**2)
    d = np.stack([sin_t * np.cos(pp), sin_t * np.sin(pp), cc], -1).reshape(-1, 3)
    b = hsh_basis(d, 3)
    gram = (b * weight[:, None]).T @ b
    # √(c − c²) is not a polynomial, so Gauss–Legendre is accurate to ~1e-5 here, not 1e-15.
    np.testing.assert_allclose(gram, np.eye(9), atol=1e-4)


def test_order_2_spans_constant_and_first_degree_terms():
    d = dome(30, seed=4)
    x, y, z = d.T
    g = np.sqrt(z / (1 + z))  # s·cos φ = x·√(z/(1+z)) on the unit sphere
    first_degree = np.column_stack([np.ones_like(z), z, x * g, y * g])
    b2 = hsh_basis(d, 2)
    # Same column space: each set is reproduced exactly by the other.
    for a, target in ((b2, first_degree), (first_degree, b2)):
        coef, *_ = np.linalg.lstsq(a, target, rcond=None)
        np.testing.assert_allclose(a @ coef, target, atol=1e-12)
    # H1 is odd in x and even in y; H3 the reverse; H0, H2 depend on neither.
    mirrored = d * [-1.0, 1.0, 1.0]
    np.testing.assert_allclose(hsh_basis(mirrored, 2), b2 * [1, -1, 1, 1], atol=1e-12)
    mirrored = d * [1.0, -1.0, 1.0]
    np.testing.assert_allclose(hsh_basis(mirrored, 2), b2 * [1, 1, 1, -1], atol=1e-12)


def test_constant_and_flat_lambertian_fit_exactly_with_order_2():
    d = dome(24, seed=6)
    z = d[:, 2]
    b2 = hsh_basis(d, 2)
    pinv = hsh_fit_matrix(d, 2)
    for signal in (np.full_like(z, 0.4), 0.1 + 0.7 * z):  # ambient; flat Lambertian n = +z
        np.testing.assert_allclose(b2 @ (pinv @ signal), signal, atol=1e-12)
    # A constant lives in H0 alone.
    np.testing.assert_allclose(pinv @ np.full_like(z, 0.4), [0.4 * np.sqrt(2 * np.pi), 0, 0, 0],
                               atol=1e-12)


@pytest.mark.parametrize("order", [2, 3])
def test_fit_recovers_hsh_coefficients_exactly(order):
    rng = np.random.default_rng(order)
    d = dome(30, seed=order)
    h, w, k = 13, 17, order * order
    coef = (rng.normal(size=(h, w, k)) * 0.02).astype(np.float32)
    coef[..., 0] += 0.5 * np.sqrt(2 * np.pi)  # mean luminance about 0.5
    values = np.einsum("nk,hwk->nhw", hsh_basis(d, order), coef)
    assert values.min() > 0 and values.max() < 1
    model = fit_hsh(stack_from_luminance(values), d, order, threads=2)
    assert model.coefficients.shape == (h, w, k) and model.coefficients.dtype == np.float32
    assert model.order == order and model.shape == (h, w)
    # Only the 16-bit quantisation of the stored stack separates the fit from the truth.
    np.testing.assert_allclose(model.coefficients, coef, atol=2e-4)
    for i in range(3):
        np.testing.assert_allclose(model.luminance(d[i]), values[i], atol=3e-5)
        np.testing.assert_allclose(model.luminance(d[i, :2]), values[i], atol=3e-5)


def test_fit_checks_direction_count():
    values = np.full((5, 4, 4), 0.5)
    with pytest.raises(ValueError):
        fit_hsh(stack_from_luminance(values), dome(6), 2)


def test_relight_multiplies_chroma():
    coef = np.zeros((2, 2, 4), np.float32)
    coef[..., 0] = 0.5 * np.sqrt(2 * np.pi)
    chroma = np.array([1.2, 0.9, 0.8], np.float32) * np.ones((2, 2, 3), np.float32)
    rgb = HSH(coef, chroma).relight(np.array([0.3, 0.2, 0.9]))
    np.testing.assert_allclose(rgb[1, 1], [0.6, 0.45, 0.4], rtol=1e-6)


def test_ring_of_lights_from_an_lp_file_fits_without_blowing_up():
    # On one ring only 5 of the 9 order-3 terms are independent; the .lp file's six decimals
    # make the other singular values 1e-7..1e-13 instead of 0, which must not be inverted.
    az = np.radians(np.arange(24) * 15.0)
    ring = np.round(np.stack([np.cos(az), np.sin(az), np.full(24, 1.0)], 1) / np.sqrt(2), 6)
    rng = np.random.default_rng(12)
    values = np.clip(0.5 + 0.3 * np.cos(az - 0.4)[:, None, None] * rng.uniform(0.5, 1, (1, 6, 7))
                     + rng.normal(0, 0.004, (24, 6, 7)), 0, 1)
    model = fit_hsh(stack_from_luminance(values), ring, 3)
    assert np.abs(model.coefficients).max() < 10
    # The fit is the projection onto the five-dimensional span: residuals at noise level.
    pred = np.stack([model.luminance(d) for d in ring])
    assert np.sqrt(((pred - values) ** 2).mean()) < 0.005


# ---------------------------------------------------------------------------------------------
# Order 4 (16 terms, RTIViewer's getHSH for order > 3)


def _hemisphere_quadrature(n_c: int = 40, n_phi: int = 32):
    """Directions and weights integrating exactly the products of the HSH up to order 4:
    Gauss–Legendre in cos θ (products of two terms of equal m are polynomials in c, since
    s² = c − c²) and the trapezoid rule in φ (exact for trigonometric degree < n_phi)."""
    x, wx = np.polynomial.legendre.leggauss(n_c)
    c, wc = (x + 1) / 2, wx / 2
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    cc, pp = np.meshgrid(c, phi, indexing="ij")
    weight = np.outer(wc, np.full(n_phi, 2 * np.pi / n_phi)).ravel()
    sin_t = np.sqrt(1 - cc**2)
    d = np.stack([sin_t * np.cos(pp), sin_t * np.sin(pp), cc], -1).reshape(-1, 3)
    return d, weight


def test_order_4_is_orthonormal_over_the_hemisphere(monkeypatch):
    monkeypatch.setattr(hsh_module, "HORIZON_MARGIN", 0.0)
    d, weight = _hemisphere_quadrature()
    b = hsh_basis(d, 4)
    assert b.shape == (len(d), 16) and b.dtype == np.float64
    gram = (b * weight[:, None]).T @ b
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-10)


def test_order_4_nests_orders_2_and_3():
    d = dome(25, seed=8)
    b4 = hsh_basis(d, 4)
    np.testing.assert_allclose(b4[:, :9], hsh_basis(d, 3), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b4[:, :4], hsh_basis(d, 2), rtol=1e-12, atol=1e-15)


def _gautron(l_deg: int, m: int, c: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Gautron et al.'s H_l^m written plainly: shifted associated Legendre function (with the
    Condon–Shortley phase), SH normalisation over the hemisphere, cos mφ / sin |m|φ."""
    from math import factorial

    from scipy.special import lpmv

    am = abs(m)
    k = np.sqrt((2 * l_deg + 1) / (2 * np.pi) * factorial(l_deg - am) / factorial(l_deg + am))
    legendre = lpmv(am, l_deg, 2 * c - 1)
    if m > 0:
        return np.sqrt(2) * k * legendre * np.cos(m * phi)
    if m < 0:
        return np.sqrt(2) * k * legendre * np.sin(am * phi)
    return k * legendre


def test_order_4_terms_are_gautrons_hemispherical_harmonics_with_rtiviewers_signs():
    pytest.importorskip("scipy")
    d = dome(30, seed=9)
    theta, phi = hsh_angles(d)
    c = np.cos(theta)
    b = hsh_basis(d, 4)
    for l_deg in range(4):
        for m in range(l_deg, -l_deg - 1, -1):
            k = l_deg * l_deg + l_deg - m  # the file order: m from +l down to −l
            sign = 1.0 if m == 0 else -1.0  # RTIViewer drops the Condon–Shortley phase's sign
            np.testing.assert_allclose(b[:, k], sign * _gautron(l_deg, m, c, phi),
                                       rtol=1e-9, atol=1e-12, err_msg=f"l={l_deg} m={m}")


def test_order_4_values_follow_rtiviewer_util_h():
    # RTIViewer's getHSH, order > 3 branch, written out at azimuth 30°, elevation 40°.
    light = _unit(30.0, 40.0)
    c = np.cos(np.radians(50.0))
    p = np.radians(30.0)
    q = c - c * c
    expected = [
        2 * np.sqrt(35 / np.pi) * np.cos(3 * p) * q**1.5,
        np.sqrt(210 / np.pi) * np.cos(2 * p) * (-1 + 2 * c) * (-c + c * c),
        2 * np.sqrt(21 / np.pi) * np.cos(p) * np.sqrt(q) * (1 - 5 * c + 5 * c * c),
        np.sqrt(7 / (2 * np.pi)) * (-1 + 12 * c - 30 * c * c + 20 * c**3),
        2 * np.sqrt(21 / np.pi) * np.sqrt(q) * (1 - 5 * c + 5 * c * c) * np.sin(p),
        np.sqrt(210 / np.pi) * (-1 + 2 * c) * (-c + c * c) * np.sin(2 * p),
        2 * np.sqrt(35 / np.pi) * q**1.5 * np.sin(3 * p),
    ]
    np.testing.assert_allclose(hsh_basis(light[None], 4)[0, 9:], expected, rtol=1e-12)
    # At the zenith only the zonal terms survive.
    zenith = hsh_basis(np.array([[0.0, 0.0, 1.0]]), 4)[0]
    zonal = [0, 2, 6, 12]
    np.testing.assert_allclose(np.delete(zenith, zonal), 0, atol=1e-12)
    np.testing.assert_allclose(zenith[12], np.sqrt(7 / (2 * np.pi)), rtol=1e-12)


def test_order_4_is_finite_at_the_horizon_clamp_and_the_zenith():
    d = np.array([[1.0, 0.0, 0.0], [0.3, -0.2, 1e-9], [0.0, 0.0, 1.0], [1e-9, 0.0, 1.0]])
    assert np.all(np.isfinite(hsh_basis(d, 4)))


def test_fit_recovers_order_4_coefficients():
    rng = np.random.default_rng(4)
    d = dome(60, seed=4, min_elev=10, max_elev=85)
    h, w = 5, 6
    coef = (rng.normal(size=(h, w, 16)) * 0.01).astype(np.float32)
    coef[..., 0] += 0.5 * np.sqrt(2 * np.pi)
    values = np.einsum("nk,hwk->nhw", hsh_basis(d, 4), coef)
    assert values.min() > 0 and values.max() < 1
    model = fit_hsh(stack_from_luminance(values), d, 4, threads=1)
    assert model.order == 4 and model.coefficients.shape == (h, w, 16)
    np.testing.assert_allclose(model.coefficients, coef, atol=1e-3)
    np.testing.assert_allclose(model.luminance(d[0]), values[0], atol=5e-5)


def test_rti_orders_stay_at_2_and_3():
    # The .rti files and encoded fits keep RTIBuilder's orders; order 4 is the basis's only.
    assert hsh_module.ORDERS == (2, 3)
    assert hsh_module.BASIS_ORDERS == (2, 3, 4)
