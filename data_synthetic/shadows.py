"""Cast shadows of a height field under a directional light, by vectorised ray marching."""

from __future__ import annotations

import numpy as np


def cast_shadow_mask(
    height: np.ndarray,
    pixel_size: float,
    light: np.ndarray,
    *,
    step_px: float = 1.0,
    bias_px: float = 0.05,
) -> np.ndarray:
    """Pixels whose ray towards the light is blocked by the height field.

    Every pixel marches towards the light in steps of ``step_px`` along the image plane; at
    each step the height field is sampled bilinearly at the shifted positions of all pixels at
    once (the shift is the same for every pixel, so this is four shifted slices). A pixel is in
    shadow if the field rises above its ray anywhere. Marching stops once the ray has climbed
    above the whole field's height range. Beyond the frame nothing casts shadows.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights in mm.
    pixel_size : float
        Millimetres per pixel.
    light : np.ndarray
        (3,) direction towards the light (x right, y up, z to camera), with z > 0.
    step_px : float
        March step in pixels; 1 does not skip features one pixel wide.
    bias_px : float
        Tolerance, in pixel sizes of height, that stops curved surfaces shadowing
        themselves through interpolation error.

    Returns
    -------
    np.ndarray
        (H, W) bool, True where the light is blocked.
    """
    lx, ly, lz = (float(v) for v in light)
    horizontal = np.hypot(lx, ly)
    if lz <= 0:
        raise ValueError(f"light must be above the plane (z > 0), got {light!r}")
    h, w = height.shape
    if horizontal < 1e-9 * lz:
        return np.zeros((h, w), dtype=bool)
    field = np.asarray(height, dtype=np.float32)
    lo, hi = float(field.min()), float(field.max())
    rise = lz / horizontal * step_px * pixel_size  # mm the ray climbs per step
    n_steps = int(np.ceil((hi - lo) / rise))
    if n_steps == 0:
        return np.zeros((h, w), dtype=bool)
    d_row, d_col = -ly / horizontal * step_px, lx / horizontal * step_px

    # Pad with a floor far below the field so samples beyond the frame never block the ray,
    # even after bilinear mixing with a real edge value.
    pad = int(np.ceil(n_steps * step_px)) + 2
    floor = lo - 10.0 * (hi - lo) - 1.0
    padded = np.full((h + 2 * pad, w + 2 * pad), floor, dtype=np.float32)
    padded[pad:pad + h, pad:pad + w] = field

    # Track the highest (field − ray climb) seen; comparing once at the end is cheaper than
    # comparing at every step.
    horizon = np.full((h, w), floor, dtype=np.float32)
    sample = np.empty((h, w), dtype=np.float32)
    term = np.empty((h, w), dtype=np.float32)
    for k in range(1, n_steps + 1):
        r, c = k * d_row, k * d_col
        r0, c0 = int(np.floor(r)), int(np.floor(c))
        fr, fc = np.float32(r - r0), np.float32(c - c0)
        top, left = pad + r0, pad + c0
        np.multiply(padded[top:top + h, left:left + w], (1 - fr) * (1 - fc), out=sample)
        for dr, dc, weight in ((0, 1, (1 - fr) * fc), (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
            if weight:
                np.multiply(padded[top + dr:top + dr + h, left + dc:left + dc + w], weight,
                            out=term)
                sample += term
        sample -= np.float32(k * rise)
        np.maximum(horizon, sample, out=horizon)
    return horizon > field + np.float32(bias_px * pixel_size)
