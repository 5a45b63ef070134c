"""The ground-truth surface type shared by all synthetic scenes, and helpers to build one.

Geometry follows ``docs/CONVENTIONS.md``: x to the right, y up, z towards the camera, heights
in millimetres, normals ∝ (−∂z/∂x, −∂z/∂y, 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

#: Field of view (mm across the longer image side) used when no pixel size is given, so a
#: scene describes the same physical object at every resolution.
REFERENCE_FOV_MM = 80.0


@dataclass(frozen=True, eq=False)
class Surface:
    """A synthetic object with known geometry and reflectance.

    Attributes
    ----------
    height : np.ndarray
        (H, W) float32 height above the background plane, in millimetres.
    normals : np.ndarray
        (H, W, 3) float32 unit normals (x right, y up, z towards the camera).
    mask : np.ndarray
        (H, W) bool, True on the object (the whole frame for scenes without background).
    albedo : np.ndarray
        (H, W, 3) float32 linear RGB reflectance in [0, 1].
    pixel_size : float
        Millimetres per pixel.
    name : str
        The scene name (a key of ``data_synthetic.SCENES``).
    """

    height: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    pixel_size: float
    name: str

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the pixel grid."""
        return (int(self.height.shape[0]), int(self.height.shape[1]))


def check_shape(shape: tuple[int, int]) -> tuple[int, int]:
    """Validate an image shape.

    Parameters
    ----------
    shape : tuple of int
        (H, W), each at least 8 pixels.

    Returns
    -------
    tuple of int
        (H, W) as plain ints.

    Raises
    ------
    ValueError
        If the shape is not two integers ≥ 8.
    """
    try:
        h, w = (int(v) for v in shape)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"shape must be (H, W), got {shape!r}") from exc
    if h < 8 or w < 8:
        raise ValueError(f"shape must be at least 8×8 pixels, got {shape!r}")
    return h, w


def resolve_pixel_size(shape: tuple[int, int], pixel_size: float | None) -> float:
    """Pixel size in mm, defaulting to the reference field of view across the longer side.

    Parameters
    ----------
    shape : tuple of int
        (H, W).
    pixel_size : float or None
        Millimetres per pixel, or None for ``REFERENCE_FOV_MM / max(H, W)``.

    Returns
    -------
    float
        Millimetres per pixel.
    """
    if pixel_size is None:
        return REFERENCE_FOV_MM / max(shape)
    if not np.isfinite(pixel_size) or pixel_size <= 0:
        raise ValueError(f"pixel_size must be a positive number of mm, got {pixel_size!r}")
    return float(pixel_size)


def centred_grid(shape: tuple[int, int], pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates in mm relative to the image centre (x right, y up).

    Parameters
    ----------
    shape : tuple of int
        (H, W).
    pixel_size : float
        Millimetres per pixel.

    Returns
    -------
    x, y : np.ndarray
        Float64 arrays of shapes (1, W) and (H, 1), broadcastable to (H, W).
    """
    h, w = shape
    x = (np.arange(w, dtype=np.float64) - (w - 1) / 2.0) * pixel_size
    y = -(np.arange(h, dtype=np.float64) - (h - 1) / 2.0) * pixel_size
    return x[None, :], y[:, None]


def normals_from_height(height: np.ndarray, pixel_size: float) -> np.ndarray:
    """Unit normals of a height field by second-order finite differences.

    Parameters
    ----------
    height : np.ndarray
        (H, W) heights in mm.
    pixel_size : float
        Millimetres per pixel.

    Returns
    -------
    np.ndarray
        (H, W, 3) float32 unit normals ∝ (−∂z/∂x, −∂z/∂y, 1); rows go down while y goes
        up, hence ∂z/∂y = −∂z/∂row.
    """
    d_row, d_col = np.gradient(np.asarray(height, dtype=np.float64), edge_order=2)
    n = np.stack([-d_col / pixel_size, d_row / pixel_size, np.ones_like(d_row)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def smooth_noise(shape: tuple[int, int], cells: int, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-std low-frequency noise that looks the same at every resolution.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of the output.
    cells : int
        Number of random control values across the longer side; fewer means smoother.
    rng : np.random.Generator
        Source of the control values.

    Returns
    -------
    np.ndarray
        (H, W) float64.
    """
    h, w = shape
    # Control values live on a coarse grid tied to the field of view, not to pixels, so the
    # pattern only gets sampled more finely as the resolution grows.
    ch = max(2, round(cells * h / max(h, w))) + 3
    cw = max(2, round(cells * w / max(h, w))) + 3
    coarse = rng.standard_normal((ch, cw))
    rows = 1.0 + (np.arange(h) + 0.5) / h * (ch - 3)
    cols = 1.0 + (np.arange(w) + 0.5) / w * (cw - 3)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    field = ndimage.map_coordinates(coarse, [rr, cc], order=3, mode="nearest")
    return (field - field.mean()) / max(field.std(), 1e-12)
