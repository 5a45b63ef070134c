"""Perspective normal integration on real data: masked least squares against bilateral (BiNI).

Real: every object folder of ``../shared/real/bini_depth`` (DiLiGenT objects as distributed
with Bilateral Normal Integration: ``normal_map.png`` 16-bit, ``mask.png``, ``K.txt`` in
pixels, ``depth_gt.npz`` laser depth in mm); skipped with a note when the folder is absent.
Both integrators run through :func:`reconstruct.surface.integrate_perspective` (``distance=1``,
so the depth is ``1 − height``). A perspective reconstruction from normals has one free
scale; it is fitted as BiNI's own evaluation (``evaluation_diligent.py`` of Cao et al.) does,
by the median over the mask of the ratio true depth / estimated depth, and the figure is the
mean absolute depth error (MADE, mm) over the mask. K.txt is read as [[fx, 0, cx], [0, fy,
cy]] with cx along the columns and cy along the rows from the top.

Synthetic (160×120, fx = 160, 0.5 % normal noise, rendered by ray casting, depth 220–345 mm):
a sphere (smooth), a "scissor" step (two planes whose depth jump grows from 0 at the middle
row to about ±40 mm at the top and bottom), the same step at 640×480 (fx = 640: the same
scene, four times the pixels across, so the jump grows four times faster per row in pixel
footprints, the unit of BiNI's weights), and a clay tablet relief (``data_synthetic``,
768×1024, depth = distance − height, normals from the perspective depth map).

Scale: the bilateral and masked solves of a 6000×4000 tablet relief (about 14 Mpixel in the
mask, 50 mm lens on a 36 mm sensor) in a fresh process each, peak RSS from ``VmHWM`` after
resetting it through ``/proc/self/clear_refs`` just before the solve.

Times are wall-clock seconds of the integration call on a shared 2-core machine. Other jobs
slow them down, OpenBLAS's threaded dot products inside scipy's CG most of all (measured on
harvest's bilateral solve while other jobs ran: 43 s with OpenBLAS's default threads, 6 s
with ``OPENBLAS_NUM_THREADS=1``), so the header says how it was run and the real table also
gives the process CPU time.

Run: ``.venv/bin/python benchmarks/real_integration.py [--no-scale] [--scale-size 4000 6000]``
Prints Markdown.
"""

from __future__ import annotations

import argparse
import datetime
import gc
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from procinfo import cpu_model, status_mb  # noqa: E402
from ptmcore.images import read_image  # noqa: E402
from reconstruct.calibration.camera import Intrinsics  # noqa: E402
from reconstruct.surface import integrate_perspective, read_normal_map  # noqa: E402

REAL = ROOT.parent / "shared" / "real" / "bini_depth"
METHODS = ("masked", "bilateral")


def made(height: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> float:
    """MADE (depth units) of ``1 − height`` after BiNI's median-ratio scale."""
    est = 1.0 - height.astype(np.float64)
    inside = mask & np.isfinite(est) & np.isfinite(depth)
    scale = np.median(depth[inside] / est[inside])
    return float(np.mean(np.abs(scale * est[inside] - depth[inside])))


def timed(normals, camera, mask, method):
    wall, cpu = time.perf_counter(), time.process_time()
    height = integrate_perspective(normals, camera, mask=mask, method=method, distance=1.0)
    return height, time.perf_counter() - wall, time.process_time() - cpu


def real_table() -> str:
    folders = sorted(p for p in REAL.glob("*") if (p / "depth_gt.npz").is_file()) if REAL.is_dir() else []
    if not folders:
        return f"(no real data: {REAL} is absent)"
    lines = ["| object | mask pixels | masked MADE (mm) | masked time (s) | bilateral MADE (mm) "
             "| bilateral time (s) | bilateral CPU (s) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for folder in folders:
        normals = read_normal_map(folder / "normal_map.png")
        mask = read_image(folder / "mask.png") > 0
        if mask.ndim == 3:
            mask = mask[..., 0]
        k = np.loadtxt(folder / "K.txt")
        camera = Intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        depth = np.load(folder / "depth_gt.npz")["depth_gt"]
        row = [folder.name, str(int(mask.sum()))]
        for method in METHODS:
            height, wall, cpu = timed(normals, camera, mask, method)
            row += [f"{made(height, depth, mask):.3f}", f"{wall:.2f}"]
        row.append(f"{cpu:.2f}")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------- synthetic perspective scenes


def rays(camera: Intrinsics, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) rays r = (u/fx, −v/fy, −1): the point of depth d in a pixel is d·r."""
    row, col = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return np.stack([(col - camera.cx) / camera.fx, -(row - camera.cy) / camera.fy,
                     -np.ones_like(col)], axis=-1)


def depth_normals(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Unit normals (towards the camera) of the surface d·r, by central differences."""
    points = depth[..., None] * rays(camera, depth.shape)
    d_row, d_col = np.gradient(points, axis=(0, 1))
    n = np.cross(d_row, d_col)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def sphere_scene(camera, shape, distance=300.0, radius=90.0):
    r = rays(camera, shape)
    centre = np.array([0.0, 0.0, -distance])
    a = (r * r).sum(-1)
    b = -2.0 * (r @ centre)
    disc = b * b - 4 * a * (centre @ centre - radius**2)
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    n = (t[..., None] * r - centre) / radius
    cos_view = (n * -r).sum(-1) / np.linalg.norm(r, axis=-1)
    return t, n, (disc > 0) & (cos_view > 0.3)


def scissor_scene(camera, shape, distance=300.0, tilt_deg=25.0):
    r = rays(camera, shape)
    point = np.array([0.0, 0.0, -distance])
    left = np.arange(shape[1])[None, :] < shape[1] // 2
    n1 = np.array([0.0, -math.tan(math.radians(tilt_deg)), 1.0])
    n1 /= np.linalg.norm(n1)
    n2 = np.array([0.0, 0.0, 1.0])
    depth = np.where(left, (n1 @ point) / (r @ n1), (n2 @ point) / (r @ n2))
    return depth, np.where(left[..., None], n1, n2) * np.ones(shape + (1,)), np.ones(shape, bool)


def tablet_scene(shape, focal_mm=50.0, sensor_mm=36.0):
    """The clay tablet's height as a relief in depth, seen by a pinhole camera whose pixel
    footprint at the background equals the tablet's pixel size."""
    from data_synthetic.tablet import clay_tablet

    tablet = clay_tablet(shape)
    h, w = shape
    fx = focal_mm / sensor_mm * w
    camera = Intrinsics(fx, fx, (w - 1) / 2, (h - 1) / 2)
    depth = fx * tablet.pixel_size - tablet.height.astype(np.float64)
    return camera, depth, tablet.mask


def synthetic_table() -> str:
    shape = (120, 160)
    cam = Intrinsics(160.0, 160.0, 79.5, 59.5)
    rng = np.random.default_rng(0)
    big = (480, 640)
    big_cam = Intrinsics(640.0, 640.0, 319.5, 239.5)
    scenes = {"sphere (smooth)": (cam, *sphere_scene(cam, shape)),
              "scissor step": (cam, *scissor_scene(cam, shape)),
              "scissor step 640×480": (big_cam, *scissor_scene(big_cam, big))}
    tcam, tdepth, tmask = tablet_scene((768, 1024))
    scenes["tablet relief 1024×768"] = (tcam, tdepth, depth_normals(tdepth, tcam), tmask)
    lines = ["| scene | masked MADE | bilateral MADE | unit | masked time (s) | bilateral time (s) |",
             "|---|---:|---:|---|---:|---:|"]
    for name, (camera, depth, normals, mask) in scenes.items():
        noise = rng.normal(0.0, 0.005, normals.shape)
        normals = normals + noise
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        row = [name]
        times = []
        for method in METHODS:
            height, wall, _ = timed(normals, camera, mask, method)
            row.append(f"{made(height, depth, mask):.4f}")
            times.append(f"{wall:.2f}")
        lines.append("| " + " | ".join(row + ["mm"] + times) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------- 24 Mpixel


def child(h: int, w: int, method: str) -> None:
    camera, depth, mask = tablet_scene((h, w))
    normals = depth_normals(depth, camera)
    gc.collect()
    before = status_mb("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS
    height, wall, cpu = timed(normals, camera, mask, method)
    peak = status_mb("VmHWM")
    print(f"{h}x{w}|{int(mask.sum())}|{method}|{wall:.1f}|{cpu:.1f}|{peak:.0f}|{before:.0f}|"
          f"{made(height, depth, mask) * 1000:.2f}")


def scale_table(h: int, w: int) -> str:
    lines = ["| shape | mask pixels | method | time (s) | CPU (s) | peak RSS (MB) | RSS before (MB) "
             "| MADE (µm) |", "|---|---:|---|---:|---:|---:|---:|---:|"]
    for method in METHODS:
        out = subprocess.run([sys.executable, __file__, "--child", str(h), str(w), method],
                             capture_output=True, text=True)
        if out.returncode:
            lines.append(f"| {h}x{w} | | {method} | failed: {out.stderr.strip().splitlines()[-1]} |")
        else:
            lines.append("| " + out.stdout.strip().replace("|", " | ") + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--no-scale", action="store_true", help="skip the 24 Mpixel runs")
    ap.add_argument("--scale-size", type=int, nargs=2, default=[4000, 6000], metavar=("H", "W"))
    ap.add_argument("--child", nargs=3)
    args = ap.parse_args()
    if args.child:
        child(int(args.child[0]), int(args.child[1]), args.child[2])
        return
    print(f"# Perspective integration: masked least squares and bilateral (BiNI)\n\n"
          f"{datetime.date.today().isoformat()} — {cpu_model()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, NumPy {np.__version__}, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}\n")
    print("## Real: DiLiGenT objects of BiNI (MADE after the median-ratio scale)\n")
    print(real_table(), flush=True)
    print("\n## Synthetic perspective scenes (0.5 % normal noise)\n")
    print(synthetic_table(), flush=True)
    if not args.no_scale:
        h, w = args.scale_size
        print(f"\n## {h}×{w} tablet relief, perspective (fresh process per method)\n")
        print(scale_table(h, w), flush=True)


if __name__ == "__main__":
    main()
