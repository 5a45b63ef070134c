"""Tests for reconstruct.mesh.grid and reconstruct.atomic: grid meshes, PLY/OBJ round trips."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh
from PIL import Image

from ptmcore.errors import InputError
from reconstruct.mesh import obj as obj_module
from ptmcore.atomic import atomic_write
from reconstruct.mesh.grid import GridMesh, grid_mesh
from reconstruct.mesh.obj import write_obj
from reconstruct.mesh.ply import write_ply

H, W = 6, 8
RED, BLUE = (255, 0, 0), (0, 0, 255)


def _height(h: int = H, w: int = W) -> np.ndarray:
    row, col = np.mgrid[0:h, 0:w]
    return (0.1 * col + 0.01 * row * col).astype(np.float32)


def _texture(h: int = H, w: int = W) -> np.ndarray:
    """Blue, with a red 2×2 top-left corner: shows at once whether an export is flipped."""
    tex = np.empty((h, w, 3), dtype=np.uint8)
    tex[:] = BLUE
    tex[:2, :2] = RED
    return tex


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _open3d():
    o3d = pytest.importorskip("open3d")
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


# ---------------------------------------------------------------- grid_mesh


@pytest.mark.parametrize(
    ("h", "w", "step", "n_rows", "n_cols"),
    [
        (6, 8, 1, 6, 8),
        (7, 10, 3, 3, 4),  # rows 0 3 6, cols 0 3 6 9: the last ones fall on the step
        (8, 11, 3, 4, 5),  # rows 0 3 6 7, cols 0 3 6 9 10: the last ones are added
        (5, 5, 10, 2, 2),  # step larger than the image: just the corners
    ],
)
def test_counts(h, w, step, n_rows, n_cols):
    mesh = grid_mesh(np.zeros((h, w), np.float32), step=step)
    assert mesh.vertices.shape == (n_rows * n_cols, 3)
    assert mesh.faces.shape == (2 * (n_rows - 1) * (n_cols - 1), 3)
    assert mesh.vertices.dtype == np.float32 and mesh.uv.dtype == np.float32
    assert mesh.colors.dtype == np.uint8 and mesh.faces.dtype == np.int32
    assert mesh.normals is None and mesh.unit == "pixel"
    # The last row and column are always there.
    assert mesh.vertices[:, 0].max() == w - 1 and mesh.vertices[:, 1].min() == -(h - 1)


def test_vertices_uv_colours_follow_the_conventions():
    height = _height()
    mesh = grid_mesh(height, texture=_texture(), pixel_size=0.5)
    assert mesh.unit == "mm"
    row, col = np.divmod(np.arange(H * W), W)
    np.testing.assert_allclose(mesh.vertices[:, 0], col * 0.5)
    np.testing.assert_allclose(mesh.vertices[:, 1], -row * 0.5)
    np.testing.assert_allclose(mesh.vertices[:, 2], height.ravel())
    np.testing.assert_allclose(mesh.uv[:, 0], (col + 0.5) / W, rtol=1e-6)
    np.testing.assert_allclose(mesh.uv[:, 1], 1 - (row + 0.5) / H, rtol=1e-6)
    np.testing.assert_array_equal(mesh.colors, _texture().reshape(-1, 3))
    assert (_face_normals(mesh.vertices, mesh.faces)[:, 2] > 0).all()


@pytest.mark.parametrize(
    ("hole", "dropped_faces"),
    [
        ((2, 3), 6),  # an interior vertex belongs to 6 triangles of this triangulation
        ((0, 0), 2),  # the top-left corner: both triangles of its cell
        ((0, W - 1), 1),  # the top-right corner: only one triangle of its cell touches it
    ],
)
def test_nan_holes_drop_vertices_and_touching_triangles(hole, dropped_faces):
    height = _height()
    height[hole] = np.nan
    mesh = grid_mesh(height, texture=_texture())
    assert len(mesh.vertices) == H * W - 1
    assert len(mesh.faces) == 2 * (H - 1) * (W - 1) - dropped_faces
    assert mesh.faces.min() >= 0 and mesh.faces.max() == len(mesh.vertices) - 1
    assert np.isfinite(mesh.vertices).all()
    keep = np.ones((H, W), bool)
    keep[hole] = False
    np.testing.assert_allclose(mesh.vertices[:, 2], height[keep])
    np.testing.assert_array_equal(mesh.colors, _texture()[keep])
    assert (_face_normals(mesh.vertices, mesh.faces)[:, 2] > 0).all()


def test_masked_step_mesh():
    height = np.zeros((9, 9), np.float32)
    height[:, 5:] = np.nan  # sampled columns 0 3 6 8: 6 and 8 are gone
    mesh = grid_mesh(height, step=3)
    assert len(mesh.vertices) == 4 * 2 and len(mesh.faces) == 2 * 3 * 1


def test_vertex_normals_are_sampled_and_cleaned():
    n = np.zeros((H, W, 3), np.float32)
    n[..., 0], n[..., 2] = 3.0, 4.0
    n[1, 1] = np.nan
    mesh = grid_mesh(_height(), normals=n)
    assert mesh.normals.shape == (H * W, 3) and mesh.normals.dtype == np.float32
    np.testing.assert_allclose(mesh.normals[0], (0.6, 0.0, 0.8), rtol=1e-6)
    np.testing.assert_allclose(mesh.normals[W + 1], (0.0, 0.0, 1.0))


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        grid_mesh(np.zeros((4, 4)), texture=np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(ValueError):
        grid_mesh(np.zeros((4, 4)), step=0)
    with pytest.raises(ValueError):
        grid_mesh(np.zeros((4, 4)), normals=np.zeros((4, 4, 2)))


# ---------------------------------------------------------------- PLY


def _ply_mesh() -> GridMesh:
    height = _height()
    height[2, 3] = np.nan
    n = np.zeros((H, W, 3), np.float32)
    n[..., 2] = 1.0
    return grid_mesh(height, texture=_texture(), pixel_size=0.25, normals=n)


def test_ply_header(tmp_path):
    mesh = _ply_mesh()
    Image.fromarray(_texture()).save(tmp_path / "scan_texture.png")
    write_ply(tmp_path / "scan.ply", mesh, texture_file=tmp_path / "scan_texture.png", comments=["source test"])
    data = (tmp_path / "scan.ply").read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode()
    lines = header.splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "comment TextureFile scan_texture.png" in lines  # relative to the PLY's folder
    assert "comment unit mm" in lines and "comment source test" in lines
    props = [line.split()[-1] for line in lines if line.startswith("property float") or line.startswith("property uchar")]
    assert props == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "texture_u", "texture_v"]
    assert "property list uchar int vertex_indices" in lines
    v, f = len(mesh.vertices), len(mesh.faces)
    assert len(data) == len(header) + v * (11 * 4 - 3 * 3) + f * 13
    with pytest.raises(ValueError):
        write_ply(tmp_path / "bad.ply", mesh, comments=["two\nlines"])


def test_ply_round_trip_with_trimesh(tmp_path):
    mesh = _ply_mesh()
    Image.fromarray(_texture()).save(tmp_path / "tex.png")
    write_ply(tmp_path / "m.ply", mesh, texture_file="tex.png")
    loaded = trimesh.load(tmp_path / "m.ply", process=False)
    assert loaded.vertices.shape == mesh.vertices.shape
    assert loaded.faces.shape == mesh.faces.shape
    np.testing.assert_allclose(loaded.vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    np.testing.assert_allclose(loaded.face_normals, _unit(_face_normals(mesh.vertices, mesh.faces)), atol=1e-6)
    assert (loaded.face_normals[:, 2] > 0).all()
    # trimesh reads the per-vertex texture_u/texture_v and the TextureFile comment...
    np.testing.assert_allclose(loaded.visual.uv, mesh.uv)
    assert loaded.visual.material.image.size == (W, H)
    # ...and, having a texture, keeps the vertex colours only in its raw loader output.
    with open(tmp_path / "m.ply", "rb") as handle:
        raw = trimesh.exchange.ply.load_ply(handle, skip_materials=True)
    np.testing.assert_array_equal(raw["vertex_colors"][:, :3], mesh.colors)


def test_ply_round_trip_with_open3d(tmp_path):
    o3d = _open3d()
    mesh = _ply_mesh()
    write_ply(tmp_path / "m.ply", mesh)
    loaded = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert len(loaded.vertices) == len(mesh.vertices)
    assert len(loaded.triangles) == len(mesh.faces)
    np.testing.assert_allclose(np.asarray(loaded.vertices), mesh.vertices, rtol=1e-6)
    assert loaded.has_vertex_colors() and loaded.has_vertex_normals()
    np.testing.assert_allclose(np.asarray(loaded.vertex_colors) * 255, mesh.colors, atol=1e-3)
    loaded.compute_triangle_normals()
    assert (np.asarray(loaded.triangle_normals)[:, 2] > 0).all()
    # open3d's PLY reader ignores per-vertex texture_u/texture_v (it reads no UVs here).
    assert not loaded.has_triangle_uvs()


# ---------------------------------------------------------------- OBJ


def _uv_pixel(image: Image.Image, uv: np.ndarray) -> tuple[int, ...]:
    """Colour an OBJ viewer shows at `uv` (v up: v = 1 is the image's top row)."""
    w, h = image.size
    col = int(np.clip(uv[0] * w, 0, w - 1))
    row = int(np.clip((1.0 - uv[1]) * h, 0, h - 1))
    return image.convert("RGB").getpixel((col, row))


def test_obj_files_and_text(tmp_path):
    mesh = grid_mesh(_height(), texture=_texture(), pixel_size=0.25)
    write_obj(tmp_path / "scan.obj", mesh, _texture(), comments=["source test"])
    assert sorted(os.listdir(tmp_path)) == ["scan.mtl", "scan.obj", "scan_texture.png"]
    obj = (tmp_path / "scan.obj").read_text().splitlines()
    assert "# unit mm" in obj and "# source test" in obj
    assert "mtllib scan.mtl" in obj and "usemtl scan" in obj
    assert sum(line.startswith("v ") for line in obj) == len(mesh.vertices)
    assert sum(line.startswith("vt ") for line in obj) == len(mesh.vertices)
    assert sum(line.startswith("f ") for line in obj) == len(mesh.faces)
    assert "f 1/1 9/9 10/10" in obj  # first cell: top-left, bottom-left, bottom-right
    mtl = (tmp_path / "scan.mtl").read_text().splitlines()
    for line in ["newmtl scan", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "illum 1", "map_Kd scan_texture.png"]:
        assert line in mtl


def test_obj_round_trip_with_trimesh(tmp_path):
    height = _height()
    height[3, 4] = np.nan
    mesh = grid_mesh(height, texture=_texture(), pixel_size=0.25)
    write_obj(tmp_path / "m.obj", mesh, _texture())
    loaded = trimesh.load(tmp_path / "m.obj", process=False, maintain_order=True)
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    assert (loaded.face_normals[:, 2] > 0).all()
    material = loaded.visual.material
    image = material.image
    assert image is not None and image.size == (W, H)
    # Not flipped: the top-left vertex samples the red corner, the bottom-left one blue.
    assert _uv_pixel(image, loaded.visual.uv[0]) == RED
    bottom_left = np.flatnonzero((mesh.vertices[:, 0] == 0) & (mesh.vertices[:, 1] == -(H - 1) * 0.25))
    assert _uv_pixel(image, loaded.visual.uv[bottom_left[0]]) == BLUE
    # A white material: the texture is shown with its own colours, not darkened.
    colour = getattr(material, "diffuse", None)
    if colour is None:
        colour = material.baseColorFactor
    np.testing.assert_array_equal(np.asarray(colour)[:3], (255, 255, 255))


def test_obj_round_trip_with_open3d(tmp_path):
    o3d = _open3d()
    mesh = grid_mesh(_height(), texture=_texture())
    write_obj(tmp_path / "m.obj", mesh, _texture())
    path = str(tmp_path / "m.obj")
    plain = o3d.io.read_triangle_mesh(path, enable_post_processing=False)
    assert len(plain.vertices) == len(mesh.vertices)
    assert len(plain.triangles) == len(mesh.faces)
    assert plain.has_triangle_uvs()
    np.testing.assert_allclose(np.asarray(plain.triangle_uvs), mesh.uv[mesh.faces.ravel()], atol=1e-6)
    # open3d loads the texture only with post-processing (assimp), which may split vertices.
    loaded = o3d.io.read_triangle_mesh(path, enable_post_processing=True)
    assert len(loaded.triangles) == len(mesh.faces)
    assert loaded.has_triangle_uvs() and loaded.has_textures()
    texture = np.asarray(loaded.textures[0])
    assert texture.shape == (H, W, 3)
    # open3d stores the image bottom-up (OpenGL), so v indexes rows from the bottom; the
    # first triangle's first corner is the top-left vertex, which must sample red.
    u, v = np.asarray(loaded.triangle_uvs)[0]
    np.testing.assert_allclose((u, v), mesh.uv[0], atol=1e-6)
    assert tuple(texture[int(v * H), int(u * W)]) == RED


def test_obj_from_texture_file_and_with_normals(tmp_path):
    Image.fromarray(_texture()).save(tmp_path / "photo.jpg", quality=95)
    n = np.zeros((H, W, 3), np.float32)
    n[..., 2] = 1.0
    mesh = grid_mesh(_height(), normals=n)
    write_obj(tmp_path / "m.obj", mesh, tmp_path / "photo.jpg")
    with Image.open(tmp_path / "m_texture.png") as png:
        assert png.format == "PNG" and png.size == (W, H)
    obj = (tmp_path / "m.obj").read_text().splitlines()
    assert sum(line.startswith("vn ") for line in obj) == len(mesh.vertices)
    assert "f 1/1/1 9/9/9 10/10/10" in obj
    with pytest.raises(InputError):
        write_obj(tmp_path / "x.obj", mesh, tmp_path / "missing.png")


def test_obj_without_texture_writes_vertex_colours(tmp_path):
    mesh = grid_mesh(_height(), texture=_texture())
    write_obj(tmp_path / "plain.obj", mesh)
    assert os.listdir(tmp_path) == ["plain.obj"]
    first = next(line for line in (tmp_path / "plain.obj").read_text().splitlines() if line.startswith("v "))
    assert first.split()[1:] == ["0", "0", "0", "1", "0", "0"]


def test_two_meshes_in_one_folder_keep_their_materials(tmp_path):
    other = _texture()
    other[:] = (0, 255, 0)
    write_obj(tmp_path / "a.obj", grid_mesh(_height(), texture=_texture()), _texture())
    write_obj(tmp_path / "b.obj", grid_mesh(_height()), other)
    assert {"a.mtl", "b.mtl", "a_texture.png", "b_texture.png"} <= set(os.listdir(tmp_path))
    a = trimesh.load(tmp_path / "a.obj", process=False)
    b = trimesh.load(tmp_path / "b.obj", process=False)
    assert a.visual.material.image.convert("RGB").getpixel((0, 0)) == RED
    assert b.visual.material.image.convert("RGB").getpixel((0, 0)) == (0, 255, 0)


def _obj_number(value: float) -> str:
    """Python's '%.6f' without trailing zeros, and without the sign of a zero."""
    text = ("%.6f" % value).rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def _expected_obj(mesh: GridMesh, stem: str | None) -> bytes:
    """The OBJ text write_obj must produce, formatted by Python one number at a time."""
    lines = ["# ptm-reconstruct grid mesh", f"# unit {mesh.unit}"]
    if stem is not None:
        lines.append(f"mtllib {stem}.mtl")
        vertex = mesh.vertices
    else:
        vertex = np.hstack([mesh.vertices, mesh.colors / np.float32(255)])
    rows = [("v", vertex), ("vt", mesh.uv)] + ([("vn", mesh.normals)] if mesh.normals is not None else [])
    for keyword, values in rows:
        lines += [" ".join([keyword] + [_obj_number(x) for x in row]) for row in values.tolist()]
    if stem is not None:
        lines.append(f"usemtl {stem}")
    corner = "{0}/{0}" if mesh.normals is None else "{0}/{0}/{0}"
    lines += ["f " + " ".join(corner.format(i + 1) for i in face) for face in mesh.faces.tolist()]
    return ("\n".join(lines) + "\n").encode()


def _big_mesh() -> tuple[GridMesh, np.ndarray]:
    """Over 10⁴ vertices (face indices of 1 to 5 digits), negative heights, a hole, tilted
    normals, and a pixel size whose products are not round in float32."""
    h, w = 113, 97
    rng = np.random.default_rng(2)
    row, col = np.mgrid[0:h, 0:w]
    height = (np.sin(col / 9.0) * 40.0 - row * 0.731 + rng.normal(0, 1e-3, (h, w))).astype(np.float32)
    height[50:53, 20:30] = np.nan
    normals = rng.normal(0, 0.3, (h, w, 3)).astype(np.float32)
    normals[..., 2] = 1.0
    texture = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    return grid_mesh(height, texture=texture, pixel_size=0.37, normals=normals), texture


def test_obj_text_matches_python_formatting(tmp_path, monkeypatch):
    mesh, texture = _big_mesh()
    write_obj(tmp_path / "one.obj", mesh, texture)
    assert (tmp_path / "one.obj").read_bytes() == _expected_obj(mesh, "one")
    # Many small chunks formatted by several threads give the same bytes.
    monkeypatch.setattr(obj_module, "_TEXT_CHUNK", 1000)
    monkeypatch.setattr(obj_module, "_WORKERS", 3)
    monkeypatch.setattr(obj_module, "_AHEAD", 4)
    write_obj(tmp_path / "one.obj", mesh, texture)
    assert (tmp_path / "one.obj").read_bytes() == _expected_obj(mesh, "one")
    # Without a texture: vertex colours, no material.
    mesh.normals = None
    write_obj(tmp_path / "plain.obj", mesh)
    assert (tmp_path / "plain.obj").read_bytes() == _expected_obj(mesh, None)


def test_obj_faces_in_any_order(tmp_path, monkeypatch):
    # Chunks of shuffled faces use vertices far apart, unlike a grid's rows.
    monkeypatch.setattr(obj_module, "_TEXT_CHUNK", 7)
    mesh = grid_mesh(_height(), texture=_texture())
    mesh.faces = mesh.faces[np.random.default_rng(0).permutation(len(mesh.faces))]
    write_obj(tmp_path / "m.obj", mesh, _texture())
    assert (tmp_path / "m.obj").read_bytes() == _expected_obj(mesh, "m")
    loaded = trimesh.load(tmp_path / "m.obj", process=False, maintain_order=True)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)


def test_obj_with_nan_or_infinite_numbers_raises_and_writes_no_obj(tmp_path):
    mesh = grid_mesh(_height(), texture=_texture())
    mesh.vertices[5, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_obj(tmp_path / "m.obj", mesh)
    mesh = grid_mesh(_height(), texture=_texture())
    mesh.uv[3, 0] = np.inf
    with pytest.raises(ValueError, match="infinity"):
        write_obj(tmp_path / "m.obj", mesh, _texture())
    assert "m.obj" not in os.listdir(tmp_path)
    assert not [name for name in os.listdir(tmp_path) if name.startswith(".")]  # no temporaries


# ---------------------------------------------------------------- atomic writes


def test_atomic_write_keeps_the_old_file_and_no_temporary_on_failure(tmp_path):
    target = tmp_path / "mesh.ply"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_write(target, "wb") as handle:
            handle.write(b"partial new content")
            raise RuntimeError("simulated crash")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["mesh.ply"]


def test_atomic_write_replaces_on_success(tmp_path):
    target = tmp_path / "notes.txt"
    target.write_text("old")
    with atomic_write(target, "w") as handle:
        handle.write("new\n")
    assert target.read_text() == "new\n"
    assert os.listdir(tmp_path) == ["notes.txt"]
    assert os.stat(target).st_mode & 0o644 == 0o644  # usual permissions, not mkstemp's 0600


def test_writers_leave_no_temporary_on_failure(tmp_path):
    mesh = grid_mesh(_height())
    mesh.colors = None  # breaks the writer half-way, after the header
    (tmp_path / "m.ply").write_bytes(b"old")
    with pytest.raises(Exception):
        write_ply(tmp_path / "m.ply", mesh)
    assert os.listdir(tmp_path) == ["m.ply"] and (tmp_path / "m.ply").read_bytes() == b"old"


def test_unwritable_destinations_raise_input_error(tmp_path):
    with pytest.raises(InputError, match="does not exist") as info:
        with atomic_write(tmp_path / "missing" / "m.ply"):
            pass
    assert info.value.path == str(tmp_path / "missing")
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="not a folder"):
        write_ply(tmp_path / "file" / "m.ply", grid_mesh(_height()))
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(InputError, match="is a folder"):
        write_ply(tmp_path / "folder.ply", grid_mesh(_height()))
    assert sorted(os.listdir(tmp_path)) == ["file", "folder.ply"]


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root ignores permissions")
def test_read_only_folder_raises_input_error(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(InputError, match="not writable"):
            write_obj(folder / "m.obj", grid_mesh(_height()), _texture())
    finally:
        folder.chmod(0o755)


def test_atomic_write_rejects_read_modes(tmp_path):
    with pytest.raises(ValueError):
        with atomic_write(tmp_path / "x", "rb"):
            pass


def test_permission_denied_raises_input_error(tmp_path, monkeypatch):
    # Root ignores folder permissions, so simulate the refusal of the operating system.
    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    import ptmcore.atomic

    monkeypatch.setattr(ptmcore.atomic, "open", refuse, raising=False)
    with pytest.raises(InputError, match="not writable") as info:
        write_ply(tmp_path / "m.ply", grid_mesh(_height()))
    assert info.value.path == str(tmp_path)
