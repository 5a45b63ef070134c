"""Pixels whose samples carry no direction: the same result, flagged, in the compiled kernel and
the NumPy steps, whatever the CPU's rounding (ptmcore.normals.FLAT)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ptmcore.normals import FLAT, normals_from_ptm, ptm_maximum
from ptmcore.robustptm import debiased_normals, robust_ptm

from helpers import dome, stack_from_luminance
from test_robust import _lambertian

_UP = np.float32([0.0, 0.0, 1.0])


def _capture(n, seed, level, kind):
    """A 6×8 capture of a tilted Lambertian plane under ``n`` lights, with a 2×3 box of pixels
    whose samples carry no direction: all clipped, all black, or ``level`` under every light."""
    dirs = dome(n, seed=seed)
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    values = _lambertian(np.broadcast_to(normal, (6, 8, 3)), 0.7, dirs)
    box = (slice(None), slice(2, 4), slice(3, 6))
    values[box] = {"clipped": 1.0, "black": 0.0, "constant": level}[kind]
    return stack_from_luminance(values, values >= 1.0), dirs, box[1:]


@settings(max_examples=12, deadline=None)
@given(n=st.integers(6, 40), seed=st.integers(0, 1000), level=st.floats(0.001, 0.999),
       kind=st.sampled_from(["clipped", "black", "constant"]), method=st.sampled_from(["irls", "trimmed"]))
def test_no_direction_no_normal_in_both_paths(n, seed, level, kind, method):
    stack, dirs, box = _capture(n, seed, level, kind)
    for compiled in (True, False):
        fit = robust_ptm(stack, dirs, method=method, compiled=compiled)
        assert not fit.valid[box].any()
        assert (fit.normals[box] == _UP).all()
        outside = np.ones(fit.valid.shape, bool)
        outside[box] = False
        assert fit.valid[outside].all()
        assert np.isfinite(fit.ptm.coefficients).all()  # the PTM is kept, for relighting
        # The plain fit stands in there: flat, so its plain maximum gives no normal either.
        valid = np.ones(fit.valid.shape, bool)
        assert (normals_from_ptm(fit.ptm.coefficients, valid=valid)[box] == _UP).all()
        assert not valid[box].any()


_level = st.floats(1e-6, 1e6)


@settings(max_examples=40, deadline=None)
@given(level=_level, sign=st.sampled_from([1.0, -1.0]), shape=st.lists(st.floats(-1.0, 1.0), min_size=5, max_size=5),
       relative=st.floats(0.0, 0.99))
def test_a_flat_ptm_at_any_scale_gives_no_normal(level, sign, shape, relative):
    # |a0| + … + |a4| at most FLAT × |a5|: rounding's, whatever their signs (the kernel and
    # the NumPy steps had read opposite normals from such noise).
    a = np.array([*(np.array(shape) * relative * FLAT * level / 5), sign * level])
    q = np.array([-0.3, -0.3, 0.0, 0.0, 0.0, 0.9])
    valid = np.empty((1,), bool)
    normal = debiased_normals(a[None], q, valid=valid)
    assert not valid[0]
    assert (normal[0] == _UP).all()
    # The plain maximum too: at (0, 0), where rounding had put it anywhere on the rim.
    valid = np.empty((1, 1), bool)
    assert (normals_from_ptm(a[None, None], valid=valid) == _UP).all() and not valid.any()
    lu, lv, interior = ptm_maximum(a)
    assert lu == 0 and lv == 0 and not interior


@settings(max_examples=40, deadline=None)
@given(level=_level, tilt=st.floats(-0.5, 0.5), scale=st.floats(1e-3, 1e3))
def test_the_rule_is_relative_to_the_level(level, tilt, scale):
    # A Lambertian pixel's PTM, ρ (nx lu + ny lv + nz q): read, and the same at any brightness.
    q = np.array([-0.3, -0.3, 0.0, 0.0, 0.0, 0.9])
    n = np.array([tilt, 0.2, 1.0])
    n /= np.linalg.norm(n)
    a = level * (n[2] * q + np.array([0.0, 0.0, 0.0, n[0], n[1], 0.0]))
    valid = np.empty((2,), bool)
    normals = debiased_normals(np.stack([a, scale * a]), q, valid=valid)
    assert valid.all()
    np.testing.assert_allclose(normals, np.float32([n, n]), atol=1e-5)


def test_an_all_zero_ptm_gives_no_normal():
    valid = np.ones((2, 3), bool)
    normals = debiased_normals(np.zeros((2, 3, 6), np.float32), np.zeros(6), valid=valid)
    assert not valid.any()
    assert (normals == _UP).all()
    valid[:] = True
    normals = normals_from_ptm(np.zeros((2, 3, 6), np.float32), valid=valid)  # was (1, 0, 0)
    assert not valid.any()
    assert (normals == _UP).all()


@pytest.mark.parametrize("compiled", [True, False])
def test_a_dim_shaded_pixel_is_read(compiled):
    # One 16-bit code of variation in a pixel's shading is 1.5e-5 of full scale, and real
    # shading varies by far more: a dim but shaded pixel keeps its normal.
    stack, dirs, box = _capture(24, 3, 0.5, "constant")
    values = stack.luminance.astype(np.float64) / 65534
    values[:, 2:4, 3:6] = 0.02 * np.maximum(dirs[:, 2], 0.0)[:, None, None]  # dim, facing the camera
    stack = stack_from_luminance(values)
    fit = robust_ptm(stack, dirs, compiled=compiled)
    assert fit.valid.all()
    assert np.degrees(np.arccos(np.clip(fit.normals[box][..., 2], -1, 1))).max() < 1.0
