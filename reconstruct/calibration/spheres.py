"""Finding the glossy spheres of a highlight-RTI capture and their outlines to sub-pixel precision.

A sphere is a dark disc in the per-pixel median of the capture (:func:`stack_statistics`) with a
bright trail in the per-pixel maximum (its moving highlight); :func:`detect_spheres` finds such
discs at several thresholds and :func:`refine_circle` fits each outline from its limb profile.
Spheres are (cx, cy, r) in pixels, cx the column and cy the row, pixel centres at integers.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ptmcore.bands import band_rows, run_bands
from ptmcore.errors import InputError
from ptmcore.images import ImageStack
from reconstruct.calibration.reflection import Sphere

__all__ = ["MIN_RADIUS", "check_sphere", "detect_spheres", "fit_circle", "largest_radius", "refine_circle",
           "stack_statistics"]

#: The smallest radius, in pixels, of a sphere whose highlight can be placed: its disc less
#: the anti-aliased limb must hold the highlight and the dark body around it
#: (:mod:`reconstruct.calibration.highlights` looks at no disc of fewer than 10 pixels).
MIN_RADIUS = 4.0


def largest_radius(shape: tuple[int, int]) -> float:
    """The largest radius, in pixels, of a sphere in photographs of ``shape`` (H, W): half
    the shorter side, the largest disc the frame holds."""
    return 0.5 * min(shape)


def check_sphere(sphere: Sphere, shape: tuple[int, int]) -> Sphere:
    """A sphere given by hand, checked against the photographs it is in.

    Parameters
    ----------
    sphere : (cx, cy, r)
        Centre (column, row) and radius in pixels.
    shape : (H, W)
        Size of the photographs.

    Returns
    -------
    (cx, cy, r)
        As floats.

    Raises
    ------
    InputError
        When the values are not three finite numbers, the centre lies outside the
        photographs, or the radius is below :data:`MIN_RADIUS` or above
        :func:`largest_radius`: a highlight looked for on such a disc is some other bright
        spot, or none, and its light would be made up (a radius of 1e9 gave every light as
        0 0 1).
    """
    h, w = shape
    try:
        cx, cy, r = (float(v) for v in sphere)
    except (TypeError, ValueError):
        raise InputError(f"a sphere is three numbers (centre column, row and radius in pixels), got {sphere!r}") from None
    shown = f"({cx:g}, {cy:g}, {r:g})"
    if not np.isfinite([cx, cy, r]).all():
        raise InputError(f"sphere {shown} is not three finite numbers")
    if not (0 <= cx < w and 0 <= cy < h):
        raise InputError(f"sphere {shown}: its centre lies outside the {w}×{h} photographs")
    if not MIN_RADIUS <= r <= largest_radius(shape):
        raise InputError(f"sphere {shown} does not fit the {w}×{h} photographs: its radius must be "
                         f"{MIN_RADIUS:g} to {largest_radius(shape):g} pixels (half the shorter side)")
    return cx, cy, r


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
    rmax = largest_radius((h, w)) if max_radius is None else float(max_radius)
    if np.ptp(median) <= 0:
        raise InputError("no spheres found in the photographs: they have no contrast")

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
        raise InputError("no spheres found in the photographs: no dark round disc with a moving highlight")
    found.sort(key=lambda item: -item[0])
    if expected is not None:
        if len(found) < expected:
            raise InputError(f"found {len(found)} sphere(s) in the photographs but {expected} were expected")
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
        rho = np.hypot(cc - cx0, rr - cy0) / r0
        inside_d = rho < 0.9
        inner_med = float(np.median(median[rr[inside_d], cc[inside_d]]))
        max_inside = maximum[rr[inside_d], cc[inside_d]]
        trail = float(np.percentile(max_inside, 99.5))
        # A glossy sphere's highlight trail is far brighter than its dark body, and it is a
        # trail: most of the disc stays dark in every photograph. A dark patch of a matte
        # surface, shaded in the median, is broadly bright under some light instead.
        if trail < max(4.0 * inner_med, 0.1 * bg_level, 0.05):
            continue
        if trail < 4.0 * float(np.percentile(max_inside, 25)):
            # A broad lobe (a sphere glossy rather than polished) brightens most of the
            # disc at some light, but hardly its rim: lights 15° or more above the object
            # are mirrored by normals within 38° of the view, and the rim's (0.8–0.95 of
            # the radius) are tilted 53°–72°. A matte patch, pit or sphere is lit there as
            # brightly as anywhere (a matte sphere's rim faces the low lights).
            rim = (rho > 0.8) & (rho < 0.95)
            if not rim.any() or trail < 2.5 * float(np.median(maximum[rr[rim], cc[rim]])):
                continue
        found.append((trail / max(inner_med, 1e-4), (cx0, cy0, r0)))
    return found
