"""The reflectance lobe fitted with the normals (ptmcore.lobe, robust_photometric_stereo(lobe=...))."""

from pathlib import Path

import numpy as np
import pytest

from ptmcore.lobe import FACTOR_RANGE, Lobe, estimate_lobe, lobe_factors
from ptmcore.normals import angular_error
from ptmcore.robust import RobustOptions, robust_photometric_stereo

from helpers import dome, sphere_normals, stack_from_luminance

REAL_CAT = Path(__file__).resolve().parents[1].parent / "shared" / "real" / "diligent_cat"
OPTIONS = RobustOptions("irls", 3, 0.05, 0.05, 0.4, 30.0, 3.0, 2.0, 0.002, 0.01)


def _halves(dirs):
    h = dirs + [0.0, 0.0, 1.0]
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def _glossy_sphere(specular, shininess, seed=0):
    """A sphere with a Lambertian part and a broad Blinn–Phong lobe, with noise."""
    n_true, mask = sphere_normals(72, 72, 34.0)
    dirs = dome(48, seed=seed + 5)
    shading = np.maximum(np.einsum("nc,hwc->nhw", dirs, n_true), 0.0)
    lobe = np.maximum(np.einsum("nc,hwc->nhw", _halves(dirs), n_true), 0.0) ** shininess
    values = 0.5 * shading + specular * lobe * (shading > 0)
    values += np.random.default_rng(seed).normal(0.0, 0.002, values.shape)
    return stack_from_luminance(np.clip(values, 0.0, 1.0)), n_true, mask, dirs


def test_lobe_factors_evaluate_the_polynomial_within_bounds():
    rng = np.random.default_rng(1)
    dirs = dome(20, seed=1)
    unit = rng.normal(size=(3, 50))
    unit[2] = np.abs(unit[2])
    unit /= np.linalg.norm(unit, axis=0)
    c = np.array([1.1, -2.0, 8.0, -16.0, 11.0])
    x = 1.0 - _halves(dirs) @ unit
    expected = np.clip(sum(a * x**k for k, a in enumerate(c)), *FACTOR_RANGE)
    np.testing.assert_allclose(lobe_factors(c, _halves(dirs), unit), expected, rtol=1e-5)
    # Far outside the fitted range the polynomial is clipped, never zero or negative.
    assert lobe_factors(np.array([1.0, -50.0, 0, 0, 0]), _halves(dirs), unit).min() == FACTOR_RANGE[0]


def test_lambertian_object_has_no_lobe_and_unchanged_normals():
    stack, n_true, mask, dirs = _glossy_sphere(0.0, 10.0)
    assert estimate_lobe(stack, dirs, OPTIONS) is None
    plain = robust_photometric_stereo(stack, dirs)
    with_lobe = robust_photometric_stereo(stack, dirs, lobe=True)
    assert with_lobe.lobe is None
    np.testing.assert_array_equal(plain.normals, with_lobe.normals)


@pytest.mark.parametrize("specular, shininess", [(0.4, 10.0), (0.5, 20.0)])
def test_broad_lobe_is_fitted_and_removes_the_tilt(specular, shininess):
    stack, n_true, mask, dirs = _glossy_sphere(specular, shininess)
    irls = robust_photometric_stereo(stack, dirs)
    fitted = robust_photometric_stereo(stack, dirs, lobe=True)
    assert isinstance(fitted.lobe, Lobe) and fitted.lobe.gain > 0.1
    # Up to 60° of slant, where the lights still see the surface from both sides.
    inner = mask & (n_true[..., 2] > 0.5)
    before = angular_error(irls.normals, n_true, inner).mean()
    after = angular_error(fitted.normals, n_true, inner).mean()
    assert after < 0.5 * before, (before, after)


def test_kernel_with_lobe_matches_the_numpy_steps():
    stack, n_true, mask, dirs = _glossy_sphere(0.4, 10.0)
    lobe = estimate_lobe(stack, dirs, OPTIONS)
    compiled = robust_photometric_stereo(stack, dirs, lobe=lobe)
    reference = robust_photometric_stereo(stack, dirs, lobe=lobe, compiled=False)
    assert compiled.lobe is lobe
    # Float32 rounding of the weights moves a few pixels by hundredths of a degree, as without
    # a lobe (tests/test_robust_kernel.py).
    err = angular_error(compiled.normals, reference.normals, mask)
    assert err.mean() < 2e-3 and err.max() < 0.05, (err.mean(), err.max())


@pytest.mark.skipif(not REAL_CAT.is_dir(), reason="real data (../shared/real) not present")
def test_real_cat_beats_st14():
    from ptmcore.psdataset import read_ps_dataset

    ds = read_ps_dataset(REAL_CAT)
    dirs = ds.lights.directions
    truth, mask = ds.ground_truth_normals, ds.mask
    irls = angular_error(robust_photometric_stereo(ds.stack, dirs).normals, truth, mask).mean()
    lobe = angular_error(robust_photometric_stereo(ds.stack, dirs, lobe=True).normals, truth, mask).mean()
    # ST14 (Shi et al. 2014), the best classical method of DiLiGenT, reports 6.12° on this object.
    assert lobe < 6.12 < irls, (lobe, irls)
