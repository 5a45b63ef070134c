"""reconstruct.mesh.ply.read_binary_ply: what the writer writes, read back without pyvista;
anything else refused before anything is allocated."""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from reconstruct.mesh.grid import grid_mesh
from reconstruct.mesh.ply import read_binary_ply, write_binary_ply, write_ply


def test_round_trip_of_the_general_writer(tmp_path):
    rng = np.random.default_rng(0)
    vertex = {"x": rng.random(7, np.float32), "y": rng.random(7, np.float32), "z": rng.random(7).astype(np.float32),
              "red": rng.integers(0, 256, 7, np.uint8), "quality": rng.random(7)}
    faces = rng.integers(0, 7, (5, 3))
    write_binary_ply(tmp_path / "m.ply", vertex, faces, comments=["unit mm"])
    got, got_faces = read_binary_ply(tmp_path / "m.ply")
    assert list(got) == list(vertex)
    for name in vertex:
        assert got[name].dtype == vertex[name].dtype
        np.testing.assert_array_equal(got[name], vertex[name])
    np.testing.assert_array_equal(got_faces, faces)
    write_binary_ply(tmp_path / "points.ply", {"x": vertex["x"]})
    assert read_binary_ply(tmp_path / "points.ply")[1].shape == (0, 3)


def test_a_grid_mesh_as_the_run_writes_it(tmp_path):
    height = np.arange(20, dtype=np.float32).reshape(4, 5)
    mesh = grid_mesh(height, texture=np.full((4, 5, 3), 200, np.uint8), pixel_size=0.5)
    write_ply(tmp_path / "mesh.ply", mesh)
    vertex, faces = read_binary_ply(tmp_path / "mesh.ply")
    np.testing.assert_array_equal(np.column_stack([vertex["x"], vertex["y"], vertex["z"]]), mesh.vertices)
    np.testing.assert_array_equal(faces, mesh.faces)
    assert (vertex["red"] == 200).all()


def test_big_endian_and_crlf_header(tmp_path):
    header = b"ply\r\nformat binary_big_endian 1.0\r\nelement vertex 3\r\nproperty float32 x\r\n" \
             b"element face 1\r\nproperty list uint8 int32 vertex_indices\r\nend_header\r\n"
    (tmp_path / "b.ply").write_bytes(header + struct.pack(">fff", 1.0, 2.0, 3.0) + struct.pack(">Biii", 3, 2, 1, 0))
    vertex, faces = read_binary_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(vertex["x"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(faces, [[2, 1, 0]])


@pytest.mark.parametrize("content, match", [
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n", "binary only"),
    (b"solid stl\n", "not a PLY"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nend_header\n" + b"\0" * 4,
     "bytes where the header calls for"),
    # An absurd count is refused by the file's size, not by an allocation.
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999999\nproperty float x\nend_header\n",
     "bytes where the header calls for"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nelement face 1\n"
     b"property list uchar int vertex_indices\nend_header\n" + struct.pack("<fBiii", 0.0, 3, 0, 0, 5), "out of range"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nelement face 1\n"
     b"property list uchar int vertex_indices\nend_header\n" + struct.pack("<fBiii", 0.0, 4, 0, 0, 0), "triangles"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quad x\nend_header\n" + b"\0" * 4,
     "unknown PLY type"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nelement edge 1\n"
     b"property int a\nend_header\n" + b"\0" * 8, "face element"),
])
def test_other_files_are_refused(tmp_path, content, match):
    (tmp_path / "x.ply").write_bytes(content)
    with pytest.raises(ValueError, match=match):
        read_binary_ply(tmp_path / "x.ply")


def test_a_named_pipe_is_refused_not_waited_on(tmp_path):
    import os

    from ptmcore.errors import InputError

    os.mkfifo(tmp_path / "mesh.ply")
    with pytest.raises(InputError, match="named pipe"):
        read_binary_ply(tmp_path / "mesh.ply")
    with pytest.raises(InputError, match="not found"):
        read_binary_ply(tmp_path / "none.ply")


def test_the_report_draws_a_run_mesh_without_pyvista(tmp_path):
    height = np.add.outer(np.arange(30.0), np.arange(40.0)).astype(np.float32)
    write_ply(tmp_path / "mesh.ply", grid_mesh(height, texture=np.full((30, 40, 3), 90, np.uint8)))
    code = ("import sys; from reconstruct.report.figures import mesh_render; "
            f"image = mesh_render({str(tmp_path / 'mesh.ply')!r}, (120, 80)); "
            "assert image.shape == (80, 120, 3) and image.any(); assert 'pyvista' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
