"""Reconstructions and scans as points in millimetres: :class:`Geometry` and its readers.

:func:`load_geometry` reads meshes (through trimesh) and point clouds (PCD through open3d,
and plain-text XYZ/CSV/PTS) and converts them to millimetres. The normals of the reference
surface, which ICP and the signed distances need, come from the triangles of a mesh or from
local PCA of a cloud (:func:`vertex_normals`, :func:`estimate_normals`).

Only a regular file is read, and the counts a PLY, STL, OFF or PCD header claims are checked
against the file's length before a library allocates for them. Meshes are parsed from the
file's bytes; of the files a mesh names, only regular files in its own folder are read
(:func:`mesh_files`: a glTF's buffers), and never its materials and textures.
"""

from __future__ import annotations

import io
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ptmcore.errors import InputError, open_input_file, read_input_file

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
    "mesh_files",
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
    suffix = path.suffix.lower()
    with open_input_file(path, "mesh or point cloud") as f:
        if suffix not in MESH_SUFFIXES | CLOUD_SUFFIXES:
            known = ", ".join(sorted(MESH_SUFFIXES | CLOUD_SUFFIXES))
            raise InputError(f"not a known mesh or point-cloud format (expected one of {known})",
                             path)
        try:
            data = f.read()
        except OSError as exc:
            raise InputError(f"cannot read the mesh or point cloud ({exc.strerror or exc})", path) from None
    if not data.strip():
        raise InputError("contains no points (the file is empty)", path)
    _check_claimed_counts(data, suffix, path)
    if suffix in {".xyz", ".txt", ".csv"}:
        points, faces, normals = _read_text_points(data, path, skip_count_line=False), None, None
    elif suffix == ".pts":
        points, faces, normals = _read_text_points(data, path, skip_count_line=True), None, None
    elif suffix == ".pcd":
        points, faces, normals = _read_open3d_cloud(path)
    else:
        points, faces, normals = _read_trimesh(data, suffix, path)
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
    with np.errstate(over="ignore", invalid="ignore"):
        covariance = centred.T @ centred / len(points)
    if not np.all(np.isfinite(covariance)):
        raise InputError("its coordinates are too large to be a surface in any unit", path)
    eigenvalues = np.linalg.eigvalsh(covariance)  # ascending
    # The second-largest variance is what a line lacks; relative, so units do not matter.
    if eigenvalues[1] <= 1e-10 * max(eigenvalues[2], np.finfo(float).tiny):
        raise InputError("all points lie on a line (or on one point): degenerate geometry",
                         path)


#: Bytes of each PLY property type.
_PLY_SIZES = {name: size for size, names in (
    (1, ("char", "int8", "uchar", "uint8")), (2, ("short", "int16", "ushort", "uint16")),
    (4, ("int", "int32", "uint", "uint32", "float", "float32")), (8, ("double", "float64"))) for name in names}
#: The most bytes LZF (PCD's binary_compressed) decodes from one: a 264-byte match in 3 bytes.
_LZF_MAX_RATIO = 88


def _check_claimed_counts(data: bytes, suffix: str, path: Path) -> None:
    """Refuse a file whose header claims more vertices, faces or points than its bytes can
    hold, before a library allocates for them (a lying header of a few bytes asks for
    gigabytes)."""
    claim = {".ply": _ply_claim, ".stl": _stl_claim, ".off": _off_claim, ".pcd": _pcd_claim}.get(suffix)
    found = claim(data) if claim else None
    if found is not None and found[1] > len(data):
        raise InputError(f"its header claims {found[0]}, at least {found[1]:,} bytes, but the file holds "
                         f"{len(data):,}: it is truncated or its header is damaged", path)


def _header_lines(data: bytes, end: bytes) -> tuple[list[list[bytes]], int] | None:
    """The words of the text header's lines up to the one starting with ``end``, and the
    offset after it; None when no such line is in the first 64 KB."""
    stop = data.find(b"\n" + end, 0, 1 << 16)
    if stop < 0:
        return None
    after = data.find(b"\n", stop + 1)
    after = len(data) if after < 0 else after + 1
    return [line.split() for line in data[:after].splitlines()], after


def _ply_claim(data: bytes) -> tuple[str, int] | None:
    """What a PLY header's elements need at the least: a binary property's bytes (a list's
    count), 2 bytes a text one ("0 ", the last one's line end optional)."""
    header = _header_lines(data, b"end_header")
    if header is None:
        return None
    lines, start = header
    binary = any(w[:2] in ([b"format", b"binary_little_endian"], [b"format", b"binary_big_endian"])
                 for w in lines)
    elements: list[list] = []
    for words in lines:
        if words[:1] == [b"element"] and len(words) == 3 and words[2].isdigit():
            elements.append([words[1].decode("ascii", "replace"), int(words[2]), 0])
        elif words[:1] == [b"property"] and len(words) > 2 and elements:
            kind = words[2] if words[1] == b"list" else words[1]
            elements[-1][2] += _PLY_SIZES.get(kind.decode("ascii", "replace"), 1) if binary else 2
    # A text file's last value may lack its line end.
    need = start + sum(count * size for _, count, size in elements) - (not binary)
    plural = {"vertex": "vertices", "face": "faces", "edge": "edges"}
    return ", ".join(f"{count:,} {plural.get(name, repr(name) + ' elements')}" for name, count, _ in elements), need


def _stl_claim(data: bytes) -> tuple[str, int] | None:
    """A binary STL's triangles, 50 bytes each after an 84-byte header (a text STL has no count)."""
    if data.lstrip()[:5].lower() == b"solid" or len(data) < 84:
        return None
    (count,) = struct.unpack_from("<I", data, 80)
    return f"{count:,} triangles", 84 + 50 * count


def _off_claim(data: bytes) -> tuple[str, int] | None:
    """An OFF's vertices and faces: each at least "0 0 0\n" and "3 0 1 2\n"."""
    words = re.sub(rb"#[^\n]*", b"", data[:4096]).split()
    if len(words) < 3 or not words[0].endswith(b"OFF") or not (words[1].isdigit() and words[2].isdigit()):
        return None
    vertices, faces = int(words[1]), int(words[2])
    return f"{vertices:,} vertices and {faces:,} faces", 6 * vertices + 8 * faces


def _pcd_claim(data: bytes) -> tuple[str, int] | None:
    """A PCD's points: SIZE × COUNT bytes of each field (binary), 2 bytes a value (text), or
    the compressed block's sizes, LZF's expansion at most :data:`_LZF_MAX_RATIO`."""
    header = _header_lines(data, b"DATA")
    if header is None:
        return None
    lines, start = header
    fields = {w[0].upper(): w[1:] for w in lines if w and not w[0].startswith(b"#")}
    try:
        points = int(fields[b"POINTS"][0])
        counts = [int(c) for c in fields.get(b"COUNT", [b"1"] * len(fields[b"SIZE"]))]
        row = sum(int(s) * c for s, c in zip(fields[b"SIZE"], counts))
        encoding = fields[b"DATA"][0].lower()
    except (KeyError, IndexError, ValueError):
        return None  # open3d says what is wrong with the header
    what = f"{points:,} points"
    if encoding == b"ascii":
        # open3d leaves the points a short text holds no line for as they were allocated.
        missing = sum(counts) * points - len(data[start:].split())
        return what, len(data) + 2 * missing if missing > 0 else start
    if encoding == b"binary":
        return what, start + row * points
    if len(data) < start + 8:
        return what, start + 8
    compressed, decoded = struct.unpack_from("<II", data, start)
    return what, start + 8 + max(compressed, -(-max(decoded, row * points) // _LZF_MAX_RATIO))


_NUMBER = re.compile(rb"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")


#: A text cloud's separators, read as spaces; a lone CR (old Mac OS line ends) ends a line.
_TEXT_SEPARATORS = bytes.maketrans(b",;\t\r", b"   \n")
_BLANK_LINE = re.compile(rb"^ *$", re.MULTILINE)


def _read_text_points(data: bytes, path: Path, *, skip_count_line: bool) -> np.ndarray:
    """x, y, z of a whitespace- or comma-separated text file's bytes, skipping header lines.

    The numbers are parsed in one pass into one array: a list of every field as a Python
    object took ten times the file's size.
    """
    text = data.translate(_TEXT_SEPARATORS)
    start = _first_xyz_line(text, path, skip_count_line=skip_count_line)
    end = text.find(b"\n", start)
    n_cols = len(text[start : end if end >= 0 else len(text)].split())
    rows = text.count(b"\n", start) + 1 - sum(1 for _ in _BLANK_LINE.finditer(text, start))
    body = text[start:]
    del text
    try:
        values = np.fromstring(body, sep=" ")
    except ValueError:
        raise InputError("contains a line that is not numbers", path) from None
    if values.size != n_cols * rows:
        raise InputError("lines have different numbers of columns", path)
    return values.reshape(rows, n_cols)[:, :3]


def _first_xyz_line(text: bytes, path: Path, *, skip_count_line: bool) -> int:
    """Where the first line that starts with three numbers begins: the lines before it are a
    header (after a PTS file's count of points)."""
    pos = index = 0
    while pos < len(text):
        end = text.find(b"\n", pos)
        end = len(text) if end < 0 else end
        line = text[pos:end]
        if index == 0 and skip_count_line:
            if not _NUMBER.match(line.strip()):
                raise InputError("a PTS file must start with the number of points", path)
        elif _starts_with_xyz(line):
            return pos
        elif line.strip() and index > 50:
            raise InputError("no lines of x y z numbers found", path)
        pos, index = end + 1, index + 1
    raise InputError("contains no points", path)


def _starts_with_xyz(line: bytes) -> bool:
    fields = line.replace(b",", b" ").replace(b";", b" ").split()
    return len(fields) >= 3 and all(_NUMBER.match(f) for f in fields[:3])


def _read_open3d_cloud(path: Path) -> tuple[np.ndarray, None, np.ndarray | None]:
    import open3d as o3d

    # open3d reads a PCD only by the file's name: the file was checked (a regular file, its
    # counts within its length) just before.
    try:
        cloud = o3d.io.read_point_cloud(str(path), format="pcd")
    except Exception as exc:  # open3d raises RuntimeError with a C++ message
        raise InputError(f"not a readable point cloud ({exc})", path) from None
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    return np.asarray(cloud.points), None, normals


def _read_trimesh(data: bytes, suffix: str, path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    import trimesh

    # Only the geometry is compared: trimesh would split a textured PLY's vertices where their
    # texture coordinates differ (4 of the 5 s it took to read a 24-megapixel run's mesh.ply),
    # and decode texture images with any of Pillow's decoders.
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=suffix[1:], resolver=mesh_files(path), process=False,
                              fix_texture=False, skip_materials=True)
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


#: The first bytes of the images :func:`mesh_files` serves as textures (PNG, JPEG): Pillow,
#: which trimesh hands them to, would run a program for some other formats (EPS: Ghostscript).
TEXTURE_MAGIC = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff")


def mesh_files(path: Path, *, textures: bool = False):
    """trimesh's resolver of the files the mesh ``path`` names: regular files in its folder only.

    Parameters
    ----------
    path : Path
        The mesh file.
    textures : bool
        Serve only its materials (``.mtl``) and texture images, the images only when they are
        PNG or JPEG; else only the other files it names (a glTF's buffers).

    Returns
    -------
    trimesh.resolvers.FilePathResolver
        Whose ``get`` raises :class:`InputError` for a file it does not serve.
    """
    import trimesh

    class Resolver(trimesh.resolvers.FilePathResolver):
        def get(self, name: str) -> bytes:
            named = Path(self.absolute(name.strip()))  # trimesh refuses a name outside the folder
            data = read_input_file(named, "file the mesh names")
            material = named.suffix.lower() == ".mtl"
            image = data.startswith(TEXTURE_MAGIC)
            if (material or image) and not textures:
                raise InputError("a mesh's materials and textures are not read here", named)
            if textures and not (material or image):
                raise InputError("a mesh's texture must be a PNG or JPEG image", named)
            return data

    return Resolver(str(path))


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
    # Each face's normal summed into its three vertices: bincount is twice np.add.at's speed.
    normals = np.column_stack([sum(np.bincount(f[:, k], weights=face_n[:, c], minlength=len(p)) for k in range(3))
                               for c in range(3)])
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
