"""The compiled quantisation (ptmcore.quantize) against the NumPy code it replaced, byte for byte.

The reference functions below are copies of the NumPy versions of ``ptmcore.ptmfile``
(``quantization_parameters``, ``_encode``, ``_ErrorStats`` and ``write_ptm``'s payload) and of
``reconstruct.report.web.lrgb_planes`` as they were before the kernels: every byte must be
theirs, and the error report too (its sums of squares only up to rounding).
"""

from __future__ import annotations

import numpy as np
import pytest

from ptmcore import quantize
from ptmcore.ptmfile import _header, _scale_bias, quantization_parameters, read_ptm, write_ptm
from ptmcore.quantize import coefficient_range, encode_ptm, lrgb_plane_codes
from reconstruct.report.web import PLANE_TERMS, lrgb_planes

# --- the NumPy reference --------------------------------------------------------------------


def _ref_parameters(c):
    axes = tuple(range(c.ndim - 1))
    lo = np.min(c, axis=axes).astype(np.float64)
    hi = np.max(c, axis=axes).astype(np.float64)
    pairs = [_scale_bias(float(a), float(b)) for a, b in zip(lo, hi)]
    return np.array([s for s, _ in pairs]), np.array([b for _, b in pairs], dtype=np.int64)


def _ref_encode(values, scale, bias):
    q = values.astype(np.float64)
    q /= scale
    q += bias + 0.5
    np.floor(q, out=q)
    np.clip(q, 0, 255, out=q)
    return q.astype(np.uint8)


class _RefErrorStats:
    def __init__(self):
        self.max = np.zeros(6)
        self.sq = np.zeros(6)
        self.clipped = np.zeros(6, dtype=np.int64)
        self.count = 0

    def add(self, values, codes, scale, bias):
        v = values.reshape(-1, 6).astype(np.float64)
        q = codes.reshape(-1, 6)
        err = (q.astype(np.float64) - bias) * scale - v
        np.maximum(self.max, np.abs(err).max(axis=0), out=self.max)
        self.sq += np.einsum("ij,ij->j", err, err)
        exact = v / scale + bias + 0.5
        self.clipped += np.count_nonzero((exact < 0) | (exact >= 256), axis=0)
        self.count += v.shape[0]


def _ref_payload(c, scale, bias):
    """The coefficient blocks write_ptm wrote, and its error statistics."""
    stats = _RefErrorStats()
    blocks = []
    channels = [c] if c.ndim == 3 else [c[:, :, ch, :] for ch in range(3)]
    for values in channels:
        codes = _ref_encode(values, scale, bias)
        stats.add(values, codes, scale, bias)
        blocks.append(codes[::-1].tobytes())
    return b"".join(blocks), stats


def _ref_lrgb_planes(coef, rgb):
    h, w = coef.shape[:2]
    planes = [np.ascontiguousarray(rgb)]
    scale = [1.0, 1.0, 1.0]
    bias = [0.0, 0.0, 0.0]
    for terms in PLANE_TERMS:
        plane = np.empty((h, w, 3), dtype=np.uint8)
        for c, k in enumerate(terms):
            a = coef[..., k]
            lo, hi = float(a.min()), float(a.max())
            span = hi - lo
            s = span / 255.0 if span > 0 else 1.0
            scale.append(s)
            bias.append(-(lo / 255.0) / s)
            step = np.float32(255.0 / span) if span > 0 else np.float32(0.0)
            q = (a.astype(np.float32) - np.float32(lo)) * step
            np.rint(q, out=q)
            np.clip(q, 0.0, 255.0, out=q)
            plane[..., c] = q
        planes.append(plane)
    return planes, scale, bias


# --- test data ------------------------------------------------------------------------------


def _with_ties(rng, shape, dtype=np.float32):
    """Coefficients on quarter steps: with HP's scale of 1/2 for their range, every other
    value lands exactly half-way between two codes (v/scale + bias + 0.5 an integer)."""
    c = rng.integers(-200, 200, shape).astype(dtype) * dtype(0.25)
    c[..., 1] = 7.0  # a constant coefficient
    c[..., 2] = np.abs(c[..., 2])  # min ≥ 0: bias 0
    c[..., 3] *= 1000  # a wide range
    # HP's rule with min < 0 can leave the largest values past 255: range 127.75 gives scale
    # 1/2, bias int(0.25/0.5 + 1) = 1, and 127.5/0.5 + 1 + 0.5 = 256.5 clamps.
    c[..., 4] = np.clip(c[..., 4], -0.25, 127.5)
    c[0, 0, ..., 4] = -0.25
    c[-1, -1, ..., 4] = 127.5
    return c


# Widths around the kernels' blocks of 384 values (64 pixels of 6, or 21⅓ of 18).
SHAPES = [(1, 1), (3, 7), (5, 64), (4, 65), (9, 130), (2, 1000)]


@pytest.fixture(autouse=True)
def small_bands(monkeypatch):
    """Bands of a few rows, so that small arrays still go through several bands and threads."""
    monkeypatch.setattr(quantize, "_BAND_VALUES", 2000)


def _write_bytes(c, threads=None):
    chunks = []
    stats = encode_ptm(c, *_ref_parameters(c), lambda a: chunks.append(a.tobytes()), threads=threads)
    return b"".join(chunks), stats


# --- ranges ---------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("rgb", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16, ">f4"])
def test_range_is_numpy_min_and_max(shape, rgb, dtype):
    rng = np.random.default_rng(1)
    c = (rng.normal(0, 100, shape + ((3, 6) if rgb else (6,)))).astype(dtype)
    lo, hi = coefficient_range(c)
    axes = tuple(range(c.ndim - 1))
    assert lo.dtype == np.float64 and hi.dtype == np.float64
    np.testing.assert_array_equal(lo, c.min(axis=axes).astype(np.float64))
    np.testing.assert_array_equal(hi, c.max(axis=axes).astype(np.float64))


def test_range_of_a_strided_view_and_one_thread():
    c = np.random.default_rng(2).normal(0, 1, (20, 300, 6)).astype(np.float32)
    view = c[::3, ::2]
    for threads in (1, None):
        lo, hi = coefficient_range(view, threads=threads)
        np.testing.assert_array_equal(lo, view.min(axis=(0, 1)))
        np.testing.assert_array_equal(hi, view.max(axis=(0, 1)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_range_marks_the_coefficient_that_is_not_finite(bad):
    c = np.zeros((7, 90, 3, 6), np.float32)
    c[5, 70, 1, 4] = bad
    lo, hi = coefficient_range(c)
    assert np.isnan(lo[4]) and np.isnan(hi[4])
    assert np.all(lo[[0, 1, 2, 3, 5]] == 0) and np.all(hi[[0, 1, 2, 3, 5]] == 0)
    with pytest.raises(ValueError, match="NaN or infinite"):
        quantization_parameters(c)


@pytest.mark.parametrize("rgb", [False, True])
def test_quantization_parameters_are_the_numpy_ones(rgb):
    c = _with_ties(np.random.default_rng(3), (6, 70) + ((3, 6) if rgb else (6,)))
    scale, bias = quantization_parameters(c)
    ref_scale, ref_bias = _ref_parameters(c)
    np.testing.assert_array_equal(scale, ref_scale)
    np.testing.assert_array_equal(bias, ref_bias)


# --- HP's bytes and the error report --------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("rgb", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_encoding_is_the_numpy_bytes_with_ties(shape, rgb, dtype):
    c = _with_ties(np.random.default_rng(4), shape + ((3, 6) if rgb else (6,)), dtype)
    scale, bias = _ref_parameters(c)
    ours, stats = _write_bytes(c)
    ref, ref_stats = _ref_payload(c, scale, bias)
    assert ours == ref
    np.testing.assert_array_equal(stats[0], ref_stats.max)
    np.testing.assert_array_equal(stats[2], ref_stats.clipped)
    np.testing.assert_allclose(stats[1], ref_stats.sq, rtol=1e-12, atol=0)


def test_ties_are_present_in_the_test_data():
    c = _with_ties(np.random.default_rng(4), (9, 130, 6))
    scale, bias = _ref_parameters(c)
    exact = c.astype(np.float64) / scale + bias + 0.5
    ties = exact == np.floor(exact)
    assert ties[..., 0].mean() > 0.3  # half-way values, which floor(… + 0.5) rounds up


@pytest.mark.parametrize("rgb", [False, True])
def test_values_that_clamp_and_scales_that_divide(rgb):
    """Scales and biases of the caller's choosing: values far below 0 and above 255, and
    scales that are not powers of two (the kernel then divides, as NumPy does)."""
    rng = np.random.default_rng(5)
    c = rng.normal(0, 300, (11, 77) + ((3, 6) if rgb else (6,))).astype(np.float32)
    for scale in ([0.5, 1.0, 0.25, 2.0, 4.0, 0.125], [0.3, 1.7, 0.1, 3.0, 1e-3, 7.0]):
        scale = np.array(scale)
        bias = np.array([0, 10, 128, 255, 60, 3])
        chunks = []
        stats = encode_ptm(c, scale, bias, lambda a: chunks.append(a.tobytes()))
        ref, ref_stats = _ref_payload(c, scale, bias)
        assert b"".join(chunks) == ref
        assert ref_stats.clipped.min() > 0
        np.testing.assert_array_equal(stats[0], ref_stats.max)
        np.testing.assert_array_equal(stats[2], ref_stats.clipped)
        np.testing.assert_allclose(stats[1], ref_stats.sq, rtol=1e-12)


def test_threads_do_not_change_bytes_or_sums():
    c = np.random.default_rng(6).normal(0, 50, (40, 90, 3, 6)).astype(np.float32)
    one = _write_bytes(c, threads=1)
    many = _write_bytes(c, threads=4)
    assert one[0] == many[0]
    np.testing.assert_array_equal(one[1], many[1])  # the sums too: bands are added in order


def test_a_write_error_stops_the_encoding():
    c = np.zeros((50, 40, 6), np.float32)
    calls = []

    def write(codes):
        calls.append(codes.shape)
        if len(calls) == 2:
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        encode_ptm(c, np.full(6, 0.5), np.zeros(6, int), write)
    assert len(calls) == 2


@pytest.mark.parametrize("rgb", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32, ">f4"])
def test_write_ptm_is_the_numpy_file(tmp_path, rgb, dtype):
    rng = np.random.default_rng(7)
    c = _with_ties(rng, (13, 71) + ((3, 6) if rgb else (6,)), np.float32)
    c = (c * 4).astype(dtype) if np.dtype(dtype).kind == "i" else c.astype(dtype)
    colour = None if rgb else rng.integers(0, 256, (13, 71, 3), dtype=np.uint8)
    info = write_ptm(tmp_path / "k.ptm", c, colour)
    scale, bias = _ref_parameters(c)
    payload, stats = _ref_payload(c, scale, bias)
    fmt = "PTM_FORMAT_RGB" if rgb else "PTM_FORMAT_LRGB"
    expected = _header(fmt, 71, 13, scale, bias) + payload
    if not rgb:
        expected += np.ascontiguousarray(colour[::-1]).tobytes()
    assert (tmp_path / "k.ptm").read_bytes() == expected
    assert info["bytes"] == len(expected)
    assert info["scale"] == scale.tolist() and info["bias"] == bias.tolist()
    assert info["max_error"] == stats.max.tolist()
    assert info["clipped"] == stats.clipped.tolist() and info["clipped"][4] > 0
    np.testing.assert_allclose(info["rms_error"], np.sqrt(stats.sq / stats.count), rtol=1e-12)
    assert read_ptm(tmp_path / "k.ptm").coefficients.shape == c.shape


def test_write_ptm_of_a_non_contiguous_array(tmp_path):
    rng = np.random.default_rng(8)
    c = rng.normal(0, 40, (30, 50, 6)).astype(np.float32)
    rgb = rng.integers(0, 256, (30, 50, 3), dtype=np.uint8)
    write_ptm(tmp_path / "a.ptm", c[::2, ::-1], rgb[::2, ::-1])
    write_ptm(tmp_path / "b.ptm", np.ascontiguousarray(c[::2, ::-1]), np.ascontiguousarray(rgb[::2, ::-1]))
    assert (tmp_path / "a.ptm").read_bytes() == (tmp_path / "b.ptm").read_bytes()


# --- OpenLIME's planes ----------------------------------------------------------------------


def _plane_data(rng, shape, dtype=np.float32):
    c = rng.normal(0, 60, shape + (6,)).astype(dtype)
    # a3 from 0 to 255 on half steps: step 1, so (a − lo)·step lands on every .5 (rint: to even).
    c[..., 3] = rng.integers(0, 511, shape) / 2
    c[0, 0, 3], c[-1, -1, 3] = 0.0, 255.0
    c[..., 2] = 7.5  # a constant channel
    return c


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_lrgb_planes_are_the_numpy_bytes(shape, dtype):
    rng = np.random.default_rng(9)
    c = _plane_data(rng, shape)
    c = (c * 10).astype(dtype) if np.dtype(dtype).kind == "i" else c.astype(dtype)
    rgb = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    planes, scale, bias = lrgb_planes(c, rgb)
    ref_planes, ref_scale, ref_bias = _ref_lrgb_planes(c, rgb)
    assert scale == ref_scale and bias == ref_bias
    for ours, ref in zip(planes, ref_planes):
        assert ours.dtype == np.uint8 and ours.flags.c_contiguous
        np.testing.assert_array_equal(ours, ref)


def test_lrgb_planes_round_half_steps_to_even():
    c = np.zeros((1, 4, 6), np.float32)
    c[0, :, 5] = [0.0, 0.5, 1.5, 255.0]  # a5 is plane 1, channel 0; step 1
    planes, _, _ = lrgb_planes(c, np.zeros((1, 4, 3), np.uint8))
    assert planes[1][0, :, 0].tolist() == [0, 0, 2, 255]


def test_plane_codes_clip_as_numpy_does():
    rng = np.random.default_rng(10)
    c = rng.normal(0, 200, (17, 70, 6)).astype(np.float32)
    lo = np.array([[-100, 0, 50], [-1e3, 3.25, 0]], np.float32)
    step = np.array([[1.0, 0.5, 2.0], [0.01, 1.0, 0.0]], np.float32)
    planes = lrgb_plane_codes(c, PLANE_TERMS, lo, step)
    for p, terms in enumerate(PLANE_TERMS):
        for ch, k in enumerate(terms):
            q = (c[..., k] - lo[p, ch]) * step[p, ch]
            ref = np.clip(np.rint(q), 0.0, 255.0).astype(np.uint8)
            np.testing.assert_array_equal(planes[p][..., ch], ref)
    assert any((pl == 0).any() and (pl == 255).any() for pl in planes)


def test_lrgb_planes_reject_non_finite_coefficients_by_name():
    c = np.zeros((5, 70, 6), np.float32)
    c[4, 69, 4] = np.nan
    with pytest.raises(ValueError, match="a4 is not finite"):
        lrgb_planes(c, np.zeros((5, 70, 3), np.uint8))


def test_kernel_module_is_imported_only_when_used():
    """It imports numba (half a second), which `import ptmcore` and the CLI's start avoid."""
    import subprocess
    import sys

    code = "import sys, ptmcore, ptmcore.ptmfile, reconstruct.report.web; print('ptmcore.quantize' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False"]


def test_block_holds_whole_pixels():
    assert quantize._BLOCK % 6 == 0
