"""Tests for the whole-rectangle integrators and the dispatcher: analytic surfaces, signs,
units, masks, discretisation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reconstruct.surface import (
    frankot_chellappa,
    gradients_from_normals,
    integrate,
    poisson_dct,
)

H, W = 96, 128


def _xy(h: int = H, w: int = W) -> tuple[np.ndarray, np.ndarray]:
    """Frame coordinates of the pixel centres in pixels: x right, y up (y = −row)."""
    row, col = np.mgrid[0:h, 0:w].astype(np.float64)
    return col, -row


def _normals(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Unit normals ∝ (−p, −q, 1) of a surface with gradients p = ∂z/∂x, q = ∂z/∂y."""
    n = np.stack([-p, -q, np.ones_like(p)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def _relative_rmse(z: np.ndarray, truth: np.ndarray) -> float:
    """RMSE as a fraction of the height range, both sides made mean-zero (the free constant)."""
    inside = np.isfinite(truth)
    t = truth[inside] - truth[inside].mean()
    e = z[inside].astype(np.float64) - z[inside].mean(dtype=np.float64)
    return float(np.sqrt(np.mean((e - t) ** 2)) / np.ptp(t))


def _gaussian_bump() -> tuple[np.ndarray, np.ndarray]:
    """A bump whose slopes vanish at the border: the natural case for Neumann integration."""
    x, y = _xy()
    x0, y0, s, a = 60.0, -50.0, 12.0, 10.0
    z = a * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * s * s))
    return z, _normals(-(x - x0) / s**2 * z, -(y - y0) / s**2 * z)


def _periodic_surface() -> tuple[np.ndarray, np.ndarray]:
    """Two and three periods across the image: periodic, with non-zero slopes at the border."""
    x, y = _xy()
    a, kx, ky = 3.0, 2 * np.pi * 2 / W, 2 * np.pi * 3 / H
    z = a * np.sin(kx * x) * np.cos(ky * y)
    p = a * kx * np.cos(kx * x) * np.cos(ky * y)
    q = -a * ky * np.sin(kx * x) * np.sin(ky * y)
    return z, _normals(p, q)


def _sphere_cap() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A spherical cap (radius 60 px, rim radius 40 px, rim slope 42°) with its mask."""
    x, y = _xy()
    radius, rim, cx, cy = 60.0, 40.0, 64.0, -48.0
    r2 = (x - cx) ** 2 + (y - cy) ** 2
    mask = r2 < rim**2
    s = np.sqrt(np.clip(radius**2 - r2, 1e-9, None))
    z = np.where(mask, s - math.sqrt(radius**2 - rim**2), np.nan)
    n = _normals(np.where(mask, -(x - cx) / s, 0), np.where(mask, -(y - cy) / s, 0))
    n[~mask] = np.nan
    return z, n, mask


# ---------------------------------------------------------------- gradients_from_normals


def test_gradients_of_a_plane_follow_the_frame():
    x, y = _xy(5, 7)
    n = _normals(np.full(x.shape, 0.25), np.full(x.shape, -0.5))
    p, q = gradients_from_normals(n)
    assert p.dtype == q.dtype == np.float32
    np.testing.assert_allclose(p, 0.25, atol=1e-6)
    np.testing.assert_allclose(q, -0.5, atol=1e-6)


def test_gradients_are_clamped_and_finite():
    n = np.array(
        [[[1, 0, 0], [0, -1, 0], [0.6, 0.8, -0.1], [0, 0, -1], [np.nan, np.nan, np.nan]]],
        dtype=np.float32,
    )
    p, q = gradients_from_normals(n, max_slope_deg=85.0)
    assert np.isfinite(p).all() and np.isfinite(q).all()
    tan85 = math.tan(math.radians(85.0))
    slope = np.hypot(p, q)
    np.testing.assert_allclose(slope[0, :3], tan85, rtol=1e-5)
    assert p[0, 0] < 0 and q[0, 1] > 0  # azimuth kept: the surface falls towards the normal
    np.testing.assert_allclose(np.arctan2(-q[0, 2], -p[0, 2]), math.atan2(0.8, 0.6), rtol=1e-5)
    assert p[0, 3] == q[0, 3] == 0.0  # straight away from the camera: no direction, flat
    assert p[0, 4] == q[0, 4] == 0.0  # NaN (outside a mask)
    p45, _ = gradients_from_normals(n[:, :1], max_slope_deg=45.0)
    np.testing.assert_allclose(p45, -1.0, rtol=1e-6)


def test_gradients_reject_bad_input():
    with pytest.raises(ValueError):
        gradients_from_normals(np.zeros((4, 4, 2)))
    with pytest.raises(ValueError):
        gradients_from_normals(np.zeros((4, 4, 3)), max_slope_deg=90.0)


# ---------------------------------------------------------------- accuracy on analytic surfaces


@pytest.mark.parametrize(
    ("method", "tolerance"),
    # DCT: trapezoid-rule discretisation, second order (measured 1.2e-4 of the range).
    # FC: spectral derivative, exact up to float32 for a smooth bump (measured 1.5e-6).
    [("dct", 1e-3), ("fc", 2e-5)],
)
def test_gaussian_bump_is_recovered(method, tolerance):
    z, n = _gaussian_bump()
    height = integrate(n, method)
    assert height.dtype == np.float32 and height.shape == (H, W)
    assert _relative_rmse(height, z) < tolerance
    assert abs(float(height.mean(dtype=np.float64))) < 1e-4


def test_periodic_surface_is_exact_with_periodic_fc():
    z, n = _periodic_surface()
    p, q = gradients_from_normals(n)
    # Band-limited and periodic: the torus assumption holds, only float32 rounding remains.
    assert _relative_rmse(frankot_chellappa(p, q, boundary="periodic"), z) < 1e-5
    # The border-agnostic methods see slopes at the border; still within 0.5% (measured 7e-4).
    assert _relative_rmse(frankot_chellappa(p, q), z) < 5e-3
    assert _relative_rmse(poisson_dct(p, q), z) < 5e-3


@pytest.mark.parametrize("method", ["dct", "fc"])
def test_masked_sphere_cap(method):
    z, n, mask = _sphere_cap()
    # The cap meets the flat surround at one height, so the zero-gradient surround that the
    # masked integration assumes is exact; errors come from the slope kink at the rim
    # (measured 1.8e-3 of the range).
    height = integrate(n, method, mask=mask)
    assert np.isnan(height[~mask]).all()
    assert np.isfinite(height[mask]).all()
    assert abs(float(height[mask].mean(dtype=np.float64))) < 1e-4
    assert _relative_rmse(height, z) < 1e-2


def test_nan_normals_without_mask_become_nan_heights():
    z, n, mask = _sphere_cap()
    height = integrate(n, "dct")
    np.testing.assert_array_equal(np.isnan(height), ~mask)


# ---------------------------------------------------------------- conventions and units


@pytest.mark.parametrize("method", ["dct", "fc"])
def test_plane_rising_towards_row_0_is_highest_at_row_0(method):
    # z = 0.3·y with y up: the surface rises towards the top of the image (row 0).
    x, y = _xy(40, 30)
    n = _normals(np.zeros_like(x), np.full_like(y, 0.3))
    height = integrate(n, method)
    assert (height[0] > height[-1]).all()
    assert (np.diff(height.mean(axis=1)) < 0).all()
    # DCT reproduces a plane exactly (measured 5e-8 of the range). FC's mirrored plane is a
    # triangle wave whose kinks ring a little (measured 9e-4 RMSE, 3e-3 at worst).
    tolerance = 1e-6 if method == "dct" else 3e-3
    assert _relative_rmse(height, 0.3 * y) < tolerance


@pytest.mark.parametrize("method", ["dct", "fc"])
def test_pixel_size_scales_heights(method):
    _, n = _gaussian_bump()
    base = integrate(n, method)
    scaled = integrate(n, method, pixel_size=0.05)
    np.testing.assert_allclose(scaled, 0.05 * base, atol=1e-5 * np.ptp(base))


@pytest.mark.parametrize("method", ["dct", "fc"])
def test_mask_gives_nan_outside_and_mean_zero_inside(method):
    _, n = _gaussian_bump()
    mask = np.zeros((H, W), dtype=bool)
    mask[10:80, 20:110] = True
    height = integrate(n, method, mask=mask)
    assert np.isnan(height[~mask]).all() and np.isfinite(height[mask]).all()
    assert abs(float(height[mask].mean(dtype=np.float64))) < 1e-4


def test_bad_arguments_raise_value_error():
    _, n = _gaussian_bump()
    with pytest.raises(ValueError, match="unknown integration method"):
        integrate(n, "poisson")
    p, q = gradients_from_normals(n)
    with pytest.raises(ValueError):
        frankot_chellappa(p, q, boundary="zero")
    with pytest.raises(ValueError):
        poisson_dct(p, q, pixel_size=0.0)
    with pytest.raises(ValueError):
        poisson_dct(p, q[:-1])
    with pytest.raises(ValueError):
        poisson_dct(p, q, mask=np.ones((3, 3), dtype=bool))


# ---------------------------------------------------------------- the discretisations themselves


def test_poisson_dct_is_the_least_squares_solution():
    # Arbitrary (non-integrable) gradients: the DCT solution must equal the dense
    # least-squares fit of forward differences to the trapezoid-averaged gradients.
    rng = np.random.default_rng(1)
    h, w = 7, 9
    p = rng.normal(size=(h, w)).astype(np.float32)
    q = rng.normal(size=(h, w)).astype(np.float32)
    g_row, g_col = -q.astype(np.float64), p.astype(np.float64)
    idx = np.arange(h * w).reshape(h, w)
    rows, rhs = [], []
    for a, b, g in [
        (idx[:, :-1], idx[:, 1:], (g_col[:, :-1] + g_col[:, 1:]) / 2),
        (idx[:-1, :], idx[1:, :], (g_row[:-1, :] + g_row[1:, :]) / 2),
    ]:
        block = np.zeros((a.size, h * w))
        block[np.arange(a.size), b.ravel()] = 1.0
        block[np.arange(a.size), a.ravel()] = -1.0
        rows.append(block)
        rhs.append(g.ravel())
    solution, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    solution = solution.reshape(h, w) - solution.mean()
    np.testing.assert_allclose(poisson_dct(p, q), solution, atol=1e-5)


def test_mirror_fc_equals_fc_on_the_explicitly_mirrored_field():
    rng = np.random.default_rng(2)
    h, w = 12, 15
    p = rng.normal(size=(h, w)).astype(np.float32)
    q = rng.normal(size=(h, w)).astype(np.float32)
    g_row, g_col = -q.astype(np.float64), p.astype(np.float64)
    # Even extension of z: ∂z/∂col is odd across the left/right borders and even across
    # the top/bottom ones; ∂z/∂row the other way round.
    col_ext = np.block([[g_col, -g_col[:, ::-1]], [g_col[::-1], -g_col[::-1, ::-1]]])
    row_ext = np.block([[g_row, g_row[:, ::-1]], [-g_row[::-1], -g_row[::-1, ::-1]]])
    w_row = 2 * np.pi * np.fft.fftfreq(2 * h)[:, None]
    w_col = 2 * np.pi * np.fft.fftfreq(2 * w)[None, :]
    denom = w_row**2 + w_col**2
    denom[0, 0] = 1.0
    spec = -1j * (w_col * np.fft.fft2(col_ext) + w_row * np.fft.fft2(row_ext)) / denom
    spec[0, 0] = 0.0
    reference = np.fft.ifft2(spec).real[:h, :w]
    reference -= reference.mean()
    np.testing.assert_allclose(frankot_chellappa(p, q), reference, atol=1e-5)
