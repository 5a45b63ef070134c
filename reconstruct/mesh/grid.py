"""Triangle meshes from height maps: one vertex per sampled pixel.

A height map becomes a regular grid mesh: one vertex per sampled pixel at
(x, y, z) = (col·s, −row·s, height), s the pixel size (or 1), so that the mesh seen from +z
looks like the photograph (``docs/CONVENTIONS.md``). Triangles are counter-clockwise seen
from +z, so their normals point towards the camera. Texture coordinates follow the OBJ/PLY
convention (v up): u = (col + 0.5)/W, v = 1 − (row + 0.5)/H, so texture images are stored
unflipped. The files are written by :mod:`reconstruct.mesh.ply` and :mod:`reconstruct.mesh.obj`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GridMesh", "grid_mesh"]

_DEFAULT_COLOR = 255  # untextured meshes are white, the neutral colour for shaded viewing


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


def _grid_faces(index: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Two triangles per cell of the sample grid, keeping those whose corners are all valid.

    Parameters
    ----------
    index : numpy.ndarray
        ``(h, w)`` vertex number of each sample (any value where not `valid`).
    valid : numpy.ndarray
        ``(h, w)`` bool, the samples that are vertices.

    Returns
    -------
    numpy.ndarray
        ``(F, 3)`` vertex indices of `index`'s dtype, cell by cell in row-major order; each
        cell split along its top-left to bottom-right diagonal, counter-clockwise from +z.
    """
    # Cell corners: a top-left, b top-right, c bottom-left, d bottom-right. With y up,
    # (a, c, d) and (a, d, b) are counter-clockwise seen from +z.
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    cells = (index.shape[0] - 1, index.shape[1] - 1)
    faces = np.empty(cells + (2, 3), dtype=index.dtype)
    for k, corner in enumerate((a, c, d)):
        faces[:, :, 0, k] = corner
    for k, corner in enumerate((a, d, b)):
        faces[:, :, 1, k] = corner
    if valid.all():
        return faces.reshape(-1, 3)
    va, vb, vc, vd = valid[:-1, :-1], valid[:-1, 1:], valid[1:, :-1], valid[1:, 1:]
    keep = np.empty(cells + (2,), dtype=bool)
    np.logical_and(va, vd, out=keep[..., 0])
    keep[..., 1] = keep[..., 0]
    keep[..., 0] &= vc
    keep[..., 1] &= vb
    return _take(faces.reshape(cells[0], cells[1] * 2, 3), keep.reshape(cells[0], -1))


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

    return GridMesh(
        vertices=vertices,
        faces=_grid_faces(index, valid),
        uv=uv,
        colors=colors,
        normals=vertex_normals,
        unit="pixel" if pixel_size is None else "mm",
    )


