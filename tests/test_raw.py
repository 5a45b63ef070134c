"""Camera RAW photographs developed by LibRaw (ptmcore.raw): a synthetic DNG of known truth reads
back as linear 16-bit sRGB, one development keeps a capture's photographs comparable, and files
LibRaw cannot read are refused by name, at once."""

from __future__ import annotations

import os
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_synthetic.raw import write_dng
from ptmcore.decoders import MAX_PIXELS, colour_description, embedded_profile, image_size, read_raster
from ptmcore.errors import InputError
from ptmcore.images import read_image
from ptmcore.raw import RawDevelopment, is_raw, raw_description, raw_development, raw_size, read_raw
from ptmcore.streaming import Photographs

H, W = 64, 96
NEUTRAL = (0.55, 1.0, 0.7)
#: Demosaicing (LibRaw's AHD) interpolates two of each pixel's three colours: on the smooth
#: truth below the worst error measured was 0.0010 away from the outermost pixel and 0.023 in
#: it, where AHD lacks neighbours (mean 0.0002); quantisation adds 1/14488. Three times the
#: measured error, two pixels from the border.
INNER_TOLERANCE = 0.003
BORDER = 2


def _truth(h: int = H, w: int = W) -> np.ndarray:
    """Smooth linear colours in (0.05, 0.8): no edges for demosaicing to soften, no clipping."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.1 + 0.6 * x / (w - 1)
    g = 0.15 + 0.5 * y / (h - 1)
    b = 0.1 + 0.2 * (1 + np.sin(x / 15 + y / 21))
    return np.stack([r, g, b], -1)


def _linear(img: np.ndarray) -> np.ndarray:
    assert img.dtype == np.uint16
    return img.astype(np.float64) / 65535.0


def _inner(a: np.ndarray) -> np.ndarray:
    return a[BORDER:-BORDER, BORDER:-BORDER]


@pytest.fixture
def dng(tmp_path) -> Path:
    path = tmp_path / "IMG_0001.dng"
    write_dng(path, _truth())
    return path


def test_a_dng_reads_back_as_linear_16_bit_close_to_its_truth(dng):
    img = read_raw(dng)
    assert img.shape == (H, W, 3) and img.dtype == np.uint16
    err = np.abs(_linear(img) - _truth())
    assert _inner(err).max() < INNER_TOLERANCE
    assert err.mean() < 0.001
    # read_image and read_raster route it by its name to the same development.
    assert np.array_equal(read_image(dng), img)
    assert np.array_equal(read_raster(dng), img)


@pytest.mark.parametrize(("black", "white"), [(0, 4095), (512, 15000), (1024, 65535)])
def test_grey_stays_grey_and_the_white_level_maps_to_65535(tmp_path, black, white):
    """The as-shot neutral is undone exactly (a flat field has nothing to demosaic), and LibRaw
    scales (white − black) to 65535 whatever the white level: measured within 1.2e-4."""
    path = tmp_path / "grey.dng"
    write_dng(path, np.full((H, W, 3), 0.4), neutral=NEUTRAL, black=black, white=white)
    img = _linear(read_raw(path))
    assert np.abs(img - 0.4).max() < 2e-4
    assert np.abs(img[..., 0] - img[..., 1]).max() < 2e-4 and np.abs(img[..., 2] - img[..., 1]).max() < 2e-4


def test_a_highlight_does_not_brighten_the_photograph(tmp_path):
    """LibRaw by default lowers the white level to a photograph's brightest raw value above
    75 % of it (adjust_maximum_thr): a grey of 0.5 beside a highlight of 0.9 would read 0.556."""
    truth = np.full((H, W, 3), 0.5)
    truth[10:30, 20:50] = 0.9
    path = tmp_path / "highlight.dng"
    write_dng(path, truth)
    img = _linear(read_raw(path))
    assert abs(img[50, 80, 1] - 0.5) < 2e-4 and abs(img[20, 35, 1] - 0.9) < 2e-4


def test_one_development_keeps_photographs_comparable(tmp_path):
    """The same light and pixels, but the camera's automatic balance guessed another light for
    the second photograph (another AsShotNeutral): with the first's development both read the
    same; each with its own, the second's colours shift by the ratio of the two neutrals."""
    first, second = tmp_path / "a.dng", tmp_path / "b.dng"
    other = (0.45, 1.0, 0.8)
    write_dng(first, _truth(), neutral=NEUTRAL)
    write_dng(second, _truth(), neutral=NEUTRAL, as_shot=other)
    dev = raw_development(first)
    assert dev.source == "camera" and dev.flip == 0
    assert np.allclose(dev.white_balance, (1 / 0.55, 1.0, 1 / 0.7, 1.0), rtol=1e-4)
    assert np.array_equal(read_raw(second, dev), read_raw(first))
    own = _linear(read_raw(second))
    implied = np.minimum(_truth() * np.array(NEUTRAL) / np.array(other), 1.0)
    assert _inner(np.abs(own - implied)).max() < INNER_TOLERANCE
    assert raw_development(second).white_balance != dev.white_balance
    # The photographs' reader passes the capture's development on.
    photos = Photographs([first, second], raw=dev)
    assert np.array_equal(photos.load(1), photos.load(0))
    assert np.array_equal(read_image(second, raw=dev), photos.load(0))


def test_a_second_photograph_under_another_light_keeps_its_colour(tmp_path):
    """A photograph whose light is bluer (its raw blue higher) read with the first's balance
    shows that light's colour: the ratio of the two cameras' responses."""
    first, second = tmp_path / "a.dng", tmp_path / "b.dng"
    bluer = (0.55, 1.0, 0.85)
    write_dng(first, _truth(), neutral=NEUTRAL)
    write_dng(second, _truth(), neutral=bluer)
    img = _linear(read_raw(second, raw_development(first)))
    implied = _truth() * np.array(bluer) / np.array(NEUTRAL)
    assert _inner(np.abs(img - implied)).max() < INNER_TOLERANCE
    assert _inner(np.abs(_linear(read_raw(second)) - _truth())).max() < INNER_TOLERANCE


def test_the_first_photographs_orientation_applies_to_the_capture(tmp_path):
    upright, turned = tmp_path / "a.dng", tmp_path / "b.dng"
    write_dng(upright, _truth())
    write_dng(turned, _truth(), orientation=6)  # the camera's sensor said: turned 90° clockwise
    assert raw_development(turned).flip == 6
    own = read_raw(turned)
    assert own.shape == (W, H, 3)
    assert _inner(np.abs(_linear(own) - np.rot90(_truth(), -1))).max() < INNER_TOLERANCE
    assert raw_size(turned) == image_size(turned) == (H, W)  # (width, height) as image_size gives
    as_first = read_raw(turned, raw_development(upright))
    assert np.array_equal(as_first, read_raw(upright))
    # A development given by hand (the file's multipliers are float32: a code apart at most).
    rotated = read_raw(upright, RawDevelopment((1 / 0.55, 1.0, 1 / 0.7, 0.0), flip=6))
    assert np.abs(rotated.astype(np.int32) - own).max() <= 1


def test_min_side_gives_the_half_size_development(dng):
    half = read_raw(dng, min_side=H // 2)
    assert half.shape == (H // 2, W // 2, 3) and half.dtype == np.uint16
    # Each 2 × 2 block is one pixel, without demosaicing: R, the mean of the greens, B.
    t = _truth()
    blocks = np.stack([t[0::2, 0::2, 0], (t[0::2, 1::2, 1] + t[1::2, 0::2, 1]) / 2, t[1::2, 1::2, 2]], -1)
    assert np.abs(_linear(half) - blocks).max() < 2e-4
    assert read_raw(dng, min_side=H // 2 + 1).shape == (H, W, 3)
    assert read_image(dng, min_side=10).shape == (H // 2, W // 2, 3)


def test_a_dng_never_reaches_tifffile(dng, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a .dng was given to tifffile")

    monkeypatch.setattr(tifffile, "TiffFile", refuse)
    monkeypatch.setattr(tifffile, "imread", refuse)
    assert read_image(dng).shape == (H, W, 3)
    assert image_size(dng) == (W, H)
    assert embedded_profile(dng) is None
    assert colour_description(dng).startswith("camera RAW")


def test_size_and_description_come_from_the_header(dng):
    assert is_raw(dng) and is_raw("X.NEF") and is_raw("a.Cr3") and not is_raw("a.tif")
    assert image_size(dng) == raw_size(dng) == (W, H)
    text = colour_description(dng)
    assert text == raw_description(dng)
    assert text == "camera RAW (ptm-reconstruct synthetic; LibRaw, linear, camera white balance 1.82/1/1.43)"
    assert embedded_profile(dng) is None
    dev = RawDevelopment((2.05, 1.0, 1.46, 0.0), flip=6, source="camera")
    assert dev.white_balance == (2.05, 1.0, 1.46, 1.0)
    assert dev.describe() == "camera white balance 2.05/1/1.46, rotated 90° clockwise"
    for bad in ((0.0, 1.0, 1.0, 1.0), (1.0, float("nan"), 1.0, 1.0), (1.0, 1.0, 1.0)):
        with pytest.raises(ValueError):
            RawDevelopment(bad)
    with pytest.raises(ValueError):
        RawDevelopment((1.0, 1.0, 1.0, 1.0), flip=8)


# --- files LibRaw cannot read -------------------------------------------------------------------


def _at_once(call, fifo: Path | None = None):
    """``call()``'s exception within seconds; a reader blocked on ``fifo`` is let go by opening
    the other end, so the test fails rather than hangs."""
    outcome: list = []

    def attempt():
        try:
            outcome.append(call())
        except BaseException as exc:  # noqa: BLE001 - returned to the test
            outcome.append(exc)

    worker = threading.Thread(target=attempt, daemon=True)
    start = time.perf_counter()
    worker.start()
    worker.join(10)
    if worker.is_alive():
        if fifo is not None:
            with open(fifo, "wb"):
                pass
        pytest.fail("reading a RAW file blocked")
    return outcome[0], time.perf_counter() - start


def _bad_files(tmp_path: Path, dng: Path) -> dict[str, Path]:
    data = dng.read_bytes()
    files = {
        "truncated": (tmp_path / "truncated.dng", data[:len(data) // 2]),
        "header only": (tmp_path / "header.dng", data[:100]),
        "text": (tmp_path / "notes.nef", b"not a photograph\n" * 20),
        "empty": (tmp_path / "empty.cr2", b""),
        "a TIFF": (tmp_path / "grey.dng", None),
    }
    for path, content in files.values():
        if content is not None:
            path.write_bytes(content)
    tifffile.imwrite(files["a TIFF"][0], np.full((H, W), 30000, np.uint16))
    return {k: p for k, (p, _) in files.items()}


@pytest.mark.parametrize("reader", [read_raw, read_image, raw_development, raw_description])
def test_files_libraw_cannot_read_are_refused_by_name_at_once(tmp_path, dng, capfd, reader):
    expected = {"truncated": "truncated", "header only": "truncated", "text": "LibRaw cannot read this RAW file",
                "empty": "empty", "a TIFF": "not a DNG"}
    for kind, path in _bad_files(tmp_path, dng).items():
        exc, seconds = _at_once(lambda: reader(path))
        assert isinstance(exc, InputError), (kind, exc)
        assert str(exc).startswith(str(path)) and expected[kind] in str(exc), (kind, str(exc))
        assert "\n" not in str(exc) and seconds < 2
        assert image_size(path) is None
    assert capfd.readouterr().err == ""  # nothing of LibRaw's own on stderr


def test_a_fifo_named_dng_is_refused_without_blocking(tmp_path):
    if not hasattr(os, "mkfifo"):
        pytest.skip("no named pipes here")
    path = tmp_path / "pipe.dng"
    os.mkfifo(path)
    for reader in (read_raw, read_image, raw_development, colour_description, embedded_profile):
        exc, _ = _at_once(lambda: reader(path), fifo=path)
        assert isinstance(exc, InputError) and "named pipe" in str(exc), exc
    size, _ = _at_once(lambda: image_size(path), fifo=path)
    assert size is None


def _claiming(dng: Path, out: Path, width: int, height: int) -> Path:
    """``dng`` with ImageWidth and ImageLength rewritten, its pixels (a small strip) unchanged."""
    data = bytearray(dng.read_bytes())
    with tifffile.TiffFile(dng) as tif:
        tags = tif.pages[0].tags
        for code, value in ((256, width), (257, height)):
            tag = tags[code]
            fmt = {3: "<H", 4: "<I"}[int(tag.dtype)]
            struct.pack_into(fmt, data, tag.valueoffset, value)
    out.write_bytes(bytes(data))
    return out


@pytest.mark.parametrize(("width", "height", "needle"), [
    (60000, 60000, f"more than the {MAX_PIXELS:,}"),
    (30000, 30000, "more than its"),
])
def test_an_absurd_size_is_refused_before_allocating(tmp_path, dng, width, height, needle):
    path = _claiming(dng, tmp_path / "huge.dng", width, height)
    for reader in (read_raw, raw_development):
        exc, seconds = _at_once(lambda: reader(path))
        assert isinstance(exc, InputError) and needle in str(exc), exc
        assert seconds < 2


def test_a_development_larger_than_the_memory_left_is_refused(dng, monkeypatch):
    """LibRaw's working memory (raw data, its 4-channel image, the output) is weighed against
    the memory left before anything is unpacked."""
    import ptmcore.decoders
    import ptmcore.resources

    monkeypatch.setattr(ptmcore.decoders, "_ASK_MEMORY_BYTES", 0)
    monkeypatch.setattr(ptmcore.resources, "available_memory_mb", lambda: 0.01)
    with pytest.raises(InputError, match="MiB of memory available"):
        read_raw(dng)
