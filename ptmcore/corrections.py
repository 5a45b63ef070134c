"""What is done to each photograph between its decoding and the reduction: capture defects undone.

Museum captures are rarely ideal: the room has light in it, the lamps do not light the frame
evenly, the tripod was bumped. Each correction here works on one photograph in linear light, so
every pass that decodes the photographs (:func:`ptmcore.reduce.reduce_photographs`: the stack,
the relighting fits, a second streamed pass) applies the same ones, in this order:

1. the ambient frame (lamps off) subtracted (:mod:`ptmcore.illumination`);
2. the photograph divided by its light's gain over the frame, measured on a flat board under the
   same lights (:class:`ptmcore.illumination.FlatField`);
3. the photograph resampled onto the capture's common frame (:mod:`ptmcore.align`).

The first two are in the photograph's own frame, where the room's light and the lamps' pattern
were; the last one moves it.
 A corrected photograph is float32 linear RGB, which the reduction
takes as it takes a float TIFF; with no correction the photograph goes to the reduction as it was
decoded, so clean captures (and the PTMfitter-compatible files made from 8-bit photographs) are
unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .images import srgb_to_linear

if TYPE_CHECKING:
    from .illumination import FlatField
    from .raw import RawDevelopment

__all__ = ["Corrections", "to_linear_rgb"]

#: Rows converted at a time, so that no step holds a second full-size float copy of a photograph.
_BAND_ROWS = 256
_SRGB8 = srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0)).astype(np.float32)
_LINEAR8 = (np.arange(256, dtype=np.float32) / np.float32(255.0)).astype(np.float32)


def to_linear_rgb(img: np.ndarray, linearize: bool = True) -> np.ndarray:
    """A decoded photograph as float32 ``(H, W, 3)`` linear light.

    Parameters
    ----------
    img : ndarray
        ``(H, W)`` or ``(H, W, 3)``: uint8 (sRGB when ``linearize``, else linear), uint16
        (linear, /65535) or float (linear, as it is).
    linearize : bool
        8-bit samples are sRGB-encoded.

    Returns
    -------
    ndarray, shape (H, W, 3), float32
        A new array (never a view of ``img``).
    """
    h, w = img.shape[:2]
    out = np.empty((h, w, 3), np.float32)
    rgb = img if img.ndim == 3 else img[:, :, None]
    for r0 in range(0, h, _BAND_ROWS):
        band = rgb[r0 : r0 + _BAND_ROWS]
        if img.dtype == np.uint8:
            out[r0 : r0 + _BAND_ROWS] = (_SRGB8 if linearize else _LINEAR8)[band]
        elif img.dtype == np.uint16:
            np.multiply(band, np.float32(1 / 65535), out=out[r0 : r0 + _BAND_ROWS], casting="unsafe")
        else:
            out[r0 : r0 + _BAND_ROWS] = band
    return out


@dataclass
class Corrections:
    """The corrections of a capture's photographs (all optional; see the module notes).

    Attributes
    ----------
    ambient : ndarray, shape (H, W, 3), float32, or None
        The room's light alone, linear (:func:`ptmcore.illumination.read_ambient`).
    flat : FlatField or None
        Each light's gain over the frame (:func:`ptmcore.illumination.load_flat_field`).
    transforms : ndarray, shape (N, 2, 3), or None
        For each photograph, where each pixel of the common frame lies in it
        (:attr:`ptmcore.align.Drift.transforms`); None or the identity leaves it in place.
    raw : RawDevelopment or None
        How camera RAW photographs are developed (:func:`ptmcore.raw.raw_development`): one
        white balance and orientation for the whole capture, so that its photographs stay
        comparable. It changes how they are decoded, not what is done to them after.
    """

    ambient: np.ndarray | None = None
    flat: FlatField | None = None
    transforms: np.ndarray | None = None
    raw: RawDevelopment | None = None

    @property
    def active(self) -> bool:
        """Whether any photograph's pixels change."""
        return self.ambient is not None or self.flat is not None or self.transforms is not None

    def moves(self, k: int) -> bool:
        """Whether photograph ``k`` is resampled."""
        if self.transforms is None:
            return False
        return not np.allclose(self.transforms[k], [[1, 0, 0], [0, 1, 0]], atol=1e-9)

    def apply(self, k: int, img: np.ndarray, linearize: bool = True) -> np.ndarray:
        """Photograph ``k`` (as decoded) corrected: float32 ``(H, W, 3)`` linear light, or
        ``img`` itself when nothing is to be done."""
        if not self.active:
            return img
        lin = to_linear_rgb(img, linearize)
        h = lin.shape[0]
        for r0 in range(0, h, _BAND_ROWS):
            r1 = min(h, r0 + _BAND_ROWS)
            band = lin[r0:r1]
            if self.ambient is not None:
                band -= self.ambient[r0:r1]
                np.maximum(band, 0, out=band)
            if self.flat is not None:  # a gain near 0 (a board's black corner) must not blow up
                band /= np.maximum(self.flat.gain_rows(k, r0, r1), np.float32(1e-3))[:, :, None]
        if self.moves(k):
            from .align import warp_photograph

            lin = warp_photograph(lin, self.transforms[k])
        return lin
