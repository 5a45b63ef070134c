import numpy as np
import pytest

from ptmcore import pixelfit, robust
from ptmcore.fit import fit_ptm, light_matrix
from ptmcore.lp import as_directions
from ptmcore.normals import angular_error, normals_from_ptm, photometric_stereo
from ptmcore.robust import robust_photometric_stereo
from ptmcore.robustptm import debiased_normals, hemisphere_coefficients, robust_fit_ptm, robust_ptm

from helpers import dome, sphere_normals, stack_from_luminance


def _lambertian(normals, albedo, dirs):
    return albedo * np.maximum(np.einsum("nc,hwc->nhw", dirs, normals), 0.0)


def _half_vectors(dirs):
    h = dirs + [0.0, 0.0, 1.0]
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def _corrupted_sphere(seed=0):
    """A Lambertian sphere with a Blinn–Phong highlight, random cast shadows and noise."""
    rng = np.random.default_rng(seed)
    n_true, mask = sphere_normals(36, 36, 17.0)
    dirs = dome(48, seed=seed + 11)
    values = _lambertian(n_true, 0.4, dirs)
    # A highlight brighter than the diffuse light itself, over several neighbouring lights.
    lobe = np.maximum(np.einsum("nc,hwc->nhw", _half_vectors(dirs), n_true), 0.0) ** 40
    values += 0.5 * lobe * (values > 0)
    # Cast shadows: a tenth of the samples go black.
    values[rng.random(values.shape) < 0.1] = 0.0
    values += rng.normal(0.0, 0.003, values.shape)
    return np.clip(values, 0.0, 1.0), n_true, mask, dirs


#: float32's machine epsilon: a sum of n float32 terms is within n × this of its value, relative
#: to the sum of their magnitudes.
EPS32 = float(np.finfo(np.float32).eps)


def final_weights(stack, dirs, method="irls", specular_cone=30.0):
    """The NumPy steps' final robust weights (N, H·W), with robust_ptm's other defaults."""
    opt = robust.RobustOptions(method, 3, 0.05, 0.05, 0.4, specular_cone, 3.0, 2.0, 0.002, 0.01)
    values, saturated = stack.band(0, stack.shape[0])
    n = len(stack)
    lights = robust.Lights.of(as_directions(dirs, n))
    return robust.robust_lambertian(lights, opt, values.reshape(n, -1), ~saturated.reshape(n, -1))[3]


def conditioning(weights, basis, singular, fallback):
    """Each pixel's condition number of its weighted least squares (Σ w u uᵀ + λI, as the solves
    have it), (P,): two float32 evaluations of it, whose sums of n terms are each within
    n·EPS32 of their value, differ by at most n·EPS32·κ relative to its size.

    Where the fit is ill posed (det ≤ ``singular`` × mean eigenvalue^r) ``fallback`` stands in:
    1 where a matrix product (the plain fit) takes its place, inf where an earlier estimate
    does. Within a factor 2 of that test, which of the two each evaluation takes is rounding:
    inf, nothing to compare.
    """
    u = basis.u.astype(np.float64)
    r = u.shape[1]
    gram = np.einsum("nk,nl,np->pkl", u, u, weights.astype(np.float64))
    mean = np.maximum(np.trace(gram, axis1=1, axis2=2) / r, 1e-30)
    gram += pixelfit._RIDGE * mean[:, None, None] * np.eye(r)
    eig = np.linalg.eigvalsh(gram)
    posed = np.prod(eig, axis=1) / mean**r / singular
    kappa = np.where(posed > 1, eig[:, -1] / eig[:, 0], fallback)
    return np.where((posed > 0.5) & (posed < 2), np.inf, kappa)


def test_exact_recovery_on_clean_lambertian_sphere():
    n_true, mask = sphere_normals(40, 40, 19.0)
    dirs = dome(40, seed=2)
    stack = stack_from_luminance(_lambertian(n_true, 0.6, dirs))
    ps = robust_photometric_stereo(stack, dirs)
    err = angular_error(ps.normals, n_true, mask)
    assert err.max() < 0.1, err.max()
    np.testing.assert_allclose(ps.albedo[mask], 0.6, rtol=1e-3)
    assert ps.valid[mask].all()
    # The clean samples keep their weight: all the lit ones (n·l > min_shading) count.
    lit = (np.einsum("nc,hwc->nhw", dirs, n_true) > 0.05).sum(axis=0)
    assert np.abs(ps.samples[mask].astype(int) - lit[mask]).max() <= 1

    fit = robust_ptm(stack, dirs)
    err = angular_error(fit.normals, n_true, mask)
    assert err.max() < 0.1, err.max()
    np.testing.assert_allclose(fit.normals, debiased_normals(fit.ptm.coefficients, fit.hemisphere), atol=1e-5)


def test_ptm_coefficients_exact_on_biquadratic_data():
    # Whatever samples the weights drop, six well-spread exact samples give the exact
    # coefficients, in fit_ptm's units.
    rng = np.random.default_rng(3)
    dirs = dome(30, seed=3)
    a = (rng.normal(size=(9, 11, 6)) * 0.05).astype(np.float32)
    a[..., 5] += 0.5
    values = np.einsum("nk,hwk->nhw", light_matrix(dirs), a)
    stack = stack_from_luminance(values)
    for method in robust.METHODS:
        coef = robust_fit_ptm(stack, dirs, method=method).coefficients
        np.testing.assert_allclose(coef, a, atol=5e-4)
    np.testing.assert_allclose(fit_ptm(stack, dirs).coefficients, a, atol=2e-4)


@pytest.mark.parametrize("method, ps_limit, ptm_limit", [("irls", 0.8, 2.0), ("trimmed", 1.2, 3.0)])
def test_robust_to_shadows_and_highlights(method, ps_limit, ptm_limit):
    values, n_true, mask, dirs = _corrupted_sphere()
    stack = stack_from_luminance(values)
    plain = angular_error(photometric_stereo(stack, dirs).normals, n_true, mask)
    ps = robust_photometric_stereo(stack, dirs, method=method)
    err = angular_error(ps.normals, n_true, mask)
    # Measured (mean): plain 6.4°; robust 0.50° (IRLS), 0.84° (trimmed).
    assert plain.mean() > 5.0
    assert err.mean() < ps_limit, err.mean()
    np.testing.assert_allclose(np.median(ps.albedo[mask]), 0.4, rtol=0.02)

    fit = robust_ptm(stack, dirs, method=method)
    err_ptm = angular_error(fit.normals, n_true, mask)
    plain_ptm = angular_error(normals_from_ptm(fit_ptm(stack, dirs).coefficients), n_true, mask)
    # Measured (mean): plain PTM maximum 34°; debiased robust PTM 1.3° (IRLS), 2.3° (trimmed).
    # Six coefficients absorb more of what is left of the highlight than three do.
    assert plain_ptm.mean() > 25.0
    assert err_ptm.mean() < ptm_limit, err_ptm.mean()


def test_ptm_normals_on_lambertian_sphere_much_closer_than_plain():
    n_true, mask = sphere_normals(40, 40, 19.0)  # slants up to 72°
    dirs = dome(40, seed=2)  # 15–75° elevation
    stack = stack_from_luminance(_lambertian(n_true, 0.6, dirs))
    plain = angular_error(normals_from_ptm(fit_ptm(stack, dirs).coefficients), n_true, mask)
    fit = robust_ptm(stack, dirs)
    robust_max = angular_error(normals_from_ptm(fit.ptm.coefficients), n_true, mask)
    debiased = angular_error(fit.normals, n_true, mask)
    # Measured (mean): plain maximum 17.7°, maximum of the robust fit 10.8° (it leaves out the
    # attached shadows; the rest is the biquadratic's bias), debiased 0.001°.
    assert plain.mean() > 15.0
    assert robust_max.mean() < 12.0
    assert debiased.mean() < 0.01
    slant = np.degrees(np.arccos(n_true[..., 2]))[mask]
    steep = (slant > 45) & (slant < 60)
    assert robust_max[steep].mean() < 0.5 * plain[steep].mean()  # measured 12.4° vs 33.9°


def test_plain_fit_debiased_with_hemisphere_of_the_lights():
    # Without attached shadows the plain fit is the exact projection of n·l, so reading its
    # maximum through the lights' hemisphere PTM recovers the normal.
    n_true, mask = sphere_normals(30, 30, 30.0)  # slants up to 30°
    dirs = dome(40, seed=5, min_elev=40.0)
    values = _lambertian(n_true, 0.5, dirs)
    assert values[:, mask].min() > 0
    coef = fit_ptm(stack_from_luminance(values), dirs).coefficients
    plain = angular_error(normals_from_ptm(coef), n_true, mask)
    err = angular_error(debiased_normals(coef, hemisphere_coefficients(dirs)), n_true, mask)
    assert plain.max() > 5.0
    assert err.max() < 0.05, err.max()


def test_ring_of_lights_rank_deficient_ptm():
    # All lights at one elevation: lu² + lv² is constant, the PTM basis has rank 5.
    el = np.radians(40.0)
    az = np.radians(np.arange(24) * 15.0 + 3.0)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(24, np.sin(el))], 1)
    n_true, mask = sphere_normals(30, 30, 20.0)
    stack = stack_from_luminance(_lambertian(n_true, 0.5, dirs))
    fit = robust_ptm(stack, dirs)
    assert np.isfinite(fit.ptm.coefficients).all()
    # The coefficients are the minimum-norm ones, like fit_ptm's, where nothing is left out.
    flat = mask & (n_true[..., 2] > 0.999)
    np.testing.assert_allclose(fit.ptm.coefficients[flat], fit_ptm(stack, dirs).coefficients[flat], atol=1e-4)
    err = angular_error(fit.normals, n_true, mask & (n_true[..., 2] > np.cos(np.radians(40))))
    assert err.max() < 0.1, err.max()
    ps = robust_photometric_stereo(stack, dirs)
    assert angular_error(ps.normals, n_true, mask).max() < 0.1


def test_same_result_whatever_the_bands_and_threads(monkeypatch):
    values, n_true, mask, dirs = _corrupted_sphere(seed=4)
    stack = stack_from_luminance(values)
    ref_ps = robust_photometric_stereo(stack, dirs, threads=1)
    ref_ptm = robust_ptm(stack, dirs, threads=1)
    # Bands of one row in three threads, and Cholesky chunks smaller than a band.
    monkeypatch.setattr(robust, "_BAND_BYTES", 1)
    monkeypatch.setattr(robust, "_KERNEL_PIXELS", 1)
    monkeypatch.setattr(pixelfit, "_CHUNK", 7)
    rows = []
    ps = robust_photometric_stereo(stack, dirs, threads=3, progress=rows.append)
    ptm = robust_ptm(stack, dirs, threads=3)
    assert sum(rows) == stack.shape[0] and len(rows) == stack.shape[0]
    np.testing.assert_allclose(ps.normals, ref_ps.normals, atol=1e-5)
    np.testing.assert_allclose(ps.albedo, ref_ps.albedo, atol=1e-5)
    np.testing.assert_array_equal(ps.samples, ref_ps.samples)
    # Blocks of other sizes sum the float32 products in another order.
    np.testing.assert_allclose(ptm.ptm.coefficients, ref_ptm.ptm.coefficients, atol=5e-5)
    np.testing.assert_allclose(ptm.hemisphere, ref_ptm.hemisphere, atol=5e-5)
    h, w = stack.shape
    assert ps.normals.shape == (h, w, 3) and ps.normals.dtype == np.float32
    assert ps.albedo.shape == (h, w) and ps.valid.shape == (h, w)
    assert ptm.ptm.coefficients.shape == (h, w, 6) and ptm.ptm.coefficients.dtype == np.float32
    assert ptm.normals.shape == (h, w, 3) and ptm.samples.shape == (h, w)
    np.testing.assert_allclose(np.linalg.norm(ptm.normals, axis=-1), 1.0, atol=1e-5)


def test_given_normals_fix_the_attached_shadows():
    values, n_true, mask, dirs = _corrupted_sphere(seed=1)
    stack = stack_from_luminance(values)
    fit = robust_ptm(stack, dirs, normals=n_true)
    # Measured: 1.1° mean (1.8° when the fit finds the normals itself).
    assert angular_error(fit.normals, n_true, mask).mean() < 1.5
    with pytest.raises(ValueError, match="shape"):
        robust_ptm(stack, dirs, normals=n_true[:-1])


def test_saturated_samples_are_ignored():
    n_true, mask = sphere_normals(32, 32, 14.0)
    dirs = dome(30, seed=4)
    values = _lambertian(n_true, 1.3, dirs)
    saturated = values >= 1.0
    assert saturated.any()
    ps = robust_photometric_stereo(stack_from_luminance(values, saturated), dirs)
    assert np.percentile(angular_error(ps.normals, n_true, mask), 99) < 0.5


def test_dark_pixels_are_flagged_not_guessed():
    dirs = dome(10, seed=5)
    stack = stack_from_luminance(np.zeros((10, 4, 4)))
    ps = robust_photometric_stereo(stack, dirs)
    assert not ps.valid.any()
    np.testing.assert_allclose(ps.normals[..., 2], 1.0)
    fit = robust_ptm(stack, dirs)
    assert np.isfinite(fit.ptm.coefficients).all()
    np.testing.assert_allclose(fit.normals[..., 2], 1.0)


def test_lights_in_one_plane_leave_normals_undetermined():
    az = np.radians([0.0, 30.0, 60.0, 90.0, 120.0])
    dirs = np.stack([np.cos(az), np.zeros(5), np.sin(az)], axis=1)  # all in the plane y = 0
    n_true, _ = sphere_normals(6, 6, 4.0)
    ps = robust_photometric_stereo(stack_from_luminance(_lambertian(n_true, 0.5, dirs)), dirs)
    assert not ps.valid.any()


def test_bad_options():
    stack = stack_from_luminance(np.full((8, 3, 3), 0.5))
    dirs = dome(8, seed=1)
    with pytest.raises(ValueError, match="method"):
        robust_photometric_stereo(stack, dirs, method="median")
    with pytest.raises(ValueError, match="iterations"):
        robust_ptm(stack, dirs, iterations=-1)
    with pytest.raises(ValueError, match="specular_cone"):
        robust_photometric_stereo(stack, dirs, specular_cone=95.0)
    with pytest.raises(ValueError):
        robust_ptm(stack, dirs[:-1])


def test_batched_cholesky_matches_numpy():
    rng = np.random.default_rng(0)
    r, p = 6, 50
    m = rng.normal(size=(p, r, r))
    gram = m @ m.transpose(0, 2, 1) + 0.1 * np.eye(r)
    b = rng.normal(size=(p, r))
    i, j = np.triu_indices(r)
    (x,), ok = pixelfit.cholesky_solve(np.ascontiguousarray(gram[:, i, j].T), [b.T.copy()], None)
    ridge = pixelfit._RIDGE * np.trace(gram, axis1=1, axis2=2)[:, None, None] / r * np.eye(r)
    expected = np.linalg.solve(gram + ridge, b[..., None])[..., 0]
    np.testing.assert_allclose(x.T, expected, rtol=1e-9, atol=1e-12)
    assert ok.all()
    # A singular matrix is flagged, and its solution tends to the prior.
    gram[0] = np.outer(gram[0, 0], gram[0, 0])
    prior = rng.normal(size=(r, p))
    (x,), ok = pixelfit.cholesky_solve(np.ascontiguousarray(gram[:, i, j].T), [np.zeros((r, p))], [prior])
    assert not ok[0] and ok[1:].all()
    assert np.all(np.isfinite(x))
