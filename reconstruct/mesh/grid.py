"""Triangle meshes from height maps, and their PLY and OBJ exports.

A height map becomes a regular grid mesh: one vertex per sampled pixel at
(x, y, z) = (col·s, −row·s, height), s the pixel size (or 1), so that the mesh seen from +z
looks like the photograph (``docs/CONVENTIONS.md``). Triangles are counter-clockwise seen
from +z, so their normals point towards the camera. Texture coordinates follow the OBJ/PLY
convention (v up): u = (col + 0.5)/W, v = 1 − (row + 0.5)/H, so texture images are stored
unflipped.

The writers are our own rather than trimesh's exporters: a trimesh mesh holds either UVs
or vertex colours (its visuals are one or the other), its PLY exporter writes UVs as ``s t``
with neither a ``comment TextureFile`` (what MeshLab uses to find the texture) nor our own
comments, and converting to a trimesh object first would copy every array. These writers
emit numpy records and text in bounded chunks instead. All files are written atomically.
"""

from __future__ import annotations

import io
import os
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np
from PIL import Image

from ptmcore.errors import InputError
from reconstruct.mesh import textfmt
from ptmcore.atomic import atomic_write
from ptmcore.images import encode_png

__all__ = ["GridMesh", "grid_mesh", "write_ply", "write_obj"]

# Rows per chunk when writing: bounds the temporary copies (a few tens of MB) while keeping
# the per-chunk Python overhead negligible.
_CHUNK = 100_000
# OBJ text is formatted in smaller chunks, whose temporaries stay in the CPU caches: about
# 15 % faster than 100 000 rows, and no faster below this.
_TEXT_CHUNK = 50_000
# Threads for OBJ export (NumPy and zlib release the GIL; beyond a few threads, writing the
# file is the limit), and chunks of text formatted ahead of the one being written, which
# bounds the memory they hold.
_WORKERS = min(4, os.cpu_count() or 1)
_AHEAD = 2 * _WORKERS

_DEFAULT_COLOR = 255  # untextured meshes are white, the neutral colour for shaded viewing

# OBJ numbers are written with six decimals (trailing zeros dropped): 1 nm in millimetres,
# 10⁻⁶ pixel, and finer than a float32 carries for coordinates above about 10.
_OBJ_DECIMALS = 6
_FACE_KEYWORD = textfmt.literal(b"\nf")  # each line starts with its newline, see write_obj


@dataclass
class GridMesh:
    """A triangle mesh made from a height map.

    Attributes
    ----------
    vertices : numpy.ndarray
        ``(V, 3)`` float32 positions (x right, y up, z towards the camera).
    faces : numpy.ndarray
        ``(F, 3)`` int32 (int64 for more than 2³¹ − 1 vertices) vertex indices,
        counter-clockwise seen from +z.
    uv : numpy.ndarray
        ``(V, 2)`` float32 texture coordinates, v up.
    colors : numpy.ndarray
        ``(V, 3)`` uint8 sRGB vertex colours (white without a texture).
    normals : numpy.ndarray or None
        ``(V, 3)`` float32 unit vertex normals, if known.
    unit : str
        Unit of the positions: ``"mm"`` or ``"pixel"``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None = None
    unit: str = "pixel"


def _samples(n: int, step: int) -> np.ndarray:
    """Indices 0, step, 2·step, … plus the last index, so the mesh spans the whole image."""
    idx = np.arange(0, n, step)
    if idx[-1] != n - 1:
        idx = np.append(idx, n - 1)
    return idx


def _subsample(image: np.ndarray, step: int) -> np.ndarray:
    """``image`` at the rows and columns of :func:`_samples`, by slicing (fancy indexing with
    numpy.ix_ is an order of magnitude slower); a view when the step hits the last ones."""
    out = image[::step]
    if (image.shape[0] - 1) % step:
        out = np.concatenate([out, image[-1:]], axis=0)
    part = out[:, ::step]
    if (image.shape[1] - 1) % step:
        part = np.concatenate([part, out[:, -1:]], axis=1)
    return part


def _take(grid: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Rows ``grid[keep]`` of an ``(h, w, k)`` array as ``(n, k)``; a view when all are kept.

    The selection goes through a void view of k-element records: numpy's boolean indexing
    then copies one record per kept entry, several times faster than selecting rows of a
    2-D array (which loops over the trailing axis).
    """
    k = grid.shape[-1]
    if keep.all():
        return grid.reshape(-1, k)
    grid = np.ascontiguousarray(grid)
    records = grid.view(np.dtype((np.void, grid.itemsize * k))).reshape(keep.shape)
    return records[keep].view(grid.dtype).reshape(-1, k)


def _as_rgb(texture: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A texture as ``(H, W, 3)`` uint8, checking its size."""
    texture = np.asarray(texture)
    if texture.ndim == 2:
        texture = texture[..., None]
    if texture.ndim != 3 or texture.shape[2] not in (1, 3, 4):
        raise ValueError(f"texture must be (H, W), (H, W, 3) or (H, W, 4), not {texture.shape}")
    if texture.shape[:2] != tuple(shape):
        raise ValueError(f"texture is {texture.shape[:2]}, the height map {tuple(shape)}")
    if texture.dtype != np.uint8:
        raise ValueError(f"texture must be uint8 sRGB, not {texture.dtype}")
    if texture.shape[2] == 1:
        return np.repeat(texture, 3, axis=2)
    return texture[..., :3]


def grid_mesh(
    height: np.ndarray,
    *,
    texture: np.ndarray | None = None,
    step: int = 1,
    pixel_size: float | None = None,
    normals: np.ndarray | None = None,
) -> GridMesh:
    """Build a grid mesh from a height map.

    Parameters
    ----------
    height : numpy.ndarray
        ``(H, W)`` heights, in mm when `pixel_size` is given, else in pixels. NaN marks
        pixels outside the object: their vertices and every triangle touching them are
        left out.
    texture : numpy.ndarray, optional
        ``(H, W, 3)`` uint8 sRGB image (grey ``(H, W)`` and RGBA are accepted) sampled for
        the vertex colours.
    step : int
        Sample every `step`-th row and column; the last row and column are always included
        so that the mesh covers the whole image.
    pixel_size : float, optional
        Pixel size in mm/pixel. Without it the unit is the pixel.
    normals : numpy.ndarray, optional
        ``(H, W, 3)`` normals in the project frame, sampled as vertex normals.

    Returns
    -------
    GridMesh
        Vertices numbered row by row over the kept samples; two triangles per grid cell,
        split along the top-left to bottom-right diagonal.

    Raises
    ------
    ValueError
        If the shapes do not match, `step` < 1 or `pixel_size` is not positive.
    """
    height = np.asarray(height)
    if height.ndim != 2 or height.size == 0:
        raise ValueError(f"height must be a non-empty 2-D array, not {height.shape}")
    if int(step) != step or step < 1:
        raise ValueError(f"step must be a positive integer, not {step}")
    if pixel_size is not None and not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number, not {pixel_size}")
    h_img, w_img = height.shape
    rows = _samples(h_img, int(step))
    cols = _samples(w_img, int(step))
    s = np.float32(1.0 if pixel_size is None else pixel_size)

    z = _subsample(height, int(step)).astype(np.float32, copy=False)
    valid = np.isfinite(z)
    n_valid = int(np.count_nonzero(valid))
    index_dtype = np.int32 if n_valid <= np.iinfo(np.int32).max else np.int64
    # Compact numbering of the kept vertices, row by row; −1 marks a dropped one.
    index = np.full(z.shape, -1, dtype=index_dtype)
    index[valid] = np.arange(n_valid, dtype=index_dtype)
    grid = z.shape

    # Per-vertex attributes are laid out on the sample grid by broadcasting, then the kept
    # vertices are taken in the same row-major order as the numbering.
    xyz = np.empty(grid + (3,), dtype=np.float32)
    xyz[..., 0] = (cols * s)[None, :]
    xyz[..., 1] = (-rows * s)[:, None]  # negate the integers first: no "-0" in text exports
    xyz[..., 2] = z
    vertices = _take(xyz, valid)
    del xyz

    uv = np.empty(grid + (2,), dtype=np.float32)
    uv[..., 0] = ((cols + 0.5) / w_img)[None, :]
    uv[..., 1] = (1.0 - (rows + 0.5) / h_img)[:, None]
    uv = _take(uv, valid)

    if texture is None:
        colors = np.full((n_valid, 3), _DEFAULT_COLOR, dtype=np.uint8)
    else:
        # Copied, so that the mesh never shares memory with the caller's image.
        colors = _take(_subsample(_as_rgb(texture, height.shape), int(step)), valid).copy()

    vertex_normals = None
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != (h_img, w_img, 3):
            raise ValueError(f"normals are {normals.shape}, expected {(h_img, w_img, 3)}")
        # A copy (astype), as it is normalised in place below.
        vertex_normals = _take(_subsample(normals, int(step)), valid).astype(np.float32)
        length = np.sqrt(np.einsum("ij,ij->i", vertex_normals, vertex_normals))
        good = np.isfinite(length) & (length > 0)
        vertex_normals /= np.where(good, length, 1.0)[:, None]
        # A vertex with a height but no usable normal gets the camera direction rather than
        # NaN, which most viewers render as black or reject.
        vertex_normals[~good] = (0.0, 0.0, 1.0)

    # Cell corners: a top-left, b top-right, c bottom-left, d bottom-right. With y up,
    # (a, c, d) and (a, d, b) are counter-clockwise seen from +z.
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    cells = (grid[0] - 1, grid[1] - 1)
    faces = np.empty(cells + (2, 3), dtype=index_dtype)
    for k, corner in enumerate((a, c, d)):
        faces[:, :, 0, k] = corner
    for k, corner in enumerate((a, d, b)):
        faces[:, :, 1, k] = corner
    if n_valid < valid.size:
        va, vb, vc, vd = valid[:-1, :-1], valid[:-1, 1:], valid[1:, :-1], valid[1:, 1:]
        keep = np.empty(cells + (2,), dtype=bool)
        np.logical_and(va, vd, out=keep[..., 0])
        keep[..., 1] = keep[..., 0]
        keep[..., 0] &= vc
        keep[..., 1] &= vb
        faces = _take(faces.reshape(cells[0], cells[1] * 2, 3), keep.reshape(cells[0], -1))
    else:
        faces = faces.reshape(-1, 3)

    return GridMesh(
        vertices=vertices,
        faces=faces,
        uv=uv,
        colors=colors,
        normals=vertex_normals,
        unit="pixel" if pixel_size is None else "mm",
    )


def _check_comment(text: str) -> str:
    """A header comment must stay on one line or it corrupts the file."""
    text = str(text)
    if "\n" in text or "\r" in text:
        raise ValueError(f"comments must be single lines, not {text!r}")
    return text


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
    in parallel threads, a chunk of rows at a time (:mod:`reconstruct.mesh.textfmt`).

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
