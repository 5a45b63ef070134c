"""The DCT integrator's two per-pixel passes, compiled: the Poisson equation's right-hand side
straight from a normal map, and the division of its spectrum by the Laplacian's eigenvalues.

In NumPy, normals → gradients (:func:`reconstruct.surface.integrate.gradients_from_normals`)
→ masked gradients → divergence is a chain of a dozen whole-image passes, each with a fresh
temporary: at 24 megapixels 1.6 s of the 1.9 s the integration took, most of it the system
mapping fresh memory, while the two DCTs took 0.25 s. :func:`divergence_from_normals` makes the
divergence in one pass over the normals, a band of rows per thread, writing only its result;
:func:`divide_by_eigenvalues` divides the spectrum in place. Both do the NumPy code's float32
arithmetic in the same order, so the heights are the same to the last bit (tested).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ptmcore.bands import run_bands
from ptmcore.resources import cpu_count
from reconstruct.surface.fourier import checked_normals

__all__ = ["divergence_from_normals", "divide_by_eigenvalues"]

# Rows per band of work: a thread's unit.
_BAND_ROWS = 256


# error_model="numpy": 0/0 is NaN (then a zero gradient), as in NumPy, not an exception.
@numba.njit(nogil=True, cache=True, error_model="numpy")
def _gradient_row(normals, mask, r, tan_max, g_row, g_col):  # pragma: no cover - compiled
    """Row ``r``'s gradients (∂z/∂row = −q, ∂z/∂col = p; 0 outside the mask) into ``g_row``,
    ``g_col``, as gradients_from_normals and poisson_dct's _prepare make them; return the
    number of non-finite normals."""
    bad = 0
    for c in range(normals.shape[1]):
        nx = normals[r, c, 0]
        ny = normals[r, c, 1]
        nz = normals[r, c, 2]
        finite = math.isfinite(nx) and math.isfinite(ny) and math.isfinite(nz)
        if not finite:
            bad += 1
        denom = np.float32(np.hypot(nx, ny)) / tan_max
        if math.isnan(denom) or math.isnan(nz):
            denom = np.float32(np.nan)
        elif nz > denom:
            denom = nz
        p = -nx / denom
        q = -ny / denom
        if not math.isfinite(p):
            p = np.float32(0.0)
        if not math.isfinite(q):
            q = np.float32(0.0)
        # Without a mask, the pixels whose normal is not finite are outside the object (as
        # integrate makes its mask); a normal of (x, y, −inf) would otherwise keep a slope.
        if mask[r, c] if mask is not None else finite:
            g_row[c] = -q
            g_col[c] = p
        else:
            g_row[c] = np.float32(0.0)
            g_col[c] = np.float32(0.0)
    return bad


@numba.njit(nogil=True, cache=True)
def _divergence_rows(normals, mask, tan_max, r0, r1, out):  # pragma: no cover - compiled
    """Rows ``r0:r1`` of f = Dᵀg (poisson_dct's right-hand side) into ``out``; return the
    number of non-finite normals in those rows."""
    h, w = normals.shape[0], normals.shape[1]
    half = np.float32(0.5)
    prev_row = np.zeros(w, np.float32)
    cur_row = np.empty(w, np.float32)
    next_row = np.empty(w, np.float32)
    cur_col = np.empty(w, np.float32)
    next_col = np.empty(w, np.float32)
    if r0 > 0:
        _gradient_row(normals, mask, r0 - 1, tan_max, prev_row, next_col)
    bad = _gradient_row(normals, mask, r0, tan_max, cur_row, cur_col)
    for r in range(r0, r1):
        if r + 1 < h:
            n_bad = _gradient_row(normals, mask, r + 1, tan_max, next_row, next_col)
            if r + 1 < r1:
                bad += n_bad
        # The order of poisson_dct's NumPy updates: columns' −, columns' +, rows' −, rows' +.
        for c in range(w):
            f = np.float32(0.0)
            if c < w - 1:
                f -= (cur_col[c] + cur_col[c + 1]) * half
            if c > 0:
                f += (cur_col[c - 1] + cur_col[c]) * half
            if r < h - 1:
                f -= (cur_row[c] + next_row[c]) * half
            if r > 0:
                f += (prev_row[c] + cur_row[c]) * half
            out[r, c] = f
        prev_row, cur_row, next_row = cur_row, next_row, prev_row
        cur_col, next_col = next_col, cur_col
    return bad


@numba.njit(nogil=True, cache=True)
def _divide_rows(spectrum, eig_row, eig_col, r0, r1):  # pragma: no cover - compiled
    for i in range(r0, r1):
        for j in range(spectrum.shape[1]):
            d = eig_row[i] + eig_col[j]
            spectrum[i, j] = spectrum[i, j] / d if d != 0 else np.float32(0.0)


def _threads(workers: int | None) -> int:
    """scipy.fft's ``workers`` as a thread count: −1 (or any negative) all CPUs, None one."""
    if workers is None:
        return 1
    return cpu_count() if workers < 0 else max(1, workers)


def divergence_from_normals(
    normals: np.ndarray, mask: np.ndarray | None, *, max_slope_deg: float = 85.0, workers: int | None = -1,
) -> tuple[np.ndarray, int]:
    """The right-hand side ``f = Dᵀg`` of the DCT integrator's normal equations, from normals.

    The same as :func:`reconstruct.surface.integrate.gradients_from_normals` followed by the
    masking and divergence of :func:`reconstruct.surface.fourier.poisson_dct`, in one pass.

    Parameters
    ----------
    normals : ndarray (H, W, 3), float32
        Normals (x right, y up, z towards the camera); non-finite ones give zero gradients.
    mask : ndarray (H, W) of bool, or None
        Gradients outside it are 0; without one, those of normals that are not finite.
    max_slope_deg : float
        Slope limit, as in ``gradients_from_normals``.
    workers : int or None
        Threads (as scipy.fft counts them: −1 all CPUs).

    Returns
    -------
    f : ndarray (H, W), float32
    nonfinite : int
        Normals with a NaN or infinite component.
    """
    normals = np.ascontiguousarray(checked_normals(normals, max_slope_deg))
    h, w = normals.shape[:2]
    if h == 0 or w == 0:
        raise ValueError(f"normals must be a non-empty (H, W, 3) array, not {normals.shape}")
    if mask is not None:
        mask = np.ascontiguousarray(mask, dtype=bool)
        if mask.shape != (h, w):
            raise ValueError(f"mask has shape {mask.shape}, the normals {(h, w)}")
    tan_max = np.float32(math.tan(math.radians(max_slope_deg)))
    out = np.empty((h, w), np.float32)
    counts: list[int] = []
    run_bands(h, _BAND_ROWS, lambda r0, r1: counts.append(_divergence_rows(normals, mask, tan_max, r0, r1, out)),
              threads=_threads(workers))
    return out, int(sum(counts))


def divide_by_eigenvalues(spectrum: np.ndarray, eig_row: np.ndarray, eig_col: np.ndarray, *,
                          workers: int | None = -1) -> None:
    """``spectrum[i, j] /= eig_row[i] + eig_col[j]`` in place (float32, in bands of rows); 0
    where the sum is 0 (the constant's coefficient, which the Neumann problem leaves free)."""
    eig_row = np.ascontiguousarray(eig_row, np.float32)
    eig_col = np.ascontiguousarray(eig_col, np.float32)
    run_bands(spectrum.shape[0], _BAND_ROWS, lambda r0, r1: _divide_rows(spectrum, eig_row, eig_col, r0, r1),
              threads=_threads(workers))
