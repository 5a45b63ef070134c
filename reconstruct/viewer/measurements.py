"""Measurements of the preview window as files: a height profile as CSV and as a figure, a
distance as CSV; and free numbered names in the result's ``preview/`` folder.

Every file is written atomically (:func:`ptmcore.atomic.atomic_write`).
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write

__all__ = ["free_stem", "profile_figure", "write_distance_csv", "write_profile_csv"]


def free_stem(folder: str | os.PathLike, stem: str, suffixes: tuple[str, ...]) -> Path:
    """``folder/stem`` (made if missing), numbered ``stem_1``, ``stem_2``… until no file of
    that stem with any of `suffixes` exists."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    k = 0
    while True:
        candidate = folder / (f"{stem}_{k}" if k else stem)
        if not any(candidate.with_name(candidate.name + s).exists() for s in suffixes):
            return candidate
        k += 1


def _csv_bytes(header: list[str], rows: np.ndarray) -> bytes:
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(header)
    # NaN (off the object) becomes an empty field, which spreadsheets read as missing.
    writer.writerows([["" if not np.isfinite(v) else f"{v:.6g}" for v in row] for row in rows])
    return text.getvalue().encode()


def write_profile_csv(path: str | os.PathLike, along: np.ndarray, xy: np.ndarray, heights: np.ndarray,
                      unit: str) -> Path:
    """Write a height profile: one row per sample, ``along``, ``x``, ``y`` and ``height`` in
    `unit` (the column names say it); heights off the object are empty.

    Parameters
    ----------
    along : numpy.ndarray
        ``(n,)`` distance from the first point.
    xy : numpy.ndarray
        ``(n, 2)`` sample positions (x right, y up; y = −row × pixel size).
    heights : numpy.ndarray
        ``(n,)``, NaN off the object.
    """
    u = unit.replace(" ", "_")
    rows = np.column_stack([along, xy[:, 0], xy[:, 1], heights])
    path = Path(path)
    with atomic_write(path, "wb") as f:
        f.write(_csv_bytes([f"along_{u}", f"x_{u}", f"y_{u}", f"height_{u}"], rows))
    return path


def write_distance_csv(path: str | os.PathLike, p0: np.ndarray, p1: np.ndarray, unit: str) -> Path:
    """Write a measured distance: the two points (x, y, z) and their distance, in `unit`."""
    u = unit.replace(" ", "_")
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    row = np.concatenate([p0, p1, [np.linalg.norm(p1 - p0)]])[None]
    names = [f"{a}{k}_{u}" for k in (0, 1) for a in "xyz"] + [f"distance_{u}"]
    path = Path(path)
    with atomic_write(path, "wb") as f:
        f.write(_csv_bytes(names, row))
    return path


def profile_figure(along: np.ndarray, heights: np.ndarray, unit: str, size: tuple[int, int],
                   *, title: str = "") -> np.ndarray:
    """The height profile drawn as a chart, ``(h, w, 3)`` uint8 for `size` = ``(w, h)`` pixels.

    Both axes are in the scene's unit at a free aspect (a relief of tenths of a millimetre
    along tens of millimetres would otherwise be a flat line); the title states the depth.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = int(size[0]), int(size[1])
    dpi = 100
    fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    known = np.isfinite(heights)
    if known.sum() >= 2:
        ax.plot(along, heights, color="#1f4e9c", linewidth=1.6)
        depth = float(np.ptp(heights[known]))
        ax.set_title(f"{title}height profile: range {depth:.3g} {unit} over {float(along[-1]):.3g} {unit}",
                     fontsize=10)
    else:
        ax.set_title(f"{title}height profile: the line misses the object", fontsize=10)
    ax.set_xlabel(f"along the line ({unit})", fontsize=9)
    ax.set_ylabel(f"height ({unit})", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.3)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
