"""Mesh operations for delivery: decimation, watertight solids for printing, STL and GLB.

A grid mesh (:func:`reconstruct.mesh.grid.grid_mesh`) has one vertex per pixel, far more than a
viewer or a printer needs. :func:`decimate` reduces it to a triangle budget or to a maximum
geometric error; :func:`solid` closes the relief into a printable solid, written by
:func:`write_stl`; :func:`write_glb` writes a single-file glTF for web and AR viewers.

Geometry follows ``docs/CONVENTIONS.md``: x right, y up, z towards the camera, positions in
the mesh's unit (``"mm"`` or ``"pixel"``). Every file is written through
:func:`ptmcore.atomic.atomic_write`.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
from PIL import Image

from ptmcore.atomic import atomic_write
from reconstruct.mesh.grid import GridMesh, grid_mesh
from reconstruct.mesh.topology import boundary_edges, edge_face_counts

# open3d is imported inside the functions that decimate: it is slow to import, and solids,
# STL and GLB (and the rest of the package) must work where it is not installed.
if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["decimate", "solid", "write_glb", "write_stl"]

# Open3D's quadric decimation adds a penalty quadric on boundary edges scaled by this
# weight. The outline of an object is what a conservator measures first, and the walls of
# a printed solid hang from it, so it is held much more firmly than the default of 1.
_BOUNDARY_WEIGHT = 100.0
# The max-error search stops once the triangle count is known to within this ratio: the
# error is only roughly monotonic in the count, so finer bisection buys nothing.
_SEARCH_RATIO = 1.05
_SEARCH_STEPS = 30
# Fewest triangles asked of the decimation: below this no surface is left to measure.
_MIN_FACES = 4


# --------------------------------------------------------------------------- decimation


def _o3d_mesh(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    import open3d as o3d

    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)),
    )


def _scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene (a BVH) for exact point-to-triangle distances."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    return scene


def _distances(scene: o3d.t.geometry.RaycastingScene, points: np.ndarray) -> np.ndarray:
    """Unsigned distances of `points` to the triangles of `scene`."""
    import open3d as o3d

    query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def _quadric(source: o3d.geometry.TriangleMesh, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of `source` decimated towards `target` triangles."""
    out = source.simplify_quadric_decimation(
        int(target), boundary_weight=_BOUNDARY_WEIGHT
    )
    # Collapses can leave unreferenced vertices; they would only bloat the files.
    out.remove_unreferenced_vertices()
    return np.asarray(out.vertices), np.asarray(out.triangles)


def _errors(
    original: GridMesh,
    original_scene: o3d.t.geometry.RaycastingScene,
    vertices: np.ndarray,
    faces: np.ndarray,
) -> tuple[float, float]:
    """(max, RMS) geometric error of a decimation, in the mesh's unit.

    The RMS is over the original vertices' distances to the decimated surface. The maximum
    also includes the decimated vertices' distances to the original surface: quadric
    collapses place vertices at optimal positions off the original grid, and one-sided
    distances would miss a spike that no original vertex sits next to.
    """
    if len(faces) == 0:
        return float("inf"), float("inf")
    forward = _distances(_scene(vertices, faces), original.vertices)
    backward = _distances(original_scene, vertices)
    return float(max(forward.max(), backward.max())), float(np.sqrt(np.mean(forward**2)))


def _resample(
    original: GridMesh, original_scene: o3d.t.geometry.RaycastingScene, vertices: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """UVs, colours and normals at `vertices`, interpolated on the original mesh.

    Open3D carries vertex colours through the collapses by averaging, but not the UVs
    (its UVs are per triangle corner and are dropped) and the averaged colours no longer
    match the moved vertices. Interpolating every attribute at the closest point of the
    original surface keeps them consistent with the geometry, and is exact for grid UVs,
    which are affine in x and y.
    """
    import open3d as o3d

    query = o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32))
    closest = original_scene.compute_closest_points(query)
    tri = original.faces[closest["primitive_ids"].numpy().astype(np.int64)]
    bu, bv = closest["primitive_uvs"].numpy().astype(np.float64).T
    weights = np.stack([1.0 - bu - bv, bu, bv], axis=1)

    def interpolate(values: np.ndarray) -> np.ndarray:
        return np.einsum("nkc,nk->nc", values[tri].astype(np.float64), weights)

    uv = interpolate(original.uv).astype(np.float32)
    colors = np.clip(np.rint(interpolate(original.colors)), 0, 255).astype(np.uint8)
    normals = None
    if original.normals is not None:
        normals = interpolate(original.normals)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        # Opposite normals can cancel on a crease: fall back to the camera direction.
        normals = np.where(length > 1e-12, normals / np.maximum(length, 1e-12), (0.0, 0.0, 1.0))
        normals = normals.astype(np.float32)
    return uv, colors, normals


def decimate(
    mesh: GridMesh,
    *,
    target_faces: int | None = None,
    max_error: float | None = None,
) -> tuple[GridMesh, dict[str, Any]]:
    """Reduce a mesh by quadric edge collapse, to a triangle count or an error bound.

    Open3D's ``simplify_quadric_decimation`` (Garland and Heckbert) is used, with the
    boundary held firmly so that the object's outline survives. It keeps positions only
    (its per-corner UVs are dropped), so the UVs, colours and normals of the result are
    interpolated on the original mesh at the closest point to each new vertex: exact for
    the grid UVs (affine in x, y), and colours that match where the vertex now is.
    (pymeshlab's texture-preserving collapse would keep per-wedge UVs instead, but writes
    them per face corner, which :class:`GridMesh` cannot hold.)

    Parameters
    ----------
    mesh : GridMesh
        The mesh to reduce; it is not modified.
    target_faces : int, optional
        Triangle count to reach (Open3D may stop a little above it).
    max_error : float, optional
        Largest allowed geometric error, in the mesh's unit (see the report's
        ``max_error``). The fewest triangles meeting it are searched by bisection on the
        logarithm of the count, to within 5 %.

    Returns
    -------
    GridMesh
        The reduced mesh, same unit.
    dict
        ``faces_before``, ``faces_after``, ``vertices_before``, ``vertices_after``,
        ``max_error`` (largest distance of an original vertex to the reduced surface, or of
        a reduced vertex to the original one), ``rms_error`` (RMS distance of the original
        vertices to the reduced surface), ``unit``, ``mode`` (``"target_faces"`` or
        ``"max_error"``), ``requested`` (the target or the bound), ``decimations`` (runs of
        the decimation).

    Raises
    ------
    ValueError
        Unless exactly one of `target_faces` (≥ 1) and `max_error` (≥ 0) is given.
    """
    if (target_faces is None) == (max_error is None):
        raise ValueError("give exactly one of target_faces and max_error")
    if target_faces is not None and (int(target_faces) != target_faces or target_faces < 1):
        raise ValueError(f"target_faces must be a positive integer, not {target_faces}")
    if max_error is not None and not (np.isfinite(max_error) and max_error >= 0):
        raise ValueError(f"max_error must be a non-negative number, not {max_error}")

    n_faces = len(mesh.faces)
    source = _o3d_mesh(mesh.vertices, mesh.faces)
    original_scene = _scene(mesh.vertices, mesh.faces)
    runs = 0

    if target_faces is not None:
        mode, requested = "target_faces", int(target_faces)
        if requested >= n_faces:
            vertices, faces = mesh.vertices.astype(np.float64), np.asarray(mesh.faces)
        else:
            vertices, faces = _quadric(source, requested)
            runs = 1
        err_max, err_rms = _errors(mesh, original_scene, vertices, faces)
    else:
        mode, requested = "max_error", float(max_error)
        # Invariant: the count `hi` meets the bound (the full mesh does, with error 0),
        # `lo` does not or is the floor.
        hi, lo = n_faces, min(_MIN_FACES, n_faces)
        best = (mesh.vertices.astype(np.float64), np.asarray(mesh.faces), 0.0, 0.0)
        trial = lo
        for _ in range(_SEARCH_STEPS):
            if hi <= lo * _SEARCH_RATIO or hi - lo <= 1:
                break
            vertices, faces = _quadric(source, trial)
            runs += 1
            e_max, e_rms = _errors(mesh, original_scene, vertices, faces)
            if e_max <= requested:
                hi = min(trial, len(faces)) if len(faces) else trial
                best = (vertices, faces, e_max, e_rms)
                if trial == lo:
                    break  # even the floor meets the bound
            else:
                lo = trial
            trial = round(float(np.sqrt(float(lo) * hi)))  # geometric bisection
            trial = min(max(trial, lo + 1), hi - 1)
        vertices, faces, err_max, err_rms = best

    uv, colors, normals = _resample(mesh, original_scene, vertices)
    index_dtype = mesh.faces.dtype if len(faces) else np.int32
    reduced = GridMesh(
        vertices=vertices.astype(np.float32),
        faces=np.asarray(faces).astype(index_dtype),
        uv=uv,
        colors=colors,
        normals=normals,
        unit=mesh.unit,
    )
    report = {
        "mode": mode,
        "requested": requested,
        "faces_before": n_faces,
        "faces_after": len(reduced.faces),
        "vertices_before": len(mesh.vertices),
        "vertices_after": len(reduced.vertices),
        "max_error": err_max,
        "rms_error": err_rms,
        "unit": mesh.unit,
        "decimations": runs,
    }
    return reduced, report


# --------------------------------------------------------------------------------- solid


def _fans(faces: np.ndarray, v: int) -> np.ndarray:
    """Label of the fan of each of `faces` (all containing `v`): faces sharing an edge from
    `v` are in the same fan. Labels are 0, 1, … (union-find over a handful of faces)."""
    parent = list(range(len(faces)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    first_with: dict[int, int] = {}
    for i, face in enumerate(faces.tolist()):
        for w in face:
            if w == v:
                continue
            if w in first_with:
                parent[root(i)] = root(first_with[w])
            else:
                first_with[w] = i
    roots = np.array([root(i) for i in range(len(faces))])
    return np.unique(roots, return_inverse=True)[1].ravel()


def _drop_pinches(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Faces without pinch vertices, where fans of faces meet at a single vertex.

    A mask whose pixels touch only diagonally gives such vertices. Walls hung from both
    fans would share their vertical edge below it with four faces, which is neither
    watertight for trimesh nor manifold for Open3D, and could not be printed. At each pinch the
    largest fan is kept and the others dropped, repeatedly, since dropping a fan can pinch
    a neighbour. Pinches are few (on the outline only), so the fans are found in Python.
    """
    while True:
        boundary = boundary_edges(faces, n_vertices)
        pinched = np.flatnonzero(np.bincount(boundary.ravel(), minlength=n_vertices) > 2)
        if len(pinched) == 0:
            return faces
        drop = np.zeros(len(faces), dtype=bool)
        for v in pinched:
            around = np.flatnonzero((faces == v).any(axis=1))
            fans = _fans(faces[around], int(v))
            sizes = np.bincount(fans)
            drop[around[fans != np.argmax(sizes)]] = True
        faces = faces[~drop]


def solid(
    relief: GridMesh | np.ndarray,
    base_thickness: float,
    *,
    pixel_size: float | None = None,
) -> trimesh.Trimesh:
    """Close a relief into a watertight solid for 3D printing.

    The relief is closed by vertical walls hung from its boundary edges (edges used by one
    face: the outline and the rims of holes) down to a flat base `base_thickness` below its
    lowest point. The base is the relief's own triangulation flattened onto that plane and
    reversed, so the walls meet it edge for edge and islands and holes need no polygon
    triangulation; it doubles the triangle count of the relief (decimate first for a
    smaller file). Faces are oriented outwards: the relief faces +z, the base −z.

    Vertices where parts of the mask touch only at a corner (pinches) cannot be closed
    into a manifold solid; the smaller fans of faces there are dropped (see
    ``metadata["faces_dropped"]``).

    Parameters
    ----------
    relief : GridMesh or numpy.ndarray
        A mesh that is a height field (one z per (x, y), counter-clockwise from +z), such
        as a grid mesh or its decimation, or an ``(H, W)`` height map with NaN outside the
        object, meshed by :func:`reconstruct.mesh.grid.grid_mesh`.
    base_thickness : float
        Thickness of the base below the lowest point of the relief, in the mesh's unit.
    pixel_size : float, optional
        Pixel size in mm/pixel, for a height map only.

    Returns
    -------
    trimesh.Trimesh
        The solid, not processed (vertices are not merged). ``metadata`` holds ``unit``,
        ``base_z`` and ``faces_dropped``.

    Raises
    ------
    ValueError
        If `base_thickness` is not positive, the relief has no faces, an edge is shared by
        more than two faces, or `pixel_size` is given with a mesh.
    """
    if not (np.isfinite(base_thickness) and base_thickness > 0):
        raise ValueError(f"base_thickness must be a positive number, not {base_thickness}")
    if isinstance(relief, GridMesh):
        if pixel_size is not None:
            raise ValueError("pixel_size applies to height maps; a mesh has its unit")
        mesh = relief
    else:
        mesh = grid_mesh(np.asarray(relief), pixel_size=pixel_size)
    n = len(mesh.vertices)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        raise ValueError("the relief has no faces")
    if edge_face_counts(faces, n).max() > 2:
        raise ValueError("the relief has edges shared by more than two faces")
    n_before = len(faces)
    faces = _drop_pinches(faces, n)

    # Only vertices on faces: isolated pixels of the mask would float in the solid.
    used = np.unique(faces)
    top = mesh.vertices[used].astype(np.float64)
    faces = np.searchsorted(used, faces)
    m = len(top)
    base_z = float(top[:, 2].min()) - float(base_thickness)
    bottom = top.copy()
    bottom[:, 2] = base_z

    # A boundary edge a→b runs with the relief's winding; the wall runs b→a on top and
    # a'→b' at the bottom, and the reversed base b'→a', so every edge is used once in each
    # direction: watertight and consistently wound.
    edges = boundary_edges(faces, m)
    a, b = edges[:, 0], edges[:, 1]
    wall = np.concatenate(
        [np.stack([b, a, a + m], axis=1), np.stack([b, a + m, b + m], axis=1)]
    )
    base = faces[:, ::-1] + m
    result = trimesh.Trimesh(
        vertices=np.concatenate([top, bottom]),
        faces=np.concatenate([faces, wall, base]),
        process=False,
    )
    result.metadata.update(
        {"unit": mesh.unit, "base_z": base_z, "faces_dropped": n_before - len(faces)}
    )
    return result


def write_stl(path: str | os.PathLike, mesh: trimesh.Trimesh) -> None:
    """Write a mesh (typically a :func:`solid`) as a binary STL file, atomically.

    STL has no unit field: the coordinates are written as they are, in the mesh's unit
    (``mesh.metadata["unit"]``). Slicers assume millimetres, so a mesh in pixels prints
    one pixel per millimetre; build the solid from a height map with a pixel size.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    mesh : trimesh.Trimesh
        The mesh.

    Raises
    ------
    InputError
        If the file cannot be written.
    """
    data = trimesh.exchange.stl.export_stl(mesh)
    with atomic_write(path, "wb") as handle:
        handle.write(data)


# ----------------------------------------------------------------------------------- glTF


def write_glb(
    path: str | os.PathLike, mesh: GridMesh, texture: np.ndarray | None = None
) -> None:
    """Write a mesh as a binary glTF (GLB) file, atomically.

    With a texture the mesh carries its UVs and the texture as an embedded PNG (trimesh
    flips v to glTF's top-left origin); without one, its vertex colours. Vertex normals are
    written when the mesh has them. The unit is recorded as ``{"unit": ...}`` in the
    ``asset.extras`` and in the scene's ``extras`` (which trimesh reads back into
    ``Scene.metadata``).

    glTF nominally measures in metres and its frame (y up, +z towards the viewer) is the
    project's; the coordinates are written unscaled, so a viewer that trusts the metre
    shows a mesh in mm 1000 times too large: the ``unit`` extra says what they are.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.glb`` file.
    mesh : GridMesh
        The mesh.
    texture : numpy.ndarray, optional
        ``(H, W, 3)`` uint8 sRGB image for the UVs, stored unflipped (row 0 at the top).

    Raises
    ------
    InputError
        If the file cannot be written.
    ValueError
        For a malformed texture.
    """
    if texture is not None:
        texture = np.asarray(texture)
        if texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8:
            raise ValueError(
                f"texture must be (H, W, 3) uint8, not {texture.shape} {texture.dtype}"
            )
        visual: trimesh.visual.base.Visuals = trimesh.visual.TextureVisuals(
            uv=np.asarray(mesh.uv, dtype=np.float64),
            image=Image.fromarray(np.ascontiguousarray(texture)),
        )
    else:
        rgba = np.concatenate(
            [mesh.colors, np.full((len(mesh.colors), 1), 255, dtype=np.uint8)], axis=1
        )
        visual = trimesh.visual.ColorVisuals(vertex_colors=rgba)
    tm = trimesh.Trimesh(
        vertices=mesh.vertices,
        faces=mesh.faces,
        vertex_normals=mesh.normals,
        visual=visual,
        process=False,
    )
    scene = trimesh.Scene(tm)
    scene.metadata["unit"] = mesh.unit

    def add_unit(tree: dict) -> None:
        tree["asset"].setdefault("extras", {})["unit"] = mesh.unit

    data = trimesh.exchange.gltf.export_glb(
        scene, include_normals=mesh.normals is not None, tree_postprocessor=add_unit
    )
    with atomic_write(path, "wb") as handle:
        handle.write(data)
