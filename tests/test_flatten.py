"""Tests for reconstruct.surface.flatten: known bends removed, detail kept, masked pixels inert."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from data_synthetic import SCENES
from reconstruct.surface.flatten import flatten, high_pass, remove_plane, remove_polynomial

H, W = 192, 256


def _grid() -> tuple[np.ndarray, np.ndarray]:
    row, col = np.mgrid[0:H, 0:W].astype(np.float64)
    return row, col


@pytest.fixture(scope="module")
def mask() -> np.ndarray:
    """The synthetic tablet's outline: a rounded rectangle not touching the frame."""
    return SCENES["tablet"]((H, W), seed=0).mask


@pytest.fixture(scope="module")
def pits() -> np.ndarray:
    """Wedge-sized detail: 60 Gaussian pits, sigma 2 px (FWHM 4.7 px), 0.5 deep."""
    row, col = _grid()
    rng = np.random.default_rng(1)
    out = np.zeros((H, W))
    for y0, x0 in zip(rng.uniform(10, H - 10, 60), rng.uniform(10, W - 10, 60)):
        out -= 0.5 * np.exp(-((row - y0) ** 2 + (col - x0) ** 2) / (2 * 2.0**2))
    return out


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2)))


def _bend() -> np.ndarray:
    """A tilt plus a quadratic bowl and twist, 1.3 peak-to-peak over the tablet."""
    row, col = _grid()
    x, y = (col - W / 2) / W, -(row - H / 2) / W
    return 3.0 * x**2 + 2.0 * y**2 - 1.5 * x * y + 1.0 * x - 0.5 * y + 7.0


def test_plane_is_removed_exactly(mask, pits) -> None:
    row, col = _grid()
    tilt = 0.01 * col - 0.02 * row + 3.0
    out = remove_plane(pits + tilt, mask)
    assert out.dtype == np.float32
    assert np.isnan(out[~mask]).all() and np.isfinite(out[mask]).all()
    # The fit is linear, so the tilt's contribution cancels to rounding.
    np.testing.assert_allclose(out[mask], remove_plane(pits, mask)[mask], atol=1e-5)


@pytest.mark.parametrize("method", ["poly2", "poly3"])
def test_quadratic_bend_is_recovered(mask, pits, method: str) -> None:
    bend = _bend()
    out = flatten(pits + bend, method, mask=mask)
    np.testing.assert_allclose(out[mask], flatten(pits, method, mask=mask)[mask], atol=1e-5)
    # Against the true relief the only error is the relief's own projection on the
    # polynomials: measured 0.020 against a 1.30 bend.
    error = np.abs(out - (pits - pits[mask].mean()))[mask].max()
    assert error < 0.03 * np.ptp(bend[mask])


def test_plane_leaves_a_bowl(mask, pits) -> None:
    """A plane cannot remove curvature; the quadric can (a sanity check of the orders)."""
    bend = _bend()
    # Measured: std 0.170 left against 0.070 for the pits alone.
    assert np.nanstd(remove_plane(pits + bend, mask)) > 2 * np.nanstd(pits[mask])


def test_highpass_removes_long_bend_keeps_detail(mask, pits) -> None:
    _, col = _grid()
    long_bend = 2.0 * np.sin(2 * np.pi * col / 400.0) + _bend()
    cutoff = 32.0
    inner = ndimage.binary_erosion(mask, iterations=int(cutoff))
    bend_left = high_pass(long_bend, cutoff, mask)
    detail = high_pass(pits, cutoff, mask)
    combined = flatten(pits + long_bend, "highpass", cutoff_px=cutoff, mask=mask)
    np.testing.assert_allclose(combined[mask], (bend_left + detail)[mask], atol=1e-4)
    # Measured: 0.8 % of the bend's spread left in the interior, 3.0 % over the whole
    # tablet (the one-sided average near the edge); pits keep 89 % of their depth.
    assert _rms(bend_left[inner]) < 0.015 * np.std(long_bend[mask])
    assert _rms(bend_left[mask]) < 0.05 * np.std(long_bend[mask])
    assert detail[inner].min() < 0.85 * pits[inner].min()


def test_highpass_cutoff_meaning() -> None:
    """A sinusoid at the cutoff wavelength keeps half its amplitude."""
    _, col = _grid()
    wave = np.sin(2 * np.pi * col / 20.0)
    out = high_pass(wave, 20.0)
    centre = np.s_[:, 60:-60]
    amplitude = np.sqrt(2) * np.sqrt(np.mean(out[centre] ** 2))
    assert amplitude == pytest.approx(0.5, abs=0.02)


@pytest.mark.parametrize(("method", "kw"), [("plane", {}), ("poly2", {}), ("poly3", {}),
                                            ("highpass", {"cutoff_px": 24.0})])
def test_masked_pixels_do_not_leak(mask, pits, method: str, kw: dict) -> None:
    height = pits + _bend()
    wild = height.copy()
    wild[~mask] = 1e6  # garbage outside the mask
    nan_outside = np.where(mask, height, np.nan)
    out = flatten(wild, method, mask=mask, **kw)
    ref = flatten(nan_outside, method, **kw)  # NaN marks invalid pixels without a mask
    assert out.dtype == np.float32
    assert np.isnan(out[~mask]).all()
    np.testing.assert_allclose(out[mask], ref[mask], atol=1e-5)
    assert np.array_equal(np.isnan(ref), ~mask)


def test_nan_inside_the_mask_stays_nan(mask, pits) -> None:
    height = pits + _bend()
    height[90:95, 120:125] = np.nan
    for method, kw in [("poly2", {}), ("highpass", {"cutoff_px": 16.0})]:
        out = flatten(height, method, mask=mask, **kw)
        assert np.isnan(out[90:95, 120:125]).all()
        assert np.isfinite(out[mask & np.isfinite(height)]).all()


def test_order_zero_and_trend() -> None:
    height = np.arange(12.0).reshape(3, 4)
    out, trend = remove_polynomial(height, 0, return_trend=True)
    np.testing.assert_allclose(trend, 5.5)
    np.testing.assert_allclose(out, height - 5.5)


def test_bad_arguments(mask) -> None:
    height = np.zeros((H, W))
    with pytest.raises(ValueError, match="method"):
        flatten(height, "spline")
    with pytest.raises(ValueError, match="cutoff_px"):
        flatten(height, "highpass")
    with pytest.raises(ValueError, match="cutoff_px"):
        high_pass(height, 0)
    with pytest.raises(ValueError, match="order"):
        remove_polynomial(height, -1)
    with pytest.raises(ValueError, match="valid pixels"):
        remove_polynomial(np.full((4, 4), np.nan), 2)
    with pytest.raises(ValueError, match="mask shape"):
        remove_plane(height, mask[:10])
    with pytest.raises(ValueError, match="2-D"):
        remove_plane(np.zeros(5))
    with pytest.raises(ValueError, match="bad options"):
        flatten(height, "plane", cutoff_px=3)
