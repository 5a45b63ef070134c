"""PTM files built byte by byte for the tests, independently of ``ptmcore.ptmfile``.

Includes a small JPEG-PTM encoder following HP's format: grayscale JPEG planes stored bottom
row first, planes decoded in a chosen order, planes predicted from a reference plane (optionally
inverted) as residuals ``(target − ref + 128) mod 256``, and side information (5-byte records,
big-endian pixel offset then value) that overwrites the pixels the JPEG got wrong by more than a
tolerance.
"""

from __future__ import annotations

import numpy as np
import simplejpeg

#: Plane order and references of the JPEG samples: the colour planes first (G from R, B from G),
#: then the constant term, the linear and the quadratic terms; a1 is predicted from a0 inverted.
LRGB_ORDER = [6, 8, 7, 4, 5, 3, 0, 1, 2]
LRGB_REFERENCE = [-1, 0, -1, -1, 3, -1, -1, 6, 7]
LRGB_TRANSFORM = [0, 1, 0, 0, 0, 0, 0, 0, 0]


def header(fmt: str, width: int, height: int, scale, bias, version: str = "PTM_1.2") -> bytes:
    """The text header as PTMfitter lays it out (a space after every scale and bias)."""
    text = f"{version}\n{fmt}\n{width}\n{height}\n"
    text += "".join(f"{s:f} " for s in scale) + "\n"
    text += "".join(f"{int(b)} " for b in bias) + "\n"
    return text.encode("ascii")


def smooth_codes(rng: np.random.Generator, h: int, w: int, planes: int) -> np.ndarray:
    """Byte planes ``(planes, h, w)`` with smooth content (so JPEG has something to compress)
    and an asymmetric ramp, so a flipped image is detectable."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.empty((planes, h, w), dtype=np.uint8)
    for p in range(planes):
        a, b, c = rng.uniform(-1, 1, 3)
        v = 128 + 60 * np.sin(a * x / 3 + b * y / 2 + c) + 40 * (y / max(1, h - 1)) * (p % 2 * 2 - 1)
        v += rng.normal(0, 3, (h, w))
        out[p] = np.clip(np.rint(v), 0, 255).astype(np.uint8)
    return out


def lrgb_bytes(codes: np.ndarray, rgb: np.ndarray, scale, bias, version: str = "PTM_1.2") -> bytes:
    """An uncompressed LRGB PTM from coefficient bytes ``(H, W, 6)`` and colours ``(H, W, 3)``,
    both row 0 at the top; versions before 1.2 interleave 9 bytes per pixel."""
    h, w = codes.shape[:2]
    head = header("PTM_FORMAT_LRGB", w, h, scale, bias, version)
    if version == "PTM_1.2":
        return head + codes[::-1].tobytes() + rgb[::-1].tobytes()
    return head + np.concatenate([codes, rgb], axis=2)[::-1].tobytes()


def rgb_bytes(codes: np.ndarray, scale, bias) -> bytes:
    """An uncompressed RGB-format PTM from coefficient bytes ``(H, W, 3, 6)``, row 0 at the top."""
    h, w = codes.shape[:2]
    blocks = b"".join(codes[::-1, :, c, :].tobytes() for c in range(3))
    return header("PTM_FORMAT_RGB", w, h, scale, bias) + blocks


def jpeg_ptm(
    fmt: str,
    planes: np.ndarray,
    scale,
    bias,
    *,
    quality: int = 75,
    order: list[int] | None = None,
    reference: list[int] | None = None,
    transform: list[int] | None = None,
    tolerance: int = 0,
) -> tuple[bytes, np.ndarray, dict]:
    """Encode byte planes ``(n, H, W)`` (row 0 at the top) as a JPEG PTM.

    Returns the file, the planes a reader must reconstruct (row 0 at the top; equal to
    `planes` when `tolerance` is 0) and counts of side-information records per plane.
    """
    n, h, w = planes.shape
    order = list(range(n)) if order is None else order
    reference = [-1] * n if reference is None else reference
    transform = [0] * n if transform is None else transform
    stored = planes[:, ::-1]  # file order: bottom row first
    final = np.zeros_like(stored)
    streams: list[bytes] = [b""] * n
    sides: list[bytes] = [b""] * n
    for p in sorted(range(n), key=order.__getitem__):
        target = stored[p]
        r = reference[p]
        if r >= 0:
            ref = final[r] if not transform[p] & 1 else 255 - final[r]
            residual = (target.astype(np.int16) - ref + 128) % 256
        else:
            ref = None
            residual = target.astype(np.int16)
        pixels = np.ascontiguousarray(residual.astype(np.uint8)[..., None])
        data = simplejpeg.encode_jpeg(pixels, quality=quality, colorspace="GRAY")
        decoded = simplejpeg.decode_jpeg(data, colorspace="GRAY")[..., 0].astype(np.int16)
        recon = decoded if ref is None else (decoded + ref - 128) % 256
        bad = np.flatnonzero(np.abs(recon - target.astype(np.int16)) > tolerance)
        recon = recon.reshape(-1)
        recon[bad] = target.reshape(-1)[bad]
        records = np.zeros((bad.size, 5), dtype=np.uint8)
        records[:, :4] = bad.astype(">u4").view(np.uint8).reshape(-1, 4)
        records[:, 4] = target.reshape(-1)[bad]
        final[p] = recon.reshape(h, w).astype(np.uint8)
        streams[p] = data
        sides[p] = records.tobytes()

    def line(values) -> str:
        return " ".join(str(v) for v in values) + "\n"

    text = header(fmt, w, h, scale, bias).decode("ascii")
    text += f"{quality}\n" + line(transform) + line([0] * n) + line([0] * n)
    text += line(order) + line(reference) + line(len(s) for s in streams) + line(len(s) for s in sides)
    payload = b"".join(s + si for s, si in zip(streams, sides))
    counts = {"side_records": [len(s) // 5 for s in sides]}
    return text.encode("ascii") + payload, final[:, ::-1].copy(), counts


def sample_files(rng: np.random.Generator, h: int = 6, w: int = 9) -> dict[str, bytes]:
    """One small valid file of every readable layout, for fuzzing."""
    scale = [0.5, 0.5, 0.25, 0.5, 0.25, 1.0]
    bias = [167, 97, 0, 0, 0, 0]
    planes = smooth_codes(rng, h, w, 18)
    lrgb_codes = np.moveaxis(planes[:6], 0, -1)
    rgb = np.moveaxis(planes[6:9], 0, -1)
    files = {
        "lrgb": lrgb_bytes(lrgb_codes, rgb, scale, bias),
        "lrgb_1.1": lrgb_bytes(lrgb_codes, rgb, scale, bias, version="PTM_1.1"),
        "rgb": rgb_bytes(np.moveaxis(planes.reshape(3, 6, h, w), (0, 1), (2, 3)), scale, bias),
    }
    files["jpeg_lrgb"] = jpeg_ptm(
        "PTM_FORMAT_JPEG_LRGB", planes[:9], scale, bias,
        order=LRGB_ORDER, reference=LRGB_REFERENCE, transform=LRGB_TRANSFORM, tolerance=4,
    )[0]
    files["jpeg_rgb"] = jpeg_ptm(
        "PTM_FORMAT_JPEG_RGB", planes, scale, bias,
        reference=[-1] * 6 + list(range(6)) + list(range(6, 12)), tolerance=4,
    )[0]
    return files
