"""Binary PLY export of grid meshes: colours, texture coordinates, normals, comments.

The writers are our own rather than trimesh's exporters: a trimesh mesh holds either UVs
or vertex colours (its visuals are one or the other), its PLY exporter writes UVs as ``s t``
with neither a ``comment TextureFile`` (what MeshLab uses to find the texture) nor our own
comments, and converting to a trimesh object first would copy every array. These writers
emit numpy records and text in bounded chunks instead. All files are written atomically.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import numpy as np

from ptmcore.atomic import atomic_write
from reconstruct.mesh.grid import GridMesh

__all__ = ["write_ply"]

# Rows per chunk when writing: bounds the temporary copies (a few tens of MB) while keeping
# the per-chunk Python overhead negligible.
_CHUNK = 100_000


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


def _ply_vertex_fields(with_normals: bool) -> list[tuple[str, str, str]]:
    """(name, numpy type, PLY type) of each vertex property, in file order."""
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if with_normals else [])
    fields = [(n, "<f4", "float") for n in names]
    fields += [(n, "u1", "uchar") for n in ("red", "green", "blue")]
    fields += [(n, "<f4", "float") for n in ("texture_u", "texture_v")]
    return fields


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
        If the file cannot be written (see :func:`reconstruct.atomic.atomic_write`).
    ValueError
        For a multi-line comment, or more vertices than a PLY ``int`` index can address.
    """
    n_vertices = len(mesh.vertices)
    if n_vertices > np.iinfo(np.int32).max:
        raise ValueError("too many vertices for PLY int32 indices")
    header = ["ply", "format binary_little_endian 1.0"]
    if texture_file is not None:
        header.append(f"comment TextureFile {_check_comment(_relative_name(texture_file, path))}")
    header.append(f"comment unit {_check_comment(mesh.unit)}")
    header += [f"comment {_check_comment(c)}" for c in comments]
    fields = _ply_vertex_fields(mesh.normals is not None)
    # A structured dtype without alignment is packed, like PLY's binary records.
    vertex_dtype = np.dtype([(name, np_type) for name, np_type, _ in fields])
    header.append(f"element vertex {n_vertices}")
    header += [f"property {ply_type} {name}" for name, _, ply_type in fields]
    header.append(f"element face {len(mesh.faces)}")
    header.append("property list uchar int vertex_indices")
    header.append("end_header")
    face_dtype = np.dtype([("count", "u1"), ("index", "<i4", (3,))])

    with atomic_write(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("utf-8"))
        for start in range(0, n_vertices, _CHUNK):
            sl = slice(start, start + _CHUNK)
            record = np.empty(len(mesh.vertices[sl]), dtype=vertex_dtype)
            record["x"], record["y"], record["z"] = mesh.vertices[sl].T
            if mesh.normals is not None:
                record["nx"], record["ny"], record["nz"] = mesh.normals[sl].T
            record["red"], record["green"], record["blue"] = mesh.colors[sl].T
            record["texture_u"], record["texture_v"] = mesh.uv[sl].T
            handle.write(record.tobytes())
        for start in range(0, len(mesh.faces), _CHUNK):
            block = mesh.faces[start : start + _CHUNK]
            record = np.empty(len(block), dtype=face_dtype)
            record["count"] = 3
            record["index"] = block
            handle.write(record.tobytes())
