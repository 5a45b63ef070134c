"""OBJ export of a 4-million-vertex textured mesh: our writer against trimesh's and NumPy's.

A 2000×2000 synthetic height map (pixel size 0.02 mm) with a texture and normals becomes a
grid mesh of 4 M vertices and 8 M triangles (:func:`reconstruct.mesh.grid.grid_mesh`), written
as ``mesh.obj`` with ``v``, ``vt``, ``vn`` and ``f a/a/a`` lines, ``mesh.mtl`` and the PNG
texture by three writers:

* ``ours``: :func:`reconstruct.mesh.obj.write_obj` (the lines formatted by the
  compiled kernels of :mod:`reconstruct.mesh.objtext`, in threads);
* ``trimesh``: a :class:`trimesh.Trimesh` with the vertex normals and a ``TextureVisuals``
  (UVs and a white material holding the texture), exported by
  ``trimesh.exchange.obj.export_obj(include_normals=True, include_texture=True, digits=6)``;
* ``numpy``: plain NumPy and Python: each chunk of 100 000 rows formatted with one ``%``
  operation on a repeated ``'v %.6f %.6f %.6f\\n'`` line (2.3 to 2.7× faster than
  :func:`numpy.savetxt`, which formats row by row; ``numpy.char.mod`` is slower still).

Every writer goes through :func:`ptmcore.atomic.atomic_write` (fsync and rename), as a
replacement of ours would. Each write runs in its own process, alternating ours, trimesh,
numpy, ``--runs`` times; the time is the writer call alone (building the trimesh object
included, imports not). Medians; other processes may load the machine, so the median of
each run's ratio to ours is given too. Memory (Linux only): once the mesh arrays are loaded
(and OpenCV, imported on first use for the PNG), the process's peak RSS is reset
(``/proc/self/clear_refs``), so its ``VmHWM`` after the write is the peak during the write
(``ru_maxrss`` is not: it keeps the parent's size at the fork), and "over the mesh"
subtracts the resident size before it. The last run's files are
loaded with trimesh and compared with the mesh and texture (vertices and UVs within 1e-6,
faces and texels equal).

Run: ``.venv/bin/python benchmarks/obj_export.py [--runs 5] [--size 2000]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

import numpy as np
import trimesh
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from procinfo import status_mb  # noqa: E402
from ptmcore.atomic import atomic_write  # noqa: E402
from ptmcore.png import encode_png  # noqa: E402
from reconstruct.mesh.grid import GridMesh, grid_mesh  # noqa: E402
from reconstruct.mesh.obj import write_obj  # noqa: E402

WRITERS = ("ours", "trimesh", "numpy")
_ARRAYS = ("vertices", "faces", "uv", "colors", "normals")
_CHUNK = 100_000
_MTL = "newmtl mesh\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd mesh_texture.png\n"


def _scene(size: int) -> tuple[GridMesh, np.ndarray]:
    """A ``size``×``size`` height map (mm) with bumps and fine noise, its normals and a
    smooth colour texture, meshed at 0.02 mm per pixel."""
    pixel = 0.02
    rng = np.random.default_rng(0)
    row, col = np.mgrid[0:size, 0:size].astype(np.float32) * np.float32(pixel)
    height = 2.0 * np.sin(col / 7.0) * np.cos(row / 5.0) + 0.5 * np.sin(col + row)
    height = (height + rng.normal(0.0, 0.002, height.shape)).astype(np.float32)
    dz_dy, dz_dx = np.gradient(height, pixel)
    normals = np.dstack([-dz_dx, dz_dy, np.ones_like(height)]).astype(np.float32)
    texture = np.dstack([col * 6, row * 6, 128 + 40 * height]).clip(0, 255).astype(np.uint8)
    return grid_mesh(height, texture=texture, pixel_size=pixel, normals=normals), texture


def _write_trimesh(path: Path, mesh: GridMesh, texture: np.ndarray) -> None:
    """The same files through trimesh's OBJ exporter."""
    material = trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(texture),
        ambient=(255, 255, 255, 255),
        diffuse=(255, 255, 255, 255),
        specular=(0, 0, 0, 255),
        name="mesh_texture",  # trimesh names the image after the material
    )
    tm = trimesh.Trimesh(
        vertices=mesh.vertices,
        faces=mesh.faces,
        vertex_normals=mesh.normals,
        visual=trimesh.visual.TextureVisuals(uv=mesh.uv, material=material),
        process=False,
        validate=False,
    )
    text, files = trimesh.exchange.obj.export_obj(
        tm, include_normals=True, include_texture=True, digits=6,
        return_texture=True, mtl_name="mesh.mtl",
    )
    for name, data in files.items():
        with atomic_write(path.parent / name, "wb") as handle:
            handle.write(data)
    with atomic_write(path, "wb") as handle:
        handle.write(text.encode("ascii"))


def _numpy_lines(handle: IO[bytes], line: str, values: np.ndarray) -> None:
    """Each row of `values` through the ``%`` format `line`, a chunk of rows at a time."""
    for start in range(0, len(values), _CHUNK):
        chunk = values[start : start + _CHUNK]
        handle.write(((line * len(chunk)) % tuple(chunk.ravel().tolist())).encode("ascii"))


def _write_numpy(path: Path, mesh: GridMesh, texture: np.ndarray) -> None:
    """The same files, the numbers formatted by Python's ``%`` (``'%.6f'``, ``'%d'``)."""
    with atomic_write(path.parent / "mesh_texture.png", "wb") as handle:
        handle.write(encode_png(texture))
    with atomic_write(path.parent / "mesh.mtl", "w") as handle:
        handle.write(_MTL)
    with atomic_write(path, "wb") as handle:
        handle.write(b"# plain NumPy writer\nmtllib mesh.mtl\n")
        _numpy_lines(handle, "v %.6f %.6f %.6f\n", mesh.vertices)
        _numpy_lines(handle, "vt %.6f %.6f\n", mesh.uv)
        _numpy_lines(handle, "vn %.6f %.6f %.6f\n", mesh.normals)
        handle.write(b"usemtl mesh\n")
        for start in range(0, len(mesh.faces), _CHUNK):
            corners = np.repeat(mesh.faces[start : start + _CHUNK] + 1, 3, axis=1)
            _numpy_lines(handle, "f %d/%d/%d %d/%d/%d %d/%d/%d\n", corners)


def _child(writer: str, data: Path, out: Path) -> None:
    """Load the mesh, run one writer, print its time and peak RSS (MB) as JSON."""
    arrays = {name: np.load(data / f"{name}.npy") for name in _ARRAYS}
    mesh = GridMesh(**arrays, unit="mm")
    texture = np.load(data / "texture.npy")
    # The PNG encoder's first use (its imports and threads) is not the writer's memory.
    encode_png(np.zeros((1, 1, 3), np.uint8))
    # Linux: the peak RSS is reset to the current one, so that VmHWM is the writer's.
    Path("/proc/self/clear_refs").write_text("5")
    before = status_mb("VmRSS")
    t0 = time.perf_counter()
    if writer == "ours":
        write_obj(out / "mesh.obj", mesh, texture)
    elif writer == "trimesh":
        _write_trimesh(out / "mesh.obj", mesh, texture)
    else:
        _write_numpy(out / "mesh.obj", mesh, texture)
    seconds = time.perf_counter() - t0
    peak = status_mb("VmHWM")
    print(json.dumps({"seconds": seconds, "peak": peak, "over": peak - before}))


def _check(folder: Path, mesh: GridMesh, texture: np.ndarray) -> str:
    """Load the written OBJ with trimesh and compare it with the mesh and texture."""
    loaded = trimesh.load(folder / "mesh.obj", process=False, maintain_order=True)
    same = (
        len(loaded.vertices) == len(mesh.vertices)
        and np.abs(loaded.vertices - mesh.vertices).max() <= 1e-6
        and np.abs(loaded.visual.uv - mesh.uv).max() <= 1e-6
        and np.array_equal(loaded.faces, mesh.faces)
        and np.array_equal(np.asarray(loaded.visual.material.image.convert("RGB")), texture)
    )
    return "yes" if same else "NO"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--size", type=int, default=2000, help="height map side (pixels)")
    parser.add_argument(
        "--child", nargs=3, metavar=("WRITER", "DATA", "OUT"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], Path(args.child[1]), Path(args.child[2]))
        return

    mesh, texture = _scene(args.size)
    times: dict[str, list[float]] = {w: [] for w in WRITERS}
    peaks: dict[str, list[float]] = {w: [] for w in WRITERS}
    overs: dict[str, list[float]] = {w: [] for w in WRITERS}
    with tempfile.TemporaryDirectory(prefix="obj_export_") as tmp:
        data = Path(tmp) / "data"
        data.mkdir()
        for name in _ARRAYS:
            np.save(data / f"{name}.npy", getattr(mesh, name))
        np.save(data / "texture.npy", texture)
        for run in range(args.runs):
            for writer in WRITERS:
                out = Path(tmp) / writer
                out.mkdir(exist_ok=True)
                command = [sys.executable, __file__, "--child", writer, str(data), str(out)]
                result = json.loads(subprocess.run(command, check=True, capture_output=True).stdout)
                times[writer].append(result["seconds"])
                peaks[writer].append(result["peak"])
                overs[writer].append(result["over"])
                print(f"run {run + 1} {writer}: {result['seconds']:.2f} s", file=sys.stderr)

        print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores, "
              f"Python {platform.python_version()}; {len(mesh.vertices) / 1e6:.1f} M vertices, "
              f"{len(mesh.faces) / 1e6:.1f} M triangles, {args.runs} runs")
        print("| writer | median s | × ours (median of per-run ratios) | OBJ MB | all files MB "
              "| peak RSS in the write MB | RSS over the mesh MB | loads in trimesh, same mesh |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for writer in WRITERS:
            folder = Path(tmp) / writer
            obj_mb = (folder / "mesh.obj").stat().st_size / 1e6
            all_mb = sum(f.stat().st_size for f in folder.iterdir()) / 1e6
            ratio = statistics.median(t / o for t, o in zip(times[writer], times["ours"]))
            print(f"| {writer} | {statistics.median(times[writer]):.2f} | {ratio:.2f} | "
                  f"{obj_mb:.0f} | {all_mb:.0f} | {statistics.median(peaks[writer]):.0f} | "
                  f"{statistics.median(overs[writer]):.0f} | {_check(folder, mesh, texture)} |")


if __name__ == "__main__":
    main()
