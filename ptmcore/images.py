"""Reading photographs and holding a capture's stack in bounded memory.

A capture of 50 photographs of 50 megapixels is 7.5 GB as 8-bit RGB and 30 GB as float32, so the
stack is never held like that. Each photograph is decoded (in parallel threads: JPEG decoding,
not arithmetic, dominates the run time of real captures), converted to linear RGB a band of rows
at a time, and reduced to what the later stages need:

* its linear luminance as ``uint16`` (value × 65534; 65535 marks a sample where a channel
  clipped), which is finer than an 8-bit sRGB step everywhere and half the size of float32;
* a running per-pixel sum of its linear RGB, which becomes the pixel's colour (chromaticity).

Decoders: JPEG with simplejpeg (libjpeg-turbo without Pillow's extra copy: 1.6× faster than
Pillow and 1.5× faster than OpenCV on a 24-megapixel photograph, see benchmarks/decoders.py),
or Pillow if it is missing; PNG with OpenCV because Pillow reads 16-bit RGB PNG as 8 bits;
TIFF with tifffile.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .errors import InputError

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMA_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
#: Code of a stored luminance sample that was clipped in some channel.
SATURATED = np.uint16(65535)
_LUM_SCALE = 65534.0


def _float(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v)
    return v if v.dtype == np.float64 else v.astype(np.float32, copy=False)


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """Decode sRGB values in [0, 1] to linear light (IEC 61966-2-1, exact piecewise form).

    float64 input stays float64; anything else is computed in float32.
    """
    v = _float(v)
    curve = ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(v <= 0.04045, v / 12.92, curve).astype(v.dtype, copy=False)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    """Encode linear values as sRGB (IEC 61966-2-1), clipping to [0, 1] first.

    float64 input stays float64; anything else is computed in float32.
    """
    v = np.clip(_float(v), 0.0, 1.0)
    curve = 1.055 * np.maximum(v, 0.0031308) ** (1 / 2.4) - 0.055
    return np.where(v <= 0.0031308, v * 12.92, curve).astype(v.dtype, copy=False)


def _decode_jpeg(data: bytes, path: Path) -> np.ndarray:
    try:
        import simplejpeg
    except ImportError:  # pragma: no cover - simplejpeg is a dependency; Pillow still works
        simplejpeg = None
    if simplejpeg is not None:
        try:
            header = simplejpeg.decode_jpeg_header(data)
            gray = header[2] == "Gray"
            img = simplejpeg.decode_jpeg(data, colorspace="GRAY" if gray else "RGB")
            return img[..., 0] if gray else img
        except ValueError:
            pass  # CMYK and other rarities: let Pillow try
    return _decode_pillow(path)


def _decode_pillow(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.mode not in ("L", "RGB", "I;16", "I;16B", "I;16L"):
                im = im.convert("RGB")
            return np.asarray(im)
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise InputError(f"cannot decode image ({exc})", path) from None


def _decode_png(data: bytes, path: Path) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("cannot decode PNG image (corrupt or truncated)", path)
    if img.ndim == 3:
        img = img[..., 2::-1] if img.shape[2] >= 3 else img[..., 0]  # BGR(A) -> RGB
    return img


def _decode_tiff(path: Path) -> np.ndarray:
    import tifffile

    try:
        img = tifffile.imread(path, key=0)
    except Exception as exc:  # tifffile raises many types for corrupt files
        raise InputError(f"cannot decode TIFF image ({exc})", path) from None
    if img.ndim == 3 and img.shape[0] in (3, 4) and img.shape[2] not in (3, 4):
        img = np.moveaxis(img, 0, -1)  # planar (C, H, W) layout
    return img


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a photograph as it is stored.

    Parameters
    ----------
    path : str or PathLike
        JPEG, PNG or TIFF file; 8 or 16 bit (TIFF may also be float); grey or RGB(A).

    Returns
    -------
    ndarray
        ``(H, W)`` for grey or ``(H, W, 3)`` for colour, in the file's own dtype (uint8,
        uint16 or float32). An alpha channel is dropped.

    Raises
    ------
    InputError
        If the file is missing, unreadable, not an image, or of an unsupported depth.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("image not found", path) from None
    except OSError as exc:
        raise InputError(f"cannot read image ({exc.strerror})", path) from None
    if not data:
        raise InputError("image file is empty", path)
    if data[:3] == b"\xff\xd8\xff":
        img = _decode_jpeg(data, path)
    elif data[:8] == b"\x89PNG\r\n\x1a\n":
        img = _decode_png(data, path)
    elif data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        img = _decode_tiff(path)
    else:
        img = _decode_pillow(path)
    if img.ndim == 3:
        if img.shape[2] == 1 or img.shape[2] == 2:
            img = img[..., 0]
        else:
            img = img[..., :3]
    if img.ndim not in (2, 3) or min(img.shape[:2]) < 1:
        raise InputError(f"unsupported image layout {img.shape}", path)
    if img.dtype == np.uint8 or img.dtype == np.uint16:
        return img
    if img.dtype.kind == "f":
        img = img.astype(np.float32, copy=False)
        if not np.all(np.isfinite(img)):
            raise InputError("image contains NaN or infinite values", path)
        return img
    if img.dtype == np.int16 or img.dtype == np.int32 or img.dtype == np.uint32:
        raise InputError(f"unsupported sample type {img.dtype} (use 8 or 16 bit unsigned)", path)
    raise InputError(f"unsupported sample type {img.dtype}", path)


@dataclass
class ImageStack:
    """A capture's photographs reduced to what the fit needs.

    Attributes
    ----------
    luminance : ndarray, shape (N, H, W), uint16
        Linear luminance × 65534 per photograph; :data:`SATURATED` where a channel clipped.
    chroma : ndarray, shape (H, W, 3), float32
        Per-pixel colour of unit luminance (Σ RGB / Σ luminance over the photographs; neutral
        grey where all were black): multiplying it by a luminance gives linear RGB.
    paths : list of Path
        The photographs, in order.
    bit_depth : int
        8 or 16 (32 for float TIFF); the highest among the photographs.
    linearized : bool
        Whether 8-bit sRGB values were decoded to linear light.
    saturated : ndarray, shape (N,), int64
        Number of clipped pixels in each photograph.
    """

    luminance: np.ndarray
    chroma: np.ndarray
    paths: list[Path]
    bit_depth: int
    linearized: bool
    saturated: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """Image height and width."""
        return self.luminance.shape[1], self.luminance.shape[2]

    def __len__(self) -> int:
        return self.luminance.shape[0]

    def select(self, keep: np.ndarray) -> ImageStack:
        """The stack of the photographs where ``keep`` (N,) is true (the colour stays)."""
        keep = np.asarray(keep, dtype=bool)
        if keep.all():
            return self
        return ImageStack(self.luminance[keep], self.chroma, [p for p, k in zip(self.paths, keep) if k],
                          self.bit_depth, self.linearized, self.saturated[keep])

    def band(self, r0: int, r1: int, c0: int | None = None, c1: int | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Linear luminance of rows ``r0:r1`` (columns ``c0:c1``, default all) of every photograph.

        Only that box is converted to float, so a small window of a large capture stays small.

        Returns
        -------
        values : ndarray, shape (N, r1 - r0, c1 - c0), float32
            Luminance in [0, 1]; clipped samples read as 1.
        saturated : ndarray, shape (N, r1 - r0, c1 - c0), bool
            Where a channel clipped.
        """
        raw = self.luminance[:, r0:r1, c0:c1]
        saturated = raw == SATURATED
        values = raw.astype(np.float32)
        values *= np.float32(1.0 / _LUM_SCALE)
        np.minimum(values, 1.0, out=values)
        return values, saturated


def _channel_table(dtype: np.dtype, linearize: bool, weights: np.ndarray) -> np.ndarray | None:
    """256-entry table of each channel's contribution to luminance, × 65534, for 8-bit input."""
    if dtype != np.uint8:
        return None
    v = np.arange(256, dtype=np.float32) / np.float32(255.0)
    lin = srgb_to_linear(v) if linearize else v
    return np.round(lin[None, :, None] * weights * _LUM_SCALE).astype(np.uint16)  # (1, 256, 3)


def _reduce_into(
    img: np.ndarray,
    lum_out: np.ndarray,
    channel_sum: np.ndarray,
    lock: threading.Lock,
    linearize: bool,
    gains: np.ndarray | None = None,
) -> int:
    """Write one photograph's luminance into ``lum_out`` and add its channels to ``channel_sum``.

    Returns the number of clipped pixels. ``gains`` (3,) multiply the linear channels first (a
    light's intensity divided out); clipping is judged on the stored values.

    Integer images go through OpenCV's vectorised kernels (a table look-up for 8-bit sRGB,
    a channel transform, a saturating sum): in NumPy this reduction took several times longer
    than decoding the JPEG. Each channel is first mapped to its luminance contribution
    ``w_c · linear_c · 65534`` as uint16, so their saturating sum is the luminance and clipped
    samples can be marked without a float image.
    """
    import cv2

    h, w = img.shape[:2]
    grey = img.ndim == 2
    weights = LUMA_WEIGHTS if gains is None else (LUMA_WEIGHTS * gains).astype(np.float32)
    table = _channel_table(img.dtype, linearize, weights)
    top = 254 if img.dtype == np.uint8 else 65534
    weights16 = weights * np.float32(_LUM_SCALE / 65535.0)  # for 16-bit input
    step = max(1, (1 << 20) // w)
    clipped_count = 0
    for r0 in range(0, h, step):
        block = np.ascontiguousarray(img[r0 : r0 + step])
        if block.dtype == np.float32:
            lin = np.clip(block, 0.0, 1.0)
            contrib = (lin[..., None] if grey else lin) * (weights * np.float32(_LUM_SCALE))
            contrib = np.round(contrib).astype(np.uint16)
            clipped = (block >= 1.0) if grey else (block >= 1.0).any(axis=2)
        else:
            if grey:
                block = cv2.merge([block, block, block])
            if table is not None:
                contrib = cv2.LUT(block, table)
            else:
                contrib = cv2.transform(block, np.diag(weights16))
            clipped = cv2.inRange(block, (0, 0, 0), (top, top, top)) == 0
        lum = cv2.transform(contrib, np.ones((1, 3), np.float32))
        np.minimum(lum, np.uint16(_LUM_SCALE), out=lum)
        np.copyto(lum, SATURATED, where=clipped)
        clipped_count += int(np.count_nonzero(clipped))
        lum_out[r0 : r0 + step] = lum
        with lock:
            cv2.accumulate(contrib, channel_sum[r0 : r0 + step])
    return clipped_count


def _chroma_in_place(channel_sum: np.ndarray) -> np.ndarray:
    """Turn sums of luminance contributions ``w_c · C_c`` into colour of unit luminance.

    Done in place and in bands: at 24 megapixels a whole-image expression would need a
    gigabyte of temporaries.
    """
    h, w = channel_sum.shape[:2]
    inv_w = (1.0 / LUMA_WEIGHTS).astype(np.float32)
    for r0 in range(0, h, max(1, (1 << 18) // w)):
        band = channel_sum[r0 : r0 + max(1, (1 << 18) // w)]
        lum = band.sum(axis=2, keepdims=True)
        black = lum[..., 0] <= 0
        band /= np.where(lum > 0, lum, 1.0)
        band *= inv_w
        band[black] = 1.0
    return channel_sum


def load_stack(
    paths: Sequence[str | os.PathLike],
    *,
    linearize: bool = True,
    channel_gains: np.ndarray | None = None,
    min_photographs: int = 3,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> ImageStack:
    """Decode a capture's photographs into an :class:`ImageStack`.

    Parameters
    ----------
    paths : sequence of path
        The photographs, all of the same size.
    linearize : bool
        Take 8-bit images as sRGB and decode them to linear light (16-bit and float images
        are always taken as linear).
    channel_gains : ndarray, shape (N, 3), optional
        Factors for each photograph's linear R, G, B (e.g. 1 / light intensity), applied
        before the reduction to luminance; at most 1, so no sample leaves the stored range.
    min_photographs : int
        Fewer photographs are an error (three determine a normal; calibration needs fewer).
    threads : int, optional
        Decoding threads; default: the number of CPUs.
    progress : callable, optional
        Called with 1 after each photograph.

    Returns
    -------
    ImageStack

    Raises
    ------
    InputError
        If fewer than three photographs are given, one cannot be read, or sizes differ.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise InputError("no photographs given")
    if len(paths) < min_photographs:
        raise InputError(
            f"{len(paths)} photograph(s) given; at least {min_photographs} are needed to recover normals"
        )
    if channel_gains is not None:
        channel_gains = np.asarray(channel_gains, dtype=np.float32).reshape(len(paths), 3)
        if not (np.all(np.isfinite(channel_gains)) and np.all(channel_gains > 0) and channel_gains.max() <= 1):
            raise ValueError("channel gains must be finite, positive and at most 1")
    first = read_image(paths[0])
    h, w = first.shape[:2]
    n = len(paths)
    luminance = np.empty((n, h, w), dtype=np.uint16)
    channel_sum = np.zeros((h, w, 3), dtype=np.float32)
    lock = threading.Lock()
    depths: list[int] = [0] * n
    saturated = np.zeros(n, dtype=np.int64)

    def work(k: int, img: np.ndarray | None = None) -> None:
        if img is None:
            img = read_image(paths[k])
        if img.shape[:2] != (h, w):
            raise InputError(
                f"image is {img.shape[1]}×{img.shape[0]} but {paths[0].name} is {w}×{h}; "
                "all photographs of a capture must have the same size",
                paths[k],
            )
        depths[k] = img.dtype.itemsize * 8
        gains = None if channel_gains is None else channel_gains[k]
        saturated[k] = _reduce_into(img, luminance[k], channel_sum, lock, linearize, gains)
        if progress is not None:
            progress(1)

    work(0, first)
    del first
    workers = threads or os.cpu_count() or 1
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(work, k) for k in range(1, n)]
        try:
            for f in futures:
                f.result()
        except BaseException:
            for f in futures:
                f.cancel()
            raise
    return ImageStack(luminance, _chroma_in_place(channel_sum), paths, max(depths), linearize, saturated)


def encode_png(image: np.ndarray) -> bytes:
    """Encode an 8- or 16-bit grey or RGB image ``(H, W[, 3])`` as PNG bytes.

    OpenCV's encoder releases the GIL (it runs beside other writers) and, unlike Pillow, writes
    16-bit RGB.
    """
    import cv2

    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError("PNG images must be uint8 or uint16")
    img = image[..., ::-1] if image.ndim == 3 else image  # OpenCV stores BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.shape} {image.dtype} image as PNG")
    return buf.tobytes()


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an 8- or 16-bit grey or RGB image ``(H, W[, 3])`` as PNG."""
    data = encode_png(image)
    with atomic_write(path, "wb") as f:
        f.write(data)
