"""Align a scan to a reconstruction: the transform that carries the scan onto it.

The reconstruction (a height-map mesh in mm, frame x right, y up, z towards the camera) is
the reference frame. :func:`align` registers the scan globally (FPFH features and RANSAC,
with principal-axis fallbacks for nearly symmetric objects), refines it by point-to-plane
ICP, and can fit a uniform scale; :mod:`reconstruct.compare.signed_distance` then measures the
aligned pair.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ptmcore.errors import InputError
from ptmcore.resources import cpu_count
from reconstruct.compare.geometry import Geometry, estimate_normals, point_cloud, vertex_normals

# open3d is imported on use, so that importing the package does not need it.
if TYPE_CHECKING:
    import open3d as o3d

    _Cloud = o3d.geometry.PointCloud
    _Features = tuple[o3d.geometry.PointCloud, o3d.pipelines.registration.Feature]

__all__ = ["Alignment", "align"]

# Bounding-box diagonals further apart than this are almost surely a unit mistake, which no
# registration can recover from without a scale.
_SIZE_RATIO_LIMIT = 20.0
# Below this overlap fraction RANSAC's answer is doubted and the PCA candidates are tried.
_FALLBACK_FITNESS = 0.6
# ... or when the point-to-plane RMS after ICP exceeds this many voxels.
_FALLBACK_RMS = 0.05
# An aligned pair overlapping less than this is reported as not overlapping at all.
_MIN_FITNESS = 0.01
# The fine ICP's first, wider passes move at most this many of the scan's points (a random,
# seeded choice), the last pass all of them from there: at full resolution throughout it took
# 8.8 of a 13 s alignment of a million-point scan (benchmarks/compare_speed.py).
ICP_POINTS = 200_000


@dataclass
class Alignment:
    """The result of :func:`align`.

    Attributes
    ----------
    transform : numpy.ndarray
        ``(4, 4)`` float64 matrix mapping scan coordinates into the reconstruction's frame:
        ``[[s·R, t], [0, 1]]``.
    scale : float
        ``s``; 1 for a rigid alignment.
    fitness : float
        Fraction of scan points with a reconstruction point within the final correspondence
        distance (the overlap).
    inlier_rmse : float
        RMS distance of those correspondences, mm.
    correspondence_distance : float
        The final ICP correspondence distance, mm (the overlap counts points within
        1.5 voxels; the RMS is point-to-plane).
    voxel_size : float
        Voxel size used for the coarse stages, mm.
    method : list of str
        What was done, stage by stage.
    """

    transform: np.ndarray
    scale: float
    fitness: float
    inlier_rmse: float
    correspondence_distance: float
    voxel_size: float
    method: list[str] = field(default_factory=list)


def _reference_cloud(geometry: Geometry, voxel: float) -> _Cloud:
    """The reconstruction as points with normals, the ICP target."""
    if geometry.is_mesh:
        normals = vertex_normals(geometry)
    elif geometry.normals is not None:
        normals = geometry.normals
    else:
        normals = estimate_normals(geometry.points, 2 * voxel)
    return point_cloud(geometry.points, normals)


def _features(cloud: _Cloud, voxel: float) -> _Features:
    """Downsampled copy with normals and FPFH features, for global registration."""
    import open3d as o3d

    down = cloud.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return down, fpfh


def _icp(source: _Cloud, target: _Cloud, init: np.ndarray, distances_mm: list[float],
         iterations: int = 20) -> o3d.pipelines.registration.RegistrationResult:
    """Point-to-plane ICP with a shrinking correspondence distance; returns the last result."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    transform, result = init, None
    for dist in distances_mm:
        result = reg.registration_icp(
            source, target, dist, transform, reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                       max_iteration=iterations))
        transform = result.transformation
    return result


def _pca_candidates(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """The 24 proper rotations that map the source's principal axes onto the target's,
    each with the centroids matched: a start for objects RANSAC could not match."""

    def frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        centre = points.mean(axis=0)
        _, vectors = np.linalg.eigh(np.cov((points - centre).T))
        return centre, vectors

    c_s, e_s = frame(source)
    c_t, e_t = frame(target)
    candidates = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            mapping = np.zeros((3, 3))
            mapping[list(perm), [0, 1, 2]] = signs
            rotation = e_t @ mapping @ e_s.T
            if np.linalg.det(rotation) < 0:
                continue
            transform = np.eye(4)
            transform[:3, :3] = rotation
            transform[:3, 3] = c_t - rotation @ c_s
            candidates.append(transform)
    return candidates


def _flip_candidates(pose: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """`pose` followed by a half turn about each principal axis of the reconstruction.

    A nearly symmetric object (a rectangular tablet) lets RANSAC settle on the mirror-image
    pose; a scan with extra parts (a back side) spoils the PCA frames, but not these.
    """
    centre = target.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((target - centre).T))
    candidates = []
    for k in range(3):
        axis = vectors[:, k]
        half_turn = 2.0 * np.outer(axis, axis) - np.eye(3)
        flip = np.eye(4)
        flip[:3, :3] = half_turn
        flip[:3, 3] = centre - half_turn @ centre
        candidates.append(flip @ pose)
    return candidates


def _similarity_icp(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray,
                    init: np.ndarray, max_distance: float, iterations: int = 40) -> np.ndarray:
    """Point-to-plane ICP over a similarity (rotation, translation, uniform scale).

    Linearised about the current pose: the scan point p moves to p + ω×p + σ·p + t, and the
    residual along the target normal n is (p − q)·n + ω·(p×n) + σ·(p·n) + t·n, least squares
    in (ω, t, σ). Points are centred first so that σ and t are not correlated.
    """
    tree = cKDTree(target)
    transform = init.copy()
    workers = cpu_count()
    for _ in range(iterations):
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        dist, idx = tree.query(moved, distance_upper_bound=max_distance, workers=workers)
        ok = np.isfinite(dist)
        if np.count_nonzero(ok) < 7:
            break
        p, q, n = moved[ok], target[idx[ok]], target_normals[idx[ok]]
        centre = p.mean(axis=0)
        pc = p - centre
        a = np.hstack([np.cross(pc, n), n, np.einsum("ij,ij->i", pc, n)[:, None]])
        b = -np.einsum("ij,ij->i", p - q, n)
        x, *_ = np.linalg.lstsq(a, b, rcond=None)
        omega, t, sigma = x[:3], x[3:6], x[6]
        step = Rotation.from_rotvec(omega).as_matrix() * (1.0 + sigma)
        update = np.eye(4)
        update[:3, :3] = step
        update[:3, 3] = centre + t - step @ centre
        transform = update @ transform
        if np.linalg.norm(x) < 1e-10:
            break
    return transform


class _Judge:
    """Refines a candidate pose on a sample of the scan and scores it.

    The score is (overlap, RMS): the fraction of sample points within 1.5 voxels of the
    reference, and the RMS of their point-to-plane distances. Coarse, point-to-point
    measures cannot tell a nearly symmetric object (a tablet turned by 180°) from the right
    answer; the point-to-plane RMS against a dense reference can.
    """

    def __init__(self, reference: _Cloud, sample: _Cloud, voxel: float) -> None:
        self.reference = reference
        self.points = np.asarray(reference.points)
        self.normals = np.asarray(reference.normals)
        self.tree = cKDTree(self.points)
        self.sample = sample
        self.voxel = voxel

    def __call__(self, transform: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
        transform = _icp(self.sample, self.reference, transform,
                         [0.5 * self.voxel]).transformation
        moved = np.asarray(self.sample.points) @ transform[:3, :3].T + transform[:3, 3]
        dist, idx = self.tree.query(moved, distance_upper_bound=1.5 * self.voxel,
                                    workers=cpu_count())
        ok = np.isfinite(dist)
        if not np.any(ok):
            return transform, (0.0, float("inf"))
        along = np.einsum("ij,ij->i", moved[ok] - self.points[idx[ok]], self.normals[idx[ok]])
        return transform, (ok.mean(), float(np.sqrt(np.mean(along**2))))


def _better(fit: tuple[float, float], best: tuple[float, float]) -> bool:
    """Clearly more overlap wins; near-equal overlaps are decided by the RMS."""
    return fit[0] > best[0] + 0.02 or (fit[0] > best[0] - 0.02 and fit[1] < best[1])


def _overlap(points: np.ndarray, transform: np.ndarray, target: _Cloud,
             distance: float) -> tuple[float, float]:
    """Fraction of `points`, moved by `transform`, within `distance` of a target point, and
    the RMS of their point-to-plane distances (point-to-point would add the target's point
    spacing to every distance)."""
    ref, normals = np.asarray(target.points), np.asarray(target.normals)
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    dist, idx = cKDTree(ref).query(moved, distance_upper_bound=distance, workers=cpu_count())
    ok = np.isfinite(dist)
    if not np.any(ok):
        return 0.0, float("inf")
    along = np.einsum("ij,ij->i", moved[ok] - ref[idx[ok]], normals[idx[ok]])
    return float(ok.mean()), float(np.sqrt(np.mean(along**2)))


def align(
    reconstruction: Geometry,
    scan: Geometry,
    *,
    scale: bool = False,
    initial: np.ndarray | None = None,
    no_align: bool = False,
    progress: Callable[[int], None] | None = None,
) -> Alignment:
    """Find the transform that carries the scan onto the reconstruction.

    Stages: (1) global registration: FPFH features and RANSAC on copies downsampled to
    voxels of 1/100 of the reconstruction's bounding-box diagonal; if its overlap after a
    coarse ICP is poor, the 24 axis/sign combinations of the principal axes are tried too,
    and the best overlap wins; (2) point-to-plane ICP (open3d) with correspondence distances
    shrinking from 3 voxels to a fraction of a voxel, at full resolution (the wider passes
    with at most :data:`ICP_POINTS` of the scan's points); (3) with
    ``scale=True``, a point-to-plane similarity ICP that also fits a uniform scale, since
    photometric heights may carry a global scale error.

    Parameters
    ----------
    reconstruction : Geometry
        The reference; its frame is the result's frame.
    scan : Geometry
        The geometry to move.
    scale : bool
        Also estimate a uniform scale.
    initial : numpy.ndarray, optional
        ``(4, 4)`` starting transform (scan → reconstruction); skips the global stage.
    no_align : bool
        Do not move the scan at all (use `initial` or the identity) and only measure the
        overlap, for data that are already registered.
    progress : callable, optional
        ``progress(1)`` after each of the three steps: the features, the global registration,
        the fine ICP (seconds each on a 24-megapixel reconstruction).

    Returns
    -------
    Alignment

    Raises
    ------
    InputError
        If the sizes differ by more than a factor of 20 (a unit mistake: see
        ``--scan-units``), for a malformed `initial`, or if the aligned pair does not overlap.
    """
    rec_diag, scan_diag = reconstruction.diagonal, scan.diagonal
    ratio = max(rec_diag, scan_diag) / max(min(rec_diag, scan_diag), np.finfo(float).tiny)
    if ratio > _SIZE_RATIO_LIMIT:
        raise InputError(
            f"the scan ({scan_diag:.4g} mm across) and the reconstruction ({rec_diag:.4g} mm "
            f"across) differ in size by a factor of {ratio:.0f}; is the scan in other units? "
            "Use --scan-units (mm, cm, m, in)", scan.source)
    if initial is None:
        start = np.eye(4)
    else:
        start = np.asarray(initial, dtype=np.float64)
        if start.shape != (4, 4) or not np.all(np.isfinite(start)):
            raise InputError(f"the initial transform must be a finite 4×4 matrix, "
                             f"not shape {start.shape}")
    voxel = rec_diag / 100.0
    target = _reference_cloud(reconstruction, voxel)
    source = point_cloud(scan.points)
    method: list[str] = []

    if no_align:
        final_dist = 1.5 * voxel
        fitness, rmse = _overlap(scan.points, start, target, final_dist)
        method.append("no alignment: " + ("initial transform" if initial is not None
                                          else "identity"))
        return _finish(start, fitness, rmse, final_dist, voxel, method, scan)

    advance = progress or (lambda k: None)
    source_down, source_fpfh = _features(source, voxel)
    target_down, target_fpfh = _features(target, voxel)
    advance(1)
    if initial is not None:
        best = _icp(source_down, target_down, start, [3 * voxel, voxel]).transformation
        method.append("initial transform given; no global registration")
    else:
        rng = np.random.default_rng(0)
        sample_size = min(len(scan.points), 20000)
        sample = point_cloud(scan.points[rng.choice(len(scan.points), sample_size, replace=False)])
        judge = _Judge(target.voxel_down_sample(voxel / 3), sample, voxel)
        best = _global_registration((source_down, source_fpfh), (target_down, target_fpfh),
                                    judge, scale, method)
    advance(1)

    if len(scan.points) > ICP_POINTS:
        chosen = np.random.default_rng(0).choice(len(scan.points), ICP_POINTS, replace=False)
        best = _icp(point_cloud(scan.points[np.sort(chosen)]), target, best, [1.5 * voxel, 0.5 * voxel],
                    iterations=50).transformation
        fine = _icp(source, target, best, [0.2 * voxel], iterations=50)
    else:
        fine = _icp(source, target, best, [1.5 * voxel, 0.5 * voxel, 0.2 * voxel], iterations=50)
    transform = fine.transformation
    final_dist = 0.2 * voxel
    method.append("point-to-plane ICP at full resolution, correspondence distance "
                  f"{1.5 * voxel:.3g} → {final_dist:.3g} mm")
    if scale:
        normals = np.asarray(target.normals)
        points = np.asarray(target.points)
        for dist in (1.5 * voxel, 0.5 * voxel, 0.2 * voxel):
            transform = _similarity_icp(scan.points, points, normals, transform, dist)
        method.append("point-to-plane similarity ICP (uniform scale)")
    advance(1)
    fitness, rmse = _overlap(scan.points, transform, target, 1.5 * voxel)
    return _finish(transform, fitness, rmse, final_dist, voxel, method, scan)


def _global_registration(source: _Features, target: _Features, judge: _Judge, scale: bool,
                         method: list[str]) -> np.ndarray:
    """The scan's pose from FPFH features and RANSAC, or from the fallback candidates.

    `source` and `target` are (downsampled cloud, FPFH features) of :func:`_features`. When
    RANSAC's pose, refined by a coarse ICP, overlaps poorly, the half turns and the PCA
    axis/sign candidates are refined and scored too, and the best score wins. What was
    done is appended to `method`.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    (source_down, source_fpfh), (target_down, target_fpfh) = source, target
    voxel = judge.voxel
    coarse = [3 * voxel, voxel]
    o3d.utility.random.seed(0)  # the same files give the same answer
    ransac = reg.registration_ransac_based_on_feature_matching(
        source_down, target_down, source_fpfh, target_fpfh, False, 1.5 * voxel,
        reg.TransformationEstimationPointToPoint(with_scaling=scale), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    s0 = float(np.cbrt(np.linalg.det(ransac.transformation[:3, :3])))
    if scale:
        # The ICP stages are rigid and keep the scale RANSAC found.
        method.append(f"RANSAC scale estimate {s0:.4f}")
    best = _icp(source_down, target_down, ransac.transformation, coarse).transformation
    best, best_fit = judge(best)
    method.append(f"FPFH + RANSAC (voxel {voxel:.4g} mm): overlap {best_fit[0]:.3f}, "
                  f"RMS {best_fit[1]:.3g} mm")
    if not (best_fit[0] < _FALLBACK_FITNESS or best_fit[1] > _FALLBACK_RMS * voxel):
        return best
    candidates = (_flip_candidates(best, np.asarray(target_down.points))
                  + _pca_candidates(np.asarray(source_down.points),
                                    np.asarray(target_down.points)))
    for candidate in candidates:
        if scale:
            candidate = candidate @ np.diag([s0, s0, s0, 1.0])
        refined = _icp(source_down, target_down, candidate, coarse).transformation
        refined, fit = judge(refined)
        if _better(fit, best_fit):
            best, best_fit = refined, fit
    method.append(f"fallback ({len(candidates)} half-turn and PCA axis/sign candidates): "
                  f"overlap {best_fit[0]:.3f}, RMS {best_fit[1]:.3g} mm")
    return best


def _finish(transform: np.ndarray, fitness: float, rmse: float, distance: float, voxel: float,
            method: list[str], scan: Geometry) -> Alignment:
    """The :class:`Alignment`, unless the pair overlaps too little to be compared."""
    if fitness < _MIN_FITNESS:
        raise InputError(
            f"the scan and the reconstruction do not overlap after alignment (overlap "
            f"{fitness:.1%}); are they of the same object?", scan.source)
    scale = float(np.cbrt(np.linalg.det(transform[:3, :3])))
    return Alignment(transform=np.array(transform, dtype=np.float64), scale=scale,
                     fitness=fitness, inlier_rmse=rmse, correspondence_distance=distance,
                     voxel_size=voxel, method=method)

