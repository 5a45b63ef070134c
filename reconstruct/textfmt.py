"""Vectorised ASCII formatting of numbers into text lines.

Formatting millions of numbers with Python's ``%`` operator costs a few hundred nanoseconds
each, which made OBJ export take tens of seconds. These functions format whole columns of
numbers with a fixed number of NumPy operations, and :func:`join` concatenates the columns
row by row into variable-width text without per-row Python work.

A :class:`Column` holds one short text per row, right-aligned in little-endian 64-bit
"lanes": viewed as bytes, row ``i`` is ``lanes[i]`` with its text in the last
``lengths[i]`` bytes and zero bytes before it. Right alignment is what digits give
naturally (the units digit sits at a fixed place), and the zero bytes let further text be
placed in front of a row with shifts and bitwise ors (see :func:`prepend`).

Numbers are written like ``'%.{decimals}f'`` and ``'%d'``: sign, integer digits without
leading zeros, a point and exactly `decimals` fraction digits, correctly rounded from the
exact binary value with ties to even, as Python does. Unlike Python, a value that rounds to
zero is written without a sign (``0.000000``, never ``-0.000000``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

__all__ = ["Column", "format_fixed", "format_int", "prepend", "join"]

_LANE = np.dtype("<u8")
_ALL_ONES = np.uint64(2**64 - 1)
_DOT = ord(".")
_MINUS = ord("-")
_MAX_DECIMALS = 7  # the point and fraction digits then fit one lane, see format_fixed

# Entry i is "%04d" % i in the first four bytes of a lane, so that two look-ups give the
# eight digits of a number below 10^8.
_DIGITS4 = np.frombuffer(b"".join(b"%04d\0\0\0\0" % i for i in range(10_000)), dtype=_LANE)
# Number of trailing "0" characters of "%04d" % i (4 for 0).
_TRAILING_ZEROS4 = np.array(
    [len(s) - len(s.rstrip("0")) for s in (f"{i:04d}" for i in range(10_000))], dtype=np.int64
)


class Column(NamedTuple):
    """One short text per row, right-aligned in little-endian 64-bit lanes.

    Attributes
    ----------
    lanes : numpy.ndarray
        ``(n, G)`` ``<u8`` array; the ``8·G`` bytes of row ``i`` end with its text and are
        zero before it.
    lengths : numpy.ndarray
        ``(n,)`` int64 text lengths in bytes.
    """

    lanes: np.ndarray
    lengths: np.ndarray


def _word(text: bytes) -> int:
    """`text` (at most 8 bytes) right-aligned in a lane, as an integer."""
    return int.from_bytes(text.rjust(8, b"\0"), "little")


def _lanes_for(n_bytes: int) -> int:
    return max(1, -(-n_bytes // 8))


def _place(lanes: np.ndarray, word: np.ndarray | int, offset: np.ndarray | int) -> None:
    """Or a right-aligned `word` into `lanes` so that its last byte is `offset` bytes
    before the end of each row (byte ``8·G − 1 − offset``).

    Lane ``j`` counted from the end covers the bytes ``8j`` to ``8j + 7`` before the end,
    so the word moves ``8j − offset`` bytes towards the end of that lane (a left shift) or
    ``offset − 8j`` bytes towards its start (a right shift); a word overlaps at most two
    lanes. With per-row offsets both shifts are applied to every lane: counts are unsigned,
    so a negative count wraps to a huge one and NumPy's shift then gives 0.
    """
    g = lanes.shape[1]
    word = np.asarray(word, dtype=_LANE)
    if isinstance(offset, (int, np.integer)):
        for j in range(g):
            left = 8 * j - int(offset)
            if 0 <= left < 8:
                lanes[:, g - 1 - j] |= word << np.uint64(8 * left)
            elif -8 < left < 0:
                lanes[:, g - 1 - j] |= word >> np.uint64(-8 * left)
        return
    bits = np.asarray(offset, dtype=np.uint64) * np.uint64(8)
    for j in range(g):
        lane_bits = np.uint64(64 * j)
        lanes[:, g - 1 - j] |= (word << (lane_bits - bits)) | (word >> (bits - lane_bits))


def _keep_last(lanes: np.ndarray, n_bytes: np.ndarray) -> None:
    """Zero all but the last `n_bytes` bytes of each row."""
    g = lanes.shape[1]
    n_bits = n_bytes * 8
    for j in range(g):
        kept = np.clip(n_bits - 64 * j, 0, 64).astype(np.uint64)
        lanes[:, g - 1 - j] &= _ALL_ONES << (np.uint64(64) - kept)


def _shift_to_end(lanes: np.ndarray, n_bytes: np.ndarray) -> None:
    """Move each row's bytes `n_bytes` (0 to 8) towards the end, dropping the last ones."""
    bits = n_bytes.astype(np.uint64) * np.uint64(8)
    carry_bits = np.uint64(64) - bits
    for i in range(lanes.shape[1] - 1, 0, -1):
        lanes[:, i] = (lanes[:, i] << bits) | (lanes[:, i - 1] >> carry_bits)
    lanes[:, 0] <<= bits


def _split4(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``divmod(values, 10^4)`` for values below 10^8, as index arrays."""
    values = values.astype(np.intp, copy=False)
    high = values // 10_000
    return high, values - high * 10_000


def _digits8(high: np.ndarray, low: np.ndarray) -> np.ndarray:
    """The eight digits (with leading zeros) of ``high·10^4 + low``, right-aligned."""
    return _DIGITS4[high] | (_DIGITS4[low] << np.uint64(32))


def _count_digits(values: np.ndarray, largest: int) -> np.ndarray:
    """Number of decimal digits of each non-negative integer (1 for 0); `largest` ≥ all."""
    count = np.ones(values.shape, dtype=np.int64)
    power = 10
    while power <= largest:
        count += values >= power
        power *= 10
    return count


def _integer_digits(magnitude: np.ndarray, offset: int, extra: int) -> tuple[np.ndarray, np.ndarray]:
    """Lanes holding the digits of `magnitude` (uint64) ending `offset` bytes before the
    end, with room for `extra` more bytes in front; and the digit counts.

    The bytes in front of the digits are left as "0" characters for the caller to clear.
    """
    largest = int(magnitude.max())
    n_digits = _count_digits(magnitude, largest)
    lanes = np.zeros((len(magnitude), _lanes_for(len(str(largest)) + offset + extra)), _LANE)
    rest = magnitude
    group = 0
    while True:
        # Groups of eight digits, from the units up; uint32 arithmetic for the last group.
        if largest < 10**8:
            _place(lanes, _digits8(*_split4(rest)), offset + 8 * group)
            break
        below = rest % np.uint64(10**8)
        _place(lanes, _digits8(*_split4(below)), offset + 8 * group)
        rest = rest // np.uint64(10**8)
        largest //= 10**8
        group += 1
    return lanes, n_digits


def _rounded_fraction(fraction: np.ndarray, scale: float, exact_product: bool) -> np.ndarray:
    """``round(fraction·scale)`` of float64 values in [0, 1), ties to even, computed from the
    exact product even where ``fraction·scale`` rounds in floating point."""
    product = fraction * scale
    if exact_product:
        return np.rint(product)
    # Dekker's exact product: product + error == fraction·scale exactly (no FMA in NumPy).
    split = 134217729.0  # 2^27 + 1
    c = split * scale
    scale_high = c - (c - scale)
    scale_low = scale - scale_high
    c = split * fraction
    high = c - (c - fraction)
    low = fraction - high
    error = ((high * scale_high - product) + high * scale_low + low * scale_high) + low * scale_low
    whole = np.floor(product)
    # product − whole is exact, and so is its difference from 0.5 whenever it could matter
    # (it is then at least 0.25): comparing it with −error compares the exact product's
    # fraction with one half.
    above_half = (product - whole) - 0.5
    up = (above_half > -error) | ((above_half == -error) & (np.fmod(whole, 2.0) == 1.0))
    return whole + up


def _values(values: np.ndarray, kinds: str, what: str) -> np.ndarray:
    values = np.asarray(values)
    if values.ndim != 1:
        raise ValueError(f"{what} formats a 1-D array, not shape {values.shape}")
    if values.dtype.kind not in kinds:
        raise TypeError(f"{what} cannot format {values.dtype} values")
    return values


def _check_prefix(prefix: bytes) -> bytes:
    prefix = bytes(prefix)
    if len(prefix) > 7:
        raise ValueError(f"a prefix has at most 7 bytes, not {prefix!r}")
    return prefix


def format_fixed(
    values: np.ndarray, decimals: int, *, trim: bool = False, prefix: bytes = b""
) -> Column:
    """Format floating-point numbers like ``prefix + '%.{decimals}f' % value``.

    Parameters
    ----------
    values : numpy.ndarray
        1-D array of finite floating-point numbers of magnitude below 2⁶³.
    decimals : int
        Fraction digits, 0 to 7.
    trim : bool
        Drop trailing zeros of the fraction, and the point if nothing is left after it
        (``1.5`` rather than ``1.500000``, ``2`` rather than ``2.000000``).
    prefix : bytes
        At most 7 bytes written in front of each number (before its sign).

    Returns
    -------
    Column
        The texts. Rounding is correct for the exact binary value, ties to even, exactly
        as Python's formatting; a value that rounds to zero has no minus sign.

    Raises
    ------
    ValueError
        For NaN or infinity, magnitudes of 2⁶³ or more, `decimals` outside 0 to 7, a
        prefix longer than 7 bytes or an array that is not 1-D.
    TypeError
        For values that are not floating point.
    """
    values = _values(values, "f", "format_fixed")
    prefix = _check_prefix(prefix)
    if not (isinstance(decimals, (int, np.integer)) and 0 <= decimals <= _MAX_DECIMALS):
        raise ValueError(f"decimals must be an integer from 0 to {_MAX_DECIMALS}, not {decimals!r}")
    decimals = int(decimals)
    if len(values) == 0:
        return Column(np.zeros((0, 1), _LANE), np.zeros(0, np.int64))
    if not np.isfinite(values).all():
        raise ValueError("cannot format NaN or infinity")
    magnitude = np.abs(values).astype(np.float64)
    if magnitude.max() >= 2.0**63:
        raise ValueError("cannot format magnitudes of 2**63 or more")

    if decimals:
        whole = np.floor(magnitude)
        scale = 10**decimals
        # For float16/32 values the fraction has at most 24 significant bits and
        # 10^decimals at most 17 odd bits, so their float64 product is exact.
        fraction = _rounded_fraction(magnitude - whole, float(scale), values.dtype.itemsize <= 4)
        carry = fraction == scale
        whole += carry
        fraction[carry] = 0
    else:
        # Ties go to the even integer, which the fraction alone cannot tell.
        whole = np.rint(magnitude)
        fraction = np.zeros_like(whole)
    integer = whole.astype(np.uint64)
    negative = (values < 0) & ((integer > 0) | (fraction > 0))

    point_and_fraction = decimals + 1 if decimals else 0
    lanes, n_digits = _integer_digits(integer, point_and_fraction, len(prefix) + 1)
    lengths = n_digits + point_and_fraction
    if decimals:
        high, low = _split4(fraction.astype(np.uint32))
        # The last `decimals` of the eight digits, preceded by the point.
        text = _digits8(high, low) & (_ALL_ONES << np.uint64(64 - 8 * decimals))
        text |= np.uint64(_DOT << (56 - 8 * decimals))
        _place(lanes, text, 0)
    _keep_last(lanes, lengths)
    if trim and decimals:
        zeros = _TRAILING_ZEROS4[low]
        zeros += (low == 0) * _TRAILING_ZEROS4[high]
        np.minimum(zeros, decimals, out=zeros)
        dropped = zeros + (zeros == decimals)  # the point goes with the last digit
        _shift_to_end(lanes, dropped)
        lengths -= dropped
    return _prepend_sign(Column(lanes, lengths), negative, prefix)


def format_int(values: np.ndarray, *, prefix: bytes = b"") -> Column:
    """Format integers like ``prefix + '%d' % value``.

    Parameters
    ----------
    values : numpy.ndarray
        1-D array of integers (any NumPy integer type).
    prefix : bytes
        At most 7 bytes written in front of each number (before its sign).

    Returns
    -------
    Column
        The texts.

    Raises
    ------
    ValueError
        For a prefix longer than 7 bytes or an array that is not 1-D.
    TypeError
        For values that are not integers.
    """
    values = _values(values, "iu", "format_int")
    prefix = _check_prefix(prefix)
    if len(values) == 0:
        return Column(np.zeros((0, 1), _LANE), np.zeros(0, np.int64))
    if values.dtype.kind == "u":
        magnitude = values.astype(np.uint64)
        negative = None
    else:
        magnitude = values.astype(np.int64).view(np.uint64)
        negative = values < 0
        # Two's complement: −v as uint64 is the magnitude, also for the most negative int64.
        np.negative(magnitude, out=magnitude, where=negative)
    lanes, n_digits = _integer_digits(magnitude, 0, len(prefix) + 1)
    _keep_last(lanes, n_digits)
    return _prepend_sign(Column(lanes, n_digits), negative, prefix)


def _prepend_sign(column: Column, negative: np.ndarray | None, prefix: bytes) -> Column:
    """`prefix`, then a minus sign where `negative`, in front of each text; in place when
    the lanes have room."""
    if negative is None or not negative.any():
        if not prefix:
            return column
        return _prepend_words(column, _word(prefix), len(prefix), in_place=True)
    words = np.where(negative, _word(prefix + b"-"), _word(prefix)).astype(_LANE)
    return _prepend_words(column, words, len(prefix) + negative, in_place=True)


def prepend(prefix: bytes, column: Column) -> Column:
    """Write `prefix` (at most 8 bytes) in front of every text of `column`.

    Parameters
    ----------
    prefix : bytes
        The bytes to add.
    column : Column
        The texts; not modified.

    Returns
    -------
    Column
        The longer texts.
    """
    prefix = bytes(prefix)
    if len(prefix) > 8:
        raise ValueError(f"prepend adds at most 8 bytes, not {prefix!r}")
    if not prefix:
        return column
    return _prepend_words(column, _word(prefix), len(prefix), in_place=False)


def _prepend_words(
    column: Column, words: np.ndarray | int, n_bytes: np.ndarray | int, *, in_place: bool
) -> Column:
    """Place right-aligned `words` of `n_bytes` bytes in front of the texts; into
    `column`'s own lanes if `in_place` and they have room."""
    lanes, lengths = column
    new_lengths = lengths + n_bytes
    g = _lanes_for(int(new_lengths.max()) if len(new_lengths) else 0)
    if not in_place or g > lanes.shape[1]:
        grown = np.zeros((len(lanes), max(g, lanes.shape[1])), _LANE)
        grown[:, grown.shape[1] - lanes.shape[1] :] = lanes
        lanes = grown
    _place(lanes, words, lengths)
    return Column(lanes, new_lengths)


def join(columns: Sequence[Column]) -> memoryview:
    """Concatenate the texts of the columns row by row: row 0 of every column, then row 1…

    Parameters
    ----------
    columns : sequence of Column
        Columns with the same number of rows.

    Returns
    -------
    memoryview
        The text, ready for a binary file's ``write``.

    Notes
    -----
    Each text is copied with one unaligned store of the widest column's lane width that
    ends where the text ends; the bytes it writes in front of the text are overwritten by
    the texts before it, so the stores go from the last text to the first. That order is
    the order of one NumPy fancy assignment with contiguous index and value arrays.
    """
    n = len(columns[0].lengths)
    if any(len(c.lengths) != n for c in columns):
        raise ValueError("columns must have the same number of rows")
    if n == 0:
        return memoryview(b"")
    g = max(c.lanes.shape[1] for c in columns)
    width = 8 * g
    record = np.dtype((np.void, width))
    # Laid out last text first, so that plain contiguous arrays give the reverse order.
    lanes = np.empty((n, len(columns), g), _LANE)
    lengths = np.empty((n, len(columns)), np.int64)
    lanes_backwards = lanes[::-1, ::-1]
    lengths_backwards = lengths[::-1, ::-1]
    for p, (column_lanes, column_lengths) in enumerate(columns):
        # Lanes in front of a narrower column stay uninitialised: they are stored in front
        # of its text, where only bytes that are overwritten later go.
        lanes_backwards[:, p, g - column_lanes.shape[1] :] = column_lanes
        lengths_backwards[:, p] = column_lengths
    lengths = lengths.reshape(-1)
    done = np.cumsum(lengths)
    total = int(done[-1])
    ends = total - done
    ends += lengths
    # Text byte k is buffer byte width + k, so the store for a text ending at byte e starts
    # at buffer byte e, and the first text's leading bytes land in the spare first width.
    buffer = np.empty(width + total, np.uint8)
    windows = np.ndarray((total + 1,), dtype=record, buffer=buffer, strides=(1,))
    windows[ends] = lanes.view(record).reshape(-1)
    return memoryview(buffer)[width:]
