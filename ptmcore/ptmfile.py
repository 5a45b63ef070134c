"""HP Polynomial Texture Map (``.ptm``) files: reading, writing, and HP's own LRGB fit.

File layout (Malzbender & Gelb, *Polynomial Texture Map (.ptm) File Format*, HP Labs, version
1.2, 2001), as HP's PTMfitter writes it and RTIViewer reads it::

    PTM_1.2
    PTM_FORMAT_LRGB
    8
    5
    0.500000 0.500000 0.250000 0.500000 0.250000 1.000000 \\n   (six scales, "%f ")
    167 97 0 0 0 0 \\n                                          (six integer biases, "%d ")
    <binary payload>

The format name, width and height are on their own lines; the six scales share one line and the
six biases another, each value followed by a space (RTIViewer splits these lines on spaces and
parses every bias as an integer, so a fractional bias makes it refuse the file). A coefficient is
stored as a byte and decoded as ``a_i = (byte − bias_i) · scale_i``. The polynomial multiplies
``(lu², lv², lu·lv, lu, lv, 1)``, where (lu, lv) is the light direction projected onto the image.
**Rows are stored bottom row first**; in memory this module keeps the project's convention, row 0
at the top.

Payloads:

* ``PTM_FORMAT_LRGB``, version 1.2: a block of W·H·6 bytes (a0..a5 per pixel), then a block of
  W·H·3 bytes (R, G, B per pixel). Versions before 1.2 (``PTM_1.0``, ``PTM_1.1``) interleave the
  two, 9 bytes per pixel (a0..a5 R G B). RTIViewer shows a pixel as ``rgb · L / 255``, so the
  luminance polynomial L is in units of about 0..255.
* ``PTM_FORMAT_RGB``: three blocks (R, G, B) of W·H·6 bytes, one shared set of scales and biases;
  each channel's polynomial gives that channel's value directly.
* ``PTM_FORMAT_JPEG_LRGB`` / ``PTM_FORMAT_JPEG_RGB``: after the bias line, a line with the JPEG
  quality, then seven lines of one integer per plane (9 planes for LRGB: a0..a5, R, G, B; 18 for
  RGB: a0..a5 of R, then of G, then of B, the order of the uncompressed blocks and of Perathoner's
  ptmlib; no file from HP's own JPEG-RGB writer was at hand to confirm it): transform, motion
  vector x, motion vector y, decoding order, reference plane, compressed size, side-information
  size. The payload holds, plane by plane in plane order, a grayscale JPEG stream (rows bottom
  first, like the raw formats) followed by its side information. Planes are decoded in increasing ``order``; a plane with a reference
  plane r ≥ 0 stores a residual, and its value is ``(residual + ref − 128) mod 256`` where ``ref``
  is plane r after its own decoding, or ``255 − ref`` when bit 0 of the transform (plane
  inversion) is set. Side information then overwrites single bytes: 5-byte records, a 4-byte
  big-endian offset into the plane (in file order) and the value. Bit 1 of the transform (motion
  compensation) is not supported by RTIViewer or any public reader and is refused here.

HP's quantisation (reproduces PTMfitter's header on the shared fixture): per coefficient over the
whole image (and over the three channels for the RGB format), with ``max − min = m · 2^e``
(``frexp``), ``scale = 2^(e − 8)``; if ``min < 0``, ``bias = int(−min/scale + 1)``, doubling the
scale while ``bias > 255``; otherwise ``bias = 0`` and the scale doubles while
``max/scale > 255``. A value is stored as ``floor(v/scale + bias + 0.5)`` clamped to 0..255.

PTMfitter's LRGB fit (worked out from ``shared/fixtures/ptmfitter_8x5``, whose 12 photographs
and PTMfitter output are reproduced **byte for byte** by :func:`fit_ptm_encoded` followed by
:func:`write_ptm`): it fits the photographs' own 8-bit values, not linear light.

* The luminance of a photograph is the luma ``0.2125 R + 0.7154 G + 0.0721 B`` of its bytes (the
  Rec. 709 weights as they were quoted around 2000; the current 0.2126/0.7152/0.0722 misses one
  of the 240 coefficient bytes, by 0.005 of a step; Rec. 601 weights or the mean of R, G, B miss
  most of them). In a grid search (steps of 0.0005) only weights next to these reproduce every
  byte, but that rests on a handful of bytes close to a rounding boundary in one small fixture.
* Per pixel, that luminance is normalised so that the pixel's brightest photograph has L = 255:
  ``L_n = 255 · Y_n / max_n Y_n``; the polynomial is the least-squares (pseudoinverse) fit of L_n.
* The pixel's colour in the RGB block is the least-squares solution of ``C_n ≈ rgb · L_n / 255``
  over the photographs, ``rgb = max_n Y_n · Σ C_n Y_n / Σ Y_n²``, truncated (not rounded) to an
  integer. (Fitting against the polynomial's values instead of the observed L_n gives the same
  bytes on the fixture; the mean colour times the peak luminance, or the colour of the brightest
  photograph, do not.)
"""

from __future__ import annotations

import io
import itertools
import math
import mmap
import os
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .errors import InputError, read_input_file
from .fit import fit_matrix, light_matrix
from .lp import as_directions
from .streaming import accumulate_photographs, fit_channels

__all__ = [
    "FORMAT_JPEG_LRGB",
    "FORMAT_JPEG_RGB",
    "FORMAT_LRGB",
    "FORMAT_RGB",
    "HP_LUMA_WEIGHTS",
    "PTMFile",
    "fit_ptm_encoded",
    "fit_ptm_rgb_encoded",
    "quantization_parameters",
    "quantize",
    "read_ptm",
    "write_ptm",
]

FORMAT_LRGB = "PTM_FORMAT_LRGB"
FORMAT_RGB = "PTM_FORMAT_RGB"
FORMAT_JPEG_LRGB = "PTM_FORMAT_JPEG_LRGB"
FORMAT_JPEG_RGB = "PTM_FORMAT_JPEG_RGB"
_FORMATS = (FORMAT_LRGB, FORMAT_RGB, FORMAT_JPEG_LRGB, FORMAT_JPEG_RGB)
#: Number of JPEG planes of each compressed format.
_JPEG_PLANES = {FORMAT_JPEG_LRGB: 9, FORMAT_JPEG_RGB: 18}

VERSION = "PTM_1.2"
#: Versions whose LRGB payload interleaves a0..a5 R G B per pixel (RTIViewer knows PTM_1.1;
#: relight treats every version other than 1.2 so).
_INTERLEAVED_VERSIONS = ("PTM_1.0", "PTM_1.1")

#: Luma weights HP's PTMfitter applies to the photographs' R, G, B bytes (see the module notes).
HP_LUMA_WEIGHTS = np.array([0.2125, 0.7154, 0.0721])

_HEADER_TOKEN_MAX = 40  # longer "numbers" in a header are garbage, not data
_INT_RE = re.compile(rb"[+-]?[0-9]+")
_FLOAT_RE = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_WHITESPACE = b" \t\r\n"
#: Largest plausible decompressed/compressed size ratio of one JPEG plane. A baseline JPEG needs
#: at least ~2 bits per 8×8 block (a DC code and an end-of-block code), i.e. a ratio of 256 at
#: most; the slack leaves room for arithmetic coding while still refusing, before anything is
#: allocated, a header that claims a gigapixel plane for a few bytes.
_JPEG_MAX_RATIO = 1024


# ---------------------------------------------------------------------------------------------
# The in-memory PTM


def _light_row(light: np.ndarray | Sequence[float]) -> np.ndarray:
    """The polynomial's six light terms for one direction (x, y, z) or (lu, lv)."""
    v = np.asarray(light, dtype=np.float64).reshape(-1)
    if v.size == 3:
        norm = float(np.linalg.norm(v))
        if not np.isfinite(norm) or norm == 0.0:
            raise ValueError(f"light direction {v.tolist()} is zero or not finite")
        v = v / norm  # (lu, lv) are the projection of the *unit* vector
    elif v.size != 2:
        raise ValueError(f"a light is (x, y, z) or (lu, lv), not {v.size} numbers")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"light direction {v.tolist()} is not finite")
    return light_matrix(v[None, :2])[0].astype(np.float32)


def _to_byte(values: np.ndarray) -> np.ndarray:
    """Clip to 0..255 and round to the nearest byte."""
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


@dataclass
class PTMFile:
    """A PTM as stored in a ``.ptm`` file, decoded.

    Attributes
    ----------
    format : str
        The file's format line, e.g. ``"PTM_FORMAT_LRGB"`` or ``"PTM_FORMAT_JPEG_RGB"``.
    version : str
        The file's version line, e.g. ``"PTM_1.2"``.
    width, height : int
        Size in pixels.
    scale : ndarray, shape (6,), float64
        Per-coefficient scale of the stored bytes.
    bias : ndarray, shape (6,), int64
        Per-coefficient bias of the stored bytes.
    coefficients : ndarray, float32
        Decoded coefficients, row 0 at the top: ``(H, W, 6)`` for the LRGB formats (luminance,
        about 0..255) or ``(H, W, 3, 6)`` for the RGB formats (one polynomial per channel, 0..255).
    rgb : ndarray, shape (H, W, 3), uint8, or None
        The colour block of the LRGB formats; None for the RGB formats.
    jpeg_quality : int or None
        The quality recorded in a JPEG-compressed file.
    """

    format: str
    version: str
    width: int
    height: int
    scale: np.ndarray
    bias: np.ndarray
    coefficients: np.ndarray
    rgb: np.ndarray | None
    jpeg_quality: int | None = None

    @property
    def is_lrgb(self) -> bool:
        """Whether the PTM is LRGB (one luminance polynomial and a colour per pixel)."""
        return self.coefficients.ndim == 3

    def luminance(self, light: np.ndarray | Sequence[float]) -> np.ndarray:
        """Evaluate the polynomials under one light.

        Parameters
        ----------
        light : array_like
            Direction towards the light, (x, y, z) (normalised here) or (lu, lv).

        Returns
        -------
        ndarray, float32
            ``(H, W)`` luminance for LRGB, ``(H, W, 3)`` channel values for RGB.
        """
        return self.coefficients @ _light_row(light)

    def render(self, light: np.ndarray | Sequence[float]) -> np.ndarray:
        """The image RTIViewer shows under one light (its default rendering).

        LRGB: ``rgb · L / 255``; RGB: each channel's polynomial; both clipped to 0..255 and
        truncated, as RTIViewer's ``tobyte`` does (consistent with :mod:`ptmcore.relight`).
        RTIViewer also truncates each decoded coefficient to an integer when it loads a file,
        a difference below one coefficient unit that is not reproduced here.

        Returns
        -------
        ndarray, shape (H, W, 3), uint8
        """
        values = self.luminance(light)
        if self.is_lrgb:
            # Product first: integral results stay exact, so truncation cannot drop a level.
            values = self.rgb * values[..., None] / np.float32(255)
        return np.clip(values, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# Reading


class _Cursor:
    """Reads the text header of a PTM held in memory, refusing anything malformed."""

    def __init__(self, data: bytes, path: Path) -> None:
        self.data = data
        self.pos = 0
        self.path = path

    def fail(self, problem: str) -> InputError:
        return InputError(problem, self.path)

    def line(self, what: str) -> str:
        end = self.data.find(b"\n", self.pos, self.pos + 256)
        if end < 0:
            raise self.fail(f"not a PTM file: no {what} line")
        raw = self.data[self.pos : end].strip(_WHITESPACE)
        self.pos = end + 1
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError:
            raise self.fail(f"not a PTM file: the {what} line is not text") from None

    def token(self, what: str) -> bytes:
        data, n = self.data, len(self.data)
        i = self.pos
        while i < n and data[i] in _WHITESPACE:
            i += 1
        j = i
        while j < n and data[j] not in _WHITESPACE and j - i <= _HEADER_TOKEN_MAX:
            j += 1
        if i == j:
            raise self.fail(f"header ends before the {what}")
        if j - i > _HEADER_TOKEN_MAX:
            raise self.fail(f"the {what} hold something too long to be a number")
        self.pos = j
        return data[i:j]

    def _numbers(self, count: int, what: str, pattern: re.Pattern, convert: Callable, kind: str) -> list:
        values = []
        for k in range(count):
            tok = self.token(what)
            if not pattern.fullmatch(tok):
                shown = tok.decode("ascii", "backslashreplace")
                raise self.fail(f"the {what} must be {kind}; value {k + 1} is {shown!r}")
            values.append(convert(tok))
        return values

    def ints(self, count: int, what: str) -> list[int]:
        return self._numbers(count, what, _INT_RE, int, "integers")

    def floats(self, count: int, what: str) -> list[float]:
        return self._numbers(count, what, _FLOAT_RE, float, "numbers")

    def end_header(self) -> int:
        """Consume the rest of the last header line; the payload starts right after it.

        Only the rest of *that* line may be skipped: the payload is binary and may begin with
        bytes that look like white space.
        """
        end = self.data.find(b"\n", self.pos, self.pos + 256)
        if end < 0 or self.data[self.pos : end].strip(b" \t\r"):
            raise self.fail("the header's last line has unexpected content or no line end")
        self.pos = end + 1
        return self.pos


def _decode_block(
    raw: np.ndarray, scale: np.ndarray, bias: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """Coefficient bytes ``(H, W, 6)`` in file order (bottom row first) → float32, top first.

    ``out`` may be a view into a larger array (one channel of an RGB-format PTM).
    """
    h, w = raw.shape[:2]
    if out is None:
        out = np.empty((h, w, 6), dtype=np.float32)
    s32 = scale.astype(np.float32)
    b32 = bias.astype(np.float32)
    step = max(1, (1 << 20) // (w * 6))  # bands keep the float temporaries small
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        band = raw[h - r1 : h - r0][::-1].astype(np.float32)
        band -= b32
        band *= s32
        out[r0:r1] = band
    return out


def _decode_gray_jpeg(stream: bytes, width: int, height: int, plane: int, path: Path) -> np.ndarray:
    """One grayscale JPEG plane as ``(H, W)`` uint8; InputError if it is not a JPEG of that size."""
    where = f"JPEG plane {plane}"
    # The decoders' exceptions are their own business: whatever they raise on a broken stream
    # becomes the user's one-line error.
    try:
        import simplejpeg
    except ImportError:  # pragma: no cover - simplejpeg is a dependency; Pillow still works
        simplejpeg = None
    try:
        if simplejpeg is not None:
            h, w = simplejpeg.decode_jpeg_header(stream)[:2]
        else:  # pragma: no cover
            from PIL import Image

            with Image.open(io.BytesIO(stream)) as im:
                w, h = im.size
    except Exception as exc:
        raise InputError(f"{where} is not a readable JPEG stream ({exc})", path) from None
    if (w, h) != (width, height):
        raise InputError(f"{where} is {w}×{h} but the header says {width}×{height}", path)
    try:
        if simplejpeg is not None:
            return simplejpeg.decode_jpeg(stream, colorspace="GRAY").reshape(height, width)
        with Image.open(io.BytesIO(stream)) as im:  # pragma: no cover
            return np.asarray(im.convert("L"))
    except Exception as exc:
        raise InputError(f"{where} cannot be decoded ({exc})", path) from None


def _read_jpeg_planes(cur: _Cursor, fmt: str, width: int, height: int) -> tuple[np.ndarray, int]:
    """Decode the JPEG planes of a compressed PTM; returns ``(n, H, W)`` uint8 in file order."""
    n = _JPEG_PLANES[fmt]
    path = cur.path
    (quality,) = cur.ints(1, "JPEG quality")
    transform = cur.ints(n, "plane transforms")
    cur.ints(2 * n, "motion vectors")  # meaningful only with motion compensation, refused below
    order = cur.ints(n, "plane order")
    reference = cur.ints(n, "reference planes")
    sizes = cur.ints(n, "compressed plane sizes")
    side = cur.ints(n, "side-information sizes")
    start = cur.end_header()

    if sorted(order) != list(range(n)):
        raise InputError(f"the plane order must list each of 0..{n - 1} once, not {order}", path)
    for p in range(n):
        if transform[p] not in (0, 1, 2, 3):
            raise InputError(f"plane {p}: unknown transform {transform[p]}", path)
        if transform[p] & 2:
            raise InputError(f"plane {p}: motion-compensated prediction is not supported", path)
        r = reference[p]
        if r != -1 and not (0 <= r < n and r != p and order[r] < order[p]):
            raise InputError(
                f"plane {p}: reference plane {r} is not a plane decoded before it", path
            )
        if sizes[p] <= 0:
            raise InputError(f"plane {p}: compressed size {sizes[p]} is not positive", path)
        if side[p] < 0 or side[p] % 5:
            raise InputError(
                f"plane {p}: side-information size {side[p]} is not a multiple of 5 bytes", path
            )
        if width * height > max(1 << 20, _JPEG_MAX_RATIO * sizes[p]):
            raise InputError(
                f"plane {p}: {width}×{height} pixels cannot come from {sizes[p]} compressed bytes",
                path,
            )
    # Python integers: a hostile header's sizes may not fit in 64 bits.
    offsets = list(itertools.accumulate((a + b for a, b in zip(sizes, side)), initial=start))
    if offsets[-1] > len(cur.data):
        raise InputError(
            f"file is truncated: the JPEG planes need {offsets[-1] - start} bytes after the header, "
            f"{len(cur.data) - start} are there",
            path,
        )

    planes = np.empty((n, height, width), dtype=np.uint8)
    npix = width * height
    for p in sorted(range(n), key=order.__getitem__):
        o = offsets[p]
        plane = _decode_gray_jpeg(cur.data[o : o + sizes[p]], width, height, p, path)
        r = reference[p]
        if r >= 0:
            ref = planes[r]
            if transform[p] & 1:
                ref = 255 - ref
            # uint8 arithmetic wraps, so this is (residual + ref − 128) mod 256.
            plane = plane + ref
            plane += np.uint8(128)
        if side[p]:
            rec = np.frombuffer(cur.data, np.uint8, side[p], o + sizes[p]).reshape(-1, 5)
            at = rec[:, :4].astype(np.int64) @ np.array([1 << 24, 1 << 16, 1 << 8, 1], dtype=np.int64)
            if at.max() >= npix:
                raise InputError(
                    f"plane {p}: side information addresses pixel {int(at.max())} of {npix}", path
                )
            plane = np.array(plane, copy=True).reshape(-1)
            plane[at] = rec[:, 4]
            plane = plane.reshape(height, width)
        planes[p] = plane
    return planes, quality


def _map_file(path: Path) -> bytes | mmap.mmap:
    """The file mapped read-only (only the pages read are loaded), or its bytes when it cannot
    be mapped; :func:`read_input_file` says why a file cannot be read (missing, a folder)."""
    try:
        with open(path, "rb") as f:
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):  # ValueError: an empty file cannot be mapped
        return read_input_file(path, "PTM file")


def _every(raw: np.ndarray, stride: int) -> np.ndarray:
    """A view of every ``stride``-th row and column of ``(H, W, ...)`` bytes stored bottom row
    first, counted from the top row (``image[::stride, ::stride]`` of the top-first image), still
    bottom row first."""
    return raw if stride == 1 else raw[::-1][::stride, ::stride][::-1]


def read_ptm(path: str | os.PathLike, *, max_side: int | None = None) -> PTMFile:
    """Read a ``.ptm`` file, whole or a subsample of it.

    Parameters
    ----------
    path : str or PathLike
        A PTM of format ``PTM_FORMAT_LRGB`` (versions 1.0–1.2), ``PTM_FORMAT_RGB``,
        ``PTM_FORMAT_JPEG_LRGB`` or ``PTM_FORMAT_JPEG_RGB``.
    max_side : int, optional
        Decode only every k-th row and column (from the top-left pixel), k the smallest step
        that brings the longer side to ``max_side`` or less: a preview of a large PTM. The
        file is memory-mapped and the raw formats' bytes are strided before they are decoded,
        so time and memory follow the subsample (a 24-megapixel PTM is not decoded whole).
        The JPEG formats are decoded whole (a plane's pixels depend on one another), then
        subsampled.

    Returns
    -------
    PTMFile
        Decoded coefficients (and colours) with row 0 at the top. ``width`` and ``height``
        are the file's; a subsample's arrays are ``ceil(height / k) × ceil(width / k)``.

    Raises
    ------
    InputError
        If the file is missing or unreadable, not a PTM, of an unsupported version or format,
        has a malformed header (non-numeric fields, non-positive or impossible sizes), is
        truncated, or holds a JPEG plane that cannot be decoded. Sizes are checked against the
        file's length before anything is allocated.
    """
    path = Path(path)
    if max_side is not None and max_side < 1:
        raise ValueError(f"max_side must be at least 1, not {max_side}")
    data = _map_file(path)
    if not data:
        raise InputError("PTM file is empty", path)
    cur = _Cursor(data, path)
    if data[:4] == b"#HSH":
        raise InputError("this is an HSH .rti file, not a PTM", path)
    version = cur.line("version")
    if not version.startswith("PTM_"):
        raise InputError("not a PTM file (the first line is not PTM_1.x)", path)
    if version != VERSION and version not in _INTERLEAVED_VERSIONS:
        raise InputError(f"unsupported PTM version {version[:20]!r}", path)
    fmt = cur.line("format")
    if fmt not in _FORMATS:
        raise InputError(
            f"unsupported PTM format {fmt[:40]!r} (supported: {', '.join(_FORMATS)})", path
        )
    width, height = cur.ints(2, "width and height")
    if width <= 0 or height <= 0:
        raise InputError(f"image size {width}×{height} is not positive", path)
    if fmt in _JPEG_PLANES and max(width, height) > 65535:
        raise InputError(f"image size {width}×{height} is beyond what JPEG planes can hold", path)
    scale = np.array(cur.floats(6, "scales"), dtype=np.float64)
    if not np.all(np.isfinite(scale)) or np.any(np.abs(scale) > 1e30):
        raise InputError(f"scales {scale.tolist()} are not usable numbers", path)
    bias_tokens = cur.floats(6, "biases")
    if any(not math.isfinite(b) or b != int(b) for b in bias_tokens):
        raise InputError(f"biases must be integers, got {bias_tokens}", path)
    if any(abs(b) > 1 << 20 for b in bias_tokens):
        raise InputError(f"biases {bias_tokens} are not plausible", path)
    bias = np.array([int(b) for b in bias_tokens], dtype=np.int64)

    npix = width * height
    stride = 1 if max_side is None else max(1, math.ceil(max(width, height) / max_side))
    quality = None
    if fmt in _JPEG_PLANES:
        planes, quality = _read_jpeg_planes(cur, fmt, width, height)
        planes = np.moveaxis(_every(np.moveaxis(planes, 0, -1), stride), -1, 0)
        if fmt == FORMAT_JPEG_LRGB:
            coefficients = _decode_block(np.moveaxis(planes[:6], 0, -1), scale, bias)
            rgb = np.ascontiguousarray(np.moveaxis(planes[6:9], 0, -1)[::-1])
        else:
            coefficients = np.empty(planes.shape[1:] + (3, 6), dtype=np.float32)
            for c in range(3):
                channel = np.moveaxis(planes[6 * c : 6 * c + 6], 0, -1)
                _decode_block(channel, scale, bias, coefficients[:, :, c])
            rgb = None
    else:
        start = cur.end_header()
        need = npix * (18 if fmt == FORMAT_RGB else 9)
        have = len(data) - start
        if have < need:
            raise InputError(
                f"file is truncated: a {width}×{height} {fmt} needs {need} bytes after the header, "
                f"{have} are there",
                path,
            )
        if fmt == FORMAT_RGB:
            raw = np.frombuffer(data, np.uint8, need, start).reshape(3, height, width, 6)
            channels = [_every(raw[c], stride) for c in range(3)]
            coefficients = np.empty(channels[0].shape[:2] + (3, 6), dtype=np.float32)
            for c in range(3):
                _decode_block(channels[c], scale, bias, coefficients[:, :, c])
            rgb = None
        elif version in _INTERLEAVED_VERSIONS:
            raw = _every(np.frombuffer(data, np.uint8, need, start).reshape(height, width, 9), stride)
            coefficients = _decode_block(raw[..., :6], scale, bias)
            rgb = np.ascontiguousarray(raw[::-1, :, 6:])
        else:
            coef_raw = np.frombuffer(data, np.uint8, 6 * npix, start).reshape(height, width, 6)
            rgb_raw = np.frombuffer(data, np.uint8, 3 * npix, start + 6 * npix).reshape(height, width, 3)
            coefficients = _decode_block(_every(coef_raw, stride), scale, bias)
            rgb = np.ascontiguousarray(_every(rgb_raw, stride)[::-1])
    return PTMFile(fmt, version, width, height, scale, bias, coefficients, rgb, quality)


# ---------------------------------------------------------------------------------------------
# Quantising and writing


def _scale_bias(lo: float, hi: float) -> tuple[float, int]:
    """HP's scale and bias for one coefficient whose values span ``[lo, hi]``."""
    _, e = math.frexp(hi - lo)
    scale = math.ldexp(1.0, e - 8)
    if lo < 0:
        bias = int(-lo / scale + 1)
        while bias > 255:
            scale *= 2
            bias = int(-lo / scale + 1)
    else:
        bias = 0
        while hi / scale > 255:
            scale *= 2
    return scale, bias


def _check_coefficients(coefficients: np.ndarray) -> np.ndarray:
    c = np.asarray(coefficients)
    if not ((c.ndim == 3 and c.shape[2] == 6) or (c.ndim == 4 and c.shape[2:] == (3, 6))):
        raise ValueError(f"coefficients must be (H, W, 6) or (H, W, 3, 6), not {c.shape}")
    if c.shape[0] < 1 or c.shape[1] < 1:
        raise ValueError(f"coefficients of shape {c.shape} hold no pixels")
    if c.dtype.kind not in "fiu":
        raise ValueError(f"coefficients must be numbers, not {c.dtype}")
    return c


def quantization_parameters(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """HP's per-coefficient scales and biases for a PTM.

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6) or (H, W, 3, 6)
        LRGB or per-channel (RGB format: one shared set over the three channels) coefficients.

    Returns
    -------
    scale : ndarray, shape (6,), float64
        Powers of two.
    bias : ndarray, shape (6,), int64
        Integers in 0..255.
    """
    c = _check_coefficients(coefficients)
    axes = tuple(range(c.ndim - 1))
    lo = np.min(c, axis=axes).astype(np.float64)
    hi = np.max(c, axis=axes).astype(np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("coefficients contain NaN or infinite values")
    pairs = [_scale_bias(float(a), float(b)) for a, b in zip(lo, hi)]
    return np.array([s for s, _ in pairs]), np.array([b for _, b in pairs], dtype=np.int64)


def _encode(values: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """``floor(v/scale + bias + 0.5)`` clamped to bytes (float64, so ties land as HP's do)."""
    q = values.astype(np.float64)
    q /= scale
    q += bias + 0.5
    np.floor(q, out=q)
    np.clip(q, 0, 255, out=q)
    return q.astype(np.uint8)


def quantize(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quantise PTM coefficients to bytes by HP's rule.

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6) or (H, W, 3, 6)
        LRGB or RGB-format coefficients.

    Returns
    -------
    codes : ndarray, uint8, same shape
        ``floor(v/scale + bias + 0.5)`` clamped to 0..255; decoded as ``(code − bias)·scale``.
    scale : ndarray, shape (6,), float64
    bias : ndarray, shape (6,), int64
    """
    c = _check_coefficients(coefficients)
    scale, bias = quantization_parameters(c)
    return _encode(c, scale, bias), scale, bias


def _format_scale(s: float) -> str:
    # PTMfitter writes "%f"; a scale below 2^-6 needs more decimals than that, and a rounded
    # scale would decode every coefficient wrongly, so such scales get the shortest exact form.
    text = f"{s:f}"
    return text if float(text) == s else repr(s)


def _header(fmt: str, width: int, height: int, scale: np.ndarray, bias: np.ndarray) -> bytes:
    lines = [
        VERSION,
        fmt,
        str(width),
        str(height),
        "".join(f"{_format_scale(float(s))} " for s in scale),
        "".join(f"{int(b)} " for b in bias),
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


class _ErrorStats:
    """Running per-coefficient max, RMS and clamp count of the quantisation error."""

    def __init__(self) -> None:
        self.max = np.zeros(6)
        self.sq = np.zeros(6)
        self.clipped = np.zeros(6, dtype=np.int64)
        self.count = 0

    def add(self, values: np.ndarray, codes: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> None:
        v = values.reshape(-1, 6).astype(np.float64)
        q = codes.reshape(-1, 6)
        err = (q.astype(np.float64) - bias) * scale - v
        np.maximum(self.max, np.abs(err).max(axis=0), out=self.max)
        self.sq += np.einsum("ij,ij->j", err, err)
        exact = v / scale + bias + 0.5
        self.clipped += np.count_nonzero((exact < 0) | (exact >= 256), axis=0)
        self.count += v.shape[0]


def _as_rgb8(rgb: np.ndarray, h: int, w: int) -> np.ndarray:
    a = np.asarray(rgb)
    if a.shape != (h, w, 3):
        raise ValueError(f"rgb must have shape {(h, w, 3)}, not {a.shape}")
    if a.dtype == np.uint8:
        return a
    if a.dtype.kind not in "fiu" or not np.all(np.isfinite(a)):
        raise ValueError("rgb must hold finite numbers")
    return _to_byte(a)


def write_ptm(
    path: str | os.PathLike, coefficients: np.ndarray, rgb: np.ndarray | None = None
) -> dict:
    """Write a PTM 1.2 file as HP's PTMfitter does, atomically.

    Parameters
    ----------
    path : str or PathLike
        Destination ``.ptm``.
    coefficients : ndarray
        ``(H, W, 6)`` luminance coefficients (in about 0..255, as RTIViewer expects) with `rgb`
        for ``PTM_FORMAT_LRGB``, or ``(H, W, 3, 6)`` per-channel coefficients (0..255) for
        ``PTM_FORMAT_RGB``. Row 0 at the top.
    rgb : ndarray, shape (H, W, 3), optional
        The LRGB colour block (uint8, or numbers rounded and clipped to 0..255).

    Returns
    -------
    dict
        ``format``, ``width``, ``height``, ``scale`` and ``bias`` (6 each), ``bytes`` (file
        size) and, per coefficient, ``max_error`` and ``rms_error`` (absolute error of the
        decoded coefficients against the input, in coefficient units) and ``clipped`` (values
        that fell outside the byte range; HP's bias rule can push a coefficient's very largest
        values up to two steps past 255 when its minimum is negative).

    Raises
    ------
    ValueError
        If the arrays have the wrong shapes or hold non-finite values.
    InputError
        If the file cannot be written.
    """
    c = _check_coefficients(coefficients)
    h, w = c.shape[:2]
    if c.ndim == 3:
        if rgb is None:
            raise ValueError("an LRGB PTM needs its rgb colour block")
        fmt = FORMAT_LRGB
        rgb8 = _as_rgb8(rgb, h, w)
    else:
        if rgb is not None:
            raise ValueError("an RGB-format PTM has no separate rgb block")
        fmt = FORMAT_RGB
        rgb8 = None
    scale, bias = quantization_parameters(c)
    header = _header(fmt, w, h, scale, bias)
    stats = _ErrorStats()
    per_pixel = 6 if fmt == FORMAT_LRGB else 18
    step = max(1, (1 << 20) // (w * per_pixel))  # bands keep the float64 temporaries small

    def blocks(values: np.ndarray) -> Iterator[bytes]:
        # The file wants the bottom row first: walk bands from the bottom up, flip each.
        for r1 in range(h, 0, -step):
            r0 = max(0, r1 - step)
            band = values[r0:r1]
            codes = _encode(band, scale, bias)
            stats.add(band, codes, scale, bias)
            yield codes[::-1].tobytes()

    with atomic_write(path, "wb") as f:
        f.write(header)
        if fmt == FORMAT_LRGB:
            for chunk in blocks(c):
                f.write(chunk)
            f.write(np.ascontiguousarray(rgb8[::-1]).tobytes())
        else:
            for ch in range(3):
                for chunk in blocks(c[:, :, ch, :]):
                    f.write(chunk)
    rms = np.sqrt(stats.sq / max(1, stats.count))
    return {
        "path": os.fspath(path),
        "format": fmt,
        "width": w,
        "height": h,
        "scale": scale.tolist(),
        "bias": bias.tolist(),
        "bytes": len(header) + h * w * (9 if fmt == FORMAT_LRGB else 18),
        "max_error": stats.max.tolist(),
        "rms_error": rms.tolist(),
        "clipped": stats.clipped.tolist(),
    }


# ---------------------------------------------------------------------------------------------
# Fitting in the photographs' own encoding, as PTMfitter does


def _fit_setup(images: Sequence | np.ndarray, directions: np.ndarray, solver: str) -> tuple[int, np.ndarray]:
    n = len(images)
    # Fewer than six photographs leave the six coefficients underdetermined; the
    # pseudoinverse then gives the minimum-norm fit, and the caller warns about it.
    if n < 1:
        raise InputError("no photographs given")
    pinv = fit_matrix(as_directions(directions, n), solver).astype(np.float32)
    return n, pinv


def fit_ptm_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Fit an LRGB PTM to photographs as HP's PTMfitter does, in their own encoding.

    The photographs' bytes are used as they are (sRGB-encoded, not linearised). Per photograph
    and pixel the luma ``Y = 0.2125 R + 0.7154 G + 0.0721 B`` is normalised to
    ``L = 255 · Y / max_n Y`` (the pixel's brightest photograph has L = 255), the polynomial is
    the pseudoinverse fit of L, and the colour is the least-squares ``rgb`` of
    ``C ≈ rgb · L / 255``, truncated to bytes. Written with :func:`write_ptm` this reproduces
    PTMfitter's file byte for byte on the shared fixture (see the module notes).

    The photographs are streamed: one is decoded (in background threads) and added to running
    per-pixel sums at a time, so memory is 11 float32 per pixel (the six coefficient sums, the
    peak luma, Σ C·Y and Σ Y²) plus a few photographs, however many there are.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs, 8-bit (16-bit values are divided by 257, floats multiplied by 255).
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the light matrix (:func:`ptmcore.fit.fit_matrix`).
    threads : int, optional
        Decoding threads (default: all CPUs).
    progress : callable, optional
        Called with 1 after each photograph.

    Returns
    -------
    coefficients : ndarray, shape (H, W, 6), float32
        Luminance coefficients, L in 0..255 units, row 0 at the top.
    rgb : ndarray, shape (H, W, 3), uint8
        The colour block.

    Raises
    ------
    InputError
        If no photograph is given, one cannot be read, or sizes differ.
    """
    _, pinv = _fit_setup(images, directions, solver)
    wr, wg, wb = (np.float32(x) for x in HP_LUMA_WEIGHTS)
    sums: dict[str, np.ndarray] = {}

    def allocate(shape: tuple[int, int]) -> None:
        # Sums are kept plane by plane: adding into an interleaved (H, W, 6) array makes
        # NumPy loop over the last axis of 6 and runs several times slower.
        sums.update(acc=np.zeros((6,) + shape, np.float32), peak=np.zeros(shape, np.float32),
                    cy=np.zeros((3,) + shape, np.float32), y2=np.zeros(shape, np.float32))

    def add(k: int, c: np.ndarray, r0: int, r1: int) -> None:
        y = c[..., 0] * wr + c[..., 1] * wg + c[..., 2] * wb
        for j in range(6):
            sums["acc"][j, r0:r1] += y * pinv[j, k]
        np.maximum(sums["peak"][r0:r1], y, out=sums["peak"][r0:r1])
        for j in range(3):
            sums["cy"][j, r0:r1] += c[..., j] * y
        sums["y2"][r0:r1] += y * y

    shape = accumulate_photographs(images, allocate, add, threads=threads, progress=progress)
    acc, peak, cy, y2 = sums["acc"], sums["peak"], sums["cy"], sums["y2"]
    coefficients = np.empty(shape + (6,), dtype=np.float32)
    rgb = np.empty(shape + (3,), dtype=np.uint8)
    step = max(1, (1 << 18) // shape[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        for r0 in range(0, shape[0], step):
            band = slice(r0, r0 + step)
            p = peak[band]
            # A pixel black in every photograph keeps L = 0 and colour 0.
            norm = np.where(p > 0, np.float32(255) / p, np.float32(0))[..., None]
            coefficients[band] = np.moveaxis(acc[:, band], 0, -1) * norm
            colour = np.floor(p[..., None] * np.moveaxis(cy[:, band], 0, -1) / y2[band][..., None])
            rgb[band] = np.clip(np.nan_to_num(colour, nan=0.0, posinf=255.0), 0, 255).astype(np.uint8)
    return coefficients, rgb


def fit_ptm_rgb_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Fit an RGB-format PTM (one polynomial per channel) to photographs in their own encoding.

    Each channel's byte values (0..255, not linearised) are fitted by the pseudoinverse, so
    ``PTMFile.render`` of the written file approximates the photographs directly. Streams the
    photographs like :func:`fit_ptm_encoded` (18 float32 per pixel).

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs.
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the light matrix (:func:`ptmcore.fit.fit_matrix`).
    threads : int, optional
        Decoding threads (default: all CPUs).
    progress : callable, optional
        Called with 1 after each photograph.

    Returns
    -------
    ndarray, shape (H, W, 3, 6), float32
        Per-channel coefficients in 0..255 units, row 0 at the top.
    """
    _, pinv = _fit_setup(images, directions, solver)
    return fit_channels(images, pinv, threads=threads, progress=progress)
