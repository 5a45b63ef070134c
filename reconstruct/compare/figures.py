"""Outputs of a reconstruction-versus-scan comparison: coloured PLY, histogram and overlay.

The functions take plain arrays (vertices, faces, points, signed distances in mm and the
statistics as a dict), so they do not depend on how the distances were computed
(:mod:`reconstruct.compare.align`). All of them colour distances with the same diverging map,
:func:`diverging_colors`: blue for negative, white at 0, red for positive, clipped to
±limit, so the PLY, the histogram and the overlay read alike.

Every file is written through :func:`ptmcore.atomic.atomic_write`.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterable, Mapping

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ptmcore.atomic import atomic_write

from reconstruct.report import rendering

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
#: It is :mod:`reconstruct.compare.align`'s, for distances of scan points and reverse distances.
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


def _check_comment(text: str) -> str:
    """A header comment must stay on one line or it corrupts the PLY."""
    text = str(text)
    if "\n" in text or "\r" in text:
        raise ValueError(f"comments must be single lines, not {text!r}")
    return text


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
    if faces is not None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), not {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= n):
            raise ValueError("face indices out of range")
        if n > np.iinfo(np.int32).max:
            raise ValueError("too many vertices for PLY int32 indices")
    colors = diverging_colors(distances, limit)
    lim = _format_mm(float(limit))
    n_known = int(np.count_nonzero(~np.isnan(distances)))

    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"comment unit {_UNIT}",
        (
            f"comment colour: signed distance, blue = -{lim} {_UNIT} or less, white = 0, "
            f"red = +{lim} {_UNIT} or more (ColorBrewer RdBu, linear)"
        ),
        (
            f"comment colour grey {NAN_COLOR[0]} {NAN_COLOR[1]} {NAN_COLOR[2]} = no distance "
            f"({n - n_known} of {n} vertices)"
        ),
        f"comment quality = signed distance in {_UNIT} (NaN = unknown)",
        f"comment sign convention: {_check_comment(sign_convention)}",
    ]
    header += [f"comment {_check_comment(c)}" for c in comments]
    header.append(f"element vertex {n}")
    header += [f"property float {a}" for a in ("x", "y", "z")]
    header += [f"property uchar {a}" for a in ("red", "green", "blue")]
    header.append("property float quality")
    if faces is not None:
        header.append(f"element face {len(faces)}")
        header.append("property list uchar int vertex_indices")
    header.append("end_header")

    # Packed structured records are PLY's binary layout, written in one call each.
    record = np.empty(
        n,
        dtype=[("xyz", "<f4", (3,)), ("rgb", "u1", (3,)), ("quality", "<f4")],
    )
    record["xyz"] = vertices
    record["rgb"] = colors
    record["quality"] = distances
    with atomic_write(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("utf-8"))
        handle.write(record.tobytes())
        if faces is not None:
            face_record = np.empty(len(faces), dtype=[("count", "u1"), ("index", "<i4", (3,))])
            face_record["count"] = 3
            face_record["index"] = faces
            handle.write(face_record.tobytes())


# --- histogram ---------------------------------------------------------------------------

# Labels of the statistics drawn on the histogram, in order; values are mm unless noted.
_STAT_LABELS = (
    ("mean", "mean"),
    ("std", "std"),
    ("rms", "RMS"),
    ("median_abs", "median |d|"),
    ("p95_abs", "95th pct |d|"),
    ("max_abs", "max |d|"),
)


def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """DejaVu Sans if the system has it, else Pillow's scalable built-in font."""
    for name in ("DejaVuSans.ttf", "Arial.ttf", "LiberationSans-Regular.ttf"):
        try:
            return ImageFont.truetype(name, size)
        except OSError:
            continue
    return ImageFont.load_default(size=size)


def _nice_ticks(lo: float, hi: float, target: int = 6) -> np.ndarray:
    """Round tick positions covering [lo, hi], about `target` of them."""
    if hi <= lo:
        return np.array([lo])
    step = _nice_ceil((hi - lo) / target)
    first = math.ceil(lo / step - 1e-9) * step
    ticks = np.arange(first, hi + step * 1e-6, step)
    # Rounding to the step's decimals removes "0.30000000000000004" and "-0".
    decimals = max(0, -math.floor(math.log10(step)) + 1)
    return np.round(ticks, decimals) + 0.0


def _tick_label(x: float) -> str:
    return f"{x:g}"


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
    """Draw a histogram of signed distances with its statistics as a PNG.

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
        0–1 in the overlap, as :mod:`reconstruct.compare.align` reports it), ``count``,
        ``within_tolerance`` (fraction 0–1). Other keys are ignored. Missing ones are
        computed from `distances` where possible; ``overlap`` is shown as "n/a" when absent.
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
    width, height = (int(size[0]), int(size[1]))
    if width < 400 or height < 250:
        raise ValueError(f"size must be at least (400, 250), not {size}")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive number, not {tolerance}")
    d = np.asarray(distances, dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if limit is None:
        limit = default_limit(d)
    summary = _summary(d, stats, tolerance)

    # Fonts scale with the height, so the default size stays legible on a laptop screen.
    scale = height / 560
    f_title = _font(max(12, round(22 * scale)))
    f_text = _font(max(10, round(16 * scale)))
    f_small = _font(max(9, round(14 * scale)))

    image = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(image)
    draw.text((width // 2, round(12 * scale)), title, fill="black", font=f_title, anchor="mt")

    # Layout: the plot on the left, the statistics in a panel on the right.
    panel_w = round(min(300 * scale, 0.36 * width))
    left, right = round(70 * scale), width - panel_w - round(20 * scale)
    top, bottom = round(55 * scale), height - round(65 * scale)

    a = np.abs(d)
    extent = max(float(limit), float(np.percentile(a, 99)) if a.size else 0.0)
    if tolerance is not None:
        extent = max(extent, float(tolerance) * 1.2)
    extent = _nice_ceil(extent) if extent > 0 else 1.0
    # An odd number of bins puts one bar centred on 0, which reads as "no deviation".
    n_bins = 2 * int(np.clip(math.sqrt(max(d.size, 1)) / 2, 7, 40)) + 1
    edges = np.linspace(-extent, extent, n_bins + 1)
    counts, _ = np.histogram(d, bins=edges)
    outside = int(np.count_nonzero(a > extent))
    y_max = max(int(counts.max()) if counts.size else 0, 1)
    y_ticks = _nice_ticks(0, y_max * 1.05, target=5)
    y_top = max(float(y_ticks[-1]), y_max * 1.05)

    def px(x: np.ndarray | float) -> np.ndarray | float:
        return left + (np.asarray(x) + extent) / (2 * extent) * (right - left)

    def py(c: np.ndarray | float) -> np.ndarray | float:
        return bottom - np.asarray(c) / y_top * (bottom - top)

    if tolerance is not None:
        x0, x1 = px(max(-tolerance, -extent)), px(min(tolerance, extent))
        draw.rectangle([x0, top, x1, bottom], fill=(226, 240, 226))
    # Grid lines under the bars.
    for t in y_ticks:
        draw.line([(left, py(t)), (right, py(t))], fill=(225, 225, 225), width=1)

    colors = diverging_colors(0.5 * (edges[:-1] + edges[1:]), limit)
    xs, ys = px(edges), py(counts)
    for k in np.flatnonzero(counts):
        draw.rectangle(
            [xs[k], ys[k], xs[k + 1], bottom],
            fill=tuple(int(c) for c in colors[k]),
            outline=(90, 90, 90),
        )
    if tolerance is not None:
        for edge in (-tolerance, tolerance):
            if abs(edge) <= extent:
                x = px(edge)
                for y in range(top, bottom, 8):  # dashed
                    draw.line([(x, y), (x, min(y + 4, bottom))], fill=(0, 120, 0), width=2)

    # Axes, ticks and labels.
    draw.line([(left, bottom), (right, bottom)], fill="black", width=2)
    draw.line([(left, top), (left, bottom)], fill="black", width=2)
    tick = round(6 * scale)
    for t in _nice_ticks(-extent, extent, target=6):
        x = px(t)
        draw.line([(x, bottom), (x, bottom + tick)], fill="black", width=1)
        draw.text((x, bottom + tick + 2), _tick_label(t), fill="black", font=f_small, anchor="mt")
    for t in y_ticks:
        y = py(t)
        draw.line([(left - tick, y), (left, y)], fill="black", width=1)
        draw.text((left - tick - 3, y), f"{int(t):d}", fill="black", font=f_small, anchor="rm")
    draw.text(
        ((left + right) // 2, height - round(8 * scale)),
        f"signed distance ({unit})",
        fill="black",
        font=f_text,
        anchor="mb",
    )
    draw.text((left, top - round(6 * scale)), "count", fill="black", font=f_small, anchor="lb")

    # Statistics panel.
    lines: list[tuple[str, str]] = []
    for key, label in _STAT_LABELS:
        if key in summary:
            lines.append((label, f"{summary[key]:.4g} {unit}"))
    # reconstruct.compare.align names it overlap_fraction.
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

    x_label = width - panel_w
    x_value = width - round(14 * scale)
    line_h = round(27 * scale)
    y = top
    draw.text((x_label, y), "Statistics", fill="black", font=f_text, anchor="lt")
    y += line_h + round(4 * scale)
    for label, value in lines:
        draw.text((x_label, y), label, fill=(60, 60, 60), font=f_text, anchor="lt")
        draw.text((x_value, y), value, fill="black", font=f_text, anchor="rt")
        y += line_h
    y += round(6 * scale)
    draw.text(
        (x_label, y),
        "blue: d < 0   red: d > 0",
        fill=(60, 60, 60),
        font=f_small,
        anchor="lt",
    )

    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
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

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image[..., :3])).save(buffer, format="PNG")
    with atomic_write(path, "wb") as handle:
        handle.write(buffer.getvalue())
