"""Writing the raster outputs of a run: normal maps, albedo, height, mask, report.

Every file is written through :func:`reconstruct.atomic.atomic_write`, so it appears whole or
not at all.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ptmcore.errors import InputError
from ptmcore.images import linear_to_srgb

from .atomic import atomic_write


def _png_bytes(image: np.ndarray, path: str | os.PathLike) -> bytes:
    import cv2

    img = image[..., ::-1] if image.ndim == 3 else image  # OpenCV stores BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise InputError("could not encode PNG", path)
    return buf.tobytes()


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an 8- or 16-bit grey or RGB image ``(H, W[, 3])`` as PNG."""
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError("PNG images must be uint8 or uint16")
    data = _png_bytes(image, path)
    with atomic_write(path, "wb") as f:
        f.write(data)


def normals_to_rgb16(normals: np.ndarray) -> np.ndarray:
    """Encode unit normals as a 16-bit OpenGL-style normal map (R=x, G=y, B=z; y up)."""
    n = np.nan_to_num(normals, nan=0.0)
    return np.round((np.clip(n, -1.0, 1.0) + 1.0) * (65535 / 2)).astype(np.uint16)


def albedo_to_srgb8(albedo_rgb: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear RGB albedo to displayable 8-bit sRGB.

    Albedo from photographs is reflectance times an unknown light intensity, so it can exceed 1.
    It is divided by its 99.9th percentile when that is above 1, so highlights of the brightest
    surfaces are not all clipped.

    Returns
    -------
    image : ndarray, shape (H, W, 3), uint8
    scale : float
        The divisor applied (1 when none).
    """
    finite = albedo_rgb[np.isfinite(albedo_rgb)]
    top = float(np.percentile(finite, 99.9)) if finite.size else 1.0
    scale = top if top > 1.0 else 1.0
    enc = linear_to_srgb(np.nan_to_num(albedo_rgb, nan=0.0) / np.float32(scale))
    return np.round(enc * 255).astype(np.uint8), scale


def write_height_tiff(path: str | os.PathLike, height: np.ndarray, unit: str, pixel_size: float | None) -> None:
    """Write a float32 TIFF height map; NaN outside the mask; unit in the image description."""
    import tifffile

    import io

    meta = {"unit": unit, "pixel_size_mm": pixel_size, "frame": "x right, y up, z towards camera"}
    buf = io.BytesIO()  # tifffile wants a named file; atomic_write's handle has none
    tifffile.imwrite(buf, height.astype(np.float32, copy=False), metadata=meta)
    with atomic_write(path, "wb") as f:
        f.write(buf.getbuffer())


def write_json(path: str | os.PathLike, data: dict) -> None:
    """Write a JSON document (indented, UTF-8)."""
    with atomic_write(path, "w") as f:
        json.dump(data, f, indent=2, ensure_ascii=False, allow_nan=False)
        f.write("\n")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write a ``.npy`` array."""
    with atomic_write(path, "wb") as f:
        np.save(f, array, allow_pickle=False)
