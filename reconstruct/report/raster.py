"""A coloured triangle mesh drawn in software: the report's picture of the 3D mesh.

The page's mesh picture was drawn with pyvista, whose first render in a process costs the
pyvista import and an OpenGL context (Mesa's llvmpipe on a server without a GPU): about a
second of CPU in the last stage of a run, beside the files being written. A 6-megapixel run
without that render took 0.44 s less (median of 6 paired runs, 6.36 → 5.93 s; the issue notes
of issue 14). The picture is one fixed view of a height field of at most a few hundred thousand
triangles, which a z-buffer rasteriser compiled with numba draws in a few tens of milliseconds,
with no OpenGL at all: a server or cluster node without EGL or OSMesa gets the picture too, and
every machine the same pixels. The preview window, which people turn and zoom, keeps pyvista.

What VTK does by default is followed where it shows: a perspective camera with a 30° view
angle fitted to the mesh's bounding sphere (``ResetCamera``), Gouraud shading of the vertex
colours under a light kit of key, fill, head and back lights placed relative to the camera
(``vtkLightKit``'s defaults), two-sided lighting, and 2 × 2 supersampling for smooth edges.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["render_mesh", "vertex_normals"]

#: VTK's default vertical view angle of a perspective camera, in degrees.
VIEW_ANGLE = 30.0
#: vtkLightKit's lights relative to the camera: (elevation °, azimuth °, intensity).
#: Key 0.75; fill, head and back lights a third, a third and 1/3.5 of it.
LIGHT_KIT = ((50.0, 10.0, 0.75), (-75.0, -10.0, 0.25), (0.0, 0.0, 0.25), (0.0, 110.0, 0.107), (0.0, -110.0, 0.107))
#: Clay, for a mesh without colours.
CLAY = (199, 184, 163)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals: the area-weighted mean of the normals of the faces around each
    vertex (zero for a vertex in no face).

    trimesh's ``Trimesh.vertex_normals`` is the same; importing trimesh for it would cost half a
    second of a run's last stage, which this module exists to save.

    Parameters
    ----------
    vertices : ndarray, shape (V, 3)
    faces : ndarray, shape (F, 3), int
        Counter-clockwise seen from the side the normal points to.

    Returns
    -------
    ndarray, shape (V, 3), float32
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    # The cross product's length is twice the face's area: the weighting comes with it.
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    corners = f.ravel()
    out = np.stack([np.bincount(corners, np.repeat(cross[:, c], 3), minlength=len(v)) for c in range(3)], axis=1)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, length, out=np.zeros_like(out), where=length > 0).astype(np.float32)


def _look_at(vertices: np.ndarray, view: np.ndarray, zoom: float, aspect: float):
    """VTK's ResetCamera along ``view`` with ``zoom``: eye, its axes and tan(half the angle)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-12)
    half = math.radians(VIEW_ANGLE) / 2
    if aspect < 1:  # VTK fits the sphere to the narrower side
        half = math.atan(math.tan(half) * aspect)
    back = view / np.linalg.norm(view)
    eye = center + back * radius / math.sin(half)
    forward = -back
    right = np.cross(forward, (0.0, 0.0, 1.0))
    if np.linalg.norm(right) < 1e-9:  # looking straight down: the picture's up is +y
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return eye, forward, right, up, math.tan(math.radians(VIEW_ANGLE) / 2) / zoom


def _shade(vertices, normals, colours, eye, forward, right, up, *, ambient, diffuse, specular, power):
    """Each vertex's colour lit by :data:`LIGHT_KIT` (two-sided), in 0..255 float32."""
    towards_eye = eye - vertices
    towards_eye /= np.maximum(np.linalg.norm(towards_eye, axis=1, keepdims=True), 1e-30)
    n = np.where(np.sum(normals * towards_eye, axis=1, keepdims=True) < 0, -normals, normals)
    lit = np.full(len(vertices), ambient)
    shine = np.zeros(len(vertices))
    for elevation, azimuth, intensity in LIGHT_KIT:
        el, az = math.radians(elevation), math.radians(azimuth)
        light = math.cos(el) * (math.cos(az) * -forward + math.sin(az) * right) + math.sin(el) * up
        lit += diffuse * intensity * np.clip(n @ light, 0, None)
        halfway = towards_eye + light
        halfway /= np.maximum(np.linalg.norm(halfway, axis=1, keepdims=True), 1e-30)
        shine += specular * intensity * np.clip(np.sum(n * halfway, axis=1), 0, None) ** power
    return (colours * lit[:, None] + 255.0 * shine[:, None]).astype(np.float32)


@numba.njit(nogil=True, cache=True)
def _rasterise(x, y, depth, colour, faces, image, zbuf):  # pragma: no cover - compiled
    """Draw each triangle with a z-buffer, interpolating colour perspective-correctly."""
    h, w = zbuf.shape
    for t in range(faces.shape[0]):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        za, zb, zc = depth[a], depth[b], depth[c]
        if not (za > 0 and zb > 0 and zc > 0):  # behind the eye, or NaN
            continue
        xa, ya, xb, yb, xc, yc = x[a], y[a], x[b], y[b], x[c], y[c]
        area = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        if not abs(area) > 1e-12:
            continue
        c0 = max(int(math.floor(min(xa, xb, xc))), 0)
        c1 = min(int(math.ceil(max(xa, xb, xc))), w - 1)
        r0 = max(int(math.floor(min(ya, yb, yc))), 0)
        r1 = min(int(math.ceil(max(ya, yb, yc))), h - 1)
        ia, ib, ic = 1.0 / za, 1.0 / zb, 1.0 / zc
        for r in range(r0, r1 + 1):
            py = r + 0.5
            for col in range(c0, c1 + 1):
                px = col + 0.5
                wa = ((xb - px) * (yc - py) - (yb - py) * (xc - px)) / area
                wb = ((xc - px) * (ya - py) - (yc - py) * (xa - px)) / area
                wc = 1.0 - wa - wb
                if wa < 0 or wb < 0 or wc < 0:
                    continue
                inverse = wa * ia + wb * ib + wc * ic
                z = 1.0 / inverse
                if z >= zbuf[r, col]:
                    continue
                zbuf[r, col] = z
                for ch in range(3):
                    image[r, col, ch] = (wa * ia * colour[a, ch] + wb * ib * colour[b, ch] + wc * ic * colour[c, ch]) * z


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    colours: np.ndarray | None = None,
    size: tuple[int, int] = (900, 600),
    *,
    view: tuple[float, float, float] = (0.35, -0.75, 0.85),
    zoom: float = 1.2,
    ambient: float = 0.2,
    diffuse: float = 0.85,
    specular: float = 0.1,
    power: float = 20.0,
    background: tuple[int, int, int] = (255, 255, 255),
) -> np.ndarray:
    """Draw a mesh with its vertex colours, lit and shaded, from one viewpoint.

    Parameters
    ----------
    vertices : ndarray, shape (V, 3)
        Positions (x right, y up, z towards the viewer of the object, as the meshes of this
        program have them). Vertices with NaN coordinates leave their triangles out.
    faces : ndarray, shape (F, 3), int
        Vertex indices of each triangle.
    colours : ndarray, shape (V, 3), uint8, optional
        sRGB vertex colours; clay without.
    size : (int, int)
        ``(width, height)`` of the picture.
    view : (float, float, float)
        Direction from the mesh's centre towards the eye; the camera stands back until the
        mesh's bounding sphere fills the view, then zooms by ``zoom``. z is up on the screen.
        The default, the report's: from the front (−y) and a little to the right, about 46°
        above the object plane.
    zoom : float
        Magnification after fitting the bounding sphere (VTK's ``camera.zoom``).
    ambient, diffuse, specular, power : float
        The material, as VTK's actor properties.
    background : (int, int, int)
        sRGB colour where no triangle is drawn.

    Returns
    -------
    ndarray, shape (size[1], size[0], 3), uint8

    Raises
    ------
    ValueError
        For a mesh with no triangle with finite vertices, indices out of range, a zero view
        direction or a zoom that is not positive.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), not {v.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("faces refer to vertices that do not exist")
    direction = np.asarray(view, np.float64)
    if direction.shape != (3,) or not np.isfinite(direction).all() or not direction.any():
        raise ValueError(f"view must be a non-zero direction (x, y, z), not {view}")
    if not (math.isfinite(zoom) and zoom > 0):
        raise ValueError(f"zoom must be a positive number, not {zoom}")
    finite = np.isfinite(v).all(axis=1)
    f = f[finite[f].all(axis=1)]
    if not len(f):
        raise ValueError("the mesh has no triangle to draw")
    used = v[np.unique(f)]
    width, height = int(size[0]), int(size[1])
    eye, forward, right, up, tan_half = _look_at(used, direction, zoom, width / height)

    rgb = np.broadcast_to(np.asarray(CLAY if colours is None else colours, np.float64)[..., :3], v.shape)
    placed = np.where(finite[:, None], v, 0.0)  # a NaN vertex is in no triangle drawn
    shaded = _shade(placed, vertex_normals(placed, f), rgb, eye, forward, right, up, ambient=ambient,
                    diffuse=diffuse, specular=specular, power=power)

    # Drawn at twice the size, then each 2 × 2 block averaged: edges without staircases.
    ss = 2
    big_w, big_h = width * ss, height * ss
    d = v - eye
    depth = d @ forward
    scale = (big_h / 2) / tan_half
    with np.errstate(divide="ignore", invalid="ignore"):
        x = big_w / 2 + scale * (d @ right) / depth
        y = big_h / 2 - scale * (d @ up) / depth
    image = np.empty((big_h, big_w, 3), np.float32)
    image[:] = np.asarray(background, np.float32)
    zbuf = np.full((big_h, big_w), np.inf, np.float64)
    _rasterise(x, y, np.where(finite, depth, np.nan), shaded, f, image, zbuf)
    small = (image[0::2, 0::2] + image[1::2, 0::2]) + (image[0::2, 1::2] + image[1::2, 1::2])
    small *= np.float32(0.25)
    return np.clip(np.rint(small), 0, 255).astype(np.uint8)
