"""Tests for reconstruct.mesh.objtext: OBJ lines against Python's own formatting."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from reconstruct.mesh import objtext


def _python(value: float) -> str:
    """What objtext promises: Python's '%.6f' without trailing zeros, and no '-0'."""
    text = ("%.6f" % value).rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def _lines(values: np.ndarray, keyword: bytes = b"v") -> list[str]:
    text = bytes(objtext.number_lines(values, keyword)).decode("ascii")
    assert text.startswith("\n")
    return text[1:].split("\n")


def _expected(values: np.ndarray, keyword: str = "v") -> list[str]:
    return [" ".join([keyword, *(_python(float(x)) for x in row)]) for row in values]


SPECIAL = [
    0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 1.5, -2.25, 3.0, 10.0, 100.0, -1000.0, 99.0, 0.01, 0.000001,
    0.9999996, -0.9999996, 9.9999995, 9.9999996, 99999.9999996, -99999.9999996,
    1e-9, -1e-9, 4.9e-7, -4.9e-7, 5e-7, -5e-7, 5.1e-7, -5.1e-7, 1.5e-6, 2.5e-6, 0.1, 0.7, 1 / 3, 2 / 3,
    1e9, -1e9, 123456789.123, 4294967296.5, 9999.9999999, 1e12, -9.2e12,
]


def test_special_values_match_python():
    values = np.array(SPECIAL, np.float32).reshape(-1, 1)
    assert _lines(values) == _expected(values)


def test_ties_round_to_even_like_python():
    # float32 values whose exact value lies exactly half-way between two 6-decimal numbers.
    k = np.arange(1, 2000, dtype=np.float64)
    values = ((2 * k + 1) / 2**7).astype(np.float32)  # multiples of 1/128: 7 binary decimals
    values = np.concatenate([values, values / 2**3, -values / 2**6]).astype(np.float32).reshape(-1, 1)
    assert _lines(values, b"vt") == _expected(values, "vt")


def test_random_rows_match_python():
    rng = np.random.default_rng(5)
    values = np.concatenate([
        rng.normal(0, 30, (3000, 3)), rng.uniform(-1, 1, (3000, 3)), rng.normal(0, 1e6, (300, 3)),
        np.round(rng.normal(0, 50, (300, 3)), 3),
    ]).astype(np.float32)
    assert _lines(values, b"vn") == _expected(values, "vn")


@settings(max_examples=300, deadline=None)
@given(arrays(np.float32, st.tuples(st.integers(1, 20), st.integers(1, 4)),
              elements=st.floats(-8796093022208.0, 8796093022208.0, width=32, allow_nan=False, allow_infinity=False)))
def test_property_matches_python(values):
    assert _lines(values) == _expected(values)


def test_faces_count_from_one_with_shared_indices():
    faces = np.array([[0, 1, 2], [9, 99, 1234566], [2**31 - 2, 0, 7]], np.int64)
    expected = {3: "\nf 1/1/1 2/2/2 3/3/3\nf 10/10/10 100/100/100 1234567/1234567/1234567"
                   "\nf 2147483647/2147483647/2147483647 1/1/1 8/8/8",
                2: "\nf 1/1 2/2 3/3\nf 10/10 100/100 1234567/1234567\nf 2147483647/2147483647 1/1 8/8",
                1: "\nf 1 2 3\nf 10 100 1234567\nf 2147483647 1 8"}
    for per_corner, text in expected.items():
        assert bytes(objtext.face_lines(faces, per_corner)).decode() == text
        assert bytes(objtext.face_lines(faces.astype(np.int32), per_corner)).decode() == text


def test_bad_input_is_refused():
    for bad in (np.nan, np.inf, -np.inf, 1e13):
        with pytest.raises(ValueError, match="NaN, infinity"):
            objtext.number_lines(np.array([[0.0, bad]], np.float32), b"v")
    with pytest.raises(TypeError, match="float32"):
        objtext.number_lines(np.zeros((2, 3)), b"v")
    with pytest.raises(ValueError, match="per_corner"):
        objtext.face_lines(np.zeros((1, 3), np.int32), 4)


def test_empty():
    assert bytes(objtext.number_lines(np.zeros((0, 3), np.float32), b"v")) == b""
    assert bytes(objtext.face_lines(np.zeros((0, 3), np.int32), 3)) == b""
