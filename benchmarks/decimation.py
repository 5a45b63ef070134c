"""Mesh decimation on the synthetic tablet: error against the pixel pitch.

The ground-truth height of the synthetic clay tablet (512×384, pixel size 80/512 mm) is meshed
on its mask and decimated to 1 % of its triangles; the error reported by
:func:`reconstruct.mesh.ops.decimate` (max and RMS distance between the two surfaces, both ways)
is compared with the pixel pitch. Target: below 0.5 pixel pitch.

Run: ``.venv/bin/python benchmarks/decimation.py``
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_synthetic.surfaces import SCENES  # noqa: E402
from reconstruct.mesh.grid import grid_mesh  # noqa: E402
from reconstruct.mesh.ops import decimate  # noqa: E402


def main() -> None:
    surface = SCENES["tablet"]((384, 512), seed=0)
    height = np.where(surface.mask, surface.height, np.nan).astype(np.float32)
    mesh = grid_mesh(height, pixel_size=surface.pixel_size)
    t0 = time.perf_counter()
    small, report = decimate(mesh, target_faces=max(1, len(mesh.faces) // 100))
    seconds = time.perf_counter() - t0
    pitch = surface.pixel_size
    print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores")
    print("| triangles before | after | max error (mm) | RMS error (mm) | max / pixel pitch | seconds |")
    print("| --- | --- | --- | --- | --- | --- |")
    print(f"| {report['faces_before']} | {report['faces_after']} | {report['max_error']:.4f} | "
          f"{report['rms_error']:.4f} | {report['max_error'] / pitch:.2f} | {seconds:.1f} |")


if __name__ == "__main__":
    main()
