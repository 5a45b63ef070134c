"""Removing low-frequency bending from a height map on a masked domain.

Heights integrated from photometric normals are often bent: a small error in the light
directions (or a light-intensity gradient across the dome) adds a nearly constant bias to the
gradients, which integrates to a tilt, and a bias that varies across the field integrates to
a bowl or saddle. These functions remove such trends:

* :func:`remove_plane` and :func:`remove_polynomial` fit a low-order 2-D polynomial to the
  valid pixels by least squares and subtract it. They remove exactly the polynomial trend and
  keep everything else, including the object's own large-scale shape if it projects onto the
  polynomial (a domed tablet loses part of its dome under ``order=2``).
* :func:`high_pass` subtracts a Gaussian low-pass of the height. It removes bends of any
  shape longer than the cutoff wavelength, and with them the object's shape at those scales,
  leaving only the surface detail.

Invalid pixels are NaN in the input, or outside ``mask``; they never influence the result
and stay NaN in the output. Results are float32 in the input's height units.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage

__all__ = ["flatten", "high_pass", "remove_plane", "remove_polynomial"]

#: Most pixels used in a polynomial fit; larger domains are subsampled on a regular grid,
#: which leaves the fit of a smooth trend practically unchanged at a fraction of the memory.
MAX_FIT_SAMPLES = 1_000_000

#: Gaussian sigma per pixel of cutoff wavelength: the low-pass gain
#: exp(−2π²σ²/λ²) is one half at λ = cutoff, so σ = √(ln 2 / 2) / π · cutoff ≈ 0.187 · cutoff.
SIGMA_PER_CUTOFF = float(np.sqrt(np.log(2.0) / 2.0) / np.pi)


def _valid(height: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Check the inputs; return the height as float64 and the valid-pixel mask."""
    h = np.asarray(height, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"height must be a 2-D array, got shape {h.shape}")
    valid = np.isfinite(h)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != h.shape:
            raise ValueError(f"mask shape {mask.shape} does not match height shape {h.shape}")
        valid &= mask
    return h, valid


def _normalised_coordinates(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """x (right) and y (up) of the pixel centres, scaled to [−1, 1] along the longer side.

    One common scale keeps the fit isotropic; [−1, 1] keeps the powers of order ≤ 3 of
    similar magnitude, so the least-squares matrix is well conditioned.
    """
    rows, cols = shape
    half = 0.5 * max(max(rows, cols) - 1, 1)
    x = (np.arange(cols) - 0.5 * (cols - 1)) / half
    y = -(np.arange(rows) - 0.5 * (rows - 1)) / half  # y up, rows down
    return x, y


def _exponents(order: int) -> list[tuple[int, int]]:
    """(i, j) of the monomials xⁱ yʲ with i + j ≤ order."""
    return [(i, d - i) for d in range(order + 1) for i in range(d, -1, -1)]


def remove_polynomial(
    height: np.ndarray,
    order: int = 2,
    mask: np.ndarray | None = None,
    *,
    return_trend: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Subtract the least-squares 2-D polynomial of total degree ``order`` from a height map.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights; NaN marks missing pixels.
    order : int
        Total degree: 0 removes the mean, 1 a plane, 2 a quadric (bowl, saddle), 3 a cubic.
    mask : np.ndarray, optional
        (H, W) bool, True on the pixels to fit and return; default all finite pixels.
    return_trend : bool
        Also return the fitted polynomial, evaluated on the valid pixels (NaN elsewhere).

    Returns
    -------
    np.ndarray or tuple of np.ndarray
        (H, W) float32 flattened heights, NaN outside the valid pixels; and the trend if
        ``return_trend``.

    Raises
    ------
    ValueError
        For a bad order or shape, or fewer valid pixels than polynomial terms.

    Notes
    -----
    The fit is in coordinates scaled to [−1, 1] (see :func:`_normalised_coordinates`) for
    conditioning. Domains of more than :data:`MAX_FIT_SAMPLES` pixels are fitted on a regular
    subsample.
    """
    if not isinstance(order, (int, np.integer)) or order < 0:
        raise ValueError(f"order must be a non-negative integer, got {order!r}")
    h, valid = _valid(height, mask)
    terms = _exponents(int(order))
    rows, cols = np.nonzero(valid)
    if len(rows) < len(terms):
        raise ValueError(
            f"need at least {len(terms)} valid pixels for an order-{order} fit, got {len(rows)}")
    step = int(np.ceil(len(rows) / MAX_FIT_SAMPLES))
    rows, cols = rows[::step], cols[::step]
    x, y = _normalised_coordinates(h.shape)
    design = np.stack([x[cols] ** i * y[rows] ** j for i, j in terms], axis=1)
    coef, *_ = np.linalg.lstsq(design, h[rows, cols], rcond=None)
    # Separable evaluation: each term is an outer product of a column and a row power.
    trend = np.zeros(h.shape)
    for c, (i, j) in zip(coef, terms):
        trend += c * np.outer(y ** j, x ** i)
    out = np.where(valid, h - trend, np.nan).astype(np.float32)
    if return_trend:
        return out, np.where(valid, trend, np.nan).astype(np.float32)
    return out


def remove_plane(height: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Subtract the least-squares plane (tilt and offset) from a height map.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights; NaN marks missing pixels.
    mask : np.ndarray, optional
        (H, W) bool, True on the pixels to fit and return.

    Returns
    -------
    np.ndarray
        (H, W) float32, zero-mean and untilted over the valid pixels, NaN elsewhere.
    """
    return remove_polynomial(height, 1, mask)


def high_pass(height: np.ndarray, cutoff_px: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Subtract a Gaussian low-pass of the height, computed by normalised convolution.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights; NaN marks missing pixels.
    cutoff_px : float
        Cutoff wavelength in pixels: a sinusoidal relief of this wavelength keeps half its
        amplitude. Shorter detail passes almost unchanged (wavelength cutoff/2: 94 %), longer
        undulations are removed (4 × cutoff: 4 % left, 10 × cutoff: 0.7 % left). Choose it
        a few times larger than the largest detail to keep (e.g. a wedge impression) and
        smaller than the bend to remove.
    mask : np.ndarray, optional
        (H, W) bool, True on the pixels to use and return.

    Returns
    -------
    np.ndarray
        (H, W) float32 detail, NaN outside the valid pixels.

    Notes
    -----
    The Gaussian's sigma is :data:`SIGMA_PER_CUTOFF` × ``cutoff_px``. The low-pass is
    ``G∗(w·h) / G∗w`` with w the valid-pixel indicator, so missing pixels and the area beyond
    the frame contribute nothing instead of pulling the average towards zero. Near the
    domain's edge the average is one-sided: a bend is then removed less completely there
    than in the interior (by about its curvature times sigma²).
    """
    if not np.isfinite(cutoff_px) or cutoff_px <= 0:
        raise ValueError(f"cutoff_px must be a positive number, got {cutoff_px!r}")
    h, valid = _valid(height, mask)
    if not valid.any():
        raise ValueError("no valid pixels to filter")
    sigma = SIGMA_PER_CUTOFF * float(cutoff_px)
    weight = valid.astype(np.float64)
    num = ndimage.gaussian_filter(np.where(valid, h, 0.0), sigma, mode="constant", cval=0.0)
    den = ndimage.gaussian_filter(weight, sigma, mode="constant", cval=0.0)
    # den > 0 wherever a valid pixel is within reach, which includes every valid pixel.
    low = num / np.where(den > 0, den, 1.0)
    return np.where(valid, h - low, np.nan).astype(np.float32)


_METHODS: dict[str, Callable[..., np.ndarray]] = {
    "plane": lambda height, **kw: remove_polynomial(height, 1, **kw),
    "poly2": lambda height, **kw: remove_polynomial(height, 2, **kw),
    "poly3": lambda height, **kw: remove_polynomial(height, 3, **kw),
    "highpass": high_pass,
}


def flatten(height: np.ndarray, method: str = "plane", **kw) -> np.ndarray:
    """Remove low-frequency bending with the chosen method.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights; NaN marks missing pixels.
    method : {"plane", "poly2", "poly3", "highpass"}
        :func:`remove_plane`, :func:`remove_polynomial` of order 2 or 3, or :func:`high_pass`.
    **kw
        Passed on: ``mask`` for all; ``cutoff_px`` (required) for "highpass".

    Returns
    -------
    np.ndarray
        (H, W) float32, NaN outside the valid pixels.

    Raises
    ------
    ValueError
        For an unknown method or bad arguments.
    """
    try:
        func = _METHODS[method]
    except KeyError:
        raise ValueError(
            f"method must be one of {', '.join(_METHODS)}, got {method!r}") from None
    if method == "highpass" and "cutoff_px" not in kw:
        raise ValueError('method="highpass" needs cutoff_px')
    try:
        return func(height, **kw)
    except TypeError as exc:
        # An unexpected keyword is a user error in the options, reported like the others.
        raise ValueError(f"bad options for method {method!r}: {exc}") from None
