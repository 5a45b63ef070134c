import cv2
import numpy as np
import pytest
import tifffile
from PIL import Image

from ptmcore.errors import InputError
from ptmcore.images import SATURATED, linear_to_srgb, load_stack, read_image, srgb_to_linear

from helpers import jpeg_header


def _rgb16(h=6, w=7, seed=0):
    return (np.random.default_rng(seed).random((h, w, 3)) * 60000).astype(np.uint16)


def test_srgb_round_trip_and_known_values():
    v = np.linspace(0, 1, 101, dtype=np.float32)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(v)), v, atol=1e-5)
    # IEC 61966-2-1: sRGB 0.5 is 21.4 % linear light; the linear toe below 0.04045.
    assert srgb_to_linear(np.float32(0.5)) == pytest.approx(0.21404, abs=1e-4)
    assert srgb_to_linear(np.float32(0.04)) == pytest.approx(0.04 / 12.92, rel=1e-5)


def test_reads_every_format_and_depth(tmp_path):
    rgb16 = _rgb16()
    cv2.imwrite(str(tmp_path / "a.png"), rgb16[..., ::-1])
    tifffile.imwrite(tmp_path / "a.tif", rgb16)
    rgb8 = (rgb16 >> 8).astype(np.uint8)
    Image.fromarray(rgb8).save(tmp_path / "a8.png")
    Image.fromarray(rgb8[..., 0]).save(tmp_path / "g8.png")
    Image.fromarray(rgb8).save(tmp_path / "a.jpg", quality=100)
    Image.fromarray(rgb8[..., 1]).save(tmp_path / "g.jpg", quality=100)
    cv2.imwrite(str(tmp_path / "g16.png"), rgb16[..., 2])

    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), rgb16)
    np.testing.assert_array_equal(read_image(tmp_path / "a.tif"), rgb16)
    np.testing.assert_array_equal(read_image(tmp_path / "a8.png"), rgb8)
    np.testing.assert_array_equal(read_image(tmp_path / "g8.png"), rgb8[..., 0])
    np.testing.assert_array_equal(read_image(tmp_path / "g16.png"), rgb16[..., 2])
    jpg = read_image(tmp_path / "a.jpg")
    assert jpg.shape == rgb8.shape and jpg.dtype == np.uint8
    reference = np.asarray(Image.open(tmp_path / "a.jpg"))
    assert np.abs(jpg.astype(int) - reference).max() <= 2  # decoders may differ by rounding
    assert read_image(tmp_path / "g.jpg").shape == rgb8.shape[:2]


def test_corrupt_and_missing_images(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "missing.jpg")
    good = tmp_path / "good.png"
    Image.fromarray(np.zeros((40, 40, 3), np.uint8)).save(good)
    bad = tmp_path / "bad.png"
    bad.write_bytes(good.read_bytes()[:60])
    with pytest.raises(InputError, match="bad.png"):
        read_image(bad)
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"\xff\xd8\xff" + b"\x00" * 50)
    with pytest.raises(InputError, match="junk.jpg"):
        read_image(junk)
    empty = tmp_path / "empty.tif"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_image(empty)


def test_nan_in_float_tiff_is_rejected(tmp_path):
    a = np.full((4, 4), 0.5, np.float32)
    a[1, 1] = np.nan
    tifffile.imwrite(tmp_path / "nan.tif", a)
    with pytest.raises(InputError, match="NaN"):
        read_image(tmp_path / "nan.tif")


def test_stack_linearises_8bit_and_flags_saturation(tmp_path):
    paths = []
    for k, level in enumerate([64, 128, 255]):
        img = np.full((5, 6, 3), level, np.uint8)
        img[0, 0] = (255, 10, 10)  # one clipped channel
        paths.append(tmp_path / f"{k}.png")
        Image.fromarray(img).save(paths[-1])
    stack = load_stack(paths, threads=2)
    values, saturated = stack.band(0, 5)
    assert values.shape == (3, 5, 6) and values.dtype == np.float32
    np.testing.assert_allclose(values[0, 2, 2], srgb_to_linear(np.float32(64 / 255)), rtol=1e-4)
    np.testing.assert_allclose(values[1, 2, 2], srgb_to_linear(np.float32(128 / 255)), rtol=1e-4)
    assert saturated[:, 0, 0].all() and saturated[2].all() and not saturated[:2, 1:, 1:].any()
    assert stack.luminance[0, 0, 0] == SATURATED
    assert list(stack.saturated) == [1, 1, 30]  # the red pixel, then the whole white image
    # Colour: a grey pixel has unit-luminance chroma (1, 1, 1).
    np.testing.assert_allclose(stack.chroma[3, 3], 1.0, rtol=1e-4)

    raw = load_stack(paths, linearize=False)
    np.testing.assert_allclose(raw.band(0, 5)[0][0, 2, 2], 64 / 255, rtol=1e-4)


def test_stack_rejects_mismatched_sizes_and_too_few(tmp_path):
    paths = []
    for k, shape in enumerate([(5, 6), (5, 6), (6, 5)]):
        paths.append(tmp_path / f"{k}.png")
        Image.fromarray(np.zeros(shape, np.uint8)).save(paths[-1])
    with pytest.raises(InputError, match="2.png.*same size"):
        load_stack(paths)
    with pytest.raises(InputError, match="at least 3"):
        load_stack(paths[:2])


def test_chroma_of_a_coloured_surface(tmp_path):
    rgb = np.array([0.5, 0.25, 0.125])
    paths = []
    for k, light in enumerate([1.0, 0.6, 0.3]):
        img = np.round(np.broadcast_to(rgb * light, (4, 5, 3)) * 65535).astype(np.uint16)
        paths.append(tmp_path / f"{k}.tif")
        tifffile.imwrite(paths[-1], img)
    stack = load_stack(paths)
    expected = rgb / (rgb @ [0.2126, 0.7152, 0.0722])
    # Channels are summed as uint16 luminance contributions (blue's weight is 0.07), so a dim
    # blue channel keeps about 12 bits: far finer than the 8-bit colour it ends up in.
    np.testing.assert_allclose(stack.chroma[2, 2], expected, rtol=1e-3)
    values, _ = stack.band(0, 4)
    np.testing.assert_allclose(values[:, 1, 1], np.array([1.0, 0.6, 0.3]) * (rgb @ [0.2126, 0.7152, 0.0722]), rtol=1e-4)


def test_a_header_claiming_too_many_pixels_is_refused_before_decoding(tmp_path):
    import struct
    import zlib

    from ptmcore.errors import InputError
    from ptmcore.images import read_image

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    png = tmp_path / "bomb.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 40000, 40000, 8, 0, 0, 0, 0))
                    + chunk(b"IDAT", zlib.compress(b"\0" * 100)) + chunk(b"IEND", b""))
    with pytest.raises(InputError, match="claims 40000 × 40000 pixels"):
        read_image(png)


def test_pillow_reads_what_this_program_reads_once_allowed(tmp_path):
    """Pillow's own guard (a warning above 89 megapixels, a refusal above 179) stood before
    MAX_PIXELS where Pillow opens a photograph (its EXIF): a 150-megapixel camera's photographs
    printed "decompression bomb" warnings. allow_large_images moves Pillow's limit to this
    program's."""
    import warnings

    from ptmcore.decoders import pillow_image
    from ptmcore.images import MAX_PIXELS, allow_large_images

    larger = tmp_path / "larger.jpg"
    jpeg_header(larger, 15000, 13000)
    with pytest.raises(InputError, match="more pixels than Pillow reads"):
        with pillow_image(larger):
            pass
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        allow_large_images()
        with pillow_image(larger) as im:
            assert im.size == (15000, 13000)
        # Between half this program's limit and the limit, Pillow would still warn on opening.
        huge = tmp_path / "huge.jpg"
        jpeg_header(huge, 25000, 24000)
        with pillow_image(huge) as im:
            assert im.size == (25000, 24000)
    assert not [w for w in seen if issubclass(w.category, Image.DecompressionBombWarning)]
    assert Image.MAX_IMAGE_PIXELS * 2 == MAX_PIXELS
