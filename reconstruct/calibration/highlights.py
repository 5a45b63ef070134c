"""The specular highlight on a glossy sphere: the point whose normal bisects light and view.

:func:`find_highlight` looks in one grey image; :func:`find_highlights` in the crops of every
photograph around one sphere at once; :func:`sphere_highlights` around several spheres lit by the
same lights, as the calibration does. Positions are (x_img, y_img) = (column, row) with pixel
centres at integers.

The estimate is a mean taken in the sphere's normal space, not in the image. A specular lobe
(Phong, Blinn–Phong, or a Gaussian in the angle between n and h, as in Ward's or Beckmann's
models) is a function of the angle between the sphere normal n and the half vector h of light
and view, or at least symmetric about h (Phong's r·v is unchanged when light and view swap).
Spread over the *unit sphere of normals, per solid angle*, its mass is therefore centred on h
whatever its width, and the normalised mean normal is h. In the image the same lobe is
foreshortened: a pixel covers a solid angle of normals ∝ 1/(n·v), and image position goes as
sin θ of the normal's tilt θ, so an intensity-weighted centroid of pixels is pulled towards the
disc's centre, by about 3σ² tan θ_h of light direction for a lobe of angular width σ (about a
degree for a Blinn–Phong exponent of 50 and a light 20° above the horizon,
``benchmarks/calibration.py``). Here every pixel of the highlight weighs in with its normal, its
excess intensity and the solid angle of normals it covers: the first moment of the lobe on the
sphere, the mean direction of directional statistics (Mardia & Jupp, *Directional Statistics*,
2000, §9.2) taken on the reflectance map of a sphere (Horn, *Robot Vision*, 1986, ch. 10).

What keeps the estimate free of the lobe's shape, width and clipping:

- the weights are the excess over a level set at a fixed fraction of the highlight's height
  (:data:`REGION_LEVEL`), a monotone function of intensity, so a symmetric lobe gives a
  symmetric weight, even when its core is clipped by the sensor (the excess is cut at its
  lowest value on a clipped pixel, a level every pixel's value is known to reach or not);
- the region is that level's connected set around the peak, symmetric about h for the same
  reason, instead of a blob grown by a number of pixels (which covers more normals near the
  limb than near the centre);
- the sphere's own diffuse shading kd·max(0, n·l), brighter towards the light, is fitted with
  an ambient level on the disc away from the highlight and subtracted before the mean (left
  in, it drags the mean towards the light, the more so the broader the lobe).

Each pixel's solid angle is that of the spherical quad its four corners map to.

With a pinhole camera (``intrinsics``) each pixel i has its own view v_i. Its normal is mapped
to n'_i = h(l_i, v_C), the normal that would reflect the same light l_i = 2(n_i·v_i)n_i − v_i
into one common view v_C (towards the sphere's centre): the lobe, a function of the angle
between n_i and h(l, v_i), is in these mapped normals a function of the angle between n'_i and
h(l, v_C) (exactly so when the lights and views lie in one plane: both angles are then half the
angle between l_i and l), so the mean of the mapped normals, weighted by their own solid
angles, is again h(l, v_C) and l its mirror. The position returned is the point of the sphere
that mirrors l into the camera, so
:func:`reconstruct.calibration.reflection.light_from_highlight` turns it back into l,
orthographic or not.

The lobe times (n·l)^q. Classic Phong and Blinn–Phong shading, and
:func:`data_synthetic.render.render`, take the lobe g to be the specular radiance (q = 0); a
physically based renderer multiplies a BRDF by the cosine of the light's incidence (Nicodemus
et al., *Geometrical Considerations and Nomenclature for Reflectance*, NBS 1977; Kajiya's
rendering equation, 1986), so that the radiance is g(n·h)·(n·l) (q = 1). The factor tilts the
lobe towards the light and the mean of normals follows it, by about σ² tan θ_h of normal for a
lobe of width σ: 1.6° of light direction for a Blinn–Phong exponent of 50 at 20° elevation, 5°
for 15. In one highlight the tilt cannot be told from a move of h (a Gaussian times an
exponential is a shifted Gaussian), but the factor also scales the lobe's height at the mirror
point by (n*·l)^q, n*·l = cos of half the angle between light and view: a light at 20° gives a
highlight 18 % dimmer than one overhead when q = 1, as bright when q = 0. So q is estimated
from all the highlights of a capture (:func:`sphere_highlights`): each highlight's log height is
fitted on its pixels, the heights are regressed on log(n*·l) with one intercept per sphere, and
the slope is q, shrunk towards ½ by its standard error and kept in [0, :data:`MAX_LOBE_COSINE`];
every pixel's excess is then divided by (n·l/n*·l)^q before the mean (a few rounds: the light
follows the mean). The same q that dims the highlights tilts them, so q above 1 is taken as
the data show it: an 8-bit image written from linear values without the sRGB curve, then
decoded as sRGB, raises the radiance to the power 2.2, and a lobe × n·l reads as q ≈ 2.2.
This assumes lights of equal power, as a generator's are: the scatter of unequal powers widens
the slope's error and moves q towards ½, which halves the worst case. A microfacet model's
1/(n·v) tilts the lobe the same way but brightens low lights' highlights instead; it is read
as q = 0 and its tilt is left in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ptmcore.errors import InputError
from reconstruct.calibration.camera import Intrinsics
from reconstruct.calibration.reflection import (
    Sphere,
    mirror,
    sphere_centre_3d,
    sphere_normal_at,
    sphere_normal_through,
)

#: Through a pinhole a sphere's outline is an ellipse a few per cent longer than its mean
#: radius: its pixels are looked for this many radii from the centre.
PINHOLE_REACH = 1.1

__all__ = ["MAX_LOBE_COSINE", "PINHOLE_REACH", "REGION_LEVEL", "SATURATION", "find_highlight", "find_highlights",
           "sphere_highlights"]

#: The highlight's region is where the excess over the background exceeds this fraction of
#: the peak's; each pixel weighs in with its excess above that level.
REGION_LEVEL = 0.25

#: A blob whose graded rim (excess between REGION_LEVEL and 90 % of the peak) covers less
#: than this fraction of the solid angle of its plateau has a step edge: a blown-out patch
#: rather than a lobe.
_STEP_EDGE = 0.25

#: Linear values at or above this are taken as clipped by the sensor.
SATURATION = 0.98

#: Pixels whose excess is above this fraction of the peak's are kept for the estimate of q
#: (dividing by (n·l/n*·l)^q lifts a highlight's pixels by less than 2.5× unless the lobe
#: reaches the terminator, so its region stays among them).
_KEEP_LEVEL = 0.1

#: n·l is taken as at least this when dividing by it (a lobe reaching the terminator).
_MIN_COSINE = 0.05

#: Rounds of (light from the normal, normal from the divided lobe) for a given q.
_SETTLE = 3

#: Rounds of (q from the heights, normals for q) at most.
_Q_ROUNDS = 4

#: Largest q estimated or accepted (see the module's notes: 2.2 for a lobe × n·l written
#: without the sRGB curve).
MAX_LOBE_COSINE = 3.0

#: Gaussian prior on q: the two conventions are equally likely.
_PRIOR_Q, _PRIOR_SD = 0.5, 0.5

#: Floor on the spread of a highlight's log height (1 %), for what the fit's variance misses.
_LOG_FLOOR = 0.01


@dataclass(frozen=True)
class _Disc:
    """One sphere's pixels in the images, with the geometry of the reflection they see.

    Attributes
    ----------
    rows, cols : slice
        The sphere's bounding box in the images.
    inside : ndarray, shape (h, w), bool
        The pixels used: the sphere without its anti-aliased limb. The arrays below hold
        one row per such pixel, in ``np.nonzero`` order.
    normals : ndarray, shape (M, 3)
        The sphere's normal seen at each pixel (for its diffuse shading).
    mapped : ndarray, shape (M, 3)
        The normal that would reflect the same light into ``view``: the half vector of
        ``view`` and the pixel's mirror direction (the normals themselves when orthographic).
    solid : ndarray, shape (M,)
        Solid angle of ``mapped`` normals each pixel covers.
    view : ndarray, shape (3,)
        The common view: (0, 0, 1), or towards the sphere's centre through a pinhole.
    centre : ndarray, shape (3,) or None
        The sphere's centre (unit radius) in the camera frame; None when orthographic.
    pixels : (ndarray, ndarray)
        Rows and columns of the pixels used, within the box.
    views : ndarray, shape (M, 3), or None
        Each pixel's own view (towards the camera) through a pinhole; None when
        orthographic.
    """

    rows: slice
    cols: slice
    inside: np.ndarray
    normals: np.ndarray
    mapped: np.ndarray
    solid: np.ndarray
    view: np.ndarray
    centre: np.ndarray | None = None
    pixels: tuple[np.ndarray, np.ndarray] = ()
    views: np.ndarray | None = None


def _normals_at(xx: np.ndarray, yy: np.ndarray, sphere: Sphere, intrinsics: Intrinsics | None,
                centre: np.ndarray | None, view: np.ndarray) -> tuple[np.ndarray, ...]:
    """Sphere normals, mapped normals (see :class:`_Disc`), n·v and the views (None when
    orthographic) at image points."""
    if intrinsics is None:
        normals = sphere_normal_at(xx, yy, sphere)
        return normals, normals, normals[..., 2], None
    rays = intrinsics.rays(xx, yy)
    normals = sphere_normal_through(rays, centre)
    mapped = mirror(normals, -rays) + view
    mapped /= np.linalg.norm(mapped, axis=-1, keepdims=True)
    return normals, mapped, -np.sum(normals * rays, axis=-1), -rays


def _disc(sphere: Sphere, shape: tuple[int, int], intrinsics: Intrinsics | None) -> _Disc | None:
    """The geometry of ``sphere``'s pixels in images of ``shape``; None if it is too small."""
    cx, cy, r = sphere
    h, w = shape
    reach = r if intrinsics is None else PINHOLE_REACH * r
    r0, r1 = max(int(np.floor(cy - reach)), 0), min(int(np.ceil(cy + reach)) + 1, h)
    c0, c1 = max(int(np.floor(cx - reach)), 0), min(int(np.ceil(cx + reach)) + 1, w)
    if r1 - r0 < 3 or c1 - c0 < 3:
        return None
    centre, view = None, np.array([0.0, 0.0, 1.0])
    if intrinsics is not None:
        centre = sphere_centre_3d(sphere, intrinsics)
        view = -centre / np.linalg.norm(centre)
    yy, xx = np.mgrid[r0:r1, c0:c1].astype(np.float64)
    normals, mapped, ndotv, views = _normals_at(xx, yy, sphere, intrinsics, centre, view)
    if intrinsics is None:
        inside = np.hypot(xx - cx, yy - cy) < r - 1.5
    else:
        # n·v > √(3/r) keeps pixels about 1.5 px inside the limb (distance ≈ r (n·v)²/2),
        # as the orthographic disc does.
        inside = ndotv > np.sqrt(3.0 / r)
    # Each pixel's solid angle of mapped normals: the spherical quad of its four corners,
    # half the cross product of its diagonals.
    corner_y, corner_x = np.mgrid[r0 - 0.5:r1, c0 - 0.5:c1].astype(np.float64)
    _, corners, _, _ = _normals_at(corner_x, corner_y, sphere, intrinsics, centre, view)
    diag1 = corners[1:, 1:] - corners[:-1, :-1]
    diag2 = corners[1:, :-1] - corners[:-1, 1:]
    solid = 0.5 * np.linalg.norm(np.cross(diag1[inside], diag2[inside]), axis=-1)
    return _Disc(slice(r0, r1), slice(c0, c1), inside, normals[inside], mapped[inside], solid,
                 view, centre, np.nonzero(inside), None if views is None else views[inside])


def find_highlight(
    image_gray: np.ndarray,
    sphere: Sphere,
    *,
    min_peak: float = 0.15,
    max_area_fraction: float = 0.02,
    max_lobe_deg: float = 40.0,
    intrinsics: Intrinsics | None = None,
    lobe_cosine: float = 0.0,
) -> tuple[float, float, float] | None:
    """Sub-pixel position of the mirror point of the specular highlight on one sphere.

    Inside the sphere (the anti-aliased limb excluded), the brightest pixel must stand out
    from the disc's median (its dark body). The sphere's diffuse shading is fitted away from
    the highlight and subtracted; the excess is divided by (n·l)^q (``lobe_cosine``); the
    pixels connected to the peak whose excess is above :data:`REGION_LEVEL` of the peak's
    form the highlight; the normalised mean of their sphere normals, each weighted by its
    excess above that level and by the solid angle of normals it covers, is the mirror
    normal, and the point of the sphere that mirrors the light into the camera is returned
    (see the module's notes for why this is free of the lobe's width, the light's elevation
    and a clipped core).

    Parameters
    ----------
    image_gray : np.ndarray
        (H, W) linear grey image in [0, 1].
    sphere : (cx, cy, r)
        The sphere's outline (fitted circle), in pixels.
    min_peak : float
        The brightest pixel must reach this linear level; dimmer means no highlight.
    max_area_fraction : float
        A blob with a step edge (a plateau with no graded rim, as a clipped patch without a
        lobe around it) larger than this fraction of the disc is a blown-out patch, not a
        highlight.
    max_lobe_deg : float
        Half-angle, in the sphere's normal space, of the widest highlight accepted: a
        region above half the peak wider than a cap of this half-angle is a diffuse sheen
        rather than a specular lobe. 40° admits Blinn–Phong exponents down to about 3 (7
        when a core three times the sensor's range is clipped); a Lambertian sheen is 60°
        wide.
    intrinsics : Intrinsics, optional
        Pinhole camera in the image's pixels: the sphere's normals and views are then those
        of :func:`reconstruct.calibration.reflection.light_from_highlight`. None for an
        orthographic view.
    lobe_cosine : float
        The exponent q of the factor (n·l)^q that multiplies the lobe: 0 when the lobe is
        the radiance (classic Phong and Blinn–Phong shading), 1 for a BRDF lit by a light.
        One highlight cannot tell them apart; :func:`find_highlights` estimates it from
        several. At most :data:`MAX_LOBE_COSINE`.

    Returns
    -------
    (hx, hy, confidence) or None
        Position in image coordinates (column, row) and a confidence in (0, 1]; None when
        there is no usable highlight.
    """
    img = np.asarray(image_gray, dtype=np.float32)
    return find_highlights(img[None], sphere, min_peak=min_peak,
                           max_area_fraction=max_area_fraction, max_lobe_deg=max_lobe_deg,
                           intrinsics=intrinsics, lobe_cosine=lobe_cosine)[0]


def find_highlights(images: np.ndarray, sphere: Sphere, *, min_peak: float = 0.15,
                    max_area_fraction: float = 0.02, max_lobe_deg: float = 40.0,
                    intrinsics: Intrinsics | None = None, lobe_cosine: float | None = None,
                    ) -> list[tuple[float, float, float] | None]:
    """:func:`find_highlight` on each of several images of the same sphere.

    Parameters
    ----------
    images : np.ndarray
        (N, H, W) float32 linear grey images (e.g. every photograph's crop around the sphere).
    sphere : (cx, cy, r)
        The sphere, in the images' pixels.
    min_peak, max_area_fraction, max_lobe_deg : float
        As in :func:`find_highlight`.
    intrinsics : Intrinsics, optional
        Pinhole camera in the images' pixels (principal point in the crop's coordinates for
        crops); None for an orthographic view.
    lobe_cosine : float, optional
        The exponent q of (n·l)^q (see :func:`find_highlight`); None estimates it from the
        highlights' heights against the lights' elevations (:func:`sphere_highlights`; ½
        when they cannot tell, as with fewer than four highlights).

    Returns
    -------
    list of (hx, hy, confidence) or None
        One per image.
    """
    found, _ = sphere_highlights([images], [sphere], min_peak=min_peak,
                                 max_area_fraction=max_area_fraction, max_lobe_deg=max_lobe_deg,
                                 intrinsics=[intrinsics], lobe_cosine=lobe_cosine)
    return found[0]


def sphere_highlights(
    images: list[np.ndarray],
    spheres: list[Sphere],
    *,
    min_peak: float = 0.15,
    max_area_fraction: float = 0.02,
    max_lobe_deg: float = 40.0,
    intrinsics: list[Intrinsics | None] | None = None,
    lobe_cosine: float | None = None,
) -> tuple[list[list[tuple[float, float, float] | None]], float]:
    """The highlights on several spheres lit by the same lights, with the lobe's factor
    (n·l)^q estimated from all of them.

    Each sphere's disc and normals are built once; its peak and median are taken for all
    images at once, and only images with a candidate highlight are looked at further. Then q
    is the slope of the highlights' log heights against log(n*·l) (see the module's notes),
    and every highlight is placed with it.

    Parameters
    ----------
    images : list of np.ndarray
        Per sphere, (N, H, W) float32 linear grey images around it (the same N lights).
    spheres : list of (cx, cy, r)
        Each sphere in its images' pixels.
    min_peak, max_area_fraction, max_lobe_deg : float
        As in :func:`find_highlight`.
    intrinsics : list of Intrinsics or None, optional
        Per sphere, the pinhole camera in its images' pixels; None (or a None entry) for an
        orthographic view.
    lobe_cosine : float, optional
        A known q in [0, :data:`MAX_LOBE_COSINE`]; None estimates it.

    Returns
    -------
    found : list of list of (hx, hy, confidence) or None
        Per sphere, one per image.
    lobe_cosine : float
        The q used.
    """
    if intrinsics is None:
        intrinsics = [None] * len(spheres)
    if lobe_cosine is not None and not (np.isfinite(lobe_cosine)
                                        and 0.0 <= lobe_cosine <= MAX_LOBE_COSINE):
        raise InputError(f"lobe_cosine must be in [0, {MAX_LOBE_COSINE:g}], got {lobe_cosine!r}")
    discs, lobes = [], []
    for imgs, sphere, camera in zip(images, spheres, intrinsics):
        disc = _disc(sphere, imgs.shape[1:], camera)
        lobes.append(_first_lobes(imgs, disc, min_peak, max_area_fraction, max_lobe_deg))
        discs.append(disc)
    if lobe_cosine is None:
        q = _estimate_lobe_cosine(discs, lobes)
    else:
        q = float(lobe_cosine)
        if q > 0:  # the lobes were placed for q = 0
            _settle(discs, lobes, q)
    found = []
    for disc, row, sphere, camera in zip(discs, lobes, spheres, intrinsics):
        found.append([None if lobe is None else _placed(lobe, disc, sphere, camera)
                      for lobe in row])
    return found, q


@dataclass
class _Lobe:
    """One image's highlight after its diffuse shading is taken away.

    Attributes
    ----------
    index : ndarray, shape (P,), int
        The disc pixels (rows of :class:`_Disc`'s arrays) where the highlight may lie: excess
        above a tenth of the peak's.
    excess : ndarray, shape (P,)
        Their excess over the fitted diffuse shading.
    clipped : ndarray, shape (P,), bool
        Those of the highlight's pixels the sensor clipped.
    normal : ndarray, shape (3,)
        The mirror normal (mapped, see :class:`_Disc`), updated as q is estimated.
    score : float
        Confidence before the penalty for a highlight near the limb.
    """

    index: np.ndarray
    excess: np.ndarray
    clipped: np.ndarray
    normal: np.ndarray
    score: float


def _first_lobes(images: np.ndarray, disc: _Disc | None, min_peak: float,
                 max_area_fraction: float, max_lobe_deg: float) -> list[_Lobe | None]:
    """Each image's highlight on one sphere, placed as if q = 0 (None where there is none)."""
    n = images.shape[0]
    if disc is None or int(disc.inside.sum()) < 10:
        return [None] * n
    vals = images[:, disc.rows, disc.cols][:, disc.inside]
    peaks = vals.max(axis=1).astype(np.float64)
    bodies = np.median(vals, axis=1).astype(np.float64)
    lobes: list[_Lobe | None] = [None] * n
    for k in np.flatnonzero((peaks >= min_peak) & (peaks >= 3.0 * bodies)):
        lobes[k] = _first_lobe(vals[k].astype(np.float64), disc, float(peaks[k]),
                               float(bodies[k]), max_area_fraction, max_lobe_deg)
    return lobes


def _component(disc: _Disc, mask: np.ndarray, seed: int, index: np.ndarray | None = None
               ) -> np.ndarray:
    """The 8-connected component holding ``seed`` of ``mask``.

    ``mask`` is over the disc's pixels (flat) or, with ``index``, over those pixels of the
    disc only, labelled within their bounding box; ``seed`` and the result are over the same
    pixels as ``mask``.
    """
    rr, cc = disc.pixels
    if index is not None:
        rr, cc = rr[index], cc[index]
    r0, c0 = int(rr.min()), int(cc.min())
    image = np.zeros((int(rr.max()) - r0 + 1, int(cc.max()) - c0 + 1), dtype=bool)
    image[rr - r0, cc - c0] = mask
    labels, _ = ndimage.label(image, structure=np.ones((3, 3), dtype=bool))
    flat = labels[rr - r0, cc - c0]
    return flat == flat[seed]


def _first_lobe(values: np.ndarray, disc: _Disc, peak: float, body: float,
                max_area_fraction: float, max_lobe_deg: float) -> _Lobe | None:
    """The highlight in one image's disc pixels ``values``, given their peak and median."""
    excess = values - body
    height = peak - body
    seed = int(np.argmax(values))
    half = _component(disc, excess > 0.5 * height, seed)

    # Width of the half-maximum region as the half-angle of a cap of the same solid angle.
    half_sr = float(disc.solid[half].sum())
    half_angle = float(np.degrees(np.arccos(np.clip(1.0 - half_sr / (2 * np.pi), -1.0, 1.0))))
    if half_angle > max_lobe_deg:
        return None
    region = _component(disc, excess > REGION_LEVEL * height, seed)
    plateau = region & (excess >= 0.9 * height)
    plateau_sr = float(disc.solid[plateau].sum())
    rim_sr = float(disc.solid[region].sum()) - plateau_sr
    if int(half.sum()) > max_area_fraction * values.size and rim_sr < _STEP_EDGE * plateau_sr:
        return None
    clipped = region & (values >= SATURATION)

    normal = _level_mean(excess, clipped, None, disc, 0.0, None)[0]
    # The sphere's own diffuse shading, kd·max(0, n·l), is brighter towards the light and
    # drags the mean that way: fit it with an ambient level on the disc away from the
    # highlight, subtract it, take the mean again; twice, the second time with the better
    # light.
    for _ in range(2):
        if normal is None:
            return None
        excess = values - _diffuse_background(values, disc, normal, half_angle)
        height = float(excess.max())
        if height <= 0:
            return None
        normal = _level_mean(excess, clipped, None, disc, 0.0, None)[0]
    if normal is None:
        return None
    index = np.flatnonzero((excess > _KEEP_LEVEL * height) | clipped)

    # Confidence: contrast against the body, penalised for wide or largely clipped
    # highlights (the penalty for highlights on the limb comes with the final position).
    contrast = (peak - body) / peak
    size_pen = 1.0 - half_angle / max_lobe_deg
    saturated = int((values[half] >= SATURATION).sum())
    # A flash highlight's core is often clipped; a clipped area that is large for a mirror
    # highlight leaves only the rim to place it.
    sat_pen = 1.0 if saturated <= 0.25 * max_area_fraction * values.size else 0.5
    return _Lobe(index, excess[index], clipped[index], normal,
                 contrast * (0.5 + 0.5 * size_pen) * sat_pen)


def _level_mean(excess: np.ndarray, clipped: np.ndarray, index: np.ndarray | None,
                disc: _Disc, q: float, normal: np.ndarray | None,
                ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """The mirror normal as the mean of the highlight's mapped normals, for lobes × (n·l)^q.

    The excess (over the disc's pixels, or those of ``index``) is divided by (n·l/n*·l)^q,
    with l the light that ``normal`` mirrors and n* the normal at its mirror point (the
    lobe's height there is unchanged), which leaves the lobe alone, symmetric about
    h; then clipped at its lowest value on a clipped pixel, above which every pixel's value
    is known, so that a clipped core is a symmetric plateau. The pixels connected to the
    peak above :data:`REGION_LEVEL` of it weigh in with their excess above that level and
    their solid angle.

    Returns
    -------
    normal : ndarray, shape (3,), or None
        The normalised mean; None for an empty region.
    corrected : ndarray
        The excess divided and clipped.
    region : ndarray, bool
        The highlight's pixels.
    """
    rows = slice(None) if index is None else index
    corrected = excess
    if q > 0:
        light = mirror(normal, disc.view)
        cosine = np.clip(disc.normals[rows] @ light, _MIN_COSINE, None)
        corrected = excess * (_mirror_cosine(normal, disc) / cosine) ** q
    if clipped.any():
        corrected = np.minimum(corrected, corrected[clipped].min())
    seed = int(np.argmax(corrected))
    height = float(corrected[seed])
    region = _component(disc, corrected > REGION_LEVEL * height, seed, index)
    wgt = (corrected[region] - REGION_LEVEL * height) * disc.solid[rows][region]
    mean = wgt @ disc.mapped[rows][region]
    norm = float(np.linalg.norm(mean))
    return (mean / norm if norm > 0 else None), corrected, region


def _mirror_cosine(normal: np.ndarray, disc: _Disc) -> float:
    """n·l at the mirror point of the mapped ``normal`` (h·l when orthographic)."""
    light = mirror(normal, disc.view)
    return max(float(_mirror_normal(normal, disc) @ light), _MIN_COSINE)


def _settled_normal(lobe: _Lobe, disc: _Disc, q: float) -> np.ndarray:
    """The mirror normal for lobes × (n·l)^q, from ``lobe.normal``: the light of the
    division follows the normal found (the mean moves less than the light each time)."""
    normal = lobe.normal
    for _ in range(_SETTLE if q > 0 else 1):
        found = _level_mean(lobe.excess, lobe.clipped, lobe.index, disc, q, normal)[0]
        if found is None:
            break
        normal = found
    return normal


def _settle(discs: list[_Disc | None], lobes: list[list[_Lobe | None]], q: float) -> None:
    """Place every lobe's normal for lobes × (n·l)^q (:func:`_settled_normal`)."""
    for disc, row in zip(discs, lobes):
        for lobe in row:
            if lobe is not None:
                lobe.normal = _settled_normal(lobe, disc, q)


def _log_height(lobe: _Lobe, disc: _Disc, q: float) -> tuple[float, float]:
    """Log of the lobe's height at the mirror normal, divided by (n·l)^q as in
    :func:`_level_mean`, and its variance (NaN when it cannot be measured).

    Fitted as log e = a + s·log(n·h) + b·w² on the highlight's unclipped pixels, weighted by
    e² (the log's noise goes as 1/e) and by the solid angle: s·log(n·h) is the log of a
    Blinn–Phong lobe (h each pixel's own half vector of the light and its view), and w, the
    sine of the normal's tilt out of the plane of light and view, lets the lobe be narrower
    across that plane than along it, as a Phong lobe (r·v)^s is when the light is low.
    The height of a clipped core is extrapolated from its rim.
    """
    _, corrected, region = _level_mean(lobe.excess, lobe.clipped, lobe.index, disc, q,
                                       lobe.normal)
    use = region & (corrected > 0)
    if lobe.clipped.any():
        # Next to a clipped core a JPEG rings: keep to the rim well below the clip.
        use &= corrected < 0.9 * corrected.max()
    if int(use.sum()) < 8:
        return np.nan, np.nan
    rows = lobe.index[use]
    normals = disc.normals[rows]
    light = mirror(lobe.normal, disc.view)
    if disc.views is None:
        cosine = normals @ lobe.normal
    else:
        half = light + disc.views[rows]
        cosine = np.sum(normals * half, axis=1) / np.linalg.norm(half, axis=1)
    columns = [np.ones(rows.size), np.log(np.clip(cosine, 1e-9, 1.0))]
    across = np.cross(light, disc.view)
    if np.linalg.norm(across) > 1e-3:
        columns.append((normals @ (across / np.linalg.norm(across))) ** 2)
    design = np.stack(columns, axis=1)
    root = np.sqrt(corrected[use] ** 2 * disc.solid[rows])
    y = np.log(corrected[use])
    coef, *_ = np.linalg.lstsq(design * root[:, None], y * root, rcond=None)
    resid = (y - design @ coef) * root
    scale = float(resid @ resid) / (rows.size - design.shape[1])
    inverse = np.linalg.pinv((design * root[:, None]).T @ (design * root[:, None]))
    return float(coef[0]), float(scale * inverse[0, 0])


def _estimate_lobe_cosine(discs: list[_Disc | None], lobes: list[list[_Lobe | None]]) -> float:
    """The exponent q ≥ 0 of the factor (n·l)^q on the spheres' lobes; updates every
    lobe's normal to the one for that q.

    The lobe's height at the mirror point goes as (n*·l)^q, n*·l = cos of half the angle
    between light and view: with lights of equal power, the highlights' log heights (with
    (n·l/n*·l)^q divided out, :func:`_log_height`) against log(n*·l) have slope q, each
    sphere its own intercept. The fit is redone with the normals placed for the new q
    until q settles; it is shrunk towards :data:`_PRIOR_Q` by its standard error (a
    Gaussian prior of spread :data:`_PRIOR_SD`), so that lights of unequal power, too few
    highlights or lights all at one elevation leave q halfway between the conventions.
    """
    q = 0.0
    for _ in range(_Q_ROUNDS):
        x, y, var, group = [], [], [], []
        for g, (disc, row) in enumerate(zip(discs, lobes)):
            for lobe in row:
                if lobe is None:
                    continue
                a, v = _log_height(lobe, disc, q)
                if np.isfinite(a) and np.isfinite(v):
                    x.append(np.log(_mirror_cosine(lobe.normal, disc)))
                    y.append(a)
                    var.append(v)
                    group.append(g)
        slope, se = _common_slope(np.array(x), np.array(y), np.array(var), np.array(group, int))
        new = _PRIOR_Q if not np.isfinite(se) else (
            (slope / se ** 2 + _PRIOR_Q / _PRIOR_SD ** 2) / (1.0 / se ** 2 + 1.0 / _PRIOR_SD ** 2))
        new = float(np.clip(new, 0.0, MAX_LOBE_COSINE))
        settled = abs(new - q) < 0.01
        q = new
        _settle(discs, lobes, q)
        if settled:
            break
    return q


def _common_slope(x: np.ndarray, y: np.ndarray, var: np.ndarray, group: np.ndarray
                  ) -> tuple[float, float]:
    """Weighted least-squares slope of y on x with one intercept per group, and its
    standard error (inf when it cannot be measured).

    Each point weighs 1/(var + floor²), its variance (the floor, :data:`_LOG_FLOOR`, stands
    for what the fit's own variance misses: shading and sensor quirks); the standard error
    comes from the scatter about the line, or from these variances if the scatter is
    smaller (a few points can fall on a line by chance). Points off the line by more than
    three robust spreads are left out once.
    """
    keep = np.ones(x.size, dtype=bool)
    w = 1.0 / (var + _LOG_FLOOR ** 2)
    slope, se = 0.0, np.inf
    for _ in range(2):
        groups = np.unique(group[keep])
        dof = int(keep.sum()) - groups.size - 1
        if dof < 2:
            return 0.0, np.inf
        xc, yc = x.copy(), y.copy()
        for g in groups:
            sel = keep & (group == g)
            xc[group == g] -= (w[sel] @ x[sel]) / w[sel].sum()
            yc[group == g] -= (w[sel] @ y[sel]) / w[sel].sum()
        sxx = float(w[keep] @ xc[keep] ** 2)
        if sxx <= 0:
            return 0.0, np.inf
        slope = float(w[keep] @ (xc[keep] * yc[keep])) / sxx
        resid = yc - slope * xc
        se = float(np.sqrt(max((w[keep] @ resid[keep] ** 2) / dof, 1.0) / sxx))
        spread = 1.4826 * float(np.median(np.abs(resid[keep]) * np.sqrt(w[keep])))
        out = np.abs(resid) * np.sqrt(w) > 3.0 * max(spread, 1e-12)
        if not (keep & out).any():
            break
        keep &= ~out
    return slope, se


def _placed(lobe: _Lobe, disc: _Disc, sphere: Sphere, intrinsics: Intrinsics | None
            ) -> tuple[float, float, float] | None:
    """Image position and confidence of a lobe's mirror point."""
    cx, cy, r = sphere
    hx, hy = _mirror_point(lobe.normal, disc, sphere, intrinsics)
    # A highlight on the limb (light nearly behind the sphere) is foreshortened, unreliable.
    rho = np.hypot(hx - cx, hy - cy) / r
    limb_pen = float(np.clip((0.97 - rho) / 0.07, 0.0, 1.0))
    conf = float(np.clip(lobe.score * limb_pen, 0.0, 1.0))
    if conf <= 0:
        return None
    return float(hx), float(hy), conf


def _diffuse_background(values: np.ndarray, disc: _Disc, normal: np.ndarray,
                        half_angle_deg: float) -> np.ndarray:
    """Ambient plus Lambertian shading a + kd·max(0, n·l) of the sphere, with l the light
    that the mapped ``normal`` reflects, fitted by least squares to the disc's pixels away
    from the highlight.

    "Away" is more than three half-widths (+2°) from ``normal``, where a lobe has fallen
    below 0.3 % of its peak (a Gaussian's tail at 3.5σ). A lobe so wide that this leaves
    less than a tenth of the sphere's lit pixels takes the tenth of them farthest from the
    highlight instead (with the unlit pixels beyond), so that kd is still measured.
    """
    shading = np.clip(disc.normals @ mirror(normal, disc.view), 0.0, None)
    # Two numbers need no more than a few ten thousand pixels: a large sphere is sampled.
    step = max(1, values.size // 20000)
    cosine = disc.mapped[::step] @ normal
    lit = shading[::step] > 0
    far_cos = np.cos(np.radians(3.0 * half_angle_deg + 2.0))
    if lit.any():
        far_cos = max(far_cos, float(np.quantile(cosine[lit], 0.1)))
    far = cosine <= far_cos
    if not far.any():
        return np.zeros_like(values)
    x, y = shading[::step][far], values[::step][far]
    spread = float(x.var())
    albedo = float(np.mean((x - x.mean()) * (y - y.mean()))) / spread if spread > 1e-12 else 0.0
    return (float(y.mean()) - albedo * float(x.mean())) + albedo * shading


def _mirror_normal(normal: np.ndarray, disc: _Disc, iterations: int = 50) -> np.ndarray:
    """The sphere's normal where it mirrors the light of the mapped ``normal`` into the camera.

    Orthographic: that normal. Pinhole: the light l = mirror(normal, view) is reflected into
    the camera where the sphere normal n is the half vector of l and the point's own view;
    n ← (l + v(C + n))/|…| converges (each step shrinks the error by about the sphere's
    angular radius seen from the camera).
    """
    if disc.centre is None:
        return normal
    light = mirror(normal, disc.view)
    point = disc.centre + normal
    for _ in range(iterations):
        nxt = light - point / np.linalg.norm(point)
        nxt /= np.linalg.norm(nxt)
        done = np.linalg.norm(disc.centre + nxt - point) < 1e-13
        point = disc.centre + nxt
        if done:
            break
    return point - disc.centre


def _mirror_point(normal: np.ndarray, disc: _Disc, sphere: Sphere,
                  intrinsics: Intrinsics | None) -> tuple[float, float]:
    """Image position of the sphere's point that mirrors the light of the mapped ``normal``."""
    cx, cy, r = sphere
    if intrinsics is None:
        return cx + r * normal[0], cy - r * normal[1]
    point = disc.centre + _mirror_normal(normal, disc)
    depth = -point[2]
    return (intrinsics.cx + intrinsics.fx * point[0] / depth,
            intrinsics.cy - intrinsics.fy * point[1] / depth)
