"""Compiled display encoding of a stack's samples, and PTMfitter's LRGB split fused with it.

Fitting a published basis (:func:`ptmcore.bases.fit_published`) needs every sample of the stack
as the RGB a screen shows: the pixel's chroma times the photograph's linear luminance, clipped
to [0, 1] and, for bases fitted to sRGB values, encoded by the sRGB curve. In NumPy that was
three float32 arrays of N × P × 3 per band and a power per value: of the 21 s a PTM took at 24
megapixels (48 photographs, one thread), the curve alone was 8 and the LRGB split's sums 5.
Here each sample is read once and its three channels made in registers:

* :func:`display_samples` — the ``(N, P, 3)`` display values, and :func:`display_by_pixel` the
  same laid out ``(P, 3, N)`` (for the learned, RBF and bilinear bases, which keep every
  channel);
* :func:`lrgb_samples` — the same values split at once into a luminance ``(N, P)`` and a colour
  ``(P, 3)`` as :func:`ptmcore.bases._lrgb` splits them (for the PTM and HSH), without ever
  holding the ``(N, P, 3)`` array.

The sRGB curve is read from a table of :data:`CURVE_POINTS` values with linear interpolation:
its largest error, where the curve bends most (just above the linear toe), is under 2·10⁻⁵,
two hundredths of an 8-bit step (``tests/test_displaykernel.py`` measures it). Sums are float64.

The kernels release the GIL (``nogil``) and run on the caller's bands of rows, in its threads.
Importing this module imports numba; :mod:`ptmcore.bases` imports it only when fitting.
"""

from __future__ import annotations

import numba
import numpy as np

from .images import LUMA_WEIGHTS, linear_to_srgb

__all__ = ["CURVE_POINTS", "display_by_pixel", "display_samples", "lrgb_samples"]

#: Intervals of the tabulated sRGB curve on [0, 1].
CURVE_POINTS = 4096


def _curve_tables() -> dict[str, np.ndarray]:
    v = np.linspace(0.0, 1.0, CURVE_POINTS + 1)  # float64: the curve computed in float64
    # Linear values through the same code: the identity, interpolated exactly.
    return {"srgb": linear_to_srgb(v).astype(np.float32), "linear": v.astype(np.float32)}


_TABLES = _curve_tables()


def _table(encoding: str) -> np.ndarray:
    if encoding not in _TABLES:
        raise ValueError(f"encoding must be one of {sorted(_TABLES)}, not {encoding!r}")
    return _TABLES[encoding]


_WEIGHTS = LUMA_WEIGHTS.astype(np.float32)


@numba.njit(nogil=True, cache=True, inline="always")
def _encode(v: float, table: np.ndarray) -> float:
    # Branch-free (clamped, then the table interpolated), so that the loops vectorise.
    x = min(max(v, 0.0), 1.0) * np.float32(CURVE_POINTS)
    i = min(int(x), CURVE_POINTS - 1)
    t = x - i
    return table[i] + t * (table[i + 1] - table[i])


@numba.njit(nogil=True, cache=True)
def _display_kernel(lum, chroma, table, out):
    n, p = lum.shape
    for i in range(n):  # light by light: lum's rows are contiguous
        for j in range(p):
            v = lum[i, j]
            out[i, j, 0] = _encode(chroma[j, 0] * v, table)
            out[i, j, 1] = _encode(chroma[j, 1] * v, table)
            out[i, j, 2] = _encode(chroma[j, 2] * v, table)


@numba.njit(nogil=True, cache=True)
def _by_pixel_kernel(lum, chroma, table, out):
    n, p = lum.shape
    # Pixel by pixel, each one's row written in order. Reading down lum's column j touches n
    # cache lines that the next pixels read too, so they stay in the L1 cache (light by light
    # over blocks of pixels, writing across the rows, took 30 % longer).
    for j in range(p):
        for c in range(3):
            k = chroma[j, c]
            for i in range(n):
                out[j, c, i] = _encode(k * lum[i, j], table)


@numba.njit(nogil=True, cache=True)
def _lrgb_kernel(lum, chroma, table, weights, values, colour):
    n, p = lum.shape
    w0, w1, w2 = weights[0], weights[1], weights[2]
    # A block of pixels at a time, light by light (lum's rows are contiguous), with each
    # pixel's running sums in short arrays that stay in the L1 cache.
    block = 512
    peak = np.empty(block)
    energy = np.empty(block)
    sums = np.empty((block, 3))
    for start in range(0, p, block):
        stop = min(start + block, p)
        peak[:] = 0.0
        energy[:] = 0.0
        sums[:] = 0.0
        for i in range(n):
            for j in range(start, stop):
                v = lum[i, j]
                r = _encode(chroma[j, 0] * v, table)
                g = _encode(chroma[j, 1] * v, table)
                b = _encode(chroma[j, 2] * v, table)
                y = w0 * r + w1 * g + w2 * b
                values[i, j] = y
                q = j - start
                peak[q] = max(peak[q], y)
                energy[q] += y * y
                sums[q, 0] += r * y
                sums[q, 1] += g * y
                sums[q, 2] += b * y
        for j in range(start, stop):
            q = j - start
            k = peak[q] / energy[q] if energy[q] > 0.0 else peak[q]
            r, g, b = sums[q, 0] * k, sums[q, 1] * k, sums[q, 2] * k
            over = max(max(r, g, b), 1.0)
            colour[j, 0] = r / over
            colour[j, 1] = g / over
            colour[j, 2] = b / over
            sums[q, 0] = over / peak[q] if peak[q] > 0.0 else over  # the luminance's scale
        for i in range(n):
            for j in range(start, stop):
                values[i, j] *= sums[j - start, 0]


def _inputs(lum: np.ndarray, chroma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lum = np.ascontiguousarray(lum, dtype=np.float32)
    chroma = np.ascontiguousarray(chroma, dtype=np.float32).reshape(-1, 3)
    if lum.ndim != 2 or chroma.shape[0] != lum.shape[1]:
        raise ValueError(f"luminance (N, P) and chroma (P, 3) must agree, not {lum.shape} and {chroma.shape}")
    return lum, chroma


def display_samples(lum: np.ndarray, chroma: np.ndarray, encoding: str = "srgb") -> np.ndarray:
    """The RGB a screen shows of linear luminance ``(N, P)`` and chroma ``(P, 3)``: their
    product clipped to [0, 1] and, with ``encoding="srgb"``, sRGB-encoded; ``(N, P, 3)`` float32."""
    lum, chroma = _inputs(lum, chroma)
    out = np.empty((*lum.shape, 3), np.float32)
    _display_kernel(lum, chroma, _table(encoding), out)
    return out


def display_by_pixel(lum: np.ndarray, chroma: np.ndarray, encoding: str = "srgb") -> np.ndarray:
    """:func:`display_samples` laid out by pixel, then channel: ``(P, 3, N)`` float32, each
    pixel's row the vector an interpolating basis compresses (its channels' N values in turn)."""
    lum, chroma = _inputs(lum, chroma)
    out = np.empty((lum.shape[1], 3, lum.shape[0]), np.float32)
    _by_pixel_kernel(lum, chroma, _table(encoding), out)
    return out


def lrgb_samples(lum: np.ndarray, chroma: np.ndarray, encoding: str = "srgb") -> tuple[np.ndarray, np.ndarray]:
    """:func:`display_samples` split into a luminance ``(N, P)`` and a colour ``(P, 3)``, both
    float32, as :func:`ptmcore.bases._lrgb` splits them: the luminance normalised by each
    pixel's brightest sample, the colour the least-squares colour, scaled down (and the
    luminance up) where it would exceed 1."""
    lum, chroma = _inputs(lum, chroma)
    values = np.empty(lum.shape, np.float32)
    colour = np.empty((lum.shape[1], 3), np.float32)
    _lrgb_kernel(lum, chroma, _table(encoding), _WEIGHTS, values, colour)
    return values, colour
