import numpy as np

from ptmcore.fit import PTM, evaluate_at, fit_matrix, fit_ptm, light_matrix

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


def test_evaluate_at_each_pixels_light_is_the_light_matrix_row():
    rng = np.random.default_rng(5)
    coef = rng.normal(size=(4, 5, 6))
    rgb_coef = rng.normal(size=(4, 5, 3, 6))
    d = rng.normal(size=(4, 5, 3))
    d[..., 2] = np.abs(d[..., 2]) + 0.5
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rows = light_matrix(d.reshape(-1, 3)).reshape(4, 5, 6)
    lu, lv = d[..., 0], d[..., 1]
    np.testing.assert_allclose(evaluate_at(coef, lu, lv), (coef * rows).sum(-1), rtol=1e-12)
    np.testing.assert_allclose(evaluate_at(rgb_coef, lu, lv), (rgb_coef * rows[..., None, :]).sum(-1), rtol=1e-12)
