"""The text of OBJ lines, written by compiled kernels straight into byte buffers.

An OBJ of a 24-megapixel capture's mesh is 590 MB of text. Formatting it with Python's ``%``
costs a few hundred nanoseconds a number (tens of seconds); whole NumPy columns of table
look-ups (this module's predecessor, ``textfmt``) took 0.55 s of CPU for the 318 MB of a
6-megapixel capture. These numba kernels write each line's bytes in one pass, two digits per
table look-up (about 1 ns a byte: 0.28 s for the same file, identical bytes), and release the
GIL, so chunks are formatted in parallel threads.

Numbers are written as Python's ``'%.6f'`` writes them, correctly rounded from the exact
binary value with ties to even, then without trailing zeros (``0.05``, ``-12.345678``, ``1``)
and never as ``-0``. Exactness is cheap for float32, the type of every array of a
:class:`reconstruct.mesh.grid.GridMesh`: ``x · 10⁶`` needs at most 24 + 14 significant bits,
so it is exact in float64, and rounding it to an integer rounds the exact value.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["DECIMALS", "LIMIT", "face_lines", "number_lines"]

#: Fraction digits of the numbers (before trailing zeros are dropped): 1 nm in millimetres.
DECIMALS = 6
_SCALE = 10.0**DECIMALS
#: Numbers must be smaller than this in magnitude (their scaled value fits in 63 bits).
LIMIT = float(2**63 // 10**DECIMALS)
# Bytes of one number at most: separator, sign, 13 integer digits, point, 6 digits.
_NUMBER_BYTES = 22
# Bytes of one face corner at most: separator and up to three indices of 19 digits with slashes.
_CORNER_BYTES = 1 + 3 * 20


# "00" … "99": two digits per look-up and division.
_PAIRS = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode(), np.uint8)


@numba.njit(nogil=True, cache=True, inline="always")
def _put_uint(out, pos, v):  # pragma: no cover - compiled
    """Write the decimal digits of ``v`` ≥ 0 at ``out[pos:]``; return the new position."""
    n = 1
    t = v
    while t >= 100:
        n += 2
        t //= 100
    if t >= 10:
        n += 1
    end = pos + n
    p = end
    while v >= 100:
        r = v % 100
        v //= 100
        out[p - 1] = _PAIRS[2 * r + 1]
        out[p - 2] = _PAIRS[2 * r]
        p -= 2
    if v >= 10:
        out[p - 1] = _PAIRS[2 * v + 1]
        out[p - 2] = _PAIRS[2 * v]
    else:
        out[p - 1] = 48 + v
    return end


@numba.njit(nogil=True, cache=True)
def _numbers(values, keyword, out):  # pragma: no cover - compiled
    """Lines ``keyword x y …`` of the rows of ``values`` (float32, (n, k)) into ``out``;
    return the bytes written, or -1 at a NaN, an infinity or a number beyond :data:`LIMIT`."""
    pos = 0
    n, k = values.shape
    for i in range(n):
        for b in keyword:
            out[pos] = b
            pos += 1
        for j in range(k):
            x = np.float64(values[i, j])
            if not abs(x) < LIMIT:  # NaN too
                return -1
            q = np.int64(np.rint(x * _SCALE))  # exact: see the module's docstring
            out[pos] = 32
            pos += 1
            if q < 0:
                out[pos] = 45
                pos += 1
                q = -q
            pos = _put_uint(out, pos, q // 1000000)
            frac = q % 1000000
            if frac:
                # All six digits, then the trailing zeros dropped.
                out[pos] = 46
                for d in range(3):
                    r = frac % 100
                    frac //= 100
                    out[pos + 6 - 2 * d] = _PAIRS[2 * r + 1]
                    out[pos + 5 - 2 * d] = _PAIRS[2 * r]
                pos += 7
                while out[pos - 1] == 48:
                    pos -= 1
    return pos


@numba.njit(nogil=True, cache=True)
def _faces(faces, per_corner, out):  # pragma: no cover - compiled
    """Lines ``\\nf a/a/a b/b/b c/c/c`` (``per_corner`` indices a corner, counted from 1)."""
    pos = 0
    for i in range(faces.shape[0]):
        out[pos] = 10
        out[pos + 1] = 102
        pos += 2
        for c in range(faces.shape[1]):
            out[pos] = 32
            start = pos + 1
            end = _put_uint(out, start, np.int64(faces[i, c]) + 1)
            pos = end
            for _ in range(per_corner - 1):  # "/" and the same digits again
                out[pos] = 47
                for b in range(start, end):
                    out[pos + 1 + b - start] = out[b]
                pos += 1 + end - start
    return pos


def number_lines(values: np.ndarray, keyword: bytes) -> memoryview:
    """``\\n{keyword} x y …`` for each row of ``values``, each line starting with its newline.

    Parameters
    ----------
    values : ndarray (n, k), float32
    keyword : bytes
        ``b"v"``, ``b"vt"``, ``b"vn"``.

    Raises
    ------
    ValueError
        For NaN or infinite values, or magnitudes of :data:`LIMIT` or more.
    TypeError
        For values that are not float32.
    """
    if values.dtype != np.float32 or values.ndim != 2:
        raise TypeError(f"values must be a 2-D float32 array, not {values.dtype} {values.shape}")
    prefix = np.frombuffer(b"\n" + keyword, np.uint8)
    out = np.empty(len(values) * (len(prefix) + values.shape[1] * _NUMBER_BYTES), np.uint8)
    used = _numbers(np.ascontiguousarray(values), prefix, out)
    if used < 0:
        raise ValueError(f"cannot write NaN, infinity or magnitudes of {LIMIT:.3g} or more in an OBJ file")
    return memoryview(out)[:used]


def face_lines(faces: np.ndarray, per_corner: int) -> memoryview:
    """``\\nf a/a/a b/b/b c/c/c`` for each face (``per_corner`` 1 to 3 indices per corner:
    vertex, UV and normal share their index, which OBJ counts from 1).

    Parameters
    ----------
    faces : ndarray (n, 3), integer, ≥ 0
    per_corner : int
    """
    if not 1 <= per_corner <= 3:
        raise ValueError(f"per_corner must be 1, 2 or 3, not {per_corner}")
    out = np.empty(len(faces) * (2 + faces.shape[1] * _CORNER_BYTES), np.uint8)
    used = _faces(np.ascontiguousarray(faces), per_corner, out)
    return memoryview(out)[:used]
