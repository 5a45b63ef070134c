"""The compiled robust photometric stereo against the NumPy steps it follows."""

import numpy as np
import pytest

from ptmcore import robust
from ptmcore.images import ImageStack, default_table
from ptmcore.pixelfit import SINGULAR
from ptmcore.robust import robust_photometric_stereo

from helpers import dome, sphere_normals, stack_from_luminance
from test_robust import EPS32, _corrupted_sphere, _half_vectors, _lambertian, conditioning, final_weights


def _numpy_steps(stack, directions, method, specular_cone):
    return robust_photometric_stereo(stack, directions, method=method, specular_cone=specular_cone, compiled=False)


def _angle(a, b):
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _compare(new, ref, stack, dirs, method="irls", cone=30.0):
    """The compiled fit against the NumPy steps, where float32 rounding leaves them defined.

    Both solve each pixel's weighted least squares from float32 sums of n photographs added in
    other orders, so their solutions in the lights' orthonormal basis differ by up to
    n·EPS32·κ of their size (κ: the pixel's condition number, ``test_robust.conditioning``),
    and ρn by κ(L) times that (L: the light directions), as do the normals (in radians) and
    the albedo, relative to it; plus the float32 rounding of the results. Where the last
    robust pass's fit is ill posed an earlier estimate stands: not compared. Undetermined
    normals (``valid`` False) must agree and be (0, 0, 1) with an albedo of 0.
    """
    n = len(dirs)
    kappa = conditioning(final_weights(stack, dirs, method, cone), robust.Lights.of(dirs).lambertian, SINGULAR, np.inf)
    bound = n * EPS32 * kappa.reshape(stack.shape) * np.linalg.cond(dirs) + 2 * EPS32
    np.testing.assert_array_equal(new.valid, ref.valid)
    for out in (new, ref):
        assert (out.normals[~out.valid] == np.float32([0.0, 0.0, 1.0])).all() and (out.albedo[~out.valid] == 0).all()
    defined = ref.valid & np.isfinite(bound)
    bound = bound[defined]
    angles = np.radians(_angle(new.normals[defined], ref.normals[defined]))
    assert (angles <= bound).all(), (angles / bound).max()
    moved = np.abs(new.albedo[defined] - ref.albedo[defined])
    assert (moved <= bound * ref.albedo[defined]).all(), (moved / (bound * ref.albedo[defined])).max()
    assert np.abs(new.samples.astype(int) - ref.samples).max() <= 1
    assert np.mean(new.samples != ref.samples) < 0.01


@pytest.mark.parametrize("method", robust.METHODS)
@pytest.mark.parametrize("cone", [30.0, None])
def test_kernel_matches_the_numpy_steps(method, cone):
    values, _, _, dirs = _corrupted_sphere(seed=2)
    # Some clipped samples too: they must be left out the same way.
    values[:, 10:14, 10:14] = 1.0
    saturated = values >= 1.0
    stack = stack_from_luminance(values, saturated)
    ref = _numpy_steps(stack, dirs, method, cone)
    new = robust_photometric_stereo(stack, dirs, method=method, specular_cone=cone)
    _compare(new, ref, stack, dirs, method, cone)


@pytest.mark.parametrize("method", robust.METHODS)
def test_kernel_with_photographs_and_columns_past_its_blocks(method):
    # 45 photographs, not a whole number of the kernel's blocks of photographs, and 300 columns,
    # one chunk of pixels and part of the next: the padding must change nothing.
    rng = np.random.default_rng(4)
    n_true, _ = sphere_normals(12, 300, 140.0)
    dirs = dome(45, seed=5)
    values = _lambertian(n_true, 0.4, dirs)
    lobe = np.maximum(np.einsum("nc,hwc->nhw", _half_vectors(dirs), n_true), 0.0) ** 40
    values += 0.5 * lobe * (values > 0)
    values[rng.random(values.shape) < 0.1] = 0.0
    values = np.clip(values + rng.normal(0.0, 0.003, values.shape), 0.0, 1.0)
    values[:, 4:7, 250:262] = 1.0  # clipped, across the chunks' border
    stack = stack_from_luminance(values, values >= 1.0)
    ref = _numpy_steps(stack, dirs, method, 30.0)
    new = robust_photometric_stereo(stack, dirs, method=method)
    _compare(new, ref, stack, dirs, method)


def test_kernel_with_lights_in_one_plane_and_dark_pixels():
    el = np.radians(np.linspace(20.0, 160.0, 12))
    ring = np.stack([np.cos(el), np.zeros_like(el), np.sin(el)], axis=1)  # all in the plane y = 0
    rng = np.random.default_rng(0)
    values = rng.random((len(ring), 5, 7))
    values[:, 0] = 0.0
    stack = stack_from_luminance(values)
    for dirs in (ring, dome(12, seed=3)):
        ref = _numpy_steps(stack, dirs, "irls", 30.0)
        new = robust_photometric_stereo(stack, dirs)
        _compare(new, ref, stack, dirs)
    assert not robust_photometric_stereo(stack, ring).valid.any()  # one plane: undetermined
    assert not robust_photometric_stereo(stack, dome(12, seed=3)).valid[0].any()  # black


def test_kernel_reads_8_bit_codes_through_the_stack_table():
    # An 8-bit stack (sRGB codes and their decoding table) and a 16-bit stack of the same linear
    # values give the same normals.
    values, _, mask, dirs = _corrupted_sphere(seed=3)
    table8 = default_table(np.dtype(np.uint8))
    codes = np.searchsorted(table8[:255], values).clip(0, 254).astype(np.uint8)
    stack8 = stack_from_luminance(values)
    stack8 = ImageStack(codes, stack8.chroma, [], 8, True, np.zeros(len(codes), np.int64))
    stack16 = stack_from_luminance(table8[codes])
    out8 = robust_photometric_stereo(stack8, dirs)
    out16 = robust_photometric_stereo(stack16, dirs)
    # The 16-bit copy rounds each value to 1/65534.
    assert np.percentile(_angle(out8.normals, out16.normals)[mask], 99) < 0.01
    np.testing.assert_array_equal(out8.valid, out16.valid)
