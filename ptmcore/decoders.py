"""Decoding the raster formats this program reads — JPEG, PNG and TIFF — and nothing else.

A photograph's format is told by its first bytes, never by its name, and each format goes to
one decoder chosen here: JPEG to simplejpeg (libjpeg-turbo; 1.6× faster than Pillow on a
24-megapixel photograph, benchmarks/decoders.py), PNG to imagecodecs' libpng (which reads 16-bit
colour, raises errors instead of printing libpng's lines on stderr as OpenCV does, and is as
fast), TIFF to tifffile with imagecodecs' codecs (LZW, Deflate, JPEG, PackBits: what Photoshop
and Lightroom write). Nothing is handed to a library that picks a decoder for itself: Pillow,
asked to open "any image", gives a PostScript file to Ghostscript, a subprocess that runs the
file's program; BMP, GIF, WebP and the rest are refused with one line, as any other file that is
not one of the three.

Before anything is decoded, the size a header claims is checked three ways, so a corrupt or
hostile header costs nothing: against :data:`MAX_PIXELS`; against what the file's bytes can
hold (a compressed stream expands by a bounded ratio, so 1 KB cannot hold 30000 × 30000
pixels); and against the memory this process may still take
(:func:`ptmcore.resources.available_memory_mb`). Files are opened with
:func:`ptmcore.errors.open_input_file`: regular files only, so a named pipe or a device never
blocks a run or feeds it without end.

The colour models photographs come in are read as what they mean: grey and RGB; grey stored
min-is-white (inverted); palette images through their colour map; fewer than 8 or 16 bits a
sample scaled to the full range of their type. A CMYK separation (a print derivative, whose
tones depend on a press profile) and other colour models are refused with one line. In a TIFF
of several images, the largest full-resolution one is read, not a thumbnail stored first.

An embedded ICC colour profile (JPEG APP2 ``ICC_PROFILE`` segments, PNG ``iCCP``, TIFF tag 34675)
is read with the pixels (:func:`read_raster_and_profile`): one that describes sRGB leaves the
image as it is; any other RGB or grey profile has the image converted by littlecms to linear
light in sRGB primaries (:func:`apply_colour_profile`), so an Adobe RGB photograph is not taken
as sRGB; one that cannot be used (CMYK, Lab, damaged, over :data:`MAX_PROFILE_BYTES`) is refused.

Camera RAW files (DNG, CR2, NEF, ...) are the one exception to telling a format by its content:
most are TIFF inside, so they are told by their names (:func:`ptmcore.raw.is_raw`) before any
of this, and developed by LibRaw into linear sRGB primaries (:mod:`ptmcore.raw`); they carry no
ICC profile.
"""

from __future__ import annotations

import hashlib
import io
import os
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from .errors import InputError, open_input_file

if TYPE_CHECKING:
    import PIL.Image

    from .raw import RawDevelopment

#: The largest image read, in pixels: OpenCV's own limit (2^30, e.g. 32768 × 32768). A header
#: that claims more (a decompression bomb, or a corrupt header) is refused before any memory
#: is allocated for it.
MAX_PIXELS = 1 << 30

#: At most this many pixels per byte of a JPEG file. A baseline JPEG spends at least two bits
#: on every 8 × 8 block of a component (one for its DC difference, one for its end of block),
#: 256 pixels a byte for grey; a flat grey card saved with optimised tables measures 254, a
#: flat colour one 169. Twice the grey figure leaves room for odd encoders, and a truncated
#: file that claims a huge frame (1 KB for 30000 × 30000 is 900,000 a byte) is refused.
JPEG_PIXELS_PER_BYTE = 512
#: At most this many bytes of decoded (unfiltered) data per byte of a compressed PNG or TIFF
#: strip: Deflate cannot expand beyond 1032:1 (a 258-byte match in two bits), LZW's twelve-bit
#: codes beyond about 2730:1, PackBits 64:1, JPEG as above.
MAX_EXPANSION = 4096
#: Decodes larger than this ask how much memory is left before they allocate (smaller ones
#: always fit beside a run's own bound).
_ASK_MEMORY_BYTES = 256 << 20
#: Pages and sub-images of a TIFF looked at for its main image: a file listing thousands is
#: not a photograph, and walking them all would cost time for nothing.
_MAX_TIFF_PAGES = 64

_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def image_format(head: bytes) -> str | None:
    """``"JPEG"``, ``"PNG"`` or ``"TIFF"`` from a file's first bytes, or None for anything else."""
    if head[:3] == b"\xff\xd8\xff":
        return "JPEG"
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        return "PNG"
    if head[:4] in _TIFF_MAGIC:
        return "TIFF"
    return None


def _sniff(f: BinaryIO, path: Path) -> str:
    """The format of the file open as ``f`` from its first bytes, or the error for it."""
    head = f.read(16)
    kind = image_format(head)
    if not head:
        raise InputError("image file is empty", path)
    if kind is None:
        raise InputError(_not_read(head), path)
    return kind


def _not_read(head: bytes) -> str:
    named = {b"%!PS": "PostScript", b"\xc5\xd0\xd3\xc6": "EPS", b"%PDF": "PDF", b"BM": "BMP",
             b"GIF8": "GIF", b"RIFF": "RIFF (WebP?)", b"\x00\x00\x00\x0cjP": "JPEG 2000"}
    kind = next((name for magic, name in named.items() if head.startswith(magic)), None)
    return ((f"is {kind}, not" if kind else "is not") + " a JPEG, PNG or TIFF image (told by its content, "
            "not its name); save the photographs as one of those")


@contextmanager
def pillow_image(path: str | os.PathLike) -> Iterator[PIL.Image.Image]:
    """A JPEG, PNG or TIFF opened by Pillow with that format's plugin alone (lazily: nothing
    is decoded until asked), for what Pillow reads best: EXIF, DCT-scaled thumbnails.

    Every use of Pillow on a user's file goes through here: ``Image.open`` with no
    ``formats`` tries every plugin, and its EPS plugin runs Ghostscript.

    Raises
    ------
    InputError
        As :func:`read_raster`, for a file that is missing, not regular, or not one of the three.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    with open_input_file(path, "image") as f:
        head = f.read(16)
        kind = image_format(head)
        if kind is None:
            raise InputError(_not_read(head) if head else "image file is empty", path)
        f.seek(0)
        try:
            image = Image.open(f, formats=[kind])
        except Image.DecompressionBombError:
            raise InputError("the image claims more pixels than Pillow reads (a corrupt header, or a "
                             "decompression bomb)", path) from None
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            raise InputError(f"cannot decode image ({exc})", path) from None
        with image:
            yield image


def allow_large_images() -> None:
    """Let Pillow open any image up to :data:`MAX_PIXELS`, this program's own limit.

    Photographs are not decoded by Pillow (see the module's notes), but their EXIF is read
    with it, and Pillow warns above 89 megapixels and refuses above 179 (its
    ``Image.MAX_IMAGE_PIXELS``, a guard for servers decoding untrusted uploads). A
    150-megapixel camera's photographs are ordinary here.

    Pillow's limit is process-wide, so this is called by the programs that own their process
    (the ``reconstruct`` command and a batch's workers), not on import: a notebook that
    imports ptmcore keeps Pillow's default unless it calls this.
    """
    import warnings

    from PIL import Image

    # Pillow refuses above twice its limit and warns above the limit itself: refuse where this
    # program does, and without the warning in between.
    Image.MAX_IMAGE_PIXELS = MAX_PIXELS // 2
    warnings.filterwarnings("ignore", category=Image.DecompressionBombWarning)


def _check_claim(width: int, height: int, decoded_bytes: int, path: Path) -> None:
    """Refuse a header's size before anything is allocated for it: over :data:`MAX_PIXELS`,
    or more than the memory this process may still take."""
    if width < 1 or height < 1:
        raise InputError(f"the image claims {width} × {height} pixels (a corrupt header)", path)
    if width * height > MAX_PIXELS:
        raise InputError(f"the image claims {width} × {height} pixels, more than the {MAX_PIXELS:,} this program "
                         "reads (a corrupt header, or an image too large to process)", path)
    if decoded_bytes > _ASK_MEMORY_BYTES:
        from .resources import available_memory_mb

        free = available_memory_mb()
        if decoded_bytes > free * 2**20:
            raise InputError(f"decoding the image's {width} × {height} pixels takes {decoded_bytes / 2**20:,.0f} MiB, "
                             f"more than the {free:,.0f} MiB of memory available", path)


def _implausible(width: int, height: int, nbytes: int, path: Path) -> InputError:
    return InputError(f"the image claims {width} × {height} pixels, more than its {nbytes:,} bytes can hold "
                      "(a truncated or corrupt file, or a decompression bomb)", path)


def decode_jpeg(data: bytes, path: Path, buffer: np.ndarray | None = None,
                min_side: int | None = None) -> np.ndarray:
    """A JPEG's pixels, ``(H, W)`` or ``(H, W, 3)`` uint8.

    ``buffer`` is decoded into when it is large enough (the result is then a view of it);
    ``min_side`` asks for the smallest DCT-scaled size (1/8 to 1) with both sides at least that
    long, which skips most of the work for a thumbnail.
    """
    import simplejpeg

    try:
        height, width, colorspace, _ = simplejpeg.decode_jpeg_header(data)
    except ValueError as exc:
        raise InputError(f"cannot decode JPEG image ({exc})", path) from None
    if colorspace not in ("Gray", "YCbCr", "RGB"):
        raise InputError(f"the JPEG is {colorspace} (a print separation, whose tones depend on a press profile); "
                         "export the photographs as RGB", path)
    gray = colorspace == "Gray"
    if width * height > JPEG_PIXELS_PER_BYTE * len(data):
        raise _implausible(width, height, len(data), path)
    _check_claim(width, height, width * height * (1 if gray else 3), path)
    scaled = {} if min_side is None else {"min_width": min(min_side, width), "min_height": min(min_side, height)}
    need = height * width * (1 if gray else 3)
    out = buffer[:need] if buffer is not None and buffer.nbytes >= need and not scaled else None
    mode = "GRAY" if gray else "RGB"
    try:
        img = simplejpeg.decode_jpeg(data, colorspace=mode, buffer=out, **scaled)
    except ValueError as exc:
        if "Premature end" in str(exc):
            raise InputError("cannot decode JPEG image (the file is truncated)", path) from None
        # libjpeg's warnings (stray bytes between markers, as some cameras and editors leave)
        # are errors in strict mode; the image itself may be whole, as Pillow would read it.
        try:
            img = simplejpeg.decode_jpeg(data, colorspace=mode, buffer=out, strict=False, **scaled)
        except ValueError:
            raise InputError(f"cannot decode JPEG image ({exc})", path) from None
    return img[..., 0] if gray else img


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def decode_png(data: bytes, path: Path) -> np.ndarray:
    """A PNG's pixels as stored (uint8 or uint16; a palette expanded to RGB or RGBA; grey of
    1, 2 or 4 bits scaled to 0–255 by libpng)."""
    import imagecodecs

    if len(data) < 33 or data[12:16] != b"IHDR":
        raise InputError("cannot decode PNG image (no header: corrupt or truncated)", path)
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    depth, colour = data[24], data[25]
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise InputError(f"cannot decode PNG image (bit depth {depth}, colour type {colour}: corrupt header)", path)
    stream = height * (1 + -(-width * _PNG_CHANNELS[colour] * depth // 8))
    if stream > MAX_EXPANSION * len(data):
        raise _implausible(width, height, len(data), path)
    decoded = 4 if colour == 3 else _PNG_CHANNELS[colour]
    _check_claim(width, height, width * height * decoded * (2 if depth == 16 else 1), path)
    try:
        img = imagecodecs.png_decode(data)
    except Exception as exc:  # imagecodecs.PngError, and MemoryError's kin for absurd chunks
        raise InputError(f"cannot decode PNG image ({exc})", path) from None
    return img


def _tiff_main_page(tif):
    """The TIFF's main image: the largest full-resolution one among its first pages and their
    sub-images (a camera or a scanner may store a thumbnail first)."""
    candidates = []
    for page in tif.pages[:_MAX_TIFF_PAGES]:
        candidates.append(page)
        subs = getattr(page, "pages", None)
        if subs is not None and len(candidates) < _MAX_TIFF_PAGES:
            candidates.extend(subs[:_MAX_TIFF_PAGES - len(candidates)])
    pages = [p for p in candidates if hasattr(p, "imagewidth")]
    if not pages:
        return None
    full = [p for p in pages if not (p.subfiletype & 1)] or pages  # bit 0: a reduced-resolution copy
    return max(full, key=lambda p: p.imagewidth * p.imagelength)


def _tiff_colour(page, path: Path) -> None:
    from tifffile import PHOTOMETRIC

    photometric = page.photometric
    if photometric in (PHOTOMETRIC.MINISBLACK, PHOTOMETRIC.MINISWHITE, PHOTOMETRIC.RGB, PHOTOMETRIC.PALETTE):
        return
    if photometric == PHOTOMETRIC.YCBCR and page.compression in (6, 7):  # JPEG: decoded to RGB
        return
    if photometric == PHOTOMETRIC.SEPARATED:
        raise InputError("the TIFF is CMYK (a print separation, whose tones depend on a press profile); "
                         "export the photographs as RGB", path)
    name = getattr(photometric, "name", str(photometric))
    raise InputError(f"the TIFF's colour model {name} is not read; save the photographs as RGB or grey", path)


def _tiff_claim(page, path: Path, file_size: int) -> None:
    width, height = page.imagewidth, page.imagelength
    samples = page.samplesperpixel
    bits = page.bitspersample
    itemsize = max(1, int(np.dtype(page.dtype).itemsize)) if page.dtype is not None else 1
    raw = width * height * samples * bits // 8
    stored = sum(page.databytecounts)
    ends = [o + c for o, c in zip(page.dataoffsets, page.databytecounts) if c]
    if ends and max(ends) > file_size:
        raise InputError("cannot decode TIFF image (its image data runs past the end of the file: truncated)", path)
    if page.compression == 1:  # none
        if stored < raw:
            raise InputError("cannot decode TIFF image (less image data than its size needs: truncated)", path)
    elif raw > MAX_EXPANSION * max(stored, 1):
        raise _implausible(width, height, stored, path)
    _check_claim(width, height, width * height * samples * itemsize, path)


def _tiff_pixels(page, img: np.ndarray, path: Path) -> np.ndarray:
    """The decoded page as ``(H, W[, C])`` samples that mean what a photograph's do."""
    from tifffile import PHOTOMETRIC

    if page.planarconfig == 2 and img.ndim == 3:
        img = np.moveaxis(img, 0, -1)  # separate planes (C, H, W)
    bits = page.bitspersample
    if img.dtype == bool:
        img, bits = img.astype(np.uint8) * np.uint8(255), 8
    if page.photometric == PHOTOMETRIC.PALETTE:
        if page.colormap is None:
            raise InputError("cannot decode TIFF image (a palette image without its colour map)", path)
        cmap = np.asarray(page.colormap)
        # 16-bit entries: writers store an 8-bit v as v·257 or v·256, and both shift back to v.
        cmap = (cmap >> 8).astype(np.uint8) if cmap.max(initial=0) > 255 else cmap.astype(np.uint8)
        index = np.minimum(img if img.ndim == 2 else img[..., 0], cmap.shape[1] - 1)
        return np.moveaxis(cmap, 0, -1)[index]
    if img.dtype.kind == "u" and bits < 8 * img.dtype.itemsize:
        # 2, 4 or 12 bits a sample, stored in a wider type: scale to its full range.
        top = np.iinfo(img.dtype).max
        img = (img.astype(np.float32) * np.float32(top / (2**bits - 1)) + np.float32(0.5)).astype(img.dtype)
    if page.photometric == PHOTOMETRIC.MINISWHITE:
        if img.dtype.kind != "u":
            raise InputError("the TIFF is stored min-is-white with samples that are not integers; save it as "
                             "min-is-black grey", path)
        img = np.iinfo(img.dtype).max - img
    return img


def decode_tiff(path: Path) -> np.ndarray:
    """A TIFF's main image (see :func:`_tiff_main_page`) as its samples: ``(H, W[, C])``."""
    return _decode_tiff(path)[0]


def _decode_tiff(path: Path) -> tuple[np.ndarray, bytes | None]:
    """:func:`decode_tiff` and the main image's embedded colour profile (None without one)."""
    import tifffile

    with open_input_file(path, "image") as f:
        file_size = os.fstat(f.fileno()).st_size
        try:
            with tifffile.TiffFile(f, name=path.name) as tif:
                page = _tiff_main_page(tif)
                if page is None:
                    raise InputError("cannot decode TIFF image (it holds no image)", path)
                _tiff_colour(page, path)
                _tiff_claim(page, path, file_size)
                profile = _tiff_profile(page, path)
                return _tiff_pixels(page, page.asarray(), path), profile
        except InputError:
            raise
        except MemoryError:
            raise InputError("cannot decode TIFF image (its header asks for more memory than there is: corrupt)",
                             path) from None
        except Exception as exc:  # tifffile and its codecs raise many types for corrupt files
            raise InputError(f"cannot decode TIFF image ({exc})", path) from None


def _tiff_size(path: Path) -> tuple[int, int] | None:
    import tifffile

    try:
        with open_input_file(path, "image") as f, tifffile.TiffFile(f, name=path.name) as tif:
            page = _tiff_main_page(tif)
            return None if page is None else (page.imagewidth, page.imagelength)
    except Exception:  # noqa: BLE001 - any unreadable file has no size
        return None


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(width, height)`` of a JPEG, PNG or TIFF from its header (nothing is decoded), or None
    when the file is missing, not a regular file, not one of those formats, or unreadable.
    A camera RAW file (by its name) gives its developed size (:func:`ptmcore.raw.raw_size`)."""
    from .raw import is_raw, raw_size

    path = Path(path)
    if is_raw(path):
        return raw_size(path)
    try:
        with open_input_file(path, "image") as f:
            head = f.read(64 * 1024)
    except InputError:
        return None
    kind = image_format(head)
    if kind == "PNG" and len(head) >= 24 and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if kind == "TIFF":
        return _tiff_size(path)
    if kind == "JPEG":
        import simplejpeg

        try:  # the frame header is near the start, after any EXIF (at most 64 KB)
            height, width = simplejpeg.decode_jpeg_header(head)[:2]
            return width, height
        except ValueError:
            return None
    return None


def read_raster(path: str | os.PathLike, *, buffer: np.ndarray | None = None,
                min_side: int | None = None, raw: RawDevelopment | None = None) -> np.ndarray:
    """A JPEG, PNG or TIFF file's samples as stored, whatever the file's name says.

    See :func:`ptmcore.images.read_image`, which checks and shapes the result; ``min_side``
    lets a JPEG be decoded smaller (a thumbnail). Any embedded colour profile is checked
    (a damaged one is refused) but not applied: see :func:`read_raster_and_profile`. A camera
    RAW file (told by its name) is developed by :func:`ptmcore.raw.read_raw` with ``raw``
    (default: its own development), ``buffer`` unused.

    Raises
    ------
    InputError
        Missing, not a regular file, empty, not one of the three formats, corrupt, or claiming
        more pixels than its bytes or the memory available allow.
    """
    return read_raster_and_profile(path, buffer=buffer, min_side=min_side, raw=raw)[0]


def read_raster_and_profile(path: str | os.PathLike, *, buffer: np.ndarray | None = None,
                            min_side: int | None = None, raw: RawDevelopment | None = None
                            ) -> tuple[np.ndarray, bytes | None]:
    """:func:`read_raster`'s samples and the file's embedded ICC colour profile.

    Returns
    -------
    img : ndarray
        The samples as stored, as :func:`read_raster`.
    profile : bytes or None
        The embedded ICC profile (at most :data:`MAX_PROFILE_BYTES`), None without one (and
        for a camera RAW file, developed straight into linear sRGB primaries).

    Raises
    ------
    InputError
        As :func:`read_raster`; or an embedded profile that is damaged or too large.
    """
    from .raw import is_raw, read_raw

    path = Path(path)
    if is_raw(path):  # before the content is sniffed: a DNG is a TIFF inside
        return read_raw(path, raw, min_side=min_side), None
    with open_input_file(path, "image") as f:
        kind = _sniff(f, path)
        if kind == "TIFF":
            data = b""
        else:
            try:
                f.seek(0)
                data = f.read()
            except OSError as exc:
                raise InputError(f"cannot read image ({exc.strerror or exc})", path) from None
    # The profile first: a damaged one is named as such, not as the decoder's complaint about it.
    if kind == "JPEG":
        profile = _jpeg_profile(io.BytesIO(data), path)
        return decode_jpeg(data, path, buffer, min_side), profile
    if kind == "PNG":
        profile = _png_profile(io.BytesIO(data), path)
        return decode_png(data, path), profile
    return _decode_tiff(path)


# --- embedded ICC colour profiles --------------------------------------------------------------

#: The largest embedded colour profile read, in bytes. Matrix profiles are under 4 KB and the
#: largest lookup-table profiles (printers, scanners) about 1 MB; a larger one is a damaged or
#: hostile file, and a PNG's compressed profile is never inflated beyond this.
MAX_PROFILE_BYTES = 4 << 20
_ICC_JPEG = b"ICC_PROFILE\x00"
#: Rows converted at once: a float32 band of a 10000-pixel-wide photograph is 60 MB, beside the
#: preallocated result.
_PROFILE_BAND_ROWS = 512
#: littlecms' relative colorimetric intent: the profile's white becomes white, and colours are
#: measured, not re-rendered for appearance (perceptual tables would alter the light's values).
_RELATIVE_COLORIMETRIC = 1


def _unusable(reason: str, path: Path) -> InputError:
    return InputError(f"embedded colour profile cannot be used: {reason}", path)


def _check_profile_size(size: int, path: Path) -> None:
    if size > MAX_PROFILE_BYTES:
        raise _unusable(f"it is larger than the {MAX_PROFILE_BYTES:,} bytes read (a damaged or hostile file)", path)


def _jpeg_profile(f: BinaryIO, path: Path) -> bytes | None:
    """The ICC profile in a JPEG's APP2 ``ICC_PROFILE`` segments (chunks numbered 1..count,
    joined in order), read from the markers before the scan; None without one."""
    f.seek(2)  # past SOI
    chunks: dict[int, bytes] = {}
    counts: set[int] = set()
    total = 0
    while True:
        byte = f.read(1)
        if not byte:
            break
        if byte != b"\xff":
            continue  # stray bytes between markers, which libjpeg skips too
        code = f.read(1)
        while code == b"\xff":  # fill bytes
            code = f.read(1)
        if not code or code in (b"\xda", b"\xd9"):  # start of scan, end of image: no more markers
            break
        if code == b"\x01" or b"\xd0" <= code <= b"\xd7":  # markers without a length
            continue
        size = f.read(2)
        if len(size) < 2:
            break
        length = int.from_bytes(size, "big") - 2
        if length < 0:
            break
        if code == b"\xe2":
            payload = f.read(length)
            if payload.startswith(_ICC_JPEG) and len(payload) >= 14:
                seq, count = payload[12], payload[13]
                if seq < 1 or seq > count or seq in chunks:
                    raise _unusable(f"its JPEG chunk {seq} of {count} is numbered wrongly or repeated "
                                    "(a damaged file)", path)
                counts.add(count)
                total += len(payload) - 14
                _check_profile_size(total, path)
                chunks[seq] = payload[14:]
        else:
            f.seek(length, os.SEEK_CUR)
    if not chunks:
        return None
    count = max(counts)
    if len(counts) > 1 or len(chunks) != count:
        raise _unusable(f"{len(chunks)} of its {count} JPEG chunks are present (a damaged file)", path)
    return b"".join(chunks[k] for k in range(1, count + 1))


def _png_profile(f: BinaryIO, path: Path) -> bytes | None:
    """The ICC profile in a PNG's ``iCCP`` chunk (a name, a NUL, a method byte and the zlib
    stream), inflated to at most :data:`MAX_PROFILE_BYTES`; None without one."""
    f.seek(8)  # past the signature
    while True:
        header = f.read(8)
        if len(header) < 8:
            return None
        length, kind = int.from_bytes(header[:4], "big"), header[4:]
        if kind in (b"IDAT", b"IEND"):  # iCCP comes before the image data
            return None
        if kind != b"iCCP":
            f.seek(length + 4, os.SEEK_CUR)  # and its CRC
            continue
        _check_profile_size(length, path)  # compressed, it is no larger than inflated
        body = f.read(length)
        crc = f.read(4)
        if len(body) < length or len(crc) < 4 or zlib.crc32(kind + body) != int.from_bytes(crc, "big"):
            raise _unusable("its PNG iCCP chunk is truncated or fails its checksum (a damaged file)", path)
        nul = body.find(b"\x00", 0, 80)
        if nul < 1 or nul + 2 > len(body) or body[nul + 1] != 0:
            raise _unusable("its PNG iCCP chunk has no name or an unknown compression (a damaged file)", path)
        inflate = zlib.decompressobj()
        try:
            profile = inflate.decompress(body[nul + 2:], MAX_PROFILE_BYTES + 1)
        except zlib.error as exc:
            raise _unusable(f"its compressed data is damaged ({exc})", path) from None
        _check_profile_size(len(profile) + len(inflate.unconsumed_tail), path)
        return profile


def _tiff_profile(page, path: Path) -> bytes | None:
    """The ICC profile in a TIFF page's tag 34675 (InterColorProfile); None without one."""
    tag = page.tags.get(34675)
    if tag is None:
        return None
    _check_profile_size(int(getattr(tag, "valuebytecount", 0) or tag.count), path)
    value = tag.value
    if isinstance(value, np.ndarray):
        value = value.tobytes()
    elif isinstance(value, tuple):
        value = bytes(value)
    if not isinstance(value, bytes):
        raise _unusable(f"its TIFF tag holds {type(value).__name__}, not bytes (a damaged file)", path)
    return value or None


def _profile_space(profile: bytes, path: Path) -> str:
    """``"rgb"`` or ``"gray"``, the colour space of an ICC profile, after its header's checks."""
    if len(profile) < 132 or profile[36:40] != b"acsp":
        raise _unusable("it is not an ICC profile (a damaged file)", path)
    if int.from_bytes(profile[:4], "big") > len(profile):
        raise _unusable("it is truncated (a damaged file)", path)
    space = profile[16:20]
    if space == b"RGB ":
        return "rgb"
    if space == b"GRAY":
        return "gray"
    name = space.decode("latin-1").strip() or "unnamed"
    raise _unusable(f"it describes {name} colour, not RGB or grey (a print separation or an unusual "
                    "export); save the photographs as RGB", path)


def _linear_profile(space: str) -> bytes:
    """Linear light in sRGB's primaries and D65 white (or linear grey): the converted image's
    space. (``cms_profile('srgb', gamma=1.0)`` would ignore the gamma.)"""
    import imagecodecs

    if space == "gray":
        return imagecodecs.cms_profile("gray", gamma=1.0)
    return imagecodecs.cms_profile("rgb", whitepoint=[0.3127, 0.3290, 1.0],
                                   primaries=[0.64, 0.33, 1, 0.30, 0.60, 1, 0.15, 0.06, 1], gamma=1.0)


def _test_colours(space: str) -> np.ndarray:
    """8-bit colours that tell sRGB from another space: a grid with saturated primaries (the
    gamut) and greys from near black (the tone curve's toe, where sRGB and gamma 2.2 differ)."""
    greys = np.array([0, 2, 5, 10, 20, 40, 64, 96, 128, 160, 192, 224, 255], np.uint8)
    if space == "gray":
        return greys.reshape(1, -1)
    levels = np.array([0, 20, 110, 255], np.uint8)
    grid = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1).reshape(-1, 3)
    return np.concatenate([grid, np.repeat(greys[:, None], 3, axis=1)]).reshape(1, -1, 3)


#: sRGB-equivalence already decided, by the profile's SHA-256 (a capture's photographs share one).
_SRGB_VERDICTS: dict[bytes, bool] = {}


def profile_is_srgb(profile: bytes, path: str | os.PathLike = "") -> bool:
    """Whether an ICC profile describes sRGB (or sRGB's grey), to within one 8-bit code.

    A fixed set of test colours is converted through the profile to littlecms' own sRGB
    profile: a profile that changes none by more than one code (an sRGB profile from any
    vendor, v2 or v4) is taken as sRGB, and the image as it is stored.

    Raises
    ------
    InputError
        If the profile is not RGB or grey, is damaged, or littlecms refuses it.
    """
    import imagecodecs

    path = Path(path)
    space = _profile_space(profile, path)
    key = hashlib.sha256(profile).digest()
    verdict = _SRGB_VERDICTS.get(key)
    if verdict is None:
        colours = _test_colours(space)
        try:
            out = imagecodecs.cms_transform(colours, profile, imagecodecs.cms_profile("srgb"), colorspace=space,
                                            outcolorspace="rgb", outdtype=np.uint8, intent=_RELATIVE_COLORIMETRIC)
        except Exception as exc:  # imagecodecs.CmsError: littlecms refused the profile
            raise _unusable(f"littlecms refuses it ({exc})", path) from None
        expected = colours[..., None] if space == "gray" else colours
        verdict = bool(np.abs(out.astype(np.int16) - expected.astype(np.int16)).max() <= 1)
        if len(_SRGB_VERDICTS) >= 64:
            _SRGB_VERDICTS.clear()
        _SRGB_VERDICTS[key] = verdict
    return verdict


def apply_colour_profile(img: np.ndarray, profile: bytes, path: str | os.PathLike) -> np.ndarray:
    """An image with its embedded profile applied: unchanged when the profile is sRGB.

    Parameters
    ----------
    img : ndarray
        ``(H, W)`` grey or ``(H, W, 3)`` RGB, uint8, uint16 or float32, as
        :func:`ptmcore.images.read_image` shapes it.
    profile : bytes
        The embedded ICC profile.
    path : str or PathLike
        The file, for messages.

    Returns
    -------
    ndarray
        ``img`` itself when :func:`profile_is_srgb` (8-bit as sRGB, 16-bit and float as linear,
        as without a profile); otherwise float32 linear light in sRGB's primaries and D65 white
        (linear grey for a grey profile), same shape, clipped below at 0 but not above 1.

    Raises
    ------
    InputError
        If the profile cannot be used (see :func:`profile_is_srgb`), or is RGB for a grey image
        or grey for an RGB one, or the result would not fit in memory.
    """
    import imagecodecs

    path = Path(path)
    if profile_is_srgb(profile, path):
        return img
    space = _profile_space(profile, path)
    grey = img.ndim == 2
    if grey != (space == "gray"):
        raise _unusable(f"it is {'RGB' if space == 'rgb' else 'grey'} but the image is "
                        f"{'grey' if grey else 'RGB'}; save the photograph with a matching profile", path)
    dst = _linear_profile(space)

    def convert(data: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        try:
            return imagecodecs.cms_transform(np.ascontiguousarray(data), profile, dst, colorspace=space,
                                             outcolorspace=space, outdtype=np.float32,
                                             intent=_RELATIVE_COLORIMETRIC, out=out)
        except Exception as exc:  # imagecodecs.CmsError: littlecms refused the profile
            raise _unusable(f"littlecms refuses it ({exc})", path) from None

    height, width = img.shape[:2]
    if grey and img.dtype in (np.uint8, np.uint16):
        # A grey profile is one tone curve: convert every code once, then look them up.
        codes = np.arange(np.iinfo(img.dtype).max + 1, dtype=img.dtype).reshape(-1, 256)
        table = np.maximum(convert(codes).reshape(-1), np.float32(0.0))
        _check_claim(width, height, img.size * 4, path)
        return table[img]
    _check_claim(width, height, img.size * 4, path)
    result = np.empty(img.shape, np.float32)
    for r0 in range(0, height, _PROFILE_BAND_ROWS):
        band = result[r0:r0 + _PROFILE_BAND_ROWS]
        done = convert(img[r0:r0 + _PROFILE_BAND_ROWS], band)
        if not np.shares_memory(done, band):
            band[...] = done
        np.maximum(band, np.float32(0.0), out=band)
    return result


def profile_description(profile: bytes) -> str:
    """The profile's own description ("Adobe RGB (1998)", "sRGB IEC61966-2.1"), or
    ``"embedded profile"`` when it has none that Pillow reads."""
    try:
        from PIL import ImageCms

        text = ImageCms.getProfileDescription(ImageCms.ImageCmsProfile(io.BytesIO(profile)))
    except Exception:  # noqa: BLE001 - a description is optional; the profile itself is checked elsewhere
        return "embedded profile"
    text = " ".join(str(text).split())
    return text if text and text.isprintable() else "embedded profile"


def embedded_profile(path: str | os.PathLike) -> bytes | None:
    """A JPEG, PNG or TIFF file's embedded ICC profile from its header (no pixel is decoded),
    or None without one.

    A camera RAW file has none: it is developed straight into linear sRGB primaries.

    Raises
    ------
    InputError
        As :func:`read_raster` for a file that cannot be read or is not one of the three, or a
        damaged or oversized profile.
    """
    import tifffile

    from .raw import is_raw

    path = Path(path)
    if is_raw(path):
        open_input_file(path, "RAW file").close()  # missing or not a regular file: said as for the others
        return None
    with open_input_file(path, "image") as f:
        kind = _sniff(f, path)
        try:
            if kind == "JPEG":
                return _jpeg_profile(f, path)
            if kind == "PNG":
                return _png_profile(f, path)
            f.seek(0)
            with tifffile.TiffFile(f, name=path.name) as tif:
                page = _tiff_main_page(tif)
                return None if page is None else _tiff_profile(page, path)
        except InputError:
            raise
        except Exception as exc:  # tifffile raises many types for corrupt files
            raise InputError(f"cannot decode TIFF image ({exc})", path) from None


def colour_description(path: str | os.PathLike) -> str:
    """How a photograph's colours are read, from its header alone.

    Returns
    -------
    str
        ``"sRGB (no embedded profile)"``, ``"<description> (embedded, sRGB)"`` or
        ``"<description> (embedded; converted to linear sRGB)"``; for a camera RAW file
        :func:`ptmcore.raw.raw_description` (``"camera RAW (<camera>; LibRaw, linear, camera
        white balance 2.05/1/1.46)"``, which unpacks the raw data to read the balance).

    Raises
    ------
    InputError
        As :func:`embedded_profile`, or a profile that cannot be used (:func:`profile_is_srgb`).
    """
    from .raw import is_raw, raw_description

    if is_raw(path):
        return raw_description(path)
    profile = embedded_profile(path)
    if profile is None:
        return "sRGB (no embedded profile)"
    srgb = profile_is_srgb(profile, path)
    return f"{profile_description(profile)} " + ("(embedded, sRGB)" if srgb else "(embedded; converted to linear sRGB)")
