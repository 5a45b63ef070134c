"""Image encodings of linear radiance, as a camera would store them."""

from __future__ import annotations

import os

import numpy as np
import tifffile
from PIL import Image

from ptmcore.atomic import atomic_write
from ptmcore.images import linear_to_srgb


def to_uint16_linear(radiance: np.ndarray) -> np.ndarray:
    """Clip radiance to [0, 1] and quantise linearly to 16 bits.

    Parameters
    ----------
    radiance : np.ndarray
        Linear radiance, any shape.

    Returns
    -------
    np.ndarray
        uint16, ``round(v · 65535)``.
    """
    return np.round(np.clip(radiance, 0.0, 1.0) * 65535.0).astype(np.uint16)


def to_uint8_srgb(radiance: np.ndarray) -> np.ndarray:
    """Clip radiance to [0, 1], apply the sRGB curve and quantise to 8 bits.

    Parameters
    ----------
    radiance : np.ndarray
        Linear radiance, any shape.

    Returns
    -------
    np.ndarray
        uint8, ``round(srgb(v) · 255)``.
    """
    return np.round(linear_to_srgb(np.clip(radiance, 0.0, 1.0)) * 255.0).astype(np.uint8)


def write_tiff16(path: str | os.PathLike, radiance: np.ndarray) -> None:
    """Write (H, W, 3) linear radiance as an uncompressed 16-bit linear RGB TIFF.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    radiance : np.ndarray
        (H, W, 3) linear radiance; clipped to [0, 1].
    """
    with atomic_write(path) as fh:
        # No shape metadata or timestamps, so identical images give identical files.
        tifffile.imwrite(fh, to_uint16_linear(radiance), photometric="rgb", metadata=None)


def write_jpeg8(path: str | os.PathLike, radiance: np.ndarray, quality: int = 95) -> None:
    """Write (H, W, 3) linear radiance as an 8-bit sRGB JPEG (4:4:4, no chroma subsampling).

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    radiance : np.ndarray
        (H, W, 3) linear radiance; clipped to [0, 1] before the sRGB curve.
    quality : int
        JPEG quality, 1–100.
    """
    image = Image.fromarray(to_uint8_srgb(radiance))
    with atomic_write(path) as fh:
        image.save(fh, format="JPEG", quality=quality, subsampling=0)


def write_png8(path: str | os.PathLike, radiance: np.ndarray) -> None:
    """Write linear radiance as an 8-bit sRGB PNG, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    radiance : np.ndarray
        (H, W, 3) linear radiance; clipped to [0, 1] before the sRGB curve.
    """
    image = Image.fromarray(to_uint8_srgb(radiance))
    with atomic_write(path) as fh:
        image.save(fh, format="PNG")


def write_mask_png(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Write a boolean mask as an 8-bit greyscale PNG, 255 on the object.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    mask : np.ndarray
        (H, W) bool.
    """
    image = Image.fromarray(np.where(mask, 255, 0).astype(np.uint8))
    with atomic_write(path) as fh:
        image.save(fh, format="PNG")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write an array as ``.npy`` atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    array : np.ndarray
        The data.
    """
    with atomic_write(path) as fh:
        np.save(fh, array, allow_pickle=False)
