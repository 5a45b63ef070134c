"""Normal maps made elsewhere, read into the project's frame.

Other RTI tools write normal maps as images in the OpenGL mapping (R = x, G = y up, B = z,
value = (n + 1)/2 of full scale): 16- or 8-bit PNG or TIFF, JPEG (the relight tool's
``normals.jpg``), or float arrays. Reading one gives unit normals ``(H, W, 3)`` float32 with
NaN where the map holds no direction (a zero or black background).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError
from ptmcore.images import read_image


def read_normal_map(path: str | os.PathLike) -> np.ndarray:
    """Read a normal map (``.npy``, or an 8/16-bit or float PNG/TIFF/JPEG in the OpenGL mapping).

    Returns
    -------
    ndarray, shape (H, W, 3), float32
        Unit normals (x right, y up, z towards the camera); NaN where the map has no
        direction (vectors shorter than half a unit after decoding, such as a black
        background, or pointing away from the camera).

    Raises
    ------
    InputError
        If the file is missing, unreadable, not three channels, or has no valid normal.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            n = np.load(path, allow_pickle=False).astype(np.float32)
        except FileNotFoundError:
            raise InputError("normal map not found", path) from None
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read normal map ({exc})", path) from None
    else:
        img = read_image(path)
        if img.ndim != 3:
            raise InputError("a normal map needs three channels (R = x, G = y, B = z)", path)
        if img.dtype == np.uint8:
            n = img.astype(np.float32) / np.float32(127.5) - 1
        elif img.dtype == np.uint16:
            n = img.astype(np.float32) / np.float32(32767.5) - 1
        else:
            n = img.astype(np.float32)
            if n.min() >= 0:  # stored as (n + 1)/2 in 0..1
                n = n * 2 - 1
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"a normal map must be H×W×3, got {n.shape}", path)
    length = np.linalg.norm(n, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = n / length
    bad = (length[..., 0] < 0.5) | ~np.isfinite(length[..., 0]) | (unit[..., 2] <= 0)
    unit[bad] = np.nan
    if bad.all():
        raise InputError("the normal map holds no valid normal", path)
    return unit.astype(np.float32)


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
