"""OBJ export of grid meshes, with their material and texture files.

The numbers are formatted by :mod:`reconstruct.mesh.textfmt` (whole columns at a time with
NumPy) in parallel threads, a chunk of rows at a time, rather than by trimesh's exporter or
NumPy's text output, which format each number with Python (``benchmarks/obj_export.py``).
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
from ptmcore.errors import InputError
from ptmcore.png import encode_png
from reconstruct.mesh import textfmt
from reconstruct.mesh.grid import GridMesh, _as_rgb
from reconstruct.mesh.ply import _check_comment

__all__ = ["write_obj"]

# OBJ text is formatted in smaller chunks, whose temporaries stay in the CPU caches: about
# 15 % faster than 100 000 rows, and no faster below this.
_TEXT_CHUNK = 50_000
# Threads for OBJ export (NumPy and zlib release the GIL; beyond a few threads, writing the
# file is the limit), and chunks of text formatted ahead of the one being written, which
# bounds the memory they hold.
_WORKERS = min(4, os.cpu_count() or 1)
_AHEAD = 2 * _WORKERS

# OBJ numbers are written with six decimals (trailing zeros dropped): 1 nm in millimetres,
# 10⁻⁶ pixel, and finer than a float32 carries for coordinates above about 10.
_OBJ_DECIMALS = 6
_FACE_KEYWORD = textfmt.literal(b"\nf")  # each line starts with its newline, see write_obj


def _format_chunk(
    columns: Callable[[slice], list[textfmt.Column]], rows: slice
) -> memoryview:
    """The text of lines `rows` (run in a worker thread)."""
    return textfmt.join(columns(rows))


def _write_lines(
    handle: IO[bytes],
    pool: ThreadPoolExecutor,
    n_rows: int,
    columns: Callable[[slice], list[textfmt.Column]],
) -> None:
    """Write `n_rows` lines, formatting chunks of rows in `pool` into the columns that
    :func:`reconstruct.mesh.textfmt.join` concatenates, and writing them in order.

    At most :data:`_AHEAD` chunks are formatted or waiting, which bounds the memory.
    """
    pending: deque[Future[memoryview]] = deque()
    try:
        for start in range(0, n_rows, _TEXT_CHUNK):
            if len(pending) == _AHEAD:
                handle.write(pending.popleft().result())
            rows = slice(start, start + _TEXT_CHUNK)
            pending.append(pool.submit(_format_chunk, columns, rows))
        while pending:
            handle.write(pending.popleft().result())
    except BaseException:
        for future in pending:
            future.cancel()
        raise


def _number_columns(values: np.ndarray, keyword: bytes) -> list[textfmt.Column]:
    """``keyword x y …``: one column per field of the ``(n, k)`` `values`.

    Each line starts with its newline (see :func:`write_obj`); trailing zeros are trimmed,
    which shortens the many round coordinates and keeps 0 and 1 as such.
    """
    prefixes = [b"\n" + keyword + b" "] + [b" "] * (values.shape[1] - 1)
    return [
        textfmt.format_fixed(values[:, k], _OBJ_DECIMALS, trim=True, prefix=prefix)
        for k, prefix in enumerate(prefixes)
    ]


def _face_columns(faces: np.ndarray, per_corner: int) -> list[textfmt.Column]:
    """``f a/a b/b c/c`` (or ``a/a/a`` with `per_corner` 3): vertex, UV and normal share
    their index, which OBJ counts from 1.

    Each corner's text ``" a/a/a"`` depends on its vertex only, so it is formatted once per
    vertex and gathered. A chunk of grid faces spans a few rows of vertices, so the range
    between its smallest and largest index is the cheaper set to format; otherwise every
    corner is formatted.
    """
    first, last = int(faces.min()), int(faces.max())
    if last - first < faces.size:
        numbers = np.arange(first + 1, last + 2)
        index = np.subtract(faces, first, dtype=np.intp)
    else:
        numbers = faces.reshape(-1).astype(np.int64) + 1
        index = np.arange(faces.size).reshape(faces.shape)
    slash = textfmt.format_int(numbers, prefix=b"/")
    token = textfmt.concat([textfmt.format_int(numbers, prefix=b" ")] + [slash] * (per_corner - 1))
    return [_FACE_KEYWORD] + [textfmt.take(token, index[:, k]) for k in range(3)]


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

    Numbers are written with six decimals, correctly rounded, without trailing zeros
    (``0.05``, ``-12.345678``, ``1``), never in exponent notation. The text is formatted
    in parallel threads, a chunk of rows at a time (:mod:`reconstruct.mesh.textfmt`):
    26× faster than trimesh's OBJ export on a 4 M-vertex mesh (6× NumPy's ``%``), BENCHMARKS.md.

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
    header = ["# ptm-reconstruct grid mesh", f"# unit {_check_comment(mesh.unit)}"]
    header += [f"# {_check_comment(c)}" for c in comments]

    # NumPy and zlib release the GIL, so the texture is encoded and chunks of lines are
    # formatted in parallel threads.
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
                    lambda sl: _number_columns(
                        np.hstack([mesh.vertices[sl], mesh.colors[sl] / np.float32(255)]), b"v"
                    ),
                )
            else:
                _write_lines(
                    handle, pool, n_vertices, lambda sl: _number_columns(mesh.vertices[sl], b"v")
                )
            _write_lines(handle, pool, n_vertices, lambda sl: _number_columns(mesh.uv[sl], b"vt"))
            if mesh.normals is not None:
                _write_lines(
                    handle, pool, n_vertices, lambda sl: _number_columns(mesh.normals[sl], b"vn")
                )
            if texture is not None:
                handle.write(f"\nusemtl {stem}".encode("utf-8"))
            per_corner = 2 if mesh.normals is None else 3
            _write_lines(
                handle, pool, len(mesh.faces), lambda sl: _face_columns(mesh.faces[sl], per_corner)
            )
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

    A PNG is copied rather than decoded and encoded again: at 24 megapixels that is seconds.
    """
    if isinstance(texture, np.ndarray):
        rgb = _as_rgb(texture, texture.shape[:2])
        return encode_png(np.ascontiguousarray(rgb))
    try:
        data = Path(texture).read_bytes()
        if data.startswith(b"\x89PNG\r\n\x1a\n"):
            return data
        with Image.open(io.BytesIO(data)) as image:
            return encode_png(np.asarray(image.convert("RGB")))
    except (OSError, Image.DecompressionBombError) as exc:
        raise InputError(f"cannot read the texture image ({exc})", texture) from exc
