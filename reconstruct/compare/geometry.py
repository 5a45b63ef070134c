"""Reconstructions and scans as points in millimetres: :class:`Geometry` and its readers.

:func:`load_geometry` reads meshes (through trimesh) and point clouds (PCD through open3d,
and plain-text XYZ/CSV/PTS) and converts them to millimetres. The normals of the reference
surface, which ICP and the signed distances need, come from the triangles of a mesh or from
local PCA of a cloud (:func:`vertex_normals`, :func:`estimate_normals`).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ptmcore.errors import InputError

# open3d is imported on use: it is slow to import, and reading meshes and text clouds
# does not need it.
if TYPE_CHECKING:
    import open3d as o3d

__all__ = [
    "CLOUD_SUFFIXES",
    "MESH_SUFFIXES",
    "UNITS",
    "Geometry",
    "estimate_normals",
    "load_geometry",
    "point_cloud",
    "vertex_normals",
]

#: Millimetres per unit accepted by :func:`load_geometry`.
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}

MESH_SUFFIXES = {".ply", ".obj", ".stl", ".off", ".glb", ".gltf"}
CLOUD_SUFFIXES = {".ply", ".pcd", ".xyz", ".txt", ".csv", ".pts"}


@dataclass
class Geometry:
    """Points (and possibly triangles) of a reconstruction or a scan, in millimetres.

    Attributes
    ----------
    points : numpy.ndarray
        ``(P, 3)`` float64 positions in mm (mesh vertices, or the cloud's points).
    faces : numpy.ndarray or None
        ``(F, 3)`` int64 vertex indices for a mesh; None for a point cloud.
    normals : numpy.ndarray or None
        ``(P, 3)`` float64 unit normals per point, if the file had them.
    source : Path or None
        The file it was read from.
    """

    points: np.ndarray
    faces: np.ndarray | None = None
    normals: np.ndarray | None = None
    source: Path | None = None

    @property
    def is_mesh(self) -> bool:
        """True when there are triangles."""
        return self.faces is not None and len(self.faces) > 0

    @property
    def diagonal(self) -> float:
        """Length of the axis-aligned bounding box's diagonal, mm."""
        return float(np.linalg.norm(self.points.max(axis=0) - self.points.min(axis=0)))


def load_geometry(path: str | os.PathLike, *, units: str = "mm") -> Geometry:
    """Read a mesh or point cloud and convert it to millimetres.

    Meshes: PLY, OBJ, STL, OFF, GLB/glTF (via trimesh). Point clouds: PLY and PCD, XYZ/TXT/CSV
    (x y z in the first three columns, separated by whitespace or commas, header lines and
    extra columns ignored) and PTS (a point count, then ``x y z [intensity r g b]``).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    units : str
        The file's unit: "mm", "cm", "m" or "in".

    Returns
    -------
    Geometry

    Raises
    ------
    InputError
        If the file is missing or unreadable, not a mesh or point cloud, empty, has
        non-finite coordinates, or all its points lie on a line; or for an unknown unit.
    """
    path = Path(path)
    if units not in UNITS:
        raise InputError(f"unknown unit {units!r}; choose from {', '.join(UNITS)}", path)
    if not path.exists():
        raise InputError("mesh or point cloud not found", path)
    if path.is_dir():
        raise InputError("is a folder, not a mesh or point cloud", path)
    suffix = path.suffix.lower()
    if suffix in {".xyz", ".txt", ".csv"}:
        points, faces, normals = _read_text_points(path, skip_count_line=False), None, None
    elif suffix == ".pts":
        points, faces, normals = _read_text_points(path, skip_count_line=True), None, None
    elif suffix == ".pcd":
        points, faces, normals = _read_open3d_cloud(path)
    elif suffix in MESH_SUFFIXES:
        points, faces, normals = _read_trimesh(path)
    else:
        known = ", ".join(sorted(MESH_SUFFIXES | CLOUD_SUFFIXES))
        raise InputError(f"not a known mesh or point-cloud format (expected one of {known})",
                         path)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3) * UNITS[units]
    _check_points(points, path)
    if faces is not None and len(faces) == 0:
        faces = None
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if len(normals) != len(points) or not np.all(np.isfinite(normals)):
            normals = None
    return Geometry(points=points, faces=faces, normals=normals, source=path)


def _check_points(points: np.ndarray, path: Path | None) -> None:
    """Empty, non-finite or collinear points cannot be compared with anything."""
    if len(points) == 0:
        raise InputError("contains no points", path)
    if not np.all(np.isfinite(points)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(points), axis=1)))
        raise InputError(f"{bad} points have NaN or infinite coordinates", path)
    if len(points) < 3:
        raise InputError(f"has only {len(points)} points; need at least 3", path)
    centred = points - points.mean(axis=0)
    eigenvalues = np.linalg.eigvalsh(centred.T @ centred / len(points))  # ascending
    # The second-largest variance is what a line lacks; relative, so units do not matter.
    if eigenvalues[1] <= 1e-10 * max(eigenvalues[2], np.finfo(float).tiny):
        raise InputError("all points lie on a line (or on one point): degenerate geometry",
                         path)


_NUMBER = re.compile(rb"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")


def _read_text_points(path: Path, *, skip_count_line: bool) -> np.ndarray:
    """x, y, z of a whitespace- or comma-separated text file, skipping header lines."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read the point file ({exc.strerror or exc})", path) from None
    lines = data.splitlines()
    start = 0
    if skip_count_line:
        first = lines[0].strip() if lines else b""
        if not _NUMBER.match(first):
            raise InputError("a PTS file must start with the number of points", path)
        start = 1
    # Header lines are whatever precedes the first line that starts with three numbers.
    while start < len(lines) and not _starts_with_xyz(lines[start]):
        if lines[start].strip() and start > 50:
            raise InputError("no lines of x y z numbers found", path)
        start += 1
    body = b"\n".join(line for line in lines[start:] if line.strip())
    if not body:
        raise InputError("contains no points", path)
    # One parse of the whole body: commas become spaces, so both layouts read alike.
    text = body.replace(b",", b" ").replace(b";", b" ").replace(b"\t", b" ")
    rows = text.split(b"\n")
    n_cols = len(rows[0].split())
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise InputError("contains a line that is not numbers", path) from None
    if values.size != n_cols * len(rows):
        raise InputError("lines have different numbers of columns", path)
    return values.reshape(len(rows), n_cols)[:, :3]


def _starts_with_xyz(line: bytes) -> bool:
    fields = line.replace(b",", b" ").replace(b";", b" ").split()
    return len(fields) >= 3 and all(_NUMBER.match(f) for f in fields[:3])


def _read_open3d_cloud(path: Path) -> tuple[np.ndarray, None, np.ndarray | None]:
    import open3d as o3d

    try:
        cloud = o3d.io.read_point_cloud(str(path))
    except Exception as exc:  # open3d raises RuntimeError with a C++ message
        raise InputError(f"not a readable point cloud ({exc})", path) from None
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    return np.asarray(cloud.points), None, normals


def _read_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    import trimesh

    # Only the geometry is compared: trimesh would split a textured PLY's vertices where their
    # texture coordinates differ (4 of the 5 s it took to read a 24-megapixel run's mesh.ply),
    # and decode the texture image.
    options = {"fix_texture": False, "skip_materials": True} if path.suffix.lower() == ".ply" else {}
    try:
        loaded = trimesh.load(str(path), process=False, **options)
    except Exception as exc:  # trimesh raises many kinds for a malformed file
        raise InputError(f"not a readable mesh or point cloud ({exc})", path) from None
    if isinstance(loaded, trimesh.Scene):
        # A GLB/glTF scene: its meshes, each moved by its node transform.
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] \
            if loaded.geometry else []
        if not meshes:
            raise InputError("contains no mesh", path)
        loaded = trimesh.util.concatenate(meshes)
    if isinstance(loaded, trimesh.Trimesh):
        faces = np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3)
        normals = None
        if "vertex_normals" in loaded._cache or "normals" in getattr(loaded, "metadata", {}):
            normals = np.asarray(loaded.vertex_normals)
        return np.asarray(loaded.vertices), faces, normals
    if isinstance(loaded, trimesh.PointCloud):
        return np.asarray(loaded.vertices), None, None
    raise InputError("is not a mesh or point cloud", path)


def point_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """An open3d point cloud, the input of its registration and normal estimation.

    Parameters
    ----------
    points : numpy.ndarray
        ``(P, 3)`` positions.
    normals : numpy.ndarray, optional
        ``(P, 3)`` normals.

    Returns
    -------
    open3d.geometry.PointCloud
    """
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return cloud


def vertex_normals(geometry: Geometry) -> np.ndarray:
    """Area-weighted vertex normals of a mesh, oriented towards +z (the camera) on the whole.

    Parameters
    ----------
    geometry : Geometry
        A mesh.

    Returns
    -------
    numpy.ndarray
        ``(P, 3)`` float64 unit normals; ``(0, 0, 1)`` at vertices on no face.
    """
    p, f = geometry.points, geometry.faces
    face_n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    if face_n[:, 2].sum() < 0:
        face_n = -face_n
    normals = np.zeros_like(p)
    for k in range(3):
        np.add.at(normals, f[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.tile([0.0, 0.0, 1.0], (len(p), 1)),
                     where=length > 0)


def estimate_normals(points: np.ndarray, radius: float) -> np.ndarray:
    """Normals of a point cloud from local PCA, pointing towards +z (the camera) where they can.

    Parameters
    ----------
    points : numpy.ndarray
        ``(P, 3)`` positions, mm.
    radius : float
        Neighbourhood radius, mm (at most 30 neighbours are used).

    Returns
    -------
    numpy.ndarray
        ``(P, 3)`` float64 unit normals.
    """
    import open3d as o3d

    cloud = point_cloud(points)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    cloud.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    return np.asarray(cloud.normals)
