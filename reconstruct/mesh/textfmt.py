"""Vectorised ASCII formatting of numbers into text lines.

Formatting millions of numbers with Python's ``%`` operator costs a few hundred nanoseconds
each, which made OBJ export take tens of seconds. These functions format whole columns of
numbers with a few NumPy operations each, and :func:`join` concatenates the columns row by
row into variable-width text without per-row Python work. OBJ export with them is 26×
faster than trimesh's on a 4 M-vertex mesh (6× NumPy's ``%``), BENCHMARKS.md.

A :class:`Column` holds one short text per row, right-aligned in little-endian 64-bit
"lanes": viewed as bytes, row ``i`` is ``lanes[i]`` with its text in the last
``lengths[i]`` bytes and zero bytes before it. Most of the text comes from look-up tables
(a prefix, the sign and up to four integer digits in one entry; the point and the fraction
digits in another), so that a number costs a few table look-ups and shifts.

Numbers are written like ``'%.{decimals}f'`` and ``'%d'``: sign, integer digits without
leading zeros, a point and exactly `decimals` fraction digits, correctly rounded from the
exact binary value with ties to even, as Python does. Unlike Python, a value that rounds to
zero is written without a sign (``0.000000``, never ``-0.000000``).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

__all__ = ["Column", "format_fixed", "format_int", "literal", "concat", "take", "join"]

_LANE = np.dtype("<u8")
_MAX_DECIMALS = 6  # the fraction table then has at most 10^6 entries (9 MB)
_MAX_PREFIX = 6  # leaves room for the sign and at least one digit in a table entry


class Column(NamedTuple):
    """One short text per row, right-aligned in little-endian 64-bit lanes.

    Attributes
    ----------
    lanes : numpy.ndarray
        ``(n, G)`` ``<u8`` array; the ``8·G`` bytes of row ``i`` end with its text and are
        zero before it.
    lengths : numpy.ndarray
        ``(n,)`` integer text lengths in bytes.
    """

    lanes: np.ndarray
    lengths: np.ndarray


def _n_lanes(n_bytes: int) -> int:
    return max(1, -(-n_bytes // 8))


def _words(texts: Sequence[bytes]) -> np.ndarray:
    """Texts of at most 8 bytes, each right-aligned in a lane (read-only)."""
    return np.frombuffer(b"".join(t.rjust(8, b"\0") for t in texts), dtype=_LANE)


def _read_only(array: np.ndarray) -> np.ndarray:
    """`array`, protected: the cached tables are shared by all calls and threads."""
    array.flags.writeable = False
    return array


@functools.cache
def _head_table(prefix: bytes, digits: int) -> tuple[np.ndarray, np.ndarray]:
    """Entry ``i + 10^digits·negative``: `prefix`, a minus if negative, then ``str(i)``."""
    texts = [prefix + sign + b"%d" % i for sign in (b"", b"-") for i in range(10**digits)]
    return _words(texts), _read_only(np.array([len(t) for t in texts], dtype=np.int64))


@functools.cache
def _group_table(digits: int) -> np.ndarray:
    """Entry ``i``: ``i`` with `digits` digits, leading zeros included."""
    return _words([b"%0*d" % (digits, i) for i in range(10**digits)])


@functools.cache
def _fraction_table(decimals: int, trim: bool) -> tuple[np.ndarray, np.ndarray]:
    """Entry ``i``: the point and ``i`` as `decimals` fraction digits, optionally without
    trailing zeros (and then without the point for 0)."""
    fraction = np.arange(10**decimals, dtype=np.int64)
    text = np.full(len(fraction), ord(".") << (56 - 8 * decimals), dtype=_LANE)
    for k in range(decimals):
        digit = (fraction // 10 ** (decimals - 1 - k)) % 10 + ord("0")
        text |= digit.astype(_LANE) << np.uint64(8 * (8 - decimals + k))
    lengths = np.full(len(fraction), decimals + 1, dtype=np.int64)
    if trim:
        zeros = np.zeros(len(fraction), dtype=np.int64)
        for k in range(1, decimals + 1):
            zeros += fraction % 10**k == 0
        dropped = zeros + (zeros == decimals)  # the point goes with the last digit
        text <<= dropped.astype(np.uint64) * np.uint64(8)
        lengths -= dropped
    return _read_only(text), _read_only(lengths.astype(np.uint8))


def _place(lanes: np.ndarray, word: np.ndarray, offset: np.ndarray | int) -> None:
    """Or a right-aligned `word` into `lanes` so that its last byte is `offset` bytes
    before the end of each row.

    Lane ``j`` counted from the end covers the bytes ``8j`` to ``8j + 7`` before the end,
    so the word moves ``8j − offset`` bytes towards the end of that lane (a left shift) or
    ``offset − 8j`` towards its start (a right shift); a word overlaps at most two lanes.
    With per-row offsets both shifts are applied to every lane: counts are unsigned, so a
    negative count wraps to a huge one, for which NumPy's shifts give 0.
    """
    g = lanes.shape[1]
    if isinstance(offset, int):
        for j in range(g):
            left = 8 * j - offset
            if 0 <= left < 8:
                lanes[:, g - 1 - j] |= word << np.uint64(8 * left)
            elif -8 < left < 0:
                lanes[:, g - 1 - j] |= word >> np.uint64(-8 * left)
        return
    bits = offset.astype(np.uint64) * np.uint64(8)
    for j in range(g):
        lane_bits = np.uint64(64 * j)
        lanes[:, g - 1 - j] |= (word << (lane_bits - bits)) | (word >> (bits - lane_bits))


def _integer_text(
    magnitude: np.ndarray, largest: int, negative: np.ndarray | None, prefix: bytes
) -> Column:
    """`prefix`, a minus where `negative`, then the digits of the unsigned integers
    `magnitude`, none of which exceeds `largest`."""
    digits = min(4, 7 - len(prefix))  # prefix, sign and digits fill at most one lane
    base = 10**digits
    heads, head_lengths = _head_table(prefix, digits)
    if largest < base:
        index = magnitude.astype(np.intp)
        if negative is not None:
            np.add(index, base, out=index, where=negative)
        return Column(heads.take(index)[:, None], head_lengths.take(index))

    # Groups of `digits` digits from the units up; the highest non-zero one ("head") comes
    # from the head table with the prefix and sign, the ones below it with leading zeros.
    if largest < 2**32:
        magnitude = magnitude.astype(np.uint32)  # much faster division than uint64
    groups = []
    rest = magnitude
    while largest >= base:
        rest, group = np.divmod(rest, base)
        groups.append(group.astype(np.intp))
        largest //= base
    groups.append(rest.astype(np.intp))
    level = np.zeros(len(magnitude), dtype=np.intp)
    index = groups[0]
    for k in range(1, len(groups)):
        above = magnitude >= base**k
        level += above
        index = np.where(above, groups[k], index)
    if negative is not None:
        np.add(index, base, out=index, where=negative)
    lengths = head_lengths.take(index) + digits * level
    lanes = np.zeros((len(magnitude), _n_lanes(int(lengths.max()))), dtype=_LANE)
    group_words = _group_table(digits)
    for k, group in enumerate(groups[:-1]):
        _place(lanes, np.where(level > k, group_words.take(group), np.uint64(0)), digits * k)
    _place(lanes, heads.take(index), digits * level)
    return Column(lanes, lengths)


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


def _checked(values: np.ndarray, kinds: str, prefix: bytes, what: str) -> tuple[np.ndarray, bytes]:
    values = np.asarray(values)
    if values.ndim != 1:
        raise ValueError(f"{what} formats a 1-D array, not shape {values.shape}")
    if values.dtype.kind not in kinds:
        raise TypeError(f"{what} cannot format {values.dtype} values")
    prefix = bytes(prefix)
    if len(prefix) > _MAX_PREFIX:
        raise ValueError(f"a prefix has at most {_MAX_PREFIX} bytes, not {prefix!r}")
    return values, prefix


def _empty() -> Column:
    return Column(np.zeros((0, 1), _LANE), np.zeros(0, np.int64))


def format_fixed(
    values: np.ndarray, decimals: int, *, trim: bool = False, prefix: bytes = b""
) -> Column:
    """Format floating-point numbers like ``prefix + '%.{decimals}f' % value``.

    Parameters
    ----------
    values : numpy.ndarray
        1-D array of finite floating-point numbers of magnitude below 2⁶³.
    decimals : int
        Fraction digits, 0 to 6.
    trim : bool
        Drop trailing zeros of the fraction, and the point if nothing is left after it
        (``1.5`` rather than ``1.500000``, ``2`` rather than ``2.000000``).
    prefix : bytes
        At most 6 bytes written in front of each number (before its sign).

    Returns
    -------
    Column
        The texts. Rounding is correct for the exact binary value, ties to even, exactly
        as Python's formatting; a value that rounds to zero has no minus sign.

    Raises
    ------
    ValueError
        For NaN or infinity, magnitudes of 2⁶³ or more, `decimals` outside 0 to 6, a
        prefix longer than 6 bytes or an array that is not 1-D.
    TypeError
        For values that are not floating point.
    """
    values, prefix = _checked(values, "f", prefix, "format_fixed")
    if not (isinstance(decimals, (int, np.integer)) and 0 <= decimals <= _MAX_DECIMALS):
        raise ValueError(f"decimals must be an integer from 0 to {_MAX_DECIMALS}, not {decimals!r}")
    decimals = int(decimals)
    if len(values) == 0:
        return _empty()
    magnitude = np.absolute(values, dtype=np.float64)
    largest = float(magnitude.max())  # NaN if there is one
    if not np.isfinite(largest):
        raise ValueError("cannot format NaN or infinity")
    if largest >= 2.0**63:
        raise ValueError("cannot format magnitudes of 2**63 or more")

    negative = values < 0
    if not decimals:
        # Ties go to the even integer, which the fraction alone cannot tell.
        whole = np.rint(magnitude)
        negative &= whole > 0
        return _integer_text(whole.astype(np.uint64), round(largest), negative, prefix)
    whole = np.floor(magnitude)
    scale = 10**decimals
    # For float16/32 values the fraction has at most 24 significant bits and 10^decimals
    # at most 14 odd bits, so their float64 product is exact.
    fraction = _rounded_fraction(magnitude - whole, float(scale), values.dtype.itemsize <= 4)
    carry = fraction == scale
    whole += carry
    np.subtract(fraction, scale, out=fraction, where=carry)
    negative &= whole + fraction > 0
    head = _integer_text(whole.astype(np.uint64), int(largest) + 1, negative, prefix)

    tail_words, tail_lengths = _fraction_table(decimals, trim)
    index = fraction.astype(np.intp)
    tail_length = tail_lengths.take(index)
    lengths = head.lengths + tail_length
    # The integer text moves towards the start by the tail's length (at most 7 bytes).
    shift = np.left_shift(tail_length, 3, dtype=np.uint64)
    carry_shift = np.uint64(64) - shift
    g = head.lanes.shape[1]
    lanes = np.empty((len(values), _n_lanes(int(lengths.max()))), dtype=_LANE)
    np.right_shift(head.lanes[:, -1], shift, out=lanes[:, -1])
    lanes[:, -1] |= tail_words.take(index)
    for k in range(1, lanes.shape[1]):
        np.left_shift(head.lanes[:, -k], carry_shift, out=lanes[:, -1 - k])
        if k < g:
            lanes[:, -1 - k] |= head.lanes[:, -1 - k] >> shift
    return Column(lanes, lengths)


def format_int(values: np.ndarray, *, prefix: bytes = b"") -> Column:
    """Format integers like ``prefix + '%d' % value``.

    Parameters
    ----------
    values : numpy.ndarray
        1-D array of integers (any NumPy integer type).
    prefix : bytes
        At most 6 bytes written in front of each number (before its sign).

    Returns
    -------
    Column
        The texts.

    Raises
    ------
    ValueError
        For a prefix longer than 6 bytes or an array that is not 1-D.
    TypeError
        For values that are not integers.
    """
    values, prefix = _checked(values, "iu", prefix, "format_int")
    if len(values) == 0:
        return _empty()
    smallest, largest = int(values.min()), int(values.max())
    if smallest >= 0:
        return _integer_text(values.astype(np.uint64), largest, None, prefix)
    negative = values < 0
    magnitude = values.astype(np.int64).view(np.uint64)
    # Two's complement: −v as uint64 is the magnitude, also for the most negative int64.
    np.negative(magnitude, out=magnitude, where=negative)
    return _integer_text(magnitude, max(largest, -smallest), negative, prefix)


def literal(text: bytes) -> Column:
    """The same `text` (at most 8 bytes) on every row: a one-row column that :func:`join`
    repeats."""
    text = bytes(text)
    if len(text) > 8:
        raise ValueError(f"a literal has at most 8 bytes, not {text!r}")
    return Column(_words([text])[:, None], np.array([len(text)], dtype=np.int64))


def concat(columns: Sequence[Column]) -> Column:
    """Concatenate the texts of columns with the same number of rows, row by row, into one
    column.

    Parameters
    ----------
    columns : sequence of Column
        At least one column.

    Returns
    -------
    Column
        Row ``i`` is the concatenation of the columns' rows ``i``.
    """
    result = columns[0]
    for column in columns[1:]:
        if len(column.lengths) != len(result.lengths):
            raise ValueError("columns must have the same number of rows")
        lengths = result.lengths + column.lengths
        lanes = np.zeros((len(lengths), _n_lanes(int(lengths.max(initial=0)))), dtype=_LANE)
        lanes[:, lanes.shape[1] - column.lanes.shape[1] :] = column.lanes
        g = result.lanes.shape[1]
        for j in range(g):
            _place(lanes, result.lanes[:, g - 1 - j], column.lengths + 8 * j)
        result = Column(lanes, lengths)
    return result


def take(column: Column, index: np.ndarray) -> Column:
    """Rows `index` of `column` (like :func:`numpy.take`)."""
    lanes = np.ascontiguousarray(column.lanes)
    g = lanes.shape[1]
    # Whole rows as single records: numpy.take copies those much faster than rows of a
    # 2-D array.
    rows = lanes.view(np.dtype((np.void, 8 * g))).reshape(-1).take(index)
    return Column(rows.view(_LANE).reshape(-1, g), column.lengths.take(index))


def join(columns: Sequence[Column]) -> memoryview:
    """Concatenate the texts of the columns row by row: row 0 of every column, then row 1…

    Parameters
    ----------
    columns : sequence of Column
        Columns with the same number of rows, or one row (see :func:`literal`), which is
        repeated (no rows if a column has none).

    Returns
    -------
    memoryview
        The text, ready for a binary file's ``write``.

    Notes
    -----
    When every column's texts have one length, the lines are rows of a byte matrix, filled
    column by column. Otherwise each text is copied with one unaligned store of the widest
    column's lane width that ends where the text ends; the bytes it writes in front of the
    text are overwritten by the texts before it, so the stores go from the last text to
    the first. That order is the order of one NumPy fancy assignment with contiguous index
    and value arrays.
    """
    rows = {len(c.lengths) for c in columns}
    n = 0 if 0 in rows else max(rows)  # one row is repeated, as in NumPy broadcasting
    if rows - {1, n}:
        raise ValueError("columns must have the same number of rows, or one")
    if n == 0:
        return memoryview(b"")
    widths = [int(c.lengths[0]) for c in columns]
    if all((c.lengths == w).all() for c, w in zip(columns, widths)):
        return _join_fixed(columns, n, widths)
    g = max(c.lanes.shape[1] for c in columns)
    width = 8 * g
    record = np.dtype((np.void, width))
    # Laid out last text first, so that plain contiguous arrays give the reverse order.
    lanes = np.empty((n, len(columns), g), _LANE)
    lengths = np.empty((n, len(columns)), np.int64)
    lanes_backwards = lanes[::-1, ::-1]
    lengths_backwards = lengths[::-1, ::-1]
    for p, (column_lanes, column_lengths) in enumerate(columns):
        # Lane by lane: NumPy copies a few-lane block row by row, several times slower.
        # Lanes in front of a narrower column stay uninitialised: they are stored in front
        # of its text, where only bytes that are overwritten later go.
        first = g - column_lanes.shape[1]
        for j in range(column_lanes.shape[1]):
            lanes_backwards[:, p, first + j] = column_lanes[:, j]
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


def _join_fixed(columns: Sequence[Column], n: int, widths: list[int]) -> memoryview:
    """:func:`join` for columns whose texts have the given constant widths."""
    lines = np.empty((n, sum(widths)), np.uint8)
    start = 0
    for (lanes, _), width in zip(columns, widths):
        if width:
            # Texts as single records: copied record by record, not byte by byte.
            record = np.dtype((np.void, width))
            text = np.ascontiguousarray(lanes).view(np.uint8)[:, lanes.shape[1] * 8 - width :]
            lines[:, start : start + width].view(record)[:, 0] = text.view(record)[:, 0]
        start += width
    return memoryview(lines.reshape(-1))
