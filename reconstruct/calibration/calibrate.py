"""Light directions from the highlights on black glossy spheres ("highlight RTI").

A hand-held flash lights the object from a different direction in each photograph; one or
more black glossy spheres beside the object show a small mirror highlight where the sphere
normal bisects the light and the viewing direction. With an orthographic camera (a distant
lens, view v = (0, 0, 1)) the light follows from the highlight position alone; with a pinhole
camera (:class:`reconstruct.calibration.camera.Intrinsics`, e.g. from EXIF) the view is each
highlight's own ray and the sphere's position comes from its outline
(:func:`reconstruct.calibration.reflection.sphere_centre_3d`).

Coordinates: image positions are (x_img, y_img) = (column, row) with pixel centres at integers;
spheres are (cx, cy, r) in those units. Directions use the project frame: x right, y up,
z towards the camera (so y = (cy − hy)/r, rows go down).

The geometry of the reflection is in :mod:`reconstruct.calibration.reflection`. Near lights (a
flash close to the object) are triangulated from two or more spheres by
:mod:`reconstruct.calibration.triangulate`; here every sphere gives a distant direction, and their
disagreement lowers the confidence.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from ptmcore.atomic import atomic_write
from ptmcore.bands import band_rows, run_bands
from ptmcore.errors import InputError
from ptmcore.images import ImageStack, linear_to_srgb, load_stack
from ptmcore.lp import write_lp
from reconstruct.calibration.camera import Intrinsics
from reconstruct.calibration.reflection import Sphere, light_from_highlight


@dataclass
class Calibration:
    """Light directions read from sphere highlights.

    Attributes
    ----------
    directions : np.ndarray
        (N, 3) unit vectors towards the lights; rows of NaN for unusable photographs.
    confidence : np.ndarray
        (N,) in [0, 1]; 0 for unusable photographs. Lowered when spheres disagree.
    sphere_directions : np.ndarray
        (S, N, 3) the direction each sphere gives (NaN where it has no usable highlight).
    sphere_confidence : np.ndarray
        (S, N) confidence of each sphere's highlight (0 where none).
    highlights : np.ndarray
        (S, N, 2) highlight positions (x_img, y_img) in pixels, NaN where none.
    disagreement_deg : np.ndarray
        (N,) largest angle between any sphere's direction and the combined one (0 for a
        single usable sphere, NaN for unusable photographs).
    spheres : list of (cx, cy, r)
        The spheres used.
    names : list of str
        File names of the photographs, in order.
    flagged : list of str
        Names of the photographs whose direction could not be read (NaN rows).
    intrinsics : Intrinsics or None
        The pinhole camera used for the reflection; None for the orthographic view.
    shape : (H, W) or None
        Size of the photographs in pixels.
    """

    directions: np.ndarray
    confidence: np.ndarray
    sphere_directions: np.ndarray
    sphere_confidence: np.ndarray
    highlights: np.ndarray
    disagreement_deg: np.ndarray
    spheres: list[Sphere]
    names: list[str] = field(default_factory=list)
    flagged: list[str] = field(default_factory=list)
    intrinsics: Intrinsics | None = None
    shape: tuple[int, int] | None = None

    @property
    def view_model(self) -> str:
        """``"orthographic"`` or ``"perspective (fx=…, fy=…, cx=…, cy=… px)"``."""
        k = self.intrinsics
        if k is None:
            return "orthographic"
        return f"perspective (fx={k.fx:.1f}, fy={k.fy:.1f}, cx={k.cx:.1f}, cy={k.cy:.1f} px)"

    @property
    def usable(self) -> np.ndarray:
        """(N,) bool: photographs with a direction."""
        return np.isfinite(self.directions).all(axis=1)


# --------------------------------------------------------------------------- circles


def fit_circle(x: np.ndarray, y: np.ndarray) -> Sphere:
    """Least-squares circle through points: algebraic (Kåsa) fit, then Gauss–Newton.

    The algebraic fit is biased towards small circles on partial arcs; a few geometric
    iterations minimise the true radial distances and remove that bias.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.size < 3:
        raise ValueError("need at least 3 points to fit a circle")
    A = np.column_stack([x, y, np.ones_like(x)])
    b = x * x + y * y
    (a0, a1, a2), *_ = np.linalg.lstsq(A, b, rcond=None)
    cx, cy = a0 / 2.0, a1 / 2.0
    r = np.sqrt(max(a2 + cx * cx + cy * cy, 0.0))
    for _ in range(10):
        dx, dy = x - cx, y - cy
        d = np.hypot(dx, dy)
        d = np.where(d == 0, 1e-12, d)
        J = np.column_stack([-dx / d, -dy / d, -np.ones_like(d)])
        res = d - r
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if np.abs(step).max() < 1e-6:
            break
    return float(cx), float(cy), float(r)


def refine_circle(image: np.ndarray, sphere: Sphere, *, n_rays: int = 360,
                  search: float | None = None) -> Sphere:
    """Sub-pixel sphere outline from the limb's intensity profile.

    Along rays from the centre, each ray's limb is where the profile crosses halfway between
    its own inside and outside levels (the background varies around a sphere, so one global
    level would move the edge); a robust circle fit of those points follows.

    Parameters
    ----------
    image : np.ndarray
        (H, W) linear grey image in which the sphere is dark (e.g. the stack median).
    sphere : (cx, cy, r)
        Starting estimate, good to a few pixels.
    n_rays : int
        Number of rays.
    search : float, optional
        Half-width of the radial search band in pixels; default max(4, 0.15 r).

    Returns
    -------
    (cx, cy, r)
    """
    cx, cy, r = sphere
    search = max(4.0, 0.15 * r) if search is None else search
    step = 0.25
    t = np.arange(-search, search + step / 2, step)
    theta = np.linspace(0.0, 2 * np.pi, n_rays, endpoint=False)
    radii = r + t  # (T,)
    xs = cx + np.cos(theta)[:, None] * radii[None, :]
    ys = cy + np.sin(theta)[:, None] * radii[None, :]
    prof = ndimage.map_coordinates(image, [ys.ravel(), xs.ravel()], order=1,
                                   mode="nearest").reshape(xs.shape)
    edge = max(2, len(t) // 6)
    inside = np.median(prof[:, :edge], axis=1)
    outside = np.median(prof[:, -edge:], axis=1)
    level = 0.5 * (inside + outside)
    contrast = outside - inside
    above = prof >= level[:, None]
    # First sample above the level, scanning outwards; the crossing is interpolated between
    # it and the sample before.
    first = np.argmax(above, axis=1)
    ok = (contrast > 0.02 * max(float(np.median(outside)), 1e-6)) & (first > 0) & above.any(1)
    i1 = np.clip(first, 1, len(t) - 1)
    rows = np.arange(n_rays)
    p0, p1 = prof[rows, i1 - 1], prof[rows, i1]
    frac = np.clip((level - p0) / np.where(p1 - p0 == 0, 1e-12, p1 - p0), 0, 1)
    rad = radii[i1 - 1] + frac * step
    ok &= np.isfinite(rad)
    if ok.sum() < 12:
        return sphere
    ex = cx + np.cos(theta[ok]) * rad[ok]
    ey = cy + np.sin(theta[ok]) * rad[ok]
    fit = fit_circle(ex, ey)
    # Rays that hit something else dark (a shadow, the object) give outliers; drop them.
    for _ in range(3):
        res = np.hypot(ex - fit[0], ey - fit[1]) - fit[2]
        mad = np.median(np.abs(res - np.median(res))) + 1e-3
        keep = np.abs(res) < max(4.0 * 1.4826 * mad, 0.3)
        if keep.sum() < 12 or keep.all():
            break
        ex, ey = ex[keep], ey[keep]
        fit = fit_circle(ex, ey)
    return fit


def stack_statistics(stack: ImageStack) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel median and maximum of a stack's linear luminance, in bands of rows."""
    h, w = stack.shape
    median = np.empty((h, w), dtype=np.float32)
    maximum = np.empty((h, w), dtype=np.float32)

    def work(r0: int, r1: int) -> None:
        values, _ = stack.band(r0, r1)
        median[r0:r1] = np.median(values, axis=0)
        maximum[r0:r1] = values.max(axis=0)

    run_bands(h, band_rows(len(stack), w), work)
    return median, maximum


def _sphere_crops(stack: ImageStack, sphere: Sphere) -> tuple[np.ndarray, int, int]:
    """Every photograph's linear luminance in the sphere's bounding box, and the box's corner.

    Only these few thousand pixels per photograph are needed to find highlights, so the
    whole stack is never converted to float.
    """
    h, w = stack.shape
    cx, cy, r = sphere
    x0, x1 = max(0, int(cx - r) - 2), min(w, int(np.ceil(cx + r)) + 3)
    y0, y1 = max(0, int(cy - r) - 2), min(h, int(np.ceil(cy + r)) + 3)
    values, _ = stack.band(y0, y1, x0, x1)
    return values, x0, y0


def detect_spheres(
    median: np.ndarray,
    maximum: np.ndarray,
    *,
    expected: int | None = None,
    min_radius: float | None = None,
    max_radius: float | None = None,
) -> list[Sphere]:
    """Find the dark glossy spheres from a capture's per-pixel statistics.

    A sphere is a dark disc in the per-pixel median (the moving highlight is absent from
    most photographs) whose per-pixel maximum shows a bright trail (the highlight moved over
    it). Candidates are the dark regions (Otsu threshold of the median, holes filled), kept
    when their size is in the radius range, they are round (area close to that of the
    fitted circle) and their maximum is bright; each new one (not already found at another
    threshold) is then refined to sub-pixel precision from the limb profile
    (:func:`refine_circle`).

    Parameters
    ----------
    median, maximum : np.ndarray
        (H, W) linear grey per-pixel median and maximum (see :func:`stack_statistics`).
    expected : int, optional
        Number of spheres to return (the most convincing); InputError if fewer are found.
    min_radius, max_radius : float, optional
        Radius range in pixels; default 2 % to 50 % of the shorter image side.

    Returns
    -------
    list of (cx, cy, r)
        Sorted left to right.

    Raises
    ------
    InputError
        If no sphere (or fewer than ``expected``) is found.
    """
    from skimage.measure import label

    median = np.asarray(median, dtype=np.float32)
    maximum = np.asarray(maximum, dtype=np.float32)
    if median.ndim != 2 or median.shape != maximum.shape:
        raise InputError("median and maximum must be (H, W) images of the same size")
    h, w = median.shape
    side = min(h, w)
    rmin = max(6.0, 0.02 * side) if min_radius is None else float(min_radius)
    rmax = 0.5 * side if max_radius is None else float(max_radius)
    if np.ptp(median) <= 0:
        raise InputError("no spheres found: the photographs have no contrast")

    found: list[tuple[float, Sphere]] = []
    for level in _dark_levels(median):
        dark = median < level
        dark = ndimage.binary_opening(dark, iterations=2)
        dark = ndimage.binary_fill_holes(dark)
        bg_level = float(np.median(median[~dark])) if (~dark).any() else float(median.max())
        for score, rough in _round_dark_discs(median, maximum, label(dark), bg_level,
                                              rmin, rmax):
            # The same sphere is found at several levels: refine only the new ones.
            if _seen(rough, found):
                continue
            cx, cy, r = refine_circle(median, rough)
            if rmin <= r <= rmax and abs(r - rough[2]) < 0.2 * rough[2] and not _seen((cx, cy, r), found):
                found.append((score, (cx, cy, r)))
    if not found:
        raise InputError("no spheres found: no dark round disc with a moving highlight "
                         "(pass the spheres explicitly if they are there)")
    found.sort(key=lambda item: -item[0])
    if expected is not None:
        if len(found) < expected:
            raise InputError(f"found {len(found)} sphere(s) but {expected} were expected")
        found = found[:expected]
    return sorted((s for _, s in found), key=lambda s: (s[0], s[1]))


def _seen(sphere: Sphere, found: list[tuple[float, Sphere]]) -> bool:
    """Whether ``sphere``'s centre lies within half a radius of one already found."""
    return any(np.hypot(sphere[0] - s[0], sphere[1] - s[1]) <= 0.5 * min(sphere[2], s[2])
               for _, s in found)


def _dark_levels(median: np.ndarray, count: int = 6) -> np.ndarray:
    """Thresholds at which to look for dark discs in the median image.

    One global threshold fails when the background has patches nearly as dark as the
    spheres (a textured or shadowed object): at Otsu's level they touch a sphere and its
    region is no longer round. Black spheres are darker than almost anything else by a
    ratio, so thresholds are also taken on a geometric scale, from twice the darkest levels
    up to the larger of Otsu's thresholds on the linear and on the logarithmic values;
    a sphere is round at some of them.
    """
    from skimage.filters import threshold_otsu

    positive = median[median > 0]
    floor = float(np.percentile(positive, 0.1)) if positive.size else 1e-6
    linear = float(threshold_otsu(median))
    log = float(np.exp(threshold_otsu(np.log(np.maximum(median, max(floor, 1e-6))))))
    top = max(linear, log)
    low = min(max(2.0 * floor, 1e-6), top)
    return np.unique(np.concatenate([[linear], np.geomspace(low, top, count)]))


def _round_dark_discs(median: np.ndarray, maximum: np.ndarray, labels: np.ndarray,
                      bg_level: float, rmin: float, rmax: float
                      ) -> list[tuple[float, Sphere]]:
    """(score, rough (cx, cy, r)) of the labelled regions that look like glossy spheres."""
    from skimage.measure import regionprops

    found = []
    for region in regionprops(labels):
        r0 = np.sqrt(region.area / np.pi)
        if not rmin * 0.8 <= r0 <= rmax * 1.2:
            continue
        # Roundness: a disc fills its bounding box by π/4 and is nearly convex.
        minr, minc, maxr, maxc = region.bbox
        bw, bh = maxc - minc, maxr - minr
        if region.solidity < 0.9 or not 0.8 < bw / max(bh, 1) < 1.25:
            continue
        if abs(region.area / (bw * bh) - np.pi / 4) > 0.08:
            continue
        cy0, cx0 = region.centroid
        rr, cc = region.coords[:, 0], region.coords[:, 1]
        inside_d = np.hypot(cc - cx0, rr - cy0) < 0.9 * r0
        inner_med = float(np.median(median[rr[inside_d], cc[inside_d]]))
        max_inside = maximum[rr[inside_d], cc[inside_d]]
        trail = float(np.percentile(max_inside, 99.5))
        # A glossy sphere's highlight trail is far brighter than its dark body, and it is a
        # trail: most of the disc stays dark in every photograph. A dark patch of a matte
        # surface, shaded in the median, is broadly bright under some light instead.
        if trail < max(4.0 * inner_med, 0.1 * bg_level, 0.05):
            continue
        if trail < 4.0 * float(np.percentile(max_inside, 25)):
            continue
        found.append((trail / max(inner_med, 1e-4), (cx0, cy0, r0)))
    return found


# --------------------------------------------------------------------------- highlights


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
    return _highlights(img[None], sphere, min_peak=min_peak,
                       max_area_fraction=max_area_fraction)[0]


def _highlights(images: np.ndarray, sphere: Sphere, *, min_peak: float = 0.15,
                max_area_fraction: float = 0.02) -> list[tuple[float, float, float] | None]:
    """:func:`find_highlight` on each of (N, H, W) float32 images of the same sphere.

    The disc and the pixel grid are built once; the disc's peak and median are taken for
    all images at once, and only images with a candidate highlight are labelled.
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


# --------------------------------------------------------------------------- calibration


def calibration_camera(
    photograph: str | os.PathLike,
    shape: tuple[int, int],
    *,
    intrinsics: str | Intrinsics | None = None,
    focal_mm: float | None = None,
    sensor_width_mm: float | None = None,
    exif: bool = False,
) -> Intrinsics | None:
    """The camera model for :func:`calibrate` from whichever description the user gave.

    At most one of: ``intrinsics`` (an :class:`Intrinsics` or ``"fx,fy,cx,cy"`` in
    pixels), ``focal_mm`` with ``sensor_width_mm`` (square pixels, principal point at the
    image centre; :meth:`Intrinsics.from_focal`), or ``exif`` (read from ``photograph``'s
    EXIF by :func:`reconstruct.calibration.camera.intrinsics_from_exif`). None of them: None, the
    orthographic view.

    Parameters
    ----------
    photograph : str or PathLike
        One photograph of the capture, whose EXIF is read with ``exif``.
    shape : (H, W)
        Size of the photographs in pixels (e.g. ``ImageStack.shape``).
    intrinsics, focal_mm, sensor_width_mm, exif
        See above.

    Returns
    -------
    Intrinsics or None

    Raises
    ------
    InputError
        Two descriptions at once, a focal length without a sensor width (or the reverse),
        non-positive or non-numeric values, or ``exif`` on a photograph without the tags.
    """
    from reconstruct.calibration.camera import intrinsics_from_exif, parse_intrinsics

    lens = focal_mm is not None or sensor_width_mm is not None
    if sum([intrinsics is not None, lens, bool(exif)]) > 1:
        raise InputError("give the camera one way only: intrinsics, focal length with sensor "
                         "width, or EXIF")
    if isinstance(intrinsics, str):
        try:
            return parse_intrinsics(intrinsics)
        except ValueError as exc:
            raise InputError(f"--intrinsics: {exc}") from None
    if intrinsics is not None:
        return intrinsics
    if exif:
        camera = intrinsics_from_exif(photograph)
        if camera is None:
            raise InputError("the EXIF has no focal length with sensor resolution or 35 mm "
                             "equivalent; give the focal length and sensor width instead",
                             photograph)
        return camera
    if not lens:
        return None
    if focal_mm is None or sensor_width_mm is None:
        raise InputError("a focal length needs the sensor width too (and the reverse)")
    height, width = shape
    try:
        return Intrinsics.from_focal(float(focal_mm), float(sensor_width_mm), width, height)
    except (TypeError, ValueError) as exc:
        raise InputError(f"bad focal length or sensor width: {exc}") from None


def calibrate_stack(
    stack: ImageStack,
    *,
    spheres: list[Sphere] | None = None,
    expected: int | None = None,
    names: list[str] | None = None,
    min_confidence: float = 0.2,
    disagreement_tol_deg: float = 5.0,
    intrinsics: Intrinsics | None = None,
) -> Calibration:
    """Calibrate from a decoded capture (:func:`ptmcore.load_stack`); see :func:`calibrate`."""
    n = len(stack)
    names = [p.name for p in stack.paths] if names is None else list(names)
    if spheres is None:
        if n < 3:
            raise InputError("need at least 3 photographs to detect the spheres; "
                             "pass the spheres explicitly for fewer")
        spheres = detect_spheres(*stack_statistics(stack), expected=expected)
    else:
        spheres = [tuple(float(v) for v in s) for s in spheres]
        h, w = stack.shape
        for s in spheres:
            if len(s) != 3 or not np.isfinite(s).all() or s[2] <= 0:
                raise InputError(f"a sphere must be (cx, cy, r) with r > 0, got {s!r}")
            if not (0 <= s[0] < w and 0 <= s[1] < h):
                raise InputError(f"sphere centre ({s[0]}, {s[1]}) lies outside the "
                                 f"{w}×{h} image")
        if not spheres:
            raise InputError("the list of spheres is empty")
    m = len(spheres)
    sdirs = np.full((m, n, 3), np.nan)
    sconf = np.zeros((m, n))
    hl = np.full((m, n, 2), np.nan)
    for i, sph in enumerate(spheres):
        crops, x0, y0 = _sphere_crops(stack, sph)
        local = (sph[0] - x0, sph[1] - y0, sph[2])
        for k, found in enumerate(_highlights(crops, local)):
            if found is not None:
                hl[i, k] = found[0] + x0, found[1] + y0
                sconf[i, k] = found[2]
        seen = np.isfinite(hl[i, :, 0])
        if seen.any():
            sdirs[i, seen] = light_from_highlight(hl[i, seen, 0], hl[i, seen, 1], sph,
                                                  intrinsics)

    # Combine spheres per photograph: confidence-weighted mean of unit vectors.
    wts = np.where(np.isfinite(sdirs).all(-1), sconf, 0.0)  # (M, N)
    summed = np.einsum("mn,mnc->nc", wts, np.nan_to_num(sdirs))
    norm = np.linalg.norm(summed, axis=1)
    has = wts.sum(0) > 0
    combined = np.full((n, 3), np.nan)
    combined[has] = summed[has] / norm[has, None]
    cosang = np.einsum("mnc,nc->mn", np.nan_to_num(sdirs), np.nan_to_num(combined))
    ang = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    ang = np.where(wts > 0, ang, 0.0)
    # With one sphere there is nothing to disagree with (and arccos near 1 is only rounding).
    disagree = np.where(has, np.where((wts > 0).sum(0) >= 2, ang.max(0), 0.0), np.nan)
    mean_conf = np.where(has, wts.sum(0) / np.maximum((wts > 0).sum(0), 1), 0.0)
    # Spheres that disagree mean a bad highlight or a near light; either way trust it less.
    conf = mean_conf * np.clip(1.0 - np.nan_to_num(disagree) / disagreement_tol_deg, 0, 1)
    bad = ~has | (conf < min_confidence)
    combined[bad] = np.nan
    conf = np.where(bad, 0.0, conf)
    flagged = [names[k] for k in np.flatnonzero(bad)]
    return Calibration(directions=combined, confidence=conf, sphere_directions=sdirs,
                       sphere_confidence=sconf, highlights=hl, disagreement_deg=disagree,
                       spheres=[tuple(s) for s in spheres], names=names, flagged=flagged,
                       intrinsics=intrinsics, shape=stack.shape)


def calibrate(
    paths: list[str | os.PathLike],
    *,
    spheres: list[Sphere] | None = None,
    expected: int | None = None,
    min_confidence: float = 0.2,
    disagreement_tol_deg: float = 5.0,
    intrinsics: Intrinsics | None = None,
) -> Calibration:
    """Light directions of a highlight-RTI capture from its glossy spheres.

    Parameters
    ----------
    paths : list of str or PathLike
        The photographs (JPEG, PNG, TIFF; 8-bit is decoded from sRGB).
    spheres : list of (cx, cy, r), optional
        Known spheres in pixels (cx = column, cy = row); detected when omitted.
    expected : int, optional
        Number of spheres to detect.
    min_confidence : float
        Photographs whose combined confidence is lower are flagged (NaN direction).
    disagreement_tol_deg : float
        Angle between spheres' directions at which the confidence drops to 0.
    intrinsics : Intrinsics, optional
        Pinhole camera (see :func:`reconstruct.calibration.camera.intrinsics_from_exif` and
        :meth:`~reconstruct.calibration.camera.Intrinsics.from_focal`): the reflection then uses
        each highlight's own view ray (:func:`light_from_highlight`). None: orthographic
        view, right for long lenses.

    Returns
    -------
    Calibration

    Raises
    ------
    InputError
        Missing or unreadable photographs, mismatched sizes, no spheres found.
    """
    paths = [Path(p) for p in paths]
    stack = load_stack(paths, min_photographs=1)
    return calibrate_stack(stack, spheres=spheres, expected=expected,
                           min_confidence=min_confidence,
                           disagreement_tol_deg=disagreement_tol_deg, intrinsics=intrinsics)


def write_calibration_lp(path: str | os.PathLike, calibration: Calibration,
                         names: list[str] | None = None) -> int:
    """Write an ``.lp`` file of the usable photographs only.

    Parameters
    ----------
    path : str or PathLike
        Destination.
    calibration : Calibration
        Result of :func:`calibrate`.
    names : list of str, optional
        Names to write (relative to the ``.lp`` file's folder); default the calibration's.

    Returns
    -------
    int
        Number of photographs written.
    """
    names = calibration.names if names is None else list(names)
    if len(names) != len(calibration.directions):
        raise InputError(f"{len(names)} names for {len(calibration.directions)} photographs")
    ok = calibration.usable
    if not ok.any():
        raise InputError("no photograph has a usable light direction", path)
    write_lp(path, [nm for nm, u in zip(names, ok) if u], calibration.directions[ok])
    return int(ok.sum())


def write_diagnostic(path: str | os.PathLike, image: np.ndarray, calibration: Calibration,
                     k: int) -> None:
    """A PNG of photograph ``k`` with the sphere outlines and the highlights found.

    Outlines are green; a found highlight is a red cross; a sphere without a usable
    highlight in this photograph gets a yellow outline instead. The view model used
    (:attr:`Calibration.view_model`) is written in the top-left corner.
    """
    from PIL import Image, ImageDraw

    img = np.asarray(image)
    if img.dtype == np.uint8:
        rgb = img
    else:
        # 16-bit and float photographs are linear (ptmcore.images.read_image): encode them
        # as sRGB, as a viewer would show them, or they look far too dark.
        v = img.astype(np.float32)
        if img.dtype == np.uint16:
            v = v / 65535.0
        rgb = (linear_to_srgb(v) * 255 + 0.5).astype(np.uint8)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    pil = Image.fromarray(np.ascontiguousarray(rgb[..., :3]))
    draw = ImageDraw.Draw(pil)
    draw.text((3, 2), f"{calibration.view_model} view", fill=(255, 255, 255))
    for i, (cx, cy, r) in enumerate(calibration.spheres):
        hx, hy = calibration.highlights[i, k]
        colour = (0, 255, 0) if np.isfinite(hx) else (255, 255, 0)
        draw.ellipse([cx - r, cy - r, cx + r, cy + r], outline=colour, width=1)
        draw.line([cx - 3, cy, cx + 3, cy], fill=colour)
        draw.line([cx, cy - 3, cx, cy + 3], fill=colour)
        if np.isfinite(hx):
            a = max(4.0, 0.08 * r)
            draw.line([hx - a, hy, hx + a, hy], fill=(255, 0, 0), width=1)
            draw.line([hx, hy - a, hx, hy + a], fill=(255, 0, 0), width=1)
    with atomic_write(path, "wb") as f:
        pil.save(f, format="PNG")
