"""How live ``reconstruct preview``'s light slider is: one relight on a 2048×1536 texture.

The synthetic tablet's height at 2048×1536 becomes a display mesh of at most 250 000 vertices
(as ``reconstruct preview`` subsamples it) and a PTM made from its normals (the Lambertian
shading n·l with √(1 − lu² − lv²) ≈ 1 − (lu² + lv²)/2, which is a PTM). Timed, median of 15
light positions: the relit texture alone (:func:`reconstruct.viewer.scene.relit_texture`),
the light callback (relight and copy into VTK's texture memory), and the callback plus an
off-screen render of a 1280×900 window (texture upload and draw; on a machine without a GPU
this is Mesa's software rasteriser), then the render alone for smaller display meshes.

Run: ``.venv/bin/python benchmarks/preview_relight.py``
"""

from __future__ import annotations

import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_synthetic.surfaces import SCENES
from ptmcore.relight import light_direction
from reconstruct.mesh.grid import grid_mesh
from reconstruct.viewer.preview import build_plotter
from reconstruct.viewer.scene import (
    MAX_VERTICES,
    PreviewScene,
    _grid_step,
    relit_texture,
)

SHAPE = (1536, 2048)
REPEATS = 15


def _scene() -> PreviewScene:
    surface = SCENES["tablet"](SHAPE, seed=0)
    height = np.where(surface.mask, surface.height, np.nan).astype(np.float32)
    gy, gx = np.gradient(np.nan_to_num(height), surface.pixel_size)
    # Rows go down and y up: ∂z/∂y = −∂z/∂row (docs/CONVENTIONS.md).
    n = np.stack([-gx, gy, np.ones_like(gx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    coef = np.empty(SHAPE + (6,), np.float32)
    coef[..., 0] = coef[..., 1] = -127.5 * n[..., 2]
    coef[..., 2] = 0
    coef[..., 3], coef[..., 4], coef[..., 5] = 255 * n[..., 0], 255 * n[..., 1], 255 * n[..., 2]
    rgb = np.full(SHAPE + (3,), (190, 150, 110), np.uint8)
    mesh = grid_mesh(height, step=_grid_step(SHAPE, MAX_VERTICES), pixel_size=surface.pixel_size)
    return PreviewScene("bench", mesh.vertices, mesh.faces, "mm", uv=mesh.uv, coefficients=coef, rgb=rgb,
                        normals=n.astype(np.float32), albedo=rgb, height=height, pixel_size=surface.pixel_size)


def _median_ms(fn, lights) -> float:
    times = []
    for az in lights:
        t0 = time.perf_counter()
        fn(az)
        times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times))


def main() -> None:
    scene = _scene()
    lights = np.linspace(0, 360, REPEATS, endpoint=False) + 7
    window = build_plotter(scene, off_screen=True, size=(1280, 900))
    try:
        window.screenshot()  # first upload and shader compilation out of the timing
        relit = _median_ms(lambda az: relit_texture(scene, light_direction(azimuth_deg=az, elevation_deg=35)), lights)
        callback = _median_ms(lambda az: window.on_light(az, 35), lights)
        rendered = _median_ms(lambda az: (window.on_light(az, 35), window.plotter.render()), lights)
    finally:
        window.close()
    print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores")
    print(f"texture {SHAPE[1]}×{SHAPE[0]}, display mesh {len(scene.vertices):,} vertices, "
          f"{len(scene.faces):,} triangles")
    print("| relit texture (ms) | light callback (ms) | callback + render 1280×900 (ms) |")
    print("| --- | --- | --- |")
    print(f"| {relit:.0f} | {callback:.0f} | {rendered:.0f} |")
    # Where the render dominates (software OpenGL), it scales with the mesh and the window.
    print("\n| display vertices | render 1280×900 (ms) | render 640×450 (ms) |")
    print("| --- | --- | --- |")
    for limit in (MAX_VERTICES, 60_000, 15_000):
        mesh = grid_mesh(scene.height, step=_grid_step(SHAPE, limit), pixel_size=scene.pixel_size)
        small = replace(scene, vertices=mesh.vertices, faces=mesh.faces, uv=mesh.uv)
        row = []
        for size in ((1280, 900), (640, 450)):
            window = build_plotter(small, off_screen=True, size=size)
            try:
                window.screenshot()
                row.append(_median_ms(lambda az, w=window: w.plotter.render(), lights[:7]))
            finally:
                window.close()
        print(f"| {len(mesh.vertices):,} | {row[0]:.0f} | {row[1]:.0f} |")


if __name__ == "__main__":
    main()
