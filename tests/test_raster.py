"""The software mesh rendering of the report (reconstruct.report.raster)."""

import numpy as np
import pytest

from reconstruct.mesh.grid import grid_mesh
from reconstruct.report.raster import render_mesh, vertex_normals

WHITE = np.array([255, 255, 255])


def _square(z: float = 0.0, half: float = 1.0, flip: bool = False):
    vertices = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return vertices, faces[:, ::-1] if flip else faces


def test_vertex_normals_are_area_weighted_unit_vectors():
    vertices, faces = _square()
    np.testing.assert_allclose(vertex_normals(vertices, faces), np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-7)
    # A vertex between a large face tilted about x and a small flat one leans to the large one.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -4, 4], [1, -4, 4.0]])
    faces = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 4]])
    n = vertex_normals(vertices, faces)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, rtol=1e-6)
    big = np.cross(vertices[3] - vertices[0], vertices[1] - vertices[0])
    small = np.cross(vertices[1] - vertices[0], vertices[2] - vertices[0])
    expected = big + small
    np.testing.assert_allclose(n[0], expected / np.linalg.norm(expected), rtol=1e-6)
    assert not vertex_normals(np.vstack([vertices, [[9, 9, 9]]]), faces)[5].any()  # in no face


def test_a_square_seen_from_above_fills_the_middle_and_leaves_the_background():
    vertices, faces = _square()
    colours = np.tile([200, 40, 40], (4, 1)).astype(np.uint8)
    image = render_mesh(vertices, faces, colours, (120, 80), view=(0.0, -0.01, 1.0), zoom=1.0)
    assert image.shape == (80, 120, 3) and image.dtype == np.uint8
    middle = image[40, 60].astype(int)
    assert middle[0] > 2 * middle[1] and middle[1] == middle[2]  # its own colour, lit
    np.testing.assert_array_equal(image[2, 2], WHITE)  # corners: background
    np.testing.assert_array_equal(image[2, 117], WHITE)
    # VTK's camera: the bounding sphere (radius √2) fits the 30° view at distance √2 / sin 15°,
    # where the picture's height spans 2·distance·tan 15°; the square's side is 2 of it.
    drawn = np.any(image != WHITE, axis=2)
    rows = np.flatnonzero(drawn.any(axis=1))
    distance = np.sqrt(2) / np.sin(np.radians(15))
    side = 2 / (2 * distance * np.tan(np.radians(15))) * 80
    assert abs((rows[-1] - rows[0] + 1) - side) <= 2


@pytest.mark.parametrize("order", [[0, 1], [1, 0]])
def test_the_nearer_surface_hides_the_farther_whatever_the_order(order):
    near, near_faces = _square(z=1.0, half=0.5)
    far, far_faces = _square(z=0.0)
    vertices = np.vstack([near, far])
    faces = [near_faces, far_faces + 4]
    colours = np.vstack([np.tile([250, 0, 0], (4, 1)), np.tile([0, 0, 250], (4, 1))]).astype(np.uint8)
    image = render_mesh(vertices, np.vstack([faces[k] for k in order]), colours, (90, 60), view=(0.0, -0.01, 1.0))
    middle = image[30, 45].astype(int)
    assert middle[0] > 100 and middle[2] < 40  # red, and a little white highlight
    assert (image[..., 2] > 100).any()  # the far square still shows around the near one


def test_straight_from_above_the_picture_keeps_y_up():
    vertices, faces = _square()
    colours = np.array([[250, 0, 0], [250, 0, 0], [0, 0, 250], [0, 0, 250]], np.uint8)  # blue at y = +1
    image = render_mesh(vertices, faces, colours, (60, 60), view=(0.0, 0.0, 1.0)).astype(int)
    assert image[15, 30, 2] > image[15, 30, 0] and image[45, 30, 0] > image[45, 30, 2]


def test_a_surface_seen_from_behind_is_lit_as_from_the_front():
    vertices, faces = _square()
    front = render_mesh(vertices, faces, None, (60, 40), view=(0.0, -0.01, 1.0))
    back = render_mesh(vertices, faces[:, ::-1], None, (60, 40), view=(0.0, -0.01, 1.0))
    np.testing.assert_array_equal(front, back)
    assert front[20, 30].max() < 255  # clay, shaded


def test_missing_vertices_leave_their_triangles_out_and_bad_meshes_are_refused():
    height = np.ones((6, 8), np.float32)
    mesh = grid_mesh(height, pixel_size=1.0)
    vertices = np.array(mesh.vertices, np.float64)
    whole = render_mesh(vertices, mesh.faces, None, (80, 60))
    vertices[0] = np.nan
    holed = render_mesh(vertices, mesh.faces, None, (80, 60))
    assert np.any(holed != whole) and np.any(holed != WHITE)
    with pytest.raises(ValueError, match="no triangle"):
        render_mesh(np.full((3, 3), np.nan), [[0, 1, 2]])
    with pytest.raises(ValueError, match="do not exist"):
        render_mesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        render_mesh(np.zeros((3, 2)), [[0, 1, 2]])
    with pytest.raises(ValueError, match="view"):
        render_mesh(vertices, mesh.faces, view=(0, 0, 0))
    with pytest.raises(ValueError, match="zoom"):
        render_mesh(vertices, mesh.faces, zoom=0)


def test_the_view_matches_vtks_camera():
    """The camera follows VTK's ResetCamera and zoom: the mesh's outline in the picture is
    the one pyvista draws (where an OpenGL context can be had)."""
    from reconstruct.report import rendering

    y, x = np.mgrid[0:40, 0:60].astype(np.float32)
    height = 4 * np.exp(-((x - 30) ** 2 + (y - 20) ** 2) / 150).astype(np.float32)
    mesh = grid_mesh(height, pixel_size=1.0)
    view = np.array([0.35, -0.75, 0.85])
    ours = np.any(render_mesh(mesh.vertices, mesh.faces, None, (300, 200), view=tuple(view), zoom=1.2) < 250, axis=2)

    def draw(plotter):
        import pyvista as pv

        surface = pv.PolyData.from_regular_faces(np.asarray(mesh.vertices, np.float32), mesh.faces)
        plotter.set_background("white")
        plotter.add_mesh(surface, color=(0.5, 0.5, 0.5))
        center = np.asarray(surface.center)
        plotter.camera_position = [tuple(center + view), tuple(center), (0.0, 0.0, 1.0)]
        plotter.reset_camera()
        plotter.camera.zoom(1.2)

    try:
        theirs = np.any(rendering.render_image(draw, (300, 200)) < 250, axis=2)
    except RuntimeError as exc:
        pytest.skip(f"no off-screen rendering here ({exc})")
    overlap = (ours & theirs).sum() / (ours | theirs).sum()
    assert overlap > 0.97, overlap
