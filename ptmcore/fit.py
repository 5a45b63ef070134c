"""Fitting Polynomial Texture Maps (Malzbender, Gelb, Wolters, SIGGRAPH 2001).

Per pixel, the luminance under a light whose direction projects to (lu, lv) is modelled as
``L = a0·lu² + a1·lv² + a2·lu·lv + a3·lu + a4·lv + a5``. Over N photographs this is the linear
system ``Λ a = L`` with one row ``[lu², lv², lu·lv, lu, lv, 1]`` of the N×6 light matrix Λ per
photograph. Λ is the same for every pixel, so the least-squares solution for all pixels is one
6×N matrix, the Moore–Penrose pseudoinverse Λ⁺, applied to the stack: a matrix product done in
bands of rows in float32.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .bands import band_rows, run_bands
from .images import ImageStack
from .lp import as_directions


def ptm_terms(lu: np.ndarray, lv: np.ndarray, axis: int = -1) -> np.ndarray:
    """The six terms ``lu², lv², lu·lv, lu, lv, 1`` of the PTM at lights ``(lu, lv)``, stacked
    along a new ``axis``, in the arrays' own type.

    Parameters
    ----------
    lu, lv : ndarray
        The lights' projections, of one shape.
    axis : int
        Where the six terms go in the result.

    Returns
    -------
    ndarray
        ``lu``'s shape with an axis of 6 inserted at ``axis``.
    """
    return np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=axis)


def evaluate_at(coefficients: np.ndarray, lu: np.ndarray, lv: np.ndarray) -> np.ndarray:
    """Each pixel's polynomial at its own light ``(lu[p], lv[p])``.

    Parameters
    ----------
    coefficients : ndarray, shape (..., 6) or (..., 3, 6)
        A PTM's luminance coefficients, or an RGB-format PTM's per channel.
    lu, lv : ndarray, shape (...)
        Each pixel's light.

    Returns
    -------
    ndarray, shape (...) or (..., 3)
    """
    terms = ptm_terms(lu, lv)
    if coefficients.ndim == terms.ndim + 1:  # RGB format: the same light for the three channels
        terms = terms[..., None, :]
    return (coefficients * terms).sum(axis=-1)


def light_matrix(directions: np.ndarray) -> np.ndarray:
    """The N×6 PTM light matrix ``[lu², lv², lu·lv, lu, lv, 1]``.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Unit vectors towards the lights (only x = lu and y = lv are used).

    Returns
    -------
    ndarray, shape (N, 6), float64
    """
    d = np.asarray(directions, dtype=np.float64)
    return ptm_terms(d[:, 0], d[:, 1], axis=1)


def fit_matrix(directions: np.ndarray, method: str = "pinv", **options) -> np.ndarray:
    """The 6×N matrix that maps N luminances to the six PTM coefficients.

    By default the Moore–Penrose pseudoinverse Λ⁺, with singular values below the precision of
    the light directions treated as zero (:func:`ptmcore.solvers.solve_matrix`): a ring of
    lamps at one elevation, read from an ``.lp`` file with six decimals, otherwise has a
    spurious 1e-7 singular value that turns noise into coefficients in the thousands.
    ``method`` and ``options`` select another {1}-inverse (see ptmcore.solvers).
    """
    from .solvers import solve_matrix  # solvers builds on light_matrix above

    return solve_matrix(directions, method, **options)


@dataclass
class LinearRelighting:
    """Per-pixel luminance as a linear combination of basis functions of the light, plus colour.

    Subclasses name the basis (:class:`PTM`, :class:`ptmcore.hsh.HSH`) by :meth:`basis`.

    Attributes
    ----------
    coefficients : ndarray, shape (H, W, K), float32
        Per pixel, in the units of the luminance that was fitted (linear, 0..1).
    chroma : ndarray, shape (H, W, 3), float32
        Per-pixel colour of unit luminance: the RGB under a light is ``chroma · L``.
    """

    coefficients: np.ndarray
    chroma: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """Image height and width."""
        return self.coefficients.shape[:2]

    def basis(self, light: np.ndarray) -> np.ndarray:
        """The K basis functions at one light direction."""
        raise NotImplementedError

    def luminance(self, light: np.ndarray) -> np.ndarray:
        """Luminance ``(H, W)`` under one light direction (x, y, z) or (lu, lv)."""
        return self.coefficients @ self.basis(np.asarray(light, dtype=np.float64)).astype(np.float32)

    def relight(self, light: np.ndarray) -> np.ndarray:
        """Linear RGB image ``(H, W, 3)`` under one light direction."""
        return self.chroma * self.luminance(light)[..., None]


@dataclass
class PTM(LinearRelighting):
    """An LRGB Polynomial Texture Map: coefficients a0..a5, shape (H, W, 6)."""

    def basis(self, light: np.ndarray) -> np.ndarray:
        return light_matrix(light[None, :2])[0]


def fit_ptm(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> PTM:
    """Fit an LRGB PTM to a stack by least squares.

    Parameters
    ----------
    stack : ImageStack
        The photographs' luminance.
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the light matrix (:func:`fit_matrix`).
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    PTM
    """
    matrix = fit_matrix(as_directions(directions, len(stack)), solver)
    return PTM(apply_fit_matrix(stack, matrix, threads=threads, progress=progress), stack.chroma)


def apply_fit_matrix(
    stack: ImageStack,
    matrix: np.ndarray,
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Coefficients ``matrix @ luminance`` of every pixel: any linear basis fitted at once.

    Parameters
    ----------
    stack : ImageStack
    matrix : ndarray, shape (K, N)
        Maps the N luminances of a pixel to its K coefficients (e.g. a pseudoinverse).

    Returns
    -------
    ndarray, shape (H, W, K), float32
    """
    n = len(stack)
    h, w = stack.shape
    k = matrix.shape[0]
    m = np.asarray(matrix, dtype=np.float32)
    coef = np.empty((h, w, k), dtype=np.float32)

    def work(r0: int, r1: int) -> None:
        values, _ = stack.band(r0, r1)
        # (K, N) @ (N, rows·W): one BLAS call per band.
        coef[r0:r1] = (m @ values.reshape(n, -1)).T.reshape(r1 - r0, w, k)

    run_bands(h, band_rows(n, w), work, threads=threads, progress=progress)
    return coef
