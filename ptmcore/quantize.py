"""Compiled quantisation passes: HP's ``.ptm`` bytes and OpenLIME's planes, each value read once.

Writing a 24-megapixel PTM in NumPy took seconds of element-wise passes: the per-coefficient
minimum and maximum (two reductions over the whole array), the float64 encoding and, for the
error report, as many float64 temporaries again. Here numba kernels read each coefficient once
per pass, with no temporaries: running results (minimum, maximum, error statistics) are kept per
position of a short block of a row, so that the loops vectorise and those arrays stay in the L1
cache:

* :func:`coefficient_range` — the per-coefficient minimum and maximum, in one pass;
* :func:`encode_ptm` — HP's bytes, ``floor(v/scale + (bias + 0.5))`` clamped to 0..255 in
  float64, in the order of the file (bottom row first), fused with the error report of
  :func:`ptmcore.ptmfile.write_ptm` (max |error|, Σ error², clamped values);
* :func:`lrgb_plane_codes` — OpenLIME's coefficient planes, ``rint((a − lo) · step)`` clipped to
  0..255 in float32 (:func:`reconstruct.report.web.lrgb_planes`).

Each value goes through the same operations, in the same order and precision, as in the NumPy
code they replace: numba neither reassociates nor contracts a product and a sum into a fused
multiply-add without ``fastmath``, which is not used here, so every byte is the NumPy code's
(``tests/test_quantize_kernel.py``; HP's fixture in ``tests/test_ptmfile.py``). Only the sums of
squared errors are added in another order (per band, then the bands in order), which moves the
reported RMS in its last digits and never depends on the threads' timing.

The kernels release the GIL (``nogil``) and run on bands of rows in the caller's threads, so the
work spreads over the cores without numba's threading layer; :func:`encode_ptm` hands the bands
to its caller in file order, so the file is written while the next bands are encoded.

Arrays of float32 or float64 (native byte order) are read as they are; other numbers are
converted to float64 a band at a time (exactly, for integers up to 2^53), which is what the
NumPy code did before quantising. Importing this module imports numba (about half a second), so
:mod:`ptmcore.ptmfile` and :mod:`reconstruct.report.web` import it only when they need it.
Compiled code is cached on disk (``cache=True``), so only the first run after installation pays
for compilation.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import numba
import numpy as np

from .resources import thread_count

__all__ = ["coefficient_range", "encode_ptm", "lrgb_plane_codes"]

#: Coefficient values per band of rows: a band's float32 values (8 MiB) and codes (2 MiB) are
#: small next to a 24-megapixel PTM, yet a band is long enough that the threads' hand-offs cost
#: nothing measurable.
_BAND_VALUES = 1 << 21

#: Values per block of a row. The kernels walk a row's values in order, block by block, and
#: keep per-position running results (minimum, maximum, error statistics) for one block: the
#: loops then have no dependency from one value to the next, so the compiler vectorises them,
#: and the block's arrays stay in the L1 cache. A multiple of 6, so position ``j`` of a block
#: always holds coefficient ``j % 6`` (rows of (W, 6) and of (W, 3, 6) values alike).
_BLOCK = 384

#: Rows of the error statistics :func:`encode_ptm` returns: max |error|, Σ error², clamped values.
_MAX, _SQ, _CLIPPED = range(3)


# ---------------------------------------------------------------------------------------------
# Kernels


@numba.njit(nogil=True, cache=True)
def _range_rows(values, lo, hi, bad):  # pragma: no cover - compiled
    """Per-position minimum and maximum of rows ``values`` (rows, m), ``m`` a multiple of 6,
    folded into ``lo``, ``hi`` (:data:`_BLOCK`,) of the values' type; ``bad`` (:data:`_BLOCK`,)
    becomes NaN where a value is NaN or infinite (``v − v``), which no comparison would tell."""
    n, m = values.shape
    for r in range(n):
        row = values[r]
        for j0 in range(0, m, _BLOCK):
            # A slice per block: indices that start at 0 are known not to be negative, so the
            # loads and stores are plain vector ones (j0 + j would need numba's wraparound).
            block = row[j0 : j0 + _BLOCK]
            for j in range(block.shape[0]):
                v = block[j]
                if v < lo[j]:
                    lo[j] = v
                if v > hi[j]:
                    hi[j] = v
                bad[j] += v - v


@numba.njit(nogil=True, cache=True)
def _encode_rows(values, recip, scale, bias, half, out, worst, sq, clipped):  # pragma: no cover - compiled
    """HP's bytes of rows ``values`` (rows, m) into ``out`` (rows, m) uint8, rows in reverse
    order (the file's), and the error statistics per position of a block.

    The arithmetic is :func:`ptmcore.ptmfile._encode`'s and ``_ErrorStats``' in float64, in
    their order: the byte is ``floor(v/scale + (bias + 0.5))`` clamped to 0..255; the error
    ``(byte − bias)·scale − v``; a value is clamped when ``v/scale + bias + 0.5`` is outside
    [0, 256). ``scale``, ``bias`` (as float64) and ``half`` (``bias + 0.5``) hold the pattern of
    a block, (:data:`_BLOCK`,). ``recip``, the scales' reciprocals, replaces the division by a
    product: the caller passes it only when every scale is a power of two whose reciprocal is a
    float64, and then ``v · (1/scale)`` and ``v / scale`` round the same real number, so they are
    the same float; None divides.

    ``worst``, ``sq`` and ``clipped`` (:data:`_BLOCK`,) accumulate max |error|, Σ error² and the
    count of clamped values per position.
    """
    n, m = values.shape
    for i in range(n):
        row = values[n - 1 - i]
        dst = out[i]
        for j0 in range(0, m, _BLOCK):
            block = row[j0 : j0 + _BLOCK]
            codes = dst[j0 : j0 + _BLOCK]
            for j in range(block.shape[0]):
                v = np.float64(block[j])
                if recip is None:
                    d = v / scale[j]
                else:
                    d = v * recip[j]
                q = np.floor(d + half[j])
                # No NaN reaches here (the caller checks), so the clamp needs no NaN rule.
                q = min(max(q, 0.0), 255.0)
                codes[j] = np.uint8(q)
                e = (q - bias[j]) * scale[j] - v
                if abs(e) > worst[j]:
                    worst[j] = abs(e)
                sq[j] += e * e
                exact = d + bias[j] + 0.5
                if exact < 0.0 or exact >= 256.0:
                    clipped[j] += 1.0


@numba.njit(nogil=True, cache=True)
def _plane_rows(coef, terms, lo, step, out):  # pragma: no cover - compiled
    """OpenLIME's coefficient planes of ``coef`` (rows, W, 6): channel ``c`` of plane ``p``,
    ``out[p]`` (rows, W, 3), is ``rint((a_k − lo) · step)`` clipped to 0..255 with
    ``k = terms[p, c]``, in float32 as :func:`reconstruct.report.web.lrgb_planes` computed it."""
    for r in range(coef.shape[0]):
        src = coef[r]
        for p in range(terms.shape[0]):
            dst = out[p][r]
            for c in range(3):
                # One channel along the row at a time (the row stays in the cache), with its
                # coefficient, offset and step in registers.
                k = terms[p, c]
                offset = lo[p, c]
                scale = step[p, c]
                for x in range(src.shape[0]):
                    q = np.rint((np.float32(src[x, k]) - offset) * scale)
                    dst[x, c] = np.uint8(min(max(q, np.float32(0.0)), np.float32(255.0)))


# ---------------------------------------------------------------------------------------------
# Bands and threads


def _kernel_input(values: np.ndarray, other: type = np.float64) -> np.ndarray:
    """``values`` as the kernels read them: float32 or float64 in native order as they are,
    anything else converted to ``other`` (the type the NumPy code converted them to)."""
    if values.dtype == np.float32 or values.dtype == np.float64:  # False for non-native order
        return values
    return values.astype(other)


def _rows(values: np.ndarray) -> np.ndarray:
    """Values (rows, ...) as the kernels' C-contiguous rows (rows, m): a view when they are
    contiguous, else a copy of the band (one compiled layout, and plain vector loads)."""
    return np.ascontiguousarray(_kernel_input(values)).reshape(values.shape[0], -1)


def _rows_per_band(values: np.ndarray) -> int:
    """Rows of ``values`` (H, W, ...) per band: about :data:`_BAND_VALUES` values."""
    per_row = max(1, values[:1].size)
    return max(1, _BAND_VALUES // per_row)


def _bands(height: int, rows: int) -> list[tuple[int, int]]:
    return [(r0, min(height, r0 + rows)) for r0 in range(0, height, rows)]


def _workers(threads: int | None, tasks: int) -> int:
    return max(1, min(tasks, thread_count(threads)))


def _per_coefficient(block: np.ndarray) -> np.ndarray:
    """A block's per-position values (..., :data:`_BLOCK`) as (..., _BLOCK / 6, 6)."""
    return block.reshape(block.shape[:-1] + (_BLOCK // 6, 6))


def _as_4d(values: np.ndarray) -> np.ndarray:
    """(H, W, 6) LRGB or (H, W, 3, 6) RGB-format coefficients as (H, W, C, 6) (a view)."""
    values = np.asarray(values)
    if values.ndim == 3:
        values = values[:, :, None, :]
    if values.ndim != 4 or values.shape[3] != 6:
        raise ValueError(f"coefficients must be (H, W, 6) or (H, W, 3, 6), not {values.shape}")
    return values


def coefficient_range(values: np.ndarray, *, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-coefficient minimum and maximum, in one pass over the values.

    Parameters
    ----------
    values : ndarray, shape (H, W, 6) or (H, W, 3, 6)
        LRGB or RGB-format PTM coefficients (the RGB format's range is over the three channels).
    threads : int, optional
        Threads for bands of rows; default: the number of CPUs.

    Returns
    -------
    lo, hi : ndarray, shape (6,), float64
        The minimum and maximum of each coefficient, exactly (every float32 is a float64);
        NaN for a coefficient with a NaN or infinite value, so that a caller's finiteness
        check catches both.
    """
    v = _as_4d(values)
    if v.size == 0:
        raise ValueError("coefficients hold no values")
    bands = _bands(v.shape[0], _rows_per_band(v))

    def one(band: tuple[int, int]) -> np.ndarray:
        rows = _rows(v[band[0] : band[1]])
        # In the values' own type: a float32 minimum is the float64 one, at twice the lanes.
        lo = np.full(_BLOCK, np.inf, dtype=rows.dtype)
        hi = np.full(_BLOCK, -np.inf, dtype=rows.dtype)
        bad = np.zeros(_BLOCK, dtype=rows.dtype)
        _range_rows(rows, lo, hi, bad)
        return np.stack(
            [
                _per_coefficient(lo).min(axis=0),
                _per_coefficient(hi).max(axis=0),
                np.isnan(_per_coefficient(bad)).any(axis=0),
            ]
        ).astype(np.float64)

    workers = _workers(threads, len(bands))
    if workers == 1:
        parts = [one(b) for b in bands]
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            parts = list(pool.map(one, bands))
    lo = np.min([p[0] for p in parts], axis=0)
    hi = np.max([p[1] for p in parts], axis=0)
    # NaN, or ±inf (which lo or hi then shows already): NaN fails every finiteness check.
    bad = np.any([p[2] > 0 for p in parts], axis=0)
    lo[bad] = np.nan
    hi[bad] = np.nan
    return lo, hi


def encode_ptm(
    values: np.ndarray,
    scale: np.ndarray,
    bias: np.ndarray,
    write: Callable[[np.ndarray], object],
    *,
    threads: int | None = None,
) -> np.ndarray:
    """HP's bytes of a PTM's coefficients in file order, handed to ``write`` band by band.

    The bands are encoded in threads, a few ahead of the one being written, and passed to
    ``write`` in the calling thread in file order: for each channel (one for LRGB, R, G, B
    for the RGB format) the rows from the bottom up, a pixel's six codes together.

    Parameters
    ----------
    values : ndarray, shape (H, W, 6) or (H, W, 3, 6)
        The coefficients, row 0 at the top.
    scale : ndarray, shape (6,)
        HP's scales (:func:`ptmcore.ptmfile.quantization_parameters`).
    bias : ndarray, shape (6,)
        HP's integer biases.
    write : callable
        Called with each band's codes, a C-contiguous uint8 array (rows, W, 6); it may keep
        the array.
    threads : int, optional
        Threads that encode; default: the number of CPUs.

    Returns
    -------
    ndarray, shape (3, 6), float64
        Per coefficient: the largest absolute error of the decoded value ``(code − bias)·scale``
        against the input, the sum of the squared errors, and the number of values clamped to
        0..255 (a value is clamped when ``v/scale + bias + 0.5`` is outside [0, 256)).
    """
    v = _as_4d(values)
    h, w, channels = v.shape[:3]
    s = np.asarray(scale, dtype=np.float64).reshape(-1)
    b = np.asarray(bias).reshape(-1)
    if s.shape != (6,) or b.shape != (6,):
        raise ValueError("scale and bias must hold six numbers each")
    repeat = _BLOCK // 6
    scale_pattern = np.tile(s, repeat)
    bias_pattern = np.tile(b.astype(np.float64), repeat)
    half_pattern = np.tile((b + 0.5).astype(np.float64), repeat)  # as _encode: bias + 0.5, then added
    recip = 1.0 / s
    exact = np.all(np.frexp(s)[0] == 0.5) and np.all(np.isfinite(recip)) and np.all(recip * s == 1.0)
    recip_pattern = np.tile(recip, repeat) if exact else None
    rows = _rows_per_band(v[:, :, :1])
    # The file's order: each channel's rows from the bottom band up.
    tasks = [(ch, r0, r1) for ch in range(channels) for r0, r1 in reversed(_bands(h, rows))]

    def one(task: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        ch, r0, r1 = task
        # One channel of the RGB format is not contiguous: it is copied, a band at a time.
        band = _rows(v[r0:r1, :, ch, :])
        codes = np.empty(band.shape, dtype=np.uint8)
        acc = np.zeros((3, _BLOCK))
        _encode_rows(band, recip_pattern, scale_pattern, bias_pattern, half_pattern, codes,
                     acc[_MAX], acc[_SQ], acc[_CLIPPED])
        per = _per_coefficient(acc)
        stats = np.stack([per[_MAX].max(axis=0), per[_SQ].sum(axis=0), per[_CLIPPED].sum(axis=0)])
        return codes.reshape(r1 - r0, w, 6), stats

    parts: list[np.ndarray] = []
    workers = _workers(threads, len(tasks))
    if workers == 1:
        for task in tasks:
            codes, stats = one(task)
            write(codes)
            parts.append(stats)
    else:
        # A band or two ahead per thread keeps every thread busy while the caller writes,
        # and bounds the memory held to a few bands.
        ahead = 2 * workers
        pending: deque[Future] = deque()
        with ThreadPoolExecutor(max_workers=workers) as pool:
            try:
                for task in tasks:
                    pending.append(pool.submit(one, task))
                    if len(pending) > ahead:
                        codes, stats = pending.popleft().result()
                        write(codes)
                        parts.append(stats)
                while pending:
                    codes, stats = pending.popleft().result()
                    write(codes)
                    parts.append(stats)
            finally:
                for f in pending:  # after an error: do not encode what will not be written
                    f.cancel()
    total = np.zeros((3, 6))
    for stats in parts:  # in file order, so the sums do not depend on the threads' timing
        np.maximum(total[_MAX], stats[_MAX], out=total[_MAX])
        total[_SQ] += stats[_SQ]
        total[_CLIPPED] += stats[_CLIPPED]
    return total


def lrgb_plane_codes(
    coefficients: np.ndarray,
    terms: tuple[tuple[int, int, int], ...],
    lo: np.ndarray,
    step: np.ndarray,
    *,
    threads: int | None = None,
) -> list[np.ndarray]:
    """Coefficient planes of OpenLIME's LRGB layout, in one pass over the coefficients.

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6)
        a0..a5.
    terms : tuple of tuples of 3 int
        Per plane, the coefficient of each channel.
    lo, step : ndarray, shape (planes, 3)
        Per channel, the offset and the step, as float32: the byte is
        ``rint((float32(a) − lo) · step)`` clipped to 0..255, in float32.
    threads : int, optional
        Threads for bands of rows; default: the number of CPUs.

    Returns
    -------
    list of ndarray
        One C-contiguous ``(H, W, 3)`` uint8 image per plane.
    """
    coef = np.asarray(coefficients)
    if coef.ndim != 3 or coef.shape[2] != 6:
        raise ValueError(f"coefficients must be (H, W, 6), not {coef.shape}")
    t = np.asarray(terms, dtype=np.int64).reshape(-1, 3)
    if t.shape[0] == 0 or t.min() < 0 or t.max() > 5:
        raise ValueError(f"terms {terms} are not planes of coefficients a0..a5")
    lo32 = np.ascontiguousarray(lo, dtype=np.float32).reshape(t.shape)
    step32 = np.ascontiguousarray(step, dtype=np.float32).reshape(t.shape)
    h, w = coef.shape[:2]
    out = [np.empty((h, w, 3), dtype=np.uint8) for _ in range(t.shape[0])]

    def one(band: tuple[int, int]) -> None:
        r0, r1 = band
        views = tuple(plane[r0:r1] for plane in out)
        _plane_rows(np.ascontiguousarray(_kernel_input(coef[r0:r1], np.float32)), t, lo32, step32, views)

    bands = _bands(h, _rows_per_band(coef))
    workers = _workers(threads, len(bands))
    if workers == 1:
        for band in bands:
            one(band)
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(one, bands))
    return out
