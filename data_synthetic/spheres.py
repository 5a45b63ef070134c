"""Synthetic "highlight RTI" captures: a dull scene with black glossy spheres beside it.

Each photograph is lit by one distant light; the light direction can be read back from the
mirror highlight on each sphere. The camera is orthographic and the frame is the project's:
x right, y up, z towards the camera; pixel (row, col) has its centre at image coordinates
(x_img, y_img) = (col, row), and sphere centres are given in those coordinates.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError
from ptmcore.lp import write_lp

from .encoding import write_jpeg8
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
    """

    folder: Path
    image_paths: tuple[Path, ...]
    directions: np.ndarray
    spheres: tuple[tuple[float, float, float], ...]
    hidden: tuple[int, ...]
    truth_lp: Path
    shape: tuple[int, int]


def _write_png8(path: Path, radiance: np.ndarray) -> None:
    """Write linear radiance as an 8-bit sRGB PNG, atomically."""
    from PIL import Image

    from ptmcore.atomic import atomic_write
    from ptmcore.images import linear_to_srgb

    pixels = np.round(linear_to_srgb(radiance) * 255.0).astype(np.uint8)
    with atomic_write(path, "wb") as f:
        Image.fromarray(pixels).save(f, format="PNG")


def _check_spheres(spheres, shape: tuple[int, int]) -> tuple[tuple[float, float, float], ...]:
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
) -> SphereCaptureInfo:
    """Render and write a highlight-RTI capture with black glossy spheres.

    The scene is a dull Lambertian plane with a low textured relief and a varying albedo,
    plus the spheres: albedo ``sphere_albedo`` and a white Phong lobe
    ``specular · max(0, r·v)^shininess`` (r the mirror reflection of the light, v = +z), so
    the highlight sits where the sphere normal bisects light and view. Pixels are averaged
    over a 3×3 supersampling grid so sphere limbs are anti-aliased like a real lens would.
    Shadows cast by the spheres are not rendered.

    Parameters
    ----------
    out_dir : str or PathLike
        Folder to write into (created if needed).
    shape : tuple of int
        (H, W) of the photographs.
    n_lights : int
        Number of photographs; directions from :func:`dome_lights` (15°–75°, jittered).
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
        Phong exponent and peak, diffuse albedo of the spheres, sensor noise (std, full
        scale 1).

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
    sph = _check_spheres(spheres, (h, w))
    hidden = tuple(sorted({int(k) for k in hidden}))
    if any(k < 0 or k >= n_lights for k in hidden):
        raise InputError(f"hidden photographs must be in 0..{n_lights - 1}, got {hidden}")

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the capture folder: {exc.strerror}", out) from None

    rng = np.random.default_rng(seed)
    lights = dome_lights(n_lights, seed=seed)

    # Background: a gently rolling plane with a mottled albedo, rendered at pixel resolution
    # (it has no sharp edges), then upsampled onto the supersampling grid by repetition.
    relief = 2.0 * smooth_noise((h, w), 12, rng)
    bg_normals = normals_from_height(relief, 1.0).astype(np.float64)
    tint = np.array([0.55, 0.47, 0.38])
    bg_albedo = tint * np.clip(1.0 + 0.15 * smooth_noise((h, w), 30, rng), 0.5, 1.5)[..., None]

    ss = _SUPERSAMPLE
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    cols = (np.arange(w)[:, None] + sub[None, :]).ravel()
    rows = (np.arange(h)[:, None] + sub[None, :]).ravel()
    X, Y = np.meshgrid(cols, rows)  # (H·ss, W·ss) image coordinates of the sub-samples
    sphere_id = np.full(X.shape, -1, dtype=np.int32)
    sn = np.zeros(X.shape + (3,))
    for i, (cx, cy, r) in enumerate(sph):
        u, v = (X - cx) / r, (cy - Y) / r  # y up: rows go down
        rho2 = u * u + v * v
        inside = rho2 < 1.0
        sphere_id[inside] = i
        sn[inside] = np.stack([u[inside], v[inside], np.sqrt(1.0 - rho2[inside])], axis=-1)
    on_sphere = sphere_id >= 0
    n_sph = sn[on_sphere]  # (M, 3)

    bg_up_normals = np.repeat(np.repeat(bg_normals, ss, 0), ss, 1)
    bg_up_albedo = np.repeat(np.repeat(bg_albedo, ss, 0), ss, 1)

    paths = []
    ext = ".png" if encoding == "png" else ".jpg"
    for k, light in enumerate(lights):
        img = bg_up_albedo * np.clip(bg_up_normals @ light, 0, None)[..., None]
        ndotl = n_sph @ light
        sphere_rad = sphere_albedo * np.clip(ndotl, 0, None)
        if k not in hidden:
            # Phong: r·v with v = +z is the z component of the mirror direction 2(n·l)n − l.
            rdotv = np.clip(2.0 * ndotl * n_sph[:, 2] - light[2], 0, None)
            sphere_rad = sphere_rad + specular * np.where(ndotl > 0, rdotv ** shininess, 0.0)
        img[on_sphere] = sphere_rad[:, None]
        img = img.reshape(h, ss, w, ss, 3).mean(axis=(1, 3))
        img += rng.normal(0.0, noise, img.shape)
        path = out / f"img_{k:03d}{ext}"
        if encoding == "png":
            _write_png8(path, img.astype(np.float32))
        else:
            write_jpeg8(path, img.astype(np.float32), quality=95)
        paths.append(path)

    truth_lp = out / "truth.lp"
    write_lp(truth_lp, [p.name for p in paths], lights)
    np.save(out / "truth.npy", lights)
    return SphereCaptureInfo(folder=out, image_paths=tuple(paths), directions=lights,
                             spheres=sph, hidden=hidden, truth_lp=truth_lp, shape=(h, w))
