"""The pictures of ``report.html``, small and quick to make from an output folder.

The page shows pictures at most :data:`MAX_WIDTH` pixels wide, so the maps are subsampled once,
first, to :data:`PREVIEW_SIDE` pixels (:func:`previews`: every s-th row and column, which on a
memory-mapped file reads only those rows), and every picture is made from those subsamples; a
24-megapixel run's pictures then cost a fraction of a second and a few megabytes. Figures are
NumPy images ``(H, W, 3)`` uint8, or encoded bytes where a plotting library makes them.
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.colourtags import srgb_save_options
from ptmcore.decoders import MAX_EXPANSION
from ptmcore.errors import InputError, open_input_file
from ptmcore.images import ImageStack, linear_to_srgb, srgb_to_linear
from ptmcore.png import encode_png
from ptmcore.ptmfile import PTMFile
from ptmcore.published import PublishedBasis
from ptmcore.relight import light_direction

from reconstruct.report import plots, rendering
from reconstruct.report.summary import unit_words

#: Widest picture in the report, in pixels: a laptop screen shows it whole.
MAX_WIDTH = 1000

#: Longest side of the maps' subsamples that every picture is made from (:func:`previews`):
#: the height figure's image is about 700 pixels wide, the normal map is area-averaged to 500
#: and the Lambertian relit renderings take every other sample (480).
PREVIEW_SIDE = 960

#: Longest side of the height grid rendered in place of a mesh too large to render from its
#: file: about three screen pixels per grid cell in the 900-pixel render, which smooth shading
#: hides, at half the render time of 600.
MESH_RENDER_SIDE = 320

#: Longest side of the report's relit renderings, pixels (the PTM's subsample, the published
#: basis' renderings).
RELIT_SIDE = 480

#: The lights of the relit renderings: (label, azimuth °, elevation °). Azimuth 0° is light
#: from the right, 90° from the top (``ptmcore.relight.light_direction``).
RELIGHT_LIGHTS = (
    ("overhead", 0.0, 90.0),
    ("45° from the upper left", 135.0, 45.0),
    ("raking 12° from the left", 180.0, 12.0),
    ("raking 12° from the top", 90.0, 12.0),
    ("raking 12° from the right", 0.0, 12.0),
    ("raking 12° from the bottom", 270.0, 12.0),
)

#: The light of the specular-enhancement picture: (label, azimuth °, elevation °); high enough
#: that the highlights fall on the surface's slopes, not only on its edges.
SPECULAR_LIGHT = ("40° from the upper left", 135.0, 40.0)

# Lambertian shading through tables: 8-bit sRGB to linear, and linear to sRGB fine enough
# (4096 steps) that neighbouring output levels stay distinct near black, where the curve is
# steepest. A table lookup is several times faster than the power law on every pixel.
_SRGB_TO_LINEAR = srgb_to_linear(np.arange(256, dtype=np.float32) / 255)
_ENCODE_STEPS = 4096
_LINEAR_TO_SRGB = np.round(255 * linear_to_srgb(np.linspace(0.0, 1.0, _ENCODE_STEPS))).astype(np.uint8)


def stride_for(shape: Sequence[int], max_side: int) -> int:
    """The smallest integer step that brings the longer of ``shape[:2]`` to ``max_side`` or less."""
    return max(1, math.ceil(max(shape[0], shape[1]) / max_side))


def fit_width(image: np.ndarray, max_width: int) -> np.ndarray:
    """``image`` resized (area average) to at most ``max_width`` pixels wide, or as it is."""
    import cv2

    h, w = image.shape[:2]
    if w <= max_width:
        return image
    size = (max_width, max(1, round(h * max_width / w)))
    return cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)


def fit_side(image: np.ndarray, max_side: int) -> np.ndarray:
    """``image`` resized (area average) so that its longer side is at most ``max_side``, or as
    it is."""
    h, w = image.shape[:2]
    k = max_side / max(h, w)
    return fit_width(image, max(1, round(w * k))) if k < 1 else image


def finite_range(values: np.ndarray) -> tuple[float, float]:
    """The 0.5th to 99.5th percentile of the finite values: a colour range that a few outliers
    do not stretch (``(0, 1)`` without finite values, widened when they are all equal)."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, [0.5, 99.5]))
    return (lo, hi) if hi > lo else (lo - 0.5, lo + 0.5)


def display_pixel_size(report: dict | None) -> float | None:
    """Millimetres per height-map pixel for drawing a run's x and y beside its heights.

    The run's pixel size when its heights are in mm and its camera is orthographic; None
    otherwise (heights in pixels or relative depth, or a perspective camera, whose pixels do
    not all cover the same size on the object): x and y are then in pixels.
    """
    report = report or {}
    params = report.get("parameters") or {}
    if report.get("height_unit") != "mm" or params.get("intrinsics"):
        return None
    return params.get("pixel_size") or None


def linear_ptm(report: dict | None) -> bool:
    """Whether a run's PTM holds linear light (fitted to 16-bit photographs), as its
    ``report.json`` says: its renderings are then encoded as sRGB for display."""
    return ((report or {}).get("ptm") or {}).get("encoding") == "linear"


def holds_linear_light(source: str | os.PathLike) -> bool:
    """Whether a relightable file, or an output folder's, holds linear light.

    Its run's ``report.json`` (in the folder, or beside the file) says so in ``ptm.encoding``
    (``--ptm-encoding linear``, and 16-bit captures before their files were display-encoded);
    renderings of it are then encoded as sRGB for display
    (:func:`ptmcore.relight.display_srgb`). A file without a report is taken as display-encoded,
    as RTIViewer takes it.
    """
    source = Path(source)
    try:
        report = json.loads(((source if source.is_dir() else source.parent) / "report.json").read_text("utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(report, dict) and linear_ptm(report)


def encode(image: np.ndarray, fmt: str = "PNG", quality: int = 85) -> bytes:
    """Encode an 8-bit grey or RGB image as ``"PNG"`` (:func:`ptmcore.png.encode_png`)
    or ``"JPEG"`` bytes, tagged as sRGB (:mod:`ptmcore.colourtags`): these are pictures for
    people (the report's figures, the gallery's thumbnails)."""
    from PIL import Image

    if fmt == "PNG":
        return encode_png(np.asarray(image), srgb=True)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format=fmt, quality=quality, **srgb_save_options(fmt))
    return buf.getvalue()


def downscale_file(path: str | os.PathLike, max_width: int = MAX_WIDTH, fmt: str = "PNG") -> bytes:
    """An image file as ``fmt`` bytes at most ``max_width`` wide (a PNG that fits is kept as it is)."""
    from PIL import Image

    from ptmcore.decoders import pillow_image

    with pillow_image(path) as im:
        if im.width <= max_width and im.format == fmt:
            return Path(path).read_bytes()
        im = im.convert("RGB")
        im.thumbnail((max_width, max_width * im.height // im.width + 1), Image.Resampling.LANCZOS)
        return encode(np.asarray(im), fmt)


def photograph_thumbnail(path: str | os.PathLike, max_side: int = 240) -> np.ndarray:
    """A photograph reduced to ``max_side`` pixels for a contact sheet, 8-bit RGB.

    JPEGs are decoded at an eighth of their size (libjpeg's DCT scaling), which skips most of
    the arithmetic but not the entropy decoding: a 24-megapixel photograph of 18 MB still
    costs about 0.15 s (:func:`stack_thumbnail` makes one from an already decoded stack).
    16-bit and float images are linear light: they are scaled to their 99.5th percentile and
    encoded as sRGB so they look as a photograph does.
    """
    from ptmcore.images import read_image

    image = read_image(path, min_side=max_side)
    s = stride_for(image.shape, 2 * max_side)
    image = image[::s, ::s]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.dtype != np.uint8:
        image = _linear_to_srgb8(image.astype(np.float32), stretch=True)
    return fit_side(image, max_side)


def stack_thumbnail(stack: ImageStack, index: int, *, max_side: int = 240) -> np.ndarray:
    """A contact-sheet thumbnail of photograph ``index`` of a decoded stack, 8-bit RGB.

    What :func:`photograph_thumbnail` makes from the file, without decoding it again: the
    photograph's linear luminance times the capture's colour, every s-th pixel (s brings the
    longer side to twice ``max_side``), area-averaged to ``max_side`` and encoded as sRGB.

    Parameters
    ----------
    stack : ptmcore.images.ImageStack
        The capture's photographs (``Capture.stack``), before the pipeline releases it.
    index : int
        Which photograph.
    max_side : int
        Longer side of the thumbnail.

    Returns
    -------
    ndarray, shape (h, w, 3), uint8
        8-bit photographs as they were encoded; deeper ones (linear light) scaled to their
        99.5th percentile, as :func:`photograph_thumbnail` shows them.
    """
    s = stride_for(stack.shape, 2 * max_side)
    codes = stack.luminance[index, ::s, ::s]
    # The stack's table maps its codes (luminance × 65534, or 8-bit sRGB) to linear light; a
    # stack without one holds luminance × 65534.
    table = getattr(stack, "table", None)
    luminance = table[codes] if table is not None else codes * np.float32(1 / 65534)
    linear = luminance[..., None] * stack.chroma[::s, ::s]
    return fit_side(_linear_to_srgb8(linear, stretch=stack.bit_depth > 8), max_side)


def _linear_to_srgb8(linear: np.ndarray, *, stretch: bool) -> np.ndarray:
    """Linear light as 8-bit sRGB; ``stretch``: divided by its 99.5th percentile first."""
    top = (float(np.percentile(linear, 99.5)) or 1.0) if stretch else 1.0
    return np.round(linear_to_srgb(np.clip(linear / top, 0, 1)) * 255).astype(np.uint8)


def normal_colors(normals: np.ndarray) -> np.ndarray:
    """Normals ``(..., 3)`` as 8-bit OpenGL-style colours (R = x, G = y, B = z), (n + 1)/2;
    NaN (no normal) is black."""
    n = np.clip(np.nan_to_num(np.asarray(normals, dtype=np.float32), nan=-1.0), -1.0, 1.0)
    return np.round((n + 1) * 127.5).astype(np.uint8)


def shade_lambertian(normals: np.ndarray, albedo: np.ndarray, light: np.ndarray) -> np.ndarray:
    """8-bit sRGB colours of a Lambertian surface: albedo × max(n·l, 0) in linear light.

    Parameters
    ----------
    normals : ndarray, shape (..., 3)
        Unit normals (NaN where unknown: black).
    albedo : ndarray, shape (..., 3), uint8
        sRGB colour without shading, at the normals' size.
    light : ndarray, shape (3,)
        Unit vector towards the light.
    """
    # fmax: a NaN normal shades to 0 instead of spreading NaN.
    shade = np.fmax(normals @ np.asarray(light, dtype=np.float32), np.float32(0))
    return encode_srgb8(_SRGB_TO_LINEAR[albedo] * shade[..., None])


def encode_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear light (0–1; beyond is clipped) as 8-bit sRGB, through a table of
    :data:`_ENCODE_STEPS` entries: twice as fast as the curve itself for a screen's pictures."""
    index = np.clip(linear * (_ENCODE_STEPS - 1), 0, _ENCODE_STEPS - 1).astype(np.int32)
    return _LINEAR_TO_SRGB[index]


def relit_from_ptm(ptm: str | os.PathLike | PTMFile, max_side: int = 480, *, linear: bool = False
                   ) -> list[tuple[str, np.ndarray]]:
    """RTIViewer's default rendering of a subsample of a ``.ptm`` file under :data:`RELIGHT_LIGHTS`.

    Only the subsample is decoded (:func:`ptmcore.ptmfile.read_ptm` with ``max_side``), so a
    PTM of any size costs about the same; a ``PTMFile`` already read is rendered as it is.
    ``linear``: the PTM holds linear light (fitted to 16-bit photographs); its renderings are
    then encoded as sRGB for display (:func:`ptmcore.relight.display_srgb`).
    """
    from ptmcore.ptmfile import read_ptm

    small = ptm if isinstance(ptm, PTMFile) else read_ptm(ptm, max_side=max_side)
    return [(label, for_display(small.render(light_direction(azimuth_deg=az, elevation_deg=el)), linear))
            for label, az, el in RELIGHT_LIGHTS]


#: The published bases as a caption names them (``reconstruct run --basis``'s names).
BASIS_WORDS = {"ptm": "PTM", "hsh2": "HSH order 2", "hsh3": "HSH order 3", "hsh4": "HSH order 4",
               "rbf": "RBF interpolation of the photographs", "bilinear": "bilinear interpolation of the photographs",
               "neural": "NeuralRTI's learned basis"}


def basis_words(name: str) -> str:
    """A relighting basis' name in words: ``"hsh3"`` → ``"HSH order 3"`` (a name it does not
    know, as it is)."""
    return BASIS_WORDS.get(name, name)


def relit_from_basis(basis: str | os.PathLike | PublishedBasis, max_side: int = 480) -> list[tuple[str, np.ndarray]]:
    """A published relighting basis rendered as its page renders it (display-encoded, whatever
    its encoding) under :data:`RELIGHT_LIGHTS`, at most ``max_side`` pixels on the longer side.

    A ``web/`` folder is read at the size the pictures need
    (:func:`reconstruct.report.webread.read_relightable` with ``max_side``: a pyramid level or
    DCT-scaled planes, up to twice ``max_side``), so a basis of any size costs about the same;
    each rendering is then area-averaged to ``max_side``.
    """
    from reconstruct.report.webread import read_relightable

    small = basis if isinstance(basis, PublishedBasis) else read_relightable(basis, max_side=max_side)
    return [(label, fit_side(small.display(light_direction(azimuth_deg=az, elevation_deg=el)), max_side))
            for label, az, el in RELIGHT_LIGHTS]


def specular_from_ptm(ptm: PTMFile, *, linear: bool = False) -> np.ndarray:
    """RTIViewer's specular enhancement of a PTM (LRGB, or RGB converted by
    :func:`ptmcore.relight.as_lrgb`) under :data:`SPECULAR_LIGHT`, with RTIViewer's default
    weights, as ``reconstruct relight --mode specular`` renders it, encoded for display as
    :func:`relit_from_ptm`."""
    from ptmcore.relight import as_lrgb, specular_enhancement

    _, az, el = SPECULAR_LIGHT
    return for_display(specular_enhancement(*as_lrgb(ptm), light_direction(azimuth_deg=az, elevation_deg=el)), linear)


def for_display(image: np.ndarray, linear: bool) -> np.ndarray:
    """An 8-bit rendering of a PTM as a person is shown it: encoded as sRGB
    (:func:`ptmcore.relight.display_srgb`) when the PTM holds `linear` light, else as it is."""
    from ptmcore.relight import display_srgb

    return display_srgb(image) if linear else np.asarray(image)


def relit_lambertian(
    normals: np.ndarray, albedo_srgb: np.ndarray | None, max_side: int = 480
) -> list[tuple[str, np.ndarray]]:
    """Lambertian shading (:func:`shade_lambertian`) of a subsample under :data:`RELIGHT_LIGHTS`.

    ``albedo_srgb`` is the 8-bit sRGB albedo, grey or RGB (any size: it is resampled to the
    normals' subsample), or None for a uniform light grey (sRGB 203, 0.6 in linear light).
    """
    import cv2

    s = stride_for(normals.shape, max_side)
    n = np.asarray(normals[::s, ::s], dtype=np.float32)
    h, w = n.shape[:2]
    if albedo_srgb is None:
        albedo = np.full((h, w, 3), 203, np.uint8)
    else:
        albedo = cv2.resize(np.ascontiguousarray(albedo_srgb), (w, h), interpolation=cv2.INTER_AREA)
        if albedo.ndim == 2:
            albedo = np.repeat(albedo[..., None], 3, axis=2)
    return [(label, shade_lambertian(n, albedo, light_direction(azimuth_deg=az, elevation_deg=el)))
            for label, az, el in RELIGHT_LIGHTS]


def map_array(path: str | os.PathLike) -> np.ndarray:
    """A ``.npy`` or uncompressed TIFF array as a read-only memory map (nothing is read until
    it is sliced); a file that cannot be mapped (a compressed or tiled TIFF) is read whole.

    Only a regular file is opened, and its header's size is checked against the file's
    before anything is allocated (:func:`reconstruct.surface.normalmaps.read_npy` for
    ``.npy``: never pickled objects).

    Raises
    ------
    InputError
        If the file is missing, not a regular file, not a readable array of numbers, or
        shorter than its header says.
    """
    from reconstruct.surface.normalmaps import read_npy

    path = Path(path)
    if path.suffix == ".npy":
        return read_npy(path, "map", mmap=True)
    with open_input_file(path, "TIFF map") as f:
        stored = os.fstat(f.fileno()).st_size
        array, problem = _tiff_array(f, stored, path.name)
    if problem:
        raise InputError(problem, path)
    return array


def _tiff_array(f, stored: int, name: str) -> tuple[np.ndarray | None, str | None]:
    """The first image of the TIFF ``name`` open as ``f`` (``stored`` bytes long), mapped or
    read, or None and what is wrong with it."""
    import logging

    import tifffile

    # tifffile's exceptions on a damaged file are its own business: each is the user's one line.
    # It also logs what it finds damaged, lines that would print beside that one.
    log = logging.getLogger("tifffile")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        with tifffile.TiffFile(f, name=name) as tif:
            series = tif.series[0].levels[0]
            shape, dtype = tuple(series.shape), np.dtype(tif.byteorder + series.dtype.char)
            if series.dataoffset is not None and math.prod(shape):
                # A mapping longer than the file is refused by mmap: a lying header allocates nothing.
                return np.memmap(f, dtype, "r", series.dataoffset, shape, "C"), None
            claimed = math.prod(shape) * dtype.itemsize
            # A compressed TIFF expands at most MAX_EXPANSION times, as a photograph's does.
            if claimed > MAX_EXPANSION * stored:
                return None, (f"its header claims a {'×'.join(map(str, shape))} image of {dtype} "
                              f"({claimed:,} bytes) that {stored:,} bytes cannot hold")
            return tif.asarray(), None
    except Exception as exc:  # noqa: BLE001 - see above
        return None, f"not a readable TIFF map ({str(exc) or type(exc).__name__})"
    finally:
        log.setLevel(level)


def read_subsampled(path: str | os.PathLike, max_side: int) -> tuple[np.ndarray, int]:
    """A ``.npy`` or uncompressed TIFF array read through a memory map, strided to ``max_side``.

    Returns the subsample and the stride. Files that cannot be mapped are read whole.
    """
    full = map_array(path)
    s = stride_for(full.shape, max_side)
    return np.array(full[::s, ::s]), s


@dataclass
class Previews:
    """Subsamples of a run's maps, every ``stride``-th row and column of the full maps, from
    which every picture of ``report.html`` is made (:func:`previews`).

    Attributes
    ----------
    stride : int
        Step of the subsamples in full-size pixels (a scale bar measures the full map with it).
    normals : ndarray, shape (h, w, 3), float32, or None
        Unit normals.
    height : ndarray, shape (h, w), float32, or None
        Heights, NaN outside the object.
    albedo : ndarray, shape (h, w, 3) or (h, w), uint8, or None
        The 8-bit sRGB albedo (the texture), for Lambertian relighting without a PTM.
    """

    stride: int = 1
    normals: np.ndarray | None = None
    height: np.ndarray | None = None
    albedo: np.ndarray | None = None


def previews(*, normals: np.ndarray | None = None, height: np.ndarray | None = None,
             albedo: np.ndarray | None = None, max_side: int = PREVIEW_SIDE) -> Previews:
    """Every s-th row and column of full-size maps, s the smallest step that brings the
    longest side to ``max_side``: what the page's pictures are made from.

    Strided slicing costs nothing on arrays in memory and reads only the rows it takes from a
    memory-mapped file (:func:`map_array`); the results are small copies. The maps (``(H, W,
    3)`` normals, ``(H, W)`` heights, ``(H, W[, 3])`` uint8 albedo) share one stride, so that
    their samples coincide.
    """
    maps = {"normals": normals, "height": height, "albedo": albedo}
    shapes = [np.shape(m) for m in maps.values() if m is not None]
    s = max((stride_for(shape, max_side) for shape in shapes), default=1)
    small = {name: None if m is None else np.array(m[::s, ::s]) for name, m in maps.items()}
    for name in ("normals", "height"):
        if small[name] is not None:
            small[name] = small[name].astype(np.float32, copy=False)
    return Previews(s, **small)


def thin(image: np.ndarray, max_side: int) -> tuple[np.ndarray, int]:
    """``image`` strided (a view) so that its longer side is at most ``max_side``; and the step."""
    k = stride_for(image.shape, max_side)
    return image[::k, ::k], k


def nice_length(x: float) -> float:
    """The largest 1, 2 or 5 × 10^k not above ``x`` (> 0)."""
    k = 10.0 ** math.floor(math.log10(x))
    # The tolerance keeps a length that is round but for rounding (0.2 as 0.19999...).
    return max(m * k for m in (1, 2, 5) if m * k <= x * (1 + 1e-9))


def height_figure(
    height: np.ndarray, stride: int, unit: str, pixel_size: float | None, *, width_px: int = plots.CHART_WIDTH,
    profile: int | None = None,
) -> bytes:
    """The height map with a colour bar and a scale bar, as PNG bytes (matplotlib).

    Drawn at the width the page shows it, with labels of :data:`plots.FONT_SIZE` and the
    colour bar's ticks at round values (1, 2 or 5 × 10^k).

    Parameters
    ----------
    height : ndarray, shape (h, w)
        A subsample of the height map (NaN outside the object).
    stride : int
        Its step in the full map's pixels, so the scale bar measures the full map.
    unit : str
        The heights' unit (``mm``, ``pixel``, ``relative depth``).
    pixel_size : float or None
        Millimetres per pixel of the full map; the scale bar is in mm when given, else in
        pixels.
    profile : int, optional
        A row of the subsample to mark with a dashed line (where the profile is drawn).
    """
    import matplotlib as mpl
    from matplotlib.font_manager import FontProperties
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    h, w = height.shape
    full_w, full_h = w * stride, h * stride
    fig_w = width_px / 100
    fig_h = min(fig_w * 1.2, max(2.5, fig_w * 0.8 * full_h / full_w + 0.3))
    fig = plots.figure(width_px, round(fig_h * 100))
    ax = fig.add_subplot()
    lo, hi = finite_range(height)
    cmap = mpl.colormaps["viridis"].with_extremes(bad=(0.92, 0.92, 0.92))
    im = ax.imshow(np.ma.masked_invalid(height), cmap=cmap, vmin=lo, vmax=hi,
                   extent=(0, full_w, full_h, 0), interpolation="antialiased")
    ax.set_xticks([])
    ax.set_yticks([])
    label = unit_words(unit)
    bar = fig.colorbar(im, ax=ax, shrink=0.9, ticks=plots.round_ticks())
    bar.set_label(f"height ({label})", fontsize=plots.FONT_SIZE)
    bar.ax.tick_params(labelsize=plots.FONT_SIZE)
    if profile is not None:
        y = (profile + 0.5) * stride
        ax.plot([0, full_w], [y, y], color="white", linewidth=2.2, linestyle=(0, (6, 4)))
        ax.plot([0, full_w], [y, y], color="black", linewidth=0.9, linestyle=(0, (6, 4)))
    per_px, bar_unit = (pixel_size, "mm") if pixel_size else (1.0, "pixels")
    length = nice_length(0.25 * full_w * per_px)
    scale = AnchoredSizeBar(ax.transData, length / per_px, f"{length:g} {bar_unit}", "lower right",
                            pad=0.4, sep=4, color="black", frameon=True, size_vertical=max(full_h / 120, 1),
                            fontproperties=FontProperties(size=plots.FONT_SIZE + 1))
    scale.patch.set_alpha(0.8)
    ax.add_artist(scale)
    return plots.png(fig)


def vertical_exaggeration(width: float, height: float, depth: float | None) -> int:
    """A vertical exaggeration that makes a relief show in an oblique view: the round factor
    (1, 2 or 5 × 10^k, at least 1) that brings the relief's depth to about 15 % of the
    object's longer side (a 2 mm relief on an 80 mm tablet: ×5).

    ``width``, ``height`` and ``depth`` share one unit; without a depth the factor is 1.
    """
    if not depth or not math.isfinite(depth) or depth <= 0:
        return 1
    target = 0.15 * max(width, height) / depth
    return int(nice_length(target)) if target >= 1 else 1


#: Largest mesh rendered from its file; larger ones are rendered from the height map at the
#: picture's resolution (the same surface: the grid mesh samples the height map), which keeps
#: the render's time and memory small for 24-megapixel runs.
MAX_RENDER_FACES = 400_000


def ply_header(path: str | os.PathLike) -> list[list[str]]:
    """The header lines of a PLY file split into words (its first 4 KiB: ours are far smaller)."""
    with open(path, "rb") as f:
        header = f.read(4096).split(b"end_header", 1)[0]
    return [line.split() for line in header.decode("latin-1").splitlines()]


def ply_face_count(path: str | os.PathLike) -> int | None:
    """The face count in a PLY file's header, or None if it has none."""
    return next((int(w[2]) for w in ply_header(path) if w[:2] == ["element", "face"] and len(w) == 3), None)


def surface_from_height(height: np.ndarray, stride: int, pixel_size: float | None,
                        texture: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices, faces and vertex colours (or None without ``texture``) of the grid mesh of a
    strided height map, in the full mesh's frame; ``texture`` is the 8-bit sRGB colour at the
    height map's samples."""
    from reconstruct.mesh.grid import grid_mesh

    mesh = grid_mesh(height, texture=texture, pixel_size=(pixel_size or 1.0) * stride)
    return mesh.vertices, mesh.faces, mesh.colors if texture is not None else None


def mesh_render(
    mesh: str | os.PathLike | tuple[np.ndarray, np.ndarray, np.ndarray | None],
    size: tuple[int, int] = (900, 600),
    *,
    exaggeration: float = 1.0,
) -> np.ndarray:
    """A rendering of a mesh with its colours, seen obliquely from the front.

    Drawn in software (:func:`reconstruct.report.raster.render_mesh`: no OpenGL context); a
    binary PLY of triangles is read directly, any other mesh file with pyvista.

    Parameters
    ----------
    mesh : path or (vertices, faces, colours)
        A mesh file (PLY with vertex colours, OBJ, STL...), or ``(V, 3)`` positions, ``(F, 3)``
        indices and ``(V, 3)`` uint8 sRGB colours or None.
    size : tuple of int
        ``(width, height)`` of the picture.
    exaggeration : float
        Factor applied to the mesh's z (heights) before rendering.

    Returns
    -------
    ndarray, shape (size[1], size[0], 3), uint8
        Coloured by the mesh's vertex colours when it has them, else clay.

    Raises
    ------
    RuntimeError
        If the mesh cannot be read (or pyvista, to read a file, is missing) or has nothing
        to draw; the caller shows a note instead.
    """
    from reconstruct.report.raster import render_mesh

    if isinstance(mesh, tuple):
        vertices, faces, colours = mesh
    else:
        vertices, faces, colours = _read_mesh(mesh)
    vertices = np.array(vertices, np.float64)
    vertices[:, 2] *= exaggeration
    try:
        return render_mesh(vertices, faces, colours, size)  # its view: obliquely from the front
    except ValueError as exc:
        raise RuntimeError(f"cannot render the mesh ({exc})") from exc


def _read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices, triangles and vertex colours (or None) of a mesh file: a binary PLY of
    triangles (a run's ``mesh.ply``) read directly, anything else by pyvista."""
    from reconstruct.mesh.ply import read_binary_ply

    try:
        vertex, faces = read_binary_ply(path)
    except ValueError:
        pass  # another layout or format: pyvista's readers
    except InputError as exc:
        raise RuntimeError(f"cannot read the mesh ({exc.problem})") from exc
    else:
        if not {"x", "y", "z"} <= vertex.keys():
            raise RuntimeError("cannot read the mesh (its vertices have no x, y, z)")
        colours = None
        if {"red", "green", "blue"} <= vertex.keys() and all(vertex[c].dtype == np.uint8 for c in ("red", "green", "blue")):
            colours = np.column_stack([vertex[c] for c in ("red", "green", "blue")]).astype(np.uint8)
        return np.column_stack([vertex["x"], vertex["y"], vertex["z"]]), faces, colours
    try:
        import pyvista as pv
    except ImportError as exc:
        raise RuntimeError(f"reading a mesh file needs pyvista ({exc})") from exc
    try:
        with rendering.VTK_LOCK:
            surface = pv.read(str(path)).triangulate()
            colours = surface.point_data.get("RGB")
            return (np.asarray(surface.points), np.asarray(surface.regular_faces),
                    None if colours is None else np.asarray(colours, np.uint8)[:, :3])
    except Exception as exc:  # pyvista's readers raise assorted types
        raise RuntimeError(f"cannot read the mesh ({exc})") from exc
