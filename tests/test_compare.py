"""Tests for reconstruct.compare: loading, aligning and measuring a scan against a mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from data_synthetic import write_capture
from ptmcore.errors import InputError
from reconstruct.compare import Geometry, align, distances, load_geometry, within_tolerance
from reconstruct.compare.signed_distance import _mesh_distances
from reconstruct.mesh.grid import grid_mesh


class Case:
    """A small synthetic capture: the true mesh, the scan and the true scan → mesh transform."""

    def __init__(self, folder: Path) -> None:
        info = write_capture(folder, shape=(120, 160), n_lights=8)
        height = np.load(info.ground_truth_dir / "height.npy")
        mesh = grid_mesh(height, pixel_size=info.pixel_size)
        self.folder = folder
        self.rec = Geometry(mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64))
        self.scan_path = info.scan_path
        self.scan = load_geometry(info.scan_path)
        to_scan = np.loadtxt(info.ground_truth_dir / "scan_transform.txt")
        self.truth = np.linalg.inv(to_scan)
        self.to_scan = to_scan
        # The scan's points in the ground-truth frame, for cropping and true distances.
        self.true_points = _apply(self.truth, self.scan.points)


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _errors(found: np.ndarray, truth: np.ndarray, scale: float = 1.0) -> tuple[float, float]:
    """Rotation angle (degrees) and translation (mm) between two transforms."""
    rotation = (found[:3, :3] / scale) @ truth[:3, :3].T
    angle = np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1)))
    return float(angle), float(np.linalg.norm(found[:3, 3] - truth[:3, 3]))


def _true_rms(case: Case, scan_points_true: np.ndarray) -> float:
    signed, boundary = _mesh_distances(case.rec, scan_points_true)
    return float(np.sqrt(np.mean(signed[~boundary] ** 2)))


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Case:
    return Case(tmp_path_factory.mktemp("capture"))


@pytest.fixture(scope="module")
def baseline(case: Case):
    alignment = align(case.rec, case.scan)
    return alignment, distances(case.rec, case.scan, alignment, reverse=True)


def test_recovers_the_scan_transform(case: Case, baseline) -> None:
    alignment, _ = baseline
    angle, shift = _errors(alignment.transform, case.truth)
    # Issue target: 0.1° and 0.02 mm (measured ≈ 0.009° and 0.006 mm).
    assert angle < 0.1
    assert shift < 0.02
    assert alignment.scale == pytest.approx(1.0, abs=1e-9)
    assert alignment.fitness > 0.99


def test_rms_matches_the_true_rms(case: Case, baseline) -> None:
    _, result = baseline
    true_rms = _true_rms(case, case.true_points)
    assert result.stats["rms"] == pytest.approx(true_rms, rel=0.05)
    assert result.stats["overlap_fraction"] > 0.99
    assert result.stats["count"] == np.count_nonzero(result.mask)
    assert result.stats["max_abs"] >= result.stats["p95_abs"] >= result.stats["median_abs"]
    assert abs(result.stats["mean"]) < 0.005
    # The scan's noise is 0.02 mm: nearly all within 0.06 mm, few within 0.005 mm.
    assert within_tolerance(result, 0.06) > 0.99
    assert within_tolerance(result, 0.005) < 0.3
    assert within_tolerance(result.signed, 1.0) == 1.0
    assert result.reverse is not None and result.reverse_stats["rms"] < 0.05


def test_sign_is_positive_towards_the_camera(case: Case, baseline) -> None:
    alignment, _ = baseline
    lifted = Geometry(_apply(case.to_scan, case.true_points + [0.0, 0.0, 0.3]))
    result = distances(case.rec, lifted, alignment, max_distance=1.0)
    # A vertical 0.3 mm is less along a sloping surface's normal, never more.
    assert 0.27 < result.stats["mean"] < 0.301
    assert np.all(result.signed[result.mask] > 0)


def test_partial_overlap(case: Case) -> None:
    half = case.true_points[:, 0] < np.median(case.true_points[:, 0])
    scan = Geometry(case.scan.points[half])
    alignment = align(case.rec, scan)
    angle, shift = _errors(alignment.transform, case.truth)
    assert angle < 0.1 and shift < 0.05
    result = distances(case.rec, scan, alignment)
    assert result.stats["rms"] == pytest.approx(_true_rms(case, case.true_points[half]),
                                                rel=0.05)


def test_scan_with_a_back_side(case: Case) -> None:
    rng = np.random.default_rng(1)
    n = len(case.scan.points)
    low, high = case.true_points.min(axis=0), case.true_points.max(axis=0)
    back = np.column_stack([rng.uniform(low[0], high[0], n), rng.uniform(low[1], high[1], n),
                            np.full(n, -8.0)])
    scan = Geometry(np.vstack([case.scan.points, _apply(case.to_scan, back)]))
    alignment = align(case.rec, scan)
    angle, shift = _errors(alignment.transform, case.truth)
    assert angle < 0.1 and shift < 0.05
    result = distances(case.rec, scan, alignment)
    assert result.stats["overlap_fraction"] == pytest.approx(0.5, abs=0.02)
    assert result.stats["rms"] == pytest.approx(_true_rms(case, case.true_points), rel=0.05)


def test_scale_error_is_recovered(case: Case) -> None:
    rec = Geometry(case.rec.points * 1.05, case.rec.faces)
    alignment = align(rec, case.scan, scale=True)
    assert alignment.scale == pytest.approx(1.05, rel=2e-3)
    angle, _ = _errors(alignment.transform, case.truth, alignment.scale)
    assert angle < 0.1
    result = distances(rec, case.scan, alignment)
    assert result.stats["rms"] < 0.05


def test_outliers_do_not_spoil_the_statistics(case: Case) -> None:
    rng = np.random.default_rng(2)
    low, high = case.scan.points.min(axis=0), case.scan.points.max(axis=0)
    n = len(case.scan.points) // 20
    scan = Geometry(np.vstack([case.scan.points, rng.uniform(low, high, (n, 3))]))
    alignment = align(case.rec, scan)
    angle, shift = _errors(alignment.transform, case.truth)
    assert angle < 0.1 and shift < 0.05
    result = distances(case.rec, scan, alignment)
    assert result.stats["overlap_fraction"] == pytest.approx(1 / 1.05, abs=0.02)
    assert result.stats["rms"] == pytest.approx(_true_rms(case, case.true_points), rel=0.1)


def test_scan_in_centimetres(case: Case, tmp_path: Path) -> None:
    path = tmp_path / "scan_cm.xyz"
    np.savetxt(path, case.scan.points / 10.0, header="x y z", fmt="%.7f")
    scan = load_geometry(path, units="cm")
    np.testing.assert_allclose(scan.points, case.scan.points, atol=1e-5)
    alignment = align(case.rec, scan, initial=case.truth)
    angle, shift = _errors(alignment.transform, case.truth)
    assert angle < 0.1 and shift < 0.02


def test_initial_transform_and_no_align(case: Case) -> None:
    alignment = align(case.rec, case.scan, initial=case.truth, no_align=True)
    np.testing.assert_array_equal(alignment.transform, case.truth)
    assert alignment.fitness > 0.99


# ---------------------------------------------------------------------------- loading formats


def test_text_formats(tmp_path: Path) -> None:
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5], [1, 1, 2]], dtype=float)
    csv = tmp_path / "p.csv"
    csv.write_text("# exported\nx,y,z,intensity\n"
                   + "".join(f"{x},{y},{z},7\n" for x, y, z in pts))
    np.testing.assert_allclose(load_geometry(csv).points, pts)
    pts_file = tmp_path / "p.pts"
    pts_file.write_text("4\n" + "".join(f"{x} {y} {z} 12 255 0 0\n" for x, y, z in pts))
    np.testing.assert_allclose(load_geometry(pts_file, units="m").points, pts * 1000)
    txt = tmp_path / "p.txt"
    txt.write_text("".join(f"{x}\t{y}  {z}\n" for x, y, z in pts))
    np.testing.assert_allclose(load_geometry(txt, units="in").points, pts * 25.4)


def test_mesh_and_cloud_formats(tmp_path: Path) -> None:
    import open3d as o3d

    box = trimesh.creation.box((2.0, 3.0, 4.0))
    for suffix in ("obj", "stl", "off", "glb", "ply"):
        path = tmp_path / f"box.{suffix}"
        box.export(path)
        geometry = load_geometry(path)
        assert geometry.is_mesh, suffix
        assert geometry.diagonal == pytest.approx(np.sqrt(29.0)), suffix
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(box.vertices))
    o3d.io.write_point_cloud(str(tmp_path / "box.pcd"), cloud)
    geometry = load_geometry(tmp_path / "box.pcd")
    assert not geometry.is_mesh and len(geometry.points) == 8


def test_textured_ply_keeps_its_vertices(tmp_path: Path) -> None:
    # Two triangles sharing an edge whose vertices have other texture coordinates in each face
    # (a seam, as MeshLab writes per-face texcoords): the geometry is 4 vertices, not 6.
    header = ("ply\nformat ascii 1.0\ncomment TextureFile t.png\nelement vertex 4\n"
              "property float x\nproperty float y\nproperty float z\n"
              "element face 2\nproperty list uchar int vertex_indices\n"
              "property list uchar float texcoord\nend_header\n")
    body = ("0 0 0\n1 0 0\n1 1 0\n0 1 1\n"
            "3 0 1 2 6 0 0 0.5 0 0.5 0.5\n"
            "3 0 2 3 6 0.6 0 0.9 0.5 0.6 1\n")
    path = tmp_path / "seam.ply"
    path.write_text(header + body)
    geometry = load_geometry(path)
    assert geometry.is_mesh and len(geometry.points) == 4
    np.testing.assert_array_equal(np.sort(geometry.faces, axis=1), [[0, 1, 2], [0, 2, 3]])


# ------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("name, content, message", [
    ("missing.ply", None, "not found"),
    ("garbage.ply", b"this is not a ply file\n", "not a readable"),
    ("notes.doc", b"x", "not a known"),
    ("empty.xyz", b"", "no points"),
    ("header_only.csv", b"x,y,z\n", "no points"),
    ("nan.xyz", b"0 0 0\n1 0 nan\n0 1 1\n", "NaN"),
    ("line.xyz", b"0 0 0\n1 1 1\n2 2 2\n3 3 3\n", "line"),
    ("ragged.xyz", b"0 0 0\n1 1\n", "columns"),
    ("bad.pts", b"abc\n0 0 0\n", "number of points"),
])
def test_bad_files(tmp_path: Path, name: str, content: bytes | None, message: str) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=message) as info:
        load_geometry(path)
    assert info.value.path == str(path)


def test_bad_unit(case: Case) -> None:
    with pytest.raises(InputError, match="unknown unit"):
        load_geometry(case.scan_path, units="furlong")


def test_sizes_orders_of_magnitude_apart(case: Case) -> None:
    scan = Geometry(case.scan.points * 1000.0, source=case.scan_path)
    with pytest.raises(InputError, match="--scan-units") as info:
        align(case.rec, scan)
    assert info.value.path == str(case.scan_path)


def test_no_overlap(case: Case) -> None:
    far = case.truth.copy()
    far[:3, 3] += [0.0, 0.0, 500.0]
    with pytest.raises(InputError, match="do not overlap"):
        align(case.rec, case.scan, initial=far, no_align=True)


def test_bad_initial_and_tolerance(case: Case, baseline) -> None:
    with pytest.raises(InputError, match="4×4"):
        align(case.rec, case.scan, initial=np.eye(3))
    with pytest.raises(InputError, match="tolerance"):
        within_tolerance(baseline[1], -1.0)
    with pytest.raises(InputError, match="max_distance"):
        distances(case.rec, case.scan, baseline[0], max_distance=0.0)
