"""Photographs, masks and textures from hostile or unusual files (issue 36).

Only JPEG, PNG and TIFF are decoded, each by a decoder chosen from the file's content: nothing
a file holds may start a program (Pillow gives PostScript to Ghostscript), block the run (a
named pipe), or allocate what its header claims beyond what its bytes and the memory allow.
The colour models photographs come in are read for what they mean, not as RGB.
"""

from __future__ import annotations

import io
import os
import re
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from ptmcore import decoders
from ptmcore.decoders import image_size, pillow_image
from ptmcore.errors import InputError
from ptmcore.images import read_image

from helpers import jpeg_header

POSTSCRIPT = (b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 160 120\n"
              b"/f (MARKER) (w) file def f (x) writestring f closefile\n"
              b".5 .5 .5 setrgbcolor 0 0 160 120 rectfill showpage\n")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_subprocess(monkeypatch):
    """Fail the test if anything starts a program."""
    def refuse(*args, **kwargs):
        raise AssertionError(f"a subprocess was started: {args[:1]}")

    monkeypatch.setattr(subprocess.Popen, "__init__", refuse)
    monkeypatch.setattr(os, "system", refuse)
    monkeypatch.setattr(os, "posix_spawn", refuse, raising=False)


def _postscript(path: Path, marker: Path) -> Path:
    path.write_bytes(POSTSCRIPT.replace(b"MARKER", str(marker).encode()))
    return path


def _rgb8(h=30, w=40, seed=0):
    return (np.random.default_rng(seed).random((h, w, 3)) * 255).astype(np.uint8)


def test_a_postscript_file_named_jpg_is_refused_by_every_reader(tmp_path, no_subprocess):
    from reconstruct.calibration.camera import intrinsics_from_exif
    from reconstruct.report.figures import downscale_file, photograph_thumbnail

    marker = tmp_path / "PWNED"
    ps = _postscript(tmp_path / "img_002.jpg", marker)
    readers = [read_image, photograph_thumbnail, downscale_file, intrinsics_from_exif]
    for reader in readers:
        with pytest.raises(InputError, match="is PostScript, not a JPEG, PNG or TIFF image"):
            reader(ps)
    with pytest.raises(InputError, match="is PostScript"):
        with pillow_image(ps):
            pass
    assert image_size(ps) is None
    assert not marker.exists()


def test_a_postscript_photograph_stops_a_run_with_one_line(tmp_path, capsys, no_subprocess):
    from helpers import run_cli
    from test_cli import _assert_one_line_error

    marker = tmp_path / "PWNED"
    folder = tmp_path / "cap"
    folder.mkdir()
    names = [f"img_{k:03d}.jpg" for k in range(6)]
    for k, name in enumerate(names):
        Image.fromarray(_rgb8(seed=k)).save(folder / name)
    _postscript(folder / names[2], marker)
    theta = np.linspace(0, 2 * np.pi, len(names), endpoint=False)
    lines = [f"{n} {0.5 * np.cos(t):.4f} {0.5 * np.sin(t):.4f} {np.sqrt(0.75):.4f}" for n, t in zip(names, theta)]
    (folder / "lights.lp").write_text(f"{len(names)}\n" + "\n".join(lines) + "\n")
    code, _, err = run_cli(["run", folder, "-o", tmp_path / "out"], capsys)
    _assert_one_line_error(code, err, names[2])
    assert "PostScript" in err
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_every_pillow_open_in_the_package_names_its_formats():
    """Image.open with no ``formats`` tries every plugin, EPS (Ghostscript) among them."""
    loose = []
    for folder in ("ptmcore", "reconstruct", "cli", "data_synthetic"):
        for path in (ROOT / folder).rglob("*.py"):
            text = path.read_text(encoding="utf-8")
            for match in re.finditer(r"Image\.open\(", text):
                call = text[match.end():text.find("\n", match.end()) + 1]
                if "formats=" not in call:
                    loose.append(f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, match.start()) + 1}")
    assert not loose, f"Image.open without formats= at {loose}"


@pytest.mark.parametrize("special", ["fifo", "/dev/zero"])
def test_special_files_are_refused_without_blocking(tmp_path, special):
    from reconstruct.report.figures import photograph_thumbnail

    if special == "fifo":
        path = tmp_path / "img.jpg"
        os.mkfifo(path)
        needle = "named pipe"
    else:
        path = Path(special)
        needle = "device"
    outcome = {}

    def attempt():
        for reader in (read_image, photograph_thumbnail):
            try:
                reader(path)
            except InputError as exc:
                outcome.setdefault("errors", []).append(str(exc))
        outcome["size"] = image_size(path)

    worker = threading.Thread(target=attempt, daemon=True)
    worker.start()
    worker.join(20)
    if worker.is_alive() and special == "fifo":
        with open(path, "wb"):  # let a blocked reader go before failing
            pass
    assert not worker.is_alive(), "reading a special file blocked"
    assert len(outcome["errors"]) == 2 and all(needle in e for e in outcome["errors"])
    assert outcome["size"] is None


def test_a_jpeg_claiming_more_than_its_bytes_hold_is_refused_before_decoding(tmp_path, monkeypatch):
    import simplejpeg

    bomb = tmp_path / "bomb.jpg"
    jpeg_header(bomb, 30000, 30000)
    assert bomb.stat().st_size < 2000
    monkeypatch.setattr(simplejpeg, "decode_jpeg", lambda *a, **k: pytest.fail("decoded a bomb"))
    with pytest.raises(InputError, match=r"claims 30000 × 30000 pixels, more than its [\d,]+ bytes can hold"):
        read_image(bomb)


def test_a_png_claiming_more_than_deflate_can_expand_to_is_refused(tmp_path):
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    png = tmp_path / "bomb.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 16, 2, 0, 0, 0))
                    + chunk(b"IDAT", zlib.compress(b"\0" * 1000)) + chunk(b"IEND", b""))
    with pytest.raises(InputError, match="more than its .* bytes can hold"):
        read_image(png)


def test_a_decode_larger_than_the_memory_left_is_refused(tmp_path, monkeypatch):
    import ptmcore.resources

    path = tmp_path / "a.png"
    Image.fromarray(_rgb8()).save(path)
    assert read_image(path).shape == (30, 40, 3)
    monkeypatch.setattr(decoders, "_ASK_MEMORY_BYTES", 0)
    monkeypatch.setattr(ptmcore.resources, "available_memory_mb", lambda: 0.001)
    with pytest.raises(InputError, match=r"takes 0 MiB, more than the 0 MiB of memory available"):
        read_image(path)


def test_corrupt_pngs_say_why_in_one_line_and_print_nothing_else(tmp_path, capfd):
    good = io.BytesIO()
    Image.fromarray(_rgb8(60, 80)).save(good, "PNG")
    data = good.getvalue()
    (tmp_path / "crc.png").write_bytes(data[:60] + bytes([data[60] ^ 0xFF]) + data[61:])
    (tmp_path / "short.png").write_bytes(data[: len(data) // 2])
    for name in ("crc.png", "short.png"):
        with pytest.raises(InputError, match=f"{name}: cannot decode PNG image"):
            read_image(tmp_path / name)
    assert capfd.readouterr().err == ""  # OpenCV's libpng printed "libpng error: ..." here


def test_cmyk_photographs_are_refused_not_read_as_rgb(tmp_path):
    rgb = _rgb8()
    cmyk = 255 - np.concatenate([rgb, np.zeros_like(rgb[..., :1])], axis=2)
    tifffile.imwrite(tmp_path / "c.tif", cmyk, photometric="separated")
    Image.fromarray(rgb).convert("CMYK").save(tmp_path / "c.jpg")
    for name in ("c.tif", "c.jpg"):
        with pytest.raises(InputError, match="CMYK .*export the photographs as RGB"):
            read_image(tmp_path / name)


def test_min_is_white_and_palette_tiffs_mean_what_they_show(tmp_path):
    grey = _rgb8()[..., 0]
    tifffile.imwrite(tmp_path / "white.tif", 255 - grey, photometric="miniswhite")
    np.testing.assert_array_equal(read_image(tmp_path / "white.tif"), grey)
    grey16 = grey.astype(np.uint16) * 257
    tifffile.imwrite(tmp_path / "white16.tif", 65535 - grey16, photometric="miniswhite")
    np.testing.assert_array_equal(read_image(tmp_path / "white16.tif"), grey16)

    rgb = _rgb8()
    palette = Image.fromarray(rgb).quantize(64)
    expected = np.asarray(palette.convert("RGB"))
    palette.save(tmp_path / "p.tif")
    np.testing.assert_array_equal(read_image(tmp_path / "p.tif"), expected)
    palette.save(tmp_path / "p.png")
    np.testing.assert_array_equal(read_image(tmp_path / "p.png"), expected)

    bilevel = grey > 128
    tifffile.imwrite(tmp_path / "b.tif", bilevel, photometric="minisblack")
    np.testing.assert_array_equal(read_image(tmp_path / "b.tif"), bilevel.astype(np.uint8) * 255)
    # A bit set in a min-is-white bilevel image is black, as a fax's (and as Pillow shows it).
    tifffile.imwrite(tmp_path / "bw.tif", bilevel, photometric="miniswhite")
    np.testing.assert_array_equal(read_image(tmp_path / "bw.tif"), (~bilevel).astype(np.uint8) * 255)
    with Image.open(tmp_path / "bw.tif") as im:
        np.testing.assert_array_equal(read_image(tmp_path / "bw.tif"), np.asarray(im.convert("L")))


def test_a_tiff_with_a_thumbnail_first_gives_its_full_image(tmp_path):
    rgb = _rgb8(60, 80)
    thumb = np.ascontiguousarray(rgb[::4, ::4])
    with tifffile.TiffWriter(tmp_path / "pages.tif") as w:
        w.write(thumb, subfiletype=1)
        w.write(rgb)
    with tifffile.TiffWriter(tmp_path / "subifd.tif") as w:
        w.write(thumb, subifds=1, subfiletype=1)
        w.write(rgb)
    for name in ("pages.tif", "subifd.tif"):
        np.testing.assert_array_equal(read_image(tmp_path / name), rgb)
        assert image_size(tmp_path / name) == (80, 60)


@pytest.mark.parametrize("compression", ["lzw", "zlib", "packbits", "jpeg"])
def test_compressed_tiffs_as_photoshop_and_lightroom_write_them(tmp_path, compression):
    rgb16 = (np.random.default_rng(1).random((30, 40, 3)) * 60000).astype(np.uint16)
    if compression == "jpeg":
        y, x = np.mgrid[0:30, 0:40]
        smooth = np.stack([x * 6, y * 8, x * 3 + y * 4], axis=2).astype(np.uint8)
        tifffile.imwrite(tmp_path / "a.tif", smooth, compression="jpeg", photometric="rgb")
        assert np.abs(read_image(tmp_path / "a.tif").astype(int) - smooth).mean() < 3  # lossy
        return
    tifffile.imwrite(tmp_path / "a.tif", rgb16, compression=compression)
    np.testing.assert_array_equal(read_image(tmp_path / "a.tif"), rgb16)
    tifffile.imwrite(tmp_path / "p.tif", np.moveaxis(rgb16, -1, 0), planarconfig="separate",
                     photometric="rgb", compression=compression)
    np.testing.assert_array_equal(read_image(tmp_path / "p.tif"), rgb16)


def test_a_truncated_uncompressed_tiff_is_refused(tmp_path):
    path = tmp_path / "a.tif"
    tifffile.imwrite(path, _rgb8(60, 80))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 2000])
    with pytest.raises(InputError, match="a.tif: cannot decode TIFF image .*truncated"):
        read_image(path)


def _valid_files() -> dict[str, bytes]:
    rgb = _rgb8(24, 32)
    out = {}
    for fmt in ("JPEG", "PNG"):
        buf = io.BytesIO()
        Image.fromarray(rgb).save(buf, fmt)
        out[fmt] = buf.getvalue()
    for compression in (None, "lzw"):
        buf = io.BytesIO()
        tifffile.imwrite(buf, rgb, compression=compression)
        out[f"TIFF-{compression}"] = buf.getvalue()
    return out


VALID = _valid_files()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(sorted(VALID)), data=st.data())
def test_damaged_photographs_give_an_image_or_one_input_error(tmp_path, kind, data):
    """Any truncation or byte damage of a valid file: an image of the claimed size, or InputError."""
    blob = bytearray(VALID[kind])
    cut = data.draw(st.integers(0, len(blob)), label="cut")
    edits = data.draw(st.lists(st.tuples(st.integers(0, len(blob) - 1), st.integers(0, 255)), max_size=6))
    for at, value in edits:
        blob[at] = value
    path = tmp_path / "p.jpg"
    path.write_bytes(bytes(blob[:cut] if data.draw(st.booleans(), label="truncate") else blob))
    try:
        img = read_image(path)
    except InputError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
    else:
        assert img.ndim in (2, 3) and img.dtype in (np.uint8, np.uint16, np.float32)
    image_size(path)  # never raises


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(magic=st.sampled_from([b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n", b"II*\x00", b"MM\x00*", b"%!PS", b""]),
       body=st.binary(max_size=400))
def test_arbitrary_bytes_after_any_magic_give_an_input_error_or_an_image(tmp_path, magic, body):
    path = tmp_path / "x.tif"
    path.write_bytes(magic + body)
    try:
        read_image(path)
    except InputError:
        pass
    image_size(path)
