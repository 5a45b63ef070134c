"""Embedded ICC colour profiles: an Adobe RGB photograph is converted to linear sRGB, an sRGB one
is read exactly as an untagged one, and a profile that cannot be used is refused by name."""

from __future__ import annotations

import zlib
from pathlib import Path

import imagecodecs
import numpy as np
import pytest
import simplejpeg
import tifffile
from PIL import Image, ImageCms

from ptmcore.decoders import (
    MAX_PROFILE_BYTES,
    _linear_profile,
    colour_description,
    embedded_profile,
    profile_is_srgb,
)
from ptmcore.errors import InputError
from ptmcore.images import read_image, srgb_to_linear

D65 = [0.3127, 0.3290, 1.0]
ADOBE = imagecodecs.cms_profile("rgb", whitepoint=D65, primaries=[0.64, 0.33, 1, 0.21, 0.71, 1, 0.15, 0.06, 1],
                                gamma=563 / 256)
SRGB = imagecodecs.cms_profile("srgb")
LINEAR = _linear_profile("rgb")


def _truth(h: int = 48, w: int = 64) -> np.ndarray:
    """Smooth linear colours inside sRGB's gamut (so inside Adobe RGB's): JPEG keeps them well."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    r = 0.05 + 0.85 * x / (w - 1)
    g = 0.05 + 0.85 * y / (h - 1)
    b = 0.05 + 0.4 * (1 + np.sin(x / 9 + y / 13))
    return np.stack([r, g, b], -1).astype(np.float32)


def _to_adobe(linear: np.ndarray, dtype=np.uint8) -> np.ndarray:
    return imagecodecs.cms_transform(linear, LINEAR, ADOBE, colorspace="rgb", outcolorspace="rgb",
                                     outdtype=dtype, intent=1)


def _with_icc(jpeg: bytes, profile: bytes, chunk: int = 65519, order=None) -> bytes:
    """A JPEG with ``profile`` in APP2 ICC_PROFILE segments right after SOI."""
    parts = [profile[k:k + chunk] for k in range(0, len(profile), chunk)]
    segments = []
    for seq, part in enumerate(parts, 1):
        payload = b"ICC_PROFILE\x00" + bytes([seq, len(parts)]) + part
        segments.append(b"\xff\xe2" + (len(payload) + 2).to_bytes(2, "big") + payload)
    if order is not None:
        segments = [segments[k] for k in order]
    return jpeg[:2] + b"".join(segments) + jpeg[2:]


def _png_with_iccp(png: bytes, compressed: bytes, name: bytes = b"icc") -> bytes:
    body = name + b"\x00\x00" + compressed
    chunk = len(body).to_bytes(4, "big") + b"iCCP" + body + zlib.crc32(b"iCCP" + body).to_bytes(4, "big")
    end_ihdr = 8 + 8 + 13 + 4
    return png[:end_ihdr] + chunk + png[end_ihdr:]


def test_destination_is_linear_srgb():
    codes = np.arange(256, dtype=np.uint8)
    img = np.stack([*np.meshgrid(codes, codes[::-1], indexing="ij"), np.full((256, 256), 200, np.uint8)], -1)
    out = imagecodecs.cms_transform(img, SRGB, LINEAR, colorspace="rgb", outcolorspace="rgb",
                                    outdtype=np.float32, intent=1)
    np.testing.assert_allclose(out, srgb_to_linear(img / np.float32(255)), atol=1e-3)


def test_srgb_verdicts():
    assert profile_is_srgb(SRGB)
    assert profile_is_srgb(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    assert not profile_is_srgb(ADOBE)
    # sRGB's primaries with a plain gamma 2.2 differ in the shadows: not sRGB.
    gamma22 = imagecodecs.cms_profile("rgb", whitepoint=D65, primaries=[0.64, 0.33, 1, 0.30, 0.60, 1, 0.15, 0.06, 1],
                                      gamma=2.2)
    assert not profile_is_srgb(gamma22)


@pytest.mark.parametrize("kind", ["jpeg", "jpeg-chunks", "png", "tiff"])
def test_adobe_rgb_converted_to_linear(tmp_path: Path, kind: str):
    truth = _truth()
    adobe = _to_adobe(truth)
    path = tmp_path / f"adobe.{kind[:4]}"
    if kind.startswith("jpeg"):
        jpeg = simplejpeg.encode_jpeg(adobe, quality=98, colorsubsampling="444")
        if kind == "jpeg":
            path.write_bytes(_with_icc(jpeg, ADOBE))
        else:  # several chunks, stored out of order: the sequence numbers put them back
            path.write_bytes(_with_icc(jpeg, ADOBE, chunk=-(-len(ADOBE) // 4), order=[2, 0, 3, 1]))
        tol = 0.03
    elif kind == "png":
        Image.fromarray(adobe).save(path, icc_profile=ADOBE)
        tol = 0.01
    else:
        tifffile.imwrite(path, adobe, photometric="rgb", extratags=[(34675, 7, len(ADOBE), ADOBE, True)])
        tol = 0.01
    img = read_image(path)
    assert img.dtype == np.float32 and img.shape == truth.shape
    assert img.min() >= 0
    np.testing.assert_allclose(img, truth, atol=tol)
    assert colour_description(path).endswith("(embedded; converted to linear sRGB)")


def test_adobe_rgb_16_bit_tiff(tmp_path: Path):
    truth = _truth()
    path = tmp_path / "adobe16.tif"
    tifffile.imwrite(path, _to_adobe(truth, np.uint16), photometric="rgb",
                     extratags=[(34675, 7, len(ADOBE), ADOBE, True)])
    img = read_image(path)
    assert img.dtype == np.float32
    np.testing.assert_allclose(img, truth, atol=2e-3)


def test_srgb_tagged_reads_as_untagged(tmp_path: Path):
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 256, (40, 56, 3), dtype=np.uint8)
    jpeg = simplejpeg.encode_jpeg(pixels, quality=90)
    plain, tagged = tmp_path / "plain.jpg", tmp_path / "tagged.jpg"
    plain.write_bytes(jpeg)
    tagged.write_bytes(_with_icc(jpeg, ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()))
    a, b = read_image(plain), read_image(tagged)
    assert a.dtype == b.dtype == np.uint8
    assert np.array_equal(a, b)
    assert colour_description(plain) == "sRGB (no embedded profile)"
    assert colour_description(tagged).endswith(" (embedded, sRGB)")

    # 16-bit with an sRGB profile: as without one (taken as linear), unchanged.
    deep = (pixels.astype(np.uint16) * 257)
    png16 = tmp_path / "deep.png"
    # Pillow does not write 16-bit RGB PNG: imagecodecs does, and the iCCP chunk is added.
    png16.write_bytes(_png_with_iccp(imagecodecs.png_encode(deep), zlib.compress(SRGB)))
    out = read_image(png16)
    assert out.dtype == np.uint16 and np.array_equal(out, deep)


def test_grey_profile(tmp_path: Path):
    grey22 = imagecodecs.cms_profile("gray", gamma=2.2)
    codes = np.tile(np.arange(256, dtype=np.uint8), (4, 1))
    path = tmp_path / "grey.png"
    Image.fromarray(codes, "L").save(path, icc_profile=grey22)
    img = read_image(path)
    assert img.dtype == np.float32 and img.shape == codes.shape
    np.testing.assert_allclose(img, (codes / 255.0) ** 2.2, atol=1e-3)


def test_damaged_profiles_refused(tmp_path: Path):
    jpeg = simplejpeg.encode_jpeg(np.full((16, 16, 3), 128, np.uint8))
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(_with_icc(jpeg, b"not a profile at all " * 20))
    truncated = tmp_path / "truncated.jpg"
    truncated.write_bytes(_with_icc(jpeg, ADOBE[:200]))
    corrupt = bytearray(ADOBE)
    corrupt[132:] = b"\xff" * (len(ADOBE) - 132)  # the tag table
    refused = tmp_path / "refused.jpg"
    refused.write_bytes(_with_icc(jpeg, bytes(corrupt)))
    missing = tmp_path / "missing.jpg"
    missing.write_bytes(_with_icc(jpeg, ADOBE, chunk=200, order=[0, 2]))
    lab = tmp_path / "lab.jpg"
    lab.write_bytes(_with_icc(jpeg, ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes()))
    for path in (garbage, truncated, refused, missing, lab):
        with pytest.raises(InputError, match="embedded colour profile cannot be used") as info:
            read_image(path)
        assert path.name in str(info.value) and "\n" not in str(info.value)
        with pytest.raises(InputError, match=path.name):
            colour_description(path)


def test_png_damaged_or_oversized_iccp(tmp_path: Path):
    png = imagecodecs.png_encode(np.full((8, 8, 3), 100, np.uint8))
    big = tmp_path / "big.png"
    big.write_bytes(_png_with_iccp(png, zlib.compress(b"\0" * (MAX_PROFILE_BYTES + 10))))
    with pytest.raises(InputError, match="big.png: embedded colour profile cannot be used: it is larger"):
        read_image(big)
    with pytest.raises(InputError, match="larger"):
        embedded_profile(big)
    broken = tmp_path / "broken.png"
    broken.write_bytes(_png_with_iccp(png, zlib.compress(ADOBE)[:-20]))
    with pytest.raises(InputError, match="broken.png: embedded colour profile cannot be used"):
        read_image(broken)


def test_grey_image_with_rgb_profile_refused(tmp_path: Path):
    path = tmp_path / "grey-adobe.tif"
    tifffile.imwrite(path, np.full((8, 8), 90, np.uint8), extratags=[(34675, 7, len(ADOBE), ADOBE, True)])
    with pytest.raises(InputError, match="grey-adobe.tif: embedded colour profile cannot be used: it is RGB"):
        read_image(path)
