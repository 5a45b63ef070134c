import numpy as np
import pytest
from helpers import mutate
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from ptm_samples import (
    LRGB_ORDER,
    LRGB_REFERENCE,
    LRGB_TRANSFORM,
    jpeg_ptm,
    lrgb_bytes,
    rgb_bytes,
    sample_files,
    smooth_codes,
)

from ptmcore.errors import InputError
from ptmcore.fit import light_matrix
from ptmcore.images import read_image
from ptmcore.lp import read_lp
from ptmcore.ptmencoded import HP_LUMA_WEIGHTS, fit_ptm_encoded, fit_ptm_rgb_encoded
from ptmcore.ptmfile import PTMFile, quantization_parameters, quantize, read_ptm, write_ptm

SCALE = [0.5, 0.5, 0.25, 0.5, 0.25, 1.0]
BIAS = [167, 97, 0, 0, 0, 0]


def _decode(codes, scale=SCALE, bias=BIAS):
    return ((codes.astype(np.float64) - bias) * scale).astype(np.float32)


def _write(tmp_path, data, name="x.ptm"):
    p = tmp_path / name
    p.write_bytes(data)
    return p


@pytest.fixture
def capture(shared_fixture):
    lights = read_lp(shared_fixture / "reference_8x5.lp")
    photos = np.stack([read_image(p) for p in lights.paths])
    return shared_fixture, lights, photos


# --- HP PTMfitter's file --------------------------------------------------------------------


def test_reads_ptmfitter_fixture(capture):
    folder, lights, photos = capture
    data = (folder / "reference_8x5.ptm").read_bytes()
    header = (
        b"PTM_1.2\nPTM_FORMAT_LRGB\n8\n5\n"
        b"0.500000 0.500000 0.250000 0.500000 0.250000 1.000000 \n167 97 0 0 0 0 \n"
    )
    assert data.startswith(header)
    assert len(data) - len(header) == 9 * 8 * 5

    ptm = read_ptm(folder / "reference_8x5.ptm")
    assert (ptm.format, ptm.version, ptm.width, ptm.height) == ("PTM_FORMAT_LRGB", "PTM_1.2", 8, 5)
    np.testing.assert_array_equal(ptm.scale, SCALE)
    np.testing.assert_array_equal(ptm.bias, BIAS)
    assert ptm.coefficients.shape == (5, 8, 6) and ptm.coefficients.dtype == np.float32
    assert ptm.rgb.shape == (5, 8, 3) and ptm.rgb.dtype == np.uint8
    # The first stored pixel is the bottom-left one.
    payload = np.frombuffer(data[len(header):], np.uint8)
    np.testing.assert_array_equal(ptm.coefficients[4, 0], _decode(payload[:6]))
    np.testing.assert_array_equal(ptm.rgb[4, 0], payload[240:243])


def test_relighting_the_fixture_reproduces_the_photographs(capture):
    """RTIViewer's rgb·L/255 at the 12 lights of the .lp against the 12 JPEGs.

    Measured: mean |difference| 0.87 levels, max 5 (8-bit; the PTM's model, JPEG error and
    RTIViewer's truncation to bytes); with rows taken top-first instead of bottom-first the
    mean is about 21 levels.
    """
    folder, lights, photos = capture
    ptm = read_ptm(folder / "reference_8x5.ptm")
    rendered = np.stack([ptm.render(d) for d in lights.directions]).astype(int)
    diff = np.abs(rendered - photos)
    assert diff.mean() < 1.0 and diff.max() <= 6

    flipped = PTMFile(**{**ptm.__dict__, "coefficients": ptm.coefficients[::-1], "rgb": ptm.rgb[::-1]})
    wrong = np.stack([flipped.render(d) for d in lights.directions]).astype(int)
    assert np.abs(wrong - photos).mean() > 10 * diff.mean()


def test_fit_reproduces_ptmfitter_byte_for_byte(capture, tmp_path):
    """Our fit of the same 12 photographs, written as .ptm, is PTMfitter's file exactly:
    same header (format line, size, power-of-two scales in %f, integer biases, trailing
    spaces) and the same 360 payload bytes, so the decoded coefficients differ by 0."""
    folder, lights, photos = capture
    reference = (folder / "reference_8x5.ptm").read_bytes()
    coefficients, rgb = fit_ptm_encoded(lights.paths, lights.directions)
    assert coefficients.shape == (5, 8, 6) and coefficients.dtype == np.float32
    info = write_ptm(tmp_path / "ours.ptm", coefficients, rgb)
    ours = (tmp_path / "ours.ptm").read_bytes()

    header_len = reference.index(b"\n", reference.index(b"167 97")) + 1
    assert ours[:header_len] == reference[:header_len]
    assert info["scale"] == SCALE and info["bias"] == BIAS
    assert info["bytes"] == len(reference)
    assert ours == reference

    theirs = read_ptm(folder / "reference_8x5.ptm")
    mine = read_ptm(tmp_path / "ours.ptm")
    assert np.abs(mine.coefficients - theirs.coefficients).max() == 0
    # Quantisation error of our fit: at most half a step per coefficient.
    assert all(e <= s / 2 + 1e-6 for e, s in zip(info["max_error"], SCALE))
    # The unquantised fit is within half a step of PTMfitter's decoded coefficients.
    assert np.all(np.abs(coefficients - theirs.coefficients) <= np.array(SCALE) / 2 + 1e-4)


def test_fit_from_arrays_equals_fit_from_files(capture):
    folder, lights, photos = capture
    c1, rgb1 = fit_ptm_encoded(lights.paths, lights.directions, threads=2)
    c2, rgb2 = fit_ptm_encoded(photos, lights.directions)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(rgb1, rgb2)


def test_rgb_format_fit_relights_the_photographs(capture, tmp_path):
    """RGB format (one polynomial per channel): measured mean 0.65, max 3 levels."""
    folder, lights, photos = capture
    coefficients = fit_ptm_rgb_encoded(lights.paths, lights.directions)
    assert coefficients.shape == (5, 8, 3, 6)
    write_ptm(tmp_path / "rgb.ptm", coefficients)
    ptm = read_ptm(tmp_path / "rgb.ptm")
    assert ptm.format == "PTM_FORMAT_RGB" and ptm.rgb is None
    diff = np.abs(np.stack([ptm.render(d) for d in lights.directions]).astype(int) - photos)
    assert diff.mean() < 1.0 and diff.max() <= 4


def test_fit_of_too_few_photographs_interpolates_and_mismatched_sizes_fail(tmp_path):
    rng = np.random.default_rng(0)
    imgs = rng.integers(1, 255, (6, 4, 5, 3), dtype=np.uint8)
    az = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    r = np.array([0.3, 0.5, 0.7, 0.4, 0.6, 0.8])
    dirs = np.stack([r * np.cos(az), r * np.sin(az), np.sqrt(1 - r * r)], 1)
    # Five photographs underdetermine six coefficients: the minimum-norm solution passes
    # through every observed luminance (the pipeline warns about the rank).
    coefficients, _ = fit_ptm_encoded(imgs[:5], dirs[:5])
    y = imgs[:5].astype(np.float64) @ np.array(HP_LUMA_WEIGHTS)
    observed = 255 * y / y.max(axis=0)
    np.testing.assert_allclose(np.einsum("nk,hwk->nhw", light_matrix(dirs[:5]), coefficients), observed, atol=1e-2)
    dirs = np.tile([0.0, 0.0, 1.0], (6, 1))
    with pytest.raises(InputError, match="same size"):
        fit_ptm_encoded(list(imgs[:5]) + [imgs[5, :3]], dirs)


def test_black_pixels_fit_to_zero():
    imgs = np.zeros((6, 2, 3, 3), np.uint8)
    imgs[:, 0, 0] = 200
    az = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    r = np.array([0.3, 0.5, 0.7, 0.4, 0.6, 0.8])  # varied elevations: a full-rank light matrix
    dirs = np.stack([r * np.cos(az), r * np.sin(az), np.sqrt(1 - r * r)], 1)
    coefficients, rgb = fit_ptm_encoded(imgs, dirs)
    assert np.all(np.isfinite(coefficients))
    assert np.all(coefficients[1] == 0) and np.all(rgb[1] == 0)
    np.testing.assert_allclose(coefficients[0, 0], [0, 0, 0, 0, 0, 255], atol=1e-3)
    # The colour is truncated, so float error may land it on 199.
    assert np.all((rgb[0, 0] == 200) | (rgb[0, 0] == 199)) and np.all(rgb[0, 1:] == 0)


# --- quantisation ---------------------------------------------------------------------------


def test_quantisation_follows_hp_rule():
    c = np.zeros((2, 2, 6), np.float32)
    c[..., 0] = [[-43.5, 0.0], [10.0, 20.0]]  # min < 0: bias from the minimum
    c[..., 1] = [[0.0, 1.0], [2.0, 600.0]]  # min ≥ 0: scale doubles until max fits
    c[..., 5] = 3.0  # constant
    scale, bias = quantization_parameters(c)
    # range 63.5 = 0.99·2^6 → scale 2^-2; bias int(43.5/0.25 + 1) = 175
    assert scale[0] == 0.25 and bias[0] == 175
    # range 600 → 2^10·0.59 → 2^2 = 4 → 600/4 = 150 ≤ 255
    assert scale[1] == 4.0 and bias[1] == 0
    codes, s, b = quantize(c)
    assert codes[0, 0, 0] == np.floor(-43.5 / 0.25 + 175 + 0.5)
    assert codes.dtype == np.uint8


@settings(max_examples=150, deadline=None)
@given(
    arrays(
        np.float32,
        st.tuples(st.integers(1, 5), st.integers(1, 5), st.just(6)),
        elements=st.floats(-1e4, 1e4, width=32),
    )
)
def test_quantisation_error_is_half_a_step(values):
    codes, scale, bias = quantize(values)
    assert np.all((bias >= 0) & (bias <= 255))
    assert np.all(np.log2(scale) == np.round(np.log2(scale)))
    exact = values / scale + bias + 0.5
    inside = (exact >= 0) & (exact < 256)
    err = np.abs((codes.astype(np.float64) - bias) * scale - values)
    bound = scale / 2 + 1e-9 * np.abs(values)  # float32 input: its own rounding is far smaller
    assert np.all(err[inside] <= bound[inside])


def test_rejects_non_finite_coefficients(tmp_path):
    c = np.zeros((2, 2, 6), np.float32)
    c[0, 0, 2] = np.nan
    with pytest.raises(ValueError):
        write_ptm(tmp_path / "x.ptm", c, np.zeros((2, 2, 3), np.uint8))


# --- writing and reading back ---------------------------------------------------------------


def test_round_trip_lrgb(tmp_path):
    rng = np.random.default_rng(1)
    c = rng.normal(0, 40, (7, 11, 6)).astype(np.float32)
    c[..., 5] += 120
    rgb = rng.integers(0, 256, (7, 11, 3), dtype=np.uint8)
    info = write_ptm(tmp_path / "a.ptm", c, rgb)
    ptm = read_ptm(tmp_path / "a.ptm")
    assert ptm.format == "PTM_FORMAT_LRGB" and (ptm.width, ptm.height) == (11, 7)
    np.testing.assert_array_equal(ptm.rgb, rgb)
    scale = np.array(info["scale"])
    ok = ~_clipped(c, scale, np.array(info["bias"]))
    err = np.abs(ptm.coefficients - c)
    assert np.all(err[ok] <= np.broadcast_to(scale / 2 + 1e-4, c.shape)[ok])
    worst = np.where(ok, err, 0).reshape(-1, 6).max(0)
    np.testing.assert_allclose(info["max_error"], worst, rtol=1e-4, atol=1e-5)
    assert info["clipped"] == list(np.count_nonzero(~ok.reshape(-1, 6), axis=0))
    assert (tmp_path / "a.ptm").stat().st_size == info["bytes"]


def _clipped(c, scale, bias):
    exact = c.astype(np.float64) / scale + bias + 0.5
    return (exact < 0) | (exact >= 256)


def test_round_trip_rgb_shares_one_scale_and_bias(tmp_path):
    rng = np.random.default_rng(2)
    c = rng.normal(0, 30, (5, 4, 3, 6)).astype(np.float32)
    c[:, :, 2, 0] -= 100  # only the blue channel reaches this low
    info = write_ptm(tmp_path / "b.ptm", c)
    ptm = read_ptm(tmp_path / "b.ptm")
    assert ptm.format == "PTM_FORMAT_RGB" and ptm.coefficients.shape == (5, 4, 3, 6)
    scale, bias = quantization_parameters(c)
    np.testing.assert_array_equal(ptm.scale, scale)
    np.testing.assert_array_equal(ptm.bias, bias)
    ok = ~_clipped(c, scale, bias)
    assert np.all(np.abs(ptm.coefficients - c)[ok] <= np.broadcast_to(scale / 2 + 1e-4, c.shape)[ok])
    assert info["bytes"] == (tmp_path / "b.ptm").stat().st_size


def test_header_layout_matches_ptmfitter(tmp_path):
    c = np.zeros((3, 2, 6), np.float32)
    c[0, 0] = [-10, 5, 4, 8, 3, 200]  # ranges ≥ 2, so scales ≥ 2^-6 print exactly as %f
    write_ptm(tmp_path / "h.ptm", c, np.zeros((3, 2, 3), np.uint8))
    lines = (tmp_path / "h.ptm").read_bytes().split(b"\n")[:6]
    assert lines[:4] == [b"PTM_1.2", b"PTM_FORMAT_LRGB", b"2", b"3"]
    scales = lines[4].split(b" ")
    assert len(scales) == 7 and scales[-1] == b""
    assert all(len(s.split(b".")[1]) == 6 for s in scales[:6])
    biases = lines[5].split(b" ")
    assert len(biases) == 7 and biases[-1] == b"" and all(b.isdigit() for b in biases[:6])


def test_tiny_scales_are_written_exactly(tmp_path):
    c = np.zeros((2, 2, 6), np.float32)
    c[..., 0] = [[0.0, 0.001], [0.002, 0.003]]  # range 0.77·2^-8: scale 2^-16, beyond %f
    write_ptm(tmp_path / "t.ptm", c, np.zeros((2, 2, 3), np.uint8))
    assert b"1.52587890625e-05 " in (tmp_path / "t.ptm").read_bytes()
    ptm = read_ptm(tmp_path / "t.ptm")
    assert ptm.scale[0] == 2.0**-16
    np.testing.assert_allclose(ptm.coefficients[..., 0], c[..., 0], atol=2.0**-17)


def test_write_to_missing_folder_is_input_error(tmp_path):
    with pytest.raises(InputError):
        write_ptm(tmp_path / "nope" / "x.ptm", np.zeros((1, 1, 6)), np.zeros((1, 1, 3), np.uint8))


def test_render_and_luminance():
    c = np.zeros((1, 2, 6), np.float32)
    c[0, 0] = [0, 0, 0, 100, 0, 100]  # L = 100·lu + 100
    c[0, 1, 5] = 510  # saturates
    ptm = PTMFile("PTM_FORMAT_LRGB", "PTM_1.2", 2, 1, np.ones(6), np.zeros(6, int), c,
                  np.array([[[255, 128, 0], [10, 20, 30]]], np.uint8))
    np.testing.assert_allclose(ptm.luminance([0.6, 0.0, 0.8])[0, 0], 160, rtol=1e-6)
    np.testing.assert_allclose(ptm.luminance([1.2, 0.0, 1.6])[0, 0], 160, rtol=1e-6)  # normalised
    np.testing.assert_allclose(ptm.luminance([0.6, 0.0])[0, 0], 160, rtol=1e-6)
    img = ptm.render([0.6, 0.0, 0.8])
    np.testing.assert_array_equal(img[0, 0], [160, 80, 0])
    np.testing.assert_array_equal(img[0, 1], [20, 40, 60])


# --- other layouts --------------------------------------------------------------------------


def test_reads_pre_1_2_interleaved_lrgb(tmp_path):
    rng = np.random.default_rng(3)
    planes = smooth_codes(rng, 4, 7, 9)
    codes, rgb = np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:], 0, -1)
    new = read_ptm(_write(tmp_path, lrgb_bytes(codes, rgb, SCALE, BIAS), "new.ptm"))
    old = read_ptm(_write(tmp_path, lrgb_bytes(codes, rgb, SCALE, BIAS, version="PTM_1.1"), "old.ptm"))
    assert old.version == "PTM_1.1"
    np.testing.assert_array_equal(old.coefficients, _decode(codes))
    np.testing.assert_array_equal(old.rgb, rgb)
    np.testing.assert_array_equal(old.coefficients, new.coefficients)
    np.testing.assert_array_equal(old.rgb, new.rgb)


def test_reads_width_and_height_on_one_line(tmp_path):
    rng = np.random.default_rng(4)
    planes = smooth_codes(rng, 3, 4, 9)
    data = lrgb_bytes(np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:], 0, -1), SCALE, BIAS)
    data = data.replace(b"\n4\n3\n", b"\n4 3\n", 1)
    ptm = read_ptm(_write(tmp_path, data))
    assert (ptm.width, ptm.height) == (4, 3)


def test_reads_uncompressed_rgb_format(tmp_path):
    rng = np.random.default_rng(5)
    planes = smooth_codes(rng, 5, 3, 18)
    codes = np.moveaxis(planes.reshape(3, 6, 5, 3), (0, 1), (2, 3))
    ptm = read_ptm(_write(tmp_path, rgb_bytes(codes, SCALE, BIAS)))
    np.testing.assert_array_equal(ptm.coefficients, _decode(codes))


def test_jpeg_lrgb_lossless_by_side_information_equals_raw(tmp_path):
    """With side information for every pixel the JPEG got wrong, the planes come back exactly:
    the file then reads like the uncompressed LRGB of the same bytes (orientation included)."""
    rng = np.random.default_rng(6)
    planes = smooth_codes(rng, 10, 13, 9)
    data, expected, counts = jpeg_ptm(
        "PTM_FORMAT_JPEG_LRGB", planes, SCALE, BIAS,
        order=LRGB_ORDER, reference=LRGB_REFERENCE, transform=LRGB_TRANSFORM, tolerance=0,
    )
    np.testing.assert_array_equal(expected, planes)
    assert sum(counts["side_records"]) > 0
    jp = read_ptm(_write(tmp_path, data, "j.ptm"))
    raw_file = lrgb_bytes(np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:], 0, -1), SCALE, BIAS)
    raw = read_ptm(_write(tmp_path, raw_file, "r.ptm"))
    assert jp.format == "PTM_FORMAT_JPEG_LRGB" and jp.jpeg_quality == 75
    np.testing.assert_array_equal(jp.coefficients, raw.coefficients)
    np.testing.assert_array_equal(jp.rgb, raw.rgb)


def test_jpeg_lrgb_with_prediction_and_side_information(tmp_path):
    rng = np.random.default_rng(7)
    planes = smooth_codes(rng, 16, 20, 9)
    data, expected, counts = jpeg_ptm(
        "PTM_FORMAT_JPEG_LRGB", planes, SCALE, BIAS, quality=60,
        order=LRGB_ORDER, reference=LRGB_REFERENCE, transform=LRGB_TRANSFORM, tolerance=3,
    )
    # Predicted planes (1 from inverted 0, 4 from 3, 7 from 6, 8 from 7) and corrected pixels.
    assert counts["side_records"][1] > 0 and sum(counts["side_records"]) > 0
    assert np.abs(expected.astype(int) - planes).max() <= 3
    ptm = read_ptm(_write(tmp_path, data))
    np.testing.assert_array_equal(ptm.coefficients, _decode(np.moveaxis(expected[:6], 0, -1)))
    np.testing.assert_array_equal(ptm.rgb, np.moveaxis(expected[6:], 0, -1))


@pytest.mark.parametrize("layout", ["lrgb", "lrgb_1.1", "rgb", "jpeg_lrgb", "jpeg_rgb"])
@pytest.mark.parametrize("max_side", [5, 7, 100])
def test_subsampled_read_equals_the_whole_strided(tmp_path, layout, max_side):
    """``max_side`` decodes every k-th row and column from the top-left pixel, as the whole
    file strided would give (k = ceil(longest side / max_side))."""
    rng = np.random.default_rng(9)
    h, w = 11, 14
    if layout.startswith("jpeg"):
        fmt = "PTM_FORMAT_JPEG_LRGB" if layout == "jpeg_lrgb" else "PTM_FORMAT_JPEG_RGB"
        data, _, _ = jpeg_ptm(fmt, smooth_codes(rng, h, w, 9 if layout == "jpeg_lrgb" else 18), SCALE, BIAS,
                              quality=80)
    elif layout == "rgb":
        planes = smooth_codes(rng, h, w, 18)
        data = rgb_bytes(np.moveaxis(planes.reshape(3, 6, h, w), (0, 1), (2, 3)), SCALE, BIAS)
    else:
        planes = smooth_codes(rng, h, w, 9)
        version = "PTM_1.1" if layout == "lrgb_1.1" else "PTM_1.2"
        data = lrgb_bytes(np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:], 0, -1), SCALE, BIAS,
                          version=version)
    path = _write(tmp_path, data)
    whole, small = read_ptm(path), read_ptm(path, max_side=max_side)
    k = -(-w // max_side)
    assert (small.width, small.height) == (w, h) and max(small.coefficients.shape[:2]) <= max_side
    np.testing.assert_array_equal(small.coefficients, whole.coefficients[::k, ::k])
    if whole.rgb is None:
        assert small.rgb is None
    else:
        np.testing.assert_array_equal(small.rgb, whole.rgb[::k, ::k])
        assert small.rgb.flags.c_contiguous
    with pytest.raises(ValueError):
        read_ptm(path, max_side=0)


def test_jpeg_rgb(tmp_path):
    rng = np.random.default_rng(8)
    planes = smooth_codes(rng, 9, 12, 18)
    reference = [-1] * 6 + list(range(6)) + list(range(6, 12))
    data, expected, counts = jpeg_ptm(
        "PTM_FORMAT_JPEG_RGB", planes, SCALE, BIAS,
        reference=reference, transform=[0] * 12 + [1] * 6, tolerance=2,
    )
    ptm = read_ptm(_write(tmp_path, data))
    assert ptm.format == "PTM_FORMAT_JPEG_RGB" and ptm.rgb is None
    codes = np.moveaxis(expected.reshape(3, 6, 9, 12), (0, 1), (2, 3))
    np.testing.assert_array_equal(ptm.coefficients, _decode(codes))
    raw = read_ptm(_write(tmp_path, rgb_bytes(np.moveaxis(planes.reshape(3, 6, 9, 12), (0, 1), (2, 3)),
                                              SCALE, BIAS), "raw.ptm"))
    assert np.abs(ptm.coefficients - raw.coefficients).max() <= 2 * max(SCALE)


# --- hostile input --------------------------------------------------------------------------


def _lrgb_header(w, h, scale="1 1 1 1 1 1", bias="0 0 0 0 0 0"):
    return f"PTM_1.2\nPTM_FORMAT_LRGB\n{w}\n{h}\n{scale} \n{bias} \n".encode()


@pytest.mark.parametrize(
    "data, message",
    [
        (b"", "empty"),
        (b"hello\nworld\n", "not a PTM"),
        (b"#HSH1.2\n3\n", "HSH"),
        (b"PTM_9.9\nPTM_FORMAT_LRGB\n", "version"),
        (b"PTM_1.2\nPTM_FORMAT_PTM_LUT\n1\n1\n", "unsupported PTM format"),
        (_lrgb_header(0, 5), "not positive"),
        (_lrgb_header(-3, 5), "not positive"),
        (_lrgb_header("eight", 5), "integers"),
        (_lrgb_header(99999999, 99999999) + b"\0" * 100, "truncated"),
        (_lrgb_header(4, 4) + b"\0" * 10, "truncated"),
        (_lrgb_header(1, 1, scale="1 1 1 1 1 nan"), "numbers"),
        (_lrgb_header(1, 1, scale="1 1 1 1 1 1e999"), "not usable"),
        (_lrgb_header(1, 1, bias="0 0 0 0 0 0.5"), "integers"),
        (_lrgb_header(1, 1, bias="0 0 0 0 0"), "header ends before the biases"),
        (_lrgb_header(1, 1, bias="0 0 0 0 0 0 7") + b"\0" * 9, "unexpected content"),
        (b"PTM_1.2\nPTM_FORMAT_LRGB\n1\n", "header ends"),
    ],
)
def test_bad_files_raise_input_error(tmp_path, data, message):
    with pytest.raises(InputError, match=message):
        read_ptm(_write(tmp_path, data))


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_ptm(tmp_path / "absent.ptm")
    with pytest.raises(InputError, match="folder"):
        read_ptm(tmp_path)


def _replace_line(data: bytes, index: int, text: bytes) -> bytes:
    lines = data.split(b"\n")
    lines[index] = text
    return b"\n".join(lines)


@pytest.mark.parametrize(
    "line, text, message",
    [
        (6, b"75", None),  # quality: any integer is fine
        (7, b"2 0 0 0 0 0 0 0 0", "motion"),
        (7, b"9 0 0 0 0 0 0 0 0", "unknown transform"),
        (10, b"0 0 1 2 3 4 5 6 7", "order"),
        (11, b"1 0 -1 -1 -1 -1 -1 -1 -1", "reference plane"),
        (13, b"0 0 0 0 0 0 0 0 3", "multiple of 5"),
        (12, b"0 1 1 1 1 1 1 1 1", "not positive"),
    ],
)
def test_bad_jpeg_headers(tmp_path, line, text, message):
    rng = np.random.default_rng(9)
    data, _, _ = jpeg_ptm("PTM_FORMAT_JPEG_LRGB", smooth_codes(rng, 4, 5, 9), SCALE, BIAS, quality=75)
    bad = _replace_line(data, line, text)
    if message is None:
        read_ptm(_write(tmp_path, bad))
    else:
        with pytest.raises(InputError, match=message):
            read_ptm(_write(tmp_path, bad))


def test_undecodable_jpeg_plane(tmp_path):
    rng = np.random.default_rng(10)
    data, _, _ = jpeg_ptm("PTM_FORMAT_JPEG_LRGB", smooth_codes(rng, 4, 5, 9), SCALE, BIAS)
    start = data.index(b"\xff\xd8")
    with pytest.raises(InputError, match="JPEG plane 0"):
        read_ptm(_write(tmp_path, data[:start] + b"\0" * 8 + data[start + 8:]))


def test_reader_only_raises_input_error_under_fuzzing(tmp_path):
    """A few thousand truncated, bit-flipped and header-mangled files of every layout: the
    reader either returns a consistent PTM or raises InputError, never anything else."""
    rng = np.random.default_rng(1234)
    seeds = sample_files(rng)
    path = tmp_path / "f.ptm"
    cases = 0
    outcomes = {"ok": 0, "error": 0}
    for _ in range(600):
        for name, good in seeds.items():
            header_end = good.index(b"\n", good.index(b"\n", 30) + 1) + 200
            data = mutate(good, rng, header_bytes=header_end, header_lines=15)
            path.write_bytes(bytes(data))
            try:
                ptm = read_ptm(path)
            except InputError as exc:
                assert str(exc).startswith(str(path))
                outcomes["error"] += 1
            else:
                h, w = ptm.height, ptm.width
                assert ptm.coefficients.shape[:2] == (h, w)
                assert ptm.coefficients.shape[-1] == 6
                assert (ptm.rgb is None) == (ptm.coefficients.ndim == 4)
                outcomes["ok"] += 1
            cases += 1
    assert cases == 3000
    assert outcomes["ok"] > 100 and outcomes["error"] > 1000
