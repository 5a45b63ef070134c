"""The JPEG-compressed PTM formats, ``PTM_FORMAT_JPEG_LRGB`` and ``PTM_FORMAT_JPEG_RGB`` (read only).

Layout (see :mod:`ptmcore.ptmfile` for the rest of the header): after the bias line, a line
with the JPEG quality, then seven lines of one integer per plane (9 planes for LRGB: a0..a5, R,
G, B; 18 for RGB: a0..a5 of R, then of G, then of B, the order of the uncompressed blocks and of
Perathoner's ptmlib; no file from HP's own JPEG-RGB writer was at hand to confirm it):
transform, motion vector x, motion vector y, decoding order, reference plane, compressed size,
side-information size. The payload holds, plane by plane in plane order, a grayscale JPEG stream
(rows bottom first, like the raw formats) followed by its side information. Planes are decoded
in increasing ``order``; a plane with a reference plane r ≥ 0 stores a residual, and its value
is ``(residual + ref − 128) mod 256`` where ``ref`` is plane r after its own decoding, or
``255 − ref`` when bit 0 of the transform (plane inversion) is set. Side information then
overwrites single bytes: 5-byte records, a 4-byte big-endian offset into the plane (in file
order) and the value. Bit 1 of the transform (motion compensation) is not supported by
RTIViewer or any public reader and is refused here.
"""

from __future__ import annotations

import io
import itertools
from pathlib import Path

import numpy as np

from .decoders import JPEG_PIXELS_PER_BYTE
from .errors import InputError
from .ptmheader import HeaderCursor

__all__ = ["read_jpeg_planes"]


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
            from PIL import Image  # JPEG only: other Pillow plugins (EPS) would start programs

            with Image.open(io.BytesIO(stream), formats=["JPEG"]) as im:
                w, h = im.size
    except Exception as exc:
        raise InputError(f"{where} is not a readable JPEG stream ({exc})", path) from None
    if (w, h) != (width, height):
        raise InputError(f"{where} is {w}×{h} but the header says {width}×{height}", path)
    try:
        if simplejpeg is not None:
            return simplejpeg.decode_jpeg(stream, colorspace="GRAY").reshape(height, width)
        with Image.open(io.BytesIO(stream), formats=["JPEG"]) as im:  # pragma: no cover
            return np.asarray(im.convert("L"))
    except Exception as exc:
        raise InputError(f"{where} cannot be decoded ({exc})", path) from None


def read_jpeg_planes(cur: HeaderCursor, n: int, width: int, height: int) -> tuple[np.ndarray, int]:
    """Read the plane table after a compressed PTM's bias line, and decode its planes.

    Parameters
    ----------
    cur : HeaderCursor
        The file's header, read up to and including the biases.
    n : int
        Number of planes: 9 for ``PTM_FORMAT_JPEG_LRGB``, 18 for ``PTM_FORMAT_JPEG_RGB``.
    width, height : int
        Size of a plane, from the header.

    Returns
    -------
    planes : ndarray, shape (n, H, W), uint8
        The planes in plane order, rows in file order (bottom row first).
    quality : int
        The JPEG quality the header records.

    Raises
    ------
    InputError
        If the plane table is inconsistent, the file is truncated, or a plane cannot be
        decoded.
    """
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
        # A plane's pixels the photographs' rule for JPEG allows its compressed bytes: a header
        # claiming a gigapixel plane for a few bytes is refused before anything is allocated.
        if width * height > JPEG_PIXELS_PER_BYTE * sizes[p]:
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
