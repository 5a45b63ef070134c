"""Camera RAW photographs with a known truth: DNG files of a Bayer sensor whose colours are
sRGB's own, so that developing them gives back the linear image they were made from.

The synthetic camera's three colour filters see sRGB's linear R, G and B, each scaled by the
camera's response to white (``neutral``: a real sensor's green is the most sensitive, and the
light's colour scales the channels further). Its DNG tags say exactly that: ColorMatrix1
(XYZ → camera) is ``diag(neutral) · M``, with ``M`` the XYZ → linear sRGB matrix (D65), under
CalibrationIlluminant1 D65, and AsShotNeutral is ``neutral``. A developer that undoes the
as-shot white balance and converts to sRGB, as :func:`ptmcore.raw.read_raw` has LibRaw do,
then returns the input.

LibRaw's scale, measured with rawpy 0.28 (LibRaw 0.22): the 16-bit output is
``linear_rgb · max(neutral) · 65535`` whatever ``black`` and ``white`` are. LibRaw maps
``white − black`` to 65535 in the channel with the smallest white-balance multiplier (the
largest neutral: green, normally) and scales the others by their multiplier over it; a neutral
of (0.5, 0.8, 0.6) gave 0.4 for a grey of 0.5, (0.5, 0.8, 0.9) gave 0.45. With the default
neutral (green 1) the output is ``linear_rgb · 65535``: a flat grey within 1.2e-4 for white
levels 4095, 15000 and 65535, a smooth image within 0.001 away from its outermost pixel, which
demosaicing gets wrong by up to 0.023 (``tests/test_raw.py``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import tifffile

from ptmcore.atomic import atomic_write

__all__ = ["XYZ_TO_SRGB", "bayer_mosaic", "write_dng"]

#: XYZ → linear sRGB (IEC 61966-2-1, D65 white), rows R, G, B.
XYZ_TO_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                        [-0.9692660, 1.8760108, 0.0415560],
                        [0.0556434, -0.2040259, 1.0572252]])

# TIFF/DNG tags and types written (DNG specification 1.4; TIFF/EP for the CFA tags).
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _SRATIONAL = 1, 2, 3, 4, 5, 10
_CFA = 32803  # PhotometricInterpretation: colour filter array
_D65 = 21     # CalibrationIlluminant: the EXIF LightSource code of D65
_DENOMINATOR = 1_000_000


def bayer_mosaic(linear_rgb: np.ndarray) -> np.ndarray:
    """An RGGB Bayer mosaic of an ``(H, W, 3)`` image: R at even rows and columns, B at odd
    rows and columns, G elsewhere; ``(H, W)``, the image's dtype."""
    img = np.asarray(linear_rgb)
    mosaic = img[..., 1].copy()
    mosaic[0::2, 0::2] = img[0::2, 0::2, 0]
    mosaic[1::2, 1::2] = img[1::2, 1::2, 2]
    return mosaic


def _rationals(values: np.ndarray) -> tuple[int, ...]:
    """Numerators and denominators, interleaved, as (S)RATIONAL tags store them."""
    out: list[int] = []
    for v in np.ravel(values):
        out += [int(round(float(v) * _DENOMINATOR)), _DENOMINATOR]
    return tuple(out)


def write_dng(path: str | os.PathLike, linear_rgb: np.ndarray, *, neutral: Sequence[float] = (0.55, 1.0, 0.7),
              black: int = 512, white: int = 15000, orientation: int = 1,
              model: str = "ptm-reconstruct synthetic", as_shot: Sequence[float] | None = None) -> None:
    """Write a linear sRGB image as the DNG of a Bayer camera, atomically.

    Parameters
    ----------
    path : str or PathLike
        The ``.dng`` file.
    linear_rgb : ndarray, shape (H, W, 3)
        Linear light in sRGB's primaries, clipped to [0, 1]: what developing the file gives back.
    neutral : sequence of 3 float
        The camera's raw R, G, B for white (each in (0, 1]): written as AsShotNeutral and
        folded into ColorMatrix1, and each channel's raw values are scaled by it.
    black, white : int
        The sensor's black and white levels (BlackLevel, WhiteLevel), 0 ≤ black < white ≤ 65535.
    orientation : int
        The TIFF Orientation tag, 1 to 8 (6: the camera was turned 90° clockwise, the
        photograph is to be rotated so).
    model : str
        Model and UniqueCameraModel (Make is ``"ptm-reconstruct"``).
    as_shot : sequence of 3 float, optional
        The AsShotNeutral tag when it is not ``neutral``: a camera whose automatic white
        balance guessed another light (the pixels stay those of ``neutral``).

    Raises
    ------
    ValueError
        If the image is not ``(H, W, 3)`` with H, W ≥ 2, or an argument is out of range.
    """
    img = np.asarray(linear_rgb, dtype=np.float64)
    n = np.asarray(neutral, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 2:
        raise ValueError(f"expected an (H, W, 3) image at least 2 × 2, not {img.shape}")
    if n.shape != (3,) or not np.all((n > 0) & (n <= 1)):
        raise ValueError(f"neutral must be 3 values in (0, 1], not {neutral!r}")
    if not 0 <= black < white <= 65535:
        raise ValueError(f"need 0 <= black < white <= 65535, not black={black}, white={white}")
    shot = n if as_shot is None else np.asarray(as_shot, dtype=np.float64)
    if shot.shape != (3,) or not np.all((shot > 0) & (shot <= 1)):
        raise ValueError(f"as_shot must be 3 values in (0, 1], not {as_shot!r}")
    if orientation not in range(1, 9):
        raise ValueError(f"orientation must be 1 to 8, not {orientation!r}")
    camera = np.clip(np.nan_to_num(img), 0.0, 1.0) * n  # the filters' responses
    raw = np.round(black + (white - black) * bayer_mosaic(camera)).astype(np.uint16)
    tags = [
        (271, _ASCII, 0, "ptm-reconstruct", True),                 # Make
        (272, _ASCII, 0, model, True),                             # Model
        (274, _SHORT, 1, orientation, True),                       # Orientation
        (33421, _SHORT, 2, (2, 2), True),                          # CFARepeatPatternDim
        (33422, _BYTE, 4, (0, 1, 1, 2), True),                     # CFAPattern: R G / G B
        (50706, _BYTE, 4, (1, 4, 0, 0), True),                     # DNGVersion 1.4.0.0
        (50707, _BYTE, 4, (1, 1, 0, 0), True),                     # DNGBackwardVersion 1.1.0.0
        (50708, _ASCII, 0, model, True),                           # UniqueCameraModel
        (50714, _LONG, 1, int(black), True),                       # BlackLevel
        (50717, _LONG, 1, int(white), True),                       # WhiteLevel
        (50721, _SRATIONAL, 9, _rationals(np.diag(n) @ XYZ_TO_SRGB), True),  # ColorMatrix1
        (50728, _RATIONAL, 3, _rationals(shot), True),             # AsShotNeutral
        (50778, _SHORT, 1, _D65, True),                            # CalibrationIlluminant1
    ]
    with atomic_write(path) as fh:
        # The mosaic in IFD 0 (NewSubFileType 0: the main image), uncompressed, one strip.
        tifffile.imwrite(fh, raw, photometric=_CFA, subfiletype=0, extratags=tags, metadata=None)
