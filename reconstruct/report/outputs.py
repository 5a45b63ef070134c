"""Writing the raster outputs of a run: normal maps, albedo, height, mask, report.

Every file is written through :func:`ptmcore.atomic.atomic_write`, so it appears whole or not
at all. Large PNGs are encoded by :func:`write_png`, bands of rows in parallel threads.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from ptmcore.images import linear_to_srgb

from ptmcore.atomic import atomic_write

# Bytes of image data per band that one thread filters and compresses: a few hundred rows of a
# 24-megapixel image, small enough to spread over the threads and to bound the memory.
_PNG_BAND_BYTES = 4 << 20
# Threads for PNG encoding (zlib and NumPy leave the GIL), and bands compressed ahead of the
# one being written.
_PNG_WORKERS = min(4, os.cpu_count() or 1)
_PNG_AHEAD = 2 * _PNG_WORKERS
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_ADLER_BASE = 65521


def normals_to_rgb16(normals: np.ndarray) -> np.ndarray:
    """Encode unit normals as a 16-bit OpenGL-style normal map (R=x, G=y, B=z; y up).

    Value = round((n + 1) · 65535 / 2), clipped; NaN becomes 0.
    """
    import cv2

    # One saturating, rounding pass in OpenCV; NumPy needs five passes over the image.
    n = np.ascontiguousarray(normals, dtype=np.float32)
    return cv2.addWeighted(n, 65535 / 2, n, 0.0, 65535 / 2, dtype=cv2.CV_16U)


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
    import cv2

    # A subsample estimates the percentile as well as all 70 million values of a 24-megapixel
    # image would, in a fraction of the time.
    flat = albedo_rgb.reshape(-1)
    sample = flat[:: max(1, flat.size // 1_000_000)]
    sample = sample[np.isfinite(sample)]
    top = float(np.percentile(sample, 99.9)) if sample.size else 1.0
    scale = top if top > 1.0 else 1.0
    # Quantise to 16 bits, then encode through a 65536-entry table: the sRGB curve costs a
    # power function per value otherwise. The step (1/65535) is below 0.06 of an 8-bit level.
    a = np.ascontiguousarray(albedo_rgb, dtype=np.float32)
    index = cv2.addWeighted(a, 65535.0 / scale, a, 0.0, 0.0, dtype=cv2.CV_16U)
    table = np.round(linear_to_srgb(np.arange(65536, dtype=np.float64) / 65535.0) * 255).astype(np.uint8)
    return table[index], scale


def _png_chunk(kind: bytes, data: bytes | memoryview) -> list[bytes | memoryview]:
    """A PNG chunk as its pieces: length and type, data, CRC of type and data."""
    return [struct.pack(">I", len(data)) + kind, data, struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))]


def _adler32_combine(adler1: int, adler2: int, length2: int) -> int:
    """The Adler-32 of two pieces of data from theirs (zlib's ``adler32_combine``); ``length2``
    is the length of the second."""
    rem = length2 % _ADLER_BASE
    sum1 = ((adler1 & 0xFFFF) + (adler2 & 0xFFFF) - 1) % _ADLER_BASE
    sum2 = (rem * (adler1 & 0xFFFF) + (adler1 >> 16) + (adler2 >> 16) - rem) % _ADLER_BASE
    return sum1 | (sum2 << 16)


def _png_band(rows: np.ndarray, level: int, last: bool) -> tuple[list[bytes | memoryview], int, int]:
    """Filter and deflate one band of rows ``(n, W[, C])`` (run in a worker thread).

    Returns the band's IDAT chunk pieces, the Adler-32 of its filtered bytes and their count.
    Filter "sub" (each byte minus the same byte of the pixel to its left) when compressing,
    which turns smooth gradients and flat areas into runs of small values; "none" when
    storing. Each band is an independent raw deflate stream ended by a sync flush (a byte
    boundary, as pigz does), so the bands concatenate into one zlib stream.
    """
    n = rows.shape[0]
    # PNG stores 16-bit samples big-endian.
    raw = (rows.astype(">u2") if rows.dtype == np.uint16 else np.ascontiguousarray(rows)).view(np.uint8)
    raw = raw.reshape(n, -1)
    bpp = rows.itemsize * (rows.shape[2] if rows.ndim == 3 else 1)
    filtered = np.empty((n, raw.shape[1] + 1), np.uint8)
    if level:
        filtered[:, 0] = 1
        filtered[:, 1 : 1 + bpp] = raw[:, :bpp]
        np.subtract(raw[:, bpp:], raw[:, :-bpp], out=filtered[:, 1 + bpp :])  # wraps mod 256
    else:
        filtered[:, 0] = 0
        filtered[:, 1:] = raw
    data = memoryview(filtered).cast("B")
    # Z_RLE: matches at distance 1 only; no larger than the default strategy on photographs
    # and normal maps (their pixels rarely repeat further away), and twice as fast.
    deflate = zlib.compressobj(level, zlib.DEFLATED, -15, 9, zlib.Z_RLE)
    packed = deflate.compress(data) + deflate.flush(zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH)
    return _png_chunk(b"IDAT", packed), zlib.adler32(data), len(data)


def write_png(path: str | os.PathLike, image: np.ndarray, *, compress: bool = True) -> None:
    """Write an 8- or 16-bit grey or RGB image ``(H, W[, 3])`` as PNG, bands in parallel.

    A plain PNG that every reader opens (one zlib stream over several IDAT chunks). It is
    written without OpenCV's encoder, which works row by row in one thread and takes more than
    a second for a 24-megapixel 16-bit image even uncompressed: here bands of rows are filtered
    with NumPy and deflated by zlib in parallel threads (pigz's way), both of which leave the
    GIL. At 24 megapixels: 8-bit RGB 0.4 s on two free cores (OpenCV 0.75 s), the same size;
    16-bit RGB stored 0.3 s (OpenCV 2 s at its default compression).

    Parameters
    ----------
    path : path
        The file to write.
    image : ndarray, shape (H, W) or (H, W, 3), uint8 or uint16
    compress : bool
        Deflate with zlib's fastest level and run-length matching (as small as OpenCV's
        default on photographs). False stores the data uncompressed: valid and fastest, for
        data that hardly compresses (a 16-bit normal map's low bytes are noise: compression
        saves a quarter of the size for about six times the time).
    """
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"PNG images must be uint8 or uint16, not {image.dtype}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3) or 0 in image.shape:
        raise ValueError(f"PNG images must be (H, W) or (H, W, 3), not {image.shape}")
    h, w = image.shape[:2]
    colour = 2 if image.ndim == 3 else 0
    header = struct.pack(">IIBBBBB", w, h, 8 * image.itemsize, colour, 0, 0, 0)
    band = max(1, _PNG_BAND_BYTES // (image[0].nbytes + 1))
    level = 1 if compress else 0
    with atomic_write(path, "wb") as f, ThreadPoolExecutor(max_workers=_PNG_WORKERS) as pool:
        f.write(_PNG_SIGNATURE)
        f.writelines(_png_chunk(b"IHDR", header))
        f.writelines(_png_chunk(b"IDAT", b"\x78\x01"))  # zlib header: deflate, 32 KiB window
        adler, pending = 1, deque[Future]()

        def write_next() -> None:
            nonlocal adler
            pieces, band_adler, length = pending.popleft().result()
            f.writelines(pieces)
            adler = _adler32_combine(adler, band_adler, length)

        try:
            for r0 in range(0, h, band):
                if len(pending) == _PNG_AHEAD:
                    write_next()
                pending.append(pool.submit(_png_band, image[r0 : r0 + band], level, r0 + band >= h))
            while pending:
                write_next()
        except BaseException:
            for future in pending:
                future.cancel()
            raise
        f.writelines(_png_chunk(b"IDAT", struct.pack(">I", adler)))
        f.writelines(_png_chunk(b"IEND", b""))


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
