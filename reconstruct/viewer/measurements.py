"""Measurements of the preview window and their files: a height profile as CSV and as a
figure, a distance as CSV; and free numbered names in the result's ``preview/`` folder.

Every file is written atomically (:func:`ptmcore.atomic.atomic_write`).
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write
from reconstruct.report import plots
from reconstruct.report.summary import unit_words

__all__ = [
    "Measurement",
    "export_measurement",
    "free_paths",
    "profile_figure",
    "rgb_pixels",
    "write_distance_csv",
    "write_profile_csv",
]


@dataclass(frozen=True)
class Measurement:
    """A two-point measurement of the window, as it was made.

    Attributes
    ----------
    kind : str
        ``"distance"`` or ``"profile"``: what was measured, and so what is exported.
    p0, p1 : numpy.ndarray
        ``(3,)`` end points in true heights (without the view's exaggeration).
    along : numpy.ndarray
        ``(n,)`` distance from `p0` along the line, in the scene's unit.
    xy : numpy.ndarray
        ``(n, 2)`` the samples' positions on the image plane.
    heights : numpy.ndarray
        ``(n,)`` surface height at the samples (NaN off the object).
    """

    kind: str
    p0: np.ndarray
    p1: np.ndarray
    along: np.ndarray
    xy: np.ndarray
    heights: np.ndarray


def free_paths(folder: str | os.PathLike, stem: str, suffixes: tuple[str, ...]) -> list[Path]:
    """``folder/stem + suffix`` for each of `suffixes` (the folder made if missing), all
    numbered ``stem_1``, ``stem_2``… until none of them exists.

    The suffixes are appended, never put in place of the stem's own: a stem with dots
    (``tablet_v1.2_profile``) keeps its whole name.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    k = 0
    while True:
        base = f"{stem}_{k}" if k else stem
        paths = [folder / (base + s) for s in suffixes]
        if not any(p.exists() for p in paths):
            return paths
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
                   *, title: str = ""):
    """The height profile drawn as a chart: a matplotlib ``Figure`` of `size` = ``(w, h)``
    pixels (:func:`reconstruct.report.plots.figure`).

    Both axes are in the scene's unit at a free aspect (a relief of tenths of a millimetre
    along tens of millimetres would otherwise be a flat line); the title states the depth.
    """
    fig = plots.figure(int(size[0]), int(size[1]))
    ax = fig.add_subplot()
    words = unit_words(unit)
    known = np.isfinite(heights)
    if known.sum() >= 2:
        ax.plot(along, heights, color="#1f4e9c", linewidth=1.6)
        depth = float(np.ptp(heights[known]))
        ax.set_title(f"{title}height profile: range {depth:.3g} {words} over {float(along[-1]):.3g} {words}",
                     fontsize=10)
    else:
        ax.set_title(f"{title}height profile: the line misses the object", fontsize=10)
    ax.set_xlabel(f"along the line ({words})", fontsize=9)
    ax.set_ylabel(f"height ({words})", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.3)
    return fig


def rgb_pixels(fig) -> np.ndarray:
    """A matplotlib figure drawn on its Agg canvas, ``(h, w, 3)`` uint8."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def export_measurement(measurement: Measurement, folder: str | os.PathLike, name: str, unit: str,
                       png_size: tuple[int, int]) -> list[Path]:
    """Write a measurement into `folder` under free names (:func:`free_paths`): a profile as
    ``<name>_profile.csv`` and a `png_size` chart ``<name>_profile.png``, a distance as
    ``<name>_distance.csv``. Returns the files written."""
    m = measurement
    if m.kind == "profile":
        csv_path, png_path = free_paths(folder, f"{name}_profile", (".csv", ".png"))
        write_profile_csv(csv_path, m.along, m.xy, m.heights, unit)
        chart = plots.png(profile_figure(m.along, m.heights, unit, png_size, title=f"{name}: "))
        with atomic_write(png_path, "wb") as f:
            f.write(chart)
        return [csv_path, png_path]
    (csv_path,) = free_paths(folder, f"{name}_distance", (".csv",))
    return [write_distance_csv(csv_path, m.p0, m.p1, unit)]
