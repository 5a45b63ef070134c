"""Speed of the scan comparison: a 1-million-point scan against a 2-million-triangle mesh.

The synthetic tablet's true height on a 1000×1000 grid (about 2 million triangles) is the
reconstruction, written and read back as a run's textured ``mesh.ply`` (``reconstruct compare
OUT scan`` reads it so); a synthetic laser scan of 1 million points (0.02 mm noise, moved by a random
rigid transform) is aligned to it and its distances measured, as ``reconstruct compare`` does.
Reports the time and the process's peak memory of each stage, and the alignment error against
the known transform. Target: the comparison in ≤ 20 s.

Run: ``.venv/bin/python benchmarks/compare_speed.py``
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_synthetic.scan import sample_scan  # noqa: E402
from data_synthetic.surfaces import SCENES  # noqa: E402
from reconstruct.compare import Geometry, align, distances, load_geometry  # noqa: E402
from reconstruct.mesh.grid import grid_mesh  # noqa: E402
from reconstruct.mesh.ply import write_ply  # noqa: E402
from reconstruct.pipeline.profiling import StageTimer  # noqa: E402


def main() -> None:
    surface = SCENES["tablet"]((1000, 1000), pixel_size=0.08, seed=0)
    texture = np.full((*surface.height.shape, 3), 128, np.uint8)
    mesh = grid_mesh(surface.height, texture=texture, pixel_size=surface.pixel_size,
                     normals=surface.normals.astype(np.float32))
    points, transform = sample_scan(surface, 1_000_000, seed=1)
    scan = Geometry(points.astype(np.float64))
    timer = StageTimer()
    with tempfile.TemporaryDirectory() as folder:
        write_ply(Path(folder) / "mesh.ply", mesh, texture_file="mesh_texture.png")
        with timer.stage("read"):
            rec = load_geometry(Path(folder) / "mesh.ply")
    with timer.stage("align"):
        alignment = align(rec, scan)
    with timer.stage("distances"):
        result = distances(rec, scan, alignment)
    composed = alignment.transform @ transform
    angle = np.degrees(np.arccos(np.clip((np.trace(composed[:3, :3]) - 1) / 2, -1, 1)))
    shift = np.linalg.norm(composed[:3, 3])
    total = sum(s["seconds"] for s in timer.stages.values())
    print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores")
    print(f"{len(mesh.faces):,} triangles, {len(points):,} scan points")
    print("| stage | seconds | peak RSS MB |\n| --- | --- | --- |")
    for name, s in timer.stages.items():
        print(f"| {name} | {s['seconds']:.1f} | {s['peak_rss_mb']:.0f} |")
    print(f"| **total** | **{total:.1f}** | |")
    print(f"alignment error {angle:.5f}°, {shift:.4f} mm; RMS {result.stats['rms']:.4f} mm, "
          f"overlap {result.stats['overlap_fraction']:.3f}")


if __name__ == "__main__":
    main()
