"""Normal maps made elsewhere, read into the project's frame.

Other RTI tools write normal maps as images in the OpenGL mapping (R = x, G = y up, B = z,
value = (n + 1)/2 of full scale): 16- or 8-bit PNG or TIFF, JPEG (the relight tool's
``normals.jpg``), or float arrays. Reading one gives unit normals ``(H, W, 3)`` float32 with
NaN where the map holds no direction (a zero or black background).
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path
from tokenize import TokenError

import numpy as np

from ptmcore.errors import InputError, open_input_file
from ptmcore.images import read_image

#: The first bytes of every ``.npy`` file.
_NPY_MAGIC = b"\x93NUMPY"

#: A normal map smaller than this in either direction gives no surface (a mesh needs a cell).
MIN_SIDE = 2


def read_npy(path: str | os.PathLike, what: str, *, mmap: bool = False) -> np.ndarray:
    """A numeric array from a user's ``.npy`` file, or an :class:`InputError` that says why not.

    The header is checked before any data is read: pickled Python objects are never loaded,
    and a file shorter than its header promises is refused before memory is allocated for it.
    Only a regular file is opened (a FIFO or a device is refused without blocking).

    Parameters
    ----------
    path : str or PathLike
        The ``.npy`` file.
    what : str
        What it holds, for messages ("normal map", "ground-truth normals").
    mmap : bool
        Map the file read-only instead of reading it: nothing is read until the array is
        sliced (a subsample of a large map).

    Returns
    -------
    ndarray
        Of a boolean, integer or floating-point dtype, any shape; a read-only
        :class:`numpy.memmap` with ``mmap`` (a plain array when it holds no values).

    Raises
    ------
    InputError
        If the file is missing or unreadable, not an ``.npy`` file (a text file, an ``.npz``
        archive), has a damaged header, holds Python objects, records or complex numbers,
        or is truncated.
    """
    path = Path(path)
    with open_input_file(path, what) as f:
        if f.read(len(_NPY_MAGIC)) != _NPY_MAGIC:
            raise InputError(f"not a NumPy .npy array file (a {what} saved with numpy.save was expected)", path)
        f.seek(0)
        shape, fortran, dtype = _npy_header(f, path)
        if dtype.hasobject:
            raise InputError(f"holds Python objects, not numbers: a {what} must be an array of numbers "
                             "(objects are not loaded, they could run code)", path)
        if dtype.kind not in "biuf" or dtype.subdtype is not None:
            raise InputError(f"holds {dtype} values; a {what} must be an array of plain numbers", path)
        promised = math.prod(shape) * dtype.itemsize
        held = os.fstat(f.fileno()).st_size - f.tell()
        if held < promised:
            raise InputError(f"is truncated: its header promises a {'×'.join(map(str, shape))} array of "
                             f"{dtype} ({promised:,} bytes) but the file holds {held:,}", path)
        if mmap and promised:
            return np.memmap(f, dtype, "r", f.tell(), shape, "F" if fortran else "C")
        f.seek(0)
        try:
            return np.load(f, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read {what} ({exc})", path) from None


def _npy_header(f, path: Path) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Shape, Fortran order and dtype from an ``.npy`` header, the file left at the data; numpy's
    own checks, reported as input errors."""
    fmt = np.lib.format
    try:
        # numpy parses the header as a Python literal: a damaged one may warn of escapes.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            version = fmt.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(f)
            elif version == (2, 0):
                shape, fortran, dtype = fmt.read_array_header_2_0(f)
            else:  # 3.0 only adds UTF-8 field names, of records this reader refuses anyway
                raise ValueError(f"format version {version[0]}.{version[1]} is not supported")
    except (ValueError, TypeError, SyntaxError, TokenError, EOFError, OverflowError, RecursionError,
            MemoryError) as exc:
        raise InputError(f"not a readable NumPy .npy array file: its header is damaged ({exc})", path) from None
    if any(n < 0 for n in shape):
        raise InputError(f"not a readable NumPy .npy array file: its header gives shape {shape}", path)
    return shape, fortran, dtype


def read_normal_map(path: str | os.PathLike) -> np.ndarray:
    """Read a normal map (``.npy``, or an 8/16-bit or float PNG/TIFF/JPEG in the OpenGL mapping).

    A ``.npy`` map holds floats, ``(H, W, 3)`` x, y, z; NaN or a zero vector marks a pixel
    without a normal. Vectors need not be unit: they are normalised.

    Returns
    -------
    ndarray, shape (H, W, 3), float32
        Unit normals (x right, y up, z towards the camera); NaN where the map has no
        direction (vectors shorter than half a unit after decoding, such as a black
        background, or pointing away from the camera).

    Raises
    ------
    InputError
        If the file is missing, unreadable, not of floats (``.npy``), not three channels,
        smaller than 2×2 pixels, holds infinite values, or has no valid normal.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        raw = read_npy(path, "normal map")
        if raw.dtype.kind != "f":
            raise InputError(f"holds {raw.dtype} values; a .npy normal map must hold floats "
                             "(x, y, z of each pixel's normal)", path)
        _check_layout(raw.shape, path)
        with np.errstate(over="ignore"):
            n = raw.astype(np.float32)
        if np.isinf(n).any():
            raise InputError("the normal map holds infinite (or too large) values; "
                             "NaN marks a pixel without a normal", path)
    else:
        img = read_image(path)
        if img.ndim != 3:
            raise InputError("a normal map needs three channels (R = x, G = y, B = z)", path)
        _check_layout(img.shape, path)
        if img.dtype == np.uint8:
            n = img.astype(np.float32) / np.float32(127.5) - 1
        elif img.dtype == np.uint16:
            n = img.astype(np.float32) / np.float32(32767.5) - 1
        else:
            n = img.astype(np.float32)
            if n.min() >= 0:  # stored as (n + 1)/2 in 0..1
                n = n * 2 - 1
    return _unit_normals(n, path)


def _check_layout(shape: tuple[int, ...], path: Path) -> None:
    if len(shape) != 3 or shape[2] != 3:
        raise InputError(f"a normal map must be H×W×3 (x, y, z of each pixel), got shape {tuple(shape)}", path)
    if min(shape[:2]) < MIN_SIDE:
        raise InputError(f"the normal map is {shape[1]}×{shape[0]} pixels; a surface needs at least "
                         f"{MIN_SIDE}×{MIN_SIDE}", path)


def _unit_normals(n: np.ndarray, path: Path) -> np.ndarray:
    """``n`` (a fresh float32 array, changed in place) normalised; NaN where it is no direction
    towards the camera."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        # Scaled by the largest component first, so that the length of large vectors does not
        # overflow float32.
        big = np.abs(n).max(axis=2, keepdims=True)
        n /= big
        norm = np.linalg.norm(n, axis=2, keepdims=True)
        n /= norm
        bad = ~(big[..., 0] * norm[..., 0] >= 0.5) | ~(n[..., 2] > 0)  # NaN compares False: bad
    n[bad] = np.nan
    if bad.all():
        raise InputError("the normal map holds no valid normal (every pixel is NaN, (nearly) zero, "
                         "or points away from the camera)", path)
    return n


def shaded(
    normals: np.ndarray, light: tuple[float, float, float] = (-0.4, 0.4, 0.82)
) -> np.ndarray:
    """A grey rendering ``max(0, n·l)`` as 8-bit RGB, for a texture when no colour is known.

    The default light comes from the upper left, as cartographers and most viewers shade
    reliefs, so that bumps read as bumps.
    """
    lt = np.asarray(light, dtype=np.float32)
    lt /= np.linalg.norm(lt)
    s = np.clip(np.nan_to_num(normals @ lt, nan=0.0), 0.0, 1.0)
    grey = np.round(s * 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)
