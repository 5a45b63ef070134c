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
from .images import ImageStack, linear_to_srgb, srgb_to_linear
from .lp import as_directions


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
    lu, lv = d[:, 0], d[:, 1]
    return np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=1)


def fit_matrix(directions: np.ndarray) -> np.ndarray:
    """The 6×N matrix Λ⁺ that maps N luminances to the six PTM coefficients."""
    return np.linalg.pinv(light_matrix(directions))


@dataclass
class PTM:
    """An LRGB Polynomial Texture Map.

    Attributes
    ----------
    coefficients : ndarray, shape (H, W, 6), float32
        a0..a5 per pixel, in the units of the luminance that was fitted (linear, 0..1).
    chroma : ndarray, shape (H, W, 3), float32
        Per-pixel colour of unit luminance: the RGB under a light is ``chroma · L``.
    """

    coefficients: np.ndarray
    chroma: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.coefficients.shape[:2]

    def luminance(self, light: np.ndarray) -> np.ndarray:
        """Luminance ``(H, W)`` under one light direction (x, y, z) or (lu, lv)."""
        row = light_matrix(np.asarray(light, dtype=np.float64)[None, :2]).astype(np.float32)[0]
        return self.coefficients @ row

    def relight(self, light: np.ndarray) -> np.ndarray:
        """Linear RGB image ``(H, W, 3)`` under one light direction."""
        return self.chroma * self.luminance(light)[..., None]


def fit_ptm(
    stack: ImageStack,
    directions: np.ndarray,
    *,
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
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    PTM
    """
    n = len(stack)
    h, w = stack.shape
    pinv = fit_matrix(as_directions(directions, n)).astype(np.float32)
    coef = np.empty((h, w, 6), dtype=np.float32)

    def work(r0: int, r1: int) -> None:
        values, _ = stack.band(r0, r1)
        # (6, N) @ (N, rows·W): one BLAS call per band.
        coef[r0:r1] = (pinv @ values.reshape(n, -1)).T.reshape(r1 - r0, w, 6)

    run_bands(h, band_rows(n, w), work, threads=threads, progress=progress)
    return PTM(coef, stack.chroma)


def _encoded_table(stack: ImageStack) -> np.ndarray:
    """Stored luminance code → luminance in the photographs' 0–255 encoding (65536 entries)."""
    v = np.arange(65536, dtype=np.float64) / 65534.0
    v[-1] = 1.0  # the clipped-sample code
    if stack.linearized or stack.bit_depth > 8:
        v = linear_to_srgb(v)
    return (v * 255.0).astype(np.float32)


def _srgb_unclipped(v: np.ndarray) -> np.ndarray:
    """The sRGB encoding continued above 1, so that ratios of saturated colours survive."""
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.maximum(v, 0.0031308) ** (1 / 2.4) - 0.055).astype(
        np.float32
    )


def fit_ptm_display(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """An LRGB PTM for viewers: coefficients in sRGB-encoded luminance (0–255) and 8-bit colour.

    RTIViewer renders an LRGB PTM as ``rgb · L / 255`` and shows the result as it is, so the
    polynomial must be fitted to the photographs in their own encoding (as HP's PTMfitter fits
    the sRGB bytes), not to linear light. The stack holds linear luminance; each sample is
    encoded back through the sRGB curve (a table of its 65536 codes) before the same
    pseudoinverse fit. The colour follows from the pixel's linear chromaticity ``c`` (unit
    luminance): ``rgb = 255·srgb(c·Y0)/srgb(Y0)`` at the pixel's luminance Y0 under a light
    from the zenith, exact there and close elsewhere since the sRGB curve is near a power law;
    where a channel exceeds 255 (saturated colours), rgb is divided and the pixel's
    coefficients multiplied by the same factor, which leaves their product alone.
    Photographs read with ``linearize=False`` are fitted as they are.

    Returns
    -------
    coefficients : ndarray, shape (H, W, 6), float32
        In 0–255 luminance units.
    rgb : ndarray, shape (H, W, 3), uint8
    """
    n = len(stack)
    h, w = stack.shape
    pinv = fit_matrix(as_directions(directions, n)).astype(np.float32)
    table = _encoded_table(stack)
    coef = np.empty((h, w, 6), dtype=np.float32)

    def work(r0: int, r1: int) -> None:
        encoded = table[stack.luminance[:, r0:r1]].reshape(n, -1)
        coef[r0:r1] = (pinv @ encoded).T.reshape(r1 - r0, w, 6)

    run_bands(h, band_rows(n, w), work, threads=threads)
    c = np.maximum(stack.chroma, 0.0)
    if stack.linearized or stack.bit_depth > 8:
        # The pixel's luminance under a light from the zenith (its polynomial's constant term),
        # where the colour ratio is taken exactly: rgb_c = 255·srgb(c_c·Y0)/srgb(Y0).
        y0 = srgb_to_linear(np.clip(coef[..., 5] / np.float32(255), 1e-3, 1.0))[..., None]
        c = _srgb_unclipped(c * y0) / _srgb_unclipped(y0)
    k = np.maximum(c.max(axis=2), 1.0)
    coef *= k[..., None]
    rgb = np.clip(np.round(c / k[..., None] * 255.0), 0, 255).astype(np.uint8)
    return coef, rgb
