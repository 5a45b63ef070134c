"""Compare a reconstruction with a laser scan: load, align, measure distances.

The reconstruction (a height-map mesh in mm, frame x right, y up, z towards the camera) is
the reference frame: :func:`align` finds the transform that carries the scan onto it, and
:func:`distances` measures every scan point against the reconstruction's surface, positive
when the scan lies on the camera side of it.

Typical use::

    rec = load_geometry("height_mesh.ply")
    scan = load_geometry("scan.ply", units="cm")
    alignment = align(rec, scan)
    result = distances(rec, scan, alignment)
    result.stats["rms"], within_tolerance(result, 0.1)
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ptmcore.errors import InputError

#: Millimetres per unit accepted by :func:`load_geometry`.
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}

MESH_SUFFIXES = {".ply", ".obj", ".stl", ".off", ".glb", ".gltf"}
CLOUD_SUFFIXES = {".ply", ".pcd", ".xyz", ".txt", ".csv", ".pts"}

# Bounding-box diagonals further apart than this are almost surely a unit mistake, which no
# registration can recover from without a scale.
_SIZE_RATIO_LIMIT = 20.0
# Below this overlap fraction RANSAC's answer is doubted and the PCA candidates are tried.
_FALLBACK_FITNESS = 0.6
# ... or when the point-to-plane RMS after ICP exceeds this many voxels.
_FALLBACK_RMS = 0.05
# An aligned pair overlapping less than this is reported as not overlapping at all.
_MIN_FITNESS = 0.01


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


# --------------------------------------------------------------------------------------------
# Loading


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
    if not path.exists():
        raise InputError("mesh or point cloud not found", path)
    if path.is_dir():
        raise InputError("is a folder, not a mesh or point cloud", path)
    suffix = path.suffix.lower()
    if suffix in {".xyz", ".txt", ".csv"}:
        points, faces, normals = _read_text_points(path, skip_count_line=False), None, None
    elif suffix == ".pts":
        points, faces, normals = _read_text_points(path, skip_count_line=True), None, None
    elif suffix == ".pcd":
        points, faces, normals = _read_open3d_cloud(path)
    elif suffix in MESH_SUFFIXES:
        points, faces, normals = _read_trimesh(path)
    else:
        known = ", ".join(sorted(MESH_SUFFIXES | CLOUD_SUFFIXES))
        raise InputError(f"not a known mesh or point-cloud format (expected one of {known})",
                         path)
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
    eigenvalues = np.linalg.eigvalsh(centred.T @ centred / len(points))  # ascending
    # The second-largest variance is what a line lacks; relative, so units do not matter.
    if eigenvalues[1] <= 1e-10 * max(eigenvalues[2], np.finfo(float).tiny):
        raise InputError("all points lie on a line (or on one point): degenerate geometry",
                         path)


_NUMBER = re.compile(rb"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")


def _read_text_points(path: Path, *, skip_count_line: bool) -> np.ndarray:
    """x, y, z of a whitespace- or comma-separated text file, skipping header lines."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read the point file ({exc.strerror or exc})", path) from None
    lines = data.splitlines()
    start = 0
    if skip_count_line:
        first = lines[0].strip() if lines else b""
        if not _NUMBER.match(first):
            raise InputError("a PTS file must start with the number of points", path)
        start = 1
    # Header lines are whatever precedes the first line that starts with three numbers.
    while start < len(lines) and not _starts_with_xyz(lines[start]):
        if lines[start].strip() and start > 50:
            raise InputError("no lines of x y z numbers found", path)
        start += 1
    body = b"\n".join(line for line in lines[start:] if line.strip())
    if not body:
        raise InputError("contains no points", path)
    # One parse of the whole body: commas become spaces, so both layouts read alike.
    text = body.replace(b",", b" ").replace(b";", b" ").replace(b"\t", b" ")
    rows = text.split(b"\n")
    n_cols = len(rows[0].split())
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise InputError("contains a line that is not numbers", path) from None
    if values.size != n_cols * len(rows):
        raise InputError("lines have different numbers of columns", path)
    return values.reshape(len(rows), n_cols)[:, :3]


def _starts_with_xyz(line: bytes) -> bool:
    fields = line.replace(b",", b" ").replace(b";", b" ").split()
    return len(fields) >= 3 and all(_NUMBER.match(f) for f in fields[:3])


def _read_open3d_cloud(path: Path) -> tuple[np.ndarray, None, np.ndarray | None]:
    import open3d as o3d

    try:
        cloud = o3d.io.read_point_cloud(str(path))
    except Exception as exc:  # open3d raises RuntimeError with a C++ message
        raise InputError(f"not a readable point cloud ({exc})", path) from None
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    return np.asarray(cloud.points), None, normals


def _read_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False)
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


# --------------------------------------------------------------------------------------------
# Alignment


def _o3d_cloud(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return cloud


def _mesh_vertex_normals(geometry: Geometry) -> np.ndarray:
    """Area-weighted vertex normals, oriented towards +z on the whole (the camera)."""
    p, f = geometry.points, geometry.faces
    face_n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    if face_n[:, 2].sum() < 0:
        face_n = -face_n
    normals = np.zeros_like(p)
    for k in range(3):
        np.add.at(normals, f[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.tile([0.0, 0.0, 1.0], (len(p), 1)),
                     where=length > 0)


def _estimate_normals(points: np.ndarray, radius: float) -> np.ndarray:
    """Normals from local PCA, pointing towards +z (the camera) where they can."""
    import open3d as o3d

    cloud = _o3d_cloud(points)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    cloud.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    return np.asarray(cloud.normals)


def _reference_cloud(geometry: Geometry, voxel: float):
    """The reconstruction as points with normals, the ICP target."""
    if geometry.is_mesh:
        normals = _mesh_vertex_normals(geometry)
    elif geometry.normals is not None:
        normals = geometry.normals
    else:
        normals = _estimate_normals(geometry.points, 2 * voxel)
    return _o3d_cloud(geometry.points, normals)


def _features(cloud, voxel: float):
    """Downsampled copy with normals and FPFH features, for global registration."""
    import open3d as o3d

    down = cloud.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return down, fpfh


def _icp(source, target, init: np.ndarray, distances_mm: list[float], iterations: int = 20):
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
    import itertools

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
    for _ in range(iterations):
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        dist, idx = tree.query(moved, distance_upper_bound=max_distance, workers=-1)
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
        step = _rotation_from_vector(omega) * (1.0 + sigma)
        update = np.eye(4)
        update[:3, :3] = step
        update[:3, 3] = centre + t - step @ centre
        transform = update @ transform
        if np.linalg.norm(x) < 1e-10:
            break
    return transform


def _rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross



class _Judge:
    """Refines a candidate pose on a sample of the scan and scores it.

    The score is (overlap, RMS): the fraction of sample points within 1.5 voxels of the
    reference, and the RMS of their point-to-plane distances. Coarse, point-to-point
    measures cannot tell a nearly symmetric object (a tablet turned by 180°) from the right
    answer; the point-to-plane RMS against a dense reference can.
    """

    def __init__(self, reference, sample, voxel: float) -> None:
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
                                    workers=-1)
        ok = np.isfinite(dist)
        if not np.any(ok):
            return transform, (0.0, float("inf"))
        along = np.einsum("ij,ij->i", moved[ok] - self.points[idx[ok]], self.normals[idx[ok]])
        return transform, (ok.mean(), float(np.sqrt(np.mean(along**2))))


def _better(fit: tuple[float, float], best: tuple[float, float]) -> bool:
    """Clearly more overlap wins; near-equal overlaps are decided by the RMS."""
    return fit[0] > best[0] + 0.02 or (fit[0] > best[0] - 0.02 and fit[1] < best[1])


def _overlap(points: np.ndarray, transform: np.ndarray, target,
             distance: float) -> tuple[float, float]:
    """Fraction of `points`, moved by `transform`, within `distance` of a target point, and
    the RMS of their point-to-plane distances (point-to-point would add the target's point
    spacing to every distance)."""
    ref, normals = np.asarray(target.points), np.asarray(target.normals)
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    dist, idx = cKDTree(ref).query(moved, distance_upper_bound=distance, workers=-1)
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
) -> Alignment:
    """Find the transform that carries the scan onto the reconstruction.

    Stages: (1) global registration: FPFH features and RANSAC on copies downsampled to
    voxels of 1/100 of the reconstruction's bounding-box diagonal; if its overlap after a
    coarse ICP is poor, the 24 axis/sign combinations of the principal axes are tried too,
    and the best overlap wins; (2) point-to-plane ICP (open3d) with correspondence distances
    shrinking from 3 voxels to a fraction of a voxel, at full resolution; (3) with
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

    Returns
    -------
    Alignment

    Raises
    ------
    InputError
        If the sizes differ by more than a factor of 20 (a unit mistake: see
        ``--scan-units``), for a malformed `initial`, or if the aligned pair does not overlap.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
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
    source = _o3d_cloud(scan.points)
    method: list[str] = []

    if no_align:
        final_dist = 1.5 * voxel
        fitness, rmse = _overlap(scan.points, start, target, final_dist)
        method.append("no alignment: " + ("initial transform" if initial is not None
                                          else "identity"))
        return _finish(start, fitness, rmse, final_dist, voxel, method, scan)

    source_down, source_fpfh = _features(source, voxel)
    target_down, target_fpfh = _features(target, voxel)
    rng = np.random.default_rng(0)
    sample_size = min(len(scan.points), 20000)
    sample = _o3d_cloud(scan.points[rng.choice(len(scan.points), sample_size, replace=False)])
    judge = _Judge(target.voxel_down_sample(voxel / 3), sample, voxel)
    coarse = [3 * voxel, voxel]
    if initial is not None:
        best = _icp(source_down, target_down, start, coarse).transformation
        method.append("initial transform given; no global registration")
    else:
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
        if best_fit[0] < _FALLBACK_FITNESS or best_fit[1] > _FALLBACK_RMS * voxel:
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
    fitness, rmse = _overlap(scan.points, transform, target, 1.5 * voxel)
    return _finish(transform, fitness, rmse, final_dist, voxel, method, scan)


def _finish(transform: np.ndarray, fitness: float, rmse: float, distance: float, voxel: float,
            method: list[str], scan: Geometry) -> Alignment:
    if fitness < _MIN_FITNESS:
        raise InputError(
            f"the scan and the reconstruction do not overlap after alignment (overlap "
            f"{fitness:.1%}); are they of the same object?", scan.source)
    scale = float(np.cbrt(np.linalg.det(transform[:3, :3])))
    return Alignment(transform=np.array(transform, dtype=np.float64), scale=scale,
                     fitness=fitness, inlier_rmse=rmse, correspondence_distance=distance,
                     voxel_size=voxel, method=method)


# --------------------------------------------------------------------------------------------
# Distances


def _boundary_edges(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Keys (a·n + b, a < b) of the edges used by one face only, and a boundary-vertex mask."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges.sort(axis=1)
    keys = edges[:, 0].astype(np.int64) * n_vertices + edges[:, 1]
    unique, counts = np.unique(keys, return_counts=True)
    boundary = unique[counts == 1]
    on_boundary = np.zeros(n_vertices, dtype=bool)
    on_boundary[boundary // n_vertices] = True
    on_boundary[boundary % n_vertices] = True
    return boundary, on_boundary


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
    boundary, boundary_vertex = _boundary_edges(mesh.faces, len(p))
    n = len(p)
    at_boundary = np.zeros(len(points), dtype=bool)
    for k in range(3):
        a, b = f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        key = np.minimum(a, b) * n + np.maximum(a, b)
        at_boundary |= on_edge[:, k] & np.isin(key, boundary)
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
    _, idx = tree.query(points, workers=-1)
    offset = points - points_ref[idx]
    n = normals_ref[idx]
    signed = np.einsum("ij,ij->i", offset, n)
    tangential = np.linalg.norm(offset - signed[:, None] * n, axis=1)
    spacing_sample = points_ref[:: max(1, len(points_ref) // 20000)]
    spacing = np.median(tree.query(spacing_sample, k=2, workers=-1)[0][:, 1])
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
                       else _estimate_normals(reconstruction.points, 2 * alignment.voxel_size))
        signed, at_boundary = _cloud_distances(reconstruction.points, ref_normals, moved)
    mask = ~at_boundary & (np.abs(signed) <= max_distance)
    result = DistanceResult(signed=signed, mask=mask, aligned_points=moved,
                            stats=_stats(signed, mask, max_distance))
    if reverse:
        scan_normals = _estimate_normals(moved, 2 * alignment.voxel_size)
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
