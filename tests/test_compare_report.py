"""Tests of the comparison outputs: colour map, coloured PLY, histogram and overlay."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from reconstruct.compare.figures import (
    NAN_COLOR,
    default_limit,
    diverging_colors,
    write_distance_ply,
    write_histogram,
    write_overlay,
)
from reconstruct.mesh.grid import grid_mesh


def _dome(n: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A small dome mesh in mm and a signed distance per vertex (a tilt plus NaNs)."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    height = 5.0 * np.exp(-((xx - n / 2) ** 2 + (yy - n / 2) ** 2) / (0.1 * n * n))
    mesh = grid_mesh(height, pixel_size=0.5)
    d = (mesh.vertices[:, 0] - mesh.vertices[:, 0].mean()) * 0.02
    d[::50] = np.nan
    return mesh.vertices, mesh.faces, d.astype(np.float64)


def test_colors_at_ends_and_zero():
    c = diverging_colors(np.array([-2.0, -1.0, 0.0, 1.0, 2.0, np.nan]), 1.0)
    assert c.dtype == np.uint8 and c.shape == (6, 3)
    assert tuple(c[2]) == (255, 255, 255)
    assert tuple(c[1]) == tuple(c[0]) == (5, 48, 97)  # clipped to −limit
    assert tuple(c[3]) == tuple(c[4]) == (103, 0, 31)
    assert tuple(c[5]) == NAN_COLOR
    # Blue dominates on the negative side and red on the positive side, all the way.
    t = np.linspace(-1, 1, 201)
    rgb = diverging_colors(t, 1.0).astype(int)
    assert np.all(rgb[t < -0.01, 2] > rgb[t < -0.01, 0])
    assert np.all(rgb[t > 0.01, 0] > rgb[t > 0.01, 2])
    with pytest.raises(ValueError):
        diverging_colors(t, 0.0)


def test_default_limit_is_a_nice_95th_percentile():
    rng = np.random.default_rng(0)
    d = rng.normal(0, 0.1, 10_000)
    lim = default_limit(np.append(d, [np.nan, np.inf, 50.0]))
    p95 = np.percentile(np.abs(d), 95)
    assert p95 <= lim < 2.5 * p95
    assert lim in (0.2, 0.25, 0.5)
    assert default_limit(np.array([0.7])) == 1.0
    assert default_limit(np.array([np.nan])) == 1.0
    assert default_limit(np.array([0.03, -0.03])) == pytest.approx(0.05)


def test_ply_mesh_reread_with_colors_and_comments(tmp_path):
    import open3d as o3d
    import trimesh

    verts, faces, d = _dome()
    path = tmp_path / "dist.ply"
    write_distance_ply(path, verts, faces, d, 0.2, comments=["scan scan.ply"])
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "comment unit mm" in header
    assert "-0.2 mm" in header and "+0.2 mm" in header
    assert "comment sign convention:" in header
    assert "comment scan scan.ply" in header

    tm = trimesh.load(path, process=False)
    assert tm.vertices.shape == verts.shape and tm.faces.shape == faces.shape
    np.testing.assert_allclose(tm.vertices, verts, atol=1e-5)
    colors = np.asarray(tm.visual.vertex_colors)[:, :3]
    np.testing.assert_array_equal(colors, diverging_colors(d, 0.2))
    assert (colors[np.isnan(d)] == NAN_COLOR).all()

    o3 = o3d.io.read_triangle_mesh(str(path))
    assert len(o3.triangles) == len(faces)
    np.testing.assert_allclose(
        np.asarray(o3.vertex_colors), diverging_colors(d, 0.2) / 255.0, atol=1e-6
    )


def test_ply_points_reread(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, (500, 3))
    d = pts[:, 2] * 0.3
    path = tmp_path / "scan.ply"
    write_distance_ply(path, pts, None, d, 0.25)
    pc = o3d.io.read_point_cloud(str(path))
    assert len(pc.points) == 500
    np.testing.assert_allclose(np.asarray(pc.colors), diverging_colors(d, 0.25) / 255.0)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic write leaves nothing behind


def test_ply_rejects_bad_input(tmp_path):
    verts, faces, d = _dome(5)
    with pytest.raises(ValueError):
        write_distance_ply(tmp_path / "x.ply", verts, faces, d[:-1], 1.0)
    with pytest.raises(ValueError):
        write_distance_ply(tmp_path / "x.ply", verts, faces, d, 1.0, comments=["a\nb"])
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("tolerance", [None, 0.1])
def test_histogram_png(tmp_path, tolerance):
    rng = np.random.default_rng(2)
    d = rng.normal(0.01, 0.08, 20_000)
    stats = {"overlap_fraction": 0.93, "rms": float(np.sqrt(np.mean(d**2)))}
    path = tmp_path / "hist.png"
    write_histogram(path, d, stats, tolerance=tolerance)
    with Image.open(path) as im:
        assert im.size == (900, 560)
        rgb = np.asarray(im.convert("RGB"))
    colors = {tuple(c) for c in rgb.reshape(-1, 3)}
    assert len(colors) > 20
    lim = default_limit(d)
    # The saturated ends and a pale central bar both appear among the pixels.
    for value in (-lim, lim):
        assert tuple(int(c) for c in diverging_colors(np.array([value]), lim)[0]) in colors
    if tolerance is not None:
        assert (226, 240, 226) in colors  # the tolerance band


def test_histogram_custom_size_and_empty(tmp_path):
    path = tmp_path / "h.png"
    write_histogram(path, np.array([]), {}, size=(640, 400))
    with Image.open(path) as im:
        assert im.size == (640, 400)


def test_overlay_png(tmp_path):
    verts, faces, d = _dome(30)
    rng = np.random.default_rng(3)
    scan = verts[rng.choice(len(verts), 400, replace=False)] + [0, 0, 0.05]
    path = tmp_path / "overlay.png"
    try:
        write_overlay(path, verts, faces, scan, d, 0.2, size=(600, 300))
    except RuntimeError as exc:
        if "not available" in str(exc):
            pytest.skip(str(exc))
        raise
    with Image.open(path) as im:
        assert im.size == (600, 300)
        rgb = np.asarray(im.convert("RGB")).astype(int)
    background = np.array([255, 255, 255])
    for half in (rgb[:, :300], rgb[:, 300:]):
        assert np.mean(np.any(half != background, axis=-1)) > 0.05
    # The heat map shows both blue and red distances.
    right = rgb[:, 300:].reshape(-1, 3)
    assert np.any(right[:, 2] > right[:, 0] + 60)
    assert np.any(right[:, 0] > right[:, 2] + 60)
    # The scan points (orange) appear on the left.
    left = rgb[:, :300].reshape(-1, 3)
    assert np.any((left[:, 0] > 200) & (left[:, 1] > 90) & (left[:, 1] < 160) & (left[:, 2] < 80))


def test_overlay_distances_on_scan(tmp_path):
    verts, faces, _ = _dome(20)
    scan = verts[::3] + [0, 0, 0.05]
    d = np.linspace(-0.3, 0.3, len(scan))
    try:
        write_overlay(tmp_path / "o.png", verts, faces, scan, d, 0.2, size=(400, 200), on="scan")
    except RuntimeError as exc:
        if "not available" in str(exc):
            pytest.skip(str(exc))
        raise
    assert (tmp_path / "o.png").stat().st_size > 1000
    with pytest.raises(ValueError):
        write_overlay(tmp_path / "p.png", verts, faces, scan, d[:-1], 0.2, on="scan")
