"""Camera RAW photographs (DNG, CR2, CR3, NEF, ARW, ORF, RW2, RAF, PEF, SRW, ...) developed by
LibRaw (through rawpy) into linear light.

A RAW file is told by its name, not its content: DNG, CR2, NEF, ARW and most others are TIFF
files inside, so they are routed here by suffix (:func:`is_raw`) before the content-sniffing
JPEG/PNG/TIFF decoders of :mod:`ptmcore.decoders` see them. A ``.dng`` never reaches tifffile,
which would read its thumbnail or its undemosaiced mosaic as the photograph.

A capture's photographs are developed alike, so that their values stay comparable between
lights (:class:`RawDevelopment`):

* linear 16-bit output (gamma 1, no automatic brightening) in sRGB's primaries and D65 white,
  which is what :func:`ptmcore.images.read_image` means by a 16-bit photograph;
* one white balance for the whole capture: the first photograph's as-shot (camera) balance,
  never LibRaw's automatic one, which would differ from light to light;
* LibRaw's ``adjust_maximum_thr`` off: by default LibRaw lowers the white level to a
  photograph's brightest raw value when that is above 75 % of it, which brightens exactly the
  photographs that have a highlight (measured: a grey of 0.50 came out as 0.556 beside a
  highlight at 0.9 of the white level);
* one orientation, the first photograph's: a camera pointing down into a dome has no reliable
  up, and its orientation sensor may flip between photographs.

LibRaw's output scale: a raw value ``v`` becomes ``(v − black) / (white − black) · 65535 · m_c``
where ``m_c`` is the channel's white-balance multiplier divided by the smallest of them (LibRaw
normalises them so) and then clipped at 65535; a neutral at the white level is 65535 whatever
the white level (measured for white levels 4095, 15000 and 65535 with
:func:`data_synthetic.raw.write_dng`: within 1.2e-4 on a flat grey).

Reading is bounded as every decoder's is: the file through
:func:`ptmcore.errors.open_input_file` (a FIFO or a device is refused, nothing blocks), its
bytes handed to LibRaw in memory (no subprocess, no path given to a C library), and the sizes
LibRaw reads from the header checked against :data:`ptmcore.decoders.MAX_PIXELS`, against what
the file's bytes can hold and against the memory available before anything is unpacked.
"""

from __future__ import annotations

import io
import math
import os
import struct
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import decoders
from .decoders import MAX_EXPANSION, _check_claim
from .errors import InputError, open_input_file

if TYPE_CHECKING:
    import rawpy

__all__ = ["RAW_SUFFIXES", "RawDevelopment", "is_raw", "raw_description", "raw_development", "raw_size", "read_raw"]

#: File name suffixes (lower case) of the camera RAW formats read with LibRaw.
RAW_SUFFIXES = frozenset({
    ".dng",                          # Adobe DNG (Leica, Pentax, Ricoh, phones, converters)
    ".cr2", ".cr3", ".crw",          # Canon
    ".nef", ".nrw",                  # Nikon
    ".arw", ".srf", ".sr2",          # Sony
    ".orf",                          # Olympus / OM System
    ".rw2", ".rwl",                  # Panasonic, Leica
    ".raf",                          # Fujifilm
    ".pef",                          # Pentax
    ".srw",                          # Samsung
    ".iiq",                          # Phase One (common in heritage imaging)
    ".3fr", ".fff",                  # Hasselblad
    ".erf", ".kdc", ".dcr", ".mrw", ".mos", ".x3f",
})

#: LibRaw's flip codes (``sizes.flip``, ``user_flip``) in words.
_FLIPS = {0: "as stored", 1: "mirrored left-right", 2: "mirrored top-bottom", 3: "rotated 180°",
          4: "transposed", 5: "rotated 90° anticlockwise", 6: "rotated 90° clockwise", 7: "transverse"}
#: LibRaw's working memory per pixel beyond the raw data: its 4-channel uint16 image (8 bytes)
#: and the 16-bit RGB output (6 bytes).
_IMAGE_BYTES, _OUTPUT_BYTES = 8, 6
#: LibRaw's demosaicing. On a synthetic 480 × 384 capture of 24 DNGs (mean normal error; its
#: linear TIFFs 0.39°): AHD 0.62°, DHT 0.59°, PPG 0.61°, AAHD 0.65°, DCB 0.70°, VNG 0.70°,
#: bilinear 0.96° (2026-11-29). AHD, LibRaw's default and the most widely used, is kept: the
#: others are within the measurement's spread, and the gap to the TIFFs is the mosaic's own.
DEMOSAIC = "AHD"
#: The raw data, per raw pixel, at most: a 4-channel uint16 "stack" (LinearRaw DNG, Foveon);
#: a Bayer mosaic takes 2, but which one a file holds is known only after unpacking it.
_RAW_BYTES = 8
#: TIFF tags read from a RAW file's first IFD and its sub-IFDs.
_MAKE, _MODEL, _SUBIFDS, _DNG_VERSION = 271, 272, 330, 50706
_DATA_TAGS = ((273, 279), (324, 325))  # (StripOffsets, StripByteCounts), (TileOffsets, TileByteCounts)
_TIFF_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4}


def is_raw(path: str | os.PathLike) -> bool:
    """Whether a file is a camera RAW photograph, by its suffix (:data:`RAW_SUFFIXES`).

    By name, not content: most RAW formats are TIFF inside and would otherwise be taken for
    one by :func:`ptmcore.decoders.image_format`.
    """
    return Path(path).suffix.lower() in RAW_SUFFIXES


@dataclass(frozen=True)
class RawDevelopment:
    """How a capture's RAW photographs are developed, all alike (see the module's notes).

    Attributes
    ----------
    white_balance : tuple of 4 float
        LibRaw's ``user_wb`` multipliers, R G B G2 (for a 4-colour sensor, its four colours),
        normalised to G = 1. LibRaw divides them by the smallest before use, so only their
        ratios matter.
    flip : int
        LibRaw's flip code (``user_flip``): 0 as stored, 3 rotated 180°, 5 rotated 90°
        anticlockwise, 6 rotated 90° clockwise (1, 2, 4, 7: mirrored).
    source : str
        Where the white balance came from: ``"camera"`` (as shot), ``"daylight"`` (the
        camera's daylight balance, when the file has no as-shot one), ``"monochrome"`` (a
        sensor without colours) or ``"given"``.
    """

    white_balance: tuple[float, float, float, float]
    flip: int = 0
    source: str = "given"

    def __post_init__(self) -> None:
        wb = tuple(float(m) for m in self.white_balance)
        if len(wb) != 4 or not all(math.isfinite(m) and m >= 0 for m in wb) or min(wb[:3]) <= 0:
            raise ValueError(f"white balance must be 4 finite multipliers, R G B positive, not {self.white_balance!r}")
        if wb[3] == 0:
            wb = (*wb[:3], wb[1])  # LibRaw's convention: no second green means the first
        object.__setattr__(self, "white_balance", tuple(m / wb[1] for m in wb))
        if int(self.flip) != self.flip or not 0 <= self.flip <= 7:
            raise ValueError(f"flip must be one of LibRaw's codes 0 to 7, not {self.flip!r}")
        object.__setattr__(self, "flip", int(self.flip))

    def describe(self) -> str:
        """A short text for reports: ``"camera white balance 2.05/1/1.46"`` (and the
        orientation when it is not as stored)."""
        r, g, b, g2 = self.white_balance
        if self.source == "monochrome":
            return "monochrome" + (f", {_FLIPS[self.flip]}" if self.flip else "")
        text = f"{self.source} white balance {_number(r)}/{_number(g)}/{_number(b)}"
        if abs(g2 - g) > 1e-6:
            text += f"/{_number(g2)}"
        if self.flip:
            text += f", {_FLIPS[self.flip]}"
        return text


def _number(x: float) -> str:
    return f"{x:.3g}"


# --- reading the file -----------------------------------------------------------------------------


def _read_bytes(path: Path) -> bytes:
    """The file's bytes (a regular file only, so nothing blocks), after asking whether they fit."""
    with open_input_file(path, "RAW file") as f:
        size = os.fstat(f.fileno()).st_size
        _check_memory(size, "reading the file", path)
        try:
            data = f.read()
        except OSError as exc:
            raise InputError(f"cannot read RAW file ({exc.strerror or exc})", path) from None
    if not data:
        raise InputError("RAW file is empty", path)
    return data


def _check_memory(nbytes: int, what: str, path: Path) -> None:
    if nbytes > decoders._ASK_MEMORY_BYTES:  # read when asked: tests lower it
        from .resources import available_memory_mb

        free = available_memory_mb()
        if nbytes > free * 2**20:
            raise InputError(f"{what} takes {nbytes / 2**20:,.0f} MiB, more than the {free:,.0f} MiB of memory "
                             "available", path)


def _reason(exc: BaseException) -> str:
    """LibRaw's message for an error, as words: rawpy gives LibRaw's C string as bytes."""
    text = exc.args[0] if exc.args else type(exc).__name__
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    text = " ".join(str(text).split()) or type(exc).__name__
    if isinstance(exc, MemoryError):
        text = "not enough memory"
    return text[:1].lower() + text[1:]


@contextmanager
def _libraw(path: Path) -> Iterator[None]:
    """Turn whatever LibRaw (or rawpy) raises for a corrupt or unsupported file into one line."""
    try:
        yield
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - rawpy.LibRawError and its kin, OSError, MemoryError, ...
        raise InputError(f"LibRaw cannot read this RAW file ({_reason(exc)})", path) from None


def _open(path: Path, data: bytes) -> rawpy.RawPy:
    """A RawPy opened on the file's bytes: the header read, nothing unpacked. Close it.

    Only the RawPy keeps ``data`` (until it unpacks it): a caller that drops its own
    reference lets the bytes go as soon as LibRaw has decoded them.
    """
    import rawpy

    raw = rawpy.RawPy()
    try:
        with _libraw(path):
            # BytesIO.read() of a whole buffer returns the same bytes object: no copy.
            raw.open_buffer(io.BytesIO(data))
    except BaseException:
        raw.close()
        raise
    return raw


def _checked_sizes(raw: rawpy.RawPy, path: Path, file_size: int) -> rawpy.ImageSizes:
    """LibRaw's sizes, refused when absurd: none, beyond :data:`MAX_PIXELS`, or more than the
    file's bytes can hold (before anything is allocated for them)."""
    s = raw.sizes
    if min(s.width, s.height, s.raw_width, s.raw_height, s.iwidth, s.iheight) < 1:
        raise InputError(f"LibRaw cannot read this RAW file (it claims {s.width} × {s.height} pixels: "
                         "a corrupt header, or no image LibRaw can develop)", path)
    _check_claim(s.raw_width, s.raw_height, 0, path)
    # A RAW's data is at most MAX_EXPANSION times smaller than its 16-bit samples (lossless
    # JPEG and Deflate expand far less), so a small file claiming a huge sensor is corrupt.
    if 2 * s.raw_width * s.raw_height > MAX_EXPANSION * file_size:
        raise InputError(f"the RAW file claims {s.raw_width} × {s.raw_height} pixels, more than its {file_size:,} "
                         "bytes can hold (a truncated or corrupt file)", path)
    return s


def _developed_size(s: rawpy.ImageSizes, flip: int, half: bool) -> tuple[int, int]:
    """``(width, height)`` of LibRaw's output for ``sizes`` (LibRaw's own arithmetic: the
    half-size shrink, the stretch of non-square pixels, then the flip)."""
    height, width = ((s.height + 1) >> 1, (s.width + 1) >> 1) if half else (s.height, s.width)
    aspect = s.pixel_aspect
    if aspect and math.isfinite(aspect) and aspect != 1:
        if aspect < 1:
            height = int(height / aspect + 0.5)
        else:
            width = int(width * aspect + 0.5)
    return (height, width) if flip & 4 else (width, height)


def _development(raw: rawpy.RawPy, path: Path) -> RawDevelopment:
    """The file's own development: its as-shot white balance (else its daylight one), its flip.
    Unpacks the raw data (rawpy reads the balances only after unpacking)."""
    colours = raw.num_colors
    flip = raw.sizes.flip if 0 <= raw.sizes.flip <= 7 else 0  # LibRaw's codes; anything else is as stored
    for source, wb in (("camera", raw.camera_whitebalance), ("daylight", raw.daylight_whitebalance)):
        m = [float(x) for x in wb]
        if colours != 4 and m[3] <= 0:
            m[3] = m[1]
        if all(math.isfinite(x) and x > 0 for x in m):
            return RawDevelopment((m[0], m[1], m[2], m[3]), flip, source)
    if colours == 1:  # a monochrome sensor: nothing to balance
        return RawDevelopment((1.0, 1.0, 1.0, 1.0), flip, "monochrome")
    raise InputError("the RAW file has neither an as-shot nor a daylight white balance that LibRaw knows "
                     "(an unsupported camera?)", path)


# --- the TIFF structure of TIFF-based RAW files, for DNG checks and the camera's name ----------


def _tiff_order(data: bytes) -> str | None:
    """``"<"`` or ``">"`` for a TIFF-like header (TIFF, ORF's ``IIRO``, RW2's ``IIU``), else None."""
    if data[:2] == b"II":
        return "<"
    if data[:2] == b"MM":
        return ">"
    return None


def _ifd(data: bytes, offset: int, order: str) -> dict[int, tuple[int, int, int]]:
    """The entries of the IFD at ``offset``: tag → (type, count, offset of the value); empty
    when it lies outside the data."""
    if not 8 <= offset <= len(data) - 2:
        return {}
    (n,) = struct.unpack_from(order + "H", data, offset)
    if offset + 2 + 12 * n > len(data):
        return {}
    entries = {}
    for k in range(n):
        at = offset + 2 + 12 * k
        tag, kind, count = struct.unpack_from(order + "HHI", data, at)
        size = _TIFF_TYPE_SIZES.get(kind, 0) * count
        value_at = at + 8 if size <= 4 else struct.unpack_from(order + "I", data, at + 8)[0]
        entries[tag] = (kind, count, value_at)
    return entries


def _numbers(data: bytes, entry: tuple[int, int, int], order: str) -> np.ndarray | None:
    """A SHORT or LONG entry's values (as int64: offsets and counts add without overflow);
    None when not one or outside the data."""
    kind, count, at = entry
    code = {3: "u2", 4: "u4", 13: "u4"}.get(kind)
    if code is None or at + _TIFF_TYPE_SIZES[kind] * count > len(data):
        return None
    return np.frombuffer(data, order + code, count, at).astype(np.int64)


def _text(data: bytes, entry: tuple[int, int, int] | None) -> str:
    if entry is None or entry[0] != 2 or entry[2] + entry[1] > len(data):
        return ""
    raw = data[entry[2]:entry[2] + min(entry[1], 128)].split(b"\x00")[0]
    text = " ".join(raw.decode("latin-1").split())
    return text if text.isprintable() else ""


def _camera_name(data: bytes) -> str:
    """The camera's make and model from the file's first IFD (TIFF-based formats, CR3's CMT1
    box) or a RAF header; ``""`` when not found."""
    if data[:16] == b"FUJIFILMCCD-RAW ":
        make, model = "FUJIFILM", " ".join(data[0x1C:0x3C].split(b"\x00")[0].decode("latin-1").split())
    else:
        base = 0
        if data[4:12] == b"ftypcrx ":  # CR3: an ISO box file whose CMT1 box is a TIFF's first IFD
            base = data.find(b"CMT1", 0, 1 << 16) + 4
            if base < 4:
                return ""
        tiff = data[base:]
        order = _tiff_order(tiff)
        if order is None or len(tiff) < 8:
            return ""
        ifd0 = _ifd(tiff, struct.unpack_from(order + "I", tiff, 4)[0], order)
        make, model = _text(tiff, ifd0.get(_MAKE)), _text(tiff, ifd0.get(_MODEL))
    if not model.isprintable() or not make.isprintable():
        return ""
    # "Canon" + "Canon EOS 5D Mark IV", "NIKON CORPORATION" + "NIKON D850": the model says both.
    if make and not model.lower().startswith(make.split()[0].lower()):
        return f"{make} {model}".strip()
    return model or make


def _check_dng(path: Path, data: bytes) -> None:
    """A ``.dng`` must be a DNG (a TIFF with DNGVersion in its first IFD: LibRaw would take a
    grey TIFF named .dng for a raw mosaic) and hold all the image data its IFDs point to (a
    truncated copy is named as such, before LibRaw prints its own complaint on stderr)."""
    order = _tiff_order(data)
    if order is None or len(data) < 8 or struct.unpack_from(order + "H", data, 2)[0] != 42:
        raise InputError("is not a DNG (no TIFF header; told by its name, a DNG is a TIFF inside)", path)
    offset = struct.unpack_from(order + "I", data, 4)[0]
    if offset + 2 > len(data) or offset + 2 + 12 * struct.unpack_from(order + "H", data, offset)[0] > len(data):
        raise InputError("the RAW file is truncated (its first IFD lies past the end of the file)", path)
    ifd0 = _ifd(data, offset, order)
    if _DNG_VERSION not in ifd0:
        raise InputError("is not a DNG (its TIFF header has no DNGVersion tag); a TIFF should be named .tif", path)
    ifds = [ifd0]
    subs = _numbers(data, ifd0[_SUBIFDS], order) if _SUBIFDS in ifd0 else None
    ifds += [_ifd(data, int(o), order) for o in ([] if subs is None else subs[:64])]
    for ifd in ifds:
        for offsets_tag, counts_tag in _DATA_TAGS:
            if offsets_tag in ifd and counts_tag in ifd:
                offsets, counts = _numbers(data, ifd[offsets_tag], order), _numbers(data, ifd[counts_tag], order)
                if offsets is None or counts is None:
                    continue
                k = min(len(offsets), len(counts))
                if np.any((counts[:k] > 0) & (offsets[:k] + counts[:k] > len(data))):
                    raise InputError("the RAW file is truncated (its image data runs past the end of the file)",
                                     path)


def _prepared(path: Path) -> bytes:
    data = _read_bytes(path)
    if path.suffix.lower() == ".dng":
        _check_dng(path, data)
    return data


def _own_development(path: Path, data: bytes) -> RawDevelopment:
    """:func:`raw_development` of the file's bytes (``data`` is released once unpacked)."""
    with closing(_open(path, data)) as raw:
        s = _checked_sizes(raw, path, len(data))
        _check_memory(len(data) + _RAW_BYTES * s.raw_width * s.raw_height, "unpacking the RAW data", path)
        del data
        with _libraw(path):
            return _development(raw, path)


# --- the public functions ----------------------------------------------------------------------------


def raw_development(path: str | os.PathLike) -> RawDevelopment:
    """A RAW photograph's own development: its as-shot white balance and its orientation.

    Parameters
    ----------
    path : str or PathLike
        A camera RAW file (:func:`is_raw`).

    Returns
    -------
    RawDevelopment
        The camera's as-shot multipliers (``camera_whitebalance``), or its daylight ones when
        the file has none (all zeros); a missing second green is the first. The flip is the
        file's (``sizes.flip``). Develop every photograph of a capture with the first one's.
        rawpy gives the multipliers only after unpacking the raw data, which this does (a
        fifth of a full development's time).

    Raises
    ------
    InputError
        As :func:`read_raw`.
    """
    path = Path(path)
    return _own_development(path, _prepared(path))


def read_raw(path: str | os.PathLike, development: RawDevelopment | None = None, *,
             min_side: int | None = None) -> np.ndarray:
    """Develop a camera RAW photograph into linear 16-bit RGB with LibRaw.

    Parameters
    ----------
    path : str or PathLike
        A camera RAW file (:func:`is_raw`), read through
        :func:`ptmcore.errors.open_input_file` (regular files only).
    development : RawDevelopment, optional
        The capture's white balance and orientation (:func:`raw_development` of its first
        photograph). Default: the file's own, which is right for one photograph but lets a
        capture's photographs differ if their as-shot balance or orientation differ.
    min_side : int, optional
        The caller accepts a smaller image whose sides are both at least this long: LibRaw's
        half-size development (each 2 × 2 Bayer block one pixel, no demosaicing) is used when
        its sides are long enough.

    Returns
    -------
    ndarray, shape (H, W, 3), uint16
        Linear light in sRGB's primaries and D65 white (gamma 1, no automatic brightening, the
        white level at 65535; see the module's notes), oriented by the development's flip. A
        monochrome sensor's grey is repeated into the three channels.

    Raises
    ------
    InputError
        Naming the file: missing, not a regular file, empty, a ``.dng`` that is not a DNG or is
        truncated, a file LibRaw cannot read (corrupt, truncated, unsupported), sizes beyond
        :data:`ptmcore.decoders.MAX_PIXELS` or what the file's bytes can hold, more memory
        than is available, or no white balance LibRaw knows.
    """
    import rawpy

    path = Path(path)
    data = _prepared(path)
    with closing(_open(path, data)) as raw:
        s = _checked_sizes(raw, path, len(data))
        flip = development.flip if development is not None else s.flip & 7
        half = min_side is not None and min((s.height + 1) >> 1, (s.width + 1) >> 1) >= min_side
        out_w, out_h = _developed_size(s, flip, half)
        # LibRaw holds the file's bytes until unpacked, the raw data, its 4-channel image and
        # the output at once; counted at full size even for a half-size development, whose
        # shrink LibRaw decides only after unpacking (a Bayer mosaic is shrunk, others not).
        need = (len(data) + _RAW_BYTES * s.raw_width * s.raw_height + _IMAGE_BYTES * s.iwidth * s.iheight
                + _OUTPUT_BYTES * max(out_w * out_h, s.width * s.height))
        _check_claim(out_w, out_h, need, path)
        del data
        with _libraw(path):
            dev = development if development is not None else _development(raw, path)
            img = raw.postprocess(
                demosaic_algorithm=getattr(rawpy.DemosaicAlgorithm, DEMOSAIC), half_size=half,
                use_camera_wb=False, use_auto_wb=False, user_wb=list(dev.white_balance),
                output_color=rawpy.ColorSpace.sRGB, output_bps=16, gamma=(1.0, 1.0),
                no_auto_bright=True, adjust_maximum_thr=0.0, highlight_mode=rawpy.HighlightMode.Clip,
                user_flip=dev.flip)
    # The array owns LibRaw's output buffer (freed with it), which outlives the closed RawPy.
    if img.dtype != np.uint16 or img.ndim != 3 or img.shape[2] not in (1, 3) or min(img.shape[:2]) < 1:
        raise InputError(f"LibRaw cannot read this RAW file (it developed {img.shape} {img.dtype}, not RGB)", path)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return img


def raw_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(width, height)`` of a RAW photograph as :func:`read_raw` develops it with the file's
    own development (its own flip), from its header alone (nothing is unpacked); None when the
    file cannot be read.

    Ordered as :func:`ptmcore.decoders.image_size`, whose answer for RAW files this is. A
    capture developed with another photograph's flip may have width and height swapped.
    """
    path = Path(path)
    try:
        data = _prepared(path)
        with closing(_open(path, data)) as raw:
            s = _checked_sizes(raw, path, len(data))
            return _developed_size(s, s.flip, False)
    except InputError:
        return None


def raw_description(path: str | os.PathLike, development: RawDevelopment | None = None) -> str:
    """How a RAW photograph's colours are read, for reports:
    ``"camera RAW (Canon EOS 5D Mark IV; LibRaw, linear, camera white balance 2.05/1/1.46)"``.

    Parameters
    ----------
    path : str or PathLike
        A camera RAW file.
    development : RawDevelopment, optional
        The capture's development; default the file's own (:func:`raw_development`, which
        unpacks the raw data).

    Raises
    ------
    InputError
        As :func:`read_raw`.
    """
    path = Path(path)
    data = _prepared(path)
    camera = _camera_name(data)
    if development is None:
        development = _own_development(path, data)
    return f"camera RAW ({camera + '; ' if camera else ''}LibRaw, linear, {development.describe()})"
