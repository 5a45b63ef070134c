"""Writing the raster outputs of a run: normal maps, albedo, height, mask, report.

Every file is written through :func:`ptmcore.atomic.atomic_write`, so it appears whole or not
at all. PNGs are written by :func:`ptmcore.png.write_png`, bands of rows in parallel threads.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.bands import band_rows, run_bands
from ptmcore.images import linear_to_srgb
from ptmcore.png import write_png


def normals_to_rgb16(normals: np.ndarray) -> np.ndarray:
    """Encode unit normals as a 16-bit OpenGL-style normal map (R=x, G=y, B=z; y up).

    Value = round((n + 1) · 65535 / 2), clipped; NaN becomes 0.
    """
    import cv2

    # One saturating, rounding pass in OpenCV; NumPy needs five passes over the image.
    n = np.ascontiguousarray(normals, dtype=np.float32)
    return cv2.addWeighted(n, 65535 / 2, n, 0.0, 65535 / 2, dtype=cv2.CV_16U)


def albedo_to_srgb8(albedo_rgb: np.ndarray, *, threads: int | None = None) -> tuple[np.ndarray, float]:
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
    flat = albedo_rgb.reshape(-1)
    scale = _albedo_scale(flat[:: _sample_step(flat.size)])
    return _encode_bands(lambda rows: albedo_rgb[rows], albedo_rgb.shape, scale, threads), scale


def albedo_texture(chroma: np.ndarray, albedo: np.ndarray, *,
                   threads: int | None = None) -> tuple[np.ndarray, float]:
    """The colour albedo ``chroma · albedo`` as 8-bit sRGB: :func:`albedo_to_srgb8` of the
    product, the same bytes, without its full-size float32 image (0.3 GB at 24 megapixels).

    Parameters
    ----------
    chroma : ndarray, shape (H, W, 3), float32
        Colour of unit luminance (:attr:`ptmcore.images.ImageStack.chroma`).
    albedo : ndarray, shape (H, W), float32
        Luminance albedo.
    threads : int, optional
        Bands of rows encoded in parallel; default: the number of CPUs.
    """
    size = chroma.size
    # The values albedo_to_srgb8 samples from the product, picked from its two factors.
    index = np.arange(0, size, _sample_step(size))
    sample = chroma.reshape(-1)[index] * albedo.reshape(-1)[index // 3]
    scale = _albedo_scale(sample)
    return _encode_bands(lambda rows: chroma[rows] * albedo[rows][..., None], chroma.shape, scale, threads), scale


def _sample_step(size: int) -> int:
    # A subsample estimates the percentile as well as all 70 million values of a 24-megapixel
    # image would, in a fraction of the time.
    return max(1, size // 1_000_000)


def _albedo_scale(sample: np.ndarray) -> float:
    sample = sample[np.isfinite(sample)]
    top = float(np.percentile(sample, 99.9)) if sample.size else 1.0
    return top if top > 1.0 else 1.0


def _encode_bands(values, shape: tuple[int, ...], scale: float, threads: int | None) -> np.ndarray:
    """8-bit sRGB of ``values(rows)``, linear, divided by ``scale``; bands in threads."""
    import cv2

    # Quantise to 16 bits, then encode through a 65536-entry table: the sRGB curve costs a
    # power function per value otherwise. The step (1/65535) is below 0.06 of an 8-bit level.
    table = np.round(linear_to_srgb(np.arange(65536, dtype=np.float64) / 65535.0) * 255).astype(np.uint8)
    out = np.empty(shape, np.uint8)

    def band(r0: int, r1: int) -> None:
        a = np.ascontiguousarray(values(slice(r0, r1)), dtype=np.float32)
        index = cv2.addWeighted(a, 65535.0 / scale, a, 0.0, 0.0, dtype=cv2.CV_16U)
        np.take(table, index, out=out[r0:r1])

    run_bands(shape[0], band_rows(1, shape[1] * shape[2]), band, threads=threads)
    return out


def write_normals_png(path: str | os.PathLike, normals: np.ndarray, *, compress: bool = False) -> None:
    """Write unit normals as the 16-bit normal map ``normals.png`` (:func:`normals_to_rgb16`).

    Stored uncompressed by default (:func:`write_png`): a third larger than with zlib's
    fastest level (144 MB instead of 109 MB at 24 megapixels), in a sixth of the time.
    """
    write_png(path, normals_to_rgb16(normals), compress=compress)


def write_height_tiff(path: str | os.PathLike, height: np.ndarray, unit: str, pixel_size: float | None) -> None:
    """Write a float32 TIFF height map; NaN outside the mask; unit in the image description."""
    import tifffile

    meta = {"unit": unit, "pixel_size_mm": pixel_size, "frame": "x right, y up, z towards camera"}
    with atomic_write(path, "wb") as f:
        tifffile.imwrite(f, height.astype(np.float32, copy=False), metadata=meta)


def write_json(path: str | os.PathLike, data: dict) -> None:
    """Write a JSON document (indented, UTF-8)."""
    with atomic_write(path, "w") as f:
        json.dump(data, f, indent=2, ensure_ascii=False, allow_nan=False)
        f.write("\n")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write a ``.npy`` array."""
    with atomic_write(path, "wb") as f:
        np.save(f, array, allow_pickle=False)
