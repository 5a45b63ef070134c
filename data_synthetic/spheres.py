"""Synthetic "highlight RTI" captures: a dull scene with black glossy spheres beside it.

Each photograph is lit by one distant light; the light direction can be read back from the
mirror highlight on each sphere. The camera is orthographic by default, or a pinhole camera
(``focal_px``) for short lenses; the frame is the project's: x right, y up, z towards the
camera; pixel (row, col) has its centre at image coordinates (x_img, y_img) = (col, row), and
sphere centres are given in those coordinates.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError
from ptmcore.lp import write_lp
from reconstruct.calibration.camera import Intrinsics
from reconstruct.calibration.reflection import ray_sphere_distance, sphere_normal_at

from .encoding import write_jpeg8, write_npy, write_png8
from .lights import dome_lights
from .surface import normals_from_height, smooth_noise

#: Default spheres (cx, cy, r) in pixels for the default 300×400 image: two, ≥ 150 px across.
DEFAULT_SPHERES = ((95.0, 90.0, 78.0), (310.3, 205.6, 80.4))

_SUPERSAMPLE = 3


@dataclass(frozen=True)
class SphereCaptureInfo:
    """What :func:`render_sphere_capture` wrote.

    Attributes
    ----------
    folder : Path
        The capture folder.
    image_paths : tuple of Path
        The photographs, in light order.
    directions : np.ndarray
        (N, 3) float64 true unit light directions (x right, y up, z to camera).
    spheres : tuple of (float, float, float)
        True (cx, cy, r) of each sphere in pixels (cx = column, cy = row).
    hidden : tuple of int
        Indices of the photographs whose highlights are occluded.
    truth_lp : Path
        ``folder/truth.lp`` with the true directions of all photographs.
    shape : tuple of int
        (H, W) of the photographs.
    camera : Intrinsics or None
        The pinhole camera of a perspective capture; None for an orthographic one.
    outlines : tuple of (x0, y0, a, b, phi)
        Each sphere's true outline as an ellipse: centre (column, row), semi-axes in pixels
        and the major axis's angle in radians (a circle (cx, cy, r, r, 0) when
        orthographic).
    """

    folder: Path
    image_paths: tuple[Path, ...]
    directions: np.ndarray
    spheres: tuple[tuple[float, float, float], ...]
    hidden: tuple[int, ...]
    truth_lp: Path
    shape: tuple[int, int]
    camera: Intrinsics | None = None
    outlines: tuple[tuple[float, float, float, float, float], ...] = ()


def _pinhole_outline(centre: np.ndarray, focal_px: float, principal: tuple[float, float]
                     ) -> tuple[float, float, float, float, float]:
    """Ellipse (x0, y0, a, b, phi) that a pinhole camera (square pixels) sees of a unit sphere.

    A closed form independent of :func:`reconstruct.calibration.reflection.sphere_outline` (which
    takes the conic of the tangent cone), kept as ground truth: the tests compare the two.

    With θ the angle of the centre off the optical axis and α the half-angle of the tangent
    cone (sin α = 1/|C|), the major axis lies on the radial image line with its ends at
    f·tan(θ ± α) from the principal point, and the semi-minor axis is
    f·sin α / √(cos²θ − sin²α).
    """
    dist = float(np.linalg.norm(centre))
    theta = float(np.arccos(-centre[2] / dist))
    alpha = float(np.arcsin(1.0 / dist))
    near, far = focal_px * np.tan(theta - alpha), focal_px * np.tan(theta + alpha)
    b = focal_px * np.sin(alpha) / np.sqrt(np.cos(theta) ** 2 - np.sin(alpha) ** 2)
    # Image direction of the centre: x right = +column, y up = −row.
    phi = float(np.arctan2(-centre[1], centre[0])) if theta > 0 else 0.0
    mid = 0.5 * (near + far)
    return (principal[0] + mid * np.cos(phi), principal[1] + mid * np.sin(phi),
            0.5 * (far - near), float(b), phi)


def _outline_boxes(outlines) -> list[tuple[float, float, float, float]]:
    """(x_min, y_min, x_max, y_max) in image coordinates of each outline ellipse."""
    boxes = []
    for x0, y0, a, b, phi in outlines:
        ex = np.hypot(a * np.cos(phi), b * np.sin(phi))
        ey = np.hypot(a * np.sin(phi), b * np.cos(phi))
        boxes.append((x0 - ex, y0 - ey, x0 + ex, y0 + ey))
    return boxes


def _sphere_patch(box, spheres, camera: Intrinsics | None, centres: np.ndarray | None,
                  shape: tuple[int, int]):
    """The supersampled pixels of one sphere's box: which sub-samples see a sphere, and there
    the unit normal and the direction to the camera (None when orthographic).

    Returns (r0, r1, c0, c1, on_sphere, normals, view). Every sphere is tested, so a box that
    overlaps another sphere shows it too; the nearest sphere wins.
    """
    h, w = shape
    r0, r1 = max(int(np.floor(box[1])) - 1, 0), min(int(np.ceil(box[3])) + 2, h)
    c0, c1 = max(int(np.floor(box[0])) - 1, 0), min(int(np.ceil(box[2])) + 2, w)
    ss = _SUPERSAMPLE
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    cols = (np.arange(c0, c1)[:, None] + sub[None, :]).ravel()
    rows = (np.arange(r0, r1)[:, None] + sub[None, :]).ravel()
    X, Y = np.meshgrid(cols, rows)  # image coordinates of the sub-samples
    on_sphere = np.zeros(X.shape, dtype=bool)
    sn = np.zeros(X.shape + (3,))
    if camera is None:
        for sphere in spheres:
            normals = sphere_normal_at(X, Y, sphere)
            inside = normals[..., 2] > 0  # off the disc the normal is clamped to the limb
            on_sphere |= inside
            sn[inside] = normals[inside]
        return r0, r1, c0, c1, on_sphere, sn[on_sphere], None
    rays = camera.rays(X, Y)
    depth = np.full(X.shape, np.inf)
    for c in centres:
        t, hit = ray_sphere_distance(rays, c)
        nearer = hit & (t < depth)
        depth[nearer] = t[nearer]
        on_sphere |= nearer
        sn[nearer] = t[nearer, None] * rays[nearer] - c
    n_sph = sn[on_sphere]
    n_sph /= np.linalg.norm(n_sph, axis=1, keepdims=True)
    return r0, r1, c0, c1, on_sphere, n_sph, -rays[on_sphere]


def _pinhole_scene(spheres, focal_px: float, shape: tuple[int, int]
                   ) -> tuple[Intrinsics, np.ndarray, tuple]:
    """The pinhole camera (principal point at the image centre), the spheres' centres in its
    frame for unit radii, and their outline ellipses, checking that each outline fits.

    Sphere (cx, cy, r) has its centre on the ray through pixel (cx, cy), at the depth where
    a unit radius looks r pixels long.
    """
    h, w = shape
    if not (np.isfinite(focal_px) and focal_px > 0):
        raise InputError(f"focal_px must be a positive number of pixels, got {focal_px!r}")
    camera = Intrinsics(float(focal_px), float(focal_px), (w - 1) / 2.0, (h - 1) / 2.0)
    centres = np.array([[(cx - camera.cx) / r, -(cy - camera.cy) / r, -focal_px / r]
                        for cx, cy, r in spheres])
    outlines = tuple(_pinhole_outline(c, float(focal_px), (camera.cx, camera.cy))
                     for c in centres)
    for (cx, cy, r), box in zip(spheres, _outline_boxes(outlines)):
        if box[0] < 1 or box[1] < 1 or box[2] > w - 2 or box[3] > h - 2:
            raise InputError(f"sphere {(cx, cy, r)!r} seen through a {focal_px}-pixel "
                             f"lens does not fit inside a {h}×{w} image")
    return camera, centres, outlines


def _paint_spheres(img: np.ndarray, background: np.ndarray, patch: tuple, light: np.ndarray,
                   highlight: bool, shininess: float, specular: float,
                   sphere_albedo: float, lobe: str = "phong", n_dot_l: bool = False) -> None:
    """Shade the sub-samples of a :func:`_sphere_patch` under a distant light and average
    them into `img` in place; sub-samples off the spheres see `background`, the patch's box of
    the unpainted image. With `n_dot_l` the lobe is multiplied by n·l.

    Boxes may overlap: each box starts again from the background and covers every sphere
    within it. Without `highlight` (an occluded flash) the spheres get no specular lobe.
    """
    r0, r1, c0, c1, on_sphere, n_sph, view = patch
    ss = _SUPERSAMPLE
    ndotl = n_sph @ light
    sphere_rad = sphere_albedo * np.clip(ndotl, 0, None)
    if highlight:
        # v = +z when orthographic, else each sub-sample's own direction to the camera.
        ndotv = n_sph[:, 2] if view is None else np.sum(n_sph * view, axis=1)
        vdotl = light[2] if view is None else view @ light
        if lobe == "phong":
            # r·v with r = 2(n·l)n − l the mirror direction of the light.
            cosine = 2.0 * ndotl * ndotv - vdotl
        else:
            # n·h with h = (l + v)/|l + v|, the half vector.
            cosine = (ndotl + ndotv) / np.sqrt(2.0 + 2.0 * vdotl)
        cosine = np.clip(cosine, 0, None)
        spec = np.where(ndotl > 0, cosine ** shininess, 0.0)
        if n_dot_l:
            spec *= np.clip(ndotl, 0, None)
        sphere_rad = sphere_rad + specular * spec
    fine = np.repeat(np.repeat(background, ss, 0), ss, 1)
    fine[on_sphere] = sphere_rad[:, None]
    img[r0:r1, c0:c1] = fine.reshape(r1 - r0, ss, c1 - c0, ss, 3).mean(axis=(1, 3))


def check_spheres(spheres, shape: tuple[int, int]) -> tuple[tuple[float, float, float], ...]:
    """Validate the sphere list against the image size."""
    h, w = shape
    out = []
    for s in spheres:
        try:
            cx, cy, r = (float(v) for v in s)
        except (TypeError, ValueError):
            raise InputError(f"each sphere must be (cx, cy, r), got {s!r}") from None
        if not (np.isfinite([cx, cy, r]).all() and r > 0):
            raise InputError(f"sphere {s!r} needs a finite centre and a positive radius")
        if cx - r < 1 or cy - r < 1 or cx + r > w - 2 or cy + r > h - 2:
            raise InputError(f"sphere {s!r} does not fit inside a {h}×{w} image")
        out.append((cx, cy, r))
    if not out:
        raise InputError("need at least one sphere")
    return tuple(out)


def render_sphere_capture(
    out_dir: str | os.PathLike,
    *,
    shape: tuple[int, int] = (300, 400),
    n_lights: int = 24,
    spheres=DEFAULT_SPHERES,
    seed: int = 0,
    hidden: tuple[int, ...] | list[int] = (),
    encoding: str = "png",
    shininess: float = 500.0,
    specular: float = 3.0,
    sphere_albedo: float = 0.02,
    noise: float = 0.003,
    focal_px: float | None = None,
    background_tint: tuple[float, float, float] = (0.55, 0.47, 0.38),
    background_texture: float = 0.15,
    lobe: str = "phong",
    min_elevation_deg: float = 15.0,
    max_elevation_deg: float = 75.0,
    n_dot_l: bool = False,
) -> SphereCaptureInfo:
    """Render and write a highlight-RTI capture with black glossy spheres.

    The scene is a dull Lambertian plane with a low textured relief and a varying albedo,
    plus the spheres: albedo ``sphere_albedo`` and a white specular lobe on the side facing
    the light, either Phong ``specular · max(0, r·v)^shininess`` (r the mirror reflection of
    the light, v = +z) or Blinn–Phong ``specular · max(0, n·h)^shininess`` (h the half
    vector of light and view, as :func:`data_synthetic.render.render` shades surfaces), so
    the highlight is brightest where the sphere normal bisects light and view. A Blinn–Phong
    exponent is about four times a Phong one of the same width (n·h = cos δ where r·v = cos
    2δ); exponents of 10–50 give the broad highlights of spheres that are glossy rather than
    polished, and ``specular`` above 1 clips the highlight's core, as an overexposed flash
    does. Pixels are averaged over a 3×3 supersampling grid so sphere limbs are anti-aliased
    like a real lens would. Shadows cast by the spheres are not rendered.

    With ``focal_px`` the camera is a pinhole at the origin looking along −z, principal
    point at the image centre ((W − 1)/2, (H − 1)/2). Sphere (cx, cy, r) then has its centre
    on the ray through pixel (cx, cy), at the depth where its radius looks r pixels long
    (depth = focal_px · radius / r; the image does not depend on the absolute scale).
    Each sub-sample's ray is intersected with the spheres, so they appear as the ellipses a
    lens gives, and the Phong lobe uses the direction from the hit point to the camera as
    the view, so highlights are where a real lens puts them. The background is shaded as
    in the orthographic case (distant lights, its own normals).

    Parameters
    ----------
    out_dir : str or PathLike
        Folder to write into (created if needed).
    shape : tuple of int
        (H, W) of the photographs.
    n_lights : int
        Number of photographs; directions from :func:`dome_lights` (jittered).
    spheres : sequence of (cx, cy, r)
        Sphere centres (cx = column, cy = row) and radii in pixels.
    seed : int
        Seeds the light jitter, the scene texture and the sensor noise.
    hidden : sequence of int
        Photographs whose sphere highlights are occluded (the spheres get no specular lobe),
        as when the flash is blocked from the spheres; calibration should flag them.
    encoding : {"png", "jpeg"}
        8-bit sRGB PNG (lossless) or JPEG (quality 95).
    shininess, specular, sphere_albedo, noise : float
        Lobe exponent and peak, diffuse albedo of the spheres, sensor noise (std, full
        scale 1).
    focal_px : float, optional
        Focal length in pixels of a pinhole camera; None (default) for an orthographic
        view.
    background_tint : (float, float, float)
        Mean linear RGB albedo of the background plane.
    background_texture : float
        Relative amplitude of the background's albedo mottling (0 for a plain albedo).
    lobe : {"phong", "blinn-phong"}
        The specular lobe's model.
    n_dot_l : bool
        Multiply the lobe by max(0, n·l), as a physically based renderer shades a BRDF lit
        by a distant light (radiance = BRDF × n·l), instead of taking the lobe as the
        radiance. The lobe is then brightest a little off the mirror point, towards the
        light, and dimmer by about h·l the lower the light.
    min_elevation_deg, max_elevation_deg : float
        Elevations of the dome's lowest and highest rings (0 < min ≤ max ≤ 90).

    Returns
    -------
    SphereCaptureInfo
        Paths, the true directions and spheres. ``truth.lp`` and ``truth.npy`` hold the
        true directions of every photograph (hidden ones included).
    """
    try:
        h, w = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape must be (height, width), got {shape!r}") from None
    if h < 16 or w < 16:
        raise InputError(f"images must be at least 16×16 pixels, got {h}×{w}")
    if n_lights < 3:
        raise InputError(f"need at least 3 lights, got {n_lights}")
    if encoding not in ("png", "jpeg"):
        raise InputError(f"unknown encoding {encoding!r}; choose png or jpeg")
    if lobe not in ("phong", "blinn-phong"):
        raise InputError(f"unknown lobe {lobe!r}; choose phong or blinn-phong")
    if not (np.isfinite(shininess) and shininess > 0):
        raise InputError(f"shininess must be a positive exponent, got {shininess!r}")
    sph = check_spheres(spheres, (h, w))
    camera, centres, outlines = None, None, tuple((cx, cy, r, r, 0.0) for cx, cy, r in sph)
    if focal_px is not None:
        camera, centres, outlines = _pinhole_scene(sph, focal_px, (h, w))
    hidden = tuple(sorted({int(k) for k in hidden}))
    if any(k < 0 or k >= n_lights for k in hidden):
        raise InputError(f"hidden photographs must be in 0..{n_lights - 1}, got {hidden}")

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the capture folder: {exc.strerror}", out) from None

    rng = np.random.default_rng(seed)
    try:
        lights = dome_lights(n_lights, min_elevation_deg, max_elevation_deg, seed=seed)
    except ValueError as exc:
        raise InputError(str(exc)) from None

    # Background: a gently rolling plane with a mottled albedo, shaded at pixel resolution
    # (it has no sharp edges); only the spheres' boxes are supersampled.
    relief = 2.0 * smooth_noise((h, w), 12, rng)
    bg_normals = normals_from_height(relief, 1.0).astype(np.float64)
    tint = np.asarray(background_tint, dtype=np.float64)
    if tint.shape != (3,) or not (np.isfinite(tint).all() and (tint >= 0).all()):
        raise InputError(f"background_tint must be three albedos ≥ 0, got {background_tint!r}")
    if not (np.isfinite(background_texture) and background_texture >= 0):
        raise InputError(f"background_texture must be ≥ 0, got {background_texture!r}")
    mottle = np.clip(1.0 + background_texture * smooth_noise((h, w), 30, rng), 0.5, 1.5)
    bg_albedo = tint * mottle[..., None]

    patches = [_sphere_patch(box, sph, camera, centres, (h, w))
               for box in _outline_boxes(outlines)]

    paths = []
    ext = ".png" if encoding == "png" else ".jpg"
    for k, light in enumerate(lights):
        background = bg_albedo * np.clip(bg_normals @ light, 0, None)[..., None]
        img = background.copy()
        for patch in patches:
            r0, r1, c0, c1 = patch[:4]
            _paint_spheres(img, background[r0:r1, c0:c1], patch, light, k not in hidden,
                           shininess, specular, sphere_albedo, lobe, n_dot_l)
        img += rng.normal(0.0, noise, img.shape)
        path = out / f"img_{k:03d}{ext}"
        if encoding == "png":
            write_png8(path, img.astype(np.float32))
        else:
            write_jpeg8(path, img.astype(np.float32), quality=95)
        paths.append(path)

    truth_lp = out / "truth.lp"
    write_lp(truth_lp, [p.name for p in paths], lights)
    write_npy(out / "truth.npy", lights)
    return SphereCaptureInfo(folder=out, image_paths=tuple(paths), directions=lights,
                             spheres=sph, hidden=hidden, truth_lp=truth_lp, shape=(h, w),
                             camera=camera, outlines=outlines)


#: Order in which the frame's corners receive spheres: opposite corners first, so two spheres
#: see the lights from as different places as the frame allows.
_CORNERS = ("top-left", "bottom-right", "top-right", "bottom-left")

#: Smallest sphere worth placing: calibration reads a highlight's position to a fraction of a
#: pixel, so a smaller sphere gives its light to several degrees at best.
MIN_CORNER_RADIUS = 12.0


def corner_spheres(mask: np.ndarray, count: int, gap: float = 6.0) -> tuple[tuple[float, float, float], ...]:
    """Spheres in the frame's corners, each as large as the background there allows.

    Parameters
    ----------
    mask : ndarray, shape (H, W), bool
        True on the object, which the spheres must not cover.
    count : int
        Number of spheres, 1 to 4 (top-left, bottom-right, top-right, bottom-left).
    gap : float
        Background kept between a sphere and the object or the frame's edge, in pixels.

    Returns
    -------
    tuple of (cx, cy, r)
        Centres (column, row) and radii in pixels.

    Raises
    ------
    InputError
        For a count out of range, or a corner too small for a sphere of
        :data:`MIN_CORNER_RADIUS` pixels.
    """
    from scipy import ndimage

    if not 1 <= count <= len(_CORNERS):
        raise InputError(f"spheres must be 1 to {len(_CORNERS)} (one per corner of the frame), got {count}")
    h, w = mask.shape
    clear = ndimage.distance_transform_edt(~mask) if mask.any() else np.full(mask.shape, np.inf)
    rows, cols = np.mgrid[0:h, 0:w]
    to_edge = np.minimum.reduce([rows + 0.5, cols + 0.5, h - 0.5 - rows, w - 0.5 - cols])
    # A sphere centred at a pixel reaches r + gap towards the object and the frame's edge.
    reach = np.minimum(clear - gap, to_edge - gap)
    halves = {"top": slice(0, h // 2), "bottom": slice(h - h // 2, h),
              "left": slice(0, w // 2), "right": slice(w - w // 2, w)}
    spheres = []
    for corner in _CORNERS[:count]:
        vertical, horizontal = corner.split("-")
        quadrant = reach[halves[vertical], halves[horizontal]]
        r0, c0 = halves[vertical].start, halves[horizontal].start
        row, col = np.unravel_index(np.argmax(quadrant), quadrant.shape)
        radius = float(quadrant[row, col])
        if radius < MIN_CORNER_RADIUS:
            raise InputError(f"the {corner} corner of a {h}×{w} frame leaves room for a sphere of "
                             f"{max(radius, 0):.0f} pixels beside the object, less than "
                             f"{MIN_CORNER_RADIUS:.0f}: render larger images or fewer spheres")
        spheres.append((float(c0 + col), float(r0 + row), radius))
    return tuple(spheres)


def paint_spheres(images: np.ndarray, lights: np.ndarray, spheres, *, seed: int = 0, noise: float = 0.003,
                  shininess: float = 500.0, specular: float = 3.0, sphere_albedo: float = 0.02) -> None:
    """Put black glossy spheres into rendered photographs, in place (orthographic view).

    Shaded as in :func:`render_sphere_capture` (Phong lobe, 3×3 supersampling), with
    Gaussian sensor noise of their own.

    Parameters
    ----------
    images : ndarray, shape (N, H, W, 3), float32
        Linear radiance, one photograph per light.
    lights : ndarray, shape (N, 3)
        Unit vectors towards the lights.
    spheres : sequence of (cx, cy, r)
        Centres (column, row) and radii in pixels, inside the frame.
    seed : int
        Seeds the noise.
    noise, shininess, specular, sphere_albedo : float
        As in :func:`render_sphere_capture`.
    """
    sph = check_spheres(spheres, images.shape[1:3])
    outlines = tuple((cx, cy, r, r, 0.0) for cx, cy, r in sph)
    patches = [_sphere_patch(box, sph, None, None, images.shape[1:3]) for box in _outline_boxes(outlines)]
    rng = np.random.default_rng(seed)
    for image, light in zip(images, np.asarray(lights, dtype=np.float64)):
        # The boxes as they were before any was painted (boxes may overlap), in float64 as
        # the shading is: copies of the boxes only, not of the whole photograph.
        backgrounds = [image[r0:r1, c0:c1].astype(np.float64) for r0, r1, c0, c1, *_ in patches]
        for patch, background in zip(patches, backgrounds):
            _paint_spheres(image, background, patch, light, True, shininess, specular, sphere_albedo)
            box = image[patch[0]:patch[1], patch[2]:patch[3]]
            # The background around a sphere already has its noise.
            sphere = np.any(box != background, axis=-1)
            box[sphere] += rng.normal(0.0, noise, (int(sphere.sum()), 3)).astype(image.dtype)
