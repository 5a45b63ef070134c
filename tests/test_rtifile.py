import struct

import numpy as np
import pytest
from PIL import Image

from helpers import mutate
from ptmcore.errors import InputError
from ptmcore.hsh import hsh_basis
from ptmcore.ptmfile import write_ptm
from ptmcore.rtifile import RTIFile, fit_rti_hsh, read_rti_hsh, render_float, write_rti_hsh

H, W = 24, 32


def _lights():
    d = []
    for el in np.radians([20, 35, 50, 65, 80]):
        for az in np.radians(np.arange(0, 360, 36)):
            d.append([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return np.array(d)


def _lambertian_capture():
    """Photographs (bytes, in their own encoding) of a bumpy coloured Lambertian surface."""
    yy, xx = np.mgrid[0:H, 0:W]
    n = np.stack([0.3 * np.sin(xx / 5.0), 0.3 * np.cos(yy / 4.0), np.ones((H, W))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    albedo = np.stack([np.full((H, W), 0.9), 0.6 + 0.2 * xx / W, np.full((H, W), 0.4)], -1)
    d = _lights()
    photos = np.stack(
        [np.round(255 * albedo * np.clip(n @ l, 0, None)[..., None]).astype(np.uint8) for l in d]
    )
    return photos, d


@pytest.fixture(scope="module")
def capture():
    return _lambertian_capture()


def _write(tmp_path, data, name="x.rti"):
    p = tmp_path / name
    p.write_bytes(data)
    return p


def _rti(w=3, h=2, terms=9, scale=None, bias=None, payload=None, head=None):
    scale = np.ones(terms, np.float32) if scale is None else np.asarray(scale, np.float32)
    bias = np.zeros(terms, np.float32) if bias is None else np.asarray(bias, np.float32)
    if payload is None:
        payload = bytes(range(256)) * (w * h * 3 * terms // 256 + 1)
        payload = payload[: w * h * 3 * terms]
    head = head if head is not None else f"#HSH1.2\n3\n{w} {h} 3\n{terms} 2 1\n".encode()
    return head + scale.astype("<f4").tobytes() + bias.astype("<f4").tobytes() + payload


# --- the format -----------------------------------------------------------------------------


def test_decoding_and_payload_order(tmp_path):
    """byte/255·scale + bias; pixel by pixel from the bottom row; R terms, G terms, B terms."""
    w, h, k = 3, 2, 4
    scale = np.array([2.0, 1.0, 0.5, 4.0])
    bias = np.array([-1.0, 0.0, 0.25, -2.0])
    payload = np.arange(w * h * 3 * k, dtype=np.uint8)
    f = read_rti_hsh(_write(tmp_path, _rti(w, h, k, scale, bias, payload.tobytes())))
    assert (f.width, f.height, f.order, f.basis_type) == (3, 2, 2, 2)
    raw = payload.reshape(h, w, 3, k)[::-1]  # file row 0 is the bottom image row
    expect = raw / 255.0 * scale + bias
    np.testing.assert_allclose(f.coefficients, expect, rtol=1e-6, atol=1e-6)
    assert f.coefficients.dtype == np.float32 and f.coefficients.shape == (h, w, 3, k)
    # First stored bytes: bottom-left pixel, red band's 4 terms then green's.
    np.testing.assert_allclose(f.coefficients[h - 1, 0, 0], np.arange(4) / 255 * scale + bias, atol=1e-6)
    np.testing.assert_allclose(f.coefficients[h - 1, 0, 1], np.arange(4, 8) / 255 * scale + bias, atol=1e-6)


def test_render_is_rtiviewer_truncation_of_255_times_the_sum(tmp_path):
    c = np.zeros((1, 4, 3, 9), np.float32)
    light = np.array([0.3, -0.2, 0.9])
    hw = hsh_basis(light.reshape(1, 3), 3)[0]
    # Values chosen so 255·Σ c_k H_k is 10.7, −3, 300 and 254.999 in the red band.
    for col, target in enumerate([10.7 / 255, -3 / 255, 300 / 255, 254.999 / 255]):
        c[0, col, 0, 0] = target / hw[0]
    f = RTIFile(4, 1, 3, 2, np.ones(9, np.float32), np.zeros(9, np.float32), c)
    np.testing.assert_array_equal(f.render(light)[0, :, 0], [10, 0, 255, 254])


def test_header_structure(tmp_path, capture):
    photos, d = capture
    c = fit_rti_hsh(photos, d, 3)
    p = tmp_path / "cap.rti"
    info = write_rti_hsh(p, c, order=3)
    data = p.read_bytes()
    head = f"#HSH1.2\n3\n{W} {H} 3\n9 2 1\n".encode()
    assert data.startswith(head)
    assert len(data) == len(head) + 8 * 9 + W * H * 3 * 9 == info["bytes"]
    scale = np.frombuffer(data, "<f4", 9, len(head))
    bias = np.frombuffer(data, "<f4", 9, len(head) + 36)
    np.testing.assert_array_equal(scale, np.float32(info["scale"]))
    np.testing.assert_array_equal(bias, np.float32(info["bias"]))
    # RTIBuilder's rule: bias = min, scale = max − min of each term over the image and bands.
    flat = c.reshape(-1, 9)
    np.testing.assert_allclose(bias, flat.min(0), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(scale, flat.max(0) - flat.min(0), rtol=1e-5, atol=1e-7)
    first = np.frombuffer(data, np.uint8, 27, len(head) + 72)
    # Bottom-left pixel first, codes 0..255 spanning min..max.
    np.testing.assert_array_equal(
        first.reshape(3, 9), np.clip(np.floor((c[H - 1, 0] - bias) / scale * 255 + 0.5), 0, 255)
    )


# --- round trip and rendering ---------------------------------------------------------------


@pytest.mark.parametrize("order", [2, 3])
def test_round_trip_within_half_a_step(tmp_path, order):
    rng = np.random.default_rng(order)
    k = order * order
    c = (rng.normal(size=(7, 5, 3, k)) * rng.uniform(0.01, 2, k)).astype(np.float32)
    p = tmp_path / "r.rti"
    info = write_rti_hsh(p, c, order=order)
    f = read_rti_hsh(p)
    assert (f.width, f.height, f.order) == (5, 7, order)
    half = np.array(info["scale"]) / 510
    err = np.abs(f.coefficients.astype(np.float64) - c).reshape(-1, k).max(0)
    assert np.all(err <= half * 1.0001 + 1e-7)
    np.testing.assert_allclose(info["max_error"], err, rtol=1e-4, atol=1e-7)


def test_constant_term_round_trips(tmp_path):
    c = np.zeros((2, 2, 3, 4), np.float32)
    c[..., 0] = 0.5
    p = tmp_path / "c.rti"
    write_rti_hsh(p, c, order=2)
    np.testing.assert_array_equal(read_rti_hsh(p).coefficients, c)


@pytest.mark.parametrize(
    "order, photo_max, photo_mean, overall_mean", [(2, 14, 5.0, 2.5), (3, 5, 1.2, 0.8)]
)
def test_render_reproduces_lambertian_capture(tmp_path, capture, order, photo_max, photo_mean,
                                              overall_mean):
    """Measured against the 50 photographs: order 3 at most 4 levels off, worst photograph's
    mean 0.93, overall mean 0.66; order 2 at most 13, 4.2 and 1.97 (its 4 terms cannot follow
    the Lambertian falloff at low lights);
    the 8-bit render is within RTIViewer's truncation (1 level) plus the quantisation bound
    Σ_k |H_k| · scale_k/510 · 255 of the exact float render."""
    photos, d = capture
    c = fit_rti_hsh(photos, d, order)
    p = tmp_path / "cap.rti"
    info = write_rti_hsh(p, c, order=order)
    f = read_rti_hsh(p)
    half = np.array(info["scale"]) / 510
    basis = hsh_basis(d, order)
    means = []
    for k, light in enumerate(d):
        shown = f.render(light).astype(np.float64)
        exact = 255 * render_float(c, light)
        bound = 1 + 255 * np.abs(basis[k]) @ half + 1e-3
        inside = (exact > 0) & (exact < 255)
        assert np.all(np.abs(shown - exact)[inside] <= bound)
        diff = np.abs(shown - photos[k])
        assert diff.max() <= photo_max and diff.mean() <= photo_mean
        means.append(diff.mean())
    assert np.mean(means) <= overall_mean


def test_fit_from_files_equals_fit_from_arrays(tmp_path, capture):
    photos, d = capture
    paths = []
    for k in range(6):
        paths.append(tmp_path / f"p{k}.png")
        Image.fromarray(photos[k]).save(paths[-1])
    np.testing.assert_allclose(fit_rti_hsh(paths, d[:6], 2), fit_rti_hsh(photos[:6], d[:6], 2), atol=1e-6)


def test_fit_rejects_mismatched_sizes_and_nothing():
    d = _lights()[:2]
    with pytest.raises(InputError, match="same size"):
        fit_rti_hsh([np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5, 3), np.uint8)], d, 2)
    with pytest.raises(InputError):
        fit_rti_hsh([], np.zeros((0, 3)), 2)


def test_writer_rejects_bad_arrays(tmp_path):
    with pytest.raises(ValueError):
        write_rti_hsh(tmp_path / "a.rti", np.zeros((2, 2, 3, 9)), order=2)
    with pytest.raises(ValueError):
        write_rti_hsh(tmp_path / "a.rti", np.zeros((2, 2, 3, 16)), order=4)
    bad = np.zeros((2, 2, 3, 4))
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError):
        write_rti_hsh(tmp_path / "a.rti", bad, order=2)
    with pytest.raises(InputError):
        write_rti_hsh(tmp_path / "missing" / "a.rti", np.zeros((2, 2, 3, 4)), order=2)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("h, w, dtype, message", [
    (0, 2, np.float32, "hold no pixels"),
    (2, 0, np.float32, "hold no pixels"),
    (2, 2, bool, "must be numbers"),
])
def test_rti_and_ptm_writers_refuse_unwritable_coefficients_alike(tmp_path, h, w, dtype, message):
    with pytest.raises(ValueError, match=message):
        write_rti_hsh(tmp_path / "a.rti", np.zeros((h, w, 3, 4), dtype), order=2)
    with pytest.raises(ValueError, match=message):
        write_ptm(tmp_path / "a.ptm", np.zeros((h, w, 3, 6), dtype))
    assert not list(tmp_path.iterdir())


# --- hostile input --------------------------------------------------------------------------

GOOD = _rti()


@pytest.mark.parametrize(
    "data, message",
    [
        (b"", "empty"),
        (b"PTM_1.2\nPTM_FORMAT_LRGB\n", "ptm"),
        (b"hello", "comment"),
        (b"#HSH1.2", "truncated"),
        (GOOD.replace(b"\n3\n", b"\n1\n", 1), "file type 1"),
        (GOOD.replace(b"\n3\n", b"\nthree\n", 1), "file type"),
        (GOOD.replace(b"3 2 3\n", b"3 2\n"), "width height bands"),
        (GOOD.replace(b"3 2 3\n", b"0 2 3\n"), "not positive"),
        (GOOD.replace(b"3 2 3\n", b"3 2 4\n"), "colour bands"),
        (GOOD.replace(b"3 2 3\n", b"99999999 99999999 3\n"), "truncated"),
        (GOOD.replace(b"3 2 3\n", b"3.5 2 3\n"), "integer"),
        (GOOD.replace(b"9 2 1\n", b"9 2 2\n"), "element size"),
        (GOOD.replace(b"9 2 1\n", b"16 2 1\n"), "16-term"),
        (GOOD.replace(b"9 2 1\n", b"7 2 1\n"), "7 terms"),
        (GOOD[:-1], "truncated"),
        (b"#HSH1.2\n3\n" + b"1" * 1000, "short text line"),
        (b"#HSH1.2\n\xff\xfe\n", "not text"),
        (_rti(scale=[np.nan] + [1] * 8), "finite"),
        (_rti(bias=[np.inf] + [0] * 8), "finite"),
    ],
)
def test_bad_files_raise_input_error(tmp_path, data, message):
    p = _write(tmp_path, data)
    with pytest.raises(InputError, match=message) as exc:
        read_rti_hsh(p)
    assert str(exc.value).startswith(str(p))


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_rti_hsh(tmp_path / "none.rti")
    with pytest.raises(InputError, match="folder"):
        read_rti_hsh(tmp_path)


def test_reader_only_raises_input_error_under_fuzzing(tmp_path):
    """1,000 truncated, byte-flipped, token-mangled and line-shuffled files: the reader either
    returns a consistent file or raises InputError naming it, never anything else."""
    rng = np.random.default_rng(99)
    seeds = [_rti(), _rti(4, 3, 4, scale=[0.5, 1, 2, 3], bias=[-1, 0, 1, 2])]
    path = tmp_path / "f.rti"
    outcomes = {"ok": 0, "error": 0}
    for case in range(1000):
        good = seeds[case % 2]
        data = mutate(good, rng, header_bytes=60, header_lines=5)
        path.write_bytes(bytes(data))
        try:
            f = read_rti_hsh(path)
        except InputError as exc:
            assert str(exc).startswith(str(path))
            outcomes["error"] += 1
        else:
            assert f.coefficients.shape == (f.height, f.width, 3, f.order**2)
            assert np.all(np.isfinite(f.coefficients))
            f.render([0.1, 0.2, 0.9])
            outcomes["ok"] += 1
    assert outcomes["ok"] > 50 and outcomes["error"] > 300


def test_struct_little_endian_floats(tmp_path):
    """The scales and biases are binary little-endian float32 (fwrite on x86), not text."""
    data = _rti(2, 1, 4, scale=[1.5, 0, 0, 0], bias=[0.25, 0, 0, 0], payload=bytes(24))
    head = b"#HSH1.2\n3\n2 1 3\n4 2 1\n"
    assert data[len(head):len(head) + 4] == struct.pack("<f", 1.5)
    f = read_rti_hsh(_write(tmp_path, data))
    np.testing.assert_allclose(f.coefficients[..., 0], 0.25)
