"""RTIViewer's ``.rti`` files of hemispherical harmonics (HSH): writing, reading, fitting.

RTIBuilder's HSH fitter writes these files and RTIViewer opens them. Layout::

    #HSH1.2                         comment lines, each starting with '#'
    3                               file type: 3 = HSH (1 would be a PTM in this container)
    W H 3                           width, height, number of colour bands (always 3, RGB)
    K 2 1                           terms (4, 9 or 16 = order²), basis type, element size (1 byte)
    <K float32: scale per term>     binary, little endian (native x86 fwrite)
    <K float32: bias per term>
    <payload: W·H·3·K bytes>

The payload is pixel by pixel, **bottom row first** (like a PTM), left to right; within a pixel
the K bytes of red, then the K of green, then the K of blue. A byte decodes as
``value = byte/255 · scale_k + bias_k``; RTIBuilder takes ``bias_k = min`` and
``scale_k = max − min`` of term k over the whole image and the three bands, and stores
``round((v − min)/(max − min) · 255)``.

RTIViewer shows a pixel under a light as ``tobyte(255 · Σ_k value_k · H_k(θ, φ))`` per band,
with H_k, θ, φ and the θ clamp of :func:`ptmcore.hsh.hsh_basis`; ``tobyte`` takes an ``int``,
so the product is truncated towards zero and then clamped to 0..255. The coefficients are thus
in 0..1 units of the photographs' own (sRGB-encoded) pixel values: :func:`fit_rti_hsh` fits
``byte/255`` of each channel, not linear light.

Sources (read, not copied): cnr-isti-vclab/relight, ``src/legacy_rti.cpp``
(``LRti::loadHSH``: comment lines, type 3, ``W H 3`` and ``terms basis_type size`` as text
lines, then ``terms`` float scales and ``terms`` float biases read with ``fread``, lines of
``W·terms·3`` bytes stored with ``Y = height − 1 − y``, the per-pixel R/G/B term order, and
"in .rti system HSH it's c·scale + bias"; ``LRti::encodeUniversal`` writes the same header with
basis type 2 and element size 1); RTIViewer (Visual Computing Lab ISTI-CNR / Cultural Heritage
Imaging) ``hsh.cpp``: ``Hsh::loadData`` decodes the universal-``.rti`` bytes as
``c/255 · first_array[k] + second_array[k]`` and ``Hsh::createImage`` renders
``tobyte(val·255)`` per band.

Not supported: 16-term (order 4) files, whose basis :mod:`ptmcore.hsh` does not provide; the
reader refuses them with an :class:`~ptmcore.errors.InputError`.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .atomic import atomic_write
from .errors import InputError, read_input_file
from .hsh import ORDERS, hsh_basis
from .ptmencoded import EncodedFit
from .ptmfile import check_coefficient_values, check_memory

if TYPE_CHECKING:
    from .corrections import Corrections

__all__ = [
    "FILE_TYPE_HSH",
    "RTIFile",
    "fit_rti_hsh",
    "read_rti_hsh",
    "render_float",
    "write_rti_hsh",
]

#: The file-type line of an HSH ``.rti``.
FILE_TYPE_HSH = 3
#: The basis-type field RTIBuilder (and relight's ``encodeUniversal``) write for HSH.
BASIS_TYPE = 2
#: Longest header line (type, size, basis) accepted, in bytes.
_MAX_LINE = 256
_INT = re.compile(r"[+-]?[0-9]{1,18}")


# ---------------------------------------------------------------------------------------------
# Rendering


def _render(coefficients: np.ndarray, light: np.ndarray) -> np.ndarray:
    """RTIViewer's 8-bit image of ``(H, W, 3, K)`` coefficients under one light."""
    c = np.asarray(coefficients)
    k = c.shape[-1]
    order = int(round(math.sqrt(k)))
    weights = hsh_basis(np.asarray(light, dtype=np.float64).reshape(1, -1), order)[0]
    h, w = c.shape[:2]
    out = np.empty((h, w, 3), dtype=np.uint8)
    step = max(1, (1 << 18) // max(1, w * 3 * k))
    for r0 in range(0, h, step):
        val = c[r0 : r0 + step].astype(np.float64) @ weights * 255.0
        # tobyte(int): C++ converts the double to int by truncation, then clamps.
        out[r0 : r0 + step] = np.clip(np.trunc(val), 0, 255).astype(np.uint8)
    return out


@dataclass
class RTIFile:
    """A decoded HSH ``.rti`` file.

    Attributes
    ----------
    width, height, order : int
    basis_type : int
        The header's basis-type field (RTIBuilder writes 2; RTIViewer ignores it).
    scale, bias : ndarray, shape (K,), float32
        Per-term decoding ``value = byte/255 · scale + bias``.
    coefficients : ndarray, shape (H, W, 3, K), float32
        Decoded coefficients per RGB band, 0..1 units, row 0 at the top.
    """

    width: int
    height: int
    order: int
    basis_type: int
    scale: np.ndarray
    bias: np.ndarray
    coefficients: np.ndarray

    def render(self, light: np.ndarray) -> np.ndarray:
        """The ``(H, W, 3)`` uint8 image RTIViewer shows under a light (x, y, z) or (lu, lv)."""
        return _render(self.coefficients, light)


def render_float(coefficients: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Exact ``(H, W, 3)`` float64 value ``Σ_k c_k H_k`` (0..1 units) without any rounding."""
    c = np.asarray(coefficients, dtype=np.float64)
    order = int(round(math.sqrt(c.shape[-1])))
    return c @ hsh_basis(np.asarray(light, dtype=np.float64).reshape(1, -1), order)[0]


# ---------------------------------------------------------------------------------------------
# Writing


def _check_coefficients(coefficients: np.ndarray, order: int) -> np.ndarray:
    if order not in ORDERS:
        raise ValueError(f"HSH order must be one of {ORDERS}, got {order!r}")
    c = np.asarray(coefficients)
    k = order * order
    if c.ndim != 4 or c.shape[2:] != (3, k):
        raise ValueError(f"coefficients must have shape (H, W, 3, {k}) for order {order}, not {c.shape}")
    return check_coefficient_values(c)


def quantization_parameters(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTIBuilder's per-term ``scale = max − min`` and ``bias = min`` (float32) over image and bands."""
    c = np.asarray(coefficients)
    k = c.shape[-1]
    flat = c.reshape(-1, k)
    lo = flat.min(axis=0).astype(np.float64)
    hi = flat.max(axis=0).astype(np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("coefficients contain NaN or infinite values")
    if np.any(np.abs(lo) > 1e30) or np.any(np.abs(hi) > 1e30):
        raise ValueError("coefficients are too large for a float32 header")
    bias = lo.astype(np.float32)
    scale = (hi - bias.astype(np.float64)).astype(np.float32)
    # float32 rounding must not leave the maximum above bias + scale.
    scale = np.where(bias.astype(np.float64) + scale < hi, np.nextafter(scale, np.float32(np.inf)), scale)
    return scale.astype(np.float32), bias


def _encode(values: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> np.ndarray:
    s = scale.astype(np.float64)
    b = bias.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = (values.astype(np.float64) - b) / np.where(s > 0, s, 1.0) * 255.0
    q = np.where(s > 0, q, 0.0)
    return np.clip(np.floor(q + 0.5), 0, 255).astype(np.uint8)


def _decode(codes: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> np.ndarray:
    return (codes.astype(np.float32) * np.float32(1 / 255) * scale.astype(np.float32)
            + bias.astype(np.float32))


def _header(width: int, height: int, k: int) -> bytes:
    lines = ["#HSH1.2", str(FILE_TYPE_HSH), f"{width} {height} 3", f"{k} {BASIS_TYPE} 1"]
    return ("\n".join(lines) + "\n").encode("ascii")


def write_rti_hsh(path: str | os.PathLike, coefficients: np.ndarray, *, order: int) -> dict:
    """Write an HSH ``.rti`` file as RTIBuilder does, atomically.

    Parameters
    ----------
    path : str or PathLike
        Destination ``.rti``.
    coefficients : ndarray, shape (H, W, 3, order²)
        Per-band HSH coefficients in 0..1 units (``Σ c_k H_k`` is the pixel value / 255),
        row 0 at the top.
    order : {2, 3}
        HSH order (4 or 9 terms).

    Returns
    -------
    dict
        ``path``, ``width``, ``height``, ``order``, ``scale`` and ``bias`` (per term),
        ``bytes`` (file size), and per term ``max_error`` and ``rms_error`` of the decoded
        coefficients against the input (at most half a step, ``scale/510``).

    Raises
    ------
    ValueError
        If the array has the wrong shape or holds non-finite values.
    InputError
        If the file cannot be written.
    """
    c = _check_coefficients(coefficients, order)
    h, w, _, k = c.shape
    scale, bias = quantization_parameters(c)
    header = _header(w, h, k)
    max_err = np.zeros(k)
    sq = np.zeros(k)
    step = max(1, (1 << 20) // (w * 3 * k))
    with atomic_write(path, "wb") as f:
        f.write(header)
        f.write(scale.astype("<f4").tobytes())
        f.write(bias.astype("<f4").tobytes())
        # Bottom row first: walk bands from the bottom up and flip each.
        for r1 in range(h, 0, -step):
            band = c[max(0, r1 - step) : r1]
            codes = _encode(band, scale, bias)
            err = (_decode(codes, scale, bias).astype(np.float64) - band).reshape(-1, k)
            np.maximum(max_err, np.abs(err).max(axis=0), out=max_err)
            sq += np.einsum("ij,ij->j", err, err)
            f.write(np.ascontiguousarray(codes[::-1]).tobytes())
    return {
        "path": os.fspath(path),
        "width": w,
        "height": h,
        "order": order,
        "scale": scale.tolist(),
        "bias": bias.tolist(),
        "bytes": len(header) + 8 * k + h * w * 3 * k,
        "max_error": max_err.tolist(),
        "rms_error": np.sqrt(sq / (h * w * 3)).tolist(),
    }


# ---------------------------------------------------------------------------------------------
# Reading


def _ints(data: bytes, pos: int, count: int, what: str, path: Path) -> tuple[list[int], int]:
    """Parse one text line of `count` integers starting at `pos`; returns them and the next pos."""
    end = data.find(b"\n", pos, pos + _MAX_LINE)
    if end < 0:
        if len(data) - pos <= _MAX_LINE:
            raise InputError(f"file is truncated in the header (no {what} line)", path)
        raise InputError(f"the {what} line is not a short text line", path)
    try:
        text = data[pos:end].decode("ascii")
    except UnicodeDecodeError:
        raise InputError(f"the {what} line is not text", path) from None
    tokens = text.split()
    if len(tokens) != count or not all(_INT.fullmatch(t) for t in tokens):
        raise InputError(f"the {what} line must hold {count} integer(s), not {text.strip()[:40]!r}", path)
    return [int(t) for t in tokens], end + 1


def read_rti_hsh(path: str | os.PathLike) -> RTIFile:
    """Read an HSH ``.rti`` file (RTIBuilder / RTIViewer layout, see the module notes).

    Raises
    ------
    InputError
        If the file is missing, not an ``.rti``, not of type 3 (HSH), not 3 bands of 1-byte
        elements with 4 or 9 terms, has non-numeric or impossible header fields or non-finite
        scales and biases, or is truncated or longer than its header's size. Sizes are checked
        against the file's length before anything is allocated.
    """
    path = Path(path)
    data = read_input_file(path, "RTI file")
    if not data:
        raise InputError("RTI file is empty", path)
    if data.startswith(b"PTM_"):
        raise InputError("this is a .ptm file, not an HSH .rti", path)
    if not data.startswith(b"#"):
        raise InputError("not an .rti file (it does not start with a '#' comment line)", path)
    pos = 0
    while pos < len(data) and data[pos : pos + 1] == b"#":
        end = data.find(b"\n", pos)
        if end < 0:
            raise InputError("file is truncated in the comment lines", path)
        pos = end + 1
    (rti_type,), pos = _ints(data, pos, 1, "file type", path)
    if rti_type != FILE_TYPE_HSH:
        raise InputError(f"file type {rti_type} is not supported (only 3, HSH)", path)
    (width, height, bands), pos = _ints(data, pos, 3, "width height bands", path)
    if width <= 0 or height <= 0:
        raise InputError(f"image size {width}×{height} is not positive", path)
    if bands != 3:
        raise InputError(f"{bands} colour bands are not supported (only 3)", path)
    (terms, basis_type, element), pos = _ints(data, pos, 3, "terms basis_type element_size", path)
    if element != 1:
        raise InputError(f"element size {element} is not supported (only 1 byte)", path)
    if terms == 16:
        raise InputError("16-term (order 4) HSH files are not supported", path)
    if terms not in (4, 9):
        raise InputError(f"{terms} terms is not an HSH basis (4 or 9)", path)
    order = 2 if terms == 4 else 3
    # Python integers: hostile sizes may not fit in 64 bits.
    need = 8 * terms + width * height * 3 * terms
    have = len(data) - pos
    if have < need:
        raise InputError(
            f"file is truncated: a {width}×{height} HSH of {terms} terms needs {need} bytes "
            f"after the header, {have} are there",
            path,
        )
    if have > need:
        # RTIBuilder writes nothing after the payload: more bytes mean the header's size is not
        # the payload's, and reading it so would scramble the image.
        raise InputError(
            f"the header's size {width}×{height} does not match the payload: {have - need} bytes follow "
            f"the {need} an HSH of that size and {terms} terms has; the file is damaged",
            path,
        )
    check_memory(width * height * 3 * terms * 4, width, height, path)
    scale = np.frombuffer(data, "<f4", terms, pos).astype(np.float32)
    bias = np.frombuffer(data, "<f4", terms, pos + 4 * terms).astype(np.float32)
    if not (np.all(np.isfinite(scale)) and np.all(np.isfinite(bias))):
        raise InputError("the scales and biases are not finite numbers", path)
    if np.any(np.abs(scale) > 1e30) or np.any(np.abs(bias) > 1e30):
        raise InputError("the scales and biases are not plausible", path)
    raw = np.frombuffer(data, np.uint8, width * height * 3 * terms, pos + 8 * terms)
    raw = raw.reshape(height, width, 3, terms)
    coefficients = np.empty((height, width, 3, terms), dtype=np.float32)
    step = max(1, (1 << 20) // (width * 3 * terms))
    for r0 in range(0, height, step):
        r1 = min(height, r0 + step)
        # File row r is image row height − 1 − r.
        coefficients[height - r1 : height - r0] = _decode(raw[r0:r1][::-1], scale, bias)
    return RTIFile(width, height, order, basis_type, scale, bias, coefficients)


# ---------------------------------------------------------------------------------------------
# Fitting


def fit_rti_hsh(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    order: int = 3,
    *,
    encoding: str = "stored",
    linearize: bool = True,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    corrections: Corrections | None = None,
) -> np.ndarray:
    """Fit per-channel HSH coefficients to photographs in their own encoding, as RTIBuilder does.

    Each channel's ``byte/255`` (sRGB-encoded, not linearised; 16-bit values /65535, floats as
    they are) is fitted by the pseudoinverse of the HSH light matrix
    (:func:`ptmcore.hsh.hsh_fit_matrix`), so :meth:`RTIFile.render` of the written file
    approximates the photographs. The photographs are streamed a few at a time into running sums
    (3·order² float32 per pixel; :func:`ptmcore.reduce.reduce_photographs`), so memory does not
    grow with their number. :func:`ptmcore.images.load_stack_and_fits` makes the same fit in the
    pass that decodes the stack.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs.
    directions : ndarray, shape (N, 3)
        Light directions, one per photograph.
    order : {2, 3}
    encoding : {"stored", "srgb", "linear"}
        The values fitted (:class:`ptmcore.ptmencoded.EncodedFit`); "stored" is RTIBuilder's.
    linearize : bool
        8-bit photographs are sRGB (else linear), for ``encoding`` other than "stored".
    threads : int, optional
        Decoding and summing threads (default: all CPUs).
    progress : callable, optional
        Called with 1 after each photograph.
    corrections : Corrections, optional
        Done to each photograph before the fit (:mod:`ptmcore.corrections`).

    Returns
    -------
    ndarray, shape (H, W, 3, order²), float32
        Coefficients in 0..1 units, row 0 at the top.

    Raises
    ------
    InputError
        If no photograph is given, one cannot be read, or sizes differ.
    """
    from .reduce import reduce_photographs  # numba's import costs a second; `import ptmcore` does not need it

    if order not in ORDERS:
        raise ValueError(f"HSH order must be one of {ORDERS}, got {order!r}")
    n = len(images)
    if n < 1:
        raise InputError("no photographs given")
    fit = EncodedFit(directions, None, hsh_order=order, encoding=encoding)
    fit.matrices(n)  # bad directions fail before any photograph is decoded
    return reduce_photographs(images, stack=False, linearize=linearize, fit=fit, threads=threads,
                              progress=progress, corrections=corrections).hsh
