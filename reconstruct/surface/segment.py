"""Automatic foreground segmentation of the photographed object from its albedo and normals.

The object (a tablet, coin or relief) lies on a background such as a cloth or a table. Two
cues separate them, and either may be weak on its own:

* **albedo contrast**: the object's colour differs from the background's. The background
  colour is taken from a strip along the frame's border.
* **normal deviation**: the background is a flat plane facing the camera, n ≈ (0, 0, 1),
  while the object has slopes (rims, reliefs). A flat object top deviates little, but the
  rim around it usually closes a ring that hole filling turns into the whole object.

Each cue is measured in units of its own spread over the border strip (a robust z-score), so
neither needs a hand-set scale; the per-pixel maximum of the two is thresholded with Otsu's
method and cleaned up with morphology.

Assumptions, and when it fails
------------------------------
* Most of the frame's border shows background. Objects may touch or cross the frame, but if
  the object covers most of the border the "background" statistics describe the object and
  the mask comes out inverted or empty.
* The background is roughly uniform in colour and flat. A strongly patterned or creased
  cloth, a vignetted or unevenly lit background (after photometric stereo this shows up as
  albedo gradients) raises its spread and can hide a low-contrast object.
* An object of the background's colour *and* without slopes (e.g. a flat, polished coin on
  a matching cloth) cannot be found from these cues.
* Holes are filled only where they are enclosed within the frame: a hole open to the frame's
  edge is indistinguishable from background.
* Components smaller than ``min_fraction`` of the largest are dropped, so several fragments
  photographed together are kept only if they are of similar size.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage import filters, measure, morphology

__all__ = ["foreground_mask"]

_METHODS = ("auto", "albedo", "normals")
# Floors on the background spread, so a noiseless synthetic background does not turn every
# tiny colour or angle difference into a huge z-score: 2 % relative colour, 2 degrees.
_ALBEDO_FLOOR = 0.02
_ANGLE_FLOOR_DEG = 2.0
# Below this contrast (in background spreads) nothing stands out: the image is uniform.
_MIN_CONTRAST = 6.0


def _border_strip(shape: tuple[int, int], width: int) -> np.ndarray:
    """Boolean mask of a strip ``width`` pixels wide along the frame's four edges."""
    strip = np.zeros(shape, dtype=bool)
    strip[:width], strip[-width:], strip[:, :width], strip[:, -width:] = True, True, True, True
    return strip


def _robust_z(feature: np.ndarray, reference: np.ndarray, floor: float) -> np.ndarray:
    """Deviation of ``feature`` above the reference pixels' median, in units of their spread."""
    median = np.median(reference)
    # 1.4826·MAD estimates a normal distribution's sigma but ignores the few object pixels
    # that may cross the border strip.
    spread = 1.4826 * np.median(np.abs(reference - median))
    return (feature - median) / max(float(spread), floor)


def _albedo_score(albedo: np.ndarray, strip: np.ndarray) -> np.ndarray:
    """Robust z-score of each pixel's relative colour distance from the border colour."""
    border = np.median(albedo[strip], axis=0)
    # Relative distance, so the score does not depend on the exposure or albedo scale.
    scale = max(float(np.linalg.norm(border)), 1e-6)
    distance = np.linalg.norm(albedo - border, axis=-1) / scale
    return _robust_z(distance, distance[strip], _ALBEDO_FLOOR)


def _normal_score(normals: np.ndarray, strip: np.ndarray) -> np.ndarray:
    """Robust z-score of each pixel's tilt away from the camera axis, in degrees."""
    norm = np.linalg.norm(normals, axis=-1)
    nz = np.where(norm > 0, normals[..., 2] / np.where(norm > 0, norm, 1.0), 1.0)
    tilt = np.degrees(np.arccos(np.clip(nz, -1.0, 1.0)))
    return _robust_z(tilt, tilt[strip], _ANGLE_FLOOR_DEG)


def _keep_large_components(mask: np.ndarray, min_fraction: float) -> np.ndarray:
    """Keep the connected components at least ``min_fraction`` of the largest one's area."""
    labels = measure.label(mask, connectivity=2)
    if labels.max() == 0:
        return mask
    areas = np.bincount(labels.ravel())
    areas[0] = 0
    keep = areas >= min_fraction * areas.max()
    keep[0] = False
    return keep[labels]


def foreground_mask(
    albedo_rgb: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    method: str = "auto",
    border_fraction: float = 0.03,
    min_fraction: float = 0.2,
    smooth_px: float | None = None,
) -> np.ndarray:
    """Segment the photographed object from the background.

    Parameters
    ----------
    albedo_rgb : np.ndarray
        (H, W, 3) albedo or mean colour, any scale (linear RGB preferred). A (H, W) grey
        albedo is accepted too. NaN counts as background colour.
    normals : np.ndarray, optional
        (H, W, 3) normals (x right, y up, z towards the camera); need not be unit length.
        NaN or zero vectors count as facing the camera.
    method : {"auto", "albedo", "normals"}
        Cues to use: "auto" takes the per-pixel maximum of both (albedo alone when
        ``normals`` is None); the others use one cue only.
    border_fraction : float
        Width of the border strip that samples the background, as a fraction of the shorter
        side (at least 2 pixels).
    min_fraction : float
        Components smaller than this fraction of the largest are dropped; 1 keeps only the
        largest.
    smooth_px : float, optional
        Scale of the outline smoothing and of the morphological clean-up, in pixels; default
        1 % of the shorter side (at least 1.5). Details of the outline smaller than this are
        lost.

    Returns
    -------
    np.ndarray
        (H, W) bool, True on the object.

    Raises
    ------
    ValueError
        For bad shapes or options, or when nothing stands out from the background (a uniform
        image, or an object that fills the whole frame). A uniform image raises rather than
        returning the whole frame so that a failed segmentation is never silent; callers that
        want "everything" then can use ``np.ones(shape, bool)`` deliberately.

    Notes
    -----
    The score of a pixel is ``max(z_albedo, z_normal)``, each a robust z-score against the
    border strip; the threshold is Otsu's on the scores of a lightly blurred score map, but
    never below 3 background spreads so noise alone is not called object. The binary mask
    is closed (bridges a rim broken by shadows), hole-filled, opened (removes specks and
    spurs), reduced to its large components, and its outline is smoothed by blurring and
    re-thresholding at one half. See the module docstring for the assumptions.
    """
    albedo = np.asarray(albedo_rgb, dtype=np.float32)
    if albedo.ndim == 2:
        albedo = albedo[..., None]
    if albedo.ndim != 3 or albedo.shape[2] not in (1, 3):
        raise ValueError(f"albedo_rgb must be (H, W, 3) or (H, W), got shape {albedo.shape}")
    shape = albedo.shape[:2]
    if min(shape) < 8:
        raise ValueError(f"image must be at least 8×8 pixels, got {shape}")
    if method not in _METHODS:
        raise ValueError(f"method must be one of {', '.join(_METHODS)}, got {method!r}")
    if method == "normals" and normals is None:
        raise ValueError('method="normals" needs the normals')
    if not 0 < min_fraction <= 1:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")

    width = max(2, round(border_fraction * min(shape)))
    strip = _border_strip(shape, width)
    scores = []
    if method in ("auto", "albedo"):
        border_colour = np.nanmedian(albedo[strip], axis=0)
        albedo = np.where(np.isfinite(albedo), albedo, border_colour)
        scores.append(_albedo_score(albedo, strip))
    if normals is not None and method in ("auto", "normals"):
        nrm = np.asarray(normals, dtype=np.float32)
        if nrm.shape != (*shape, 3):
            raise ValueError(f"normals must have shape {(*shape, 3)}, got {nrm.shape}")
        nrm = np.where(np.isfinite(nrm), nrm, np.float32(0.0))
        scores.append(_normal_score(nrm, strip))
    score = np.maximum.reduce(scores) if len(scores) > 1 else scores[0]

    radius = smooth_px if smooth_px is not None else max(1.5, 0.01 * min(shape))
    # A light blur makes the score of noisy photometric-stereo output less speckled before
    # thresholding, without moving edges by more than the smoothing scale.
    score = ndimage.gaussian_filter(score, 0.5 * radius)
    if float(score.max()) < _MIN_CONTRAST:
        raise ValueError(
            "no object stands out from the background (uniform image, or an object covering "
            "the whole frame and its border); pass an explicit mask instead")
    # Otsu on scores clipped to a high percentile: a few extreme scores (specular glints,
    # deep shadows) would otherwise drag the threshold up into the object.
    clipped = np.minimum(score, np.percentile(score, 99.5))
    threshold = max(float(filters.threshold_otsu(clipped)), 3.0)
    mask = score > threshold

    r = max(1, round(radius))
    disk = morphology.disk(r)
    # Padding by edge replication lets closing and opening treat an object that runs off the
    # frame as continuing beyond it, instead of eroding it along the frame's edge.
    pad = 2 * r
    padded = np.pad(mask, pad, mode="edge")
    padded = ndimage.binary_closing(padded, structure=disk)
    padded = ndimage.binary_opening(padded, structure=disk)
    mask = ndimage.binary_fill_holes(padded[pad:-pad, pad:-pad])
    mask = ndimage.binary_opening(mask, structure=disk)
    mask = _keep_large_components(mask, min_fraction)
    # Blurring and re-thresholding at one half removes staircase and single-pixel jags while
    # keeping the area (a straight edge does not move).
    mask = ndimage.gaussian_filter(mask.astype(np.float32), radius, mode="nearest") > 0.5
    if not mask.any():
        raise ValueError("segmentation left no object; pass an explicit mask instead")
    return mask
