"""Every image written for people says it is sRGB (PNG ``sRGB``/``gAMA``/``cHRM`` chunks, a JPEG's or
TIFF's sRGB ICC profile); data (normal maps, masks, the web page's planes and layers) stays
untagged, byte for byte as the untagged writer makes it."""

from __future__ import annotations

import base64
import contextlib
import io
import re
import struct
import zlib
from pathlib import Path
from types import SimpleNamespace

import imagecodecs
import numpy as np
import pytest
import tifffile
from PIL import Image

from ptmcore import colourtags
from ptmcore.colourtags import srgb_icc_profile
from ptmcore.decoders import profile_is_srgb
from ptmcore.png import encode_png, write_png

COLOUR_CHUNKS = {b"sRGB", b"gAMA", b"cHRM", b"iCCP", b"cICP"}
CHRM = (31270, 32900, 64000, 33000, 30000, 60000, 15000, 6000)


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """A PNG's chunks as (type, data), CRCs checked."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    chunks, at = [], 8
    while at < len(data):
        (length,) = struct.unpack(">I", data[at:at + 4])
        kind, body = data[at + 4:at + 8], data[at + 8:at + 8 + length]
        assert struct.unpack(">I", data[at + 8 + length:at + 12 + length])[0] == zlib.crc32(kind + body)
        chunks.append((kind, body))
        at += 12 + length
    assert chunks[-1][0] == b"IEND"
    return chunks


def assert_png_srgb(data: bytes, what: str = "") -> None:
    """The sRGB chunk (perceptual), with gAMA 45455 and cHRM for D65/Rec. 709, before the image
    data; no ICC profile beside it."""
    chunks = png_chunks(data)
    kinds = [k for k, _ in chunks]
    found = {k: body for k, body in chunks if k in COLOUR_CHUNKS}
    assert set(found) == {b"sRGB", b"gAMA", b"cHRM"}, (what, kinds)
    first_data = min(kinds.index(k) for k in (b"PLTE", b"IDAT") if k in kinds)
    assert all(kinds.index(k) < first_data for k in found), (what, kinds)
    assert found[b"sRGB"] == b"\x00", what
    assert struct.unpack(">I", found[b"gAMA"]) == (45455,), what
    assert struct.unpack(">8I", found[b"cHRM"]) == CHRM, what


def assert_png_untagged(data: bytes, what: str = "") -> None:
    kinds = {k for k, _ in png_chunks(data)}
    assert not kinds & COLOUR_CHUNKS, (what, kinds)


def jpeg_icc(data: bytes) -> bytes | None:
    """The ICC profile of a JPEG's APP2 ``ICC_PROFILE`` segments (before its scan), or None;
    the segments' lengths are checked by walking them."""
    assert data[:2] == b"\xff\xd8"
    at, parts = 2, {}
    while True:
        assert data[at] == 0xFF, at
        marker = data[at + 1]
        if marker == 0xDA:  # start of scan: the headers end here
            break
        (length,) = struct.unpack(">H", data[at + 2:at + 4])
        body = data[at + 4:at + 2 + length]
        if marker == 0xE2 and body.startswith(b"ICC_PROFILE\x00"):
            parts[body[12]] = (body[13], body[14:])
        at += 2 + length
    if not parts:
        return None
    count = next(iter(parts.values()))[0]
    assert sorted(parts) == list(range(1, count + 1))
    return b"".join(parts[k][1] for k in sorted(parts))


def assert_jpeg_srgb(data: bytes, what: str = "") -> None:
    profile = jpeg_icc(data)
    assert profile is not None, what
    assert profile == srgb_icc_profile() and profile_is_srgb(profile), what


def assert_tagged(data: bytes, what: str = "") -> None:
    if data.startswith(b"\x89PNG"):
        assert_png_srgb(data, what)
    else:
        assert_jpeg_srgb(data, what)


def _main(argv) -> None:
    from reconstruct.cli.main import main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
        code = main([str(a) for a in argv])
    assert code == 0, err.getvalue()


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> SimpleNamespace:
    """A small synthetic run with a mask and a scan (so histogram.png and overlay.png), and a
    PTM relit to several formats."""
    from data_synthetic import write_capture

    root = tmp_path_factory.mktemp("srgb")
    info = write_capture(root / "cap", "tablet", shape=(48, 64), n_lights=16, seed=3)
    out = root / "out"
    _main(["run", info.folder, "-o", out, "--pixel-size", info.pixel_size, "--mask", "auto",
           "--scan", Path(info.folder) / "scan.ply", "-q"])
    relit = {}
    for ext in ("png", "jpg", "tif", "gif"):
        relit[ext] = root / f"relit.{ext}"
        light = ["--sweep", "3"] if ext == "gif" else ["--light", "0.3,0.4,0.866"]
        _main(["relight", out, "-o", relit[ext], *light])
    return SimpleNamespace(root=root, cap=Path(info.folder), out=out, relit=relit)


# --- the writers --------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(7, 9), (7, 9, 3)])
def test_tagging_a_png_only_adds_the_three_chunks_after_ihdr(dtype, shape):
    image = (np.arange(np.prod(shape)) * 97 % np.iinfo(dtype).max).astype(dtype).reshape(shape)
    plain, tagged = encode_png(image), encode_png(image, srgb=True)
    assert_png_untagged(plain)
    assert_png_srgb(tagged)
    # Signature and IHDR (33 bytes), then the 73 bytes of sRGB (13), gAMA (16) and cHRM (44).
    assert len(tagged) == len(plain) + 73
    assert tagged[:33] + tagged[106:] == plain
    with Image.open(io.BytesIO(tagged)) as im:
        assert im.info["srgb"] == 0 and im.info["gamma"] == pytest.approx(0.45455)
    assert np.array_equal(imagecodecs.png_decode(tagged), image)


def test_write_png_tags_only_when_asked(tmp_path):
    image = np.full((5, 6, 3), 200, np.uint8)
    write_png(tmp_path / "data.png", image)
    write_png(tmp_path / "picture.png", image, srgb=True)
    assert (tmp_path / "data.png").read_bytes() == encode_png(image)
    assert (tmp_path / "picture.png").read_bytes() == encode_png(image, srgb=True)


def test_the_icc_profile_is_srgb_and_the_same_on_every_run():
    profile = srgb_icc_profile()
    assert profile_is_srgb(profile)
    assert len(profile) == struct.unpack(">I", profile[:4])[0] < 1000
    assert profile[24:36] == struct.pack(">6H", 2000, 1, 1, 0, 0, 0)  # not the time it was made
    srgb_icc_profile.cache_clear()
    try:
        assert srgb_icc_profile() == profile
    finally:
        srgb_icc_profile.cache_clear()


@pytest.mark.parametrize("fmt", ["PNG", "JPEG", "TIFF", "WEBP", "GIF"])
def test_pillow_options_tag_each_format_that_can_say_so(fmt):
    buf = io.BytesIO()
    Image.fromarray(np.full((4, 5, 3), 90, np.uint8)).save(buf, format=fmt, **colourtags.srgb_save_options(fmt))
    with Image.open(io.BytesIO(buf.getvalue())) as im:
        if fmt == "PNG":
            assert_png_srgb(buf.getvalue())
        elif fmt == "GIF":
            assert "icc_profile" not in im.info  # GIF: no profile in practice
        else:
            assert im.info["icc_profile"] == srgb_icc_profile()
    if fmt == "JPEG":
        assert_jpeg_srgb(buf.getvalue())


# --- a run's outputs ------------------------------------------------------------------------------

def test_run_outputs_for_people_are_tagged(run):
    names = ["albedo.png", "mesh_texture.png", "histogram.png"]
    names += ["overlay.png"] if (run.out / "overlay.png").exists() else []  # needs off-screen OpenGL
    for name in names:
        assert_png_srgb((run.out / name).read_bytes(), name)


def test_the_tag_is_all_that_changed_in_the_albedo(run):
    tagged = (run.out / "albedo.png").read_bytes()
    with Image.open(run.out / "albedo.png") as im:
        pixels = np.asarray(im)
    assert tagged == encode_png(pixels, srgb=True)
    assert (run.out / "mesh_texture.png").read_bytes() == tagged


def test_every_picture_in_the_report_is_tagged(run):
    page = (run.out / "report.html").read_text(encoding="utf-8")
    pictures = re.findall(r'src="data:image/(\w+);base64,([A-Za-z0-9+/=]+)"', page)
    assert len(pictures) == page.count("data:image/") >= 15
    kinds = set()
    for kind, data in pictures:
        kinds.add(kind)
        assert_tagged(base64.b64decode(data), kind)
    assert kinds == {"png", "jpeg"}


def test_data_is_untagged_and_as_the_plain_writer_makes_it(run):
    from reconstruct.report.outputs import normals_to_rgb16

    normals = np.load(run.out / "normals.npy")
    assert (run.out / "normals.png").read_bytes() == encode_png(normals_to_rgb16(normals), compress=False)
    with Image.open(run.out / "mask.png") as im:
        mask = np.asarray(im)
    assert (run.out / "mask.png").read_bytes() == encode_png(mask)
    for name in ("normals.png", "mask.png", "web/normals.png", "web/height.png"):
        assert_png_untagged((run.out / name).read_bytes(), name)
    planes = sorted((run.out / "web").glob("plane_*.jpg"))
    assert len(planes) == 3
    for plane in planes:
        assert jpeg_icc(plane.read_bytes()) is None, plane.name
    with tifffile.TiffFile(run.out / "height.tif") as tif:
        assert 34675 not in tif.pages[0].tags


def test_relit_images_are_tagged_but_a_gif_cannot_be(run):
    assert_png_srgb(run.relit["png"].read_bytes(), "relit.png")
    assert_jpeg_srgb(run.relit["jpg"].read_bytes(), "relit.jpg")
    with tifffile.TiffFile(run.relit["tif"]) as tif:
        assert tif.pages[0].tags[34675].value == srgb_icc_profile()
    with Image.open(run.relit["gif"]) as im:
        assert im.format == "GIF" and "icc_profile" not in im.info


def test_gallery_thumbnails_are_tagged(run):
    from reconstruct.batch.gallery import write_thumbnails

    written = write_thumbnails(run.out, run.root / "thumbnails", "tablet")
    assert set(written) == {"relit", "height"}
    for rel in written.values():
        assert_tagged((run.root / rel).read_bytes(), rel)


def test_light_plot_chart_and_calibration_diagnostic_are_tagged(run, tmp_path):
    from reconstruct.calibration.calibrate import write_diagnostic
    from reconstruct.report import plots

    _main(["lights", run.cap / "lights.lp", "-o", tmp_path / "lights.png"])
    assert_png_srgb((tmp_path / "lights.png").read_bytes(), "lights.png")
    chart = plots.figure(300, 150)  # as the preview's exported profiles are drawn
    chart.add_subplot().plot([0, 1, 3])
    assert_png_srgb(plots.png(chart), "chart")
    calibration = SimpleNamespace(view_model="orthographic", spheres=[(20.0, 15.0, 8.0)],
                                  highlights=np.array([[[18.0, 13.0]]]))
    write_diagnostic(tmp_path / "diagnostic.png", np.full((30, 40, 3), 120, np.uint8), calibration, 0)
    assert_png_srgb((tmp_path / "diagnostic.png").read_bytes(), "diagnostic.png")
