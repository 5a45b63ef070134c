"""Signed distances between an aligned scan and a reconstruction, and their statistics.

:func:`distances` measures every scan point against the reconstruction's surface (exactly
to the nearest triangle of a mesh, to the tangent plane of the nearest point of a cloud),
positive when the scan lies on the camera side of it (+z, where the normals point). Points
whose nearest surface point is on the reconstruction's boundary, or that lie further than a
limit, are outside the overlap and left out of the statistics.

Typical use::

    rec = load_geometry("height_mesh.ply")
    scan = load_geometry("scan.ply", units="cm")
    alignment = align(rec, scan)
    result = distances(rec, scan, alignment)
    result.stats["rms"], within_tolerance(result, 0.1)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ptmcore.errors import InputError
from ptmcore.resources import cpu_count
from reconstruct.compare.registration import Alignment
from reconstruct.compare.geometry import Geometry, estimate_normals
from reconstruct.mesh.topology import boundary_edges, edge_keys

__all__ = ["DistanceResult", "distances", "within_tolerance"]


@dataclass
class DistanceResult:
    """The result of :func:`distances`.

    Attributes
    ----------
    signed : numpy.ndarray
        ``(P,)`` float64 signed distance of every scan point to the reconstruction, mm;
        positive on the camera side (the side the surface normal points to).
    mask : numpy.ndarray
        ``(P,)`` bool: the point is in the overlap (its nearest surface point is not on the
        reconstruction's boundary and it lies within ``max_distance``).
    aligned_points : numpy.ndarray
        ``(P, 3)`` the scan points in the reconstruction's frame.
    stats : dict
        Over the overlap: ``mean``, ``std``, ``rms``, ``median_abs``, ``p95_abs``,
        ``max_abs`` (the one-sided Hausdorff distance), ``count``, ``overlap_fraction``,
        ``max_distance``.
    reverse : numpy.ndarray or None
        With ``reverse=True``: ``(V,)`` signed distance of each reconstruction point to the
        scan, same sign convention (positive when the scan lies on the camera side).
    reverse_mask : numpy.ndarray or None
        Overlap mask of ``reverse``.
    reverse_stats : dict or None
        Statistics of ``reverse`` over its overlap.
    """

    signed: np.ndarray
    mask: np.ndarray
    aligned_points: np.ndarray
    stats: dict[str, float]
    reverse: np.ndarray | None = None
    reverse_mask: np.ndarray | None = None
    reverse_stats: dict[str, float] | None = None


def _mesh_distances(mesh: Geometry, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed point-to-triangle distance, and whether the closest point is on the boundary."""
    import open3d as o3d

    vertices = mesh.points.astype(np.float32)
    faces = mesh.faces.astype(np.uint32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces))
    answer = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    closest = answer["points"].numpy().astype(np.float64)
    tri = answer["primitive_ids"].numpy().astype(np.int64)
    uv = answer["primitive_uvs"].numpy().astype(np.float64)

    p = mesh.points
    f = mesh.faces[tri]
    normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    # Whole-mesh orientation: the side the camera sees is positive.
    all_n = np.cross(p[mesh.faces[:, 1]] - p[mesh.faces[:, 0]],
                     p[mesh.faces[:, 2]] - p[mesh.faces[:, 0]])
    if all_n[:, 2].sum() < 0:
        normal = -normal
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    offset = points - closest
    signed = np.einsum("ij,ij->i", offset, normal)
    # The closest point's own distance is exact; the normal only gives the sign. Beside a
    # triangle the offset is not along the normal, and its length is still the distance.
    signed = np.copysign(np.linalg.norm(offset, axis=1), np.where(signed == 0, 1.0, signed))

    # On an edge one barycentric weight is ~0 (open3d gives float32). The weights are
    # (1 − u − v, u, v) for the corners (0, 1, 2); the edge opposite corner k has weight 0.
    weights = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    on_edge = weights < 1e-4
    boundary = boundary_edges(mesh.faces, len(p))
    boundary_keys = edge_keys(boundary, len(p))
    boundary_vertex = np.zeros(len(p), dtype=bool)
    boundary_vertex[boundary.ravel()] = True
    at_boundary = np.zeros(len(points), dtype=bool)
    for k in range(3):
        opposite = f[:, [(k + 1) % 3, (k + 2) % 3]]
        at_boundary |= on_edge[:, k] & np.isin(edge_keys(opposite, len(p)), boundary_keys)
    # At a corner (two weights ~0) the vertex may be on the boundary through another face.
    corner = on_edge.sum(axis=1) >= 2
    corner_vertex = f[np.arange(len(f)), np.argmax(weights, axis=1)]
    at_boundary |= corner & boundary_vertex[corner_vertex]
    return signed, at_boundary


def _cloud_distances(points_ref: np.ndarray, normals_ref: np.ndarray,
                     points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane distance to the nearest reference point, and whether it is beyond the
    edge of the reference (its tangential offset is larger than the point spacing)."""
    tree = cKDTree(points_ref)
    _, idx = tree.query(points, workers=cpu_count())
    offset = points - points_ref[idx]
    n = normals_ref[idx]
    signed = np.einsum("ij,ij->i", offset, n)
    tangential = np.linalg.norm(offset - signed[:, None] * n, axis=1)
    spacing_sample = points_ref[:: max(1, len(points_ref) // 20000)]
    spacing = np.median(tree.query(spacing_sample, k=2, workers=cpu_count())[0][:, 1])
    return signed, tangential > 2.0 * spacing


def _stats(values: np.ndarray, mask: np.ndarray, max_distance: float) -> dict[str, float]:
    inside = values[mask]
    count = int(inside.size)
    stats = {"count": count, "overlap_fraction": count / max(len(values), 1),
             "max_distance": float(max_distance)}
    if count == 0:
        stats.update(dict.fromkeys(["mean", "std", "rms", "median_abs", "p95_abs", "max_abs"],
                                   float("nan")))
        return stats
    absolute = np.abs(inside)
    stats.update(
        mean=float(inside.mean()), std=float(inside.std()),
        rms=float(np.sqrt(np.mean(inside**2))), median_abs=float(np.median(absolute)),
        p95_abs=float(np.percentile(absolute, 95)), max_abs=float(absolute.max()))
    return stats


def distances(
    reconstruction: Geometry,
    scan: Geometry,
    alignment: Alignment,
    *,
    reverse: bool = False,
    max_distance: float | None = None,
) -> DistanceResult:
    """Signed distances from the aligned scan to the reconstruction.

    For a mesh, the exact distance to the nearest triangle (open3d's ``RaycastingScene``);
    for a point cloud, the distance to the tangent plane of the nearest point. The sign
    comes from the surface normal, oriented so that the camera side (+z) is positive.

    Parameters
    ----------
    reconstruction : Geometry
        The reference surface.
    scan : Geometry
        The scan, in its own frame.
    alignment : Alignment
        From :func:`align`.
    reverse : bool
        Also measure each reconstruction point against the scan.
    max_distance : float, optional
        Points further than this (mm) are outside the overlap. Default: 5 × the alignment's
        inlier RMSE, but at least 0.1 voxel, so that a stray point does not count.

    Returns
    -------
    DistanceResult
    """
    if max_distance is None:
        max_distance = max(5.0 * alignment.inlier_rmse, 0.1 * alignment.voxel_size)
    elif not (np.isfinite(max_distance) and max_distance > 0):
        raise InputError(f"max_distance must be a positive number of mm, not {max_distance}")
    t = alignment.transform
    moved = scan.points @ t[:3, :3].T + t[:3, 3]
    if reconstruction.is_mesh:
        signed, at_boundary = _mesh_distances(reconstruction, moved)
        ref_normals = None
    else:
        ref_normals = (reconstruction.normals if reconstruction.normals is not None
                       else estimate_normals(reconstruction.points, 2 * alignment.voxel_size))
        signed, at_boundary = _cloud_distances(reconstruction.points, ref_normals, moved)
    mask = ~at_boundary & (np.abs(signed) <= max_distance)
    result = DistanceResult(signed=signed, mask=mask, aligned_points=moved,
                            stats=_stats(signed, mask, max_distance))
    if reverse:
        scan_normals = estimate_normals(moved, 2 * alignment.voxel_size)
        # Distance of a reconstruction point to the scan is −(its offset from the scan), so
        # that positive still means the scan lies on the camera side.
        back, beyond = _cloud_distances(moved, scan_normals, reconstruction.points)
        back = -back
        back_mask = ~beyond & (np.abs(back) <= max_distance)
        result.reverse, result.reverse_mask = back, back_mask
        result.reverse_stats = _stats(back, back_mask, max_distance)
    return result


def within_tolerance(result: DistanceResult | np.ndarray, tolerance_mm: float) -> float:
    """Fraction of the overlap whose distance is within ±`tolerance_mm`.

    Parameters
    ----------
    result : DistanceResult or numpy.ndarray
        Distances (only the overlap of a DistanceResult counts; NaN in an array is skipped).
    tolerance_mm : float
        The tolerance, mm.

    Returns
    -------
    float
        In [0, 1]; NaN when there is nothing to count.
    """
    if not (np.isfinite(tolerance_mm) and tolerance_mm >= 0):
        raise InputError(f"the tolerance must be a non-negative number of mm, "
                         f"not {tolerance_mm}")
    if isinstance(result, DistanceResult):
        values = result.signed[result.mask]
    else:
        values = np.asarray(result, dtype=np.float64).ravel()
        values = values[np.isfinite(values)]
    if values.size == 0:
        return float("nan")
    return float(np.count_nonzero(np.abs(values) <= tolerance_mm) / values.size)
