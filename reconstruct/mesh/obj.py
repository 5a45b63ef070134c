"""OBJ export of grid meshes, with their material and texture files.

The lines are formatted by compiled kernels (:mod:`reconstruct.mesh.objtext`) in parallel
threads, a chunk of rows at a time, rather than by trimesh's exporter or NumPy's text output,
which format each number with Python (``benchmarks/obj_export.py``).
All files are written atomically.
"""

from __future__ import annotations

import io
import os
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import IO

import numpy as np
from PIL import Image

from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError, read_input_file
from ptmcore.png import encode_png
from ptmcore.resources import cpu_count
from reconstruct.mesh import objtext
from reconstruct.mesh.grid import GridMesh, _as_rgb
from reconstruct.mesh.ply import _check_comment

__all__ = ["write_obj"]

# OBJ text is formatted in chunks of rows, in parallel threads, and written in order.
_TEXT_CHUNK = 100_000
# Threads for OBJ export (the text kernels and zlib release the GIL; beyond a few threads,
# writing the file is the limit), and chunks of text formatted ahead of the one being
# written, which bounds the memory they hold.
_WORKERS = min(4, cpu_count())
_AHEAD = 2 * _WORKERS


def _write_lines(
    handle: IO[bytes],
    pool: ThreadPoolExecutor,
    n_rows: int,
    lines: Callable[[slice], memoryview],
) -> None:
    """Write `n_rows` lines, formatting chunks of rows (``lines(rows)``) in `pool` and
    writing them in order.

    At most :data:`_AHEAD` chunks are formatted or waiting, which bounds the memory.
    """
    pending: deque[Future[memoryview]] = deque()
    try:
        for start in range(0, n_rows, _TEXT_CHUNK):
            if len(pending) == _AHEAD:
                handle.write(pending.popleft().result())
            pending.append(pool.submit(lines, slice(start, start + _TEXT_CHUNK)))
        while pending:
            handle.write(pending.popleft().result())
    except BaseException:
        for future in pending:
            future.cancel()
        raise


def write_obj(
    path: str | os.PathLike,
    mesh: GridMesh,
    texture: str | os.PathLike | np.ndarray | None = None,
    *,
    comments: Iterable[str] = (),
) -> None:
    """Write a mesh as a Wavefront OBJ with its MTL material and PNG texture.

    For ``folder/name.obj`` the files are ``folder/name.obj``, ``folder/name.mtl`` (material
    ``name``) and ``folder/name_texture.png``, so several meshes can share a folder. The
    material is white (``Ka``/``Kd`` 1, ``Ks`` 0, ``illum 1``) so that viewers show the
    texture's own colours. The texture is stored as given: with v up in the UVs, image row 0
    is the top of the mesh.

    Numbers are written with six decimals, correctly rounded from their float32 values (the
    type of a GridMesh's arrays; others are rounded to it first), without trailing zeros
    (``0.05``, ``-12.345678``, ``1``), never in exponent notation. The text is formatted
    by compiled kernels in parallel threads, a chunk of rows at a time
    (:mod:`reconstruct.mesh.objtext`; against trimesh's OBJ export: BENCHMARKS.md).

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.obj`` file.
    mesh : GridMesh
        The mesh.
    texture : str, os.PathLike or numpy.ndarray, optional
        Texture image: a file readable by Pillow (converted to PNG) or an ``(H, W, 3)``
        uint8 sRGB array. Without one no MTL or PNG is written and the vertex colours are
        written as ``v x y z r g b`` (an extension MeshLab and trimesh read).
    comments : iterable of str
        Extra comment lines for the OBJ header.

    Raises
    ------
    InputError
        If the texture file cannot be read or an output cannot be written.
    ValueError
        For a multi-line comment, a malformed texture array, or NaN or infinite vertex
        coordinates, texture coordinates or normals.
    """
    path = os.fspath(path)
    folder = os.path.dirname(path)
    stem = os.path.splitext(os.path.basename(path))[0]
    n_vertices = len(mesh.vertices)
    # GridMesh's float32 (objtext writes float32 exactly); a hand-made float64 mesh is rounded.
    vertices, uv = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.uv, np.float32)
    normals = None if mesh.normals is None else np.asarray(mesh.normals, np.float32)
    header = ["# ptm-reconstruct grid mesh", f"# unit {_check_comment(mesh.unit)}"]
    header += [f"# {_check_comment(c)}" for c in comments]

    # The text kernels and zlib release the GIL, so the texture is encoded and chunks of
    # lines are formatted in parallel threads.
    with ThreadPoolExecutor(max_workers=_WORKERS) as pool:
        texture_written = None
        if texture is not None:
            png = _texture_png(texture)
            mtl_name = f"{stem}.mtl"
            png_name = f"{stem}_texture.png"
            texture_written = pool.submit(_write_bytes, os.path.join(folder, png_name), png)
            with atomic_write(os.path.join(folder, mtl_name), "w") as handle:
                handle.write(
                    f"# ptm-reconstruct material for {stem}.obj\n"
                    f"newmtl {stem}\n"
                    "Ka 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
                    f"map_Kd {png_name}\n"
                )
            header += [f"mtllib {mtl_name}"]

        # Each line after the header starts with its newline, so that formatted chunks
        # are plain concatenations.
        with atomic_write(path, "wb") as handle:
            handle.write("\n".join(header).encode("utf-8"))
            if texture is None:
                _write_lines(
                    handle,
                    pool,
                    n_vertices,
                    lambda sl: objtext.number_lines(
                        np.hstack([vertices[sl], np.asarray(mesh.colors[sl], np.float32) / np.float32(255)]), b"v"
                    ),
                )
            else:
                _write_lines(handle, pool, n_vertices, lambda sl: objtext.number_lines(vertices[sl], b"v"))
            _write_lines(handle, pool, n_vertices, lambda sl: objtext.number_lines(uv[sl], b"vt"))
            if normals is not None:
                _write_lines(handle, pool, n_vertices, lambda sl: objtext.number_lines(normals[sl], b"vn"))
            if texture is not None:
                handle.write(f"\nusemtl {stem}".encode("utf-8"))
            per_corner = 2 if mesh.normals is None else 3
            _write_lines(handle, pool, len(mesh.faces), lambda sl: objtext.face_lines(mesh.faces[sl], per_corner))
            handle.write(b"\n")
            if texture_written is not None:
                # The OBJ appears last (when this block ends): once it exists, the files
                # it references do too.
                texture_written.result()


def _write_bytes(path: str, data: bytes) -> None:
    """Write a whole file (run in a worker thread)."""
    with atomic_write(path, "wb") as handle:
        handle.write(data)


def _texture_png(texture: str | os.PathLike | np.ndarray) -> bytes:
    """The texture as PNG bytes: a PNG file's own bytes, or an image or array encoded as PNG.

    A PNG is copied rather than decoded and encoded again: at 24 megapixels that is seconds
    (it keeps its own colour tags, or none). An array, or a JPEG or TIFF without an ICC
    profile, is tagged as sRGB; one with a profile is converted to RGB without it and left
    untagged, as before.
    """
    if isinstance(texture, np.ndarray):
        rgb = _as_rgb(texture, texture.shape[:2])
        return encode_png(np.ascontiguousarray(rgb), srgb=True)
    try:
        data = read_input_file(texture, "texture image")
        if data.startswith(b"\x89PNG\r\n\x1a\n"):
            return data
        # Pillow chooses among these plugins alone: with none named it tries every one, and
        # its EPS plugin runs Ghostscript.
        with Image.open(io.BytesIO(data), formats=["JPEG", "TIFF"]) as image:
            return encode_png(np.asarray(image.convert("RGB")), srgb=not image.info.get("icc_profile"))
    except (OSError, Image.DecompressionBombError) as exc:
        raise InputError(f"cannot read the texture image ({exc})", texture) from exc
