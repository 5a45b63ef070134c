"""Tests for reconstruct.mesh.ops (decimation, printable solids, STL and GLB exports), the
boundary edges of reconstruct.mesh.topology and the general writer of reconstruct.mesh.ply."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh

from reconstruct.mesh.grid import GridMesh, grid_mesh
from reconstruct.mesh.ops import decimate, solid, write_glb, write_stl
from reconstruct.mesh.ply import write_binary_ply
from reconstruct.mesh.topology import boundary_edges, directed_edges, edge_face_counts, edge_keys

o3d = pytest.importorskip("open3d")
o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


def _relief(h: int = 100, w: int = 100) -> np.ndarray:
    """A smooth relief, about 8 pixels high: a bump on a gentle wave."""
    row, col = np.mgrid[0:h, 0:w].astype(np.float64)
    bump = 6.0 * np.exp(-((row - 0.5 * h) ** 2 + (col - 0.45 * w) ** 2) / (2 * (0.2 * w) ** 2))
    return (bump + 2.0 * np.sin(col / (0.12 * w))).astype(np.float32)


def _gradient_texture(h: int, w: int) -> np.ndarray:
    """Red follows the column and green the row, so a colour tells where it was sampled."""
    row, col = np.mgrid[0:h, 0:w]
    tex = np.zeros((h, w, 3), dtype=np.uint8)
    tex[..., 0] = np.rint(col * 255 / (w - 1))
    tex[..., 1] = np.rint(row * 255 / (h - 1))
    return tex


def _masked_relief(h: int = 40, w: int = 48) -> np.ndarray:
    """The relief over a disc with an off-centre hole: irregular outline and an inner rim."""
    height = _relief(h, w) + 5.0
    row, col = np.mgrid[0:h, 0:w]
    outside = (row - h / 2) ** 2 + (col - w / 2) ** 2 > (0.45 * min(h, w)) ** 2
    hole = (row - 0.45 * h) ** 2 + (col - 0.6 * w) ** 2 < (0.12 * min(h, w)) ** 2
    height[outside | hole] = np.nan
    return height


def _vertical_height_error(original: GridMesh, reduced: GridMesh) -> np.ndarray:
    """|z| difference at each original vertex, by casting vertical rays onto `reduced`."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(reduced.vertices), o3d.core.Tensor(reduced.faces.astype(np.uint32))
    )
    top = float(original.vertices[:, 2].max()) + 10.0
    rays = np.zeros((len(original.vertices), 6), dtype=np.float32)
    rays[:, :2] = original.vertices[:, :2]
    rays[:, 2] = top
    rays[:, 5] = -1.0
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.abs(top - t - original.vertices[:, 2])


def _o3d_watertight(mesh: trimesh.Trimesh) -> bool:
    om = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces)
    )
    return bool(om.is_watertight())


def _prism_volume(relief: GridMesh, base_z: float) -> float:
    """Volume between a height-field mesh and the plane z = base_z (signed xy areas)."""
    v = relief.vertices.astype(np.float64)[relief.faces]
    e1, e2 = v[:, 1, :2] - v[:, 0, :2], v[:, 2, :2] - v[:, 0, :2]
    area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return float(np.sum(area * (v[:, :, 2].mean(axis=1) - base_z)))


def _glb_json(path) -> dict:
    data = path.read_bytes()
    length, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A  # "JSON"
    return json.loads(data[20 : 20 + length])


# ---------------------------------------------------------------------------- decimate


def test_decimate_to_one_percent_keeps_height_error_under_half_a_pixel():
    h, w = 100, 100
    mesh = grid_mesh(_relief(h, w), texture=_gradient_texture(h, w))
    target = len(mesh.faces) // 100
    reduced, report = decimate(mesh, target_faces=target)

    assert report["faces_before"] == len(mesh.faces) == 19602
    assert report["faces_after"] == len(reduced.faces) <= 1.1 * target
    assert report["unit"] == "pixel" and reduced.unit == "pixel"
    # Measured: max height error 0.12 pixel, RMS 0.03 (relief 7.6 pixels high, 196 of
    # 19 602 triangles).
    # Rays exactly on the rim can graze past the border edges: measure inside it.
    x, y = mesh.vertices[:, 0], -mesh.vertices[:, 1]
    inner = (x > 0) & (x < w - 1) & (y > 0) & (y < h - 1)
    dz = _vertical_height_error(mesh, reduced)[inner]
    assert np.isfinite(dz).all()
    assert dz.max() < 0.5
    assert report["max_error"] < 0.5 and 0 < report["rms_error"] <= report["max_error"]

    # Attributes are resampled at the closest point of the original surface, which lies
    # within the decimation error of the new vertex: UV (affine in x, y) and colour agree
    # with the vertex's own position to that accuracy.
    x, y = reduced.vertices[:, 0], reduced.vertices[:, 1]
    shift = report["max_error"]
    np.testing.assert_allclose(reduced.uv[:, 0], (x + 0.5) / w, atol=shift / w)
    np.testing.assert_allclose(reduced.uv[:, 1], 1 - (-y + 0.5) / h, atol=shift / h)
    np.testing.assert_allclose(reduced.colors[:, 0], x * 255 / (w - 1), atol=1 + shift * 2.6)
    np.testing.assert_allclose(reduced.colors[:, 1], -y * 255 / (h - 1), atol=1 + shift * 2.6)
    # The outline is held: the reduced mesh still spans the whole grid.
    np.testing.assert_allclose(reduced.vertices[:, :2].min(axis=0), (0, -(h - 1)), atol=1e-2)
    np.testing.assert_allclose(reduced.vertices[:, :2].max(axis=0), (w - 1, 0), atol=1e-2)


def test_decimate_max_error_mode_meets_the_bound_with_few_faces():
    mesh = grid_mesh(_relief(60, 60), pixel_size=0.05)  # unit mm
    bound = 0.02  # mm
    reduced, report = decimate(mesh, max_error=bound)
    assert report["mode"] == "max_error" and report["unit"] == "mm"
    assert report["max_error"] <= bound
    assert report["faces_after"] < 0.2 * report["faces_before"]
    # The report is the truth: measure independently (original vertices to new surface).
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(reduced.vertices), o3d.core.Tensor(reduced.faces.astype(np.uint32))
    )
    dist = scene.compute_distance(o3d.core.Tensor(mesh.vertices)).numpy()
    assert dist.max() <= report["max_error"] + 1e-6
    # Halving the bound needs more faces.
    _, tighter = decimate(mesh, max_error=bound / 4)
    assert tighter["faces_after"] > report["faces_after"]
    assert tighter["max_error"] <= bound / 4


def test_decimate_argument_checks():
    mesh = grid_mesh(_relief(10, 10))
    with pytest.raises(ValueError):
        decimate(mesh)
    with pytest.raises(ValueError):
        decimate(mesh, target_faces=10, max_error=0.1)
    with pytest.raises(ValueError):
        decimate(mesh, target_faces=0)
    _, report = decimate(mesh, target_faces=10**6)  # more than there are: unchanged
    assert report["faces_after"] == len(mesh.faces) and report["max_error"] == 0


# ------------------------------------------------------------------------------- solid


@pytest.mark.parametrize("pixel_size", [None, 0.1])
def test_solid_of_masked_relief_is_watertight(pixel_size):
    height = _masked_relief()
    relief = grid_mesh(height, pixel_size=pixel_size)
    closed = solid(height, 2.0, pixel_size=pixel_size)
    assert closed.is_watertight and closed.is_winding_consistent
    assert _o3d_watertight(closed)
    assert closed.volume > 0
    assert closed.metadata["unit"] == relief.unit
    base_z = float(np.nanmin(height)) - 2.0
    assert closed.metadata["base_z"] == pytest.approx(base_z)
    np.testing.assert_allclose(closed.vertices[:, 2].min(), base_z)
    np.testing.assert_allclose(closed.volume, _prism_volume(relief, base_z), rtol=1e-6)
    # One body with a hole through it: Euler characteristic 0 (genus 1).
    assert closed.euler_number == 0


def test_solid_drops_pinches_and_handles_a_decimated_mesh():
    height = _masked_relief()
    # Two squares sharing only the vertex of pixel (5, 5), top-right and bottom-left of
    # it (the grid's diagonals join top-left and bottom-right blocks through faces).
    pinch = np.full((12, 12), np.nan, dtype=np.float32)
    pinch[1:6, 5:11] = 1.0
    pinch[5:11, 0:6] = 2.0
    pinched = solid(pinch, 1.0)
    assert pinched.metadata["faces_dropped"] > 0
    assert pinched.is_watertight and pinched.is_winding_consistent and _o3d_watertight(pinched)
    assert pinched.volume > 0

    reduced, _ = decimate(grid_mesh(height), target_faces=300)
    closed = solid(reduced, 1.5)
    assert closed.is_watertight and closed.is_winding_consistent and _o3d_watertight(closed)
    assert closed.volume > 0
    with pytest.raises(ValueError):
        solid(height, 0.0)


def test_write_stl_round_trip(tmp_path):
    closed = solid(_masked_relief(), 1.0, pixel_size=0.1)
    path = tmp_path / "relief.stl"
    write_stl(path, closed)
    assert path.read_bytes()[:5] != b"solid"  # binary, not ASCII
    assert path.stat().st_size == 84 + 50 * len(closed.faces)
    back = trimesh.load(path, file_type="stl")
    assert len(back.faces) == len(closed.faces)
    assert back.is_watertight
    np.testing.assert_allclose(back.volume, closed.volume, rtol=1e-5)
    assert [p.name for p in tmp_path.iterdir()] == ["relief.stl"]  # no temporary left


# -------------------------------------------------------------------------------- GLB


def test_write_glb_with_texture(tmp_path):
    h, w = 20, 30
    tex = _gradient_texture(h, w)
    mesh = grid_mesh(_relief(h, w), texture=tex, pixel_size=0.2)
    path = tmp_path / "relief.glb"
    write_glb(path, mesh, tex)

    tree = _glb_json(path)
    assert tree["asset"]["extras"]["unit"] == "mm"
    scene = trimesh.load(path)
    assert scene.metadata["unit"] == "mm"
    (back,) = scene.geometry.values()
    assert len(back.faces) == len(mesh.faces)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    assert back.visual.kind == "texture"
    np.testing.assert_allclose(back.visual.uv, mesh.uv, atol=1e-6)
    image = np.asarray(back.visual.material.baseColorTexture.convert("RGB"))
    np.testing.assert_array_equal(image, tex)


def test_write_glb_with_vertex_colours(tmp_path):
    h, w = 12, 16
    mesh = grid_mesh(_masked_relief(h, w), texture=_gradient_texture(h, w))
    path = tmp_path / "relief.glb"
    write_glb(path, mesh)
    assert _glb_json(path)["asset"]["extras"]["unit"] == "pixel"
    scene = trimesh.load(path)
    assert scene.metadata["unit"] == "pixel"
    (back,) = scene.geometry.values()
    assert back.visual.kind == "vertex"
    np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], mesh.colors)


def test_boundary_edges_of_a_square_with_a_hole():
    # A 4×4 grid of vertices, 3×3 quads split in two, without the centre quad.
    mesh = grid_mesh(np.zeros((4, 4), np.float32))
    faces = np.asarray(mesh.faces)
    centre = {5, 6, 9, 10}
    faces = faces[[not set(f) <= centre for f in faces.tolist()]]
    edges = boundary_edges(faces, 16)
    assert edges.shape == (16, 2) and edges.dtype == np.int64
    # Each boundary vertex starts one edge and ends one: closed loops.
    np.testing.assert_array_equal(np.sort(edges[:, 0]), np.sort(edges[:, 1]))
    assert set(edges.ravel()) == set(range(16))
    # Directed as the faces wind them, counter-clockwise from +z: the outline turns left
    # (positive signed area) and the hole's rim right.
    x, y = mesh.vertices[:, 0].astype(np.float64), mesh.vertices[:, 1].astype(np.float64)

    def area(e: np.ndarray) -> float:  # the shoelace formula
        return 0.5 * float(np.sum(x[e[:, 0]] * y[e[:, 1]] - x[e[:, 1]] * y[e[:, 0]]))

    outer = ~np.isin(edges, list(centre)).any(axis=1)
    assert area(edges[outer]) > 0 > area(edges[~outer])
    counts = edge_face_counts(faces, 16)
    assert counts.shape == (3 * len(faces),) and set(counts) == {1, 2}
    assert len(directed_edges(faces)) == 3 * len(faces)
    np.testing.assert_array_equal(edge_keys([[2, 7], [7, 2]], 16), [2 * 16 + 7] * 2)


def test_write_binary_ply_layout(tmp_path):
    x = np.array([0.0, 1.0, 2.0], np.float32)
    quality = np.array([1.5, -2.0, np.nan])
    vertex = {"x": x, "y": x, "z": x, "red": np.array([1, 2, 3], np.uint8), "quality": quality}
    write_binary_ply(tmp_path / "m.ply", vertex, [[0, 1, 2]], comments=["unit mm"])
    data = (tmp_path / "m.ply").read_bytes()
    header, body = data.split(b"end_header\n")
    assert header.decode().splitlines() == [
        "ply", "format binary_little_endian 1.0", "comment unit mm", "element vertex 3",
        "property float x", "property float y", "property float z", "property uchar red",
        "property double quality", "element face 1", "property list uchar int vertex_indices",
    ]
    record = np.dtype([("xyz", "<f4", 3), ("red", "u1"), ("quality", "<f8")])
    vertices = np.frombuffer(body[: 3 * record.itemsize], record)
    np.testing.assert_array_equal(vertices["quality"], quality)
    assert body[3 * record.itemsize :] == struct.pack("<Biii", 3, 0, 1, 2)
    write_binary_ply(tmp_path / "p.ply", {"x": x})
    assert b"element face" not in (tmp_path / "p.ply").read_bytes()
    for bad in ({"x": x, "y": x[:2]}, {"x": x.astype(bool)}):
        with pytest.raises(ValueError):
            write_binary_ply(tmp_path / "bad.ply", bad)
    with pytest.raises(ValueError, match="out of range"):
        write_binary_ply(tmp_path / "bad.ply", {"x": x}, [[0, 1, 3]])
    with pytest.raises(ValueError, match="single lines"):
        write_binary_ply(tmp_path / "bad.ply", {"x": x}, comments=["a\nb"])
    assert not (tmp_path / "bad.ply").exists()
