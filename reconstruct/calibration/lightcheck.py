"""Checking a light layout before (or without) taking the photographs.

:func:`check_lights` summarises a dome or a set of hand-held light positions: whether the six
PTM coefficients are all determined (rank and condition of the light matrix, and why not),
how the lights are spread in elevation and azimuth, and how much of the hemisphere is near
some light. :func:`report_text` turns it into a few lines for the command line and
:func:`write_polar_plot` draws the layout as a PNG, each light labelled with its photograph
(:func:`short_labels`).

Angles follow the project frame: azimuth 0° is a light from the right (+x), 90° from the top
(+y); elevation is measured from the object's plane, 90° straight above it (+z). Lights
without a photograph's name are numbered from 1, as the lines of an ``.lp`` file.
"""

from __future__ import annotations

import functools
import io
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ptmcore.atomic import atomic_write
from ptmcore.colourtags import srgb_save_options
from ptmcore.relight import light_angles
from ptmcore.solvers import LP_PRECISION, RankInfo, analyse_lights, duplicate_groups

__all__ = ["LightReport", "check_lights", "plot_positions", "polar_plot_png", "report_text", "short_labels",
           "write_polar_plot"]

#: Edges (degrees) of the elevation histogram and of the plot's rings.
ELEVATION_EDGES = np.arange(0.0, 91.0, 15.0)

#: Above this condition number of the light matrix, noise in the photographs is amplified
#: noticeably in the coefficients (a well-spread 24-light dome is about 10).
CONDITION_WARNING = 100.0

#: An azimuth gap wider than this leaves slopes facing that way lit only by extrapolation.
GAP_WARNING_DEG = 90.0

#: Without a light below this elevation there is no raking light to show fine relief.
RAKING_DEG = 30.0

#: Lights closer than this to the zenith have no meaningful azimuth.
_ZENITH_DEG = 89.9

#: Points of the equal-area hemisphere lattice used for the coverage (±1/n accuracy).
_COVERAGE_SAMPLES = 20000

#: Margin around the plot's rim, as a fraction of the image size (room for azimuth labels).
PLOT_MARGIN = 0.1


@dataclass
class LightReport:
    """What a light layout is good for.

    Attributes
    ----------
    count : int
        Number of lights.
    rank : RankInfo
        Rank of the PTM light matrix and why it is below 6.
    condition : float
        Condition number of the determined part of the light matrix (``rank.condition``).
    elevation_range : tuple of float
        Lowest and highest elevation, degrees.
    elevation_edges : ndarray, shape (7,)
        Histogram bin edges, degrees: 0, 15, …, 90 (the last bin includes 90°).
    elevation_counts : ndarray, shape (6,)
        Lights per elevation bin; lights at or below the horizon are in none.
    azimuth_gap : float
        Largest azimuth range without a light, degrees (360 with fewer than two lights that
        have an azimuth; lights within 0.1° of the zenith have none).
    azimuth_gap_start : float
        Azimuth where that gap starts, counter-clockwise, degrees in [0, 360).
    coverage : float
        Fraction of the upper hemisphere's solid angle within `coverage_radius` of a light.
    coverage_radius : float
        Degrees.
    warnings : list of str
        Problems in plain words; empty for a good layout.
    """

    count: int
    rank: RankInfo
    condition: float
    elevation_range: tuple[float, float]
    elevation_edges: np.ndarray
    elevation_counts: np.ndarray
    azimuth_gap: float
    azimuth_gap_start: float
    coverage: float
    coverage_radius: float
    warnings: list[str]


def _unit(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0:
        raise ValueError(f"expected light directions of shape (N, 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if not np.all(np.isfinite(d)) or np.any(norm < 1e-12):
        raise ValueError("light directions must be finite and non-zero")
    return d / norm


@functools.lru_cache(maxsize=1)
def _hemisphere_lattice() -> np.ndarray:
    # Fibonacci lattice with z uniform in (0, 1): on a sphere, equal steps in z enclose equal
    # areas (Archimedes), so every point stands for the same solid angle.
    k = np.arange(_COVERAGE_SAMPLES, dtype=np.float64)
    z = (k + 0.5) / _COVERAGE_SAMPLES
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _coverage(unit: np.ndarray, radius_deg: float) -> float:
    dist, _ = cKDTree(unit).query(_hemisphere_lattice(), k=1)
    # Chord length of an angle θ on the unit sphere is 2·sin(θ/2).
    return float(np.mean(dist <= 2.0 * math.sin(math.radians(radius_deg) / 2.0)))


def _largest_gap(azim: np.ndarray) -> tuple[float, float]:
    if len(azim) < 2:
        return 360.0, float(azim[0]) if len(azim) else 0.0
    a = np.sort(azim)
    gaps = np.diff(np.append(a, a[0] + 360.0))
    k = int(np.argmax(gaps))
    return float(gaps[k]), float(a[k])


def check_lights(
    directions: np.ndarray,
    *,
    coverage_radius: float = 15.0,
    precision: float = LP_PRECISION,
) -> LightReport:
    """Summarise a light layout without any photographs.

    Parameters
    ----------
    directions : ndarray, shape (N, 3)
        Vectors towards the lights (x right, y up, z towards the camera); normalised here.
    coverage_radius : float
        Angular radius, degrees, for :attr:`LightReport.coverage`.
    precision : float
        Precision of the directions, for the rank decision
        (see :func:`ptmcore.solvers.rank_tolerance`).

    Returns
    -------
    LightReport

    Raises
    ------
    ValueError
        If `directions` is not (N, 3), or holds zero or non-finite vectors.
    """
    unit = _unit(directions)
    n = len(unit)
    info = analyse_lights(unit, precision=precision)
    azim, elev = light_angles(unit)
    # Binning to 0.001° keeps a lamp at 30° in the 30–45° bin: sin 30° is not exact in binary,
    # and an .lp file's six decimals can make it read 29.99999°.
    counts, _ = np.histogram(np.round(elev, 3), bins=ELEVATION_EDGES)
    gap, gap_start = _largest_gap(azim[elev < _ZENITH_DEG])
    coverage = _coverage(unit, coverage_radius)

    warnings: list[str] = []
    if info.rank < 6:
        warnings.append(
            f"the light matrix has rank {info.rank} of 6: not all six PTM coefficients are determined"
        )
        warnings += info.causes
    else:
        for g in duplicate_groups(unit, precision=precision):
            names = [str(k + 1) for k in g]
            warnings.append(
                f"duplicate light directions (photographs {', '.join(names[:-1])} and {names[-1]}): "
                "they average noise but add no new direction"
            )
    if info.rank > 0 and info.condition > CONDITION_WARNING:
        warnings.append(
            f"ill-conditioned light layout (condition number {info.condition:.0f}): noise in the "
            "photographs is strongly amplified in the fitted coefficients"
        )
    low = np.flatnonzero(elev <= 0.0)
    if len(low):
        warnings.append(
            f"{len(low)} light{'s are' if len(low) > 1 else ' is'} at or below the horizon "
            f"(photograph{'s' if len(low) > 1 else ''} {', '.join(str(k + 1) for k in low)})"
        )
    if gap >= 360.0:
        warnings.append(
            f"all lights come from azimuth {gap_start:.0f}°: surfaces facing any other way are lit "
            "only by extrapolation"
            if np.any(elev < _ZENITH_DEG)
            else "all lights are at the zenith: no light comes from any side"
        )
    elif gap > GAP_WARNING_DEG:
        end = (gap_start + gap) % 360.0
        warnings.append(
            f"no light from azimuth {gap_start:.0f}° to {end:.0f}° (a gap of {gap:.0f}°): surfaces "
            "facing that way are lit only by extrapolation"
        )
    if elev.min() > RAKING_DEG:
        warnings.append(
            f"no raking light: the lowest light is at {elev.min():.1f}° elevation, so relighting "
            f"below {RAKING_DEG:.0f}° is extrapolated"
        )
    return LightReport(
        count=n,
        rank=info,
        condition=info.condition,
        elevation_range=(float(elev.min()), float(elev.max())),
        elevation_edges=ELEVATION_EDGES.copy(),
        elevation_counts=counts,
        azimuth_gap=gap,
        azimuth_gap_start=gap_start,
        coverage=coverage,
        coverage_radius=float(coverage_radius),
        warnings=warnings,
    )


def report_text(report: LightReport) -> str:
    """A few readable lines describing a :class:`LightReport`, for the command line."""
    e = report.elevation_edges
    bins = ", ".join(f"{e[k]:.0f}–{e[k + 1]:.0f}°: {c}" for k, c in enumerate(report.elevation_counts))
    lo, hi = report.elevation_range
    plural = "s" if report.count != 1 else ""
    if report.azimuth_gap >= 360.0:
        azimuth = "all lights from one azimuth"
    else:
        start, gap = report.azimuth_gap_start, report.azimuth_gap
        azimuth = f"largest azimuth gap {gap:.1f}° (from {start:.1f}° to {(start + gap) % 360.0:.1f}°)"
    lines = [
        f"{report.count} light{plural}, elevation {lo:.1f}° to {hi:.1f}° ({bins})",
        f"rank {report.rank.rank} of 6, condition number {report.condition:.3g} "
        f"(singular values at or below {report.rank.tolerance:.2g} count as zero)",
        f"{azimuth}; {100 * report.coverage:.0f}% of the hemisphere within "
        f"{report.coverage_radius:.0f}° of a light",
    ]
    lines += [f"warning: {w}" for w in report.warnings]
    if not report.warnings:
        lines.append("no problems found")
    return "\n".join(lines)


def plot_positions(directions: np.ndarray, size: int) -> np.ndarray:
    """Where :func:`write_polar_plot` draws each light, in pixels.

    The plot's centre is ``(size/2, size/2)`` and its rim has radius
    ``R = size·(1/2 − PLOT_MARGIN)``. A light at elevation e and azimuth φ is at radius
    ``ρ = R·(90° − e)/90°`` and ``(x, y) = (size/2 + ρ·cos φ, size/2 − ρ·sin φ)``, so 0° (from
    the right) is to the right and 90° (from the top) is up. Pixel (col, row) covers
    ``[col, col + 1) × [row, row + 1)``. The drawn dots are within half a pixel of these
    positions (matplotlib snaps markers to pixel centres).

    Parameters
    ----------
    directions : ndarray, shape (N, 3)
    size : int
        Width and height of the image.

    Returns
    -------
    ndarray, shape (N, 2)
        x (towards the right) and y (downwards) in pixels.
    """
    azim, elev = light_angles(_unit(directions))
    rho = size * (0.5 - PLOT_MARGIN) * (90.0 - elev) / 90.0
    phi = np.radians(azim)
    return np.stack([size / 2 + rho * np.cos(phi), size / 2 - rho * np.sin(phi)], axis=1)


def _stem(name: str) -> str:
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    return base.rsplit(".", 1)[0] if "." in base[1:] else base


def _shared_prefix(texts: list[str]) -> int:
    """Length of the prefix all ``texts`` share, short of a number it would cut in two."""
    n = len(os.path.commonprefix(texts))
    # "img_010", "img_011" share "img_01": the labels must read 010 and 011, not 0 and 1.
    while n and texts[0][n - 1].isdigit():
        n -= 1
    return n


def short_labels(names: Sequence[str]) -> list[str]:
    """Short labels for photographs: their names without folder, extension, and the prefix
    and suffix every name shares (``IMG_0012.JPG`` … → ``0012`` …), numbers kept whole.

    Parameters
    ----------
    names : sequence of str
        Photograph file names (or paths).

    Returns
    -------
    list of str
        One label per name; the names' stems where shortening would leave a label empty or
        two alike.
    """
    stems = [_stem(str(n)) for n in names]
    if len(stems) < 2:
        return stems
    start = _shared_prefix(stems)
    end = _shared_prefix([s[::-1] for s in stems])
    labels = [s[start:len(s) - end] for s in stems]
    if not all(labels) or len(set(labels)) < len(set(stems)):
        return stems
    return labels


def write_polar_plot(
    path: str | os.PathLike,
    directions: np.ndarray,
    *,
    names: Sequence[str] | None = None,
    title: str | None = None,
    size: int = 640,
) -> None:
    """Draw a light layout as a polar plot PNG.

    Azimuth runs around (0° = light from the right, 90° = from the top), elevation is the
    radius (90° at the centre, 0° at the rim) with labelled rings every 15°. Each light is a
    dark dot labelled with its photograph (:func:`short_labels` of ``names``), or its number
    from 1 without names; see :func:`plot_positions` for the exact geometry.

    Parameters
    ----------
    path : str or PathLike
        Destination PNG, written atomically.
    directions : ndarray, shape (N, 3)
        Vectors towards the lights.
    names : sequence of str, optional
        The photograph of each light (file names or paths).
    title : str, optional
        Drawn in the top-left corner.
    size : int
        Width and height in pixels (at least 200).
    """
    with atomic_write(path, "wb") as f:
        f.write(polar_plot_png(directions, names=names, title=title, size=size))


def polar_plot_png(
    directions: np.ndarray,
    *,
    names: Sequence[str] | None = None,
    title: str | None = None,
    size: int = 640,
) -> bytes:
    """The PNG bytes of :func:`write_polar_plot` (for a page that embeds it), tagged as sRGB."""
    if size < 200:
        raise ValueError(f"plot size must be at least 200 pixels, got {size}")
    fig = _polar_figure(directions, names, title, size)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi, pil_kwargs=srgb_save_options("PNG"))
    return buf.getvalue()


def _polar_figure(directions: np.ndarray, names: Sequence[str] | None, title: str | None, size: int):
    """The matplotlib figure of :func:`write_polar_plot`, on a polar axes of its own."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    azim, elev = light_angles(_unit(directions))
    if names is not None and len(names) != len(elev):
        raise ValueError(f"{len(names)} names for {len(elev)} lights")
    labels = short_labels(names) if names is not None else [str(k + 1) for k in range(len(elev))]
    dpi = 100
    pt = 72.0 / dpi  # points per pixel
    small, label = max(10, size // 50) * pt, max(11, size // 45) * pt
    grid, ink = "#c8c8c8", "#5a5a5a"
    # A figure of its own (no pyplot), so plots can be drawn from several threads at once.
    fig = Figure(figsize=(size / dpi, size / dpi), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    # The axes' square spans the image less the margins, so its rim is where plot_positions
    # puts it.
    ax = fig.add_axes((PLOT_MARGIN, PLOT_MARGIN, 1 - 2 * PLOT_MARGIN, 1 - 2 * PLOT_MARGIN),
                      projection="polar")
    ax.set_theta_zero_location("E")
    ax.set_ylim(0.0, 90.0)  # the radius is 90° − elevation
    rings = ELEVATION_EDGES[1:-1]
    ax.set_yticks(90.0 - rings, [f"{el:.0f}°" for el in rings], fontsize=small, color=ink)
    ax.set_rlabel_position(85.0)  # just right of the upward spoke
    ax.set_thetagrids(np.arange(0, 360, 30), [f"{az}°" for az in range(0, 360, 30)],
                      fontsize=label, color=ink)
    # Azimuth labels halfway across the margin.
    ax.tick_params(axis="x", pad=0.45 * size * PLOT_MARGIN * pt - label / 2)
    ax.grid(color=grid, linewidth=1.0)
    ax.spines["polar"].set_color("#787878")

    dot = max(4.0, size / 110)
    theta, rho = np.radians(azim), 90.0 - elev
    # Unclipped, so lights at or below the horizon show on or beyond the rim.
    ax.plot(theta, rho, "o", ms=2 * dot * pt, mfc="#14286e", mec="black", mew=1.0,
            linestyle="none", clip_on=False, zorder=3)
    for text, t, r in zip(labels, theta, rho):
        ax.annotate(text, (t, r), xytext=(dot + 1, dot + 1), textcoords="offset pixels",
                    fontsize=small, color="black", annotation_clip=False, zorder=4)

    legend = "radius: elevation (90° centre, 0° rim) · angle: azimuth (0° = light from the right)"
    fig.text(0.5, 0.25 * PLOT_MARGIN, legend, ha="center", va="center", fontsize=small, color=ink)
    if title:
        fig.text(3 / size, 1 - 3 / size, title, ha="left", va="top", fontsize=label)
    return fig
