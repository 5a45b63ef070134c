"""The compiled robust photometric stereo against the NumPy steps it follows."""

import numpy as np
import pytest

from ptmcore import robust
from ptmcore.images import ImageStack, default_table
from ptmcore.robust import robust_photometric_stereo

from helpers import dome, sphere_normals, stack_from_luminance
from test_robust import _corrupted_sphere, _half_vectors, _lambertian


def _numpy_steps(stack, directions, method, specular_cone):
    return robust_photometric_stereo(stack, directions, method=method, specular_cone=specular_cone, compiled=False)


def _angle(a, b):
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


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
    # Float32 rounding only: the sums are added in another order. Measured ≤ 1e-4°.
    assert _angle(new.normals, ref.normals).max() < 1e-3
    np.testing.assert_allclose(new.albedo, ref.albedo, atol=1e-5)
    np.testing.assert_array_equal(new.valid, ref.valid)
    assert np.abs(new.samples.astype(int) - ref.samples).max() <= 1
    assert np.mean(new.samples != ref.samples) < 0.01


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
    assert _angle(new.normals, ref.normals).max() < 1e-3
    np.testing.assert_allclose(new.albedo, ref.albedo, atol=1e-5)
    np.testing.assert_array_equal(new.valid, ref.valid)
    assert np.abs(new.samples.astype(int) - ref.samples).max() <= 1
    assert np.mean(new.samples != ref.samples) < 0.01


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
        np.testing.assert_array_equal(new.valid, ref.valid)
        np.testing.assert_allclose(new.normals[new.valid], ref.normals[ref.valid], atol=1e-5)
        np.testing.assert_allclose(new.normals[~new.valid], np.broadcast_to([0.0, 0.0, 1.0], (int((~new.valid).sum()), 3)))
    assert not robust_photometric_stereo(stack, ring).valid.any()  # one plane: undetermined


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
