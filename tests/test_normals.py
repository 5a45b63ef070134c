import numpy as np
import pytest

from ptmcore.normals import angular_error, lambertian_albedo, normals_from_ptm, photometric_stereo, ptm_maximum

from helpers import dome, sphere_normals, stack_from_luminance


def _biquadratic_with_maximum_at(lu0, lv0, a0=-1.0, a1=-0.7, a2=0.3, a5=1.0):
    # Gradient zero at (lu0, lv0): 2·a0·lu + a2·lv + a3 = 0 and a2·lu + 2·a1·lv + a4 = 0.
    a3 = -(2 * a0 * lu0 + a2 * lv0)
    a4 = -(a2 * lu0 + 2 * a1 * lv0)
    return np.stack(np.broadcast_arrays(a0, a1, a2, a3, a4, a5), axis=-1).astype(np.float64)


def test_closed_form_maximum_on_biquadratic_field():
    rows, cols = np.mgrid[0:30, 0:40]
    lu0 = (cols - 20) / 30.0
    lv0 = (15 - rows) / 22.0
    coef = _biquadratic_with_maximum_at(lu0, lv0).astype(np.float32)
    n = normals_from_ptm(coef)
    np.testing.assert_allclose(n[..., 0], lu0, atol=1e-5)
    np.testing.assert_allclose(n[..., 1], lv0, atol=1e-5)
    np.testing.assert_allclose(n[..., 2], np.sqrt(1 - lu0**2 - lv0**2), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)


def _brute_force_disk_max(a):
    t = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    r = np.linspace(0, 1, 400)
    lu = (r[:, None] * np.cos(t)[None]).ravel()
    lv = (r[:, None] * np.sin(t)[None]).ravel()
    val = a[0] * lu**2 + a[1] * lv**2 + a[2] * lu * lv + a[3] * lu + a[4] * lv
    k = np.argmax(val)
    return lu[k], lv[k], val[k]


@pytest.mark.parametrize(
    "a",
    [
        [1.0, 1.0, 0.0, 0.3, 0.1, 0.0],  # convex: maximum on the circle
        [0.5, -0.8, 0.2, -0.1, 0.4, 0.2],  # saddle
        [-0.2, -0.2, 0.0, 1.0, 0.6, 0.0],  # concave, stationary point far outside the disk
        [0.0, 0.0, 0.0, 0.0, 0.5, 0.0],  # linear: straight up the gradient
    ],
)
def test_maximum_falls_back_to_the_unit_circle(a):
    a = np.array(a)
    lu, lv, interior = ptm_maximum(a[None])
    assert not interior[0]
    assert lu[0] ** 2 + lv[0] ** 2 == pytest.approx(1.0, abs=1e-5)
    bu, bv, best = _brute_force_disk_max(a)
    got = a[0] * lu[0] ** 2 + a[1] * lv[0] ** 2 + a[2] * lu[0] * lv[0] + a[3] * lu[0] + a[4] * lv[0]
    assert got >= best - 1e-6


def _render(normals, albedo, dirs, ambient=0.0):
    shading = np.einsum("nc,hwc->nhw", dirs, normals)
    return albedo * np.maximum(shading, 0) + ambient


def test_photometric_stereo_exact_on_lambertian_sphere_with_shadows():
    n_true, mask = sphere_normals(48, 56, 22.0)
    dirs = dome(40, seed=2)
    values = _render(n_true, 0.6, dirs)
    values[5, 20:30, 20:30] = 0.0  # a cast shadow across part of the sphere
    ps = photometric_stereo(stack_from_luminance(values), dirs)
    err = angular_error(ps.normals, n_true, mask)
    assert err.max() < 0.5, err.max()
    assert np.median(err) < 0.05
    np.testing.assert_allclose(ps.albedo[mask], 0.6, rtol=5e-3)
    assert ps.valid[mask].all()


def test_photometric_stereo_ignores_saturated_samples():
    n_true, mask = sphere_normals(32, 32, 14.0)
    dirs = dome(30, seed=4)
    values = _render(n_true, 1.3, dirs)
    saturated = values >= 1.0
    assert saturated.any()
    ps = photometric_stereo(stack_from_luminance(values, saturated), dirs)
    err = angular_error(ps.normals, n_true, mask)
    assert np.percentile(err, 99) < 0.5
    np.testing.assert_allclose(np.median(ps.albedo[mask]), 1.3, rtol=5e-3)


def test_undetermined_pixels_are_flagged():
    dirs = dome(10, seed=5)
    values = np.zeros((10, 4, 4))
    ps = photometric_stereo(stack_from_luminance(values), dirs)
    assert not ps.valid.any()
    np.testing.assert_allclose(ps.normals[..., 2], 1.0)


def test_lambertian_albedo_given_true_normals():
    n_true, mask = sphere_normals(30, 30, 13.0)
    dirs = dome(25, seed=6)
    values = _render(n_true, 0.45, dirs)
    rho = lambertian_albedo(stack_from_luminance(values), dirs, n_true)
    np.testing.assert_allclose(rho[mask], 0.45, rtol=2e-3)


def test_ptm_normals_close_on_lambertian_sphere_without_shadows():
    # On a Lambertian surface the biquadratic only approximates n·l (its √(1 − lu² − lv²) term
    # most of all), so the maximum is pulled towards the view direction by a few degrees at
    # moderate slant: a bias of the model, which is why photometric stereo is the default.
    from ptmcore.fit import fit_ptm

    n_true, mask = sphere_normals(40, 40, 30.0)
    dirs = dome(48, seed=7, min_elev=30)
    values = _render(n_true, 0.5, dirs)
    ptm = fit_ptm(stack_from_luminance(values), dirs)
    n = normals_from_ptm(ptm.coefficients)
    inner = mask & (n_true[..., 2] > 0.9)
    err = angular_error(n, n_true, inner)
    assert np.median(err) < 5.0
    centre = mask & (n_true[..., 2] > 0.995)
    assert angular_error(n, n_true, centre).max() < 2.0


def test_angular_error_values():
    a = np.array([[[0, 0, 1.0]]])
    b = np.array([[[np.sin(0.1), 0, np.cos(0.1)]]])
    assert angular_error(a, b)[0, 0] == pytest.approx(np.degrees(0.1), rel=1e-4)
