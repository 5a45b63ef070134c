"""The compiled robust PTM fit against the NumPy steps it follows (ptmcore.robustptm)."""

import numpy as np
import pytest

from ptmcore import robust, robustptm
from ptmcore.fit import light_matrix
from ptmcore.pixelfit import orthonormal_basis
from ptmcore.robustptm import debiased_normals, robust_ptm

from helpers import dome, sphere_normals, stack_from_luminance
from test_robust import EPS32, _corrupted_sphere, _half_vectors, _lambertian, conditioning, final_weights

_UP = np.array([0.0, 0.0, 1.0], np.float32)


def _angle(a, b):
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _turn(a, q, da, dq):
    """Degrees the debiased normals of PTMs ``a`` and hemisphere PTMs ``q`` (..., 6) can turn
    when each of a0–a4 moves by ``da`` and each of q0–q4 by ``dq`` (...): first order, by
    finite differences of those sizes, plus the float32 rounding of two normals."""
    a, q = a.astype(np.float64), q.astype(np.float64)
    base = debiased_normals(a, q)
    turn = np.full(a.shape[:-1], np.degrees(2 * EPS32))
    for k in range(5):
        a_k, q_k = a.copy(), q.copy()
        a_k[..., k] += da
        q_k[..., k] += dq
        turn += _angle(debiased_normals(a_k, q), base) + _angle(debiased_normals(a, q_k), base)
    return turn


def _compare(new, ref, stack, dirs, method="irls", cone=30.0):
    """The compiled fit against the NumPy steps, where float32 rounding leaves them defined.

    Both solve each pixel's weighted least squares from float32 sums of n photographs added in
    other orders (by BLAS, by the kernel), so the fits differ by up to n·EPS32·κ of their size
    (κ: the pixel's condition number, ``test_robust.conditioning``), compared as the fitted
    polynomials' values at the lights (what the fit determines, whatever the basis's rank), and
    by the float32 rounding of the coefficients. The debiased normals may differ by what moves
    of the coefficients that size turn them; where the PTM is flat (``ptmcore.normals.FLAT``)
    both are (0, 0, 1) and flagged.
    """
    n = len(dirs)
    phi = light_matrix(dirs)
    basis = orthonormal_basis(phi, dirs[:, 2:3])
    kappa = conditioning(final_weights(stack, dirs, method, cone), basis, robustptm._PTM_SINGULAR, 1.0)
    bound = n * EPS32 * kappa.reshape(stack.shape)
    # The largest move of the coefficients that a move of their values at the lights can be.
    to_coefficients = np.linalg.norm(basis.back, 2)
    moves = []
    for got, want in ((new.ptm.coefficients, ref.ptm.coefficients), (new.hemisphere, ref.hemisphere)):
        want = want.astype(np.float64)
        size = np.linalg.norm(want @ phi.T, axis=-1)
        stored = EPS32 * np.linalg.norm(phi, 2) * np.linalg.norm(want, axis=-1)
        moved = np.linalg.norm((got - want) @ phi.T, axis=-1)
        assert (moved <= bound * size + stored).all(), (moved / (bound * size + stored)).max()
        moves.append(bound * size * to_coefficients + EPS32 * np.abs(want).max(axis=-1))
    np.testing.assert_array_equal(new.valid, ref.valid)
    assert (new.normals[~new.valid] == _UP).all() and (ref.normals[~ref.valid] == _UP).all()
    # Not where rounding chooses between the weighted and the plain fit (κ = inf).
    defined = ref.valid & np.isfinite(bound)
    turn = _turn(ref.ptm.coefficients, ref.hemisphere, *(np.where(defined, m, 0.0) for m in moves))
    angles = _angle(new.normals, ref.normals)
    assert (angles[defined] <= turn[defined]).all(), (angles / turn)[defined].max()
    np.testing.assert_allclose(new.samples, ref.samples, atol=0.05)
    # The normals are the debiased normals of the PTM and hemisphere the kernel wrote (in
    # float64, before they were stored as float32).
    again = debiased_normals(new.ptm.coefficients, new.hemisphere)
    stored = [EPS32 * np.abs(x).max(axis=-1) for x in (new.ptm.coefficients, new.hemisphere)]
    assert (_angle(again, new.normals) <= _turn(new.ptm.coefficients, new.hemisphere, *stored)).all()


@pytest.mark.parametrize("method", robust.METHODS)
@pytest.mark.parametrize("cone", [30.0, None])
def test_kernel_matches_the_numpy_steps(method, cone):
    values, _, _, dirs = _corrupted_sphere(seed=2)
    values[:, 10:14, 10:14] = 1.0  # clipped samples, left out the same way
    stack = stack_from_luminance(values, values >= 1.0)
    ref = robust_ptm(stack, dirs, method=method, specular_cone=cone, compiled=False)
    new = robust_ptm(stack, dirs, method=method, specular_cone=cone)
    _compare(new, ref, stack, dirs, method, cone)
    # Every sample clipped: the plain fit of a constant, a flat PTM, no normal.
    assert not new.valid[10:14, 10:14].any()
    assert new.valid.sum() == new.valid.size - 16


def test_kernel_with_photographs_and_columns_past_its_blocks():
    # 45 photographs (not a whole number of the kernel's blocks) and 300 columns (a chunk of
    # pixels and part of the next): the padding must change nothing.
    rng = np.random.default_rng(4)
    n_true, _ = sphere_normals(12, 300, 140.0)
    dirs = dome(45, seed=5)
    values = _lambertian(n_true, 0.4, dirs)
    values += 0.5 * np.maximum(np.einsum("nc,hwc->nhw", _half_vectors(dirs), n_true), 0.0) ** 40 * (values > 0)
    values[rng.random(values.shape) < 0.1] = 0.0
    values = np.clip(values + rng.normal(0.0, 0.003, values.shape), 0.0, 1.0)
    stack = stack_from_luminance(values, values >= 1.0)
    _compare(robust_ptm(stack, dirs), robust_ptm(stack, dirs, compiled=False), stack, dirs)


def test_kernel_falls_back_to_the_plain_fit_like_the_numpy_steps():
    # Black pixels and pixels lit by few lights: weights too few for six coefficients, where
    # the plain fit stands in; lights on a ring (a rank-deficient PTM basis), fewer lights than
    # coefficients, and lights in one plane (a rank-deficient Lambertian basis too). Random
    # values make ill-conditioned fits, where rounding moves the solution by more.
    rng = np.random.default_rng(0)
    for dirs in (dome(12, seed=3), _ring(16), dome(5, seed=4), _arc(10)):
        values = rng.random((len(dirs), 6, 9)) * 0.5
        values[:, 0] = 0.0
        values[3:, 1] = 0.0
        stack = stack_from_luminance(values)
        ref = robust_ptm(stack, dirs, compiled=False)
        new = robust_ptm(stack, dirs)
        _compare(new, ref, stack, dirs)
        assert np.isfinite(new.ptm.coefficients).all()
        assert not new.valid[0].any()  # black: an all-zero PTM


def _arc(n):
    el = np.radians(np.linspace(20.0, 160.0, n))
    return np.stack([np.cos(el), np.zeros_like(el), np.sin(el)], axis=1)  # all in the plane y = 0


def _ring(n):
    az = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    el = np.radians(35.0)
    return np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.full(n, np.sin(el))], axis=1)


def test_kernel_recovers_a_clean_lambertian_sphere_and_threads_agree(monkeypatch):
    n_true, mask = sphere_normals(40, 40, 19.0)
    dirs = dome(40, seed=2)
    stack = stack_from_luminance(_lambertian(n_true, 0.6, dirs))
    monkeypatch.setattr(robust, "_KERNEL_PIXELS", 40 * 6)  # bands of 6 rows: two threads share them
    one = robust_ptm(stack, dirs, threads=1)
    two = robust_ptm(stack, dirs, threads=2)
    np.testing.assert_array_equal(one.ptm.coefficients, two.ptm.coefficients)
    np.testing.assert_array_equal(one.normals, two.normals)
    assert _angle(one.normals[mask], n_true[mask]).max() < 0.2


def test_options_the_kernel_does_not_do_run_the_numpy_steps():
    values, _, _, dirs = _corrupted_sphere(seed=1)
    stack = stack_from_luminance(values)
    fixed = robust.robust_photometric_stereo(stack, dirs).normals
    for kwargs in ({"refine": 1}, {"normals": fixed}):
        a = robust_ptm(stack, dirs, **kwargs)
        b = robust_ptm(stack, dirs, compiled=False, **kwargs)
        np.testing.assert_array_equal(a.ptm.coefficients, b.ptm.coefficients)


def test_the_robust_ptm_is_not_fitted_with_a_lobe():
    values, _, _, dirs = _corrupted_sphere(seed=1)
    stack = stack_from_luminance(values)
    opt = robust.RobustOptions("irls", 3, 0.05, 0.05, 0.4, 30.0, 3.0, 2.0, 0.002, 0.01)
    prior = np.zeros(stack.shape + (3,), np.float32)
    with pytest.raises(ValueError, match="lobe"):
        robust.robust_rows(stack, dirs, opt, 1, None, prior=prior, ptm=())
