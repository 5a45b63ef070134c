"""Outputs of a reconstruction-versus-scan comparison: coloured PLY, histogram and overlay.

The functions take plain arrays (vertices, faces, points, signed distances in mm and the
statistics as a dict), so they do not depend on how the distances were computed
(:mod:`reconstruct.compare.signed_distance`). All of them colour distances with the same
diverging map, :func:`diverging_colors`: blue for negative, white at 0, red for positive,
clipped to ±limit, so the PLY, the histogram and the overlay read alike.

Every file is written through :func:`ptmcore.atomic.atomic_write`.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.colourtags import srgb_save_options
from ptmcore.png import write_png
from reconstruct.mesh.ply import write_binary_ply
from reconstruct.report import rendering

# matplotlib and pyvista are imported on use: they are slow to import and only the
# histogram and the overlay need them.
if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "DEFAULT_SIGN_CONVENTION",
    "NAN_COLOR",
    "default_limit",
    "distance_lookup_table",
    "diverging_colors",
    "write_distance_ply",
    "write_histogram",
    "write_overlay",
]

# ColorBrewer RdBu (11 classes), blue end first, with the centre pushed from #f7f7f7 to pure
# white so that "no deviation" is unmistakable and distinct from the grey of unknown values.
_RDBU = np.array(
    [
        (5, 48, 97),
        (33, 102, 172),
        (67, 147, 195),
        (146, 197, 222),
        (209, 229, 240),
        (255, 255, 255),
        (253, 219, 199),
        (244, 165, 130),
        (214, 96, 77),
        (178, 24, 43),
        (103, 0, 31),
    ],
    dtype=np.float64,
)
_RDBU_T = np.linspace(-1.0, 1.0, len(_RDBU))

#: Colour of vertices or points without a distance (NaN): a mid grey, not on the map.
NAN_COLOR = (150, 150, 150)

#: Sign convention written into outputs unless the caller states its own.
#: It is :mod:`reconstruct.compare.signed_distance`'s, for distances of scan points and
#: reverse distances.
DEFAULT_SIGN_CONVENTION = (
    "d > 0: the scan lies on the camera side of the reconstruction (where its normals point)"
)

_UNIT = "mm"


def diverging_colors(values: np.ndarray, limit: float) -> np.ndarray:
    """Map signed values to a blue–white–red diverging colour map.

    Piecewise-linear ColorBrewer RdBu: ``-limit`` and below are dark blue ``(5, 48, 97)``,
    0 is white, ``+limit`` and above dark red ``(103, 0, 31)``. Infinities are clipped like
    any value; NaN gets :data:`NAN_COLOR`.

    Parameters
    ----------
    values : numpy.ndarray
        Values of any shape (typically ``(N,)`` signed distances in mm).
    limit : float
        Positive value mapped to the saturated ends.

    Returns
    -------
    numpy.ndarray
        ``values.shape + (3,)`` uint8 sRGB colours.

    Raises
    ------
    ValueError
        If `limit` is not a positive finite number.
    """
    limit = float(limit)
    if not (math.isfinite(limit) and limit > 0):
        raise ValueError(f"limit must be a positive number, not {limit}")
    values = np.asarray(values, dtype=np.float64)
    known = ~np.isnan(values)
    t = np.clip(np.where(known, values, 0.0) / limit, -1.0, 1.0)
    # One np.interp per channel is vectorised over all values; the table is tiny.
    rgb = np.stack([np.interp(t, _RDBU_T, _RDBU[:, k]) for k in range(3)], axis=-1)
    out = np.rint(rgb).astype(np.uint8)
    out[~known] = NAN_COLOR
    return out


def _nice_ceil(x: float) -> float:
    """The smallest of 1, 2, 2.5, 5 × 10^k that is ≥ `x` (> 0)."""
    exponent = math.floor(math.log10(x))
    for mantissa in (1.0, 2.0, 2.5, 5.0, 10.0):
        # The tolerance keeps 0.2 from becoming 0.25 through float rounding of 10^k.
        nice = mantissa * 10.0**exponent
        if nice >= x * (1 - 1e-9):
            return float(nice)
    return float(10.0 ** (exponent + 1))  # pragma: no cover - mantissa 10 always matches


def default_limit(distances: np.ndarray) -> float:
    """A colour-map limit: the 95th percentile of |d|, rounded up to a nice number.

    Rounding up to 1, 2, 2.5 or 5 × 10^k gives round scalar-bar labels, and the 95th
    percentile keeps a few outliers (edges, holes) from washing the map out.

    Parameters
    ----------
    distances : numpy.ndarray
        Signed distances; NaN and infinities are ignored.

    Returns
    -------
    float
        A positive limit. Falls back to max |d| when the percentile is 0, and to 1.0 (mm)
        when there are no non-zero finite distances.
    """
    d = np.abs(np.asarray(distances, dtype=np.float64).ravel())
    d = d[np.isfinite(d)]
    if d.size == 0:
        return 1.0
    level = float(np.percentile(d, 95))
    if level <= 0:
        level = float(d.max())
    if level <= 0:
        return 1.0
    return _nice_ceil(level)


def _format_mm(x: float) -> str:
    """A length with at most 4 significant digits and no exponent for report-sized values."""
    return f"{x:.4g}"


def write_distance_ply(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray | None,
    distances: np.ndarray,
    limit: float,
    *,
    comments: Iterable[str] = (),
    sign_convention: str = DEFAULT_SIGN_CONVENTION,
) -> None:
    """Write a mesh or point cloud coloured by signed distance as binary PLY.

    Vertex properties: ``x y z`` (float), ``red green blue`` (uchar, from
    :func:`diverging_colors`; NaN distances grey) and ``quality`` (float, the signed
    distance in mm, NaN where unknown), which MeshLab can re-map to its own colour scales.
    Faces, when given, as ``list uchar int vertex_indices``. The header comments state the
    unit, the colour range and the sign convention.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    vertices : numpy.ndarray
        ``(V, 3)`` positions in mm.
    faces : numpy.ndarray or None
        ``(F, 3)`` vertex indices, or None for a point cloud (e.g. the scan points).
    distances : numpy.ndarray
        ``(V,)`` signed distances in mm, NaN where unknown.
    limit : float
        Colour range ±limit (mm).
    comments : iterable of str
        Extra header comments, one line each.
    sign_convention : str
        What a positive distance means; written as a comment.

    Raises
    ------
    ValueError
        For mismatched shapes, out-of-range face indices, a bad `limit` or a multi-line
        comment.
    InputError
        If the file cannot be written.
    """
    vertices = np.asarray(vertices)
    distances = np.asarray(distances, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), not {vertices.shape}")
    n = len(vertices)
    if distances.shape != (n,):
        raise ValueError(f"distances must be ({n},) like the vertices, not {distances.shape}")
    lim = _format_mm(float(limit))
    n_known = int(np.count_nonzero(~np.isnan(distances)))
    header = [
        f"unit {_UNIT}",
        (
            f"colour: signed distance, blue = -{lim} {_UNIT} or less, white = 0, "
            f"red = +{lim} {_UNIT} or more (ColorBrewer RdBu, linear)"
        ),
        (
            f"colour grey {NAN_COLOR[0]} {NAN_COLOR[1]} {NAN_COLOR[2]} = no distance "
            f"({n - n_known} of {n} vertices)"
        ),
        f"quality = signed distance in {_UNIT} (NaN = unknown)",
        f"sign convention: {sign_convention}",
        *comments,
    ]
    vertex = dict(zip(("x", "y", "z"), vertices.astype(np.float32).T))
    vertex.update(zip(("red", "green", "blue"), diverging_colors(distances, limit).T))
    vertex["quality"] = distances.astype(np.float32)
    write_binary_ply(path, vertex, faces, comments=header)


# --- histogram ---------------------------------------------------------------------------

# Labels of the statistics printed beside the histogram, in order; values are mm unless noted.
_STAT_LABELS = (
    ("mean", "mean"),
    ("std", "std"),
    ("rms", "RMS"),
    ("median_abs", "median |d|"),
    ("p95_abs", "95th pct |d|"),
    ("max_abs", "max |d|"),
)
_TOLERANCE_BAND = (226, 240, 226)
_TOLERANCE_LINE = (0, 120, 0)
_BAR_EDGE = (90, 90, 90)
_GREY_TEXT = (60, 60, 60)
_DPI = 100


def _rgb(color: Iterable[int]) -> tuple[float, ...]:
    """An 8-bit colour as matplotlib's fractions."""
    return tuple(c / 255 for c in color)


def _summary(
    distances: np.ndarray, stats: Mapping[str, float], tolerance: float | None
) -> dict[str, float]:
    """The statistics to print: those given, the missing ones computed from `distances`."""
    d = distances
    a = np.abs(d)
    computed: dict[str, float] = {}
    if d.size:
        computed = {
            "mean": float(d.mean()),
            "std": float(d.std()),
            "rms": float(np.sqrt(np.mean(d * d))),
            "median_abs": float(np.median(a)),
            "p95_abs": float(np.percentile(a, 95)),
            "max_abs": float(a.max()),
        }
        if tolerance is not None:
            computed["within_tolerance"] = float(np.mean(a <= tolerance))
    computed["count"] = float(d.size)
    out = dict(computed)
    out.update({k: float(v) for k, v in stats.items() if v is not None})
    return out


def _bins(d: np.ndarray, limit: float, tolerance: float | None) -> tuple[np.ndarray, float]:
    """Bin edges over ±extent: the colour limit, widened to the 99th percentile of |d| and
    past the tolerance, rounded up to a nice number."""
    a = np.abs(d)
    extent = max(float(limit), float(np.percentile(a, 99)) if a.size else 0.0)
    if tolerance is not None:
        extent = max(extent, float(tolerance) * 1.2)
    extent = _nice_ceil(extent) if extent > 0 else 1.0
    # An odd number of bins puts one bar centred on 0, which reads as "no deviation".
    n_bins = 2 * int(np.clip(math.sqrt(max(d.size, 1)) / 2, 7, 40)) + 1
    return np.linspace(-extent, extent, n_bins + 1), extent


def _stat_lines(
    summary: Mapping[str, float], unit: str, tolerance: float | None, limit: float,
    outside: int, extent: float,
) -> list[tuple[str, str]]:
    """(label, value) rows of the statistics panel."""
    lines = [(label, f"{summary[key]:.4g} {unit}") for key, label in _STAT_LABELS
             if key in summary]
    # reconstruct.compare.signed_distance names it overlap_fraction.
    overlap = summary.get("overlap", summary.get("overlap_fraction"))
    lines.append(("overlap", "n/a" if overlap is None else f"{100 * overlap:.1f} %"))
    lines.append(("count", f"{int(summary['count']):,}"))
    if tolerance is not None:
        lines.append(("tolerance", f"±{tolerance:g} {unit}"))
        within = summary.get("within_tolerance")
        lines.append(("within", "n/a" if within is None else f"{100 * within:.1f} %"))
    lines.append(("colour range", f"±{limit:g} {unit}"))
    if outside:
        lines.append(("beyond plot", f"{outside:,} (|d| > {extent:g})"))
    return lines


def _histogram_figure(
    width: int, height: int, title: str, xlabel: str
) -> tuple[Figure, Axes, Axes, tuple[float, float]]:
    """A figure of `width` × `height` pixels with the title, the plot's axes (and x label) on
    the left and the statistics panel's on the right; and the sizes of the text and the
    small text (pt). The panel's y runs down from its top in pixels of the default size."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    # A figure of its own (no pyplot), so histograms can be drawn from several threads.
    fig = Figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI, facecolor="white")
    FigureCanvasAgg(fig)
    # Text scales with the height, so the default size stays legible on a laptop screen,
    # down to a legible minimum (sizes in pixels, converted to points).
    scale = height / 560
    title_size, text_size, small_size = (
        max(least, size * scale) * 72 / _DPI for size, least in ((22, 12), (16, 10), (14, 9))
    )
    fig.text(0.5, 1 - 12 * scale / height, title, ha="center", va="top", fontsize=title_size)
    panel_w = min(300 * scale, 0.36 * width)
    left, right = 70 * scale, width - panel_w - 20 * scale
    # Tick labels and the x label below the plot do not shrink below their minimum sizes.
    top, bottom = 55 * scale, height - max(65 * scale, 40)
    plot = fig.add_axes((left / width, 1 - bottom / height, (right - left) / width,
                         (bottom - top) / height))
    panel = fig.add_axes((1 - panel_w / width, 1 - bottom / height,
                          (panel_w - 14 * scale) / width, (bottom - top) / height))
    panel.set_axis_off()
    panel.set_ylim((bottom - top) / scale, 0)
    plot.set_xlabel(xlabel, fontsize=text_size, labelpad=2)
    return fig, plot, panel, (text_size, small_size)


def write_histogram(
    path: str | os.PathLike,
    distances: np.ndarray,
    stats: Mapping[str, float],
    *,
    tolerance: float | None = None,
    unit: str = "mm",
    size: tuple[int, int] = (900, 560),
    limit: float | None = None,
    title: str = "Signed distance, reconstruction to scan",
) -> None:
    """Draw a histogram of signed distances with its statistics as a PNG (matplotlib).

    Bars are coloured with :func:`diverging_colors` at their centres (same map and limit
    as the PLY and the overlay); the tolerance band, when given, is shaded and its share
    printed. The plotted range is ±max(limit, 99th percentile of |d|, rounded up); values
    beyond it are counted in a note rather than piled into the end bars.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.png``.
    distances : numpy.ndarray
        Signed distances (non-finite values are dropped).
    stats : mapping of str to float
        Statistics to print. Recognised keys: ``mean``, ``std``, ``rms``, ``median_abs``,
        ``p95_abs``, ``max_abs`` (in `unit`), ``overlap`` or ``overlap_fraction`` (fraction
        0–1 in the overlap, as :mod:`reconstruct.compare.signed_distance` reports it),
        ``count``, ``within_tolerance`` (fraction 0–1). Other keys are ignored. Missing ones
        are computed from `distances` where possible; ``overlap`` is shown as "n/a" when
        absent.
    tolerance : float, optional
        Half-width of the accepted band ±tolerance.
    unit : str
        Unit of the distances, for the labels.
    size : tuple of int
        ``(width, height)`` in pixels.
    limit : float, optional
        Colour limit; :func:`default_limit` of the distances by default.
    title : str
        Title line.

    Raises
    ------
    ValueError
        If `size` is too small to draw on or `tolerance` is not positive.
    InputError
        If the file cannot be written.
    """
    from matplotlib.ticker import MaxNLocator, ScalarFormatter

    width, height = (int(size[0]), int(size[1]))
    if width < 400 or height < 250:
        raise ValueError(f"size must be at least (400, 250), not {size}")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive number, not {tolerance}")
    d = np.asarray(distances, dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if limit is None:
        limit = default_limit(d)
    edges, extent = _bins(d, limit, tolerance)
    counts, _ = np.histogram(d, bins=edges)
    outside = int(np.count_nonzero(np.abs(d) > extent))

    fig, ax, panel, (text_size, small_size) = _histogram_figure(
        width, height, title, f"signed distance ({unit})"
    )
    if tolerance is not None:
        ax.axvspan(max(-tolerance, -extent), min(tolerance, extent), lw=0,
                   color=_rgb(_TOLERANCE_BAND), zorder=0)
        for edge in (-tolerance, tolerance):
            if abs(edge) <= extent:
                ax.axvline(edge, color=_rgb(_TOLERANCE_LINE), lw=1.5, ls=(0, (3, 3)), zorder=3)
    shown = counts > 0
    centres = 0.5 * (edges[:-1] + edges[1:])
    ax.bar(centres[shown], counts[shown], width=np.diff(edges)[shown],
           color=diverging_colors(centres[shown], limit) / 255, edgecolor=_rgb(_BAR_EDGE),
           linewidth=0.75, zorder=2)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(0, max(int(counts.max()) if counts.size else 0, 1) * 1.05)
    ax.yaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10], integer=True))
    ax.xaxis.set_major_formatter(ScalarFormatter(useOffset=False))
    ax.grid(axis="y", color=_rgb((225, 225, 225)), zorder=1)
    ax.set_axisbelow(True)
    ax.spines[["top", "right"]].set_visible(False)
    ax.tick_params(labelsize=small_size, length=3, pad=2)
    ax.set_ylabel("count", fontsize=small_size)

    lines = _stat_lines(_summary(d, stats, tolerance), unit, tolerance, limit, outside, extent)
    panel.text(0, 0, "Statistics", va="top", fontsize=text_size)
    for k, (label, value) in enumerate(lines):
        y = 31 + 27 * k
        panel.text(0, y, label, va="top", color=_rgb(_GREY_TEXT), fontsize=text_size)
        panel.text(1, y, value, va="top", ha="right", fontsize=text_size)
    panel.text(0, 37 + 27 * len(lines), "blue: d < 0   red: d > 0", va="top",
               color=_rgb(_GREY_TEXT), fontsize=small_size)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=_DPI, pil_kwargs=srgb_save_options("PNG"))
    with atomic_write(path, "wb") as handle:
        handle.write(buffer.getvalue())


# --- overlay render ----------------------------------------------------------------------


def distance_lookup_table(limit: float):
    """A VTK lookup table of :func:`diverging_colors` over ±limit, NaN grey (matplotlib-free)."""
    import pyvista as pv

    lut = pv.LookupTable()
    rgb = diverging_colors(np.linspace(-limit, limit, 256), limit)
    lut.values = np.column_stack([rgb, np.full(256, 255, np.uint8)])
    lut.scalar_range = (-limit, limit)
    lut.nan_color = tuple(c / 255 for c in NAN_COLOR)
    return lut


def _distances_on(
    verts: np.ndarray, faces: np.ndarray, points: np.ndarray, dist: np.ndarray, on: str
) -> str:
    """Which object carries the distances ("reconstruction" or "scan"), shapes checked."""
    if verts.ndim != 2 or verts.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError("reconstruction must be (V, 3) vertices and (F, 3) faces")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"scan_points must be (P, 3), not {points.shape}")
    if on == "auto":
        on = "reconstruction" if dist.shape == (len(verts),) else "scan"
    expected = {"reconstruction": len(verts), "scan": len(points)}
    if on not in expected:
        raise ValueError(f"on must be 'auto', 'reconstruction' or 'scan', not {on!r}")
    if dist.shape != (expected[on],):
        raise ValueError(f"distances are {dist.shape}, the {on} has {expected[on]} points")
    return on


def write_overlay(
    path: str | os.PathLike,
    reconstruction_vertices: np.ndarray,
    reconstruction_faces: np.ndarray,
    scan_points: np.ndarray,
    distances: np.ndarray,
    limit: float,
    *,
    size: tuple[int, int] = (1200, 600),
    on: str = "auto",
    unit: str = "mm",
) -> None:
    """Render the aligned pair and the distance heat map side by side as a PNG.

    Left: the reconstruction in grey with the scan points in orange. Right: the object
    carrying the distances (reconstruction or scan points) coloured with
    :func:`diverging_colors` over ±limit, with a scalar bar; unknown distances are grey.
    Both views look down −z (the photograph's view, ``docs/CONVENTIONS.md``) and share
    one camera.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.png``.
    reconstruction_vertices, reconstruction_faces : numpy.ndarray
        ``(V, 3)`` positions (mm) and ``(F, 3)`` indices of the reconstruction, aligned with
        the scan.
    scan_points : numpy.ndarray
        ``(P, 3)`` scan points in the same frame.
    distances : numpy.ndarray
        ``(V,)`` or ``(P,)`` signed distances (NaN where unknown).
    limit : float
        Colour range ±limit.
    size : tuple of int
        ``(width, height)`` of the image.
    on : {"auto", "reconstruction", "scan"}
        Which object the distances belong to; ``"auto"`` decides by length (and prefers the
        reconstruction when V == P).
    unit : str
        Unit for the scalar bar title.

    Raises
    ------
    ValueError
        For shapes that do not match.
    RuntimeError
        If off-screen rendering is not available (no EGL or OSMesa); callers may turn it
        into a warning and skip the image.
    InputError
        If the file cannot be written.
    """
    verts = np.asarray(reconstruction_vertices, dtype=np.float32)
    faces = np.asarray(reconstruction_faces, dtype=np.int64)
    points = np.asarray(scan_points, dtype=np.float32)
    dist = np.asarray(distances, dtype=np.float64)
    on = _distances_on(verts, faces, points, dist, on)
    limit = float(limit)
    if not (math.isfinite(limit) and limit > 0):
        raise ValueError(f"limit must be a positive number, not {limit}")

    try:
        import pyvista as pv
    except ImportError as exc:  # pragma: no cover - pyvista is a dependency
        raise RuntimeError(f"off-screen rendering needs pyvista ({exc})") from exc

    mesh = pv.PolyData.from_regular_faces(verts, faces)
    cloud = pv.PolyData(points)
    carrier = mesh if on == "reconstruction" else cloud
    carrier = carrier.copy()
    carrier.point_data["distance"] = dist
    point_size = 3.0 if len(points) < 200_000 else 2.0

    def draw(plotter) -> None:
        plotter.set_background("white")

        plotter.subplot(0, 0)
        plotter.add_text(
            "aligned: reconstruction (grey), scan (orange)", font_size=10, color="black"
        )
        plotter.add_mesh(mesh, color=(0.75, 0.75, 0.75), smooth_shading=True)
        plotter.add_mesh(
            cloud, color=(0.95, 0.5, 0.1), point_size=point_size, render_points_as_spheres=False
        )

        plotter.subplot(0, 1)
        plotter.add_text(f"signed distance on the {on}", font_size=10, color="black")
        if on == "scan":
            plotter.add_mesh(mesh, color=(0.85, 0.85, 0.85), opacity=0.25)
        plotter.add_mesh(
            carrier,
            scalars="distance",
            cmap=distance_lookup_table(limit),
            clim=(-limit, limit),
            nan_color=tuple(c / 255 for c in NAN_COLOR),
            point_size=point_size,
            smooth_shading=on == "reconstruction",
            # Mostly ambient light, so shading does not shift the colours read off the bar.
            ambient=0.6,
            diffuse=0.4,
            scalar_bar_args={
                "title": f"distance ({unit})",
                "color": "black",
                "n_labels": 5,
                "fmt": "%.3g",
                # Horizontal under the object: linked cameras cannot leave room at the side.
                "vertical": False,
                "position_x": 0.2,
                "position_y": 0.03,
                "width": 0.6,
                "height": 0.1,
            },
        )
        plotter.link_views()
        plotter.view_xy()
        plotter.reset_camera()

    image = rendering.render_image(draw, size, shape=(1, 2), border=False)
    write_png(path, np.ascontiguousarray(image[..., :3]), srgb=True)
