"""The camera's drift between photographs: measured, and undone by resampling.

A bumped tripod or a sagging head moves the camera between photographs; a pixel then sees a
different point of the object in each, and every fit (PTM, normals) mixes neighbours: half the
photographs of a synthetic tablet moved by 4 × 3 px raised the mean normal error from 0.35° to
4.6°. Two photographs under different lights cannot be compared directly (the shading changes
completely), so each photograph is compared with the capture's own prediction of it: a PTM fitted
to all the photographs, evaluated for its light *leaving it out* (the hat-matrix shortcut), has
the same shading and the majority's geometry. Phase correlation of the two (sub-pixel, by
scikit-image's upsampled DFT) gives the photograph's offset; the photographs are shifted by their
offsets, the PTM fitted again and the offsets measured again, until they settle.

The work is on a few tiles of the frame, copied from each photograph while it is decoded
(:class:`DriftProbe`), so a steady capture pays no second decoding; several tiles give a small
rotation as well as the translation. The frame that most photographs share is kept (of two
equal groups, the one the capture started in).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .images import LUMA_WEIGHTS, srgb_to_linear

__all__ = ["ALIGN_THRESHOLD_PX", "Drift", "DriftProbe", "measure_drift", "warp_photograph"]

#: A photograph displaced by more than this anywhere in the frame (pixels) makes a run resample
#: the capture. Steady captures read up to 0.55 px on the synthetic tablet (its grazing lights'
#: cast shadows, which the PTM prediction does not have, pull the registration) and 0.78 px and
#: 0.67 px on the real captures of ../shared/real (benchmarks/drift.py, 2026-11-28): a lower
#: threshold would resample steady captures, blurring them for nothing. Above it, the error
#: the drift causes grows fast (4 × 3 px: 4.6° mean normal error against 0.35°).
ALIGN_THRESHOLD_PX = 1.0
#: The probe's memory at most (bytes): its tiles shrink for captures of many photographs.
PROBE_BYTES = 64 << 20
#: The largest tile side (pixels): enough texture for a sub-pixel offset, small enough that
#: a capture's measurement takes about a second.
TILE = 192
#: The smallest useful tile side.
MIN_TILE = 32
_SRGB8 = srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0)).astype(np.float32)
#: Passes of fitting and measuring; a steady capture stops after the first.
_PASSES = 10
#: Below this confidence (correlation of the photograph's and its prediction's details) a
#: tile's offset is not trusted: a featureless or dark tile.
_MIN_CONFIDENCE = 0.2


class DriftProbe:
    """Tiles of every photograph, copied while the capture is decoded.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the photographs.
    n : int
        The number of photographs.

    Attributes
    ----------
    origins : ndarray, shape (T, 2)
        Each tile's top-left ``(row, column)``.
    size : int
        The tiles' side.
    tiles : ndarray, shape (n, T, size, size), float32
        Linear luminance.
    """

    def __init__(self, shape: tuple[int, int], n: int) -> None:
        h, w = int(shape[0]), int(shape[1])
        size = min(TILE, int(min(h, w) / 2.5))
        spread = min(h, w) >= 4 * size
        count = 5 if spread else 1
        size = min(size, int(np.sqrt(PROBE_BYTES / (4 * count * max(1, n)))))
        self.size = max(MIN_TILE, size - size % 2)
        s = self.size
        centres = [(h // 2, w // 2)]
        if spread:
            centres += [(h // 4, w // 4), (h // 4, 3 * w // 4), (3 * h // 4, w // 4), (3 * h // 4, 3 * w // 4)]
        self.origins = np.array([(min(max(0, r - s // 2), h - s), min(max(0, c - s // 2), w - s))
                                 for r, c in centres], np.int64)
        self.shape = (h, w)
        self.tiles = np.zeros((n, len(self.origins), s, s), np.float32)
        self.seen = np.zeros(n, bool)

    def take(self, k: int, img: np.ndarray, srgb8: bool) -> None:
        """Copy photograph ``k``'s tiles: ``img`` ``(H, W, 3)`` as the reduction reads it (uint8,
        sRGB when ``srgb8``; uint16 linear; float linear; a grey one may be a stride-0 view)."""
        s = self.size
        for t, (r, c) in enumerate(self.origins):
            part = img[r : r + s, c : c + s]
            if part.dtype == np.uint8:
                rgb = _SRGB8[part] if srgb8 else part.astype(np.float32) / np.float32(255)
            elif part.dtype == np.uint16:
                rgb = part.astype(np.float32) / np.float32(65535)
            else:
                rgb = part.astype(np.float32, copy=False)
            self.tiles[k, t] = rgb @ LUMA_WEIGHTS
        self.seen[k] = True


@dataclass
class Drift:
    """Each photograph's displacement against the capture's common frame.

    Attributes
    ----------
    offsets : ndarray, shape (N, 2)
        ``(dx, dy)`` in pixels, x to the right and y up: where the common frame's content lies
        in the photograph, at the frame's centre.
    rotation_deg : ndarray, shape (N,)
        Counter-clockwise rotation of the photograph's content, degrees.
    transforms : ndarray, shape (N, 2, 3)
        For each photograph, the affine map from a pixel ``(column, row)`` of the common frame
        to where it lies in the photograph (OpenCV's ``WARP_INVERSE_MAP`` convention).
    confidence : ndarray, shape (N,)
        0 to 1: how well the photograph's details matched its prediction (0: not measured,
        offset taken as 0).
    shape : tuple of int
        ``(H, W)`` of the frame.
    """

    offsets: np.ndarray
    rotation_deg: np.ndarray
    transforms: np.ndarray
    confidence: np.ndarray
    shape: tuple[int, int]

    def displacement(self) -> np.ndarray:
        """``(N,)`` the largest distance, pixels, any corner of the frame moves in each photograph."""
        h, w = self.shape
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], np.float64)
        moved = np.einsum("nij,cj->nci", self.transforms, corners)
        return np.linalg.norm(moved - corners[None, :, :2], axis=2).max(axis=1)

    def largest(self) -> tuple[int, float]:
        """The photograph displaced most, and by how many pixels (rotation included)."""
        d = self.displacement()
        k = int(np.argmax(d))
        return k, float(d[k])

    def needs_alignment(self, threshold: float = ALIGN_THRESHOLD_PX) -> bool:
        """Whether some photograph is displaced by more than ``threshold`` pixels."""
        return self.largest()[1] > threshold


def _ptm_basis(lights: np.ndarray) -> np.ndarray:
    lu, lv = lights[:, 0], lights[:, 1]
    return np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=1)


def _details(tile: np.ndarray) -> np.ndarray:
    """A tile's fine detail, windowed: minus its blur (the shading's slow part), times a Hann
    window (so that its edges do not correlate with themselves)."""
    from scipy.ndimage import gaussian_filter

    high = tile - gaussian_filter(tile, 4.0, mode="nearest")
    s = tile.shape[-1]
    window = np.hanning(s).astype(np.float32)
    return high * window[:, None] * window[None, :]


def _shift(tiles: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Each tile moved back by its offset ``d`` (rows, columns): the common frame's view."""
    from scipy.ndimage import shift

    out = np.empty_like(tiles)
    for i in range(len(tiles)):
        out[i] = tiles[i] if not d[i].any() else shift(tiles[i], -d[i], order=3, mode="nearest")
    return out


def _measure_tiles(tiles: np.ndarray, lights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``(N, 2)`` (rows, columns) of each photograph's tile, and their confidence."""
    from skimage.registration import phase_cross_correlation

    n = len(tiles)
    a = _ptm_basis(lights)
    p = np.linalg.pinv(a)
    leverage = np.clip(np.einsum("ij,ji->i", a, p), 0, 0.95)
    d = np.zeros((n, 2))
    details = np.stack([_details(t) for t in tiles])

    def predictions() -> np.ndarray:
        # Each photograph as the others predict it, in the common frame.
        flat = _shift(tiles, d).reshape(n, -1)
        pred = a @ (p @ flat)
        return (flat - (flat - pred) / (1 - leverage)[:, None]).reshape(tiles.shape)

    for _ in range(_PASSES):
        loo = predictions()
        found = d.copy()
        for k in range(n):
            ref = _details(loo[k])
            if ref.any() and details[k].any():
                # The shift that brings the photograph onto its prediction: minus its offset.
                found[k] = -np.asarray(phase_cross_correlation(ref, details[k], upsample_factor=10,
                                                               normalization=None)[0], float)
        moved, d = np.abs(found - d).max(), found
        if moved < 0.05:  # settled: a steady capture stops after the first passes
            break
    loo = predictions()
    aligned = _shift(tiles, d)
    confidence = np.array([_correlation(_details(loo[k]), _details(aligned[k])) for k in range(n)])
    return d, confidence


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return 0.0 if na == 0 or nb == 0 else float(np.clip((a * b).sum() / (na * nb), 0, 1))


def _common_frame(shift: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """The photographs of the frame most of them share: the largest group within a pixel of one
    another (a bumped tripod splits a capture in two groups: before and after), and of equal
    groups the one of the earliest photograph, the frame the capture started in."""
    k = np.flatnonzero(measured)
    close = np.linalg.norm(shift[k, None] - shift[None, k], axis=2) <= 1.0
    best = int(np.argmax(close.sum(axis=1)))  # argmax takes the first of equals: the earliest
    ref = np.zeros(len(shift), bool)
    ref[k[close[best]]] = True
    return ref


def measure_drift(probe: DriftProbe, lights: np.ndarray) -> Drift:
    """Each photograph's offset (and small rotation) against the capture's common frame.

    Parameters
    ----------
    probe : DriftProbe
        Filled by the decoding pass.
    lights : ndarray, shape (N, 3)
        Unit directions towards the lights, one per photograph.

    Returns
    -------
    Drift
    """
    lights = np.asarray(lights, np.float64)
    n, count = probe.tiles.shape[:2]
    per_tile = np.zeros((n, count, 2))
    conf = np.zeros((n, count))
    for t in range(count):
        per_tile[:, t], conf[:, t] = _measure_tiles(probe.tiles[:, t], lights)
    trusted = conf >= _MIN_CONFIDENCE
    h, w = probe.shape
    centre = np.array([(h - 1) / 2, (w - 1) / 2])
    pos = probe.origins + probe.size / 2 - 0.5 - centre  # tile centres (rows, columns) from the frame's centre
    shift = np.zeros((n, 2))
    theta = np.zeros(n)
    for k in range(n):
        use = trusted[k]
        if not use.any():
            continue
        if use.sum() >= 3:
            # Small rotation θ about the centre (rows down, columns right): a tile at (r, c)
            # moves by (θ·c, −θ·r) beside the translation.
            rows = np.zeros((2 * use.sum(), 3))
            rows[0::2, 0], rows[0::2, 2] = 1, pos[use, 1]
            rows[1::2, 1], rows[1::2, 2] = 1, -pos[use, 0]
            sol, *_ = np.linalg.lstsq(rows, per_tile[k, use].reshape(-1), rcond=None)
            shift[k], theta[k] = sol[:2], sol[2]
        else:
            shift[k] = np.median(per_tile[k, use], axis=0)
    measured = trusted.any(axis=1)
    if measured.any():
        ref = _common_frame(shift, measured)
        shift[measured] -= np.median(shift[ref], axis=0)
        theta[measured] -= np.median(theta[ref])
    cos, sin = np.cos(theta), np.sin(theta)
    transforms = np.zeros((n, 2, 3))
    # (column, row) of the common frame → the photograph: rotate about the centre, then shift.
    transforms[:, 0, 0], transforms[:, 0, 1] = cos, -sin
    transforms[:, 1, 0], transforms[:, 1, 1] = sin, cos
    cxy = centre[::-1]
    transforms[:, :, 2] = cxy + shift[:, ::-1] - np.einsum("nij,j->ni", transforms[:, :, :2], cxy)
    offsets = np.stack([shift[:, 1], -shift[:, 0]], axis=1)
    confidence = np.where(trusted, conf, 0).sum(axis=1) / np.maximum(1, trusted.sum(axis=1))
    return Drift(offsets, -np.degrees(theta), transforms, confidence, (h, w))


def warp_photograph(img: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """A photograph resampled onto the common frame (bicubic; the border repeated).

    Parameters
    ----------
    img : ndarray, shape (H, W) or (H, W, 3), float32
    transform : ndarray, shape (2, 3)
        :attr:`Drift.transforms` of the photograph.

    Returns
    -------
    ndarray, float32, the shape of ``img``
    """
    import cv2

    h, w = img.shape[:2]
    return cv2.warpAffine(np.ascontiguousarray(img, np.float32), np.asarray(transform, np.float64), (w, h),
                          flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
