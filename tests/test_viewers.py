"""The meshes as MeshLab itself reads them (pymeshlab is MeshLab's engine)."""

import numpy as np
import pytest

from reconstruct.mesh.grid import grid_mesh
from reconstruct.mesh.obj import write_obj
from reconstruct.mesh.ply import write_ply

pymeshlab = pytest.importorskip("pymeshlab")


@pytest.fixture
def textured_mesh():
    h, w = 30, 40
    rows, cols = np.mgrid[0:h, 0:w]
    height = (0.02 * (cols - 20.0) ** 2 - 0.03 * rows).astype(np.float32)
    texture = np.full((h, w, 3), 90, np.uint8)
    texture[:5, :5] = (255, 0, 0)  # a red top-left corner shows whether the texture is flipped
    return grid_mesh(height, texture=texture, step=1, pixel_size=0.1), texture


def _load(path):
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    return ms  # the mesh lives only as long as its MeshSet


def test_meshlab_reads_ply_with_colours_uvs_and_texture(tmp_path, textured_mesh):
    mesh, texture = textured_mesh
    from PIL import Image

    Image.fromarray(texture).save(tmp_path / "mesh_texture.png")
    write_ply(tmp_path / "mesh.ply", mesh, texture_file="mesh_texture.png")
    ms = _load(tmp_path / "mesh.ply")
    m = ms.current_mesh()
    assert m.vertex_number() == len(mesh.vertices) and m.face_number() == len(mesh.faces)
    assert m.has_vertex_color() and m.has_vertex_tex_coord()
    assert "mesh_texture.png" in m.textures()
    np.testing.assert_allclose(m.vertex_matrix(), mesh.vertices, atol=1e-5)
    colours = m.vertex_color_matrix()  # RGBA in 0..1
    np.testing.assert_allclose(colours[0, :3], [1, 0, 0], atol=1e-3)  # vertex of pixel (0, 0)
    uv = m.vertex_tex_coord_matrix()
    assert uv[0, 0] < 0.1 and uv[0, 1] > 0.9  # top-left pixel: u small, v near 1 (v up)


def test_meshlab_reads_obj_with_material_and_texture(tmp_path, textured_mesh):
    mesh, texture = textured_mesh
    write_obj(tmp_path / "mesh.obj", mesh, texture)
    ms = _load(tmp_path / "mesh.obj")
    m = ms.current_mesh()
    assert m.vertex_number() == len(mesh.vertices) and m.face_number() == len(mesh.faces)
    assert m.has_wedge_tex_coord()
    assert "mesh_texture.png" in m.textures()
    np.testing.assert_allclose(m.vertex_matrix(), mesh.vertices, atol=1e-5)
    # Faces keep their orientation: normals towards the camera (+z) on this gentle surface.
    ms.compute_normal_per_face()
    assert (ms.current_mesh().face_normal_matrix()[:, 2] > 0).all()
