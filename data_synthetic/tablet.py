"""A clay tablet: a low rounded pillow on a flat table, covered in wedge impressions."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .surface import (
    REFERENCE_FOV_MM,
    Surface,
    centred_grid,
    check_shape,
    normals_from_height,
    resolve_pixel_size,
    smooth_noise,
)
from .wedges import random_inscription, rasterize_wedges

#: Linear-RGB clay colour (about sRGB 173, 147, 118) and the cloth it lies on.
CLAY_ALBEDO = np.array([0.42, 0.29, 0.18])
BACKGROUND_ALBEDO = np.array([0.16, 0.17, 0.20])

# Keeps the random streams of different modules apart for the same user seed.
_STREAM = 0x7AB1E7


def _rounded_rect_inset(x: np.ndarray, y: np.ndarray, half_w: float, half_h: float,
                        corner: float) -> np.ndarray:
    """Distance inwards from the edge of a centred rounded rectangle (negative outside)."""
    qx = np.abs(x) - (half_w - corner)
    qy = np.abs(y) - (half_h - corner)
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    inside = np.minimum(np.maximum(qx, qy), 0.0)
    return corner - outside - inside


def clay_tablet(
    shape: tuple[int, int] = (384, 512),
    pixel_size: float | None = None,
    seed: int = 0,
) -> Surface:
    """A rounded clay tablet with lines of cuneiform-like wedge impressions, on a flat
    background.

    Every length scales with the field of view, so at the default pixel size (80 mm across
    the longer side) the tablet is about 64 × 45 mm for a 4:3 frame, rises 3 mm at its rim and
    4.5 mm at its centre, and carries wedges 0.3–1 mm deep. Rim slopes stay below about 50°.

    Parameters
    ----------
    shape : tuple of int
        (H, W) in pixels.
    pixel_size : float, optional
        Millimetres per pixel; default ``80 / max(H, W)``.
    seed : int
        Drives the inscription (wedge positions, directions, sizes, depths) and the albedo
        variation.

    Returns
    -------
    Surface
        Height in mm, normals by finite differences of that height, the tablet as mask.
    """
    shape = check_shape(shape)
    s = resolve_pixel_size(shape, pixel_size)
    scale = max(shape) * s / REFERENCE_FOV_MM
    rng = np.random.default_rng((_STREAM, seed))
    x, y = centred_grid(shape, s)

    half_w, half_h = 0.40 * shape[1] * s, 0.37 * shape[0] * s
    base = min(half_w, half_h)
    rim_height = min(3.0 * scale, 0.15 * base)
    dome_height = 0.5 * rim_height
    rim_width = 1.6 * rim_height
    # The inset distance is smooth only within one corner radius of the edge, so the rim
    # must fit inside it.
    corner = max(rim_width, 0.3 * base)
    inset = _rounded_rect_inset(x, y, half_w, half_h, corner)
    t = np.clip(inset / rim_width, 0.0, 1.0)
    rim = 0.5 - 0.5 * np.cos(np.pi * t)
    pillow = np.clip(1 - (x / half_w) ** 2, 0, None) * np.clip(1 - (y / half_h) ** 2, 0, None)
    body = rim * (rim_height + dome_height * pillow)

    top_w, top_h = half_w - rim_width - 1.0 * scale, half_h - rim_width - 1.0 * scale
    wedges = random_inscription(rng, (-top_w, top_w), (-top_h, top_h), scale)
    impressions = rasterize_wedges(wedges, x, y, s)
    # Pressed clay has rounded creases; smoothing over about a pixel also keeps the sampled
    # field smooth enough for finite-difference normals at any resolution.
    impressions = ndimage.gaussian_filter(impressions, max(0.75, 0.08 * scale / s))
    # At very coarse pixel sizes the smoothing can carry a wedge past the rim; the table
    # stays flat regardless.
    height = np.maximum(body - impressions, 0.0).astype(np.float32)

    mask = inset > 0
    variation = 1.0 + 0.08 * smooth_noise(shape, 6, rng)
    warmth = 0.04 * smooth_noise(shape, 4, rng)
    clay = CLAY_ALBEDO * variation[..., None] * (1.0 + warmth[..., None] * [1.0, 0.2, -0.8])
    albedo = np.where(mask[..., None], clay, BACKGROUND_ALBEDO)
    return Surface(
        height=height,
        normals=normals_from_height(height, s),
        mask=mask,
        albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32),
        pixel_size=s,
        name="tablet",
    )
