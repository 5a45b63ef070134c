"""Small in-memory stacks for unit tests (no files)."""

import numpy as np

from ptmcore.images import ImageStack


def stack_from_luminance(values: np.ndarray, saturated: np.ndarray | None = None) -> ImageStack:
    """An ImageStack holding linear luminance ``values`` (N, H, W) in [0, 1]."""
    lum = np.round(np.clip(values, 0, 1) * 65534).astype(np.uint16)
    if saturated is not None:
        lum[saturated] = 65535
    n, h, w = values.shape
    return ImageStack(lum, np.ones((h, w, 3), np.float32), [], 16, False, (lum == 65535).sum(axis=(1, 2)))


def dome(n: int = 40, seed: int = 0, min_elev: float = 15.0, max_elev: float = 75.0) -> np.ndarray:
    """Random unit light directions spread over a dome."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(min_elev, max_elev, n))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)


def sphere_normals(h: int, w: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere seen from +z (y up) and its mask."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (cols - (w - 1) / 2) / radius
    y = -(rows - (h - 1) / 2) / radius
    r2 = x * x + y * y
    mask = r2 < 0.95**2
    z = np.sqrt(np.clip(1 - r2, 0, 1))
    n = np.stack([x, y, z], -1)
    n[~mask] = (0, 0, 1)
    return n.astype(np.float32), mask
