"""The pictures of ``report.html``, small and quick to make from an output folder.

Every function reads only a subsample of the large outputs (memory-mapped normals and heights,
strided before anything is computed), so a 24-megapixel run's pictures cost a fraction of a
second and a few megabytes. Figures are NumPy images ``(H, W, 3)`` uint8, or encoded bytes
where a plotting library makes them.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import rendering

#: Widest picture in the report, in pixels: a laptop screen shows it whole.
MAX_WIDTH = 1000

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

#: Largest ``coefficients.ptm`` relit from its polynomials; larger ones are relit from the
#: normals and albedo, because decoding a PTM holds all its coefficients as float32.
MAX_PTM_BYTES = 80 * 2**20


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


def encode(image: np.ndarray, fmt: str = "PNG", quality: int = 85) -> bytes:
    """Encode an 8-bit grey or RGB image as ``"PNG"`` or ``"JPEG"`` bytes."""
    from PIL import Image

    buf = io.BytesIO()
    options = {"quality": quality} if fmt == "JPEG" else {"optimize": True}
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format=fmt, **options)
    return buf.getvalue()


def downscale_file(path: str | os.PathLike, max_width: int = MAX_WIDTH, fmt: str = "PNG") -> bytes:
    """An image file as ``fmt`` bytes at most ``max_width`` wide (a PNG that fits is kept as it is)."""
    from PIL import Image

    data = Path(path).read_bytes()
    with Image.open(io.BytesIO(data)) as im:
        if im.width <= max_width and im.format == fmt:
            return data
        im = im.convert("RGB")
        im.thumbnail((max_width, max_width * im.height // im.width + 1), Image.Resampling.LANCZOS)
        return encode(np.asarray(im), fmt)


def photograph_thumbnail(path: str | os.PathLike, max_side: int = 240) -> np.ndarray:
    """A photograph reduced to ``max_side`` pixels for a contact sheet, 8-bit RGB.

    JPEGs are decoded at a reduced size (libjpeg's DCT scaling), so a 24-megapixel photograph
    costs a few milliseconds. 16-bit and float images are linear light: they are scaled to
    their 99.5th percentile and encoded as sRGB so they look as a photograph does.
    """
    from PIL import Image

    from ptmcore.images import linear_to_srgb, read_image

    path = Path(path)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        with Image.open(path) as im:
            im.draft("RGB", (max_side, max_side))
            im = im.convert("RGB")
            im.thumbnail((max_side, max_side), Image.Resampling.LANCZOS)
            return np.asarray(im)
    image = read_image(path)
    image = image[:: stride_for(image.shape, 2 * max_side), :: stride_for(image.shape, 2 * max_side)]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.dtype != np.uint8:
        v = image.astype(np.float32)
        top = float(np.percentile(v, 99.5)) or 1.0
        image = np.round(linear_to_srgb(np.clip(v / top, 0, 1)) * 255).astype(np.uint8)
    h, w = image.shape[:2]
    k = max_side / max(h, w)
    return fit_width(image, max(1, round(w * k))) if k < 1 else image


def normal_map_image(normals: np.ndarray, max_side: int = MAX_WIDTH // 2) -> np.ndarray:
    """An 8-bit OpenGL-style picture (R = x, G = y, B = z) of a subsample of ``normals``."""
    s = stride_for(normals.shape, max_side)
    n = np.asarray(normals[::s, ::s], dtype=np.float32)
    return np.round((np.nan_to_num(n, nan=-1.0) + 1) * 127.5).clip(0, 255).astype(np.uint8)


def light_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector towards a light at an azimuth and elevation (project frame)."""
    from ptmcore.relight import light_direction

    return light_direction(azimuth_deg=azimuth_deg, elevation_deg=elevation_deg)


def relit_from_ptm(path: str | os.PathLike, max_side: int = 480, *, linear: bool = False
                   ) -> list[tuple[str, np.ndarray]]:
    """RTIViewer's default rendering of a subsample of a ``.ptm`` file under :data:`RELIGHT_LIGHTS`.

    ``linear``: the PTM holds linear light (fitted to 16-bit photographs); its renderings are
    then encoded as sRGB for display (:func:`ptmcore.relight.display_srgb`).
    """
    from ptmcore.ptmfile import read_ptm
    from ptmcore.relight import display_srgb

    ptm = read_ptm(path)
    s = stride_for(ptm.coefficients.shape, max_side)
    small = replace(ptm, coefficients=np.ascontiguousarray(ptm.coefficients[::s, ::s]),
                    rgb=None if ptm.rgb is None else np.ascontiguousarray(ptm.rgb[::s, ::s]))
    del ptm
    encode = display_srgb if linear else np.asarray
    return [(label, encode(small.render(light_vector(az, el)))) for label, az, el in RELIGHT_LIGHTS]


def relit_lambertian(
    normals: np.ndarray, albedo_srgb: np.ndarray | None, max_side: int = 480
) -> list[tuple[str, np.ndarray]]:
    """Lambertian shading ``albedo · max(n·l, 0)`` of a subsample under :data:`RELIGHT_LIGHTS`.

    ``albedo_srgb`` is the 8-bit sRGB albedo (any size: it is resampled to the normals'
    subsample), or None for a uniform light grey.
    """
    import cv2

    from ptmcore.images import linear_to_srgb, srgb_to_linear

    s = stride_for(normals.shape, max_side)
    n = np.nan_to_num(np.asarray(normals[::s, ::s], dtype=np.float32))
    h, w = n.shape[:2]
    if albedo_srgb is None:
        albedo = np.full((h, w, 3), 0.6, np.float32)
    else:
        small = cv2.resize(np.ascontiguousarray(albedo_srgb), (w, h), interpolation=cv2.INTER_AREA)
        albedo = srgb_to_linear(small.astype(np.float32) / 255).astype(np.float32)
        if albedo.ndim == 2:
            albedo = np.repeat(albedo[..., None], 3, axis=2)
    out = []
    for label, az, el in RELIGHT_LIGHTS:
        shade = np.clip(n @ light_vector(az, el).astype(np.float32), 0, None)
        rgb = linear_to_srgb(np.clip(albedo * shade[..., None], 0, 1))
        out.append((label, np.round(rgb * 255).astype(np.uint8)))
    return out


def read_subsampled(path: str | os.PathLike, max_side: int) -> tuple[np.ndarray, int]:
    """A ``.npy`` or uncompressed TIFF array read through a memory map, strided to ``max_side``.

    Returns the subsample and the stride. Files that cannot be mapped are read whole.
    """
    import tifffile

    path = Path(path)
    if path.suffix == ".npy":
        full = np.load(path, mmap_mode="r")
    else:
        try:
            full = tifffile.memmap(path, mode="r")
        except ValueError:  # compressed or tiled: tifffile cannot map it
            full = tifffile.imread(path)
    s = stride_for(full.shape, max_side)
    return np.array(full[::s, ::s]), s


def _nice_length(x: float) -> float:
    """The largest 1, 2 or 5 × 10^k not above ``x``."""
    k = 10.0 ** math.floor(math.log10(x))
    return max(m * k for m in (1, 2, 5) if m * k <= x)


def height_figure(
    height: np.ndarray, stride: int, unit: str, pixel_size: float | None, *, width_px: int = 900
) -> bytes:
    """The height map with a colour bar and a scale bar, as PNG bytes (matplotlib).

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
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    h, w = height.shape
    full_w, full_h = w * stride, h * stride
    dpi = 100
    fig_w = width_px / dpi
    fig_h = min(fig_w * 1.2, max(2.5, fig_w * 0.82 * full_h / full_w + 0.6))
    fig = Figure(figsize=(fig_w, fig_h), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    finite = height[np.isfinite(height)]
    lo, hi = (np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0))
    if hi <= lo:
        hi = lo + 1e-6
    import matplotlib as mpl

    cmap = mpl.colormaps["viridis"].with_extremes(bad=(0.92, 0.92, 0.92))
    im = ax.imshow(np.ma.masked_invalid(height), cmap=cmap, vmin=lo, vmax=hi,
                   extent=(0, full_w, full_h, 0), interpolation="antialiased")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.colorbar(im, ax=ax, label=f"height ({unit})", shrink=0.9)
    per_px, bar_unit = (pixel_size, "mm") if pixel_size else (1.0, "pixels")
    length = _nice_length(0.25 * full_w * per_px)
    bar = AnchoredSizeBar(ax.transData, length / per_px, f"{length:g} {bar_unit}", "lower right",
                          pad=0.4, sep=4, color="black", frameon=True, size_vertical=max(full_h / 150, 1))
    bar.patch.set_alpha(0.75)
    ax.add_artist(bar)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


#: Largest mesh rendered from its file; larger ones are rendered from the height map at the
#: picture's resolution (the same surface: the grid mesh samples the height map), which keeps
#: the render's time and memory small for 24-megapixel runs.
MAX_RENDER_FACES = 400_000


def ply_face_count(path: str | os.PathLike) -> int | None:
    """The face count in a PLY file's header, or None if it has none."""
    with open(path, "rb") as f:
        header = f.read(4096).split(b"end_header", 1)[0]
    for line in header.splitlines():
        parts = line.split()
        if parts[:2] == [b"element", b"face"] and len(parts) == 3:
            return int(parts[2])
    return None


def surface_from_height(height: np.ndarray, stride: int, pixel_size: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of the grid mesh of a strided height map, in the full mesh's frame."""
    from .mesh import grid_mesh

    mesh = grid_mesh(height, pixel_size=(pixel_size or 1.0) * stride)
    return mesh.vertices, mesh.faces


def mesh_render(
    mesh: str | os.PathLike | tuple[np.ndarray, np.ndarray], size: tuple[int, int] = (900, 600)
) -> np.ndarray:
    """An off-screen rendering of a mesh, shaded clay grey, seen obliquely from the front.

    Parameters
    ----------
    mesh : path or (vertices, faces)
        A mesh file (PLY, OBJ, STL...) or ``(V, 3)`` positions and ``(F, 3)`` indices.
    size : tuple of int
        ``(width, height)`` of the picture.

    Returns
    -------
    ndarray, shape (size[1], size[0], 3), uint8

    Raises
    ------
    RuntimeError
        If off-screen rendering is not available (no pyvista, no EGL or OSMesa context) or
        the mesh cannot be read; the caller shows a note instead.
    """
    try:
        import pyvista as pv
    except ImportError as exc:
        raise RuntimeError(f"off-screen rendering needs pyvista ({exc})") from exc

    try:
        if isinstance(mesh, tuple):
            vertices, faces = mesh
            cells = np.column_stack([np.full(len(faces), 3, np.int64), faces]).ravel()
            surface = pv.PolyData(np.asarray(vertices, np.float32), cells)
        else:
            surface = pv.read(str(mesh))
    except Exception as exc:  # pyvista's readers raise assorted types
        raise RuntimeError(f"cannot read the mesh ({exc})") from exc

    def draw(plotter) -> None:
        plotter.set_background("white")
        plotter.add_mesh(surface, color=(0.78, 0.72, 0.64), smooth_shading=True, specular=0.15,
                         scalars=None, rgb=False)
        center = np.asarray(surface.center)
        # Oblique: from the front (−y) and a little to the right, 40° above the object plane.
        view = np.array([0.35, -0.75, 0.85])
        plotter.camera_position = [tuple(center + view), tuple(center), (0.0, 0.0, 1.0)]
        plotter.reset_camera()
        plotter.camera.zoom(1.2)

    return rendering.render_image(draw, size)
