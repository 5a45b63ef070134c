"""Property-based fuzzing of the readers of small input files: ``.lp`` light files, ``--mask``
images and normal maps (``.npy`` and images).

Whatever the bytes (arbitrary, malformed text, valid files truncated or with bytes changed,
arrays of odd shapes and types), each reader either returns a result that keeps its promises
or raises :class:`InputError` naming the file, never another exception. The PTM and RTI
readers have the same kind of test (tests/test_ptmfile.py, tests/test_rtifile.py).
"""

from __future__ import annotations

import io
import math
import struct
import zlib

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays
from PIL import Image

from ptmcore.errors import InputError
from ptmcore.lp import MIN_ELEVATION_DEG, read_lp
from reconstruct.pipeline.capture import read_mask
from reconstruct.surface.normalmaps import read_normal_map

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    # Module-scoped: hypothesis runs many examples in one call of the test function.
    return tmp_path_factory.mktemp("fuzz")


def _outcome(read, path):
    """``read(path)``, or None when it raised an InputError naming ``path``; any other
    exception fails the test."""
    try:
        return read(path)
    except InputError as exc:
        assert str(exc).startswith(str(path)), str(exc)
        return None


def _read_written(path, data: bytes, read, check) -> None:
    """Write ``data`` as ``path``, read it (:func:`_outcome`) and ``check`` what was read."""
    path.write_bytes(data)
    result = _outcome(read, path)
    if result is not None:
        check(result)


def mutated(good: bytes, header: int = 128) -> st.SearchStrategy[bytes]:
    """A valid file truncated, with bytes changed (mostly in its first ``header`` bytes), or
    with bytes inserted."""
    n = len(good)

    def changed(edits: list[tuple[int, int]]) -> bytes:
        data = bytearray(good)
        for pos, value in edits:
            data[pos % n] = value
        return bytes(data)

    position = st.one_of(st.integers(0, min(n, header) - 1), st.integers(0, n - 1))
    return st.one_of(
        st.integers(0, n - 1).map(lambda k: good[:k]),
        st.lists(st.tuples(position, st.integers(0, 255)), min_size=1, max_size=6).map(changed),
        st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=24)).map(
            lambda t: good[: t[0]] + t[1] + good[t[0]:]),
    )


# --- .lp light files --------------------------------------------------------------------------

_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-2, 2).map(lambda v: f"{v:.6f}"),
    st.integers(-(10**7), 10**7).map(str),
    st.sampled_from(["0", "1", "-0", "0.5", "1e200", "-1e200", "1e-300", "1e400", "nan", "inf",
                     "-inf", "x", "1,0", "0x10", "1_0", "+.5", "٣"]),
)
_LINE_BREAKS = "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"
_NAME = st.one_of(
    st.sampled_from(["a.jpg", "b.jpg", "img 01.tif", "C:\\capture\\a.jpg", "/abs/x.png", "..", "C:\\"]),
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters=_LINE_BREAKS), max_size=12),
)
_ENTRY = st.one_of(
    st.tuples(_NAME, _NUMBER, _NUMBER, _NUMBER).map(" ".join),
    # Mostly sensible directions, so that many files are valid and their results are checked.
    st.tuples(_NAME, st.floats(-1, 1), st.floats(-1, 1), st.floats(0.01, 1)).map(
        lambda t: f"{t[0]} {t[1]!r} {t[2]!r} {t[3]!r}"),
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters=_LINE_BREAKS), max_size=30),
)


@st.composite
def lp_texts(draw) -> str:
    entries = draw(st.lists(_ENTRY, max_size=9))
    count = draw(st.one_of(st.just(str(len(entries))), _NUMBER, st.just(f"{len(entries)} extra")))
    lines = [count, *entries]
    for _ in range(draw(st.integers(0, 2))):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(["", "# comment", "   "])))
    text = draw(st.sampled_from(["\n", "\r\n", "\r"])).join(lines)
    return draw(st.sampled_from(["", "\ufeff"])) + text


def _check_lights(lights) -> None:
    assert len(lights) >= 3 and len(lights.paths) == len(lights.directions)
    d = lights.directions
    assert d.shape == (len(lights), 3) and d.dtype == np.float64
    assert np.all(np.isfinite(d))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-9)
    assert np.all(d[:, 2] > math.sin(math.radians(MIN_ELEVATION_DEG)))
    assert all(p.name for p in lights.paths)
    assert all(isinstance(w, str) and w for w in lights.warnings)


@FUZZ
@given(text=lp_texts())
def test_lp_reader_on_malformed_text(folder, text):
    path = folder / "lights.lp"
    path.write_text(text, encoding="utf-8", newline="")
    lights = _outcome(read_lp, path)
    if lights is not None:
        _check_lights(lights)


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), mutated(b"3\na.jpg 0.5 0 0.866\nb.jpg 0 0.5 0.866\n"
                                                        b"C:\\x\\c.jpg 0 0 1\n", header=80)))
def test_lp_reader_on_arbitrary_bytes(folder, data):
    _read_written(folder / "bytes.lp", data, read_lp, _check_lights)


def test_lp_fuzzing_reaches_valid_files(folder):
    """The text strategy is not vacuous: valid files come out of it (checked by the tests
    above), and so do duplicates, whose warnings name their lines."""
    path = folder / "dup.lp"
    path.write_text("4\na.jpg 0 0 1\nb.jpg 0 0 1\nc.jpg 0 1 1\na.jpg 1 0 1\n")
    lights = read_lp(path)
    _check_lights(lights)
    assert any("lines 2 and 5" in w for w in lights.warnings)


# --- --mask images ----------------------------------------------------------------------------

_MASK_SHAPE = (6, 7)


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def _tiff(img: np.ndarray) -> bytes:
    out = io.BytesIO()
    colour = img.ndim == 3 and img.shape[2] in (3, 4)
    tifffile.imwrite(out, img, photometric="rgb" if colour else "minisblack")
    return out.getvalue()


def _jpeg(img: np.ndarray) -> bytes:
    out = io.BytesIO()
    Image.fromarray(img).save(out, "JPEG")
    return out.getvalue()


_rng = np.random.default_rng(16)
_MASK_SEEDS = [
    _png(((_rng.random(_MASK_SHAPE) > 0.5) * 255).astype(np.uint8)),
    _png((_rng.random((*_MASK_SHAPE, 3)) * 65535).astype(np.uint16)),
    _tiff((_rng.random(_MASK_SHAPE) > 0.5).astype(np.uint8)),
    _tiff(_rng.random(_MASK_SHAPE).astype(np.float32)),
    _jpeg((_rng.random((*_MASK_SHAPE, 3)) * 255).astype(np.uint8)),
]


def _check_mask(mask, shape) -> None:
    assert mask.dtype == bool and mask.shape == shape
    assert mask.any()


@FUZZ
@given(data=st.one_of(st.binary(max_size=400), *(mutated(seed) for seed in _MASK_SEEDS)))
def test_mask_reader_on_arbitrary_and_damaged_files(folder, data):
    _read_written(folder / "mask.png", data, lambda p: read_mask(p, _MASK_SHAPE),
                  lambda mask: _check_mask(mask, _MASK_SHAPE))


@FUZZ
@given(
    image=st.one_of(
        arrays(st.sampled_from([np.uint8, np.uint16]), array_shapes(min_dims=2, max_dims=2, max_side=9)),
        arrays(st.sampled_from([np.uint8, np.uint16]), st.tuples(st.integers(1, 9), st.integers(1, 9),
                                                                 st.sampled_from([1, 3, 4]))),
        arrays(np.float32, array_shapes(min_dims=2, max_dims=2, max_side=9),
               elements=st.floats(-2, 2, width=32)),
    ),
    asked=st.tuples(st.integers(1, 9), st.integers(1, 9)),
    kind=st.sampled_from(["png", "tif"]),
)
def test_mask_reader_on_odd_sizes_and_types(folder, image, asked, kind):
    if kind == "png" and image.dtype == np.float32:
        kind = "tif"  # PNG holds no floats
    path = folder / f"mask.{kind}"
    path.write_bytes(_png(image) if kind == "png" else _tiff(image))
    mask = _outcome(lambda p: read_mask(p, asked), path)
    if mask is not None:
        _check_mask(mask, asked)
        assert image.shape[:2] == asked


def _forged_png(width: int, height: int, depth: int, colour: int) -> bytes:
    """A small PNG whose header claims another size, bit depth and colour type (its checksum
    recomputed, so that the claim is believed)."""
    data = bytearray(_MASK_SEEDS[0])
    data[16:26] = struct.pack(">IIBB", width, height, depth, colour)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


def _forged_bmp(width: int, height: int) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.zeros(_MASK_SHAPE, np.uint8)).save(out, "BMP")
    data = bytearray(out.getvalue())
    data[18:26] = struct.pack("<ii", width, height)
    return bytes(data)


# Either a few pixels or at least 2^32, beyond every decoder's limit: sizes in between could
# make a decoder allocate gigabytes before it finds the data missing.
_CLAIMED = st.one_of(st.tuples(st.integers(1, 64), st.integers(1, 64)),
                     st.tuples(st.integers(2**16, 2**31 - 1), st.integers(2**16, 2**31 - 1)))


@FUZZ
@given(data=st.one_of(
    st.builds(lambda size, depth, colour: _forged_png(*size, depth, colour), _CLAIMED,
              st.sampled_from([1, 2, 4, 8, 16, 3]), st.sampled_from([0, 2, 3, 4, 6, 1])),
    st.builds(lambda size, flip: _forged_bmp(size[0], -size[1] if flip else size[1]), _CLAIMED, st.booleans()),
    mutated(_forged_bmp(*_MASK_SHAPE[::-1]), header=60),
))
def test_mask_reader_on_forged_headers(folder, data):
    _read_written(folder / "forged_mask.png", data, lambda p: read_mask(p, _MASK_SHAPE),
                  lambda mask: _check_mask(mask, _MASK_SHAPE))


# --- normal maps ------------------------------------------------------------------------------

def _npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, array, allow_pickle=True)
    return out.getvalue()


_NORMALS = _rng.normal(size=(4, 5, 3)) + [0, 0, 2]
_NPY_SEEDS = [_npy(_NORMALS.astype(np.float32)), _npy(np.asfortranarray(_NORMALS)),
              _npy(_NORMALS.astype(">f8"))]


def _check_normals(n: np.ndarray) -> None:
    assert n.dtype == np.float32 and n.ndim == 3 and n.shape[2] == 3
    assert min(n.shape[:2]) >= 2
    valid = np.isfinite(n).all(axis=2)
    assert valid.any()
    assert np.all(np.isnan(n[~valid]))  # a pixel is a whole normal or none
    np.testing.assert_allclose(np.linalg.norm(n[valid], axis=1), 1.0, atol=1e-5)
    assert np.all(n[valid][:, 2] > 0)


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), *(mutated(seed, header=128) for seed in _NPY_SEEDS)))
def test_normal_map_reader_on_arbitrary_and_damaged_npy(folder, data):
    _read_written(folder / "normals.npy", data, read_normal_map, _check_normals)


_DTYPES = st.sampled_from([np.float16, np.float32, np.float64, ">f4", np.int16, np.uint8, np.bool_,
                           np.complex64])


@FUZZ
@given(
    array=st.one_of(
        arrays(_DTYPES, array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5)),
        arrays(_DTYPES, st.tuples(st.integers(0, 5), st.integers(0, 5), st.just(3))),
        arrays(st.sampled_from([np.float32, np.float64]), st.tuples(st.integers(1, 5), st.integers(1, 5),
                                                                     st.just(3)),
               elements=st.floats(allow_nan=True, allow_infinity=True, width=32)),
    ),
)
def test_normal_map_reader_on_odd_arrays(folder, array):
    path = folder / "arrays.npy"
    path.write_bytes(_npy(array))
    normals = _outcome(read_normal_map, path)
    if normals is not None:
        _check_normals(normals)
        assert array.dtype.kind == "f" and normals.shape == array.shape


def test_normal_map_reader_refuses_pickled_objects(folder):
    path = folder / "objects.npy"
    path.write_bytes(_npy(np.array([{"x": 1}, None], dtype=object)))
    with pytest.raises(InputError, match="Python objects"):
        read_normal_map(path)


@FUZZ
@given(
    image=arrays(st.sampled_from([np.uint8, np.uint16]),
                 st.tuples(st.integers(1, 6), st.integers(1, 6), st.sampled_from([1, 3, 4]))),
    damage=st.one_of(st.none(), st.tuples(st.integers(0, 200), st.integers(0, 255))),
)
def test_normal_map_reader_on_odd_images(folder, image, damage):
    data = bytearray(_png(image))
    if damage is not None:
        data[damage[0] % len(data)] = damage[1]
    path = folder / "normals.png"
    path.write_bytes(bytes(data))
    normals = _outcome(read_normal_map, path)
    if normals is not None:
        _check_normals(normals)
