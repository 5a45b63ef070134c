"""Synthetic highlight-RTI captures under a hand-held flash at a finite distance.

A low relief (rolling ground with cuneiform-like wedge impressions, Lambertian, mottled
albedo) lies on the base plane z = 0 with two black glossy spheres resting on that plane
beside it. In each photograph a point light P sits at a jittered dome direction, one to two
image widths from the scene centre. Every surface point X sees its own light direction
(P − X)/|P − X| and an irradiance falling off as 1/|P − X|², so the photographs show the
uneven lighting of a real flash and the spheres' highlights point at the flash from two
different places: triangulating them gives the flash's position.

Frame and units: pixels; pixel (row, col) lies at x = col, y = −row (y up) and the relief's
height z above the base plane; the camera is orthographic (view (0, 0, 1)). Spheres are given
as (cx, cy, r) in image coordinates (cx = column, cy = row); their centres are at height r.
Sphere pixels are averaged over a supersampling grid so their limbs are anti-aliased; cast
shadows (of the spheres or the relief) are not rendered.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from ptmcore.lp import write_lp
from ptmcore.nearlight import image_centre, write_light_positions
from reconstruct.calibration.reflection import sphere_normal_at

from .encoding import write_mask_png, write_npy, write_png8, write_tiff16
from .lights import dome_lights
from .spheres import check_spheres
from .surface import REFERENCE_FOV_MM, centred_grid, normals_from_height, smooth_noise
from .wedges import random_inscription, rasterize_wedges

_SUPERSAMPLE = 4
_TINT = np.array([0.50, 0.40, 0.30])
# Keeps this module's random stream apart from the other scenes' for the same seed.
_STREAM = 0x2EA7


@dataclass(frozen=True)
class NearLightCaptureInfo:
    """What :func:`render_nearlight_capture` wrote.

    Attributes
    ----------
    folder : Path
        The capture folder.
    image_paths : tuple of Path
        The photographs, in light order.
    positions : np.ndarray
        (N, 3) float64 true light positions in pixels (x = column, y = −row, z above the
        base plane).
    directions : np.ndarray
        (N, 3) unit directions from the scene centre (image centre on the base plane) to the
        lights, as in ``truth.lp``.
    spheres : tuple of (float, float, float)
        (cx, cy, r) in pixels; centres at height r above the base plane.
    shape : tuple of int
        (H, W).
    pixel_size : float
        Millimetres per pixel (``height.npy`` is in mm).
    truth_lp : Path
        ``truth.lp``: the directions from the scene centre.
    positions_csv : Path
        ``light_positions_truth.csv``: the true positions (:mod:`ptmcore.nearlight` format).
    ground_truth_dir : Path
        ``ground_truth/`` with ``normals.npy``, ``height.npy`` (mm), ``albedo.npy``,
        ``mask.png`` (the relief without the spheres) and ``scene.json``.
    """

    folder: Path
    image_paths: tuple[Path, ...]
    positions: np.ndarray
    directions: np.ndarray
    spheres: tuple[tuple[float, float, float], ...]
    shape: tuple[int, int]
    pixel_size: float
    truth_lp: Path
    positions_csv: Path
    ground_truth_dir: Path


def default_spheres(shape: tuple[int, int]) -> tuple[tuple[float, float, float], ...]:
    """Two spheres in opposite corners, radius a fifth of the shorter side.

    At the default 384×512 they are 154 pixels across.
    """
    h, w = shape
    r = 0.2 * min(h, w)
    mx, my = r + 0.03 * w, r + 0.04 * h
    return ((mx, my, r), (w - 1 - mx, h - 1 - my, r))


def _relief(shape: tuple[int, int], pixel_size: float, rng: np.random.Generator) -> np.ndarray:
    """Heights in pixels: rolling ground with wedge impressions pressed into it."""
    h, w = shape
    ground = smooth_noise(shape, 8, rng)
    ground = 0.006 * max(h, w) * (ground - ground.min())
    scale = max(h, w) * pixel_size / REFERENCE_FOV_MM
    x, y = centred_grid(shape, pixel_size)
    half_w, half_h = 0.45 * w * pixel_size, 0.42 * h * pixel_size
    wedges = random_inscription(rng, (-half_w, half_w), (-half_h, half_h), scale)
    depth = rasterize_wedges(wedges, x, y, pixel_size) / pixel_size
    depth = ndimage.gaussian_filter(depth, max(0.75, 0.08 * scale / pixel_size))
    return ground + depth.max() - depth


def _shade(normals: np.ndarray, points: np.ndarray, light: np.ndarray, d0: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cosine n·l, irradiance (d0/|P − X|)² and unit l at surface points for a point light."""
    d = light - points
    dist2 = np.einsum("...c,...c->...", d, d)
    l = d / np.sqrt(dist2)[..., None]
    return np.einsum("...c,...c->...", normals, l), d0 * d0 / dist2, l


def _checked_arguments(shape, n_lights: int, encoding: str, distance, pixel_size
                       ) -> tuple[int, int, float, float, float]:
    """Validate :func:`render_nearlight_capture`'s arguments.

    Returns
    -------
    tuple
        ``(h, w, lo, hi, s)``: the image size, the distance range in image widths and the
        pixel size in mm.
    """
    try:
        h, w = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape must be (height, width), got {shape!r}") from None
    if h < 32 or w < 32:
        raise InputError(f"images must be at least 32×32 pixels, got {h}×{w}")
    if n_lights < 3:
        raise InputError(f"need at least 3 lights, got {n_lights}")
    if encoding not in ("png", "tiff16"):
        raise InputError(f"unknown encoding {encoding!r}; choose png or tiff16")
    lo, hi = (float(v) for v in distance)
    if not (np.isfinite([lo, hi]).all() and 0 < lo <= hi):
        raise InputError(f"distance must be (lo, hi) image widths with 0 < lo ≤ hi, got {distance!r}")
    s = REFERENCE_FOV_MM / max(h, w) if pixel_size is None else float(pixel_size)
    if not (np.isfinite(s) and s > 0):
        raise InputError(f"pixel_size must be a positive number of mm, got {pixel_size!r}")
    return h, w, lo, hi, s


def _sphere_patch(sphere: tuple[float, float, float]) -> tuple:
    """Sub-samples of a sphere's bounding box: which of them fall on the sphere, and the
    sphere's normal and 3D point there.

    Returns
    -------
    tuple
        ``(r0, r1, c0, c1, inside, normals, points)``: the box's pixel rows and columns, the
        ``(ss·(r1 − r0), ss·(c1 − c0))`` bool sub-samples on the disc, and ``(n, 3)`` unit
        normals and points (pixels) at those.
    """
    cx, cy, r = sphere
    ss = _SUPERSAMPLE
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    r0, r1 = int(np.floor(cy - r)) - 1, int(np.ceil(cy + r)) + 2
    c0, c1 = int(np.floor(cx - r)) - 1, int(np.ceil(cx + r)) + 2
    ys = (np.arange(r0, r1)[:, None] + sub).ravel()
    xs = (np.arange(c0, c1)[:, None] + sub).ravel()
    normals_s = sphere_normal_at(xs[None, :], ys[:, None], (cx, cy, r))
    inside = normals_s[..., 2] > 0  # off the disc the normal is clamped to the limb
    n_s = normals_s[inside]
    x_s = np.array([cx, -cy, r]) + r * n_s
    return r0, r1, c0, c1, inside, n_s, x_s


def _paint_sphere(img: np.ndarray, patch: tuple, light: np.ndarray, d0: float,
                  shininess: float, specular: float, sphere_albedo: float) -> None:
    """Shade a sphere's sub-samples (a :func:`_sphere_patch`) under the point light and
    average them, with the image's own pixels elsewhere, into `img` in place."""
    r0, r1, c0, c1, inside, n_s, x_s = patch
    ss = _SUPERSAMPLE
    ndotl, irr_s, l_s = _shade(n_s, x_s, light, d0)
    # Phong: r·v with v = +z is the z component of the mirror direction 2(n·l)n − l.
    rdotv = np.clip(2.0 * ndotl * n_s[:, 2] - l_s[:, 2], 0.0, None)
    rad = irr_s * (sphere_albedo * np.clip(ndotl, 0.0, None)
                   + specular * np.where(ndotl > 0, rdotv ** shininess, 0.0))
    fine = np.repeat(np.repeat(img[r0:r1, c0:c1], ss, 0), ss, 1)
    fine[inside] = rad[:, None]
    img[r0:r1, c0:c1] = fine.reshape(r1 - r0, ss, c1 - c0, ss, 3).mean(axis=(1, 3))


def _relief_mask(shape: tuple[int, int], spheres) -> np.ndarray:
    """The object, as a bool image: the relief without the sphere discs (and their
    anti-aliased limbs)."""
    h, w = shape
    mask = np.ones((h, w), dtype=bool)
    yy, xx = np.ogrid[0:h, 0:w]
    for cx, cy, r in spheres:
        mask &= np.hypot(xx - cx, yy - cy) > r + 2.0
    return mask


def render_nearlight_capture(
    out_dir: str | os.PathLike,
    *,
    shape: tuple[int, int] = (384, 512),
    n_lights: int = 24,
    spheres=None,
    distance: tuple[float, float] = (1.0, 2.0),
    seed: int = 0,
    encoding: str = "png",
    pixel_size: float | None = None,
    shininess: float = 500.0,
    specular: float = 3.0,
    sphere_albedo: float = 0.02,
    noise: float = 0.003,
) -> NearLightCaptureInfo:
    """Render and write a highlight-RTI capture lit by a flash at a finite distance.

    Light k sits at ``centre + d_k · u_k``: u_k from :func:`dome_lights` (15°–75°
    elevation, jittered), d_k uniform in ``distance`` × the image width, the centre being
    the image centre on the base plane. A surface point X receives ``(d̄/|P − X|)²`` with
    d̄ the middle of the distance range, so a light at the mean distance is about as bright
    as the unit distant light of the other synthetic captures. The relief reflects
    ``albedo · max(0, n·l)`` with its own l per pixel; the spheres reflect
    ``sphere_albedo · max(0, n·l) + specular · max(0, r·v)^shininess`` (r the mirror image
    of their own l), times the falloff, averaged over a 4×4 grid per pixel.

    Parameters
    ----------
    out_dir : str or PathLike
        Folder to write into (created if needed).
    shape : tuple of int
        (H, W) of the photographs.
    n_lights : int
        Number of photographs.
    spheres : sequence of (cx, cy, r), optional
        Spheres in image coordinates; default :func:`default_spheres`.
    distance : (lo, hi)
        Range of the light distances from the scene centre, in image widths.
    seed : int
        Seeds the relief, the light jitter and distances, and the sensor noise.
    encoding : {"png", "tiff16"}
        8-bit sRGB PNG or 16-bit linear TIFF.
    pixel_size : float, optional
        Millimetres per pixel, for ``height.npy`` (default 80 mm across the longer side).
    shininess, specular, sphere_albedo, noise : float
        The spheres' Phong exponent and peak, their diffuse albedo, the sensor noise (std,
        full scale 1).

    Returns
    -------
    NearLightCaptureInfo
    """
    h, w, lo, hi, s = _checked_arguments(shape, n_lights, encoding, distance, pixel_size)
    sph = check_spheres(default_spheres((h, w)) if spheres is None else spheres, (h, w))

    out = Path(out_dir)
    gt_dir = out / "ground_truth"
    try:
        gt_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the capture folder: {exc.strerror}", out) from None

    rng = np.random.default_rng((_STREAM, seed))
    height = _relief((h, w), s, rng)
    normals = normals_from_height(height, 1.0).astype(np.float64)
    albedo = _TINT * np.clip(1.0 + 0.15 * smooth_noise((h, w), 30, rng), 0.5, 1.5)[..., None]
    centre = image_centre((h, w))
    directions = dome_lights(n_lights, seed=seed)
    dists = rng.uniform(lo, hi, n_lights) * w
    positions = centre + dists[:, None] * directions
    d0 = 0.5 * (lo + hi) * w

    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    points = np.stack([cols, -rows, height], axis=-1)

    patches = [_sphere_patch(sphere) for sphere in sph]

    noise_rng = np.random.default_rng((_STREAM, seed, 1))
    paths = []
    ext = ".png" if encoding == "png" else ".tif"
    for k, light in enumerate(positions):
        cosine, irradiance, _ = _shade(normals, points, light, d0)
        img = albedo * (np.clip(cosine, 0.0, None) * irradiance)[..., None]
        for patch in patches:
            _paint_sphere(img, patch, light, d0, shininess, specular, sphere_albedo)
        img += noise_rng.normal(0.0, noise, img.shape)
        path = out / f"img_{k:03d}{ext}"
        if encoding == "png":
            write_png8(path, img)
        else:
            write_tiff16(path, img)
        paths.append(path)

    names = [p.name for p in paths]
    truth_lp = out / "truth.lp"
    write_lp(truth_lp, names, directions)
    positions_csv = out / "light_positions_truth.csv"
    write_light_positions(positions_csv, names, positions)

    write_npy(gt_dir / "normals.npy", normals.astype(np.float32))
    write_npy(gt_dir / "height.npy", (height * s).astype(np.float32))
    write_npy(gt_dir / "albedo.npy", albedo.astype(np.float32))
    write_mask_png(gt_dir / "mask.png", _relief_mask((h, w), sph))
    description = {
        "scene": "nearlight",
        "shape": [h, w],
        "pixel_size_mm": s,
        "height_units": "mm",
        "frame": "pixels: x = column, y = -row, z above the base plane; orthographic view +z",
        "seed": int(seed),
        "spheres": [list(t) for t in sph],
        "sphere_centre_height": "radius (resting on the base plane)",
        "lights": {"count": n_lights, "distance_widths": [lo, hi],
                   "reference_distance_px": d0, "file": positions_csv.name},
        "encoding": encoding,
        "render": {"shininess": shininess, "specular": specular,
                   "sphere_albedo": sphere_albedo, "noise": noise, "cast_shadows": False},
    }
    with atomic_write(gt_dir / "scene.json", "w") as f:
        json.dump(description, f, indent=2)
    return NearLightCaptureInfo(folder=out, image_paths=tuple(paths), positions=positions,
                                directions=directions, spheres=sph, shape=(h, w), pixel_size=s,
                                truth_lp=truth_lp, positions_csv=positions_csv,
                                ground_truth_dir=gt_dir)
