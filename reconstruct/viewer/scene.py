"""What ``reconstruct preview`` shows, as plain arrays: loading a source and colouring it.

A source (an output folder of ``reconstruct run``, a mesh file or a ``.ptm`` file) becomes a
:class:`PreviewScene`: a display mesh small enough to turn smoothly (at most
``max_vertices`` vertices), and the data its view modes are made from, at a bounded texture
resolution (at most ``max_texture`` pixels on the long side) so that relighting one frame
stays fast enough to follow a slider. The window itself is in :mod:`reconstruct.viewer.preview`.

View modes:

* ``relit``: the relighting basis the output folder publishes in ``web/`` (the one chosen for
  the capture, ``reconstruct run --basis``), rendered as its page renders it
  (:meth:`ptmcore.published.PublishedBasis.display`); without one, the PTM relit as RTIViewer's
  default rendering (:func:`ptmcore.relight.relight`); without a PTM, Lambertian shading of the
  albedo by the normals;
* ``albedo``: the surface colour without shading;
* ``normals``: the normal map in the OpenGL mapping (R = x, G = y, B = z);
* ``height``: the heights as a colour map (drawn by the window, with a scale bar);
* ``distance``: the signed distance to a laser scan, when a comparison exists;
* ``specular``: RTIViewer's specular enhancement of the PTM (:mod:`reconstruct.viewer.shading`);
* ``diffuse-gain``: RTIViewer's diffuse gain of the PTM;
* ``relief``: the shape alone, grey, with radiance scaling by curvature and the vertical
  exaggeration applied to the shading (for shallow reliefs; needs normals on the texture grid).

Every colour is display-encoded (sRGB): a published basis of linear light (its ``viewer.json``
says so) is encoded by its display, and renderings of a PTM that holds linear light (as
report.json says) are encoded for display.

Textured scenes (output folders and ``.ptm`` files) carry their colours as images ``(h, w,
3)``; mesh files carry them per vertex ``(V, 3)``. The colouring functions work on either.
"""

from __future__ import annotations

import io
import json
import math
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError, read_input_file, read_input_text
from ptmcore.published import PublishedBasis
from ptmcore.relight import (
    DEFAULT_EXPONENT,
    DEFAULT_GAIN,
    diffuse_gain,
    light_direction,
    relight,
)
from reconstruct.mesh.grid import grid_mesh
from reconstruct.report.figures import (
    display_pixel_size,
    for_display,
    linear_ptm,
    map_array,
    normal_colors,
    ply_header,
    shade_lambertian,
    stride_for,
)

__all__ = [
    "MODES",
    "PreviewScene",
    "Style",
    "distance",
    "load_scene",
    "mode_colors",
    "profile",
    "relit_texture",
]

MODES = ("relit", "albedo", "normals", "height", "distance", "specular", "diffuse-gain", "relief")
#: The modes drawn as colours (the others through a colour map with a scale bar).
COLOUR_MODES = ("relit", "albedo", "normals", "specular", "diffuse-gain", "relief")
#: The modes that a light shades (the window shows its direction in them).
LIT_MODES = ("relit", "height", "specular", "diffuse-gain", "relief")
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf", ".off")

#: Display limits: a mesh of this many vertices turns smoothly in software OpenGL, and one
#: relit frame of a 2048-pixel texture takes tens of milliseconds (see the report).
MAX_VERTICES = 250_000
MAX_TEXTURE = 2048


@dataclass
class PreviewScene:
    """A source ready to display.

    Attributes
    ----------
    name : str
        The source's name, for titles and screenshot file names.
    vertices : numpy.ndarray
        ``(V, 3)`` float32 display vertices (x right, y up, z towards the camera), in `unit`.
    faces : numpy.ndarray
        ``(F, 3)`` int vertex indices.
    unit : str
        ``"mm"``, ``"pixel"``, or ``"unknown"`` (a mesh file that does not say).
    uv : numpy.ndarray or None
        ``(V, 2)`` texture coordinates (v up) of textured scenes; None when the colours are
        per vertex.
    coefficients, rgb : numpy.ndarray or None
        LRGB PTM at texture resolution: ``(h, w, 6)`` float32 and ``(h, w, 3)`` uint8.
    normals : numpy.ndarray or None
        ``(h, w, 3)`` (textured) or ``(V, 3)`` float32 unit normals.
    albedo : numpy.ndarray or None
        ``(h, w, 3)`` or ``(V, 3)`` uint8 sRGB colour without shading.
    height : numpy.ndarray or None
        ``(H, W)`` float32 full-resolution height map (NaN outside the object), for exact
        profiles; None when only the mesh is known.
    pixel_size : float
        Size of one height-map pixel in `unit` (1 without a pixel size).
    vertex_distance : numpy.ndarray or None
        ``(V,)`` signed distance to a scan (mm, NaN where unknown) at the display vertices.
    distance_limit : float or None
        Colour range ±limit of the distances (mm), as the comparison drew them.
    linear_ptm : bool
        The PTM holds linear light (fitted to 16-bit photographs, as report.json says): its
        renderings are encoded as sRGB for display.
    published : PublishedBasis or None
        The relighting basis published in the output folder's ``web/``, at texture resolution:
        the ``relit`` mode renders it (specular enhancement and diffuse gain, defined on the
        PTM's polynomial, stay the PTM's).
    folder : pathlib.Path or None
        The result's folder (an output folder, or the folder of a file source), where the
        window saves figures and measurements.

    The scene's data are read, not changed, once built: :attr:`modes`, the normals at the
    PTM's maxima, the convexity and the ray-casting structure of the profiles are computed
    once, on first use, and the last diffuse gain's coefficients and the last exaggeration's
    normals are kept.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    unit: str
    uv: np.ndarray | None = None
    coefficients: np.ndarray | None = None
    rgb: np.ndarray | None = None
    normals: np.ndarray | None = None
    albedo: np.ndarray | None = None
    height: np.ndarray | None = None
    pixel_size: float = 1.0
    vertex_distance: np.ndarray | None = None
    distance_limit: float | None = None
    linear_ptm: bool = False
    folder: Path | None = None
    published: PublishedBasis | None = None
    _kept: dict = field(default_factory=dict, repr=False, compare=False)

    @cached_property
    def modes(self) -> tuple[str, ...]:
        """The view modes this scene can show, in the order of :data:`MODES`."""
        have = {
            "relit": self.published is not None or self.coefficients is not None
            or (self.normals is not None and self.albedo is not None),
            "albedo": self.albedo is not None,
            "normals": self.normals is not None,
            "height": self.height is not None or float(np.ptp(self.vertices[:, 2])) > 0,
            "distance": self.vertex_distance is not None,
            "specular": self.coefficients is not None,
            "diffuse-gain": self.coefficients is not None,
            "relief": self.normals is not None and self.uv is not None,
        }
        return tuple(m for m in MODES if have[m])

    @cached_property
    def maximum(self) -> np.ndarray:
        """``(h, w, 3)`` float32 normals at the PTM's maxima (specular enhancement's and
        diffuse gain's normals)."""
        from ptmcore.normals import normals_from_ptm

        return normals_from_ptm(self.coefficients)

    @cached_property
    def convexity(self) -> np.ndarray:
        """``(h, w)`` float32 convexity of the normals, −1…1 (:func:`shading.convexity`)."""
        from reconstruct.viewer.shading import convexity

        return convexity(self.normals)

    def _keep(self, kind: str, value: float, make) -> np.ndarray:
        """``make(value)``, kept until `kind` is asked for with another value: the light
        moves far more often than the gain or the exaggeration change."""
        last = self._kept.get(kind)
        if last is None or last[0] != value:
            last = self._kept[kind] = (value, make(value))
        return last[1]

    def gained(self, gain: float) -> np.ndarray:
        """The PTM's coefficients with diffuse gain `gain` (the last gain's are kept: a
        light move then costs one relight)."""
        return self._keep("gain", gain, lambda g: diffuse_gain(self.coefficients, g, maximum=self.maximum))

    def relief_normals(self, exaggeration: float) -> np.ndarray:
        """The normals with the heights multiplied by `exaggeration`
        (:func:`reconstruct.viewer.shading.exaggerated_normals`; the last factor's are kept)."""
        from reconstruct.viewer.shading import exaggerated_normals

        if exaggeration == 1:
            return self.normals
        return self._keep("relief", exaggeration, lambda e: exaggerated_normals(self.normals, e))

    @cached_property
    def _ray_scene(self):
        """Open3D's ray-casting structure (a BVH) of the display mesh, for profiles on mesh files."""
        from reconstruct.mesh.ops import _scene

        return _scene(self.vertices, self.faces)


@dataclass(frozen=True)
class Style:
    """Parameters of the renderings the window changes: the Phong `exponent` of RTIViewer's
    specular enhancement (its weights are RTIViewer's defaults), the diffuse `gain` (1 to 10),
    and the vertical `exaggeration` of the relief shading (and of the window's mesh)."""

    exponent: float = DEFAULT_EXPONENT
    gain: float = DEFAULT_GAIN
    exaggeration: float = 1.0


# --- colouring ---------------------------------------------------------------------------


def relit_texture(scene: PreviewScene, light: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """The scene's colours under one light.

    The published basis as its page renders it when the scene has one (display-encoded whatever
    its encoding), else the PTM relit as RTIViewer's default rendering, else the albedo shaded by
    the normals (Lambertian).

    Parameters
    ----------
    scene : PreviewScene
    light : array_like, shape (3,)
        Direction towards the light (x right, y up, z towards the camera), as
        :func:`ptmcore.relight.light_direction` accepts it (and checks it, once).

    Returns
    -------
    numpy.ndarray
        ``(h, w, 3)`` uint8 image for textured scenes, ``(V, 3)`` for per-vertex colours.

    Raises
    ------
    ValueError
        If the scene cannot be relit or the light is below the horizon.
    """
    if scene.published is not None:
        return scene.published.display(light_direction(light=light))  # checks the light
    if scene.coefficients is not None:
        image = relight(scene.coefficients, scene.rgb, light)  # checks the light
        return for_display(image, scene.linear_ptm)
    if scene.normals is None or scene.albedo is None:
        raise ValueError(f"{scene.name} has neither PTM coefficients nor normals and colours to relight")
    return shade_lambertian(scene.normals, scene.albedo, light_direction(light=light))


def mode_colors(scene: PreviewScene, mode: str, light: np.ndarray | None = None,
                style: Style = Style()) -> np.ndarray:
    """Colours of a colour mode (:data:`COLOUR_MODES`), display-encoded.

    ``height`` and ``distance`` are scalar modes, drawn through a colour map with a scale bar
    by the window. `light` is needed for the lit modes (:data:`LIT_MODES`); `style` holds the
    parameters of ``specular``, ``diffuse-gain`` and ``relief``.

    Returns
    -------
    numpy.ndarray
        ``(h, w, 3)`` or ``(V, 3)`` uint8, as :func:`relit_texture`.
    """
    from ptmcore.relight import specular_enhancement
    from reconstruct.viewer.shading import relief_shading

    if mode not in scene.modes or mode not in COLOUR_MODES:
        raise ValueError(f"{mode!r} is not a colour mode of {scene.name} (it has {', '.join(scene.modes)})")
    if mode == "albedo":
        return scene.albedo
    if mode == "normals":
        return normal_colors(scene.normals)
    if light is None:
        raise ValueError(f"the {mode} mode needs a light")
    if mode == "relit":
        return relit_texture(scene, light)
    if mode == "relief":
        return relief_shading(scene.relief_normals(style.exaggeration), scene.convexity, light)
    if mode == "specular":
        image = specular_enhancement(scene.coefficients, scene.rgb, light, exponent=style.exponent,
                                     maximum=scene.maximum)
    else:
        image = relight(scene.gained(style.gain), scene.rgb, light)
    return for_display(image, scene.linear_ptm)


# --- measuring ---------------------------------------------------------------------------


def distance(p0: np.ndarray, p1: np.ndarray) -> float:
    """Euclidean distance between two 3-D points (in the scene's unit)."""
    return float(np.linalg.norm(np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)))


def _surface_z(scene: PreviewScene, xy: np.ndarray) -> np.ndarray:
    """Height of the surface under points (x, y): from the full-resolution height map
    (bilinear) when known, else the first hit of a ray cast down onto the display mesh."""
    if scene.height is not None:
        from scipy.ndimage import map_coordinates

        rows, cols = -xy[:, 1] / scene.pixel_size, xy[:, 0] / scene.pixel_size
        return map_coordinates(scene.height, [rows, cols], order=1, mode="constant", cval=np.nan)
    import open3d as o3d

    top = float(scene.vertices[:, 2].max()) + 1.0
    rays = np.zeros((len(xy), 6), np.float32)
    rays[:, :2], rays[:, 2], rays[:, 5] = xy, top, -1.0
    hit = scene._ray_scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(hit), top - hit, np.nan)


def profile(scene: PreviewScene, p0: np.ndarray, p1: np.ndarray, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Heights along the straight line from `p0` to `p1` seen from the camera.

    Parameters
    ----------
    scene : PreviewScene
    p0, p1 : array_like, shape (3,)
        End points (only x and y are used: the line is drawn on the image plane).
    n : int
        Number of samples, at least 2.

    Returns
    -------
    distances : numpy.ndarray
        ``(n,)`` distance along the line from `p0`, in the scene's unit.
    heights : numpy.ndarray
        ``(n,)`` surface height there (NaN off the object).
    """
    if n < 2:
        raise ValueError(f"a profile needs at least 2 samples, not {n}")
    a = np.asarray(p0, dtype=np.float64)[:2]
    b = np.asarray(p1, dtype=np.float64)[:2]
    t = np.linspace(0.0, 1.0, n)
    xy = a + t[:, None] * (b - a)
    return t * float(np.linalg.norm(b - a)), _surface_z(scene, xy).astype(np.float64)


# --- loading -----------------------------------------------------------------------------


def _resize(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area-average an image to ``(h, w)`` (coefficients are linear in the light, so their
    average relights as the average of the relit pixels before clipping)."""
    import cv2

    if image.shape[:2] == shape:
        return np.asarray(image)
    flat = image.reshape(image.shape[:2] + (-1,))
    # OpenCV resamples at most 4 channels at a time with non-integer factors.
    parts = [
        cv2.resize(np.ascontiguousarray(flat[..., k:k + 4]), (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
        for k in range(0, flat.shape[2], 4)
    ]
    out = np.concatenate([p.reshape(shape + (-1,)) for p in parts], axis=2)
    return out.reshape(shape + image.shape[2:])


def _texture_shape(shape: tuple[int, int], max_texture: int) -> tuple[int, int]:
    factor = max(1.0, max(shape) / max_texture)
    return max(1, round(shape[0] / factor)), max(1, round(shape[1] / factor))


def _grid_step(shape: tuple[int, int], max_vertices: int) -> int:
    """Smallest grid step giving at most `max_vertices` vertices (last row and column kept)."""
    step = 1
    while (math.ceil((shape[0] - 1) / step) + 1) * (math.ceil((shape[1] - 1) / step) + 1) > max_vertices:
        step += 1
    return step


def _unit_normals(normals: np.ndarray) -> np.ndarray:
    """Normals rescaled to unit length (area averages are shorter); (0, 0, 1) where unknown."""
    normals = np.nan_to_num(np.asarray(normals, dtype=np.float32), nan=0.0)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    flat = np.zeros_like(normals)
    flat[..., 2] = 1.0
    return np.where(length > 1e-6, normals / np.maximum(length, 1e-6), flat).astype(np.float32)


def _read_rgb(path: Path) -> np.ndarray:
    from ptmcore.images import read_image

    image = read_image(path)
    return np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image


def _lrgb(path: Path, max_texture: int) -> tuple[tuple[int, int], np.ndarray, np.ndarray]:
    """The PTM's full size, and its LRGB coefficients and colour decoded at every k-th pixel,
    k the largest step that keeps at least the texture's resolution (the texture is then an
    area average of at most 2 × 2 samples per texel), so memory follows the texture, not the PTM."""
    from ptmcore.ptmfile import read_ptm
    from ptmcore.relight import as_lrgb

    ptm = read_ptm(path, max_side=2 * max_texture)
    return (ptm.height, ptm.width), *as_lrgb(ptm)


def _published(folder: Path, shape: tuple[int, int], tex: tuple[int, int]) -> PublishedBasis | None:
    """The basis published in the folder's ``web/`` at texture size, or None when it has none.

    Only what the texture needs is decoded (:func:`reconstruct.report.webread.read_relightable`
    with ``max_side``: a pyramid level or DCT-scaled planes, at most twice the texture's side),
    then area-averaged to the texture as the PTM is: the planes are linear in the light, so an
    MRGB average relights as the average of the relit pixels (LRGB's colour times luminance
    nearly so, as the PTM's)."""
    from dataclasses import replace

    from reconstruct.report.webread import published_folder, read_relightable, relightable_shape

    web = published_folder(folder)
    if web is None:
        return None
    declared = relightable_shape(web)
    if declared != shape:
        raise InputError(f"web/info.json is {declared}, height.tif {shape}", folder)
    basis = read_relightable(web, max_side=max(tex))
    planes = _resize(basis.planes, tex).astype(np.float32)
    colour = None if basis.colour is None else _resize(basis.colour, tex)
    return replace(basis, planes=planes, colour=colour)


def _texture_normals(normals: np.ndarray, tex: tuple[int, int], max_texture: int) -> np.ndarray:
    """Unit normals at texture size from a (memory-mapped) full-resolution normal map: strided
    as the PTM is (:func:`_lrgb`) before anything is copied, then area-averaged."""
    s = stride_for(normals.shape, 2 * max_texture)
    sample = np.nan_to_num(np.asarray(normals[::s, ::s], dtype=np.float32), nan=0.0)
    return _unit_normals(_resize(sample, tex))


def _read_distances(ply: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and signed distances (the ``quality`` property) of a ``distances.ply``."""
    import trimesh

    raw = read_input_file(ply, "distances.ply")
    try:
        loaded = trimesh.load(io.BytesIO(raw), file_type="ply", process=False, skip_materials=True)
        data = loaded.metadata["_ply_raw"]["vertex"]["data"]
        points = np.column_stack([data["x"], data["y"], data["z"]]).astype(np.float64)
        return points, np.asarray(data["quality"], dtype=np.float64)
    except (KeyError, ValueError, TypeError, OSError) as exc:
        raise InputError(f"not a distances.ply of reconstruct compare (no signed distances: {exc})", ply) from None


def _distances_on(vertices: np.ndarray, ply: Path, spacing: float) -> np.ndarray:
    """Signed distances of `ply` carried to the nearest display vertex seen from the camera;
    NaN where no distance vertex lies within a few grid spacings."""
    from scipy.spatial import cKDTree

    points, values = _read_distances(ply)
    tree = cKDTree(points[:, :2])
    # The comparison's mesh may be finer, coarser or decimated: its own spacing bounds the
    # search too.
    sample = points[:: max(1, len(points) // 2000), :2]
    own = float(np.median(tree.query(sample, k=2)[0][:, 1])) if len(points) > 1 else spacing
    gap, index = tree.query(vertices[:, :2], distance_upper_bound=2.0 * max(spacing, own))
    found = np.isfinite(gap)
    out = np.full(len(vertices), np.nan)
    out[found] = values[index[found]]
    return out


def _comparison(folder: Path, vertices: np.ndarray, spacing: float) -> tuple[np.ndarray | None, float | None]:
    ply = folder / "distances.ply"
    if not ply.is_file():
        return None, None
    d = _distances_on(vertices, ply, spacing)
    limit = None
    report = folder / "comparison.json"
    if report.is_file():
        try:
            limit = float(json.loads(read_input_text(report, "comparison.json"))["colour_range_mm"][1])
        except (KeyError, IndexError, TypeError, ValueError):
            limit = None
    if limit is None or not limit > 0:
        from reconstruct.compare.figures import default_limit

        limit = default_limit(d)
    return d, limit


def _load_folder(folder: Path, comparison: Path | None, max_vertices: int, max_texture: int) -> PreviewScene:
    height_file = folder / "height.tif"
    if not height_file.is_file():
        raise InputError("not an output folder of reconstruct run (no height.tif)", folder)
    report: dict = {}
    if (folder / "report.json").is_file():
        try:
            report = json.loads(read_input_text(folder / "report.json", "report.json"))
        except ValueError as exc:
            raise InputError(f"corrupt report.json ({exc})", folder / "report.json") from None
    height = np.asarray(map_array(height_file), dtype=np.float32)
    if height.ndim != 2:
        raise InputError(f"the height map must be one 2-D plane, not {height.shape}", height_file)
    unit = report.get("height_unit", "pixel")
    pixel_size = display_pixel_size(report)
    s = float(pixel_size) if pixel_size else 1.0

    step = _grid_step(height.shape, max_vertices)
    mesh = grid_mesh(height, step=step, pixel_size=pixel_size)
    if len(mesh.faces) == 0:
        raise InputError("the height map has no object (all NaN)", height_file)
    tex = _texture_shape(height.shape, max_texture)

    coefficients = rgb = None
    if (folder / "coefficients.ptm").is_file():
        shape, coef, colour = _lrgb(folder / "coefficients.ptm", max_texture)
        if shape != height.shape:
            raise InputError(f"coefficients.ptm is {shape}, height.tif {height.shape}", folder)
        coefficients, rgb = _resize(coef, tex).astype(np.float32), _resize(colour, tex)
        del coef, colour
    normals = None
    if (folder / "normals.npy").is_file():
        full = map_array(folder / "normals.npy")
        if full.shape != height.shape + (3,):
            raise InputError(f"normals.npy is {full.shape}, expected {height.shape + (3,)}", folder)
        normals = _texture_normals(full, tex, max_texture)
    published = _published(folder, height.shape, tex)
    albedo = None
    for name in ("albedo.png", "mesh_texture.png"):
        if (folder / name).is_file():
            albedo = _resize(_read_rgb(folder / name), tex)
            break
    if albedo is None and rgb is not None:
        albedo = rgb

    d, limit = _comparison(comparison or folder, mesh.vertices, step * s)
    return PreviewScene(
        name=folder.resolve().name,
        vertices=mesh.vertices,
        faces=mesh.faces,
        unit=unit,
        uv=mesh.uv,
        coefficients=coefficients,
        rgb=rgb,
        normals=normals,
        albedo=albedo,
        height=height,
        pixel_size=s,
        vertex_distance=d,
        distance_limit=limit,
        linear_ptm=linear_ptm(report),
        folder=folder,
        published=published,
    )


def _load_ptm(path: Path, max_vertices: int, max_texture: int) -> PreviewScene:
    """A ``.ptm`` file as a flat plane (pixel units) textured by its relit PTM: a PTM holds
    no heights, and integrating its normals is what ``reconstruct run file.ptm`` does. A
    ``report.json`` beside it says whether it holds linear light."""
    from ptmcore.normals import normals_from_ptm
    from reconstruct.report.figures import holds_linear_light

    shape, coef, colour = _lrgb(path, max_texture)
    tex = _texture_shape(shape, max_texture)
    coefficients, rgb = _resize(coef, tex).astype(np.float32), _resize(colour, tex)
    del coef, colour
    mesh = grid_mesh(np.zeros(shape, np.float32), step=_grid_step(shape, max_vertices))
    normals = normals_from_ptm(coefficients)
    scene = PreviewScene(
        name=path.stem,
        vertices=mesh.vertices,
        faces=mesh.faces,
        unit="pixel",
        uv=mesh.uv,
        coefficients=coefficients,
        rgb=rgb,
        normals=normals,
        albedo=rgb,
        linear_ptm=holds_linear_light(path),
        folder=path.parent,
    )
    # A PTM file's normals are its maxima: specular enhancement and diffuse gain reuse them.
    scene.maximum = normals
    return scene


def _mesh_unit(path: Path) -> str:
    """The unit a PLY states in a ``comment unit`` line (ours do), else ``"unknown"``."""
    if path.suffix.lower() != ".ply":
        return "unknown"
    return next((w[2] for w in ply_header(path) if w[:2] == ["comment", "unit"] and len(w) > 2), "unknown")


def _vertex_colours(mesh) -> np.ndarray | None:
    """A trimesh mesh's colours at its vertices, or None when it has none: a texture it names
    that was not read (refused, missing) leaves a material without an image, which trimesh
    cannot sample."""
    if not mesh.visual.defined:
        return None
    try:
        return mesh.visual.to_color().vertex_colors[:, :3]
    except (TypeError, ValueError, AttributeError):
        return None


def _load_mesh(path: Path, max_vertices: int) -> PreviewScene:
    """A mesh file with its colours (vertex colours, or its texture sampled at the vertices)
    and normals (the file's, else from the faces), relit per vertex."""
    import trimesh

    from reconstruct.compare.geometry import mesh_files

    data = read_input_file(path, "mesh")
    # A PLY whose texture coordinates belong to the vertices (ours) needs no splitting at
    # seams; trimesh's search for them took 2 of the 12 s a 24-megapixel run's mesh.ply took.
    per_vertex = path.suffix.lower() == ".ply" and not any(
        w[:2] == ["property", "list"] and w[-1:] == ["texcoord"] for w in ply_header(path))
    # A glTF's images, embedded or named, reach Pillow without passing the resolver's check.
    gltf = path.suffix.lower() in (".glb", ".gltf")
    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=path.suffix.lower()[1:], process=False,
                            resolver=mesh_files(path, textures=not gltf), skip_materials=gltf,
                            **({"fix_texture": False} if per_vertex else {}))
        if isinstance(mesh, trimesh.Scene):
            # force="mesh" on every file dropped a PLY's own normals with the copy it made
            # (computing them again took 6 s).
            mesh = mesh.to_mesh()
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types for unreadable files
        raise InputError(f"cannot read the mesh ({exc})", path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("no triangles in this file", path)
    colors = _vertex_colours(mesh)
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float32)
    if len(vertices) > max_vertices:
        from reconstruct.mesh.grid import GridMesh
        from reconstruct.mesh.ops import decimate

        full = GridMesh(vertices, faces, np.zeros((len(vertices), 2), np.float32),
                        colors if colors is not None else np.full((len(vertices), 3), 255, np.uint8), normals)
        small, _ = decimate(full, target_faces=2 * max_vertices)
        vertices, faces, normals = small.vertices, small.faces, small.normals
        colors = small.colors if colors is not None else None
    if colors is None:
        colors = np.full((len(vertices), 3), 200, np.uint8)
    return PreviewScene(
        name=path.stem,
        vertices=vertices,
        faces=faces,
        unit=_mesh_unit(path),
        normals=_unit_normals(normals),
        albedo=np.ascontiguousarray(colors, dtype=np.uint8),
        folder=path.parent,
    )


def load_scene(
    source: str | os.PathLike,
    *,
    comparison: str | os.PathLike | None = None,
    max_vertices: int = MAX_VERTICES,
    max_texture: int = MAX_TEXTURE,
) -> PreviewScene:
    """Load what ``reconstruct preview`` shows.

    Parameters
    ----------
    source : path
        An output folder of ``reconstruct run`` (its height map as the mesh, its PTM or
        normals and albedo for the colours, its ``distances.ply`` when it was compared), a
        mesh file (PLY, OBJ, STL, GLB, OFF) or a ``.ptm`` file (a flat plane carrying the
        relit PTM).
    comparison : path, optional
        Folder of ``reconstruct compare`` whose ``distances.ply`` belongs to this output
        folder (default: the folder itself).
    max_vertices : int
        Display mesh size limit (the mesh is subsampled or decimated to it).
    max_texture : int
        Longest side of the colour images (the PTM is area-averaged to it).

    Raises
    ------
    InputError
        If the source does not exist or is not one of these.
    """
    path = Path(source)
    if not path.exists():
        raise InputError("not found", path)
    if comparison is not None and not (Path(comparison) / "distances.ply").is_file():
        raise InputError("no distances.ply in this folder (made by reconstruct compare)", comparison)
    if path.is_dir():
        return _load_folder(path, None if comparison is None else Path(comparison), max_vertices, max_texture)
    if comparison is not None:
        raise InputError("--comparison goes with an output folder of reconstruct run", path)
    suffix = path.suffix.lower()
    if suffix == ".ptm":
        return _load_ptm(path, max_vertices, max_texture)
    if suffix in MESH_SUFFIXES:
        return _load_mesh(path, max_vertices)
    raise InputError(
        "cannot preview this file: give an output folder, a mesh (" + ", ".join(MESH_SUFFIXES) + ") or a .ptm", path
    )
