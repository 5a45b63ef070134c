"""Accuracy against ground truth (synthetic captures, or a benchmark's reference normals)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError
from ptmcore.images import read_image
from ptmcore.normals import angular_error
from reconstruct.surface.normalmaps import read_npy


@dataclass
class GroundTruth:
    """Reference data of a capture, as ``data_synthetic`` writes it in ``ground_truth/``.

    Attributes
    ----------
    normals : ndarray, shape (H, W, 3), float32
    mask : ndarray, shape (H, W), bool
        Where the object is.
    height : ndarray, shape (H, W), float32, or None
        Height in millimetres.
    source : Path or None
        The file the normals came from, for messages.
    """

    normals: np.ndarray
    mask: np.ndarray
    height: np.ndarray | None = None
    source: Path | None = None


def load_ground_truth(folder: str | os.PathLike, shape: tuple[int, int] | None = None,
                      against: str = "the photographs") -> GroundTruth:
    """Read ``normals.npy``, ``mask.png`` and (if present) ``height.npy`` from a folder.

    Parameters
    ----------
    folder : str or PathLike
    shape : tuple of int, optional
        ``(H, W)`` the normals must have.
    against : str
        What gives that size, for the message.

    Raises
    ------
    InputError
        If ``normals.npy`` is missing or not an ``(H, W, 3)`` float array (see
        :func:`reconstruct.surface.normalmaps.read_npy`) of ``shape``, or the mask or
        heights are unreadable or of another size.
    """
    folder = Path(folder)
    normals_file = folder / "normals.npy"
    normals = read_npy(normals_file, "ground-truth normals file")
    if normals.dtype.kind != "f" or normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(f"ground-truth normals must be an H×W×3 float array, got {normals.dtype} "
                         f"of shape {normals.shape}", normals_file)
    if shape is not None and normals.shape[:2] != tuple(shape):
        raise InputError(f"ground-truth normals are {normals.shape[1]}×{normals.shape[0]} pixels but "
                         f"{against} are {shape[1]}×{shape[0]}", normals_file)
    normals = normals.astype(np.float32)
    shape = normals.shape[:2]
    mask_file = folder / "mask.png"
    # A broken link or a folder in the file's place is reported, not taken for no mask.
    mask = read_image(mask_file) > 0 if os.path.lexists(mask_file) else np.ones(shape, bool)
    if mask.ndim == 3:
        mask = mask.any(axis=2)
    if mask.shape != shape:
        raise InputError(f"ground-truth mask is {mask.shape[1]}×{mask.shape[0]} pixels but its normals "
                         f"are {shape[1]}×{shape[0]}", mask_file)
    height_file = folder / "height.npy"
    height = None
    if os.path.lexists(height_file):
        height = read_npy(height_file, "ground-truth height file")
        if height.dtype.kind not in "iuf" or height.shape != shape:
            raise InputError(f"ground-truth heights must be a {shape[1]}×{shape[0]} array of numbers "
                             f"(as its normals), got {height.dtype} of shape {height.shape}", height_file)
        height = height.astype(np.float32)
    return GroundTruth(normals, mask, height, normals_file)


def normal_accuracy(normals: np.ndarray, truth: GroundTruth) -> dict[str, float]:
    """Mean, median and 95th percentile of the angular error (degrees) inside the mask."""
    if normals.shape != truth.normals.shape:
        (h, w), (th, tw) = normals.shape[:2], truth.normals.shape[:2]
        raise InputError(f"ground-truth normals are {tw}×{th} pixels but the result is {w}×{h}", truth.source)
    err = angular_error(normals, truth.normals, truth.mask)
    return {
        "mean_deg": float(err.mean()),
        "median_deg": float(np.median(err)),
        "p95_deg": float(np.percentile(err, 95)),
        "pixels": int(err.size),
    }


def height_rmse(height: np.ndarray, truth: GroundTruth) -> float | None:
    """RMS height error inside the mask after removing the mean offset (height's unit)."""
    if truth.height is None:
        return None
    m = truth.mask & np.isfinite(height)
    d = height[m].astype(np.float64) - truth.height[m]
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))
