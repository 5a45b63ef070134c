"""Cast shadows of a height field under a directional light, by vectorised ray marching."""

from __future__ import annotations

import numpy as np


def cast_shadow_mask(
    height: np.ndarray,
    pixel_size: float,
    light: np.ndarray,
    *,
    bias_px: float = 0.05,
) -> np.ndarray:
    """Pixels whose ray towards the light is blocked by the height field.

    Every pixel marches towards the light, one pixel per step along the image axis the light
    direction is closer to (so no row or column is skipped); at each step the height field is
    sampled at the shifted positions of all pixels at once. The shift is the same for every
    pixel and whole along that axis, so bilinear interpolation reduces to mixing two shifted
    slices. A pixel is in shadow if the field rises above its ray anywhere. Marching stops once
    the ray has climbed above the field's whole height range or left the frame; beyond the
    frame nothing casts shadows.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights in mm.
    pixel_size : float
        Millimetres per pixel.
    light : np.ndarray
        (3,) direction towards the light (x right, y up, z to camera), with z > 0.
    bias_px : float
        Tolerance, in pixel sizes of height, that stops curved surfaces shadowing
        themselves through interpolation error.

    Returns
    -------
    np.ndarray
        (H, W) bool, True where the light is blocked.
    """
    lx, ly, lz = (float(v) for v in np.asarray(light).ravel())
    if lz <= 0:
        raise ValueError(f"light must be above the plane (z > 0), got {light!r}")
    horizontal = np.hypot(lx, ly)
    field = np.asarray(height, dtype=np.float64)
    if horizontal < 1e-9 * lz:
        return np.zeros(field.shape, dtype=bool)

    # Reorient the field so the march always goes one column to the right per step.
    d_row, d_col = -ly, lx  # image rows grow downwards while y grows upwards
    transposed = abs(d_row) > abs(d_col)
    if transposed:
        field, d_row, d_col = field.T, d_col, d_row
    flipped = d_col < 0
    if flipped:
        field, d_col = field[:, ::-1], -d_col
    field = np.ascontiguousarray(field)
    shadow = _march_right(field, pixel_size, d_row / d_col, lz / horizontal, bias_px)
    if flipped:
        shadow = shadow[:, ::-1]
    return np.ascontiguousarray(shadow.T if transposed else shadow)


def _march_right(field: np.ndarray, pixel_size: float, rows_per_col: float, tan_elevation: float,
                 bias_px: float) -> np.ndarray:
    """Shadow mask for a light towards +column, drifting ``rows_per_col`` rows per column."""
    h, w = field.shape
    lo, hi = float(field.min()), float(field.max())
    rise = tan_elevation * np.hypot(1.0, rows_per_col) * pixel_size  # ray climb per step, mm
    # Compared before dividing: a light a hair above the horizon (2·10⁻³¹³ degrees) climbs a
    # subnormal distance per step, and the quotient overflows to infinity.
    n_steps = w - 1 if hi - lo >= rise * (w - 1) else int(np.ceil((hi - lo) / rise))
    if n_steps <= 0:
        return np.zeros((h, w), dtype=bool)

    # Subtracting the ray's climb from the field once (a ramp along the march) turns "field
    # minus climb at step k" into a plain sample, saving two passes per step.
    ramp = np.arange(w) * rise
    floor = lo - ramp[-1] - 10.0 * (hi - lo) - 1.0
    # float32 halves the memory traffic, which bounds the speed; near-zenith lights make the
    # ramp so steep that its rounding would approach the bias, and need float64.
    tolerance = bias_px * pixel_size
    exact = (max(abs(lo), abs(hi)) + ramp[-1]) * 2.0**-23 > 0.05 * tolerance
    dtype = np.float64 if exact else np.float32
    # One row of floor above and below lets samples straddle the top and bottom edges.
    padded = np.full((h + 2, w), floor, dtype=dtype)
    padded[1:-1] = field - ramp

    horizon = np.full((h, w), floor, dtype=dtype)
    scratch = np.empty(h * w, dtype=dtype)
    extra = np.empty(h * w, dtype=dtype)
    for k in range(1, n_steps + 1):
        shift = k * rows_per_col
        r0 = int(np.floor(shift))
        frac = shift - r0
        # Only pixels whose samples land on the frame need work; the window shrinks as the
        # rays leave it.
        first, stop = max(0, -1 - r0), min(h, h - r0)
        if first >= stop:
            break
        size = (stop - first, w - k)
        # Contiguous scratch of the window's shape: ufuncs run much faster on it than on a
        # strided sub-view.
        sample = scratch[:size[0] * size[1]].reshape(size)
        top = first + r0 + 1
        np.multiply(padded[top:top + size[0], k:], 1.0 - frac, out=sample)
        if frac:
            more = extra[:size[0] * size[1]].reshape(size)
            np.multiply(padded[top + 1:top + 1 + size[0], k:], frac, out=more)
            sample += more
        window = horizon[first:stop, :size[1]]
        np.maximum(window, sample, out=window)
    return horizon + ramp > field + tolerance
