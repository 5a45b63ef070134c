"""The specular highlight on a glossy sphere, to sub-pixel precision.

:func:`find_highlight` looks in one grey image; :func:`find_highlights` in the crops of every
photograph around one sphere at once, as the calibration does. Positions are (x_img, y_img) =
(column, row) with pixel centres at integers.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from reconstruct.calibration.reflection import Sphere

__all__ = ["find_highlight", "find_highlights"]


def find_highlight(
    image_gray: np.ndarray,
    sphere: Sphere,
    *,
    min_peak: float = 0.15,
    max_area_fraction: float = 0.02,
) -> tuple[float, float, float] | None:
    """Sub-pixel position of the specular highlight on one sphere.

    Inside the sphere (the anti-aliased limb excluded), pixels above a threshold halfway
    between the disc's median (its dark body) and its brightest pixel form blobs; the blob
    holding the brightest pixel, grown by two pixels, gives the highlight as its
    intensity-weighted centroid (weights are the excess over the body's median, so the
    estimate is insensitive to the dark body).

    Parameters
    ----------
    image_gray : np.ndarray
        (H, W) linear grey image in [0, 1].
    sphere : (cx, cy, r)
        The sphere, in pixels.
    min_peak : float
        The brightest pixel must reach this linear level; dimmer means no highlight.
    max_area_fraction : float
        A blob larger than this fraction of the disc is not a mirror highlight (a diffuse
        sheen or a blown-out sphere).

    Returns
    -------
    (hx, hy, confidence) or None
        Position in image coordinates (column, row) and a confidence in (0, 1]; None when
        there is no usable highlight.
    """
    img = np.asarray(image_gray, dtype=np.float32)
    return find_highlights(img[None], sphere, min_peak=min_peak,
                           max_area_fraction=max_area_fraction)[0]


def find_highlights(images: np.ndarray, sphere: Sphere, *, min_peak: float = 0.15,
                    max_area_fraction: float = 0.02) -> list[tuple[float, float, float] | None]:
    """:func:`find_highlight` on each of several images of the same sphere.

    The disc and the pixel grid are built once; the disc's peak and median are taken for
    all images at once, and only images with a candidate highlight are labelled.

    Parameters
    ----------
    images : np.ndarray
        (N, H, W) float32 linear grey images (e.g. every photograph's crop around the sphere).
    sphere : (cx, cy, r)
        The sphere, in the images' pixels.
    min_peak, max_area_fraction : float
        As in :func:`find_highlight`.

    Returns
    -------
    list of (hx, hy, confidence) or None
        One per image.
    """
    cx, cy, r = sphere
    n, h, w = images.shape
    r0, r1 = max(int(np.floor(cy - r)), 0), min(int(np.ceil(cy + r)) + 1, h)
    c0, c1 = max(int(np.floor(cx - r)), 0), min(int(np.ceil(cx + r)) + 1, w)
    if r1 - r0 < 3 or c1 - c0 < 3:
        return [None] * n
    crops = images[:, r0:r1, c0:c1]
    yy, xx = np.ogrid[r0:r1, c0:c1]
    disc = np.hypot(xx - cx, yy - cy) < r - 1.5
    disc_area = int(disc.sum())
    if disc_area < 10:
        return [None] * n
    vals = crops[:, disc]
    peaks = vals.max(axis=1).astype(np.float64)
    bodies = np.median(vals, axis=1).astype(np.float64)
    del vals
    found: list[tuple[float, float, float] | None] = [None] * n
    for k in np.flatnonzero((peaks >= min_peak) & (peaks >= 3.0 * bodies)):
        found[k] = _highlight_in_disc(crops[k], disc, disc_area, xx, yy, float(peaks[k]),
                                      float(bodies[k]), (cx, cy, r), max_area_fraction)
    return found


def _highlight_in_disc(crop: np.ndarray, disc: np.ndarray, disc_area: int, xx: np.ndarray,
                       yy: np.ndarray, peak: float, body: float, sphere: Sphere,
                       max_area_fraction: float) -> tuple[float, float, float] | None:
    """The highlight of one image's crop, given its disc's peak and median (body)."""
    cx, cy, r = sphere
    thresh = body + 0.5 * (peak - body)
    blobs, _ = ndimage.label((crop > thresh) & disc)
    iy, ix = np.unravel_index(np.argmax(np.where(disc, crop, -np.inf)), crop.shape)
    blob = blobs == blobs[iy, ix]
    area = int(blob.sum())
    if area > max_area_fraction * disc_area:
        return None
    # Grow the blob by two pixels so its anti-aliased rim weighs in symmetrically.
    grown = ndimage.binary_dilation(blob, iterations=2) & disc
    wgt = np.clip(crop - body, 0, None) * grown
    total = float(wgt.sum())
    if total <= 0:
        return None
    hx = float((wgt * xx).sum() / total)
    hy = float((wgt * yy).sum() / total)
    # Confidence: contrast against the body, penalised for large or saturated blobs and for
    # highlights on the limb (light nearly behind the sphere: foreshortened, unreliable).
    contrast = (peak - body) / peak
    saturated = int((crop[blob] >= 0.98).sum())
    size_pen = 1.0 - area / (max_area_fraction * disc_area)
    # A flash highlight's core is often clipped; only a clipped area that is large for a
    # mirror highlight suggests a blown-out or non-specular blob.
    sat_pen = 1.0 if saturated <= 0.25 * max_area_fraction * disc_area else 0.5
    rho = np.hypot(hx - cx, hy - cy) / r
    limb_pen = float(np.clip((0.97 - rho) / 0.07, 0.0, 1.0))
    conf = float(np.clip(contrast * (0.5 + 0.5 * size_pen) * sat_pen * limb_pen, 0.0, 1.0))
    if conf <= 0:
        return None
    return hx, hy, conf
