"""The compiled DCT passes (reconstruct.surface.divergence) against the NumPy steps they replace."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruct.surface.divergence import divergence_from_normals
from reconstruct.surface.fourier import poisson_dct
from reconstruct.surface.integrate import gradients_from_normals, integrate


def _normals(shape, seed=0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=shape + (3,)).astype(np.float32)
    n[..., 2] = np.abs(n[..., 2]) * 3
    n[rng.random(shape) < 0.05] = np.nan  # outside the object
    n[rng.random(shape) < 0.03, 2] = -0.2  # facing away: clamped to the slope limit
    n[rng.random(shape) < 0.02, :2] = 0.0
    n[rng.random(shape) < 0.01] = (0.0, 0.0, -1.0)  # 0/0 gradients: flat
    n[rng.random(shape) < 0.01, 0] = np.inf
    return n


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (6, 1), (2, 2), (37, 53), (600, 131)])
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("workers", [1, -1])
def test_heights_are_the_numpy_steps_to_the_bit(shape, masked, workers):
    normals = _normals(shape, seed=shape[0] * shape[1])
    mask = np.random.default_rng(3).random(shape) < 0.8 if masked else None
    heights = integrate(normals, "dct", mask=mask, pixel_size=0.05, max_slope_deg=80.0, workers=workers)
    finite = np.isfinite(normals).all(axis=-1)
    reference_mask = mask if masked else (None if finite.all() else finite)
    p, q = gradients_from_normals(normals, max_slope_deg=80.0)
    expected = poisson_dct(p, q, mask=reference_mask, pixel_size=0.05, workers=workers)
    np.testing.assert_array_equal(heights, expected)


def test_backward_infinite_normals_and_loose_masks_as_the_numpy_steps():
    normals = _normals((40, 30), seed=4)
    normals[3, 4] = (0.5, 0.2, -np.inf)  # finite slope by np.maximum, outside the object
    normals[7, 8] = (0.0, 0.3, np.inf)
    finite = np.isfinite(normals).all(axis=-1)
    p, q = gradients_from_normals(normals)
    np.testing.assert_array_equal(integrate(normals, "dct"), poisson_dct(p, q, mask=finite))
    mask = np.random.default_rng(1).random((40, 30)) < 0.7
    for loose in (mask.astype(np.uint8), mask.astype(int), mask.tolist()):  # as poisson_dct takes them
        np.testing.assert_array_equal(integrate(normals, "dct", mask=loose), poisson_dct(p, q, mask=mask))
    for bad in (0.0, -2.0, float("nan")):
        with pytest.raises(ValueError, match="pixel_size"):
            integrate(normals, "dct", pixel_size=bad)


def test_divergence_counts_nonfinite_normals_across_bands():
    normals = _normals((700, 40), seed=9)  # several bands of rows
    _, nonfinite = divergence_from_normals(normals, None, workers=2)
    assert nonfinite == int((~np.isfinite(normals).all(axis=-1)).sum()) > 0


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        divergence_from_normals(np.zeros((4, 4, 2), np.float32), None)
    with pytest.raises(ValueError, match="non-empty"):
        divergence_from_normals(np.zeros((0, 4, 3), np.float32), None)
    with pytest.raises(ValueError, match="mask has shape"):
        divergence_from_normals(np.zeros((4, 4, 3), np.float32), np.ones((3, 4), bool))
    with pytest.raises(ValueError, match="max_slope_deg"):
        divergence_from_normals(np.zeros((4, 4, 3), np.float32), None, max_slope_deg=90.0)
