"""Tests for reconstruct.mesh.textfmt: vectorised number formatting against Python's own."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reconstruct.mesh import textfmt


def _texts(column: textfmt.Column) -> list[str]:
    """The column's texts, through join (with a newline literal in front of each)."""
    text = bytes(textfmt.join([textfmt.literal(b"\n"), column])).decode("ascii")
    return text.split("\n")[1:]


def _python_fixed(value: float, decimals: int, trim: bool = False) -> str:
    """What format_fixed promises: Python's '%.{decimals}f', without the sign of a zero."""
    text = "%.*f" % (decimals, value)
    if text.startswith("-") and float(text) == 0:
        text = text[1:]
    if trim and "." in text:
        text = text.rstrip("0").rstrip(".")
    return text


def _check_fixed(
    values: np.ndarray, decimals: int, trim: bool = False, prefix: bytes = b""
) -> None:
    got = _texts(textfmt.format_fixed(values, decimals, trim=trim, prefix=prefix))
    expected = [prefix.decode() + _python_fixed(float(v), decimals, trim) for v in values]
    assert got == expected


# ---------------------------------------------------------------- format_fixed

SPECIAL = [
    0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 1.5, -2.25, 3.0,
    0.9999996, -0.9999996, 9.9999995, 9.9999996, 99999.9999996, -99999.9999996, 999999.9999995,
    1e-9, -1e-9, 4.9e-7, -4.9e-7, 5.1e-7, -5.1e-7, 0.1, 0.7, 1.0 / 3.0, 2.0 / 3.0,
    1e9, -1e9, 1e9 + 0.5, 123456789.123, 4294967296.5, 9999.9999999, 10000.0, -10000.0,
    1e15 + 0.125, 2.0**62, -(2.0**62), 1e18, 9.2e18,
]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("decimals", range(7))
@pytest.mark.parametrize("trim", [False, True])
def test_special_values_match_python(dtype, decimals, trim):
    _check_fixed(np.array(SPECIAL, dtype=dtype), decimals, trim)


def test_rounding_across_powers_of_ten_and_zeros():
    values = np.array([0.9999996, 99999.9999996, -0.0, -1e-9, -4e-7, -6e-7, 2.5, 120.0])
    assert _texts(textfmt.format_fixed(values, 6)) == [
        "1.000000", "100000.000000", "0.000000", "0.000000", "0.000000", "-0.000001",
        "2.500000", "120.000000",
    ]
    trimmed = textfmt.format_fixed(values, 6, trim=True)
    assert _texts(trimmed) == ["1", "100000", "0", "0", "0", "-0.000001", "2.5", "120"]


def test_exact_ties_round_to_even_like_python():
    # k/128 with k odd has exactly seven decimals ending in 5: a genuine tie at six decimals.
    ties = np.arange(1, 2560, 2) / 128.0 - 10.0
    ties_up_and_down = textfmt.format_fixed(np.array([0.0078125, 0.0234375]), 6)
    assert _texts(ties_up_and_down) == ["0.007812", "0.023438"]
    _check_fixed(ties, 6)
    _check_fixed(ties.astype(np.float32), 6)
    # With no decimals the parity is that of the integer part.
    halves = np.arange(-10.5, 11.0, 1.0)
    integers = textfmt.format_fixed(np.array([0.5, 1.5, 2.5, -2.5, -0.5]), 0)
    assert _texts(integers) == ["0", "2", "2", "-2", "0"]
    _check_fixed(halves, 0)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_random_values_match_python(dtype):
    rng = np.random.default_rng(7)
    n = 4000
    values = np.concatenate(
        [
            rng.uniform(-1e6, 1e6, n),
            rng.standard_normal(n) * 10.0 ** rng.integers(-9, 13, n),
            rng.integers(-(10**6), 10**6, n) / 10.0 ** rng.integers(0, 8, n),  # near-ties
            np.round(rng.uniform(-1000, 1000, n) * 2**9) / 2**9,  # many exact ties
        ]
    ).astype(dtype)
    for decimals in range(7):
        for trim in (False, True):
            _check_fixed(values, decimals, trim)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=40),
    st.integers(0, 6),
    st.booleans(),
    st.booleans(),
)
def test_property_matches_python(values, decimals, trim, single):
    array = np.array(values, dtype=np.float32 if single else np.float64)
    _check_fixed(array, decimals, trim, prefix=b"v ")


def test_prefix_goes_before_the_sign():
    column = textfmt.format_fixed(np.array([-1.5, 2.0, -123456.25]), 2, prefix=b"\nvt ")
    assert bytes(textfmt.join([column])) == b"\nvt -1.50\nvt 2.00\nvt -123456.25"


def test_fixed_rejects_bad_input():
    with pytest.raises(ValueError, match="NaN"):
        textfmt.format_fixed(np.array([1.0, np.nan]), 6)
    with pytest.raises(ValueError, match="NaN"):
        textfmt.format_fixed(np.array([np.inf], np.float32), 6)
    with pytest.raises(ValueError, match="2\\*\\*63"):
        textfmt.format_fixed(np.array([1e19]), 6)
    with pytest.raises(ValueError):
        textfmt.format_fixed(np.zeros(3), 7)
    with pytest.raises(ValueError):
        textfmt.format_fixed(np.zeros((2, 2)), 6)
    with pytest.raises(ValueError):
        textfmt.format_fixed(np.zeros(2), 6, prefix=b"1234567")
    with pytest.raises(TypeError):
        textfmt.format_fixed(np.arange(3), 6)


# ---------------------------------------------------------------- format_int


@pytest.mark.parametrize("dtype", [np.int8, np.int32, np.int64, np.uint8, np.uint32, np.uint64])
def test_integers_match_python(dtype):
    info = np.iinfo(dtype)
    lo, hi = int(info.min), int(info.max)
    edges = [0, 1, 9, 10, 99, 100, 9999, 10000, 99999999, 100000000, lo, lo + 1, hi - 1, hi]
    rng = np.random.default_rng(3)
    values = np.concatenate(
        [
            np.array([v for v in edges if lo <= v <= hi], dtype=dtype),
            rng.integers(lo, hi, 3000, dtype=dtype, endpoint=True),
            rng.integers(max(lo, -(10**6)), min(hi, 10**6), 3000, dtype=dtype, endpoint=True),
        ]
    )
    for prefix in (b"", b"/", b"\tf ", b"123456"):
        got = _texts(textfmt.format_int(values, prefix=prefix))
        assert got == [prefix.decode() + "%d" % v for v in values.tolist()]


def test_int_rejects_bad_input():
    with pytest.raises(TypeError):
        textfmt.format_int(np.zeros(3))
    with pytest.raises(ValueError):
        textfmt.format_int(np.zeros((2, 2), int))
    with pytest.raises(ValueError):
        textfmt.format_int(np.zeros(2, int), prefix=b"1234567")


# ---------------------------------------------------------------- columns


def test_concat_take_and_join():
    rng = np.random.default_rng(5)
    numbers = (rng.integers(-(10**9), 10**9, 500) // 10 ** rng.integers(0, 9, 500)).tolist()
    a = textfmt.format_int(np.array(numbers), prefix=b" ")
    b = textfmt.format_int(np.array(numbers), prefix=b"/")
    token = textfmt.concat([a, b, b])
    assert _texts(token) == [" %d/%d/%d" % (v, v, v) for v in numbers]
    index = rng.integers(0, len(numbers), 800)
    picked = textfmt.take(token, index)
    assert _texts(picked) == [" %d/%d/%d" % ((numbers[i],) * 3) for i in index]
    x = rng.standard_normal(800)
    line = textfmt.join([textfmt.literal(b"\nf"), picked, textfmt.format_fixed(x, 3, prefix=b" ")])
    expected = "".join(
        "\nf %d/%d/%d %s" % ((numbers[i],) * 3 + (_python_fixed(w, 3),)) for i, w in zip(index, x)
    )
    assert bytes(line).decode() == expected


def test_join_of_equal_length_texts_and_of_varied_ones_agree():
    # Equal lengths everywhere take the byte-matrix path; one differing row the store path.
    same = np.full(100, 1234567)
    varied = same.copy()
    varied[50] = 7
    for numbers in (same, varied):
        column = textfmt.format_int(numbers, prefix=b"/")
        line = textfmt.join([textfmt.literal(b"\nf"), column, column, textfmt.literal(b";")])
        assert bytes(line).decode() == "".join("\nf/%d/%d;" % (v, v) for v in numbers.tolist())


def test_join_overlapping_stores_keep_every_byte():
    # Many texts much shorter than the widest store (24 bytes here), and empty ones.
    rng = np.random.default_rng(11)
    n = 20_000
    digits = rng.integers(0, 10, n)
    big = rng.integers(-(10**18), 10**18, n) // 10 ** rng.integers(0, 19, n)
    empty = textfmt.Column(np.zeros((n, 1), np.uint64), np.zeros(n, np.int64))
    columns = [
        textfmt.format_int(big, prefix=b"\n#"),
        textfmt.format_int(digits),
        empty,
        textfmt.format_int(digits),
    ]
    text = bytes(textfmt.join(columns)).decode()
    assert text == "".join("\n#%d%d%d" % (a, b, b) for a, b in zip(big.tolist(), digits.tolist()))


def test_join_checks_rows_and_handles_empty_columns():
    with pytest.raises(ValueError):
        textfmt.join([textfmt.format_int(np.arange(3)), textfmt.format_int(np.arange(4))])
    empty = textfmt.format_fixed(np.zeros(0), 6)
    assert bytes(textfmt.join([textfmt.literal(b"\nv"), empty])) == b""
    assert len(empty.lengths) == 0 and len(textfmt.format_int(np.zeros(0, int)).lengths) == 0
