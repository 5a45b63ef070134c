"""A synthetic laser scan: noisy points on the true surface, in an unknown rigid pose."""

from __future__ import annotations

import os

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from reconstruct.mesh.ply import write_binary_ply
from .surface import Surface

# Keeps the random streams of different modules apart for the same user seed.
_STREAM = 0x5CA9


def random_rigid_transform(
    rng: np.random.Generator,
    angle_range_deg: tuple[float, float] = (10.0, 40.0),
    translation_range_mm: tuple[float, float] = (20.0, 60.0),
) -> np.ndarray:
    """A random rotation about a random axis followed by a random translation.

    Parameters
    ----------
    rng : np.random.Generator
        Source of randomness.
    angle_range_deg : tuple of float
        Range of the rotation angle.
    translation_range_mm : tuple of float
        Range of the translation's length.

    Returns
    -------
    np.ndarray
        (4, 4) float64 homogeneous transform ``[[R, t], [0, 1]]``.
    """
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(*angle_range_deg))
    rotation = Rotation.from_rotvec(angle * axis).as_matrix()
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = direction * rng.uniform(*translation_range_mm)
    return transform


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 homogeneous transform to (N, 3) points.

    Parameters
    ----------
    transform : np.ndarray
        (4, 4) transform.
    points : np.ndarray
        (N, 3) points.

    Returns
    -------
    np.ndarray
        (N, 3) float64 transformed points.
    """
    points = np.asarray(points, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def sample_scan(
    surface: Surface,
    n_points: int | None = None,
    *,
    noise_mm: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample a laser scan of ``surface`` and move it by a random rigid transform.

    Points are drawn uniformly over the frame; each lies on the true surface (the height
    field, bilinearly interpolated) at x = col·s, y = −row·s, z = height, with Gaussian noise
    of ``noise_mm`` added to z. Then the returned transform is applied.

    Parameters
    ----------
    surface : Surface
        The scene.
    n_points : int, optional
        Number of points; default one per four pixels.
    noise_mm : float
        Standard deviation of the depth noise, in mm.
    seed : int
        Drives positions, noise and the transform.

    Returns
    -------
    points : np.ndarray
        (n_points, 3) float32 points in the scan's frame, mm.
    transform : np.ndarray
        (4, 4) float64 transform that maps the ground-truth frame onto the scan's frame;
        its inverse brings the points back onto the surface.
    """
    h, w = surface.shape
    if n_points is None:
        n_points = h * w // 4
    rng = np.random.default_rng((_STREAM, seed))
    transform = random_rigid_transform(rng)
    rows = rng.uniform(0, h - 1, n_points)
    cols = rng.uniform(0, w - 1, n_points)
    z = ndimage.map_coordinates(surface.height.astype(np.float64), [rows, cols], order=1)
    z += rng.normal(0.0, noise_mm, n_points)
    s = surface.pixel_size
    true_points = np.stack([cols * s, -rows * s, z], axis=1)
    return apply_transform(transform, true_points).astype(np.float32), transform


def write_ply(path: str | os.PathLike, points: np.ndarray, comment: str = "") -> None:
    """Write points as a binary little-endian PLY point cloud (float x, y, z).

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    points : np.ndarray
        (N, 3) points.
    comment : str
        One line stored as a PLY comment.
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    comments = [comment] if comment else []
    write_binary_ply(path, dict(zip(("x", "y", "z"), points.T)), comments=comments)
