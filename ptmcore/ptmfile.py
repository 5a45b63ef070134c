"""HP Polynomial Texture Map (``.ptm``) files: reading and writing, with HP's quantisation.

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
* ``PTM_FORMAT_JPEG_LRGB`` / ``PTM_FORMAT_JPEG_RGB``: the same planes, each compressed as a
  grayscale JPEG, with a table of the planes after the bias line (read only; see
  :mod:`ptmcore.ptmjpeg`).

HP's quantisation (reproduces PTMfitter's header on the shared fixture): per coefficient over the
whole image (and over the three channels for the RGB format), with ``max − min = m · 2^e``
(``frexp``), ``scale = 2^(e − 8)``; if ``min < 0``, ``bias = int(−min/scale + 1)``, doubling the
scale while ``bias > 255``; otherwise ``bias = 0`` and the scale doubles while
``max/scale > 255``. A value is stored as ``floor(v/scale + bias + 0.5)`` clamped to 0..255.
:func:`write_ptm` quantises in compiled kernels (:mod:`ptmcore.quantize`) with the float64
arithmetic of :func:`quantize`, so their bytes are the same.

PTMfitter's own fit of the photographs, which :func:`write_ptm` turns into its file byte for
byte, is :func:`ptmcore.ptmencoded.fit_ptm_encoded`.
"""

from __future__ import annotations

import math
import mmap
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .errors import InputError, open_input_file
from .fit import light_matrix
from .ptmheader import HeaderCursor
from .ptmjpeg import read_jpeg_planes

__all__ = [
    "FORMAT_JPEG_LRGB",
    "FORMAT_JPEG_RGB",
    "FORMAT_LRGB",
    "FORMAT_RGB",
    "PTMFile",
    "check_coefficient_values",
    "check_memory",
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
    warnings : list of str
        What the reader found that makes the PTM of little use (one line each, naming the
        file): light-dependent coefficients the same at every pixel, an all-black colour block.
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
    warnings: list[str] = field(default_factory=list)

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


def _map_file(path: Path) -> bytes | mmap.mmap:
    """The file mapped read-only (only the pages read are loaded), or its bytes when it cannot
    be mapped (an empty file); only a regular file is opened (:func:`open_input_file`)."""
    with open_input_file(path, "PTM file") as f:
        try:
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # ValueError: an empty file cannot be mapped
            return f.read()


def _sample(raw: np.ndarray) -> np.ndarray:
    """About 64×64 pixels of ``(..., H, W, k)`` bytes, a strided view."""
    h, w = raw.shape[-3:-1]
    return raw[..., :: max(1, h // 64), :: max(1, w // 64), :]


def _spread(raw: np.ndarray) -> np.ndarray:
    """Whether each of the last axis's planes of ``raw`` holds more than one value: ``(k,)`` bool."""
    axes = tuple(range(raw.ndim - 1))
    return raw.min(axis=axes) != raw.max(axis=axes)


def _information(coef: np.ndarray, rgb: np.ndarray | None, scale: np.ndarray, path: Path) -> list[str]:
    """Refuse a payload that holds no image; the warnings of one that holds little.

    A PTM whose pixels all have the same polynomial (an all-zero or constant payload, or scales
    of 0: a coefficient with scale 0 decodes to 0 everywhere) relights as one flat colour: that
    is a damaged file, not an image. Light-dependent coefficients (a0–a4) the same at every
    pixel give one normal everywhere, and an all-black colour block relights as black: those
    are warned of. A sample of the pixels settles a real image at once; the whole payload is
    read only when the sample cannot tell.

    Parameters
    ----------
    coef : ndarray, shape (..., H, W, 6), uint8
        The coefficient bytes, whole (not a subsample).
    rgb : ndarray, shape (H, W, 3), uint8, or None
        The colour block of the LRGB formats.
    scale : ndarray, shape (6,)
    path : Path
        The file, for the messages.

    Returns
    -------
    list of str
        Warnings, one line each, naming the file.
    """
    if coef.shape[-3] * coef.shape[-2] < 2:
        return []
    useful = scale != 0
    varies = _spread(_sample(coef)) & useful
    if not varies[:5].any():
        varies = _spread(coef) & useful
    if not varies.any():
        raise InputError("every pixel holds the same polynomial (an all-zero or constant payload, or scales "
                         "of 0): the PTM holds no image; the file is damaged", path)
    found = []
    if not varies[:5].any():
        found.append("the light-dependent coefficients (a0–a4) are the same at every pixel: its normals point "
                     "one way everywhere")
    if rgb is not None and not _sample(rgb).any() and not rgb.any():
        found.append("the colour block is black at every pixel: it relights as black")
    # Each as an error's line would be: the file's name first, its control characters escaped.
    return [str(InputError(problem, path)) for problem in found]


#: Reads that allocate more than this ask how much memory is left first (smaller ones always fit
#: beside a run's own bound), as a photograph's decoding does (:mod:`ptmcore.decoders`).
ASK_MEMORY_BYTES = 256 << 20


def check_memory(nbytes: int, width: int, height: int, path: Path) -> None:
    """Refuse, before allocating, a read of ``nbytes`` that the memory left cannot hold.

    Shared with :mod:`ptmcore.rtifile`.

    Raises
    ------
    InputError
        If ``nbytes`` is more than :func:`ptmcore.resources.available_memory_mb`.
    """
    if nbytes <= ASK_MEMORY_BYTES:
        return
    from .resources import available_memory_mb

    free = available_memory_mb()
    if nbytes > free * 2**20:
        raise InputError(f"reading its {width}×{height} pixels takes {nbytes / 2**20:,.0f} MiB, more than the "
                         f"{free:,.0f} MiB of memory available", path)


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
        truncated or longer than its header's size (a raw format), holds a JPEG plane that
        cannot be decoded, or holds no image (every pixel the same polynomial: an all-zero or
        constant payload). Sizes are checked against the file's length before anything is
        allocated. What makes a PTM of little use is in :attr:`PTMFile.warnings`.
    """
    path = Path(path)
    if max_side is not None and max_side < 1:
        raise ValueError(f"max_side must be at least 1, not {max_side}")
    data = _map_file(path)
    if not data:
        raise InputError("PTM file is empty", path)
    cur = HeaderCursor(data, path)
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
    if not np.any(scale):  # said from the header, before a payload is read
        raise InputError("all six scales are 0: every coefficient would be 0 (a black image); the file is damaged", path)
    bias_tokens = cur.floats(6, "biases")
    if any(not math.isfinite(b) or b != int(b) for b in bias_tokens):
        raise InputError(f"biases must be integers, got {bias_tokens}", path)
    if any(abs(b) > 1 << 20 for b in bias_tokens):
        raise InputError(f"biases {bias_tokens} are not plausible", path)
    bias = np.array([int(b) for b in bias_tokens], dtype=np.int64)

    npix = width * height
    stride = 1 if max_side is None else max(1, math.ceil(max(width, height) / max_side))
    # The decoded arrays: float32 coefficients (three sets for the RGB formats) and the colours
    # of the subsample; a JPEG PTM's planes are decoded whole first, one more for the plane in hand.
    rgb_formats = fmt in (FORMAT_RGB, FORMAT_JPEG_RGB)
    decoded = math.ceil(height / stride) * math.ceil(width / stride) * (72 if rgb_formats else 27)
    quality = None
    if fmt in _JPEG_PLANES:
        check_memory(decoded + (_JPEG_PLANES[fmt] + 1) * npix, width, height, path)
        planes, quality = read_jpeg_planes(cur, _JPEG_PLANES[fmt], width, height)
        if fmt == FORMAT_JPEG_LRGB:
            found = _information(np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:9], 0, -1), scale, path)
        else:
            found = _information(np.moveaxis(planes.reshape(3, 6, height, width), 1, -1), None, scale, path)
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
        if have > need:
            # HP's PTMfitter writes nothing after the payload: more bytes mean the header's size
            # is not the payload's, and reading it so would scramble the image.
            raise InputError(
                f"the header's size {width}×{height} does not match the payload: {have - need} bytes "
                f"follow the {need} a {width}×{height} {fmt} has; the file is damaged",
                path,
            )
        check_memory(decoded, width, height, path)
        if fmt == FORMAT_RGB:
            raw = np.frombuffer(data, np.uint8, need, start).reshape(3, height, width, 6)
            found = _information(raw, None, scale, path)
            channels = [_every(raw[c], stride) for c in range(3)]
            coefficients = np.empty(channels[0].shape[:2] + (3, 6), dtype=np.float32)
            for c in range(3):
                _decode_block(channels[c], scale, bias, coefficients[:, :, c])
            rgb = None
        elif version in _INTERLEAVED_VERSIONS:
            raw = np.frombuffer(data, np.uint8, need, start).reshape(height, width, 9)
            found = _information(raw[..., :6], raw[..., 6:], scale, path)
            raw = _every(raw, stride)
            coefficients = _decode_block(raw[..., :6], scale, bias)
            rgb = np.ascontiguousarray(raw[::-1, :, 6:])
        else:
            coef_raw = np.frombuffer(data, np.uint8, 6 * npix, start).reshape(height, width, 6)
            rgb_raw = np.frombuffer(data, np.uint8, 3 * npix, start + 6 * npix).reshape(height, width, 3)
            found = _information(coef_raw, rgb_raw, scale, path)
            coefficients = _decode_block(_every(coef_raw, stride), scale, bias)
            rgb = np.ascontiguousarray(_every(rgb_raw, stride)[::-1])
    return PTMFile(fmt, version, width, height, scale, bias, coefficients, rgb, quality, found)


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


def check_coefficient_values(c: np.ndarray) -> np.ndarray:
    """Refuse per-pixel coefficients, already of their format's shape, that cannot be written.

    Shared with :mod:`ptmcore.rtifile` so that both writers refuse alike.

    Parameters
    ----------
    c : ndarray, shape (H, W, ...)
        The coefficients, rows and columns first.

    Returns
    -------
    ndarray
        ``c`` itself.

    Raises
    ------
    ValueError
        If ``c`` has no pixels, or its values are not numbers.
    """
    if c.shape[0] < 1 or c.shape[1] < 1:
        raise ValueError(f"coefficients of shape {c.shape} hold no pixels")
    if c.dtype.kind not in "fiu":
        raise ValueError(f"coefficients must be numbers, not {c.dtype}")
    return c


def _check_coefficients(coefficients: np.ndarray) -> np.ndarray:
    c = np.asarray(coefficients)
    if not ((c.ndim == 3 and c.shape[2] == 6) or (c.ndim == 4 and c.shape[2:] == (3, 6))):
        raise ValueError(f"coefficients must be (H, W, 6) or (H, W, 3, 6), not {c.shape}")
    return check_coefficient_values(c)


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
    from .quantize import coefficient_range  # numba's import costs half a second; `import ptmcore` does not need it

    c = _check_coefficients(coefficients)
    lo, hi = coefficient_range(c)  # one compiled pass over the values, in threads
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
    from .quantize import encode_ptm  # numba's import costs half a second; `import ptmcore` does not need it

    scale, bias = quantization_parameters(c)
    header = _header(fmt, w, h, scale, bias)
    with atomic_write(path, "wb") as f:
        f.write(header)
        # Bands are encoded in threads (HP's arithmetic and the error statistics in one compiled
        # pass) while the bands before them are written, in the file's order.
        worst, sq, clipped = encode_ptm(c, scale, bias, f.write)
        if rgb8 is not None:
            # Bottom row first, a few megabytes at a time rather than one flipped copy of it all.
            step = max(1, (4 << 20) // (w * 3))
            for r1 in range(h, 0, -step):
                f.write(np.ascontiguousarray(rgb8[max(0, r1 - step) : r1][::-1]))
    # Every value of every channel counts once per coefficient.
    count = h * w * (1 if fmt == FORMAT_LRGB else 3)
    rms = np.sqrt(sq / count)
    return {
        "path": os.fspath(path),
        "format": fmt,
        "width": w,
        "height": h,
        "scale": scale.tolist(),
        "bias": bias.tolist(),
        "bytes": len(header) + h * w * (9 if fmt == FORMAT_LRGB else 18),
        "max_error": worst.tolist(),
        "rms_error": rms.tolist(),
        "clipped": clipped.astype(np.int64).tolist(),
    }
