"""Synthetic capture defects of the light: room light, and lamps that light the frame unevenly.

For :mod:`ptmcore.illumination`'s tests and benchmark. Each function works on rendered linear
radiance ``(N, H, W, 3)`` (:func:`data_synthetic.render.render`) and the light directions:

* :func:`ambient_frame` — the room's light on the object (what a photograph with the lamps off
  records); :func:`add_ambient` adds it to every photograph;
* gain fields ``(H, W)`` or ``(N, H, W)``, multiplied into the photographs by :func:`apply_gains`:
  :func:`vignetting` (cos⁴ law), :func:`lamp_cone` (a spot whose centre moves from light to
  light), :func:`inverse_square` (a near lamp the ``.lp`` calls distant: its fall-off only);
* :func:`render_board` and :func:`write_board_capture` — a flat board under the same lights and
  gains, the flat-field capture ``ptmcore.illumination.load_flat_field`` reads.

The gains are pure gains: the lamp's direction does not change over the frame, so dividing a
photograph by its gain gives back the clean one exactly (a real near lamp also changes direction,
which no gain undoes).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ptmcore.lp import write_lp

from .encoding import write_jpeg8, write_tiff16

__all__ = [
    "add_ambient",
    "ambient_frame",
    "apply_gains",
    "inverse_square",
    "lamp_cone",
    "render_board",
    "vignetting",
    "write_board_capture",
]


def _unit(lights: np.ndarray) -> np.ndarray:
    d = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _centred(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, float]:
    """Pixel offsets from the frame's centre, x right and y up, and the half-diagonal."""
    h, w = shape
    x = np.arange(w, dtype=np.float64) - (w - 1) / 2
    y = (h - 1) / 2 - np.arange(h, dtype=np.float64)
    return x[None, :], y[:, None], 0.5 * float(np.hypot(h, w))


def ambient_frame(albedo: np.ndarray, level: float, *, gradient: float = 0.0) -> np.ndarray:
    """The room's light on the object: ``level · albedo``, brighter towards one side.

    Parameters
    ----------
    albedo : ndarray, shape (H, W, 3)
        The scene's linear reflectance (:attr:`data_synthetic.surface.Surface.albedo`).
    level : float
        The room's light as a share of a lamp facing the surface (0.1: 10 %).
    gradient : float
        The light grows linearly from ``1 − gradient`` at the left edge to ``1 + gradient`` at
        the right (a window on the right).

    Returns
    -------
    ndarray, shape (H, W, 3), float32
    """
    h, w = albedo.shape[:2]
    across = 1 + gradient * np.linspace(-1, 1, w, dtype=np.float32)
    return (np.float32(level) * albedo * across[None, :, None]).astype(np.float32)


def add_ambient(radiance: np.ndarray, ambient: np.ndarray) -> np.ndarray:
    """Add the room's light to every photograph, in place; returns ``radiance``."""
    radiance += ambient[None]
    return radiance


def vignetting(shape: tuple[int, int], corner: float = 0.7) -> np.ndarray:
    """A lens's natural vignetting, the cos⁴ law, ``(H, W)`` float32, 1 at the centre.

    ``cos⁴ θ = 1 / (1 + (r / f)²)²`` at ``r`` pixels from the centre, the focal length ``f``
    (pixels) chosen so that the corners read ``corner``.
    """
    x, y, half_diagonal = _centred(shape)
    f = half_diagonal / np.sqrt(corner ** -0.5 - 1)
    return (1.0 / (1.0 + (x * x + y * y) / (f * f)) ** 2).astype(np.float32)


def lamp_cone(shape: tuple[int, int], lights: np.ndarray, *, width: float = 0.9, floor: float = 0.25,
              offset: float = 0.3, seed: int = 0) -> np.ndarray:
    """Each lamp's spot: ``floor + (1 − floor) · exp(−d² / 2σ²)``, ``(N, H, W)`` float32.

    The spot's centre lies towards the lamp's side of the frame (a lamp aimed a little short of
    the object's centre), by ``offset`` of the half-diagonal along the lamp's azimuth, plus a
    random aiming error of a third of that; ``σ`` is ``width`` × the half-diagonal. Not
    Gaussian in log (the floor), so the flat field's polynomial has something to fit.
    """
    d = _unit(lights)
    x, y, half_diagonal = _centred(shape)
    rng = np.random.default_rng(seed)
    azimuth = d[:, :2] / np.maximum(np.linalg.norm(d[:, :2], axis=1, keepdims=True), 1e-9)
    centres = half_diagonal * offset * (azimuth + rng.normal(0, 1 / 3, size=azimuth.shape))
    sigma = width * half_diagonal
    out = np.empty((len(d), *shape), np.float32)
    for k, (cx, cy) in enumerate(centres):
        out[k] = floor + (1 - floor) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma * sigma))
    return out


def inverse_square(shape: tuple[int, int], lights: np.ndarray, distance: float = 2.0) -> np.ndarray:
    """The fall-off of near lamps the ``.lp`` takes as distant, ``(N, H, W)`` float32.

    Lamp k stands at ``distance`` × the half-diagonal from the frame's centre along ``l_k``; its
    light at ``x`` is ``|p_k|² / |p_k − x|²`` (1 at the centre). Only the fall-off: the change of
    the lamp's direction over the frame is left out, so that this is a gain.
    """
    d = _unit(lights)
    x, y, half_diagonal = _centred(shape)
    p = d * distance * half_diagonal
    out = np.empty((len(d), *shape), np.float32)
    for k, (px, py, pz) in enumerate(p):
        out[k] = (px * px + py * py + pz * pz) / ((x - px) ** 2 + (y - py) ** 2 + pz * pz)
    return out


def apply_gains(radiance: np.ndarray, *gains: np.ndarray) -> np.ndarray:
    """Multiply ``(N, H, W, 3)`` radiance by gain fields ``(H, W)`` or ``(N, H, W)``, in place."""
    for g in gains:
        g = np.asarray(g, dtype=np.float32)
        radiance *= g[..., None] if g.ndim == 3 else g[None, :, :, None]
    return radiance


def render_board(shape: tuple[int, int], lights: np.ndarray, *gains: np.ndarray, reflectance: float = 0.6,
                 noise: float = 0.003, labels: Sequence[tuple[int, int, int, int]] = (),
                 label_reflectance: float = 0.05, dust: int = 0, seed: int = 0) -> np.ndarray:
    """A flat matte board facing the camera under ``lights`` and the same ``gains``.

    ``reflectance · l_k,z · g_k(x)`` plus Gaussian noise (share of full scale), not clipped.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)``.
    lights : ndarray, shape (N, 3)
    *gains : ndarray
        ``(H, W)`` or ``(N, H, W)`` gain fields.
    reflectance : float
        The board's grey.
    noise : float
        Sensor noise.
    labels : sequence of (x, y, w, h)
        Dark rectangles stuck on the board (a label, a colour chart), reflectance
        ``label_reflectance``.
    dust : int
        Number of small dark specks (3–6 pixels across) scattered over the board.
    seed : int

    Returns
    -------
    ndarray, shape (N, H, W, 3), float32
    """
    d = _unit(lights)
    h, w = shape
    rng = np.random.default_rng(seed)
    board = np.full((h, w), reflectance, np.float32)
    for x0, y0, bw, bh in labels:
        board[y0:y0 + bh, x0:x0 + bw] = label_reflectance
    for _ in range(int(dust)):
        r, c, s = rng.integers(0, h), rng.integers(0, w), rng.integers(3, 7)
        board[r:r + s, c:c + s] *= 0.3
    out = np.empty((len(d), h, w, 3), np.float32)
    out[:] = (board[None, :, :] * d[:, 2, None, None].astype(np.float32))[..., None]
    apply_gains(out, *gains)
    if noise > 0:
        out += np.float32(noise) * rng.standard_normal(out.shape, dtype=np.float32)
    return out


def write_board_capture(folder: str | os.PathLike, radiance: np.ndarray, names: Sequence[str],
                        lights: np.ndarray | None = None, encoding: str = "tiff16") -> list[Path]:
    """Write a flat-field capture: one image per light, and an ``.lp`` when ``lights`` is given.

    Parameters
    ----------
    folder : str or PathLike
        Created if missing.
    radiance : ndarray, shape (N, H, W, 3)
        From :func:`render_board`; clipped to [0, 1] as a camera would.
    names : sequence of str
        File names, one per image (their extension is the encoding's: ``.tif`` or ``.jpg``).
    lights : ndarray, shape (N, 3), optional
        Written as ``flat.lp``.
    encoding : {"tiff16", "jpeg8"}

    Returns
    -------
    list of Path
        The images written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    writer = {"tiff16": write_tiff16, "jpeg8": write_jpeg8}[encoding]
    paths = [folder / n for n in names]
    for p, image in zip(paths, radiance):
        writer(p, image)
    if lights is not None:
        write_lp(folder / "flat.lp", list(names), _unit(lights))
    return paths
