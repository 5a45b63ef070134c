"""A spherical cap on a flat plane, with analytic normals."""

from __future__ import annotations

import numpy as np

from .surface import Surface, centred_grid, check_shape, resolve_pixel_size

#: Linear-RGB albedo of the matte cap and of the plane under it.
SPHERE_ALBEDO = np.array([0.5, 0.5, 0.5])
BACKGROUND_ALBEDO = np.array([0.16, 0.17, 0.20])


def sphere_cap(
    shape: tuple[int, int] = (384, 512),
    pixel_size: float | None = None,
    seed: int = 0,
    *,
    radius_mm: float | None = None,
    max_slope_deg: float = 70.0,
) -> Surface:
    """A matte spherical cap centred in the frame, cut where its slope reaches ``max_slope_deg``.

    Parameters
    ----------
    shape : tuple of int
        (H, W) in pixels.
    pixel_size : float, optional
        Millimetres per pixel; default ``80 / max(H, W)``.
    seed : int
        Unused: the cap is fully determined by its geometry. Accepted so every scene in
        ``SCENES`` has the same call signature.
    radius_mm : float, optional
        Sphere radius; default so the cap's footprint spans 84 % of the shorter side.
    max_slope_deg : float
        Slope at the cap's rim, where it meets the plane (0 < slope ≤ 89).

    Returns
    -------
    Surface
        Height in mm (the plane at 0), exact normals at the pixel centres, the cap as mask,
        uniform albedo.
    """
    del seed
    shape = check_shape(shape)
    s = resolve_pixel_size(shape, pixel_size)
    if not 0 < max_slope_deg <= 89:
        raise ValueError(f"max_slope_deg must be in (0, 89], got {max_slope_deg!r}")
    rim_angle = np.deg2rad(max_slope_deg)
    if radius_mm is None:
        radius_mm = 0.42 * min(shape) * s / np.sin(rim_angle)
    if radius_mm <= 0:
        raise ValueError(f"radius_mm must be positive, got {radius_mm!r}")
    x, y = centred_grid(shape, s)
    r2 = x**2 + y**2
    mask = r2 < (radius_mm * np.sin(rim_angle)) ** 2
    z_sphere = np.sqrt(np.clip(radius_mm**2 - r2, 0.0, None))
    height = np.where(mask, z_sphere - radius_mm * np.cos(rim_angle), 0.0)
    xx, yy = np.broadcast_arrays(x, y)
    on_sphere = np.stack([xx, yy, z_sphere], axis=-1) / radius_mm
    normals = np.where(mask[..., None], on_sphere, [0.0, 0.0, 1.0])
    albedo = np.where(mask[..., None], SPHERE_ALBEDO, BACKGROUND_ALBEDO)
    return Surface(
        height=height.astype(np.float32),
        normals=normals.astype(np.float32),
        mask=mask,
        albedo=albedo.astype(np.float32),
        pixel_size=s,
        name="sphere",
    )
