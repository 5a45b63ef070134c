"""Integration of a gradient field over the whole rectangle with fast transforms.

Frame (see ``docs/CONVENTIONS.md``): x to the right, y **up**, z towards the camera. A
surface z(x, y) has the normal n ∝ (−p, −q, 1) with p = ∂z/∂x and q = ∂z/∂y. Rows grow
downwards while y grows upwards, so along the array axes the gradient is
(∂z/∂row, ∂z/∂col) = (−q, p).

Two global integrators are provided, both O(N log N) with real-to-real or real-to-complex
transforms of scipy.fft that stay in float32 for float32 input:

* :func:`poisson_dct` — least squares with the natural (Neumann) boundary, solved exactly
  with the DCT (Simchony, Chellappa & Shao 1990). The default: the exact least-squares
  solution of the discrete problem (second-order accurate, exact for planes), no ringing
  at creases or steps, and no assumption about what lies beyond the image border.
* :func:`frankot_chellappa` — projection of the gradient field onto integrable Fourier
  fields (Frankot & Chellappa 1988), either on the mirror-extended field (default) or
  periodic. Spectrally accurate on smooth surfaces, but it rings near creases, steps and
  the border slopes of tilted surfaces.

Both assume a gradient field on the whole rectangle: masked pixels are given a zero gradient
(a flat surface) before integration. See the functions' notes for the consequences, and
:mod:`reconstruct.surface.masked` for integration on the mask alone.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

__all__ = ["checked_normals", "frankot_chellappa", "poisson_dct", "solve_neumann"]


def checked_normals(normals, max_slope_deg: float, dtype: type = np.float32) -> np.ndarray:
    """``normals`` as an ``(H, W, 3)`` array of ``dtype``, with ``max_slope_deg`` in (0, 90):
    the integrators' common check (here, beside them, without numba's import).

    Raises
    ------
    ValueError
        If the shape or the slope limit is not so.
    """
    normals = np.asarray(normals, dtype=dtype)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3), not {normals.shape}")
    if not 0.0 < max_slope_deg < 90.0:
        raise ValueError(f"max_slope_deg must be in (0, 90), not {max_slope_deg}")
    return normals


def _prepare(
    p: np.ndarray, q: np.ndarray, mask: np.ndarray | None, pixel_size: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validate the inputs; return float32 (∂z/∂row, ∂z/∂col) with zeros outside the mask."""
    p = np.asarray(p)
    q = np.asarray(q)
    if p.ndim != 2 or p.shape != q.shape or p.size == 0:
        raise ValueError(
            f"p and q must be non-empty 2-D arrays of one shape, not {p.shape} and {q.shape}"
        )
    if not (math.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number, not {pixel_size}")
    keep = np.isfinite(p) & np.isfinite(q)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != p.shape:
            raise ValueError(f"mask has shape {mask.shape}, the gradients {p.shape}")
        keep &= mask
    g_row = np.where(keep, -q, 0).astype(np.float32, copy=False)
    g_col = np.where(keep, p, 0).astype(np.float32, copy=False)
    return g_row, g_col, mask


def _finish(height: np.ndarray, mask: np.ndarray | None, pixel_size: float) -> np.ndarray:
    """Scale to the pixel unit, blank outside the mask and remove the free constant."""
    if pixel_size != 1.0:
        height *= np.float32(pixel_size)
    if mask is not None:
        height[~mask] = np.nan
        inside = height[mask]
        offset = inside.mean(dtype=np.float64) if inside.size else 0.0
    else:
        # float64 accumulation: a float32 sum over 24 Mpixel loses ~3 digits.
        offset = height.mean(dtype=np.float64)
    height -= np.float32(offset)
    return height


def _dct_eigenvalues(n: int) -> np.ndarray:
    """Eigenvalues 2 − 2cos(πk/n) of the 1-D Neumann Laplacian, in float64."""
    # The sin² form avoids the cancellation of 2 − 2cos at low frequencies.
    return 4.0 * np.sin(np.pi * np.arange(n) / (2.0 * n)) ** 2


def poisson_dct(
    p: np.ndarray,
    q: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    pixel_size: float = 1.0,
    workers: int | None = -1,
) -> np.ndarray:
    """Least-squares integration of a gradient field with the DCT (Simchony et al. 1990).

    Finds the height z minimising Σ (z[i, j+1] − z[i, j] − ḡx)² + Σ (z[i+1, j] − z[i, j] −
    ḡrow)² over all neighbouring pixel pairs inside the image, where ḡ is the mean of the
    two pixels' gradients (trapezoid rule, second-order accurate). Its normal equations are
    the discrete Poisson equation with the natural Neumann boundary, whose operator the
    DCT-II diagonalises, so the solution is exact up to rounding: divergence → DCT-II →
    division by the Laplacian's eigenvalues → inverse DCT-II.

    Parameters
    ----------
    p, q : numpy.ndarray
        ``(H, W)`` gradients ∂z/∂x and ∂z/∂y (y up) in height per horizontal unit, e.g.
        from :func:`gradients_from_normals`. Non-finite values count as 0.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool, True for pixels of the object.
    pixel_size : float
        Size of a pixel; the heights come out in its unit (mm when it is in mm/pixel, pixels
        when it is 1).
    workers : int or None
        Threads for scipy.fft (−1: all CPUs).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 heights with mean 0 over the mask (over the image without one),
        NaN outside the mask.

    Notes
    -----
    Masking is crude for now: gradients outside the mask are set to 0 and the whole
    rectangle is integrated, so the object is treated as lying on a flat plane that
    continues outside the mask. An object whose rim is not at one common height comes out
    bent towards that plane near the rim. Proper integration on the masked domain is a
    separate issue.

    Peak memory is about six float32 images (about 0.6 GB for 24 Mpixel).
    """
    g_row, g_col, mask = _prepare(p, q, mask, pixel_size)
    h, w = g_row.shape
    # f = Dᵀg, the right-hand side of the normal equations DᵀD z = Dᵀg; D takes forward
    # differences, so f is minus the divergence with zero flux through the border.
    # (reconstruct.surface.divergence makes the same f from normals in one compiled pass.)
    f = np.zeros((h, w), dtype=np.float32)
    edge = g_col[:, :-1] + g_col[:, 1:]
    edge *= np.float32(0.5)
    f[:, :-1] -= edge
    f[:, 1:] += edge
    del edge, g_col
    edge = g_row[:-1, :] + g_row[1:, :]
    edge *= np.float32(0.5)
    f[:-1, :] -= edge
    f[1:, :] += edge
    del edge, g_row
    return solve_neumann(f, mask, pixel_size, workers=workers)


def solve_neumann(f: np.ndarray, mask: np.ndarray | None, pixel_size: float = 1.0, *,
                  workers: int | None = -1) -> np.ndarray:
    """Heights z with DᵀD z = f (the Neumann Poisson problem of :func:`poisson_dct`), by the
    DCT; ``f`` (float32) is overwritten. Scaled by ``pixel_size``, NaN outside ``mask``, mean 0
    over it (over the image without one)."""
    from reconstruct.surface.divergence import divide_by_eigenvalues

    if not (math.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number, not {pixel_size}")
    h, w = f.shape
    spectrum = scipy.fft.dctn(f, type=2, norm="ortho", workers=workers, overwrite_x=True)
    del f
    eig_row = _dct_eigenvalues(h).astype(np.float32)
    eig_col = _dct_eigenvalues(w).astype(np.float32)
    divide_by_eigenvalues(spectrum, eig_row, eig_col, workers=workers)  # the constant's (0) becomes 0
    height = scipy.fft.idctn(spectrum, type=2, norm="ortho", workers=workers, overwrite_x=True)
    return _finish(height.astype(np.float32, copy=False), mask, pixel_size)


def frankot_chellappa(
    p: np.ndarray,
    q: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    pixel_size: float = 1.0,
    boundary: str = "mirror",
    workers: int | None = -1,
) -> np.ndarray:
    """Frankot–Chellappa integration: projection onto integrable Fourier fields.

    The height's Fourier coefficients are Z = −i(ωx·Gx + ωy·Gy) / (ωx² + ωy²), the least
    squares fit of spectral derivatives to the given gradients (Frankot & Chellappa 1988).

    Parameters
    ----------
    p, q : numpy.ndarray
        ``(H, W)`` gradients ∂z/∂x and ∂z/∂y (y up) in height per horizontal unit.
        Non-finite values count as 0.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool, True for pixels of the object.
    pixel_size : float
        Size of a pixel; the heights come out in its unit.
    boundary : {"mirror", "periodic"}
        ``"mirror"`` (default) applies the usual remedy for the periodic-boundary artefacts:
        the height is extended evenly across the image borders (so p is extended oddly
        across the left/right borders, evenly across top/bottom, and q the other way) and
        the 2H × 2W field is integrated. The extended field is never built: its Fourier
        transform reduces exactly to DCT-II/DST-II transforms of the H × W gradients, which
        saves 4× memory and time. ``"periodic"`` is the textbook method on the H × W
        torus, exact for periodic band-limited surfaces but wrong at the borders otherwise.
    workers : int or None
        Threads for scipy.fft (−1: all CPUs).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 heights with mean 0 over the mask (over the image without one),
        NaN outside the mask.

    Raises
    ------
    ValueError
        For an unknown `boundary` or mismatched inputs.

    Notes
    -----
    Masked pixels get a zero gradient before integration, as in :func:`poisson_dct` (same
    limitation). The spectral derivative assumes a band-limited surface; sharp steps ring.
    """
    if boundary not in ("mirror", "periodic"):
        raise ValueError(f"boundary must be 'mirror' or 'periodic', not {boundary!r}")
    g_row, g_col, mask = _prepare(p, q, mask, pixel_size)
    if boundary == "periodic":
        height = _fc_periodic(g_row, g_col, workers)
    else:
        height = _fc_mirror(g_row, g_col, workers)
    return _finish(height.astype(np.float32, copy=False), mask, pixel_size)


def _fc_periodic(g_row: np.ndarray, g_col: np.ndarray, workers: int | None) -> np.ndarray:
    """Frankot–Chellappa on the torus with rfft2."""
    h, w = g_row.shape
    w_row = 2.0 * np.pi * scipy.fft.fftfreq(h)
    w_col = 2.0 * np.pi * scipy.fft.rfftfreq(w)
    # The derivative of the Nyquist term (−1)^n is undefined (its frequency is ±π); zeroing
    # it keeps the spectrum Hermitian so the result is the real least-squares solution.
    if h % 2 == 0:
        w_row[h // 2] = 0.0
    if w % 2 == 0:
        w_col[w // 2] = 0.0
    w_row = w_row.astype(np.float32)[:, None]
    w_col = w_col.astype(np.float32)[None, :]
    spec = scipy.fft.rfft2(g_col, workers=workers)
    spec *= w_col
    tmp = scipy.fft.rfft2(g_row, workers=workers)
    tmp *= w_row
    spec += tmp
    del tmp
    denom = w_row**2 + w_col**2
    # Zero only where the numerator is zero too (the constant and the Nyquist corners).
    denom[denom == 0] = 1.0
    # −i·(ω·G)/|ω|²
    spec /= denom
    spec *= np.complex64(-1j)
    spec[0, 0] = 0.0
    return scipy.fft.irfft2(spec, s=(h, w), workers=workers)


def _fc_mirror(g_row: np.ndarray, g_col: np.ndarray, workers: int | None) -> np.ndarray:
    """Frankot–Chellappa on the even extension of the height, with DCT-II/DST-II.

    With the height expanded in the orthonormal DCT-II basis φ_k(r)·φ_l(c), the spectral
    derivative of φ_l(c) = √(2/W)·cos(πl(c+½)/W) along c is −(πl/W)·ψ_{l−1}(c), where ψ_m is
    the orthonormal DST-II basis. So the column gradient's DCT(rows)·DST(cols) coefficient
    at (k, l−1) is −ω_l times the height's coefficient at (k, l), and likewise for rows. The
    least-squares height coefficient is −(ω_l·Gc[k, l−1] + ω_k·Gr[k−1, l]) / (ω_k² + ω_l²),
    identical to Frankot–Chellappa on the mirrored 2H × 2W field (the DST's highest term,
    frequency π, has no cosine partner on the half-sample grid and drops out, as the
    Nyquist term of the extended FFT does).
    """
    h, w = g_row.shape
    omega_row = (np.pi * np.arange(h) / h).astype(np.float32)
    omega_col = (np.pi * np.arange(w) / w).astype(np.float32)

    spec = scipy.fft.dst(g_col, type=2, axis=1, norm="ortho", workers=workers)
    spec = scipy.fft.dct(spec, type=2, axis=0, norm="ortho", workers=workers, overwrite_x=True)
    # Shift DST index l−1 to the DCT index l (numpy copes with the overlapping slices).
    spec[:, 1:] = spec[:, :-1]
    spec[:, 0] = 0.0
    spec *= omega_col[None, :]

    tmp = scipy.fft.dst(g_row, type=2, axis=0, norm="ortho", workers=workers)
    tmp = scipy.fft.dct(tmp, type=2, axis=1, norm="ortho", workers=workers, overwrite_x=True)
    tmp[1:, :] = tmp[:-1, :]
    tmp[0, :] = 0.0
    tmp *= omega_row[:, None]
    spec += tmp
    del tmp

    denom = omega_row[:, None] ** 2 + omega_col[None, :] ** 2
    denom[0, 0] = 1.0
    spec /= denom
    del denom
    np.negative(spec, out=spec)
    spec[0, 0] = 0.0
    return scipy.fft.idctn(spec, type=2, norm="ortho", workers=workers, overwrite_x=True)

