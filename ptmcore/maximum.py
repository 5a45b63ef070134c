"""The maximum of each pixel's PTM polynomial over the unit disk, compiled: the kernel behind
:func:`ptmcore.normals.ptm_maximum` and :func:`ptmcore.normals.normals_from_ptm`.

In NumPy the search was a chain of float64 passes over a band: the closed form for every pixel,
then, for the pixels whose maximum is on the unit circle, a gathered copy of their coefficients,
a (P, 72) matrix of samples and four Newton steps of a dozen element-wise passes each, every one
with fresh temporaries, and one thread. :func:`maximum_rows` takes the pixels of a band a chunk
at a time, with every intermediate in work arrays that stay in the cache: the closed form over
the chunk, the samples for those of its pixels whose maximum is on the circle (one sample for
all of them at a time, which vectorises), then their Newton steps, one step for all of them at
a time, so that each pixel's chain of sine, cosine, division and update overlaps with the next
pixel's instead of being waited for. A pixel's steps stop where θ no longer moves: every later
step would leave it there too. What is left is mostly the sines and cosines of the steps.

The arithmetic is the NumPy steps', in float64 and in the same order (numba contracts no product
and sum into a fused multiply-add without ``fastmath``); the sines and cosines are libm's,
which NumPy's float64 ones equal to the bit (tested), so the results are the same to the bit.
The one exception is L at the 72 samples: NumPy got it from a matrix product, whose order and
fused multiply-adds are the BLAS library's (and differ between one pixel and many); here the
terms are added in their order. The last bit of a sample can then differ, which changes the
sample the refinement starts from only where two samples tie to within rounding: the equal
maxima of a symmetric polynomial (``tests/test_ptm_maximum_kernel.py``).

The kernel releases the GIL and runs in the caller's threads on bands of rows
(:func:`maximum_bands`), so ``threads`` is respected and numba's threading layer is not
involved. Compiled code is cached on disk (``cache=True``), so only the first run after
installation pays for compilation.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .bands import run_bands
from .normals import FLAT

__all__ = ["maximum_bands", "maximum_rows"]

_CIRCLE_SAMPLES = 72
_NEWTON_STEPS = 4
#: Newton's step on θ is clipped to this (radians): the best sample is within 2.5° of the
#: maximum, and a larger step means the curvature misleads.
_MAX_STEP = 0.05
#: Pixels per chunk: the work arrays of a chunk (some 40 kB) stay in the cache.
_CHUNK = 256
#: Pixels per band of rows: a thread's unit of work, and the most a band of coefficients of
#: another type than float32 or float64 is converted at a time.
_BAND_PIXELS = 1 << 16

_THETA = np.linspace(0.0, 2 * np.pi, _CIRCLE_SAMPLES, endpoint=False)
_C, _S = np.cos(_THETA), np.sin(_THETA)
#: Rows: c², s², cs, c, s of the samples (L at sample k is Σ a_i · row i; a5 does not move the
#: maximum), then θ, cos 2θ and sin 2θ there, for the first Newton step.
_TABLES = np.stack([_C * _C, _S * _S, _C * _S, _C, _S, _THETA, np.cos(2 * _THETA), np.sin(2 * _THETA)])
_CC, _SS, _CS, _COS, _SIN, _ANGLE, _COS2, _SIN2 = range(8)

# Rows of the work arrays. ``chunk``: a0..a5, then the maximum's lu and lv, of the chunk's
# pixels. ``circle``: a0..a4 of the pixels whose maximum is on the circle, the largest sample
# so far, then θ, cos θ, sin θ, cos 2θ and sin 2θ of their Newton steps.
_U, _V = 6, 7
_BEST, _T, _CT, _ST, _C2T, _S2T = 5, 6, 7, 8, 9, 10


@numba.njit(nogil=True, cache=True)
def _first_largest_sample(a0, a1, a2, a3, a4, a5, tables):  # pragma: no cover - compiled
    """np.argmax of L over the samples, for coefficients that are not all finite: samples can
    then be NaN, and np.argmax takes the first NaN as the largest."""
    # NumPy's sample matrix multiplied a5 by 0: where it is not finite every sample is NaN.
    if not math.isfinite(a5):
        return 0
    best = 0
    best_value = -math.inf
    for k in range(tables.shape[1]):
        value = (a0 * tables[_CC, k] + a1 * tables[_SS, k] + a2 * tables[_CS, k]
                 + a3 * tables[_COS, k] + a4 * tables[_SIN, k])
        if math.isnan(value):
            return k
        if value > best_value:
            best = k
            best_value = value
    return best


# Inlined where its work arrays are made: only there does the compiler know them apart, which
# it needs to vectorise the loop over the samples (called, that loop was several times slower).
@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _circle_maxima(chunk, listed, m, tables, circle, best, moving):  # pragma: no cover - compiled
    """(cos θ, sin θ), float64, of the θ that maximises L on the unit circle, for the pixels
    ``listed[:m]`` of the chunk, into its rows lu and lv.

    On the circle, L(θ) = a0 c² + a1 s² + a2 c s + a3 c + a4 s + a5 has no closed-form
    maximum (its stationary points solve a quartic), so it is sampled (``tables``) and the best
    sample refined by :data:`_NEWTON_STEPS` steps of Newton's method on L'(θ), as the NumPy
    steps did. ``circle`` (11, :data:`_CHUNK`), ``best`` and ``moving`` (:data:`_CHUNK`) are
    work arrays.
    """
    for i in range(m):
        for k in range(5):
            circle[k, i] = chunk[k, listed[i]]
        circle[_BEST, i] = -math.inf
        best[i] = 0
    # np.argmax over the samples: finite coefficients make no NaN (finite terms add up to a
    # number or ±inf), so the first of the largest is the one ``>`` keeps. The pixels with
    # other coefficients are done again below.
    for k in range(tables.shape[1]):
        cc, ss, cs, c, s = tables[_CC, k], tables[_SS, k], tables[_CS, k], tables[_COS, k], tables[_SIN, k]
        for i in range(m):
            value = circle[0, i] * cc + circle[1, i] * ss + circle[2, i] * cs + circle[3, i] * c + circle[4, i] * s
            larger = value > circle[_BEST, i]
            circle[_BEST, i] = value if larger else circle[_BEST, i]
            best[i] = k if larger else best[i]
    for i in range(m):
        j = listed[i]
        a0, a1, a2, a3, a4, a5 = chunk[0, j], chunk[1, j], chunk[2, j], chunk[3, j], chunk[4, j], chunk[5, j]
        if not (math.isfinite(a0) and math.isfinite(a1) and math.isfinite(a2) and math.isfinite(a3)
                and math.isfinite(a4) and math.isfinite(a5)):
            best[i] = _first_largest_sample(a0, a1, a2, a3, a4, a5, tables)
        k = best[i]
        circle[_T, i] = tables[_ANGLE, k]
        circle[_CT, i] = tables[_COS, k]
        circle[_ST, i] = tables[_SIN, k]
        circle[_C2T, i] = tables[_COS2, k]
        circle[_S2T, i] = tables[_SIN2, k]
        moving[i] = True
    for step in range(_NEWTON_STEPS):
        for i in range(m):
            if not moving[i]:
                continue
            a0, a1, a2, a3, a4 = circle[0, i], circle[1, i], circle[2, i], circle[3, i], circle[4, i]
            t, c, s, c2, s2 = circle[_T, i], circle[_CT, i], circle[_ST, i], circle[_C2T, i], circle[_S2T, i]
            d_a = a1 - a0
            d1 = d_a * s2 + a2 * c2 - a3 * s + a4 * c
            d2 = 2 * d_a * c2 - 2 * a2 * s2 - a3 * c - a4 * s
            # Only step where the curvature says we are near a maximum; the sample is already
            # within 2.5° of it. Where θ does not move, every later step would leave it too.
            if not d2 < 0:
                moving[i] = False
                continue
            d = d1 / d2
            if d < -_MAX_STEP:
                d = -_MAX_STEP
            elif d > _MAX_STEP:
                d = _MAX_STEP
            moved = t - d
            if moved == t:
                moving[i] = False
                continue
            circle[_T, i] = moved
            circle[_CT, i] = math.cos(moved)
            circle[_ST, i] = math.sin(moved)
            if step + 1 < _NEWTON_STEPS:
                circle[_C2T, i] = math.cos(2 * moved)
                circle[_S2T, i] = math.sin(2 * moved)
    for i in range(m):
        chunk[_U, listed[i]] = circle[_CT, i]
        chunk[_V, listed[i]] = circle[_ST, i]


# error_model="numpy": division by zero gives inf or NaN (the closed form where it is not
# used) and raises nothing, which also lets that loop vectorise.
@numba.njit(nogil=True, cache=True, error_model="numpy")
def maximum_rows(a, tables, lu, lv, nz, interior, valid=None):  # pragma: no cover - compiled
    """Each pixel's maximum over the unit disk, as :func:`ptmcore.normals.ptm_maximum`.

    Parameters
    ----------
    a : ndarray, shape (R, W, 6)
        float32 or float64 coefficients, any strides.
    tables : ndarray, shape (8, S)
        The samples of the circle (:data:`_TABLES`).
    lu, lv : ndarray, shape (R, W), float32
        Out: the light direction of the maximum.
    nz : ndarray, shape (R, W), float32, or None
        Out: the normal's third component, √(1 − lu² − lv²) in float32 as
        :func:`ptmcore.normals.normals_from_ptm` had it.
    interior : ndarray, shape (R, W), bool, or None
        Out: where the maximum is the interior closed-form one.
    valid : ndarray, shape (R, W), bool, or None
        Out: where a maximum was read (the PTM not flat, lu and lv finite).
    """
    w = a.shape[1]
    n = a.shape[0] * w
    chunk = np.empty((8, _CHUNK))
    circle = np.empty((11, _CHUNK))
    best = np.empty(_CHUNK, np.int64)
    moving = np.empty(_CHUNK, np.bool_)
    inside = np.empty(_CHUNK, np.bool_)
    flat = np.empty(_CHUNK, np.bool_)
    listed = np.empty(_CHUNK, np.int64)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for p0 in range(0, n, _CHUNK):
        # Pixels p0:p0 + m of the band, row after row: a chunk may span rows, so that a band
        # of narrow rows (a list of pixels is a column) makes whole chunks too.
        m = min(_CHUNK, n - p0)
        r, col = p0 // w, p0 % w
        for j in range(m):
            for k in range(6):
                chunk[k, j] = a[r, col, k]
            col += 1
            if col == w:
                r, col = r + 1, 0
        for j in range(m):
            a0, a1, a2, a3, a4, a5 = chunk[0, j], chunk[1, j], chunk[2, j], chunk[3, j], chunk[4, j], chunk[5, j]
            # Flat (ptmcore.normals.FLAT): the maximum would be the rounding's, which differs
            # between CPUs; (0, 0) instead. NaN and inf are never flat.
            flat[j] = (abs(a0) + abs(a1) + abs(a2) + abs(a3) + abs(a4) <= FLAT * abs(a5)) & (abs(a5) < math.inf)
            # Strictly concave with the stationary point inside the disk: Malzbender et al.'s
            # closed form. Computed everywhere, as NumPy did, and kept only there.
            den = 4 * a0 * a1 - a2 * a2
            u = (a2 * a4 - 2 * a1 * a3) / den
            v = (a2 * a3 - 2 * a0 * a4) / den
            chunk[_U, j] = 0.0 if flat[j] else u
            chunk[_V, j] = 0.0 if flat[j] else v
            inside[j] = (a0 < 0) & (den > 0) & (u * u + v * v < 1.0) & (not flat[j])
        on_circle = 0
        for j in range(m):
            if not (inside[j] or flat[j]):
                listed[on_circle] = j
                on_circle += 1
        if on_circle:
            _circle_maxima(chunk, listed, on_circle, tables, circle, best, moving)
        r, col = p0 // w, p0 % w
        for j in range(m):
            u32 = np.float32(chunk[_U, j])
            v32 = np.float32(chunk[_V, j])
            lu[r, col] = u32
            lv[r, col] = v32
            if interior is not None:
                interior[r, col] = inside[j]
            if nz is not None:
                # float32, NaN kept: np.clip and np.sqrt on the float32 results.
                z = one - u32 * u32 - v32 * v32
                if z < zero:
                    z = zero
                elif z > one:
                    z = one
                nz[r, col] = np.sqrt(z)
            if valid is not None:
                valid[r, col] = not flat[j] and math.isfinite(u32) and math.isfinite(v32)
            col += 1
            if col == w:
                r, col = r + 1, 0


def _kernel_input(band: np.ndarray) -> np.ndarray:
    """The band as the kernel reads it: float32 and float64 as they are, other types (and byte
    orders) converted to float64, as the NumPy steps did for the whole map."""
    if band.dtype in (np.dtype(np.float32), np.dtype(np.float64)):
        return band
    return band.astype(np.float64)


def maximum_bands(
    coefficients: np.ndarray,
    lu: np.ndarray,
    lv: np.ndarray,
    nz: np.ndarray | None = None,
    interior: np.ndarray | None = None,
    *,
    valid: np.ndarray | None = None,
    threads: int | None = None,
) -> None:
    """Run :func:`maximum_rows` over bands of rows of ``coefficients`` (H, W, 6) in threads.

    ``lu``, ``lv`` and ``nz`` (float32) and ``interior`` and ``valid`` (bool) are (H, W)
    outputs, or views of them; ``nz``, ``interior`` and ``valid`` may be None. ``threads``:
    default, the number of CPUs.

    Raises
    ------
    ValueError
        If ``coefficients`` is not (H, W, 6) or an output is not (H, W): the kernel does not
        check its indices.
    """
    if coefficients.ndim != 3 or coefficients.shape[2] != 6:
        raise ValueError(f"PTM coefficients must be (H, W, 6), not {coefficients.shape}")
    h, w = coefficients.shape[:2]
    for out in (lu, lv, nz, interior, valid):
        if out is not None and out.shape != (h, w):
            raise ValueError(f"an output of shape {out.shape} for coefficients of shape {coefficients.shape}")

    def work(r0: int, r1: int) -> None:
        # The kernel always gets contiguous outputs, those not asked for as scratch rows rather
        # than None: numba compiles (and caches) a specialisation of its own for each
        # combination of None and memory layout, seconds each on its first use; the outputs'
        # values and a copy of them cost little beside the search. (The coefficients are read
        # where they are, whatever their strides: a copy of the map is what this avoids.)
        outputs = [(lu, np.float32), (lv, np.float32), (nz, np.float32), (interior, np.bool_), (valid, np.bool_)]
        direct = [array is not None and array[r0:r1].flags.c_contiguous for array, _ in outputs]
        rows = [array[r0:r1] if use else np.empty((r1 - r0, w), dtype) for (array, dtype), use in zip(outputs, direct)]
        maximum_rows(_kernel_input(coefficients[r0:r1]), _TABLES, *rows)
        for (array, _), row, use in zip(outputs, rows, direct):
            if array is not None and not use:
                array[r0:r1] = row

    run_bands(h, max(1, _BAND_PIXELS // max(1, w)), work, threads=threads)
