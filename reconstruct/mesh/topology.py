"""Edges of triangle meshes: the faces' directed edges, and which of them lie on the boundary.

A boundary edge is used by one face only: the outline of a height-map mesh and the rims of
its holes. :mod:`reconstruct.mesh.ops` hangs the walls of a printable solid from these edges,
and :mod:`reconstruct.compare.signed_distance` leaves scan points that fall beyond them out of the
overlap.
"""

from __future__ import annotations

import numpy as np

__all__ = ["boundary_edges", "directed_edges", "edge_face_counts", "edge_keys"]


def directed_edges(faces: np.ndarray) -> np.ndarray:
    """The edges of every face, in winding order.

    Parameters
    ----------
    faces : numpy.ndarray
        ``(F, 3)`` vertex indices.

    Returns
    -------
    numpy.ndarray
        ``(3F, 2)`` int64 edges (a, b): face k gives rows 3k … 3k + 2, its edges 0→1, 1→2
        and 2→0.
    """
    return np.asarray(faces, dtype=np.int64)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def edge_keys(edges: np.ndarray, n_vertices: int) -> np.ndarray:
    """One integer per undirected edge: ``min(a, b)·n_vertices + max(a, b)``.

    Parameters
    ----------
    edges : numpy.ndarray
        ``(E, 2)`` vertex indices.
    n_vertices : int
        Number of vertices of the mesh (greater than every index).

    Returns
    -------
    numpy.ndarray
        ``(E,)`` int64 keys, equal for a→b and b→a.
    """
    edges = np.asarray(edges, dtype=np.int64)
    return np.minimum(edges[:, 0], edges[:, 1]) * n_vertices + np.maximum(edges[:, 0], edges[:, 1])


def edge_face_counts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """How many faces share each edge of :func:`directed_edges`.

    Parameters
    ----------
    faces : numpy.ndarray
        ``(F, 3)`` vertex indices.
    n_vertices : int
        Number of vertices of the mesh.

    Returns
    -------
    numpy.ndarray
        ``(3F,)`` counts: 1 on the boundary, 2 inside a manifold surface, more where the
        surface is not manifold.
    """
    _, inverse, counts = np.unique(
        edge_keys(directed_edges(faces), n_vertices), return_inverse=True, return_counts=True
    )
    return counts[inverse.ravel()]


def boundary_edges(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """The edges used by one face only, directed as that face winds them.

    Parameters
    ----------
    faces : numpy.ndarray
        ``(F, 3)`` vertex indices.
    n_vertices : int
        Number of vertices of the mesh.

    Returns
    -------
    numpy.ndarray
        ``(B, 2)`` int64 edges (a, b), in the order of :func:`directed_edges`. For faces
        counter-clockwise seen from +z, the outline runs counter-clockwise and holes clockwise.
    """
    return directed_edges(faces)[edge_face_counts(faces, n_vertices) == 1]
