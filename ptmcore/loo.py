"""Leave-one-out relighting error of a linear relighting basis (PTM, HSH, any N×K matrix).

How well does a basis relight an object under a light it was not fitted to? Leave light i out,
fit the rest, predict photograph i, compare. For a linear least-squares fit this needs no
refits: with the hat matrix H = B (BᵀB)⁻¹ Bᵀ = B B⁺ and the residuals of the full fit
R = (I − H) L, the leave-one-out residual of light i is exactly (Allen's PRESS identity)::

    e_i = r_i / (1 − h_ii)

H is the same for every pixel, so the leave-one-out error of the whole stack is again one
matrix product per band of rows, like the fit itself.

H is the orthogonal projection onto the column space of B, computed here from the SVD
B = U S Vᵀ as U_r U_rᵀ, r counting the singular values above ``rcond`` times the largest
(default :data:`ptmcore.hsh.RCOND`, the cut :func:`~ptmcore.hsh.fit_hsh` uses). So a
rank-deficient basis, such as the PTM's under lights on one ring, is handled like the truncated
pseudoinverse fit handles it: the prediction depends only on the kept span of B, never on how
it is parametrised. (:func:`ptmcore.fit.fit_ptm` cuts at the precision of the light directions
instead, :func:`ptmcore.solvers.rank_tolerance`: about 2.6·10⁻⁵ for 48 lights read from an
``.lp`` file, against 10⁻⁴ of the largest singular value here. A ring of lights falls below
both; a light matrix whose smallest singular values lie between the two keeps directions in
the fit that this error leaves out; elsewhere the two agree.)

A light with h_ii = 1 is the only one that pins down some combination of the coefficients:
without it the fit is undetermined and its prediction is arbitrary, so 0/0 above has no
meaning. Such lights are left out of the error, named in an :class:`UndeterminedLightWarning`
and listed by :func:`undetermined_lights`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from .bands import BAND_BYTES, band_rows, run_bands
from .errors import InputError
from .fit import light_matrix
from .hsh import RCOND, hsh_basis
from .images import ImageStack
from .lp import as_directions

#: A light whose 1 − h_ii is below this is taken as undetermined by the other lights.
LEVERAGE_TOL = 1e-8


class UndeterminedLightWarning(UserWarning):
    """Some lights cannot be predicted from the others, so they are left out of the error."""


def _projection(basis_matrix: np.ndarray, rcond: float) -> np.ndarray:
    """Orthonormal basis U_r (N×r) of the column space of B kept at ``rcond``."""
    b = np.asarray(basis_matrix, dtype=np.float64)
    if b.ndim != 2 or b.shape[0] < 1 or b.shape[1] < 1:
        raise ValueError(f"basis matrix must be N×K, got shape {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("basis matrix contains NaN or infinite values")
    u, s, _ = np.linalg.svd(b, full_matrices=False)
    rank = int(np.count_nonzero(s > rcond * s[0])) if s[0] > 0 else 0
    return u[:, :rank]


def hat_diagonal(basis_matrix: np.ndarray, *, rcond: float = RCOND) -> np.ndarray:
    """The leverages h_ii, the diagonal of the hat matrix H = B B⁺.

    Parameters
    ----------
    basis_matrix : ndarray, shape (N, K)
        One row of basis values per light.
    rcond : float
        Singular values of B below ``rcond`` times the largest count as zero.

    Returns
    -------
    ndarray, shape (N,), float64
        Values in [0, 1]; they sum to the rank of B. h_ii = 1 marks a light the fit cannot do
        without.
    """
    u = _projection(basis_matrix, rcond)
    return np.einsum("nr,nr->n", u, u)


def undetermined_lights(basis_matrix: np.ndarray, *, rcond: float = RCOND) -> np.ndarray:
    """Indices of the lights whose leave-one-out prediction is undetermined (h_ii → 1).

    Removing such a light lowers the rank of the fit (for instance the only light off a ring,
    or any light when there are no more lights than independent terms).
    """
    return np.flatnonzero(1.0 - hat_diagonal(basis_matrix, rcond=rcond) < LEVERAGE_TOL)


def _plan(basis_matrix: np.ndarray, rcond: float, warn: bool,
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """U_r, the indices of the lights that count, and 1 / (1 − h_ii) for them."""
    u = _projection(basis_matrix, rcond)
    one_minus_h = 1.0 - np.einsum("nr,nr->n", u, u)
    used = np.flatnonzero(one_minus_h >= LEVERAGE_TOL)
    if len(used) == 0:
        raise InputError(
            f"leave-one-out error is undefined: each of the {len(u)} lights is needed to determine "
            f"the {u.shape[1]} independent terms of the basis; more lights are needed"
        )
    if warn and len(used) < len(u):
        dropped = np.setdiff1d(np.arange(len(u)), used)
        warnings.warn(
            f"lights {dropped.tolist()} (0-based) cannot be predicted from the others with this "
            "basis (leverage 1); they are left out of the leave-one-out error",
            UndeterminedLightWarning,
            stacklevel=3,
        )
    return u, used, 1.0 / one_minus_h[used]


def loo_residuals(values: np.ndarray, basis_matrix: np.ndarray, *, rcond: float = RCOND,
                  warn: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out residuals ``L_i − L̂_i(−i)`` of arrays of samples, without refitting.

    Parameters
    ----------
    values : ndarray, shape (N, ...)
        Observations, one row (or image) per light.
    basis_matrix : ndarray, shape (N, K)
        The basis evaluated at each light.
    rcond : float
        Singular values of B below ``rcond`` times the largest count as zero.
    warn : bool
        Issue an :class:`UndeterminedLightWarning` if lights are left out.

    Returns
    -------
    residuals : ndarray, shape (M, ...), float64
        For each counted light i, the observation minus its prediction by the fit to all other
        lights, ``r_i / (1 − h_ii)``.
    used : ndarray, shape (M,), int
        Indices of the counted lights (all, unless some have h_ii → 1).

    Raises
    ------
    InputError
        If no light can be predicted from the others.
    """
    v = np.asarray(values, dtype=np.float64)
    n = len(basis_matrix)
    if v.shape[0] != n:
        raise ValueError(f"{v.shape[0]} rows of values for a basis of {n} lights")
    u, used, scale = _plan(basis_matrix, rcond, warn)
    flat = v.reshape(n, -1)
    # R = (I − U Uᵀ) L, with two thin products instead of the N×N hat matrix.
    resid = flat[used] - u[used] @ (u.T @ flat)
    resid *= scale[:, None]
    return resid.reshape((len(used),) + v.shape[1:]), used


def loo_error(
    stack: ImageStack,
    basis_matrix: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
    rcond: float = RCOND,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[np.ndarray, float]:
    """Leave-one-out relighting error of every pixel of a stack.

    Parameters
    ----------
    stack : ImageStack
        The photographs' linear luminance (clipped samples read as 1, as the fit sees them).
    basis_matrix : ndarray, shape (N, K)
        The relighting basis at each photograph's light, e.g. :func:`ptmcore.fit.light_matrix`
        or :func:`ptmcore.hsh.hsh_basis`.
    mask : ndarray, shape (H, W), bool, optional
        Pixels that count towards the scalar (default: all); the map covers every pixel.
    transform : callable, optional
        Applied element-wise to the observed and the predicted luminance before they are
        compared, e.g. ``lambda v: 255 * linear_to_srgb(v)`` for an error in 8-bit sRGB levels.
        Default: compare linear luminance.
    rcond : float
        Singular values of B below ``rcond`` times the largest count as zero.
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    rms_map : ndarray, shape (H, W), float32
        Per pixel, the root mean square over the counted lights of the leave-one-out error.
    mean : float
        The capture's leave-one-out RMSE: the root mean square over every counted light and
        every pixel in ``mask`` (the root of the mean of ``rms_map²``).

    Raises
    ------
    InputError
        If no light can be predicted from the others (no more lights than terms).

    Warns
    -----
    UndeterminedLightWarning
        If some lights have leverage h_ii → 1; they are left out of map and mean.

    Notes
    -----
    The arithmetic is float64: the residual of a light of high leverage is (1 − h_ii)·e_i, and
    float32 rounding of L − H L would be blown up by 1 / (1 − h_ii).
    """
    n = len(stack)
    h, w = stack.shape
    b = np.asarray(basis_matrix, dtype=np.float64)
    if b.ndim != 2 or b.shape[0] != n:
        raise ValueError(f"basis matrix must have {n} rows (one per photograph), got shape {b.shape}")
    u, used, scale = _plan(b, rcond, warn=True)
    u_used = u[used]

    def residuals(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        observed = flat[used]
        err = observed - u_used @ (u.T @ flat)
        err *= scale[:, None]
        return observed, err

    return _error_map(stack, residuals, len(used), mask, transform, threads, progress)


def loo_interpolated(
    stack: ImageStack,
    predictor: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[np.ndarray, float]:
    """Leave-one-out relighting error of every pixel of a stack, for an interpolating basis.

    As :func:`loo_error`, with each photograph predicted by a given linear combination of the
    others instead of a least-squares refit: row ``i`` of ``predictor`` ``(N, N)`` (zero on the
    diagonal) weighs the other photographs to predict photograph ``i``
    (:func:`ptmcore.interpolation.rbf_loo_matrix`, :func:`~ptmcore.interpolation.bilinear_loo_matrix`).
    The photographs' luminance is interpolated as it is, not through principal components.
    """
    n = len(stack)
    m = np.asarray(predictor, dtype=np.float64)
    if m.shape != (n, n):
        raise ValueError(f"predictor must be ({n}, {n}), one row per photograph, got shape {m.shape}")

    def residuals(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return flat, flat - m @ flat

    return _error_map(stack, residuals, n, None if mask is None else mask, transform, threads, progress)


def _error_map(stack: ImageStack, residuals: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], counted: int,
               mask: np.ndarray | None, transform: Callable[[np.ndarray], np.ndarray] | None,
               threads: int | None, progress: Callable[[int], None] | None) -> tuple[np.ndarray, float]:
    """Per-pixel RMS over ``counted`` lights of ``residuals(band)`` → (observed, error), and
    its root mean square over ``mask``, band by band."""
    n = len(stack)
    h, w = stack.shape
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (h, w):
            raise ValueError(f"mask must have shape {(h, w)}, got {mask.shape}")
        if not mask.any():
            raise ValueError("mask selects no pixel")
    mean_square = np.empty((h, w), dtype=np.float64)

    def work(r0: int, r1: int) -> None:
        values, _ = stack.band(r0, r1)
        observed, err = residuals(values.reshape(n, -1).astype(np.float64))
        if transform is not None:
            err = transform(observed) - transform(observed - err)
        mean_square[r0:r1] = np.einsum("mp,mp->p", err, err).reshape(r1 - r0, w) / counted

    # float64 band plus its residuals and their transform: budget about 4× 8 bytes a sample.
    rows = band_rows(n, w, bytes_per_sample=32, budget=BAND_BYTES)
    run_bands(h, rows, work, threads=threads, progress=progress)
    overall = float(np.sqrt(mean_square[mask].mean() if mask is not None else mean_square.mean()))
    return np.sqrt(mean_square).astype(np.float32), overall


def loo_ptm(stack: ImageStack, directions: np.ndarray, **kwargs) -> tuple[np.ndarray, float]:
    """:func:`loo_error` of the biquadratic PTM basis; keyword arguments are passed on."""
    return loo_error(stack, light_matrix(as_directions(directions, len(stack))), **kwargs)


def loo_hsh(stack: ImageStack, directions: np.ndarray, order: int = 3, **kwargs,
            ) -> tuple[np.ndarray, float]:
    """:func:`loo_error` of the HSH basis of ``order``; keyword arguments are passed on."""
    return loo_error(stack, hsh_basis(as_directions(directions, len(stack)), order), **kwargs)
