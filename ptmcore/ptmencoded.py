"""Fitting PTMs to photographs in their own encoding, as HP's PTMfitter does.

PTMfitter's LRGB fit (worked out from ``shared/fixtures/ptmfitter_8x5``, whose 12 photographs
and PTMfitter output are reproduced **byte for byte** by :func:`fit_ptm_encoded` followed by
:func:`ptmcore.ptmfile.write_ptm`): it fits the photographs' own 8-bit values, not linear light.

* The luminance of a photograph is the luma ``0.2125 R + 0.7154 G + 0.0721 B`` of its bytes (the
  Rec. 709 weights as they were quoted around 2000; the current 0.2126/0.7152/0.0722 misses one
  of the 240 coefficient bytes, by 0.005 of a step; Rec. 601 weights or the mean of R, G, B miss
  most of them). In a grid search (steps of 0.0005) only weights next to these reproduce every
  byte, but that rests on a handful of bytes close to a rounding boundary in one small fixture.
* Per pixel, that luminance is normalised so that the pixel's brightest photograph has L = 255:
  ``L_n = 255 · Y_n / max_n Y_n``; the polynomial is the least-squares (pseudoinverse) fit of L_n.
* The pixel's colour in the RGB block is the least-squares solution of ``C_n ≈ rgb · L_n / 255``
  over the photographs, ``rgb = max_n Y_n · Σ C_n Y_n / Σ Y_n²``, truncated (not rounded) to an
  integer. (Fitting against the polynomial's values instead of the observed L_n gives the same
  bytes on the fixture; the mean colour times the peak luminance, or the colour of the brightest
  photograph, do not.)
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

import numpy as np

from .errors import InputError
from .fit import fit_matrix
from .lp import as_directions
from .streaming import accumulate_photographs, fit_channels

__all__ = ["HP_LUMA_WEIGHTS", "fit_ptm_encoded", "fit_ptm_rgb_encoded"]

#: Luma weights HP's PTMfitter applies to the photographs' R, G, B bytes (see the module notes).
HP_LUMA_WEIGHTS = np.array([0.2125, 0.7154, 0.0721])


def _fit_setup(images: Sequence | np.ndarray, directions: np.ndarray, solver: str) -> tuple[int, np.ndarray]:
    n = len(images)
    # Fewer than six photographs leave the six coefficients underdetermined; the
    # pseudoinverse then gives the minimum-norm fit, and the caller warns about it.
    if n < 1:
        raise InputError("no photographs given")
    pinv = fit_matrix(as_directions(directions, n), solver).astype(np.float32)
    return n, pinv


def fit_ptm_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Fit an LRGB PTM to photographs as HP's PTMfitter does, in their own encoding.

    The photographs' bytes are used as they are (sRGB-encoded, not linearised). Per photograph
    and pixel the luma ``Y = 0.2125 R + 0.7154 G + 0.0721 B`` is normalised to
    ``L = 255 · Y / max_n Y`` (the pixel's brightest photograph has L = 255), the polynomial is
    the pseudoinverse fit of L, and the colour is the least-squares ``rgb`` of
    ``C ≈ rgb · L / 255``, truncated to bytes. Written with :func:`ptmcore.ptmfile.write_ptm` this reproduces
    PTMfitter's file byte for byte on the shared fixture (see the module notes).

    The photographs are streamed: one is decoded (in background threads) and added to running
    per-pixel sums at a time, so memory is 11 float32 per pixel (the six coefficient sums, the
    peak luma, Σ C·Y and Σ Y²) plus a few photographs, however many there are.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs, 8-bit (16-bit values are divided by 257, floats multiplied by 255).
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the light matrix (:func:`ptmcore.fit.fit_matrix`).
    threads : int, optional
        Decoding threads (default: all CPUs).
    progress : callable, optional
        Called with 1 after each photograph.

    Returns
    -------
    coefficients : ndarray, shape (H, W, 6), float32
        Luminance coefficients, L in 0..255 units, row 0 at the top.
    rgb : ndarray, shape (H, W, 3), uint8
        The colour block.

    Raises
    ------
    InputError
        If no photograph is given, one cannot be read, or sizes differ.
    """
    _, pinv = _fit_setup(images, directions, solver)
    wr, wg, wb = (np.float32(x) for x in HP_LUMA_WEIGHTS)
    sums: dict[str, np.ndarray] = {}

    def allocate(shape: tuple[int, int]) -> None:
        # Sums are kept plane by plane: adding into an interleaved (H, W, 6) array makes
        # NumPy loop over the last axis of 6 and runs several times slower.
        sums.update(acc=np.zeros((6,) + shape, np.float32), peak=np.zeros(shape, np.float32),
                    cy=np.zeros((3,) + shape, np.float32), y2=np.zeros(shape, np.float32))

    def add(k: int, c: np.ndarray, r0: int, r1: int) -> None:
        y = c[..., 0] * wr + c[..., 1] * wg + c[..., 2] * wb
        for j in range(6):
            sums["acc"][j, r0:r1] += y * pinv[j, k]
        np.maximum(sums["peak"][r0:r1], y, out=sums["peak"][r0:r1])
        for j in range(3):
            sums["cy"][j, r0:r1] += c[..., j] * y
        sums["y2"][r0:r1] += y * y

    shape = accumulate_photographs(images, allocate, add, threads=threads, progress=progress)
    acc, peak, cy, y2 = sums["acc"], sums["peak"], sums["cy"], sums["y2"]
    coefficients = np.empty(shape + (6,), dtype=np.float32)
    rgb = np.empty(shape + (3,), dtype=np.uint8)
    step = max(1, (1 << 18) // shape[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        for r0 in range(0, shape[0], step):
            band = slice(r0, r0 + step)
            p = peak[band]
            # A pixel black in every photograph keeps L = 0 and colour 0.
            norm = np.where(p > 0, np.float32(255) / p, np.float32(0))[..., None]
            coefficients[band] = np.moveaxis(acc[:, band], 0, -1) * norm
            colour = np.floor(p[..., None] * np.moveaxis(cy[:, band], 0, -1) / y2[band][..., None])
            rgb[band] = np.clip(np.nan_to_num(colour, nan=0.0, posinf=255.0), 0, 255).astype(np.uint8)
    return coefficients, rgb


def fit_ptm_rgb_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Fit an RGB-format PTM (one polynomial per channel) to photographs in their own encoding.

    Each channel's byte values (0..255, not linearised) are fitted by the pseudoinverse, so
    ``PTMFile.render`` of the written file approximates the photographs directly. Streams the
    photographs like :func:`fit_ptm_encoded` (18 float32 per pixel).

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs.
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the light matrix (:func:`ptmcore.fit.fit_matrix`).
    threads : int, optional
        Decoding threads (default: all CPUs).
    progress : callable, optional
        Called with 1 after each photograph.

    Returns
    -------
    ndarray, shape (H, W, 3, 6), float32
        Per-channel coefficients in 0..255 units, row 0 at the top.
    """
    _, pinv = _fit_setup(images, directions, solver)
    return fit_channels(images, pinv, threads=threads, progress=progress)
