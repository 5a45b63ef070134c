"""Accuracy, speed and memory of the height-map integrators.

Accuracy: RMSE (pixels) of each method on analytic surfaces with 0.5 % Gaussian gradient
noise (σ = 0.005 × RMS gradient magnitude), on a rectangular and two non-rectangular domains.
Scaling: time and peak RSS of :func:`masked_poisson` at 1, 6 and 24 megapixels (a disk-with-
notch domain, bump on a tilted plane), each size in a fresh process, the peak read from
``VmHWM`` after resetting it through ``/proc/self/clear_refs``.

Run: ``.venv/bin/python benchmarks/integration.py [--sizes 1 6 24] [--preconditioners ...]``
Prints Markdown.
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from reconstruct.surface import (  # noqa: E402
    discontinuity_preserving,
    frankot_chellappa,
    masked_poisson,
    poisson_dct,
)
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


def _vmhwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    return float("nan")


def child(mp: float, preconditioner: str) -> None:
    z, p, q, mask = _scaling_problem(mp)
    base = _vmhwm_mb()
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS
    t = time.perf_counter()
    height, info = masked_poisson(p, q, mask, preconditioner=preconditioner, return_info=True)
    dt = time.perf_counter() - t
    peak = _vmhwm_mb()
    z = z.astype(np.float64) - z[mask].mean(dtype=np.float64)
    err = float(np.sqrt(np.mean((height[mask] - z[mask]) ** 2)))
    print(f"{mp}|{preconditioner}|{p.shape[0]}x{p.shape[1]}|{int(mask.sum())}|{dt:.2f}|"
          f"{peak:.0f}|{base:.0f}|{info['iterations']}|{info['residual']:.1e}|{err:.2e}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=float, nargs="*", default=[1, 6, 24])
    ap.add_argument("--preconditioners", nargs="*", default=["multigrid", "dct"])
    ap.add_argument("--child", nargs=2)
    args = ap.parse_args()
    if args.child:
        child(float(args.child[0]), args.child[1])
        return
    cpu = next((ln.split(":", 1)[1].strip() for ln in
                Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("model name")),
               platform.processor())
    print(f"# Integration benchmark\n\n{datetime.date.today().isoformat()} — {cpu}, "
          f"{os.cpu_count()} CPUs, {platform.platform()}, Python {platform.python_version()}, "
          f"NumPy {np.__version__}\n")
    print("## RMSE (pixels), 0.5 % gradient noise, 96×112\n")
    print(accuracy_table())
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
