"""Binary PLY: one general writer, grid meshes with colours, UVs and normals, and a reader of
binary triangle meshes.

The writers are our own rather than trimesh's exporters: a trimesh mesh holds either UVs
or vertex colours (its visuals are one or the other), its PLY exporter writes UVs as ``s t``
with neither a ``comment TextureFile`` (what MeshLab uses to find the texture) nor our own
comments, and converting to a trimesh object first would copy every array. These writers
emit numpy records and text in bounded chunks instead. All files are written atomically.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.errors import open_input_file
from reconstruct.mesh.grid import GridMesh

__all__ = ["read_binary_ply", "write_binary_ply", "write_ply"]

# Rows per chunk when writing: bounds the temporary copies (a few tens of MB) while keeping
# the per-chunk Python overhead negligible.
_CHUNK = 100_000

# PLY's scalar types by numpy type (little-endian, as the files are written).
_PLY_TYPES = {
    "i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort",
    "i4": "int", "u4": "uint", "f4": "float", "f8": "double",
}
_FACE_DTYPE = np.dtype([("count", "u1"), ("index", "<i4", (3,))])
# And back, with PLY's other names for the same types.
_NUMPY_TYPES = {name: code for code, name in _PLY_TYPES.items()} | {
    "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
    "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8",
}
# The header of a PLY file this reader accepts fits in this many bytes.
_HEADER_BYTES = 1 << 16


def _check_comment(text: str) -> str:
    """A header comment must stay on one line or it corrupts the file."""
    text = str(text)
    if "\n" in text or "\r" in text:
        raise ValueError(f"comments must be single lines, not {text!r}")
    return text


def _relative_name(target: str | os.PathLike, relative_to_file: str | os.PathLike) -> str:
    """`target` as referenced from the folder of `relative_to_file`, with '/' separators."""
    target = os.fspath(target)
    if not os.path.isabs(target):
        return target.replace(os.sep, "/")
    folder = os.path.dirname(os.path.abspath(relative_to_file))
    try:
        rel = os.path.relpath(target, folder)
    except ValueError:  # another drive on Windows
        return target.replace(os.sep, "/")
    return rel.replace(os.sep, "/")


def _vertex_dtype(vertex: Mapping[str, np.ndarray]) -> tuple[np.dtype, int]:
    """The packed little-endian record of the vertex properties, and the vertex count."""
    lengths = {name: np.shape(values) for name, values in vertex.items()}
    shapes = set(lengths.values())
    if len(shapes) != 1 or len(next(iter(shapes))) != 1:
        raise ValueError(f"vertex properties must be 1-D arrays of one length, not {lengths}")
    fields = []
    for name, values in vertex.items():
        dtype = np.asarray(values).dtype.newbyteorder("<")
        if dtype.str[1:] not in _PLY_TYPES:
            raise ValueError(f"PLY has no type for property {name!r} of dtype {dtype}")
        fields.append((name, dtype))
    # A structured dtype without alignment is packed, like PLY's binary records.
    return np.dtype(fields), next(iter(shapes))[0]


def read_binary_ply(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a binary PLY file of vertices and triangles.

    Parameters
    ----------
    path : str or os.PathLike
        A ``binary_little_endian`` or ``binary_big_endian`` PLY file whose vertex element has
        scalar properties and whose face element (if any) has one list property of triangles.

    Returns
    -------
    vertex : dict of str to numpy.ndarray
        Property name → ``(V,)`` values, in file order (native byte order).
    faces : numpy.ndarray
        ``(F, 3)`` int64 vertex indices (``(0, 3)`` without a face element).

    Raises
    ------
    ValueError
        For a file this reader does not take (ASCII, other elements, polygons other than
        triangles), a malformed header, or a size that does not match the header's counts
        (checked before anything is allocated); indices out of range.
    InputError
        If the file is missing, not a regular file (a named pipe is refused, not waited on) or
        cannot be read (:func:`ptmcore.errors.open_input_file`).
    """
    with open_input_file(path, "PLY file") as handle:
        head = handle.read(_HEADER_BYTES)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            raise ValueError("not a PLY file, or its header is longer than 64 KiB")
        body = end + len(b"end_header")
        body += 2 if head[body:body + 2] == b"\r\n" else 1
        lines = [line.split() for line in head[:end].decode("latin-1").splitlines()[1:]]
        order, elements = None, []
        for words in lines:
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format" and len(words) == 3:
                order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(words[1])
                if order is None:
                    raise ValueError(f"{words[1]} PLY is not read here (binary only)")
            elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                elements[-1][2].append(words[1:])
            else:
                raise ValueError(f"malformed PLY header line {' '.join(words)!r}")
        if order is None or not elements or elements[0][0] != "vertex" or len(elements) > 2:
            raise ValueError("a PLY of a vertex element and, optionally, a face element is read here")

        def scalar(name: str) -> str:
            try:
                return order + _NUMPY_TYPES[name]
            except KeyError:
                raise ValueError(f"unknown PLY type {name!r}") from None

        _, n_vertices, properties = elements[0]
        if any(len(words) != 2 for words in properties):
            raise ValueError("vertex properties must be scalars")
        vertex_dtype = np.dtype([(name, scalar(kind)) for kind, name in properties])
        n_faces, face_dtype = 0, None
        if len(elements) == 2:
            name, n_faces, properties = elements[1]
            if name != "face" or len(properties) != 1 or len(properties[0]) != 4 or properties[0][0] != "list":
                raise ValueError("the face element must hold one list property")
            face_dtype = np.dtype([("count", scalar(properties[0][1])), ("index", scalar(properties[0][2]), (3,))])
        expected = body + n_vertices * vertex_dtype.itemsize + n_faces * (face_dtype.itemsize if face_dtype else 0)
        size = os.fstat(handle.fileno()).st_size
        if size != expected:
            raise ValueError(f"{size} bytes where the header calls for {expected} (triangles only)")
        handle.seek(body)
        records = np.fromfile(handle, dtype=vertex_dtype, count=n_vertices)
        faces = np.fromfile(handle, dtype=face_dtype, count=n_faces) if face_dtype else None
    vertex = {name: records[name].astype(records.dtype[name].newbyteorder("="))
              for name in records.dtype.names}
    if faces is None:
        return vertex, np.empty((0, 3), np.int64)
    if (faces["count"] != 3).any():
        raise ValueError("only triangles are read here")
    indices = faces["index"].astype(np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= n_vertices):
        raise ValueError("face indices out of range")
    return vertex, indices


def write_binary_ply(
    path: str | os.PathLike,
    vertex: Mapping[str, np.ndarray],
    faces: np.ndarray | None = None,
    *,
    comments: Iterable[str] = (),
) -> None:
    """Write vertex properties and triangles as a binary little-endian PLY file.

    The header is ``ply``, the format, one ``comment`` line per comment, the vertex element
    with one property per entry of `vertex`, and, when `faces` is given (even empty), a
    face element with ``property list uchar int vertex_indices``.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    vertex : mapping of str to numpy.ndarray
        Property name → ``(V,)`` values, in file order. Each property is written with its
        array's type (float32 as ``float``, uint8 as ``uchar``, …): cast before to choose.
    faces : numpy.ndarray, optional
        ``(F, 3)`` vertex indices; None for a point cloud.
    comments : iterable of str
        Header comments, one line each, without the ``comment`` keyword.

    Raises
    ------
    ValueError
        For properties of different lengths or of a type PLY lacks, malformed or
        out-of-range faces, more vertices than a PLY ``int`` index can address, or a
        multi-line comment.
    InputError
        If the file cannot be written (see :func:`ptmcore.atomic.atomic_write`).
    """
    vertex_dtype, n_vertices = _vertex_dtype(vertex)
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {_check_comment(c)}" for c in comments]
    header.append(f"element vertex {n_vertices}")
    header += [f"property {_PLY_TYPES[vertex_dtype[name].str[1:]]} {name}" for name in vertex]
    if faces is not None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), not {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
            raise ValueError("face indices out of range")
        if n_vertices > np.iinfo(np.int32).max:
            raise ValueError("too many vertices for PLY int32 indices")
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")

    with atomic_write(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("utf-8"))
        # One record buffer per element, reused for every chunk and written as it is (its
        # bytes, without the copy tobytes makes).
        record = np.empty(min(_CHUNK, n_vertices), dtype=vertex_dtype)
        for start in range(0, n_vertices, _CHUNK):
            part = record[: min(_CHUNK, n_vertices - start)]
            for name, values in vertex.items():
                part[name] = values[start : start + _CHUNK]
            handle.write(part.view(np.uint8))
        n_faces = 0 if faces is None else len(faces)
        record = np.empty(min(_CHUNK, n_faces), dtype=_FACE_DTYPE)
        record["count"] = 3
        for start in range(0, n_faces, _CHUNK):
            part = record[: min(_CHUNK, n_faces - start)]
            part["index"] = faces[start : start + _CHUNK]
            handle.write(part.view(np.uint8))


def write_ply(
    path: str | os.PathLike,
    mesh: GridMesh,
    *,
    texture_file: str | os.PathLike | None = None,
    comments: Iterable[str] = (),
) -> None:
    """Write a mesh as a binary little-endian PLY file.

    Vertex properties: ``x y z`` (float), ``nx ny nz`` (float, if the mesh has normals),
    ``red green blue`` (uchar), ``texture_u texture_v`` (float); faces as
    ``list uchar int vertex_indices``.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    mesh : GridMesh
        The mesh.
    texture_file : str or os.PathLike, optional
        Texture image for the UVs, announced as ``comment TextureFile <name>`` (read by
        MeshLab and trimesh). It is written relative to the PLY's folder.
    comments : iterable of str
        Extra header comments, one line each. ``comment unit <unit>`` is always written.

    Raises
    ------
    InputError
        If the file cannot be written (see :func:`ptmcore.atomic.atomic_write`).
    ValueError
        For a multi-line comment, or more vertices than a PLY ``int`` index can address.
    """
    header = [] if texture_file is None else [f"TextureFile {_relative_name(texture_file, path)}"]
    header += [f"unit {mesh.unit}", *comments]
    # Columns are views (no copies) unless a mesh array is not of its file type.
    vertex = dict(zip(("x", "y", "z"), np.asarray(mesh.vertices, dtype=np.float32).T))
    if mesh.normals is not None:
        vertex.update(zip(("nx", "ny", "nz"), np.asarray(mesh.normals, dtype=np.float32).T))
    vertex.update(zip(("red", "green", "blue"), np.asarray(mesh.colors, dtype=np.uint8).T))
    vertex.update(zip(("texture_u", "texture_v"), np.asarray(mesh.uv, dtype=np.float32).T))
    write_binary_ply(path, vertex, mesh.faces, comments=header)
