import warnings

import numpy as np
import pytest

from ptmcore.errors import InputError
from ptmcore.fit import light_matrix
from ptmcore.hsh import RCOND, hsh_basis
from ptmcore.images import linear_to_srgb
from ptmcore.loo import (
    UndeterminedLightWarning,
    hat_diagonal,
    loo_error,
    loo_hsh,
    loo_ptm,
    loo_residuals,
    undetermined_lights,
)

from helpers import dome, stack_from_luminance


def brute_force(values: np.ndarray, basis: np.ndarray, skip=()) -> np.ndarray:
    """Observed minus predicted for each light, refitting without it (N refits)."""
    n = len(basis)
    flat = np.asarray(values, np.float64).reshape(n, -1)
    out = []
    for i in range(n):
        if i in skip:
            continue
        keep = np.arange(n) != i
        coef = np.linalg.pinv(basis[keep], rcond=RCOND) @ flat[keep]
        out.append(flat[i] - basis[i] @ coef)
    return np.array(out).reshape((len(out),) + np.shape(values)[1:])


def test_shortcut_equals_brute_force_random_basis():
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(11, 4))
    values = rng.normal(size=(11, 3, 5))
    resid, used = loo_residuals(values, basis)
    assert resid.shape == (11, 3, 5)
    np.testing.assert_array_equal(used, np.arange(11))
    np.testing.assert_allclose(resid, brute_force(values, basis), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("make_basis", [light_matrix, lambda d: hsh_basis(d, 2),
                                        lambda d: hsh_basis(d, 3)])
def test_shortcut_equals_brute_force_rti_bases(make_basis):
    rng = np.random.default_rng(1)
    basis = make_basis(dome(16, seed=1))
    values = rng.uniform(0, 1, size=(16, 40))
    resid, _ = loo_residuals(values, basis)
    np.testing.assert_allclose(resid, brute_force(values, basis), rtol=1e-9, atol=1e-12)


def test_rank_deficient_basis_uses_its_span():
    # On one ring lu² + lv² is constant: the PTM basis has rank 5, yet no light is needed alone.
    az = np.radians(np.arange(12) * 30.0 + 7.0)
    ring = np.stack([0.6 * np.cos(az), 0.6 * np.sin(az), np.full(12, 0.8)], axis=1)
    basis = light_matrix(ring)
    assert np.linalg.matrix_rank(basis) == 5
    h = hat_diagonal(basis)
    np.testing.assert_allclose(h.sum(), 5.0)
    assert len(undetermined_lights(basis)) == 0
    values = np.random.default_rng(2).uniform(size=(12, 30))
    resid, _ = loo_residuals(values, basis)
    np.testing.assert_allclose(resid, brute_force(values, basis), rtol=1e-9, atol=1e-12)


def test_data_in_the_span_has_zero_loo_error():
    d = dome(20, seed=3)
    basis = hsh_basis(d, 3)
    coef = np.random.default_rng(3).normal(size=(9, 50))
    resid, _ = loo_residuals(basis @ coef, basis)
    np.testing.assert_allclose(resid, 0.0, atol=1e-12)


def test_loo_error_map_shape_and_values_match_brute_force():
    rng = np.random.default_rng(4)
    d = dome(14, seed=4)
    values = rng.uniform(0.05, 0.95, size=(14, 9, 11))
    stack = stack_from_luminance(values)
    basis = light_matrix(d)
    rms_map, mean = loo_error(stack, basis, threads=2)
    assert rms_map.shape == (9, 11) and rms_map.dtype == np.float32
    stored = stack.band(0, 9)[0].astype(np.float64)
    expected_map = np.sqrt((brute_force(stored, basis) ** 2).mean(axis=0))
    np.testing.assert_allclose(rms_map, expected_map, rtol=1e-6)
    assert isinstance(mean, float)
    np.testing.assert_allclose(mean, np.sqrt((expected_map**2).mean()), rtol=1e-9)


def test_loo_interpolated_map_is_each_photograph_against_its_interpolation():
    from ptmcore.interpolation import default_sigma, rbf_loo_matrix
    from ptmcore.loo import loo_interpolated

    rng = np.random.default_rng(8)
    d = dome(16, seed=8)
    stack = stack_from_luminance(rng.uniform(0.05, 0.95, size=(16, 6, 5)))
    predictor = rbf_loo_matrix(d, default_sigma(d))
    stored = stack.band(0, 6)[0].astype(np.float64).reshape(16, -1)
    # Brute force: each photograph against the weighted sum of the others, one at a time.
    errors = np.stack([stored[i] - sum(predictor[i, j] * stored[j] for j in range(16) if j != i)
                       for i in range(16)])
    rms_map, mean = loo_interpolated(stack, predictor, threads=2)
    np.testing.assert_allclose(rms_map, np.sqrt((errors ** 2).mean(axis=0)).reshape(6, 5), rtol=1e-6)
    mask = np.zeros((6, 5), bool)
    mask[2:4] = True
    _, masked = loo_interpolated(stack, predictor, mask=mask)
    np.testing.assert_allclose(masked, np.sqrt((rms_map[mask].astype(np.float64) ** 2).mean()), rtol=1e-6)
    with pytest.raises(ValueError, match="predictor"):
        loo_interpolated(stack, predictor[:5])


def test_threads_and_bands_do_not_change_the_result():
    rng = np.random.default_rng(5)
    d = dome(12, seed=5)
    stack = stack_from_luminance(rng.uniform(0.1, 0.9, size=(12, 23, 7)))
    a = loo_hsh(stack, d, 2, threads=1)
    b = loo_hsh(stack, d, 2, threads=3)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]


def test_convenience_wrappers_use_the_right_basis():
    rng = np.random.default_rng(6)
    d = dome(15, seed=6)
    stack = stack_from_luminance(rng.uniform(0.1, 0.9, size=(15, 4, 5)))
    np.testing.assert_array_equal(loo_ptm(stack, d)[0], loo_error(stack, light_matrix(d))[0])
    np.testing.assert_array_equal(loo_hsh(stack, d, 3)[0], loo_error(stack, hsh_basis(d, 3))[0])
    with pytest.raises(ValueError):
        loo_ptm(stack, d[:-1])


def test_mask_selects_pixels_for_the_mean_only():
    rng = np.random.default_rng(7)
    d = dome(12, seed=7)
    stack = stack_from_luminance(rng.uniform(0.1, 0.9, size=(12, 6, 6)))
    mask = np.zeros((6, 6), bool)
    mask[1:3, 2:5] = True
    full_map, _ = loo_ptm(stack, d)
    masked_map, mean = loo_ptm(stack, d, mask=mask)
    np.testing.assert_array_equal(full_map, masked_map)
    np.testing.assert_allclose(mean, np.sqrt((full_map[mask].astype(np.float64) ** 2).mean()),
                               rtol=1e-6)
    with pytest.raises(ValueError):
        loo_ptm(stack, d, mask=np.zeros((6, 6), bool))


def test_transform_compares_encoded_values():
    rng = np.random.default_rng(8)
    d = dome(12, seed=8)
    stack = stack_from_luminance(rng.uniform(0.1, 0.9, size=(12, 5, 4)))
    basis = hsh_basis(d, 2)

    def levels(v):
        return 255.0 * linear_to_srgb(v)

    rms_map, _ = loo_error(stack, basis, transform=levels)
    observed = stack.band(0, 5)[0].astype(np.float64)
    predicted = observed - brute_force(observed, basis)
    expected = np.sqrt(((levels(observed) - levels(predicted)) ** 2).mean(axis=0))
    np.testing.assert_allclose(rms_map, expected, rtol=1e-6)


def test_light_with_leverage_one_is_left_out_and_reported():
    rng = np.random.default_rng(9)
    # The last column is non-zero only for light 0: without light 0 its coefficient is free.
    basis = np.column_stack([rng.normal(size=(10, 3)), np.eye(10)[:, 0]])
    h = hat_diagonal(basis)
    np.testing.assert_allclose(h[0], 1.0)
    assert np.all(h[1:] < 1 - 1e-3)
    np.testing.assert_array_equal(undetermined_lights(basis), [0])
    values = rng.uniform(size=(10, 6))
    with pytest.warns(UndeterminedLightWarning, match=r"\[0\]"):
        resid, used = loo_residuals(values, basis)
    np.testing.assert_array_equal(used, np.arange(1, 10))
    assert np.all(np.isfinite(resid))
    np.testing.assert_allclose(resid, brute_force(values, basis, skip=(0,)), rtol=1e-9, atol=1e-12)

    stack = stack_from_luminance(rng.uniform(0.1, 0.9, size=(10, 3, 4)))
    with pytest.warns(UndeterminedLightWarning):
        rms_map, mean = loo_error(stack, basis)
    assert np.all(np.isfinite(rms_map)) and np.isfinite(mean)
    stored = stack.band(0, 3)[0].astype(np.float64)
    expected = np.sqrt((brute_force(stored, basis, skip=(0,)) ** 2).mean(axis=0))
    np.testing.assert_allclose(rms_map, expected, rtol=1e-6)


def test_no_warning_when_every_light_counts():
    basis = hsh_basis(dome(20, seed=10), 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loo_residuals(np.ones((20, 3)), basis)


def test_as_many_lights_as_terms_is_an_input_error():
    d = dome(9, seed=11)
    stack = stack_from_luminance(np.full((9, 2, 2), 0.5))
    np.testing.assert_allclose(hat_diagonal(hsh_basis(d, 3)), 1.0)
    with pytest.raises(InputError, match="more lights"):
        loo_hsh(stack, d, 3)
    # Order 2 has four terms, so the same nine lights are enough.
    rms_map, mean = loo_hsh(stack, d, 2)
    np.testing.assert_allclose(rms_map, 0.0, atol=1e-6)


def test_ring_rounded_like_an_lp_file_keeps_the_exact_rank():
    az = np.radians(np.arange(24) * 15.0)
    ring = np.round(np.stack([np.cos(az), np.sin(az), np.full(24, 1.0)], 1) / np.sqrt(2), 6)
    # 1, cos φ, sin φ, cos 2φ, sin 2φ: five independent terms for both PTM and HSH 3.
    np.testing.assert_allclose(hat_diagonal(light_matrix(ring)).sum(), 5.0, atol=1e-9)
    np.testing.assert_allclose(hat_diagonal(hsh_basis(ring, 3)).sum(), 5.0, atol=1e-9)
    np.testing.assert_allclose(hat_diagonal(hsh_basis(ring, 2)).sum(), 3.0, atol=1e-9)
    # Same span up to the rounding of the directions, so the same leave-one-out residuals.
    values = np.random.default_rng(13).uniform(size=(24, 10))
    np.testing.assert_allclose(loo_residuals(values, light_matrix(ring))[0],
                               loo_residuals(values, hsh_basis(ring, 3))[0], atol=1e-5)
