"""Accuracy, speed and memory of the height-map integrators.

Accuracy: RMSE (pixels) of each method on analytic surfaces with 0.5 % Gaussian gradient
noise (σ = 0.005 × RMS gradient magnitude), on a rectangular and two non-rectangular domains.
Steep walls: height RMSE (pixels) separately on the walls (pixels whose true slope, from
central differences of the true height, exceeds 45°) and on the rest of the mask ("field"),
after removing the mean error over the mask. Scenes: steep-walled wedge impressions on a
flat plate (``data_synthetic.wedges.wedge_plate``: facets up to 75°, 60 px deep), a coin-like
relief (a raised rim, a disk and three bars, walls ramped at 75° then smoothed over 0.6 px,
defined below) and a sphere cap cut at 80° (``data_synthetic.sphere``). Normals are those a
capture would give: 32 renders (lights on a dome at 20–70° elevation, cast shadows, albedo
0.6, Gaussian sensor noise 0.5 % or 2 % of full scale) through the default robust photometric
stereo. "bilateral, former" is the bilateral integrator as it was before BiNI's form (residual
rule, unweighted equations, edge-weight floor 1e-3, 51 solves); "bilateral" is the current one
(BiNI: depth-difference rule, equations weighted by nz², energy stop); "masked nz²" is
:func:`masked_poisson` with the same nz² per-pixel weights (BiNI's k = 0 limit).

``--integrator auto`` (:func:`reconstruct.surface.integrate_auto`): the same steep-walled
scenes, a clay tablet (``data_synthetic.clay_tablet``, 384×512 at 0.05 mm, true normals and
photometric stereo), a sphere to its outline, the analytic cap and scissor step, a perspective
scissor step and BiNI's real objects (``../shared/real/bini_depth``, when present): masked
least squares, bilateral integration and auto's choice with the edges bilateral cut
(``--only-auto`` prints only this table).

Scaling: time and peak RSS of :func:`masked_poisson` at 1, 6 and 24 megapixels (a disk-with-
notch domain, bump on a tilted plane), each size in a fresh process, the peak read from
``VmHWM`` after resetting it through ``/proc/self/clear_refs``.

Run: ``.venv/bin/python benchmarks/integration.py [--sizes 1 6 24] [--preconditioners ...]
[--no-walls] [--only-auto]``. Prints Markdown.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import scipy.ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from reconstruct.surface import (  # noqa: E402
    discontinuity_preserving,
    frankot_chellappa,
    masked_poisson,
    poisson_dct,
)
from data_synthetic.shadows import cast_shadow_mask  # noqa: E402
from data_synthetic.sphere import sphere_cap  # noqa: E402
from data_synthetic.surface import normals_from_height  # noqa: E402
from data_synthetic.wedges import wedge_plate  # noqa: E402
from helpers import dome, stack_from_luminance  # noqa: E402
from procinfo import cpu_model, status_mb  # noqa: E402
from ptmcore.robust import robust_photometric_stereo  # noqa: E402
from reconstruct.surface import gradients_from_normals  # noqa: E402
from test_integrate_masked import (  # noqa: E402
    _bump_on_tilted_plane,
    _cap_on_tilted_plane,
    _disk,
    _l_shape,
    _noisy,
    _rmse,
    _step,
    _tent,
)


def accuracy_table() -> str:
    surfaces = {
        "cap on tilted plane": _cap_on_tilted_plane,
        "bump on tilted plane": _bump_on_tilted_plane,
        "tent (oblique crease)": _tent,
        "scissor step": _step,
    }
    domains = {"rectangle": lambda: np.ones_like(_disk()), "disk": _disk, "L-shape": _l_shape}
    methods = {
        "dct (box)": lambda p, q, m: poisson_dct(p, q, mask=m),
        "fc (box)": lambda p, q, m: frankot_chellappa(p, q, mask=m),
        "masked": lambda p, q, m: masked_poisson(p, q, m),
        "bilateral": lambda p, q, m: discontinuity_preserving(p, q, m),
    }
    lines = ["| surface | domain | " + " | ".join(methods) + " |",
             "|---|---|" + "---:|" * len(methods)]
    for sname, surf in surfaces.items():
        z, p, q = surf()
        p, q = _noisy(p, q, 0.005)
        for dname, dom in domains.items():
            mask = dom()
            errs = [_rmse(f(p, q, mask), z, mask) for f in methods.values()]
            lines.append(f"| {sname} | {dname} | " + " | ".join(f"{e:.4f}" for e in errs) + " |")
    return "\n".join(lines)


def coin_relief(shape: tuple[int, int] = (256, 256), wall_deg: float = 75.0):
    """Height (pixels) and mask of a coin: raised rim (6 px), disk (4 px) and three bars
    (3 px) on a flat field, walls ramped at `wall_deg`, smoothed over 0.6 px."""
    h, w = shape
    row, col = np.mgrid[0:h, 0:w].astype(np.float64)
    cx, cy = (w - 1) / 2, (h - 1) / 2
    r = np.hypot(col - cx, row - cy)
    radius = 0.46 * min(h, w)
    rise = np.tan(np.radians(wall_deg))

    def plateau(inside: np.ndarray, height: float) -> np.ndarray:
        return height * np.clip(inside * rise / height, 0.0, 1.0)

    z = plateau(np.minimum(r - (radius - 10), radius - r), 6.0)
    z = np.maximum(z, plateau(0.25 * radius - np.hypot(col - cx + 0.3 * radius, row - cy), 4.0))
    for k in range(3):
        x0 = cx + 0.1 * radius + k * 0.18 * radius
        inside = np.minimum(np.minimum(col - x0, x0 + 0.08 * radius - col),
                            np.minimum(row - (cy - 0.4 * radius), cy + 0.4 * radius - row))
        z = np.maximum(z, plateau(inside, 3.0))
    return scipy.ndimage.gaussian_filter(z, 0.6), r < radius


def _ps_normals(z: np.ndarray, noise: float, seed: int = 0) -> np.ndarray:
    """Robust photometric stereo of 32 shadowed Lambertian renders of height z (pixels)."""
    n = normals_from_height(z, 1.0)
    lights = dome(32, seed=seed, min_elev=20.0, max_elev=70.0)
    rng = np.random.default_rng(seed)
    values = np.empty((len(lights),) + z.shape)
    for i, light in enumerate(lights):
        shading = np.clip(n @ light.astype(np.float32), 0.0, None)
        shading[cast_shadow_mask(z, 1.0, light)] = 0.0
        values[i] = 0.6 * shading + rng.normal(0.0, noise, z.shape)
    return robust_photometric_stereo(stack_from_luminance(np.clip(values, 0, 1)), lights).normals


def walls_table() -> str:
    cap = sphere_cap((256, 256), max_slope_deg=80.0)
    scenes = {
        "wedges 75°": (wedge_plate() / 0.05, None),
        "coin 75°": coin_relief(),
        "sphere cap 80°": (cap.height / cap.pixel_size, cap.mask),
    }
    methods = {
        "dct (box)": lambda p, q, m, nz: poisson_dct(p, q, mask=m),
        "masked": lambda p, q, m, nz: masked_poisson(p, q, m),
        "masked nz²": lambda p, q, m, nz: masked_poisson(p, q, m, weights=nz**2),
        "bilateral, former": lambda p, q, m, nz: discontinuity_preserving(
            p, q, m, rule="residuals", cosines=np.ones_like(p), min_weight=1e-3,
            iterations=51, tol=0.0, cg_tol=1e-6),
        "bilateral": lambda p, q, m, nz: discontinuity_preserving(p, q, m),
    }
    lines = ["| scene | sensor noise | wall px | " + " | ".join(methods) + " |",
             "|---|---:|---:|" + "---:|" * len(methods)]
    for name, (z, mask) in scenes.items():
        mask = np.ones(z.shape, bool) if mask is None else mask
        slope = np.degrees(np.arctan(np.hypot(*np.gradient(z))))
        wall = mask & (slope > 45.0)
        for noise in (0.005, 0.02):
            normals = _ps_normals(z, noise)
            p, q = gradients_from_normals(normals)
            nz = np.clip(normals[..., 2], 0.0, 1.0)
            cells = []
            for f in methods.values():
                e = np.where(mask, f(p, q, mask, nz) - z, np.nan)
                e -= np.nanmean(e)
                cells.append(f"{np.sqrt(np.nanmean(e[wall] ** 2)):.3f} / "
                             f"{np.sqrt(np.nanmean(e[mask & ~wall] ** 2)):.3f}")
            lines.append(f"| {name} | {noise:.1%} | {int(wall.sum())} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def auto_table() -> str:
    """``integrate_auto`` against masked least squares and bilateral integration: smooth
    reliefs, steep walls from photometric stereo, steps, and BiNI's real objects."""
    from real_integration import REAL, made, scissor_scene
    from data_synthetic import clay_tablet
    from helpers import sphere_normals
    from test_integrate_auto import _normals
    from ptmcore.images import read_image
    from reconstruct.calibration.camera import Intrinsics
    from reconstruct.surface import integrate, integrate_auto, integrate_perspective, read_normal_map

    scenes = []  # (name, normals, mask, error of a height, camera or None)
    tablet = clay_tablet((384, 512), pixel_size=0.05)
    tz = tablet.height / tablet.pixel_size
    scenes.append(("clay tablet 384×512, true normals", tablet.normals, tablet.mask,
                   lambda h, z=tz, m=tablet.mask: _rmse(h, z, m), None))
    scenes.append(("clay tablet 384×512, photometric stereo 0.5 %", _ps_normals(tz, 0.005), tablet.mask,
                   lambda h, z=tz, m=tablet.mask: _rmse(h, z, m), None))
    n, m = sphere_normals(256, 256, 100.0)
    rows, cols = np.mgrid[0:256, 0:256]
    sz = np.sqrt(np.clip(100.0 ** 2 - (cols - 127.5) ** 2 - (rows - 127.5) ** 2, 0, None))
    scenes.append(("sphere to its outline (r 100 px), true normals", n, m, lambda h, z=sz, m=m: _rmse(h, z, m), None))
    z, p, q = _cap_on_tilted_plane()
    p, q = _noisy(p, q, 0.005)
    for dname, dom in (("disk", _disk), ("L-shape", _l_shape)):
        scenes.append((f"cap on tilted plane, {dname}, 0.5 % gradient noise", _normals(p, q), dom(),
                       lambda h, z=z, m=dom(): _rmse(h, z, m), None))
    coin, coin_mask = coin_relief()
    cap = sphere_cap((256, 256), max_slope_deg=80.0)
    walls = {"coin 75°": (coin, coin_mask), "wedges 75°": (wedge_plate() / 0.05, None),
             "sphere cap 80°": (cap.height / cap.pixel_size, cap.mask)}
    for name, (wz, wm) in walls.items():
        wm = np.ones(wz.shape, bool) if wm is None else wm
        for noise in (0.005, 0.02):
            scenes.append((f"{name}, photometric stereo {noise:.1%}", _ps_normals(wz, noise), wm,
                           lambda h, z=wz, m=wm: _rmse(h, z, m), None))
    z, p, q = _step()
    p, q = _noisy(p, q, 0.005)
    for dname, dom in (("disk", _disk), ("L-shape", _l_shape)):
        scenes.append((f"scissor step, {dname}, 0.5 % gradient noise", _normals(p, q), dom(),
                       lambda h, z=z, m=dom(): _rmse(h, z, m), None))
    cam = Intrinsics(160.0, 160.0, 79.5, 59.5)
    depth, sn, sm = scissor_scene(cam, (120, 160))
    sn = sn + np.random.default_rng(0).normal(0.0, 0.005, sn.shape)
    scenes.append(("scissor step, perspective 160×120 (mm)", sn / np.linalg.norm(sn, axis=-1, keepdims=True), sm,
                   lambda h, d=depth, m=sm: made(h, d, m), cam))
    for folder in sorted(REAL.glob("*")) if REAL.is_dir() else []:
        if not (folder / "depth_gt.npz").is_file():
            continue
        rm = read_image(folder / "mask.png") > 0
        rm = rm[..., 0] if rm.ndim == 3 else rm
        k = np.loadtxt(folder / "K.txt")
        depth = np.load(folder / "depth_gt.npz")["depth_gt"]
        scenes.append((f"{folder.name} (real, DiLiGenT, perspective, mm)", read_normal_map(folder / "normal_map.png"),
                       rm, lambda h, d=depth, m=rm: made(h, d, m & np.isfinite(h) & np.isfinite(d)),
                       Intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2])))
    lines = ["| scene | masked | bilateral | auto's choice (edges cut) | auto | auto ÷ the better |",
             "|---|---:|---:|---|---:|---:|"]
    for name, normals, mask, error, camera in scenes:
        if camera is None:
            ms, bi = (error(integrate(normals, m, mask=mask)) for m in ("masked", "bilateral"))
            chosen = integrate_auto(normals, mask)
        else:
            ms, bi = (error(integrate_perspective(normals, camera, mask=mask, method=m, distance=1.0))
                      for m in ("masked", "bilateral"))
            chosen = integrate_auto(normals, mask, intrinsics=camera, distance=1.0)
        auto = error(chosen.height)
        lines.append(f"| {name} | {ms:.4f} | {bi:.4f} | {chosen.method} ({chosen.cut_edges}) | {auto:.4f} | "
                     f"{auto / min(ms, bi):.2f} |")
        print(lines[-1], file=sys.stderr, flush=True)
    return "\n".join(lines)


def _scaling_problem(mp: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    w = int(round(np.sqrt(mp * 1e6 * 1.5)))
    h = int(round(mp * 1e6 / w))
    row = np.arange(h, dtype=np.float32)[:, None]
    col = np.arange(w, dtype=np.float32)[None, :]
    cx, cy, s = w / 2, h / 2, h / 8
    r2 = (col - cx) ** 2 + (row - cy) ** 2
    b = (s * np.exp(-r2 / (2 * s * s))).astype(np.float32)
    z = 0.3 * col + 0.2 * row + b
    p = 0.3 - (col - cx) / s**2 * b  # ∂z/∂x
    q = -(0.2 - (row - cy) / s**2 * b)  # ∂z/∂y, y up
    mask = (r2 < (0.48 * h) ** 2) & ~((col > cx) & (row < cy - h / 8))
    return z.astype(np.float32), p.astype(np.float32), q.astype(np.float32), mask


def child(mp: float, preconditioner: str) -> None:
    z, p, q, mask = _scaling_problem(mp)
    base = status_mb("VmHWM")
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS
    t = time.perf_counter()
    height, info = masked_poisson(p, q, mask, preconditioner=preconditioner, return_info=True)
    dt = time.perf_counter() - t
    peak = status_mb("VmHWM")
    z = z.astype(np.float64) - z[mask].mean(dtype=np.float64)
    err = float(np.sqrt(np.mean((height[mask] - z[mask]) ** 2)))
    print(f"{mp}|{preconditioner}|{p.shape[0]}x{p.shape[1]}|{int(mask.sum())}|{dt:.2f}|"
          f"{peak:.0f}|{base:.0f}|{info['iterations']}|{info['residual']:.1e}|{err:.2e}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=float, nargs="*", default=[1, 6, 24])
    ap.add_argument("--preconditioners", nargs="*", default=["multigrid", "dct"])
    ap.add_argument("--child", nargs=2)
    ap.add_argument("--no-walls", action="store_true", help="skip the steep-walls table")
    ap.add_argument("--only-auto", action="store_true", help="only the table of --integrator auto's choices")
    args = ap.parse_args()
    if args.child:
        child(float(args.child[0]), args.child[1])
        return
    if args.only_auto:
        print(f"{datetime.date.today().isoformat()} — {cpu_model()}, {os.cpu_count()} CPUs\n")
        print(auto_table())
        return
    print(f"# Integration benchmark\n\n{datetime.date.today().isoformat()} — {cpu_model()}, "
          f"{os.cpu_count()} CPUs, {platform.platform()}, Python {platform.python_version()}, "
          f"NumPy {np.__version__}\n")
    print("## RMSE (pixels), 0.5 % gradient noise, 96×112\n")
    print(accuracy_table())
    if not args.no_walls:
        print("\n## Steep walls: height RMSE (pixels) on walls (true slope > 45°) / on the field, "
              "normals from photometric stereo\n")
        print(walls_table(), flush=True)
        print("\n## `--integrator auto`: the error of each integrator and of auto's choice (pixels unless said)\n")
        print(auto_table(), flush=True)
    print("\n## masked_poisson scaling (tol 1e-6, warm start from the box DCT)\n")
    print("| MP | preconditioner | shape | mask pixels | time (s) | peak RSS during solve (MB) "
          "| RSS before (MB) | CG iterations | rel. residual | RMSE (px) |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for mp in args.sizes:
        for pc in args.preconditioners:
            out = subprocess.run([sys.executable, __file__, "--child", str(mp), pc],
                                 capture_output=True, text=True)
            if out.returncode:
                print(f"| {mp} | {pc} | failed: {out.stderr.strip().splitlines()[-1]} |")
            else:
                print("| " + out.stdout.strip().replace("|", " | ") + " |", flush=True)


if __name__ == "__main__":
    main()
